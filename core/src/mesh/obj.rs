//! Wavefront OBJ reader (geometry only: `v` and `f`) and writer.
//!
//! Hand-written rather than tobj: tobj 4.0.5 survived a quick garbage proptest, but its
//! `LoadError` is a bare enum ("face parse error") with no line number, and it cannot be
//! recovered from outside. Reading `v` and `f` lines is a few dozen lines of code.

use std::io::{self, BufWriter, Write};

use super::{
    Failure, Fan, Location, ParseErrorKind, ParseResult, TriangleMesh, check_writable, coordinate,
    parse_number, shown, words,
};

/// Reads an OBJ file. Statements other than `v` and `f` (normals, texture coordinates, groups,
/// materials, ...) are ignored.
pub(super) fn parse(bytes: &[u8]) -> ParseResult<TriangleMesh> {
    let mut mesh = TriangleMesh::default();
    for (index, line) in bytes.split(|&b| b == b'\n').enumerate() {
        parse_line(line, &mut mesh)
            .map_err(|kind| Failure::new(Location::Line(index + 1), kind))?;
    }
    Ok(mesh)
}

fn parse_line(line: &[u8], mesh: &mut TriangleMesh) -> Result<(), ParseErrorKind> {
    let content = line.split(|&b| b == b'#').next().unwrap_or_default();
    let mut words = words(content);
    match words.next() {
        Some(b"v") => {
            let position = parse_position(words)?;
            mesh.positions.push(position);
            Ok(())
        }
        Some(b"f") => parse_face(words, mesh),
        _ => Ok(()),
    }
}

/// Parses `x y z`; an optional `w` or vertex colours after them are ignored.
fn parse_position<'a>(words: impl Iterator<Item = &'a [u8]>) -> Result<[f32; 3], ParseErrorKind> {
    let mut position = [0.0; 3];
    let mut found = 0;
    for (slot, word) in position.iter_mut().zip(words) {
        let value: f32 = parse_number(word, "a float")?;
        *slot = coordinate(value.into())?;
        found += 1;
    }
    if found < 3 {
        return Err(ParseErrorKind::WrongCount {
            what: "vertex coordinates",
            expected: 3,
            found,
        });
    }
    Ok(position)
}

fn parse_face<'a>(
    words: impl Iterator<Item = &'a [u8]>,
    mesh: &mut TriangleMesh,
) -> Result<(), ParseErrorKind> {
    let vertex_count = mesh.positions.len();
    let mut fan = Fan::default();
    for word in words {
        let index = parse_face_vertex(word, vertex_count)?;
        fan.push(index, &mut mesh.triangles);
    }
    fan.finish()
}

/// Parses one of `v`, `v/vt`, `v//vn` or `v/vt/vn` and resolves `v` to a 0-based index.
fn parse_face_vertex(word: &[u8], vertex_count: usize) -> Result<u32, ParseErrorKind> {
    let mut parts = word.split(|&b| b == b'/');
    let vertex = parts.next().unwrap_or_default();
    let index: i64 = parse_number(vertex, "a vertex index")?;
    // Texture and normal indices are not used, but a malformed one means a malformed file.
    for (n, part) in parts.enumerate() {
        if n >= 2 {
            let message = format!("face vertex {} has more than three parts", shown(word));
            return Err(ParseErrorKind::Syntax(message));
        }
        if !part.is_empty() {
            parse_number::<i64>(part, "a texture or normal index")?;
        }
    }
    resolve(index, vertex_count)
}

/// Turns a 1-based or negative (relative to the end) OBJ index into a 0-based one.
fn resolve(index: i64, vertex_count: usize) -> Result<u32, ParseErrorKind> {
    let count = i64::try_from(vertex_count).unwrap_or(i64::MAX);
    let resolved = match index {
        0 => {
            let message = "vertex index 0 is invalid (OBJ indices start at 1)".to_owned();
            return Err(ParseErrorKind::Syntax(message));
        }
        i if i > 0 => i - 1,
        i => count + i,
    };
    u32::try_from(resolved)
        .ok()
        .filter(|&r| i64::from(r) < count)
        .ok_or(ParseErrorKind::IndexOutOfRange {
            index,
            vertex_count: vertex_count as u64,
        })
}

/// Writes `mesh` as OBJ (`v` and `f` lines), with coordinates in shortest round-trip form.
pub fn write_obj(mesh: &TriangleMesh, w: impl Write) -> io::Result<()> {
    check_writable(mesh)?;
    let mut w = BufWriter::new(w);
    for [x, y, z] in &mesh.positions {
        writeln!(w, "v {x:?} {y:?} {z:?}")?;
    }
    for triangle in &mesh.triangles {
        let [a, b, c] = triangle.map(|i| u64::from(i) + 1);
        writeln!(w, "f {a} {b} {c}")?;
    }
    w.flush()
}

#[cfg(test)]
mod tests {
    use super::super::parse_mesh;

    fn error(text: &str) -> String {
        parse_mesh("bunny.obj", text.as_bytes())
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn reads_all_face_forms_and_relative_indices() {
        let text = "# comment\nv 0 0 0\nv 1 0 0 1.0\nvt 0 0\nvn 0 0 1\r\nv 1 1 0 0.5 0.5 0.5\n\
                    v 0 1 0\ng quad\nusemtl red\nf 1 2/1 3//1 4/1/1 # a quad\nf -4 -3 -2\n";
        let mesh = parse_mesh("quad.obj", text.as_bytes()).unwrap();
        assert_eq!(mesh.positions.len(), 4);
        assert_eq!(mesh.positions[2], [1.0, 1.0, 0.0]);
        assert_eq!(mesh.triangles, [[0, 1, 2], [0, 2, 3], [0, 1, 2]]);
    }

    #[test]
    fn errors_give_file_and_line() {
        assert_eq!(
            error("v 1 2 3\nv 4 5 6\nv 1 2\n"),
            "bunny.obj: line 3: expected 3 vertex coordinates, found 2"
        );
        assert_eq!(
            error("v 1 2 3\nv 1 x 3\n"),
            "bunny.obj: line 2: bad number \"x\" (expected a float)"
        );
        assert_eq!(
            error("v 1 2 3\nv 1 2 3\nf 1 2 1\nf 1 2 3\n"),
            "bunny.obj: line 4: vertex index 3 out of range (the mesh has 2 vertices)"
        );
        assert_eq!(
            error("v 1 2 3\nf -2 1 1\n"),
            "bunny.obj: line 2: vertex index -2 out of range (the mesh has 1 vertices)"
        );
        assert_eq!(
            error("v 1 2 3\nf 0 1 1\n"),
            "bunny.obj: line 2: vertex index 0 is invalid (OBJ indices start at 1)"
        );
        assert_eq!(
            error("v 1 2 3\n\nf 1 1\n"),
            "bunny.obj: line 3: face has 2 vertices, at least 3 are needed"
        );
        assert_eq!(
            error("v 1 2 3\nf 1/1/1/1 1 1\n"),
            "bunny.obj: line 2: face vertex \"1/1/1/1\" has more than three parts"
        );
        assert_eq!(
            error("v 1 2 1e39\n"),
            "bunny.obj: line 1: non-finite vertex coordinate inf"
        );
    }
}
