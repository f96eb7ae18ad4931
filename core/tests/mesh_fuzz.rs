//! Fuzzing the mesh readers (PLY ASCII and binary, OBJ, STL ASCII and binary, each also
//! gzipped) through the public `parse_mesh`: garbage, and valid files broken by bit flips,
//! truncation, splices and counts that lie (a binary STL or PLY header claiming billions of
//! records). Properties: no panic, memory in proportion to the input whatever a count claims,
//! every valid file round-trips, and every error is a `MeshError` naming the file.
//! The readers' own unit tests fuzz their grammars; this suite attacks them from outside.
//!
//! `PROPTEST_CASES=N cargo test --release -p rayfarm-common --test mesh_fuzz -- --nocapture`

mod fuzz_support;

use std::io::Write;

use fuzz_support::ByteEdit;
use proptest::prelude::*;
use rayfarm_core::mesh::{
    MeshError, ParseErrorKind, TriangleMesh, parse_mesh, write_obj, write_ply_ascii,
    write_ply_binary, write_stl_ascii, write_stl_binary,
};

const DEFAULT_CASES: u32 = 1500;

type Writer = fn(&TriangleMesh, &mut Vec<u8>) -> std::io::Result<()>;

const FORMATS: [(&str, Writer); 5] = [
    ("m.ply", |m, w| write_ply_ascii(m, w)),
    ("m.ply", |m, w| write_ply_binary(m, w)),
    ("m.obj", |m, w| write_obj(m, w)),
    ("m.stl", |m, w| write_stl_ascii(m, w)),
    ("m.stl", |m, w| write_stl_binary(m, w)),
];
const NAMES: [&str; 6] = [
    "m.ply", "m.obj", "m.stl", "m.ply.gz", "m.obj.gz", "m.stl.gz",
];

fn mesh() -> impl Strategy<Value = TriangleMesh> {
    let coord = prop_oneof![-1e4f32..1e4, Just(0.0), Just(1.5)];
    prop::collection::vec([coord.clone(), coord.clone(), coord], 3..24).prop_flat_map(|positions| {
        let n = positions.len() as u32;
        prop::collection::vec([0..n, 0..n, 0..n], 0..30).prop_map(move |triangles| TriangleMesh {
            positions: positions.clone(),
            triangles,
        })
    })
}

/// A valid file of a random format (index into FORMATS) for a random mesh.
fn valid_file() -> impl Strategy<Value = (usize, TriangleMesh, Vec<u8>)> {
    (0..FORMATS.len(), mesh()).prop_map(|(f, m)| {
        let mut bytes = Vec::new();
        FORMATS[f].1(&m, &mut bytes).unwrap();
        (f, m, bytes)
    })
}

fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

/// The properties every input must satisfy, for the reader `name` selects.
fn check_any(name: &str, bytes: &[u8]) -> Result<(), TestCaseError> {
    let (parsed, peak) = fuzz_support::peak_bytes(|| parse_mesh(name, bytes));
    // Gzip may expand ~1000 times; the bound is then on the decompressed size, checked by the
    // plain-file cases the same inputs also go through.
    let bound = if name.ends_with(".gz") { 1100 } else { 64 } * bytes.len() + (256 << 10);
    prop_assert!(
        peak <= bound,
        "{name}: {peak} bytes for a {}-byte input",
        bytes.len()
    );
    match parsed {
        Ok(m) => {
            let n = m.positions.len() as u32;
            prop_assert!(m.triangles.iter().flatten().all(|&i| i < n));
            prop_assert!(m.positions.iter().flatten().all(|x| x.is_finite()));
        }
        Err(e) => {
            prop_assert!(
                matches!(e, MeshError::Parse { .. } | MeshError::Gzip { .. }),
                "{e:?}"
            );
            prop_assert!(e.to_string().starts_with(name), "{e}");
        }
    }
    Ok(())
}

/// The same bytes taken as every format, plain and gzipped.
fn check_every_reader(bytes: &[u8]) -> Result<(), TestCaseError> {
    let zipped = gzip(bytes);
    for name in NAMES {
        let input: &[u8] = if name.ends_with(".gz") {
            &zipped
        } else {
            bytes
        };
        check_any(name, input)?;
    }
    Ok(())
}

#[test]
fn garbage() {
    fuzz_support::check(
        file!(),
        "mesh garbage",
        DEFAULT_CASES,
        prop::collection::vec(any::<u8>(), 0..1024),
        |bytes| {
            check_every_reader(&bytes)?;
            // Raw garbage as a gzip stream, with the magic so it reaches the inflater.
            let mut gz = vec![0x1f, 0x8b];
            gz.extend_from_slice(&bytes);
            check_any("m.obj.gz", &gz)
        },
    );
}

#[test]
fn valid_files_round_trip() {
    fuzz_support::check(
        file!(),
        "mesh round trip",
        DEFAULT_CASES,
        valid_file(),
        |(f, m, bytes)| {
            let name = FORMATS[f].0;
            let back = parse_mesh(name, &bytes).map_err(|e| TestCaseError::fail(e.to_string()))?;
            let corners = |m: &TriangleMesh| -> Vec<[[u32; 3]; 3]> {
                m.triangles
                    .iter()
                    .map(|t| t.map(|i| m.positions[i as usize].map(f32::to_bits)))
                    .collect()
            };
            // STL stores corners, not indices: compare triangles by their corners.
            prop_assert_eq!(corners(&back), corners(&m));
            prop_assert_eq!(
                &parse_mesh(&format!("{name}.gz"), &gzip(&bytes)).ok(),
                &Some(back)
            );
            check_any(name, &bytes)
        },
    );
}

fn mutation() -> impl Strategy<Value = ByteEdit> {
    let byte = prop_oneof![
        any::<u8>(),
        prop::sample::select(b"0123456789 \n-/.e".to_vec())
    ];
    fuzz_support::byte_edit(byte, 64)
}

#[test]
fn mutated_files() {
    let input = (valid_file(), prop::collection::vec(mutation(), 1..5));
    fuzz_support::check(
        file!(),
        "mesh mutated files",
        DEFAULT_CASES,
        input,
        |((f, _, mut bytes), edits)| {
            for m in &edits {
                m.apply(&mut bytes);
            }
            check_any(FORMATS[f].0, &bytes)?;
            check_every_reader(&bytes)
        },
    );
}

#[test]
fn spliced_files() {
    let input = (valid_file(), valid_file(), any::<usize>(), any::<usize>());
    fuzz_support::check(
        file!(),
        "mesh spliced files",
        DEFAULT_CASES,
        input,
        |((f, _, a), (_, _, b), i, j)| {
            let mut bytes = a[..i % (a.len() + 1)].to_vec();
            bytes.extend_from_slice(&b[j % (b.len() + 1)..]);
            check_any(FORMATS[f].0, &bytes)
        },
    );
}

/// Gzipped files with their compressed bytes broken: a checksum or length error, never a
/// panic or a partial mesh passed off as whole.
#[test]
fn mutated_gzip_streams() {
    let input = (valid_file(), prop::collection::vec(mutation(), 1..3));
    fuzz_support::check(
        file!(),
        "mesh mutated gzip",
        DEFAULT_CASES,
        input,
        |((f, _, bytes), edits)| {
            let mut gz = gzip(&bytes);
            for m in &edits {
                m.apply(&mut gz);
            }
            check_any(&format!("{}.gz", FORMATS[f].0), &gz)
        },
    );
}

fn counts() -> impl Strategy<Value = u64> {
    prop_oneof![
        Just(u64::from(u32::MAX)),
        Just(1 << 31),
        Just(1 << 40),
        Just(u64::MAX),
        0u64..100,
    ]
}

/// Headers whose counts claim far more than the file holds.
#[test]
fn lying_counts() {
    let input = (mesh(), counts(), counts(), 0usize..3);
    fuzz_support::check(
        file!(),
        "mesh lying counts",
        DEFAULT_CASES,
        input,
        |(m, vertices, faces, f)| {
            let (name, bytes) = match f {
                0 => {
                    let mut b = Vec::new();
                    write_stl_binary(&m, &mut b).unwrap();
                    b[80..84].copy_from_slice(&(vertices as u32).to_le_bytes());
                    ("m.stl", b)
                }
                ply => {
                    let mut b = Vec::new();
                    if ply == 1 {
                        write_ply_ascii(&m, &mut b).unwrap();
                    } else {
                        write_ply_binary(&m, &mut b).unwrap();
                    }
                    let text = String::from_utf8_lossy(&b).into_owned();
                    let nv = format!("element vertex {}\n", m.positions.len());
                    let nf = format!("element face {}\n", m.triangles.len());
                    prop_assert!(text.contains(&nv) && text.contains(&nf));
                    // The header is ASCII whatever the body: replace it within the bytes.
                    let end = text.find("end_header\n").unwrap() + "end_header\n".len();
                    let header = text[..end]
                        .replace(&nv, &format!("element vertex {vertices}\n"))
                        .replace(&nf, &format!("element face {faces}\n"));
                    let mut out = header.into_bytes();
                    out.extend_from_slice(&b[end..]);
                    ("m.ply", out)
                }
            };
            check_any(name, &bytes)
        },
    );
}

#[test]
fn a_binary_stl_claiming_four_billion_triangles_is_refused_before_allocating() {
    let mut b = vec![0u8; 84];
    b[80..84].copy_from_slice(&u32::MAX.to_le_bytes());
    let (r, peak) = fuzz_support::peak_bytes(|| parse_mesh("big.stl", &b));
    match r {
        Err(MeshError::Parse {
            kind: ParseErrorKind::CountTooLarge { count, .. },
            ..
        }) => assert_eq!(count, u64::from(u32::MAX)),
        other => panic!("{other:?}"),
    }
    assert!(peak < 4096, "{peak}");
    let ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 18446744073709551615\n\
        property float x\nproperty float y\nproperty float z\nend_header\n";
    let (r, peak) = fuzz_support::peak_bytes(|| parse_mesh("big.ply", ply));
    assert!(r.is_err_and(|e| e.to_string().contains("18446744073709551615")));
    assert!(peak < 4096, "{peak}");
}
