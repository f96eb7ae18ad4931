//! The domain file reader never panics: garbage, truncation, flipped bits, and headers whose
//! counts and offsets lie (with the checksum recomputed so the lies reach the structural checks).

use proptest::prelude::*;
use rayfarm_core::scene::domain_file::{SourceTriangle, parse_domain_bytes, write_domain};
use rayfarm_core::scene::{DomainData, Residence};

/// Bytes of the format-6 header.
const HEADER: usize = 104;

fn valid_file() -> Vec<u8> {
    static FILE: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
    FILE.get_or_init(write_valid_file).clone()
}

fn write_valid_file() -> Vec<u8> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.rfd");
    let tris = source_triangles();
    let b = rayfarm_core::geometry::Aabb {
        min: [0.0; 3],
        max: [3.0; 3],
    };
    write_domain(&path, 0, b, &tris).unwrap();
    std::fs::read(&path).unwrap()
}

/// Recomputes the checksum, which sits after magic(8) version(4) domain(4) counts(32) bounds(24).
fn reseal(bytes: &mut [u8]) {
    bytes[72..80].fill(0);
    let sum = xxhash_rust::xxh3::xxh3_64(bytes);
    bytes[72..80].copy_from_slice(&sum.to_le_bytes());
}

fn source_triangles() -> Vec<SourceTriangle> {
    (0..200)
        .map(|i| {
            let x = i as f32 * 0.01;
            SourceTriangle {
                vertices: [[x, 0.0, 0.0], [x + 0.02, 0.1, 0.0], [x, 0.0, 0.1 + x]],
                id: i,
                material: (i % 2) as u32,
                // Smooth normals on some, so the file has its normals section to lie about.
                normals: (i % 3 == 0).then_some([
                    [0.0, 0.0, 1.0],
                    [0.0, 0.6, 0.8],
                    [1.0, 0.0, 0.0],
                ]),
            }
        })
        .collect()
}

#[test]
fn a_valid_file_reads_back() {
    let d = parse_domain_bytes(&valid_file(), 2).unwrap();
    assert_eq!(d.triangle_count(), 200);
    // The blocks are the only copy: every triangle reads back from them, bit for bit.
    assert_eq!(d.normals().len(), d.blocks().len());
    let bvh = d.bvh();
    for (block, b) in d.blocks().iter().enumerate() {
        for lane in 0..4 {
            let hit = rayfarm_core::bvh::Hit {
                t: 0.0,
                block: block as u32,
                lane: lane as u32,
                id: b.id(lane),
            };
            let want = source_triangles()[b.id(lane) as usize].normals;
            let got = bvh.vertex_normals(&hit).map(|n| n.map(|v| v.to_array()));
            assert_eq!(got, want, "triangle {}", b.id(lane));
        }
    }
    let mut back: Vec<_> = d.bvh().triangles().collect();
    back.sort_by_key(|t| t.id());
    assert_eq!(back.len(), 200);
    for (t, want) in back.iter().zip(source_triangles()) {
        assert_eq!(
            (t.vertices(), t.id(), t.material),
            (want.vertices, want.id, want.material)
        );
    }
    assert!(
        parse_domain_bytes(&valid_file(), 1).is_err(),
        "material 1 is out of range for 1 material"
    );
    // Resealing after an edit the structure allows must be accepted, or the fuzzing below
    // would only ever exercise the checksum.
    let mut f = valid_file();
    f[52] ^= 1; // a bit of the bounds
    assert!(parse_domain_bytes(&f, 2).is_err());
    reseal(&mut f);
    assert!(parse_domain_bytes(&f, 2).is_ok());
}

#[test]
fn a_file_of_an_older_format_is_refused_with_its_version_and_what_to_do() {
    let mut f = valid_file();
    for old in [3u32, 4, 5] {
        f[8..12].copy_from_slice(&old.to_le_bytes());
        reseal(&mut f);
        let e = parse_domain_bytes(&f, 2).unwrap_err().to_string();
        assert!(
            e.contains(&format!("version {old}"))
                && e.contains("version 6")
                && e.contains("re-run `rayfarm prepare`"),
            "{e}"
        );
    }
}

/// A file opened mapped and copied into huge pages holds the same bytes, is checked the same
/// way (a flipped bit is refused either way), and says how it is held.
#[test]
fn a_file_reads_the_same_mapped_or_copied_into_huge_pages() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.rfd");
    let file = valid_file();
    std::fs::write(&path, &file).unwrap();
    let checksum = u64::from_le_bytes(file[72..80].try_into().unwrap());
    let open = |r| DomainData::open_as(&path, checksum, true, 2, Some(r));
    let mapped = open(Residence::Mapped).unwrap();
    let copied = open(Residence::HugePages).unwrap();
    assert_eq!(mapped.residence(), Residence::Mapped);
    assert_eq!(copied.residence(), Residence::HugePages);
    let bytes = |d: &DomainData| {
        let nodes: &[u8] = bytemuck::cast_slice(d.nodes());
        let blocks: &[u8] = bytemuck::cast_slice(d.blocks());
        let normals: &[u8] = bytemuck::cast_slice(d.normals());
        [nodes.to_vec(), blocks.to_vec(), normals.to_vec()]
    };
    assert_eq!(bytes(&mapped), bytes(&copied));
    assert_eq!(mapped.bytes(), copied.bytes());
    assert_eq!(mapped.bytes(), file.len() as u64);
    // The copy starts on a huge page's boundary, so the kernel can back it with huge pages.
    assert_eq!(
        copied.nodes().as_ptr() as usize % (2 << 20),
        104usize.next_multiple_of(64)
    );
    // A dropped copy's region is the next copy's (its pages are backed already, so the load
    // only copies), and the bytes are the file's. No other test of this file copies into
    // huge pages, so nothing else takes the spare region meanwhile.
    let region = copied.nodes().as_ptr();
    drop(copied);
    let again = open(Residence::HugePages).unwrap();
    assert_eq!(again.nodes().as_ptr(), region);
    assert_eq!(bytes(&again), bytes(&mapped));
    drop(again);
    let mut flipped = file.clone();
    flipped[file.len() - 1] ^= 1;
    std::fs::write(&path, &flipped).unwrap();
    for r in [Residence::Mapped, Residence::HugePages] {
        let e = open(r).unwrap_err().to_string();
        assert!(e.contains("corrupt"), "{r:?}: {e}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(3000))]

    #[test]
    fn garbage_is_an_error(bytes in proptest::collection::vec(any::<u8>(), 0..4096)) {
        prop_assert!(parse_domain_bytes(&bytes, 4).is_err());
    }

    #[test]
    fn truncation_is_an_error(cut in 0usize..1_000_000) {
        let f = valid_file();
        let cut = cut % f.len();
        prop_assert!(parse_domain_bytes(&f[..cut], 4).is_err());
    }

    #[test]
    fn flipped_bytes_are_an_error(at in any::<usize>(), bit in 0u8..8) {
        let mut f = valid_file();
        let at = at % f.len();
        f[at] ^= 1 << bit;
        prop_assert!(parse_domain_bytes(&f, 4).is_err());
    }

    #[test]
    fn lying_headers_and_bodies_never_panic(edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..8), header_only in any::<bool>()) {
        let mut f = valid_file();
        for (at, v) in edits {
            let at = if header_only { at % HEADER } else { at % f.len() };
            f[at] = v;
        }
        reseal(&mut f);
        // Ok is possible (an edit in padding); a panic is not.
        let _ = parse_domain_bytes(&f, 4);
    }
}
