//! The PLY body: a plan of what each property of an element is for (a coordinate, a face's
//! indices, or skipped), and the records read by it from ASCII or binary bytes, every count
//! checked against the bytes left before it drives a loop or an allocation.

use super::super::{
    Failure, Fan, Location, ParseErrorKind, ParseResult, Tokens, TriangleMesh, at, coordinate,
    shown,
};
use super::header::{Element, PropertyType, Scalar, header_error};

/// What the reader does with an element.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Role {
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

pub(super) struct Plan {
    pub(super) role: Role,
    fields: Vec<Field>,
}

/// Decides how each property of an element is read.
pub(super) fn plan(element: &Element) -> ParseResult<Plan> {
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
pub(super) fn check_single(elements: &[Element], plans: &[Plan], role: Role) -> ParseResult<()> {
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
pub(super) trait Body {
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

pub(super) struct AsciiBody<'a> {
    pub(super) tokens: Tokens<'a>,
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

pub(super) struct BinaryBody<'a> {
    pub(super) bytes: &'a [u8],
    pub(super) pos: usize,
    /// Offset of the latest value, for errors about it.
    pub(super) last: usize,
    pub(super) big_endian: bool,
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
pub(super) struct BodyReader<'h> {
    pub(super) elements: &'h [Element],
    pub(super) plans: &'h [Plan],
    pub(super) vertex_count: u64,
}

impl BodyReader<'_> {
    pub(super) fn read(&self, body: &mut impl Body) -> ParseResult<TriangleMesh> {
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
