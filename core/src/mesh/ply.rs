//! PLY reader (ASCII, binary little- and big-endian) and writers.
//!
//! Hand-written rather than ply-rs: ply-rs 0.1.3 (no release since 2020) panicked in a quick
//! proptest on a header whose element count overflows `usize` (its grammar calls
//! `parse().unwrap()`), and its binary errors carry no byte offset. The subset needed here is
//! small: x/y/z of the vertex element and the index list of the face element, while every other
//! property and element is read only to be skipped.

use std::io::{self, BufWriter, Write};

use super::{
    Failure, Fan, Location, ParseErrorKind, ParseResult, Tokens, TriangleMesh, at, check_writable,
    coordinate, parse_number, shown, words,
};

/// A PLY scalar type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scalar {
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

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    /// Used in "expected ..." messages.
    fn description(self) -> &'static str {
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
    fn integer_range(self) -> Option<(i64, i64)> {
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
    fn decode(self, raw: &[u8], big_endian: bool) -> f64 {
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
    fn parse(self, token: &[u8]) -> Result<f64, ParseErrorKind> {
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
enum PropertyType {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

#[derive(Debug)]
struct Property {
    name: Vec<u8>,
    ty: PropertyType,
}

#[derive(Debug)]
struct Element {
    name: Vec<u8>,
    count: u64,
    properties: Vec<Property>,
    /// Header line of the declaration, for errors about the element as a whole.
    line: usize,
}

impl Element {
    /// The fewest bytes one binary record can take (lists may be empty).
    fn min_binary_len(&self) -> u64 {
        let len = |p: &Property| match p.ty {
            PropertyType::Scalar(s) | PropertyType::List { count: s, .. } => s.size() as u64,
        };
        self.properties.iter().map(len).sum()
    }
}

#[derive(Debug, Clone, Copy)]
enum Encoding {
    Ascii,
    Binary { big_endian: bool },
}

struct Header {
    encoding: Encoding,
    elements: Vec<Element>,
    /// Byte offset and line number where the body starts.
    body_offset: usize,
    body_line: usize,
}

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

fn parse_header(bytes: &[u8]) -> ParseResult<Header> {
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

fn header_error(message: String) -> ParseErrorKind {
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

/// What the reader does with an element.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Role {
    Vertex,
    Face,
    Other,
}

/// What the reader does with one property of a record.
#[derive(Debug, Clone, Copy)]
enum Field {
    Coordinate { axis: usize, ty: Scalar },
    Indices { count: Scalar, item: Scalar },
    Skip(PropertyType),
}

struct Plan {
    role: Role,
    fields: Vec<Field>,
}

/// Decides how each property of an element is read.
fn plan(element: &Element) -> ParseResult<Plan> {
    let role = match &element.name[..] {
        b"vertex" => Role::Vertex,
        b"face" => Role::Face,
        _ => Role::Other,
    };
    let mut fields: Vec<Field> = element
        .properties
        .iter()
        .map(|p| Field::Skip(p.ty))
        .collect();
    match role {
        Role::Vertex => {
            for (axis, name) in [b"x", b"y", b"z"].into_iter().enumerate() {
                let field = |ty| match ty {
                    PropertyType::Scalar(ty) => Some(Field::Coordinate { axis, ty }),
                    PropertyType::List { .. } => None,
                };
                assign(element, &mut fields, &[name], "scalar", field)?;
            }
        }
        Role::Face => {
            let field = |ty| match ty {
                PropertyType::List { count, item } => Some(Field::Indices { count, item }),
                PropertyType::Scalar(_) => None,
            };
            let names: [&[u8]; 2] = [b"vertex_indices", b"vertex_index"];
            assign(element, &mut fields, &names, "list", field)?;
        }
        Role::Other => {}
    }
    Ok(Plan { role, fields })
}

/// Sets the field of the first property that is named one of `names` and whose type `field`
/// accepts; fails, naming the wanted `kind` of property, if there is none.
fn assign(
    element: &Element,
    fields: &mut [Field],
    names: &[&[u8]],
    kind: &str,
    field: impl Fn(PropertyType) -> Option<Field>,
) -> ParseResult<()> {
    for (property, slot) in element.properties.iter().zip(fields) {
        if names.contains(&&property.name[..])
            && let Some(made) = field(property.ty)
        {
            *slot = made;
            return Ok(());
        }
    }
    let message = format!(
        "element {} has no {kind} property {}",
        shown(&element.name),
        shown(names.first().copied().unwrap_or_default())
    );
    Err(Failure::new(
        Location::Line(element.line),
        header_error(message),
    ))
}

/// Face indices need one meaning of "vertex", so a second vertex or face element is refused.
fn check_single(elements: &[Element], plans: &[Plan], role: Role) -> ParseResult<()> {
    let mut matching = elements
        .iter()
        .zip(plans)
        .filter(|(_, plan)| plan.role == role);
    matching.next();
    match matching.next() {
        Some((element, _)) => {
            let message = format!("duplicate element {}", shown(&element.name));
            Err(Failure::new(
                Location::Line(element.line),
                header_error(message),
            ))
        }
        None => Ok(()),
    }
}

/// Reads values from the body of a PLY file, whatever its encoding.
trait Body {
    /// Reads one scalar of type `ty`.
    fn scalar(&mut self, ty: Scalar) -> ParseResult<f64>;
    /// Where the latest value was read.
    fn location(&self) -> Location;
    /// Fails if the rest of the body cannot hold `element.count` records, so that no loop
    /// or allocation is driven by a count the data does not back.
    fn check_count(&self, element: &Element) -> ParseResult<()>;
    /// Fails if the rest of the body cannot hold `len` values of type `item` for the list
    /// property `name`.
    fn check_list(&self, name: &[u8], len: u64, item: Scalar) -> ParseResult<()>;

    /// Skips a list of `len` values of type `item` (after `check_list`).
    fn skip_list(&mut self, len: u64, item: Scalar) -> ParseResult<()> {
        for _ in 0..len {
            self.scalar(item)?;
        }
        Ok(())
    }

    /// Reads a list length, which must be a non-negative integer.
    fn list_len(&mut self, ty: Scalar) -> ParseResult<u64> {
        let value = self.scalar(ty)?;
        if value.fract() == 0.0 && value >= 0.0 {
            // `as` saturates for a huge double, which the length checks then reject.
            Ok(value as u64)
        } else {
            let message = format!("list length {value} is not a non-negative integer");
            Err(Failure::new(
                self.location(),
                ParseErrorKind::Syntax(message),
            ))
        }
    }
}

fn too_large(what: &[u8], count: u64, available: usize, location: Location) -> Failure {
    let what = String::from_utf8_lossy(what).into_owned();
    let kind = ParseErrorKind::CountTooLarge {
        what,
        count,
        available,
    };
    Failure::new(location, kind)
}

struct AsciiBody<'a> {
    tokens: Tokens<'a>,
}

impl Body for AsciiBody<'_> {
    fn scalar(&mut self, ty: Scalar) -> ParseResult<f64> {
        let token = self.tokens.next_token().ok_or_else(|| {
            let expected = ty.description().to_owned();
            Failure::new(self.location(), ParseErrorKind::Truncated { expected })
        })?;
        ty.parse(token).map_err(at(self.location()))
    }

    fn location(&self) -> Location {
        Location::Line(self.tokens.line())
    }

    fn check_count(&self, element: &Element) -> ParseResult<()> {
        // Each property takes at least one token, and n tokens at least 2n - 1 bytes.
        let available = self.tokens.remaining();
        let tokens = element.count.checked_mul(element.properties.len() as u64);
        match tokens {
            Some(tokens) if tokens <= (available as u64).div_ceil(2) => Ok(()),
            _ => Err(too_large(
                &element.name,
                element.count,
                available,
                self.location(),
            )),
        }
    }

    fn check_list(&self, _name: &[u8], _len: u64, _item: Scalar) -> ParseResult<()> {
        // Tokens are read one at a time and nothing is allocated from the length.
        Ok(())
    }
}

struct BinaryBody<'a> {
    bytes: &'a [u8],
    pos: usize,
    /// Offset of the latest value, for errors about it.
    last: usize,
    big_endian: bool,
}

impl BinaryBody<'_> {
    fn remaining(&self) -> usize {
        self.bytes.len().saturating_sub(self.pos)
    }
}

impl Body for BinaryBody<'_> {
    fn scalar(&mut self, ty: Scalar) -> ParseResult<f64> {
        let raw = self
            .bytes
            .get(self.pos..)
            .and_then(|rest| rest.get(..ty.size()));
        let raw = raw.ok_or_else(|| {
            let expected = ty.description().to_owned();
            Failure::new(
                Location::Byte(self.pos),
                ParseErrorKind::Truncated { expected },
            )
        })?;
        self.last = self.pos;
        self.pos += ty.size();
        Ok(ty.decode(raw, self.big_endian))
    }

    fn location(&self) -> Location {
        Location::Byte(self.last)
    }

    fn check_count(&self, element: &Element) -> ParseResult<()> {
        let available = self.remaining();
        match element.count.checked_mul(element.min_binary_len()) {
            Some(needed) if needed <= available as u64 => Ok(()),
            _ => Err(too_large(
                &element.name,
                element.count,
                available,
                Location::Byte(self.pos),
            )),
        }
    }

    fn check_list(&self, name: &[u8], len: u64, item: Scalar) -> ParseResult<()> {
        let available = self.remaining();
        match len.checked_mul(item.size() as u64) {
            Some(needed) if needed <= available as u64 => Ok(()),
            _ => Err(too_large(name, len, available, self.location())),
        }
    }

    fn skip_list(&mut self, len: u64, item: Scalar) -> ParseResult<()> {
        // check_list has bounded len * size by the remaining length.
        self.pos += len as usize * item.size();
        Ok(())
    }
}

/// Reads all elements of the body into a mesh.
struct BodyReader<'h> {
    elements: &'h [Element],
    plans: &'h [Plan],
    vertex_count: u64,
}

impl BodyReader<'_> {
    fn read(&self, body: &mut impl Body) -> ParseResult<TriangleMesh> {
        let mut mesh = TriangleMesh::default();
        for (element, plan) in self.elements.iter().zip(self.plans) {
            // Records without properties take no bytes; looping over their count could take
            // forever and would read nothing.
            if element.properties.is_empty() {
                continue;
            }
            body.check_count(element)?;
            if plan.role == Role::Vertex {
                // Bounded: check_count tied the count to the remaining input.
                mesh.positions.reserve(element.count as usize);
            }
            for _ in 0..element.count {
                self.read_record(body, element, plan, &mut mesh)?;
            }
        }
        Ok(mesh)
    }

    fn read_record(
        &self,
        body: &mut impl Body,
        element: &Element,
        plan: &Plan,
        mesh: &mut TriangleMesh,
    ) -> ParseResult<()> {
        let mut position = [0.0; 3];
        for (field, property) in plan.fields.iter().zip(&element.properties) {
            let name = &property.name[..];
            match *field {
                Field::Coordinate { axis, ty } => {
                    let value = body.scalar(ty)?;
                    position[axis] = coordinate(value).map_err(at(body.location()))?;
                }
                Field::Indices { count, item } => {
                    self.read_polygon(body, name, (count, item), &mut mesh.triangles)?;
                }
                Field::Skip(PropertyType::Scalar(ty)) => {
                    body.scalar(ty)?;
                }
                Field::Skip(PropertyType::List { count, item }) => {
                    let len = body.list_len(count)?;
                    body.check_list(name, len, item)?;
                    body.skip_list(len, item)?;
                }
            }
        }
        if plan.role == Role::Vertex {
            mesh.positions.push(position);
        }
        Ok(())
    }

    fn read_polygon(
        &self,
        body: &mut impl Body,
        name: &[u8],
        (count, item): (Scalar, Scalar),
        triangles: &mut Vec<[u32; 3]>,
    ) -> ParseResult<()> {
        let len = body.list_len(count)?;
        if len < 3 {
            return Err(Failure::new(
                body.location(),
                ParseErrorKind::Degenerate { vertices: len },
            ));
        }
        body.check_list(name, len, item)?;
        let mut fan = Fan::default();
        for _ in 0..len {
            let value = body.scalar(item)?;
            let index = self.vertex_index(value).map_err(at(body.location()))?;
            fan.push(index, triangles);
        }
        Ok(())
    }

    fn vertex_index(&self, value: f64) -> Result<u32, ParseErrorKind> {
        if value.fract() != 0.0 {
            let message = format!("vertex index {value} is not an integer");
            return Err(ParseErrorKind::Syntax(message));
        }
        if value < 0.0 || value >= self.vertex_count as f64 || value > f64::from(u32::MAX) {
            return Err(ParseErrorKind::IndexOutOfRange {
                index: value as i64,
                vertex_count: self.vertex_count,
            });
        }
        Ok(value as u32)
    }
}

/// Writes `mesh` as ASCII PLY, with coordinates in shortest round-trip form.
pub fn write_ply_ascii(mesh: &TriangleMesh, w: impl Write) -> io::Result<()> {
    check_writable(mesh)?;
    let mut w = BufWriter::new(w);
    write_header(&mut w, mesh, "ascii")?;
    for [x, y, z] in &mesh.positions {
        writeln!(w, "{x:?} {y:?} {z:?}")?;
    }
    for [a, b, c] in &mesh.triangles {
        writeln!(w, "3 {a} {b} {c}")?;
    }
    w.flush()
}

/// Writes `mesh` as binary little-endian PLY.
pub fn write_ply_binary(mesh: &TriangleMesh, w: impl Write) -> io::Result<()> {
    check_writable(mesh)?;
    let mut w = BufWriter::new(w);
    write_header(&mut w, mesh, "binary_little_endian")?;
    for position in &mesh.positions {
        for coordinate in position {
            w.write_all(&coordinate.to_le_bytes())?;
        }
    }
    for triangle in &mesh.triangles {
        w.write_all(&[3])?;
        for index in triangle {
            w.write_all(&index.to_le_bytes())?;
        }
    }
    w.flush()
}

fn write_header(w: &mut impl Write, mesh: &TriangleMesh, format: &str) -> io::Result<()> {
    writeln!(w, "ply\nformat {format} 1.0")?;
    writeln!(w, "element vertex {}", mesh.positions.len())?;
    writeln!(w, "property float x\nproperty float y\nproperty float z")?;
    writeln!(w, "element face {}", mesh.triangles.len())?;
    writeln!(w, "property list uchar uint vertex_indices\nend_header")
}

#[cfg(test)]
mod tests;
