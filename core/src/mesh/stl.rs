//! STL reader (ASCII and binary) and writers.
//!
//! Hand-written rather than stl_io: stl_io 0.11.0 treats any file whose first line starts with
//! "solid " as ASCII, so it rejects valid binary files whose 80-byte header starts that way
//! (common from CAD exporters; reproduced in a quick test), and its errors are `io::Error`s
//! without line or offset. Binary STL is a fixed 50-byte record; the ASCII grammar is tiny.

use std::collections::HashMap;
use std::io::{self, BufWriter, Write};

use super::{
    Failure, Fan, Location, ParseErrorKind, ParseResult, Tokens, TriangleMesh, at, check_writable,
    coordinate, corners, parse_number, shown,
};

/// 80-byte free-form header plus a little-endian `u32` triangle count.
const PREFIX_LEN: usize = 84;
/// Normal and three vertices as `f32`, plus a 2-byte attribute.
const RECORD_LEN: usize = 50;

/// Reads an STL file, ASCII or binary.
pub(super) fn parse(bytes: &[u8]) -> ParseResult<TriangleMesh> {
    if is_ascii(bytes) {
        parse_ascii(bytes)
    } else {
        parse_binary(bytes)
    }
}

fn binary_count(bytes: &[u8]) -> Option<u32> {
    let raw = bytes.get(80..PREFIX_LEN)?;
    Some(u32::from_le_bytes(raw.try_into().ok()?))
}

/// Binary headers may start with "solid" too, so a file whose size matches its binary triangle
/// count exactly is binary whatever its first bytes are.
fn is_ascii(bytes: &[u8]) -> bool {
    let binary_size = |n: u32| PREFIX_LEN as u64 + RECORD_LEN as u64 * u64::from(n);
    let exact_binary = binary_count(bytes).is_some_and(|n| binary_size(n) == bytes.len() as u64);
    let start = bytes.trim_ascii_start();
    !exact_binary
        && start
            .get(..5)
            .is_some_and(|s| s.eq_ignore_ascii_case(b"solid"))
}

fn parse_binary(bytes: &[u8]) -> ParseResult<TriangleMesh> {
    let count = binary_count(bytes).ok_or_else(|| {
        let expected = "\"solid\" (ASCII STL) or an 84-byte binary STL header";
        Failure::new(
            Location::Byte(0),
            ParseErrorKind::MissingHeader { expected },
        )
    })?;
    let (records, _) = bytes
        .get(PREFIX_LEN..)
        .unwrap_or_default()
        .as_chunks::<RECORD_LEN>();
    // Trailing bytes after the records are tolerated: some exporters pad files.
    let records = records.get(..count as usize).ok_or_else(|| {
        let kind = ParseErrorKind::CountTooLarge {
            what: "binary STL triangle count".to_owned(),
            count: count.into(),
            available: bytes.len().saturating_sub(PREFIX_LEN),
        };
        Failure::new(Location::Byte(80), kind)
    })?;
    let mut builder = Indexer::with_capacity(records.len());
    for (n, record) in records.iter().enumerate() {
        let offset = PREFIX_LEN + n * RECORD_LEN;
        let (floats, _attribute) = record.as_chunks::<4>();
        // floats[0..3] is the normal, which is recomputed by whoever needs it.
        let corners = floats.get(3..12).unwrap_or_default().chunks(3);
        let mut triangle = [0; 3];
        for ((corner, xyz), slot) in corners.enumerate().zip(&mut triangle) {
            let place = Location::Byte(offset + 12 + 12 * corner);
            let position = binary_position(xyz).map_err(at(place))?;
            *slot = builder.index(position).map_err(at(place))?;
        }
        builder.mesh.triangles.push(triangle);
    }
    Ok(builder.mesh)
}

fn binary_position(xyz: &[[u8; 4]]) -> Result<[f32; 3], ParseErrorKind> {
    let mut position = [0.0; 3];
    for (slot, raw) in position.iter_mut().zip(xyz) {
        *slot = coordinate(f32::from_le_bytes(*raw).into())?;
    }
    Ok(position)
}

/// Gives each distinct position (bitwise) one index, since STL stores every corner in full.
struct Indexer {
    mesh: TriangleMesh,
    seen: HashMap<[u32; 3], u32>,
}

impl Indexer {
    /// `triangles` must already be bounded by the input size.
    fn with_capacity(triangles: usize) -> Self {
        let mesh = TriangleMesh {
            positions: Vec::with_capacity(triangles),
            triangles: Vec::with_capacity(triangles),
        };
        Indexer {
            mesh,
            seen: HashMap::with_capacity(triangles),
        }
    }

    fn index(&mut self, position: [f32; 3]) -> Result<u32, ParseErrorKind> {
        let positions = &mut self.mesh.positions;
        let next = u32::try_from(positions.len())
            .map_err(|_| ParseErrorKind::Syntax("more than 2^32 distinct vertices".to_owned()))?;
        let index = *self
            .seen
            .entry(position.map(f32::to_bits))
            .or_insert_with(|| {
                positions.push(position);
                next
            });
        Ok(index)
    }
}

fn parse_ascii(bytes: &[u8]) -> ParseResult<TriangleMesh> {
    let mut tokens = Tokens::new(bytes, 0, 1);
    let mut builder = Indexer::with_capacity(0);
    // Several solids may follow one another in one file.
    let mut in_solid = false;
    loop {
        let token = tokens.next_token();
        match (in_solid, token) {
            (false, None) => return Ok(builder.mesh),
            (true, None) => return Err(truncated(&tokens, "endsolid")),
            (false, Some(t)) if keyword(t, "solid") => {
                in_solid = true;
                // The rest of the line is the solid's name.
                tokens.skip_line();
            }
            (true, Some(t)) if keyword(t, "endsolid") => {
                in_solid = false;
                tokens.skip_line();
            }
            (true, Some(t)) if keyword(t, "facet") => parse_facet(&mut tokens, &mut builder)?,
            (_, Some(t)) => {
                let expected = if in_solid {
                    "\"facet\" or \"endsolid\""
                } else {
                    "\"solid\""
                };
                let message = format!("expected {expected}, found {}", shown(t));
                return Err(Failure::new(
                    Location::Line(tokens.line()),
                    ParseErrorKind::Syntax(message),
                ));
            }
        }
    }
}

fn keyword(token: &[u8], word: &str) -> bool {
    token.eq_ignore_ascii_case(word.as_bytes())
}

fn truncated(tokens: &Tokens<'_>, keyword: &str) -> Failure {
    let expected = format!("\"{keyword}\"");
    Failure::new(
        Location::Line(tokens.line()),
        ParseErrorKind::Truncated { expected },
    )
}

fn expect(tokens: &mut Tokens<'_>, word: &str) -> ParseResult<()> {
    let token = tokens.next_token().ok_or_else(|| truncated(tokens, word))?;
    if keyword(token, word) {
        return Ok(());
    }
    let message = format!("expected \"{word}\", found {}", shown(token));
    Err(Failure::new(
        Location::Line(tokens.line()),
        ParseErrorKind::Syntax(message),
    ))
}

fn number(tokens: &mut Tokens<'_>) -> ParseResult<f32> {
    let token = tokens
        .next_token()
        .ok_or_else(|| truncated(tokens, "a number"))?;
    parse_number(token, "a float").map_err(at(Location::Line(tokens.line())))
}

/// Parses from after `facet` to `endfacet`.
fn parse_facet(tokens: &mut Tokens<'_>, builder: &mut Indexer) -> ParseResult<()> {
    expect(tokens, "normal")?;
    // Normals are not kept, and some exporters write NaN there, so only the syntax matters.
    for _ in 0..3 {
        number(tokens)?;
    }
    expect(tokens, "outer")?;
    expect(tokens, "loop")?;
    let mut fan = Fan::default();
    loop {
        match tokens.next_token() {
            Some(t) if keyword(t, "vertex") => {
                let position = parse_vertex(tokens)?;
                let here = Location::Line(tokens.line());
                let index = builder.index(position).map_err(at(here))?;
                fan.push(index, &mut builder.mesh.triangles);
            }
            Some(t) if keyword(t, "endloop") => break,
            Some(t) => {
                let message = format!("expected \"vertex\" or \"endloop\", found {}", shown(t));
                return Err(Failure::new(
                    Location::Line(tokens.line()),
                    ParseErrorKind::Syntax(message),
                ));
            }
            None => return Err(truncated(tokens, "endloop")),
        }
    }
    fan.finish().map_err(at(Location::Line(tokens.line())))?;
    expect(tokens, "endfacet")
}

fn parse_vertex(tokens: &mut Tokens<'_>) -> ParseResult<[f32; 3]> {
    let mut position = [0.0; 3];
    for slot in &mut position {
        let value = number(tokens)?;
        *slot = coordinate(value.into()).map_err(at(Location::Line(tokens.line())))?;
    }
    Ok(position)
}

/// Unit normal of a triangle by the right-hand rule, zero for degenerate triangles. Computed
/// in f64 so that the cross product of large coordinates cannot overflow.
fn facet_normal([a, b, c]: [[f32; 3]; 3]) -> [f32; 3] {
    let edge =
        |from: [f32; 3], to: [f32; 3]| [0, 1, 2].map(|i| f64::from(to[i]) - f64::from(from[i]));
    let (u, v) = (edge(a, b), edge(a, c));
    let n = [
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    ];
    let len = n.iter().map(|x| x * x).sum::<f64>().sqrt();
    if len > 0.0 && len.is_finite() {
        n.map(|x| (x / len) as f32)
    } else {
        [0.0; 3]
    }
}

/// Writes `mesh` as ASCII STL, with coordinates in shortest round-trip form.
pub fn write_stl_ascii(mesh: &TriangleMesh, w: impl Write) -> io::Result<()> {
    check_writable(mesh)?;
    let mut w = BufWriter::new(w);
    writeln!(w, "solid rayfarm")?;
    for triangle in &mesh.triangles {
        let corners = corners(mesh, triangle);
        let [nx, ny, nz] = facet_normal(corners);
        writeln!(w, "  facet normal {nx:?} {ny:?} {nz:?}\n    outer loop")?;
        for [x, y, z] in corners {
            writeln!(w, "      vertex {x:?} {y:?} {z:?}")?;
        }
        writeln!(w, "    endloop\n  endfacet")?;
    }
    writeln!(w, "endsolid rayfarm")?;
    w.flush()
}

/// Writes `mesh` as binary STL. The header deliberately does not start with "solid".
pub fn write_stl_binary(mesh: &TriangleMesh, w: impl Write) -> io::Result<()> {
    check_writable(mesh)?;
    let count = u32::try_from(mesh.triangles.len()).map_err(|_| {
        super::invalid_input("binary STL holds at most 2^32 - 1 triangles".to_owned())
    })?;
    let mut w = BufWriter::new(w);
    let mut header = [b' '; 80];
    let label = b"binary STL written by rayfarm";
    header[..label.len()].copy_from_slice(label);
    w.write_all(&header)?;
    w.write_all(&count.to_le_bytes())?;
    for triangle in &mesh.triangles {
        let corners = corners(mesh, triangle);
        for value in std::iter::once(facet_normal(corners))
            .chain(corners)
            .flatten()
        {
            w.write_all(&value.to_le_bytes())?;
        }
        w.write_all(&[0, 0])?;
    }
    w.flush()
}

#[cfg(test)]
mod tests {
    use super::super::parse_mesh;
    use super::*;

    fn error(bytes: &[u8]) -> String {
        parse_mesh("part.stl", bytes).unwrap_err().to_string()
    }

    fn binary(header: &[u8], triangles: &[[[f32; 3]; 3]]) -> Vec<u8> {
        let mut bytes = header.to_vec();
        bytes.resize(80, 0);
        bytes.extend((triangles.len() as u32).to_le_bytes());
        for triangle in triangles {
            bytes.extend([0u8; 12]);
            bytes.extend(triangle.iter().flatten().flat_map(|c| c.to_le_bytes()));
            bytes.extend([0, 0]);
        }
        bytes
    }

    const TWO: [[[f32; 3]; 3]; 2] = [
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        [[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]],
    ];

    #[test]
    fn binary_file_whose_header_starts_with_solid_is_binary() {
        let mesh = parse_mesh("cad.stl", &binary(b"solid exported by CAD", &TWO)).unwrap();
        assert_eq!(mesh.positions.len(), 4, "shared corners are deduplicated");
        assert_eq!(mesh.triangles, [[0, 1, 2], [1, 3, 2]]);
    }

    #[test]
    fn binary_count_beyond_the_data_is_an_error() {
        let mut bytes = binary(b"part", &TWO);
        bytes[80..84].copy_from_slice(&u32::MAX.to_le_bytes());
        assert_eq!(
            error(&bytes),
            "part.stl: byte 80: binary STL triangle count claims 4294967295 entries, \
             more than the remaining 100 bytes can hold"
        );
        assert_eq!(
            error(b"short"),
            "part.stl: byte 0: missing header: expected \"solid\" (ASCII STL) or an 84-byte \
             binary STL header"
        );
    }

    #[test]
    fn binary_non_finite_coordinate_gives_offset() {
        let mut triangles = TWO;
        triangles[1][2][1] = f32::INFINITY;
        assert_eq!(
            error(&binary(b"part", &triangles)),
            "part.stl: byte 170: non-finite vertex coordinate inf"
        );
    }

    #[test]
    fn ascii_reads_several_solids_and_quads() {
        let text = "solid a\nfacet normal 0 0 nan\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n\
                    vertex 1 1 0\nvertex 0 1 0\nendloop\nendfacet\nendsolid a\n\
                    SOLID b\nFACET NORMAL 0 0 1 OUTER LOOP VERTEX 0 0 0 VERTEX 1 0 0 \
                    VERTEX 1 1 0 ENDLOOP ENDFACET ENDSOLID\n";
        let mesh = parse_mesh("two.stl", text.as_bytes()).unwrap();
        assert_eq!(mesh.positions.len(), 4);
        assert_eq!(mesh.triangles, [[0, 1, 2], [0, 2, 3], [0, 1, 2]]);
    }

    #[test]
    fn ascii_errors_give_the_line() {
        let text = "solid a\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0\n\
                    endloop\nendfacet\nendsolid a\n";
        assert_eq!(
            error(text.as_bytes()),
            "part.stl: line 6: bad number \"endloop\" (expected a float)"
        );
        let text = "solid a\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n";
        assert_eq!(
            error(text.as_bytes()),
            "part.stl: line 5: unexpected end of data, expected \"endloop\""
        );
        let text = "solid a\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n\
                    endloop\nendfacet\nendsolid a\n";
        assert_eq!(
            error(text.as_bytes()),
            "part.stl: line 6: face has 2 vertices, at least 3 are needed"
        );
        assert_eq!(
            error(b"solid a\nfacet normal 0 0 1\ninner loop\n"),
            "part.stl: line 3: expected \"outer\", found \"inner\""
        );
    }

    #[test]
    fn normals_are_unit_or_zero() {
        assert_eq!(facet_normal(TWO[0]), [0.0, 0.0, 1.0]);
        assert_eq!(facet_normal([[1.0; 3]; 3]), [0.0; 3]);
        let huge = [[0.0; 3], [f32::MAX, 0.0, 0.0], [0.0, f32::MAX, 0.0]];
        assert_eq!(facet_normal(huge), [0.0, 0.0, 1.0]);
    }
}
