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
mod tests;
