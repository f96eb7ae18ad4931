//! Reading and writing indexed triangle meshes: PLY, OBJ and STL, each optionally gzipped.
//!
//! The three readers are small hand-written parsers rather than ply-rs, tobj or stl_io. Each of
//! those was checked with a quick proptest: ply-rs panics on garbage headers, stl_io misreads
//! binary files whose header starts with "solid" and neither it nor tobj reports where an error
//! is. The readers here need both guarantees (no panics, file and place in every error); the
//! per-format reasons are at the top of each file. Every reader works on a byte slice, so it can
//! bound each count it reads by the input that is left before allocating anything for it.

use std::borrow::Cow;
use std::fmt;
use std::fs;
use std::io::{self, Read};
use std::path::{Path, PathBuf};
use std::str::FromStr;

use flate2::read::MultiGzDecoder;

mod obj;
mod ply;
mod stl;

pub use obj::write_obj;
pub use ply::{write_ply_ascii, write_ply_binary};
pub use stl::{write_stl_ascii, write_stl_binary};

/// An indexed triangle mesh as read from a file.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TriangleMesh {
    /// Vertex positions; all coordinates are finite.
    pub positions: Vec<[f32; 3]>,
    /// Triangles as indices into `positions`.
    pub triangles: Vec<[u32; 3]>,
}

/// Where in a file a parse error was found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Location {
    /// 1-based line number, for text formats and for the text header of PLY.
    Line(usize),
    /// Byte offset from the start of the data, for binary formats. For gzipped files the
    /// offset counts decompressed bytes.
    Byte(usize),
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Location::Line(line) => write!(f, "line {line}"),
            Location::Byte(offset) => write!(f, "byte {offset}"),
        }
    }
}

/// An error from [`read_mesh`] or [`parse_mesh`]. The message always starts with the file name.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    /// The file could not be read.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file that could not be read.
        path: PathBuf,
        /// The underlying error.
        source: io::Error,
    },
    /// The file name does not end in a supported extension.
    #[error(
        "{path}: unsupported mesh format; supported extensions are .ply, .obj and .stl, \
         each optionally followed by .gz (a raw volume, of any extension, is read with \
         --dims X,Y,Z, --dtype and --iso)"
    )]
    UnsupportedFormat {
        /// The file name as given.
        path: String,
    },
    /// The gzip stream is corrupt or truncated.
    #[error("{path}: gzip stream invalid after {decompressed} decompressed bytes: {source}")]
    Gzip {
        /// The file name as given.
        path: String,
        /// How many bytes were decompressed before the failure.
        decompressed: usize,
        /// The error reported by the decompressor.
        source: io::Error,
    },
    /// The (decompressed) data is not a valid mesh file of its format.
    #[error("{path}: {location}: {kind}")]
    Parse {
        /// The file name as given.
        path: String,
        /// Where the problem was found.
        location: Location,
        /// What is wrong.
        kind: ParseErrorKind,
    },
}

/// What is wrong with a mesh file; see [`MeshError::Parse`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum ParseErrorKind {
    /// The format's magic bytes are missing.
    #[error("missing header: expected {expected}")]
    MissingHeader {
        /// What the file should start with.
        expected: &'static str,
    },
    /// A header line is malformed or inconsistent.
    #[error("malformed header: {0}")]
    Header(String),
    /// Something other than what the grammar allows at this place.
    #[error("{0}")]
    Syntax(String),
    /// A token that should be a number is not one, or is out of range for its type.
    #[error("bad number {token} (expected {expected})")]
    BadNumber {
        /// The offending token, quoted and shortened.
        token: String,
        /// What was expected, e.g. "a float".
        expected: &'static str,
    },
    /// A statement has too few values.
    #[error("expected {expected} {what}, found {found}")]
    WrongCount {
        /// What is counted.
        what: &'static str,
        /// How many were expected.
        expected: usize,
        /// How many were found.
        found: usize,
    },
    /// A face refers to a vertex that does not exist.
    #[error("vertex index {index} out of range (the mesh has {vertex_count} vertices)")]
    IndexOutOfRange {
        /// The index as written in the file.
        index: i64,
        /// How many vertices can be referred to.
        vertex_count: u64,
    },
    /// A vertex coordinate is infinite or NaN (or overflows `f32`).
    #[error("non-finite vertex coordinate {value}")]
    NonFinite {
        /// The coordinate as read.
        value: f64,
    },
    /// The data ends in the middle of something.
    #[error("unexpected end of data, expected {expected}")]
    Truncated {
        /// What should have come next.
        expected: String,
    },
    /// A count claims more entries than the rest of the data can hold.
    #[error("{what} claims {count} entries, more than the remaining {available} bytes can hold")]
    CountTooLarge {
        /// What the count belongs to.
        what: String,
        /// The count as read.
        count: u64,
        /// How many bytes were left.
        available: usize,
    },
    /// A face with fewer than three vertices.
    #[error("face has {vertices} vertices, at least 3 are needed")]
    Degenerate {
        /// How many vertices the face has.
        vertices: u64,
    },
}

/// Reads a mesh, choosing the format from the extension (.ply, .obj, .stl, each optionally
/// followed by .gz) and checking magic bytes where the format has them.
pub fn read_mesh(path: &Path) -> Result<TriangleMesh, MeshError> {
    let name = path.display().to_string();
    // Checked before reading so that a large file of the wrong kind is not loaded for nothing.
    Format::from_name(&name).ok_or_else(|| unsupported(&name))?;
    let bytes = fs::read(path).map_err(|source| MeshError::Io {
        path: path.to_owned(),
        source,
    })?;
    parse_mesh(&name, &bytes)
}

/// Same as [`read_mesh`], from bytes already in memory; `name` is used in error messages and to
/// pick the format.
pub fn parse_mesh(name: &str, bytes: &[u8]) -> Result<TriangleMesh, MeshError> {
    let (format, gzipped) = Format::from_name(name).ok_or_else(|| unsupported(name))?;
    let data = if gzipped {
        Cow::Owned(gunzip(name, bytes)?)
    } else {
        Cow::Borrowed(bytes)
    };
    format.parse(&data).map_err(|failure| MeshError::Parse {
        path: name.to_owned(),
        location: failure.location,
        kind: failure.kind,
    })
}

fn unsupported(name: &str) -> MeshError {
    MeshError::UnsupportedFormat {
        path: name.to_owned(),
    }
}

#[derive(Debug, Clone, Copy)]
enum Format {
    Ply,
    Obj,
    Stl,
}

impl Format {
    /// The format and whether the file is gzipped, from the file name's extensions.
    fn from_name(name: &str) -> Option<(Format, bool)> {
        let lower = name.to_ascii_lowercase();
        let (stem, gzipped) = match lower.strip_suffix(".gz") {
            Some(stem) => (stem, true),
            None => (lower.as_str(), false),
        };
        let format = match Path::new(stem).extension()?.to_str()? {
            "ply" => Format::Ply,
            "obj" => Format::Obj,
            "stl" => Format::Stl,
            _ => return None,
        };
        Some((format, gzipped))
    }

    fn parse(self, bytes: &[u8]) -> ParseResult<TriangleMesh> {
        match self {
            Format::Ply => ply::parse(bytes),
            Format::Obj => obj::parse(bytes),
            Format::Stl => stl::parse(bytes),
        }
    }
}

fn gunzip(name: &str, bytes: &[u8]) -> Result<Vec<u8>, MeshError> {
    if !bytes.starts_with(&[0x1f, 0x8b]) {
        return Err(MeshError::Parse {
            path: name.to_owned(),
            location: Location::Byte(0),
            kind: ParseErrorKind::MissingHeader {
                expected: "gzip magic bytes 1f 8b",
            },
        });
    }
    // read_to_end grows the buffer as data arrives, so memory follows the real output size.
    let mut out = Vec::new();
    match MultiGzDecoder::new(bytes).read_to_end(&mut out) {
        Ok(_) => Ok(out),
        Err(source) => Err(MeshError::Gzip {
            path: name.to_owned(),
            decompressed: out.len(),
            source,
        }),
    }
}

/// A parse error before the file name is attached to it.
#[derive(Debug)]
struct Failure {
    location: Location,
    kind: ParseErrorKind,
}

type ParseResult<T> = Result<T, Failure>;

impl Failure {
    fn new(location: Location, kind: ParseErrorKind) -> Self {
        Failure { location, kind }
    }
}

/// Adapter for `map_err`: places an error at `location`.
fn at(location: Location) -> impl FnOnce(ParseErrorKind) -> Failure {
    move |kind| Failure::new(location, kind)
}

/// Quotes a token for an error message, shortened so garbage input cannot flood the message.
fn shown(token: &[u8]) -> String {
    const MAX: usize = 32;
    let text = String::from_utf8_lossy(token.get(..MAX).unwrap_or(token));
    let ellipsis = if token.len() > MAX { "..." } else { "" };
    format!("{text:?}{ellipsis}")
}

fn parse_number<T: FromStr>(token: &[u8], expected: &'static str) -> Result<T, ParseErrorKind> {
    std::str::from_utf8(token)
        .ok()
        .and_then(|text| text.parse().ok())
        .ok_or_else(|| ParseErrorKind::BadNumber {
            token: shown(token),
            expected,
        })
}

/// Narrows a coordinate to `f32`, rejecting values that are or become non-finite.
fn coordinate(value: f64) -> Result<f32, ParseErrorKind> {
    let narrowed = value as f32;
    if narrowed.is_finite() {
        Ok(narrowed)
    } else {
        Err(ParseErrorKind::NonFinite { value })
    }
}

/// Whitespace-separated words of one line.
fn words(line: &[u8]) -> impl Iterator<Item = &[u8]> {
    line.split(u8::is_ascii_whitespace)
        .filter(|word| !word.is_empty())
}

/// Whitespace-separated tokens across lines, remembering the line of the latest token.
struct Tokens<'a> {
    bytes: &'a [u8],
    pos: usize,
    line: usize,
}

impl<'a> Tokens<'a> {
    /// Starts at byte `pos`, which is on line `line` (1-based).
    fn new(bytes: &'a [u8], pos: usize, line: usize) -> Self {
        Tokens { bytes, pos, line }
    }

    /// The next token, or `None` at the end of the data.
    fn next_token(&mut self) -> Option<&'a [u8]> {
        let mut newlines = 0;
        while let Some(&byte) = self.bytes.get(self.pos) {
            if !byte.is_ascii_whitespace() {
                break;
            }
            newlines += usize::from(byte == b'\n');
            self.pos += 1;
        }
        let rest = self.bytes.get(self.pos..)?;
        let len = rest
            .iter()
            .position(u8::is_ascii_whitespace)
            .unwrap_or(rest.len());
        let token = rest.get(..len).filter(|token| !token.is_empty())?;
        // Counted only when a token follows, so that an error at the end of the data points
        // at the last line that has something on it.
        self.line += newlines;
        self.pos += len;
        Some(token)
    }

    /// Skips the rest of the current line, e.g. a free-form name.
    fn skip_line(&mut self) {
        let rest = self.bytes.get(self.pos..).unwrap_or_default();
        // Stops on the newline itself so that next_token counts it.
        self.pos += rest.iter().position(|&b| b == b'\n').unwrap_or(rest.len());
    }

    /// The line of the latest token.
    fn line(&self) -> usize {
        self.line
    }

    fn remaining(&self) -> usize {
        self.bytes.len().saturating_sub(self.pos)
    }
}

/// Fan-triangulates a polygon whose vertex indices arrive one at a time.
#[derive(Default)]
struct Fan {
    first: u32,
    previous: u32,
    len: u64,
}

impl Fan {
    fn push(&mut self, index: u32, triangles: &mut Vec<[u32; 3]>) {
        match self.len {
            0 => self.first = index,
            1 => {}
            _ => triangles.push([self.first, self.previous, index]),
        }
        self.previous = index;
        self.len += 1;
    }

    /// Fails for polygons that produced no triangle.
    fn finish(self) -> Result<(), ParseErrorKind> {
        if self.len < 3 {
            return Err(ParseErrorKind::Degenerate { vertices: self.len });
        }
        Ok(())
    }
}

/// Writers refuse meshes that their readers would reject, so every written file reads back.
fn check_writable(mesh: &TriangleMesh) -> io::Result<()> {
    if let Some(value) = mesh.positions.iter().flatten().find(|c| !c.is_finite()) {
        return Err(invalid_input(format!(
            "non-finite vertex coordinate {value}"
        )));
    }
    let count = mesh.positions.len();
    for (n, triangle) in mesh.triangles.iter().enumerate() {
        if let Some(index) = triangle.iter().find(|&&i| i as usize >= count) {
            return Err(invalid_input(format!(
                "triangle {n} refers to vertex {index} but the mesh has {count} vertices"
            )));
        }
    }
    Ok(())
}

fn invalid_input(message: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidInput, message)
}

/// The corner positions of a triangle of a mesh that passed [`check_writable`].
fn corners(mesh: &TriangleMesh, triangle: &[u32; 3]) -> [[f32; 3]; 3] {
    triangle.map(|i| mesh.positions[i as usize])
}

#[cfg(test)]
mod tests {
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
        let ascii =
            RICH_PLY_HEADER.replace("ply\n", "ply\nformat ascii 1.0\n") + RICH_PLY_ASCII_BODY;
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
        let encoding =
            prop::sample::select(vec!["ascii", "binary_little_endian", "binary_big_endian"]);
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
}
