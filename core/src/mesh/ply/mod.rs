//! PLY reader (ASCII, binary little- and big-endian) and writers.
//!
//! Hand-written rather than ply-rs: ply-rs 0.1.3 (no release since 2020) panicked in a quick
//! proptest on a header whose element count overflows `usize` (its grammar calls
//! `parse().unwrap()`), and its binary errors carry no byte offset. The subset needed here is
//! small: x/y/z of the vertex element and the index list of the face element, while every other
//! property and element is read only to be skipped.
//!
//! Three ideas, a module each: what the header declares (`header`), reading the body's records
//! by a plan of what each property is for (`body`), and the writers (`write`).

mod body;
mod header;
mod write;

use super::{ParseResult, Tokens, TriangleMesh};
use body::{AsciiBody, BinaryBody, BodyReader, Role, check_single, plan};
use header::{Encoding, parse_header};
pub use write::{write_ply_ascii, write_ply_binary};

/// Reads a PLY file.
pub(super) fn parse(bytes: &[u8]) -> ParseResult<TriangleMesh> {
    let header = parse_header(bytes)?;
    let plans = header
        .elements
        .iter()
        .map(plan)
        .collect::<ParseResult<Vec<_>>>()?;
    check_single(&header.elements, &plans, Role::Vertex)?;
    check_single(&header.elements, &plans, Role::Face)?;
    let vertex_count = header
        .elements
        .iter()
        .zip(&plans)
        .find(|(_, plan)| plan.role == Role::Vertex)
        .map_or(0, |(element, _)| element.count);
    let reader = BodyReader {
        elements: &header.elements,
        plans: &plans,
        vertex_count,
    };
    match header.encoding {
        Encoding::Ascii => reader.read(&mut AsciiBody {
            tokens: Tokens::new(bytes, header.body_offset, header.body_line),
        }),
        Encoding::Binary { big_endian } => reader.read(&mut BinaryBody {
            bytes,
            pos: header.body_offset,
            last: header.body_offset,
            big_endian,
        }),
    }
}

#[cfg(test)]
mod tests;
