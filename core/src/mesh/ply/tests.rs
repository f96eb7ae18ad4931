use super::super::{Location, MeshError, ParseErrorKind, parse_mesh};
use super::*;

fn error(name: &str, bytes: &[u8]) -> String {
    parse_mesh(name, bytes).unwrap_err().to_string()
}

const SQUARE_HEADER: &str = "ply\nformat ascii 1.0\ncomment a square\n\
    element vertex 4\nproperty float x\nproperty uchar red\nproperty double y\n\
    property list uchar int extra\nproperty int z\n\
    element material 2\nproperty list int float values\nproperty float shine\n\
    element face 1\nproperty uchar flags\nproperty list uchar uint vertex_index\n\
    end_header\n";

#[test]
fn ascii_skips_other_properties_and_elements_and_fans_quads() {
    let body = "0 255 0 2 7 7 0\n1 1 0 0 0\n1 1 1 1 9 0\n0 1 1 0 -3\n\
                3 0.5 1 2 0.25\n0 0.5\n1 4 0 1 2 3\n";
    let mesh = parse_mesh("square.ply", format!("{SQUARE_HEADER}{body}").as_bytes()).unwrap();
    let positions = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [0.0, 1.0, -3.0],
    ];
    assert_eq!(mesh.positions, positions);
    assert_eq!(mesh.triangles, [[0, 1, 2], [0, 2, 3]]);
}

#[test]
fn big_endian_with_mixed_types() {
    let header = "ply\r\nformat binary_big_endian 1.0\r\nelement vertex 3\r\n\
        property double x\r\nproperty short y\r\nproperty uchar z\r\n\
        element face 1\r\nproperty list ushort char vertex_indices\r\nend_header\r\n";
    let mut bytes = header.as_bytes().to_vec();
    for (x, y, z) in [(0.5f64, -2i16, 7u8), (1.0, 0, 0), (0.0, 1, 255)] {
        bytes.extend(x.to_be_bytes());
        bytes.extend(y.to_be_bytes());
        bytes.push(z);
    }
    bytes.extend(3u16.to_be_bytes());
    bytes.extend([2, 1, 0]);
    let mesh = parse_mesh("be.ply", &bytes).unwrap();
    assert_eq!(
        mesh.positions,
        [[0.5, -2.0, 7.0], [1.0, 0.0, 0.0], [0.0, 1.0, 255.0]]
    );
    assert_eq!(mesh.triangles, [[2, 1, 0]]);
}

#[test]
fn faces_may_precede_vertices() {
    let text = "ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n\
        element vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n\
        3 0 1 2\n0 0 0\n1 0 0\n0 1 0\n";
    assert_eq!(
        parse_mesh("f.ply", text.as_bytes()).unwrap().triangles,
        [[0, 1, 2]]
    );
}

#[test]
fn ascii_errors_give_the_line() {
    let text = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n\
        property float z\nend_header\n0 0 0\n1 0 zero\n";
    assert_eq!(
        error("bunny.ply", text.as_bytes()),
        "bunny.ply: line 9: bad number \"zero\" (expected a float)"
    );
    let text = text.replace("zero", "1e39");
    assert_eq!(
        error("bunny.ply", text.as_bytes()),
        "bunny.ply: line 9: non-finite vertex coordinate inf"
    );
}

#[test]
fn header_errors_give_the_line() {
    assert_eq!(
        error("x.ply", b"PLY\n"),
        "x.ply: line 1: missing header: expected a first line \"ply\""
    );
    assert_eq!(
        error(
            "x.ply",
            b"ply\nformat ascii 1.0\nproperty float x\nend_header\n"
        ),
        "x.ply: line 3: malformed header: property before any element"
    );
    assert_eq!(
        error(
            "x.ply",
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
        ),
        "x.ply: line 5: unexpected end of data, expected \"end_header\""
    );
    let no_z = b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n\
        property float y\nend_header\n";
    assert_eq!(
        error("x.ply", no_z),
        "x.ply: line 3: malformed header: element \"vertex\" has no scalar property \"z\""
    );
}

fn binary_triangle(indices: [u32; 3]) -> Vec<u8> {
    let mesh = TriangleMesh {
        positions: vec![[0.0; 3]; 3],
        triangles: vec![[0, 1, 2]],
    };
    let mut bytes = Vec::new();
    write_ply_binary(&mesh, &mut bytes).unwrap();
    let face = bytes.len() - 12;
    for (i, index) in indices.iter().enumerate() {
        bytes[face + 4 * i..face + 4 * i + 4].copy_from_slice(&index.to_le_bytes());
    }
    bytes
}

#[test]
fn binary_errors_give_the_byte_offset() {
    let bytes = binary_triangle([0, 5, 2]);
    let offset = bytes.len() - 8;
    assert_eq!(
        error("b.ply", &bytes),
        format!("b.ply: byte {offset}: vertex index 5 out of range (the mesh has 3 vertices)")
    );
    let truncated = &bytes[..bytes.len() - 2];
    assert_eq!(
        error("b.ply", truncated),
        format!(
            "b.ply: byte {}: vertex_indices claims 3 entries, more than the remaining 10 \
             bytes can hold",
            bytes.len() - 13
        )
    );
    let mut bad_float = binary_triangle([0, 1, 2]);
    let y_of_second = 4 * 3 + 4;
    let offset = bad_float.len() - 13 - 3 * 12 + y_of_second;
    bad_float[offset..offset + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    assert_eq!(
        error("b.ply", &bad_float),
        format!("b.ply: byte {offset}: non-finite vertex coordinate NaN")
    );
}

#[test]
fn huge_counts_fail_without_allocating() {
    let text = "ply\nformat binary_little_endian 1.0\nelement vertex 18446744073709551615\n\
        property double x\nproperty double y\nproperty double z\nend_header\n1234";
    assert_eq!(
        error("huge.ply", text.as_bytes()),
        format!(
            "huge.ply: byte {}: vertex claims 18446744073709551615 entries, more than the \
             remaining 4 bytes can hold",
            text.len() - 4
        )
    );
    let text = "ply\nformat ascii 1.0\nelement junk 1\nproperty list uint uint values\n\
        end_header\n4294967295 1 2\n";
    assert_eq!(
        error("huge.ply", text.as_bytes()),
        "huge.ply: line 6: unexpected end of data, expected a uint"
    );
    let mut bytes = b"ply\nformat binary_little_endian 1.0\nelement junk 1\n\
        property list uint uint values\nend_header\n"
        .to_vec();
    bytes.extend(u32::MAX.to_le_bytes());
    let message = error("huge.ply", &bytes);
    assert!(
        message.contains("values claims 4294967295 entries"),
        "{message}"
    );
}

#[test]
fn elements_without_properties_are_skipped_whatever_their_count() {
    let text = "ply\nformat ascii 1.0\nelement nothing 18446744073709551615\nend_header\n";
    assert_eq!(
        parse_mesh("e.ply", text.as_bytes()).unwrap(),
        TriangleMesh::default()
    );
}

#[test]
fn degenerate_faces_are_errors() {
    let text = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n\
        property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\
        0 0 0\n1 1 1\n2 0 1\n";
    let error = parse_mesh("d.ply", text.as_bytes()).unwrap_err();
    assert!(matches!(
        error,
        MeshError::Parse {
            location: Location::Line(12),
            kind: ParseErrorKind::Degenerate { vertices: 2 },
            ..
        }
    ));
}
