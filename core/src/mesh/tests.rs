use super::*;
use flate2::Compression;
use flate2::write::GzEncoder;
use proptest::prelude::*;
use proptest::sample::Index;
use std::io::Write;

type Writer = fn(&TriangleMesh, &mut Vec<u8>) -> io::Result<()>;

/// Every writer with a file name of its format.
const WRITERS: [(&str, Writer); 5] = [
    ("ascii.ply", |m, w| write_ply_ascii(m, w)),
    ("binary.ply", |m, w| write_ply_binary(m, w)),
    ("mesh.obj", |m, w| write_obj(m, w)),
    ("ascii.stl", |m, w| write_stl_ascii(m, w)),
    ("binary.stl", |m, w| write_stl_binary(m, w)),
];

const NAMES: [&str; 6] = [
    "f.ply", "f.obj", "f.stl", "f.ply.gz", "f.obj.gz", "f.stl.gz",
];

/// Proptest cases for each property below.
const CASES: u32 = 2000;

fn config() -> ProptestConfig {
    ProptestConfig {
        cases: CASES,
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

fn coordinate_strategy() -> impl Strategy<Value = f32> {
    use prop::num::f32::{NEGATIVE, NORMAL, POSITIVE, SUBNORMAL, ZERO};
    prop_oneof![
        POSITIVE | NEGATIVE | NORMAL | SUBNORMAL | ZERO,
        // Small values make coincident vertices likely, which exercises STL deduplication.
        (-3i8..3).prop_map(f32::from),
    ]
}

fn mesh_strategy() -> impl Strategy<Value = TriangleMesh> {
    let position = [
        coordinate_strategy(),
        coordinate_strategy(),
        coordinate_strategy(),
    ];
    prop::collection::vec(position, 1..20).prop_flat_map(|positions| {
        let n = positions.len() as u32;
        let triangles = prop::collection::vec([0..n, 0..n, 0..n], 0..24);
        (Just(positions), triangles).prop_map(|(positions, triangles)| TriangleMesh {
            positions,
            triangles,
        })
    })
}

fn encode(writer: Writer, mesh: &TriangleMesh) -> Vec<u8> {
    let mut bytes = Vec::new();
    writer(mesh, &mut bytes).expect("writing to a Vec cannot fail");
    bytes
}

fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut encoder = GzEncoder::new(Vec::new(), Compression::fast());
    encoder
        .write_all(bytes)
        .expect("writing to a Vec cannot fail");
    encoder.finish().expect("writing to a Vec cannot fail")
}

/// The triangles as corner positions, bitwise, which is what STL preserves.
fn soup(mesh: &TriangleMesh) -> Vec<[[u32; 3]; 3]> {
    mesh.triangles
        .iter()
        .map(|t| corners(mesh, t).map(|p| p.map(f32::to_bits)))
        .collect()
}

fn assert_same(name: &str, read: &TriangleMesh, written: &TriangleMesh) {
    if name.contains(".stl") {
        assert_eq!(soup(read), soup(written), "{name}");
    } else {
        assert_eq!(read, written, "{name}");
    }
}

/// Parses and checks that any error names the file, which every message must do.
fn parse_checked(name: &str, bytes: &[u8]) -> Result<(), TestCaseError> {
    if let Err(error) = parse_mesh(name, bytes) {
        let message = error.to_string();
        prop_assert!(message.starts_with(name), "{message}");
    }
    Ok(())
}

/// A valid file, maybe gzipped, with its name: written by one of the writers, or one of
/// the hand-made files that use features the writers never produce.
fn valid_file() -> impl Strategy<Value = (String, Vec<u8>)> {
    let written = (mesh_strategy(), 0..WRITERS.len())
        .prop_map(|(mesh, writer)| (WRITERS[writer].0, encode(WRITERS[writer].1, &mesh)));
    let seeds = prop::sample::select(rich_files());
    (prop_oneof![written, seeds], any::<bool>()).prop_map(|((name, bytes), gzipped)| {
        if gzipped {
            (format!("{name}.gz"), gzip(&bytes))
        } else {
            (name.to_owned(), bytes)
        }
    })
}

const RICH_PLY_HEADER: &str = "ply\ncomment extra properties and elements\n\
    element vertex 4\nproperty float x\nproperty uchar red\nproperty double y\n\
    property list uchar int extra\nproperty int z\n\
    element material 2\nproperty list int float values\nproperty float shine\n\
    element face 2\nproperty uchar flags\nproperty list ushort int vertex_index\n\
    end_header\n";

const RICH_PLY_ASCII_BODY: &str = "0 255 0 2 7 7 0\n1 1 0 0 0\n1 1 1 1 9 0\n\
    0 1 1 0 -3\n3 0.5 1 2 0.25\n0 0.5\n1 4 0 1 2 3\n0 3 3 2 1\n";

const RICH_OBJ: &str = "# rich\nmtllib a.mtl\nv 0 0 0\nv 1 0 0 1.0\nvt 0 0\nvn 0 0 1\r\n\
    v 1 1 0 0.5 0.5 0.5\nv 0 1 0\ng quad\nusemtl red\ns off\n\
    f 1 2/1 3//1 4/1/1 # a quad\nf -4/1 -3/1 -2/1\nl 1 2\n";

const RICH_STL: &str = "solid a\nfacet normal 0 0 nan\nouter loop\nvertex 0 0 0\n\
    vertex 1 0 0\nvertex 1 1 0\nvertex 0 1 0\nendloop\nendfacet\nendsolid a\n\
    SOLID b\nFACET NORMAL 0 0 1 OUTER LOOP VERTEX 0 0 0 VERTEX 1 0 0\n\
    VERTEX 1 1 0 ENDLOOP ENDFACET ENDSOLID\n";

/// RICH_PLY_HEADER's body in binary, in either byte order.
fn rich_ply_binary(big_endian: bool) -> Vec<u8> {
    let format = if big_endian {
        "binary_big_endian"
    } else {
        "binary_little_endian"
    };
    let header = RICH_PLY_HEADER.replace("ply\n", &format!("ply\nformat {format} 1.0\n"));
    let mut out = header.into_bytes();
    let mut put = |mut le: Vec<u8>| {
        if big_endian {
            le.reverse();
        }
        out.extend(le);
    };
    for (i, [x, y, z]) in [[0i32, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, -3]]
        .into_iter()
        .enumerate()
    {
        put((x as f32).to_le_bytes().to_vec());
        put(vec![200]);
        put(f64::from(y).to_le_bytes().to_vec());
        put(vec![i as u8]);
        (0..i).for_each(|n| put((n as i32).to_le_bytes().to_vec()));
        put(z.to_le_bytes().to_vec());
    }
    for len in [3, 0] {
        put(i32::to_le_bytes(len).to_vec());
        (0..len).for_each(|n| put((n as f32).to_le_bytes().to_vec()));
        put(0.5f32.to_le_bytes().to_vec());
    }
    for face in [&[0, 1, 2, 3][..], &[3, 2, 1]] {
        put(vec![7]);
        put((face.len() as u16).to_le_bytes().to_vec());
        face.iter().for_each(|&v| put(i32::to_le_bytes(v).to_vec()));
    }
    out
}

fn rich_files() -> Vec<(&'static str, Vec<u8>)> {
    let ascii = RICH_PLY_HEADER.replace("ply\n", "ply\nformat ascii 1.0\n") + RICH_PLY_ASCII_BODY;
    vec![
        ("rich_ascii.ply", ascii.into_bytes()),
        ("rich_le.ply", rich_ply_binary(false)),
        ("rich_be.ply", rich_ply_binary(true)),
        ("rich.obj", RICH_OBJ.as_bytes().to_vec()),
        ("rich.stl", RICH_STL.as_bytes().to_vec()),
    ]
}

#[test]
fn rich_files_are_valid() {
    let quad = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [0.0, 1.0, -3.0],
    ];
    for (name, bytes) in rich_files() {
        let mesh = parse_mesh(name, &bytes).unwrap();
        assert_eq!(mesh.positions.len(), 4, "{name}");
        if name.ends_with(".ply") {
            assert_eq!(mesh.positions, quad, "{name}");
            assert_eq!(mesh.triangles, [[0, 1, 2], [0, 2, 3], [3, 2, 1]], "{name}");
        } else {
            assert_eq!(mesh.triangles, [[0, 1, 2], [0, 2, 3], [0, 1, 2]], "{name}");
        }
    }
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn every_format_round_trips(mesh in mesh_strategy()) {
        for (name, writer) in WRITERS {
            let bytes = encode(writer, &mesh);
            assert_same(name, &parse_mesh(name, &bytes).unwrap(), &mesh);
            let gz_name = format!("{name}.gz");
            assert_same(&gz_name, &parse_mesh(&gz_name, &gzip(&bytes)).unwrap(), &mesh);
        }
    }

    #[test]
    fn garbage_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..600)) {
        for name in NAMES {
            parse_checked(name, &bytes)?;
        }
    }

    #[test]
    fn truncated_files_never_panic((name, bytes) in valid_file(), cut in any::<Index>()) {
        parse_checked(&name, &bytes[..cut.index(bytes.len() + 1)])?;
    }

    #[test]
    fn corrupted_files_never_panic(
        (name, mut bytes) in valid_file(),
        edits in prop::collection::vec((any::<Index>(), edit_byte()), 1..6),
    ) {
        for (position, value) in edits {
            let i = position.index(bytes.len());
            bytes[i] = value;
        }
        parse_checked(&name, &bytes)?;
        // The same bytes must also be safe when taken for any other format.
        for other in NAMES {
            parse_checked(other, &bytes)?;
        }
    }

    #[test]
    fn token_soup_never_panics(
        tokens in prop::collection::vec(prop::sample::select(SOUP.to_vec()), 0..80),
        name in prop::sample::select(NAMES[..3].to_vec()),
    ) {
        parse_checked(name, tokens.join(" ").as_bytes())?;
    }

    #[test]
    fn random_ply_structures_never_panic(
        header in ply_header_strategy(),
        ascii_body in prop::collection::vec(prop::sample::select(PLY_VALUES.to_vec()), 0..60),
        binary_body in prop::collection::vec(edit_byte(), 0..200),
    ) {
        let mut bytes = header.clone().into_bytes();
        if header.contains("format ascii") {
            bytes.extend(ascii_body.join(" ").bytes());
        } else {
            bytes.extend(binary_body);
        }
        parse_checked("random.ply", &bytes)?;
    }
}

/// Replacement bytes for corruption: any byte, but often one that keeps text formats
/// parseable a little further (digits, separators, signs).
fn edit_byte() -> impl Strategy<Value = u8> {
    prop_oneof![
        any::<u8>(),
        prop::sample::select(b"0123456789 \n-/.e".to_vec()),
        prop::sample::select(vec![0u8, 1, 2, 3, 0xff]),
    ]
}

const PLY_VALUES: [&str; 12] = [
    "0",
    "1",
    "2",
    "3",
    "4",
    "-1",
    "255",
    "1.5",
    "nan",
    "1e39",
    "4294967295",
    "\n",
];

/// A random but well-formed PLY header: the elements and properties the reader looks for,
/// with random types, counts and order, among others it must skip.
fn ply_header_strategy() -> impl Strategy<Value = String> {
    let scalar = prop::sample::select(vec![
        "char", "uchar", "short", "ushort", "int", "uint", "float", "double", "int8", "float64",
    ]);
    let ty = prop_oneof![
        scalar.clone().prop_map(str::to_owned),
        (scalar.clone(), scalar).prop_map(|(count, item)| format!("list {count} {item}")),
    ];
    let name = prop::sample::select(vec!["x", "y", "z", "vertex_indices", "vertex_index", "s"]);
    let property = (ty, name).prop_map(|(ty, name)| format!("property {ty} {name}\n"));
    let count = prop_oneof![0u64..5, Just(u64::from(u32::MAX)), Just(u64::MAX)];
    let element_name = prop::sample::select(vec!["vertex", "face", "other"]);
    let element = (element_name, count, prop::collection::vec(property, 0..5)).prop_map(
        |(name, count, properties)| format!("element {name} {count}\n{}", properties.concat()),
    );
    let encoding = prop::sample::select(vec!["ascii", "binary_little_endian", "binary_big_endian"]);
    (encoding, prop::collection::vec(element, 0..4)).prop_map(|(encoding, elements)| {
        format!(
            "ply\nformat {encoding} 1.0\n{}end_header\n",
            elements.concat()
        )
    })
}

/// Keywords and awkward numbers of all three text formats, so that random sequences get
/// past the headers and into the deeper parts of the grammars.
const SOUP: [&str; 40] = [
    "ply\n",
    "format",
    "ascii",
    "binary_little_endian",
    "1.0\n",
    "element",
    "vertex",
    "face",
    "property",
    "float",
    "uchar",
    "int",
    "list",
    "x",
    "y",
    "z",
    "vertex_indices",
    "end_header\n",
    "\n",
    "0",
    "1",
    "2",
    "3",
    "-1",
    "1.5",
    "1e39",
    "nan",
    "4294967296",
    "18446744073709551616",
    "v",
    "f",
    "1/2/3",
    "2//1",
    "solid",
    "facet",
    "normal",
    "outer",
    "loop",
    "endloop",
    "endfacet",
];

#[test]
fn read_mesh_reads_every_format_from_disk() {
    let mesh = TriangleMesh {
        positions: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.5]],
        triangles: vec![[0, 1, 2]],
    };
    let dir = tempfile::tempdir().unwrap();
    for (name, writer) in WRITERS {
        let path = dir.path().join(name);
        fs::write(&path, encode(writer, &mesh)).unwrap();
        assert_same(name, &read_mesh(&path).unwrap(), &mesh);
    }
}

#[test]
fn empty_mesh_round_trips() {
    let empty = TriangleMesh::default();
    for (name, writer) in WRITERS {
        assert_eq!(
            parse_mesh(name, &encode(writer, &empty)).unwrap(),
            empty,
            "{name}"
        );
    }
}

#[test]
fn missing_file_error_names_the_path() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("absent.obj");
    let error = read_mesh(&path).unwrap_err();
    assert!(matches!(error, MeshError::Io { .. }));
    assert!(error.to_string().starts_with(&path.display().to_string()));
}

#[test]
fn unknown_extension_lists_supported_ones() {
    let message = parse_mesh("scene.fbx", b"").unwrap_err().to_string();
    assert!(
        message.starts_with("scene.fbx: unsupported mesh format"),
        "{message}"
    );
    assert!(message.contains(".ply, .obj and .stl"), "{message}");
    assert!(matches!(
        parse_mesh("x.gz", b""),
        Err(MeshError::UnsupportedFormat { .. })
    ));
}

#[test]
fn extensions_are_case_insensitive() {
    assert!(parse_mesh("MESH.OBJ.GZ", &gzip(b"v 1 2 3\n")).is_ok());
}

#[test]
fn gzip_errors_name_file_and_place() {
    let message = parse_mesh("a.obj.gz", b"v 1 2 3").unwrap_err().to_string();
    assert_eq!(
        message,
        "a.obj.gz: byte 0: missing header: expected gzip magic bytes 1f 8b"
    );
    let compressed = gzip(b"v 1 2 3\nv 4 5 6\n");
    let truncated = &compressed[..compressed.len() - 4];
    let message = parse_mesh("a.obj.gz", truncated).unwrap_err().to_string();
    assert!(
        message.starts_with("a.obj.gz: gzip stream invalid after"),
        "{message}"
    );
}

#[test]
fn writers_reject_invalid_meshes() {
    let bad_index = TriangleMesh {
        positions: vec![[0.0; 3]],
        triangles: vec![[0, 0, 1]],
    };
    let nan = TriangleMesh {
        positions: vec![[f32::NAN, 0.0, 0.0]],
        triangles: vec![],
    };
    for (name, writer) in WRITERS {
        for mesh in [&bad_index, &nan] {
            let error = writer(mesh, &mut Vec::new()).unwrap_err();
            assert_eq!(error.kind(), io::ErrorKind::InvalidInput, "{name}");
        }
    }
}
