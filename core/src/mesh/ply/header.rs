//! The PLY header: its scalar types, elements and properties, parsed line by line with
//! errors naming the line.

use super::super::{
    Failure, Location, ParseErrorKind, ParseResult, at, parse_number, shown, words,
};

/// A PLY scalar type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn from_name(name: &[u8]) -> Option<Self> {
        Some(match name {
            b"char" | b"int8" => Scalar::I8,
            b"uchar" | b"uint8" => Scalar::U8,
            b"short" | b"int16" => Scalar::I16,
            b"ushort" | b"uint16" => Scalar::U16,
            b"int" | b"int32" => Scalar::I32,
            b"uint" | b"uint32" => Scalar::U32,
            b"float" | b"float32" => Scalar::F32,
            b"double" | b"float64" => Scalar::F64,
            _ => return None,
        })
    }

    pub(super) fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    /// Used in "expected ..." messages.
    pub(super) fn description(self) -> &'static str {
        match self {
            Scalar::I8 => "a char",
            Scalar::U8 => "a uchar",
            Scalar::I16 => "a short",
            Scalar::U16 => "a ushort",
            Scalar::I32 => "an int",
            Scalar::U32 => "a uint",
            Scalar::F32 => "a float",
            Scalar::F64 => "a double",
        }
    }

    /// The value range of an integer type, `None` for floating-point types.
    pub(super) fn integer_range(self) -> Option<(i64, i64)> {
        Some(match self {
            Scalar::I8 => (i8::MIN.into(), i8::MAX.into()),
            Scalar::U8 => (0, u8::MAX.into()),
            Scalar::I16 => (i16::MIN.into(), i16::MAX.into()),
            Scalar::U16 => (0, u16::MAX.into()),
            Scalar::I32 => (i32::MIN.into(), i32::MAX.into()),
            Scalar::U32 => (0, u32::MAX.into()),
            Scalar::F32 | Scalar::F64 => return None,
        })
    }

    /// Decodes a value from exactly `self.size()` bytes. Every PLY scalar fits an `f64` exactly.
    pub(super) fn decode(self, raw: &[u8], big_endian: bool) -> f64 {
        let mut le = [0u8; 8];
        for (slot, &byte) in le.iter_mut().zip(raw) {
            *slot = byte;
        }
        if big_endian {
            le[..raw.len().min(8)].reverse();
        }
        let [b0, b1, b2, b3, ..] = le;
        match self {
            Scalar::I8 => i8::from_le_bytes([b0]).into(),
            Scalar::U8 => b0.into(),
            Scalar::I16 => i16::from_le_bytes([b0, b1]).into(),
            Scalar::U16 => u16::from_le_bytes([b0, b1]).into(),
            Scalar::I32 => i32::from_le_bytes([b0, b1, b2, b3]).into(),
            Scalar::U32 => u32::from_le_bytes([b0, b1, b2, b3]).into(),
            Scalar::F32 => f32::from_le_bytes([b0, b1, b2, b3]).into(),
            Scalar::F64 => f64::from_le_bytes(le),
        }
    }

    /// Parses an ASCII token as this type, checking integer ranges.
    pub(super) fn parse(self, token: &[u8]) -> Result<f64, ParseErrorKind> {
        let expected = self.description();
        match self.integer_range() {
            Some((min, max)) => {
                let value: i64 = parse_number(token, expected)?;
                if (min..=max).contains(&value) {
                    // Integers of at most 32 bits are exact in f64.
                    Ok(value as f64)
                } else {
                    Err(ParseErrorKind::BadNumber {
                        token: shown(token),
                        expected,
                    })
                }
            }
            // Parsed at the declared precision: going through f64 for a float property
            // could round twice and break exact round trips.
            None if self == Scalar::F32 => parse_number::<f32>(token, expected).map(f64::from),
            None => parse_number(token, expected),
        }
    }
}

#[derive(Debug, Clone, Copy)]
pub(super) enum PropertyType {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

#[derive(Debug)]
pub(super) struct Property {
    pub(super) name: Vec<u8>,
    pub(super) ty: PropertyType,
}

#[derive(Debug)]
pub(super) struct Element {
    pub(super) name: Vec<u8>,
    pub(super) count: u64,
    pub(super) properties: Vec<Property>,
    /// Header line of the declaration, for errors about the element as a whole.
    pub(super) line: usize,
}

impl Element {
    /// The fewest bytes one binary record can take (lists may be empty).
    pub(super) fn min_binary_len(&self) -> u64 {
        let len = |p: &Property| match p.ty {
            PropertyType::Scalar(s) | PropertyType::List { count: s, .. } => s.size() as u64,
        };
        self.properties.iter().map(len).sum()
    }
}

#[derive(Debug, Clone, Copy)]
pub(super) enum Encoding {
    Ascii,
    Binary { big_endian: bool },
}

pub(super) struct Header {
    pub(super) encoding: Encoding,
    pub(super) elements: Vec<Element>,
    /// Byte offset and line number where the body starts.
    pub(super) body_offset: usize,
    pub(super) body_line: usize,
}

/// Splits the header into lines, tracking where the body starts.
struct Lines<'a> {
    bytes: &'a [u8],
    pos: usize,
    number: usize,
}

impl<'a> Lines<'a> {
    /// The next line without its line ending, or `None` if no complete line is left.
    fn next_line(&mut self) -> Option<&'a [u8]> {
        let rest = self.bytes.get(self.pos..)?;
        let end = rest.iter().position(|&b| b == b'\n')?;
        self.pos += end + 1;
        self.number += 1;
        let line = rest.get(..end)?;
        Some(line.strip_suffix(b"\r").unwrap_or(line))
    }
}

pub(super) fn parse_header(bytes: &[u8]) -> ParseResult<Header> {
    let mut lines = Lines {
        bytes,
        pos: 0,
        number: 0,
    };
    if lines.next_line() != Some(b"ply") {
        return Err(Failure::new(
            Location::Line(1),
            ParseErrorKind::MissingHeader {
                expected: "a first line \"ply\"",
            },
        ));
    }
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        let Some(line) = lines.next_line() else {
            let kind = ParseErrorKind::Truncated {
                expected: "\"end_header\"".to_owned(),
            };
            return Err(Failure::new(Location::Line(lines.number + 1), kind));
        };
        let here = Location::Line(lines.number);
        let mut words = words(line);
        match words.next() {
            Some(b"end_header") => break,
            Some(b"format") => encoding = Some(parse_format(words).map_err(at(here))?),
            Some(b"element") => {
                elements.push(parse_element(words, lines.number).map_err(at(here))?)
            }
            Some(b"property") => {
                let element = elements.last_mut().ok_or_else(|| {
                    Failure::new(here, header_error("property before any element".to_owned()))
                })?;
                element
                    .properties
                    .push(parse_property(words).map_err(at(here))?);
            }
            Some(b"comment" | b"obj_info") | None => {}
            Some(other) => {
                let message = format!("unknown keyword {}", shown(other));
                return Err(Failure::new(here, header_error(message)));
            }
        }
    }
    let encoding = encoding.ok_or_else(|| {
        let kind = header_error("no \"format\" line".to_owned());
        Failure::new(Location::Line(lines.number), kind)
    })?;
    Ok(Header {
        encoding,
        elements,
        body_offset: lines.pos,
        body_line: lines.number + 1,
    })
}

pub(super) fn header_error(message: String) -> ParseErrorKind {
    ParseErrorKind::Header(message)
}

/// Takes exactly `N` words, or `None` if there are fewer or more.
fn exactly<'a, const N: usize>(mut words: impl Iterator<Item = &'a [u8]>) -> Option<[&'a [u8]; N]> {
    let mut out = [&[][..]; N];
    for slot in &mut out {
        *slot = words.next()?;
    }
    words.next().is_none().then_some(out)
}

fn parse_format<'a>(words: impl Iterator<Item = &'a [u8]>) -> Result<Encoding, ParseErrorKind> {
    let [name, _version] = exactly(words)
        .ok_or_else(|| header_error("expected \"format <encoding> <version>\"".to_owned()))?;
    match name {
        b"ascii" => Ok(Encoding::Ascii),
        b"binary_little_endian" => Ok(Encoding::Binary { big_endian: false }),
        b"binary_big_endian" => Ok(Encoding::Binary { big_endian: true }),
        other => Err(header_error(format!("unknown format {}", shown(other)))),
    }
}

fn parse_element<'a>(
    words: impl Iterator<Item = &'a [u8]>,
    line: usize,
) -> Result<Element, ParseErrorKind> {
    let [name, count] = exactly(words)
        .ok_or_else(|| header_error("expected \"element <name> <count>\"".to_owned()))?;
    Ok(Element {
        name: name.to_vec(),
        count: parse_number(count, "an element count")?,
        properties: Vec::new(),
        line,
    })
}

fn parse_property<'a>(words: impl Iterator<Item = &'a [u8]>) -> Result<Property, ParseErrorKind> {
    let words: Vec<&[u8]> = words.take(5).collect();
    let (ty, name) = match words[..] {
        [ty, name] => (PropertyType::Scalar(scalar(ty)?), name),
        [b"list", count, item, name] => {
            let (count, item) = (scalar(count)?, scalar(item)?);
            (PropertyType::List { count, item }, name)
        }
        _ => {
            let message = "expected \"property <type> <name>\" or \
                           \"property list <count type> <item type> <name>\"";
            return Err(header_error(message.to_owned()));
        }
    };
    Ok(Property {
        name: name.to_vec(),
        ty,
    })
}

fn scalar(name: &[u8]) -> Result<Scalar, ParseErrorKind> {
    Scalar::from_name(name)
        .ok_or_else(|| header_error(format!("unknown property type {}", shown(name))))
}
