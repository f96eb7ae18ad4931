//! Marching cubes' case tables, derived at compile time by `const fn`s from one rule applied
//! face by face (so neighbouring cells agree on ambiguous faces), not typed in.

use super::MAX_TRIANGLES_PER_CELL;

/// Edge `e` joins corners `EDGE_CORNERS[e] = (lower, upper)`.
pub(super) const EDGE_CORNERS: [(u8, u8); 12] = build_edge_corners();

/// Triangulation of one corner configuration (bit `c` set = corner `c` inside).
#[derive(Clone, Copy)]
pub(super) struct Case {
    /// Bit `e` set when edge `e` is crossed by the surface.
    pub(super) edge_mask: u16,
    pub(super) count: u8,
    /// Triangles as triples of edge indices, wound toward the outside.
    pub(super) tris: [[u8; 3]; MAX_TRIANGLES_PER_CELL],
}

pub(super) static CASES: [Case; 256] = build_cases();

/// Edge numbering: 4 edges per axis; along `axis`, the edge's lower corner's
/// other two coordinate bits select which of the 4.
const fn edge_index(lower: usize, axis: usize) -> usize {
    let u = (axis + 1) % 3;
    let v = (axis + 2) % 3;
    axis * 4 + ((lower >> u) & 1) + 2 * ((lower >> v) & 1)
}

const fn build_edge_corners() -> [(u8, u8); 12] {
    let mut out = [(0u8, 0u8); 12];
    let mut c = 0;
    while c < 8 {
        let mut axis = 0;
        while axis < 3 {
            if (c >> axis) & 1 == 0 {
                out[edge_index(c, axis)] = (c as u8, (c | (1 << axis)) as u8);
            }
            axis += 1;
        }
        c += 1;
    }
    out
}

/// The edge joining two corners that differ in exactly one coordinate.
const fn edge_between(a: usize, b: usize) -> usize {
    let axis = (a ^ b).trailing_zeros() as usize;
    let lower = if a < b { a } else { b };
    edge_index(lower, axis)
}

const fn face_corner(axis: usize, side: usize, du: usize, dv: usize) -> usize {
    (side << axis) | (du << ((axis + 1) % 3)) | (dv << ((axis + 2) % 3))
}

/// The four corners of a face in counter-clockwise order seen from outside
/// the cell (right-hand rule about the outward normal).
const fn face_corners(axis: usize, side: usize) -> [usize; 4] {
    let c = [
        face_corner(axis, side, 0, 0),
        face_corner(axis, side, 1, 0),
        face_corner(axis, side, 1, 1),
        face_corner(axis, side, 0, 1),
    ];
    // (u, v, axis) is right-handed, so that order is CCW about +axis; the
    // low face's outward normal is -axis, so walk it the other way.
    if side == 1 {
        c
    } else {
        [c[0], c[3], c[2], c[1]]
    }
}

const fn is_inside(config: usize, corner: usize) -> bool {
    (config >> corner) & 1 == 1
}

/// True when walking from corner `from` to `to` leaves the inside.
const fn crosses_out(config: usize, from: usize, to: usize) -> bool {
    is_inside(config, from) && !is_inside(config, to)
}

/// For each crossed edge, the next crossed edge along the surface's boundary
/// loops on the cell faces (`NONE` for uncrossed edges).
///
/// Walking each face's boundary counter-clockwise from outside, a segment runs
/// from an edge entering the inside to the next edge leaving it. On a face
/// with two diagonal inside corners this cuts each inside corner off on its
/// own: the rule looks only at that face's four signs, so both cells sharing
/// the face choose the same segments (in opposite directions, as their
/// outward normals are opposite), which keeps the surface closed.
const fn face_successors(config: usize) -> [usize; 12] {
    let mut next = [NONE; 12];
    let mut f = 0;
    while f < 6 {
        let q = face_corners(f / 2, f % 2);
        let mut i = 0;
        while i < 4 {
            let (a, b) = (q[i], q[(i + 1) % 4]);
            if crosses_out(config, b, a) {
                let mut j = (i + 1) % 4;
                while !crosses_out(config, q[j], q[(j + 1) % 4]) {
                    j = (j + 1) % 4;
                }
                let entry = edge_between(a, b);
                assert!(next[entry] == NONE, "edge entered twice");
                next[entry] = edge_between(q[j], q[(j + 1) % 4]);
            }
            i += 1;
        }
        f += 1;
    }
    next
}

const NONE: usize = usize::MAX;

const fn edge_mask(config: usize) -> u16 {
    let mut mask = 0u16;
    let mut e = 0;
    while e < 12 {
        let (a, b) = EDGE_CORNERS[e];
        if is_inside(config, a as usize) != is_inside(config, b as usize) {
            mask |= 1 << e;
        }
        e += 1;
    }
    mask
}

/// Triangulates one configuration: follows each boundary loop and fans it.
/// A loop's order makes the fan's normals point away from the inside corners
/// it encloses.
const fn build_case(config: usize) -> Case {
    let next = face_successors(config);
    let mask = edge_mask(config);
    let mut case = Case {
        edge_mask: mask,
        count: 0,
        tris: [[0; 3]; MAX_TRIANGLES_PER_CELL],
    };
    let mut visited = 0u16;
    let mut start = 0;
    while start < 12 {
        if mask & (1 << start) != 0 && visited & (1 << start) == 0 {
            let (ring, len) = follow_loop(&next, start);
            let mut i = 0;
            while i < len {
                visited |= 1 << ring[i];
                i += 1;
            }
            fan(&mut case, &ring, len);
        }
        start += 1;
    }
    assert!(visited == mask, "a crossed edge is on no loop");
    case
}

/// The crossed edges of the loop through `start`, in order.
const fn follow_loop(next: &[usize; 12], start: usize) -> ([usize; 12], usize) {
    let mut ring = [0; 12];
    let mut len = 0;
    let mut cur = start;
    loop {
        assert!(cur != NONE, "crossed edge without successor");
        assert!(len < 12, "loop does not close");
        ring[len] = cur;
        len += 1;
        cur = next[cur];
        if cur == start {
            return (ring, len);
        }
    }
}

/// Appends a fan triangulation of the loop. The apex is the first loop
/// position whose fan has no triangle lying flat in a cell face: such a
/// triangle (possible when one loop crosses an ambiguous face twice) would be
/// coplanar with the neighbour cell's surface and shade badly.
const fn fan(case: &mut Case, ring: &[usize; 12], len: usize) {
    assert!(len >= 3, "loop shorter than a triangle");
    let mut apex = 0;
    while apex < len && fan_has_flat_triangle(ring, len, apex) {
        apex += 1;
    }
    if apex == len {
        apex = 0;
    }
    let mut i = 1;
    while i + 1 < len {
        let n = case.count as usize;
        assert!(n < MAX_TRIANGLES_PER_CELL, "too many triangles in one cell");
        case.tris[n] = [
            ring[apex] as u8,
            ring[(apex + i) % len] as u8,
            ring[(apex + i + 1) % len] as u8,
        ];
        case.count += 1;
        i += 1;
    }
}

const fn fan_has_flat_triangle(ring: &[usize; 12], len: usize, apex: usize) -> bool {
    let mut i = 1;
    while i + 1 < len {
        let tri = [
            ring[apex],
            ring[(apex + i) % len],
            ring[(apex + i + 1) % len],
        ];
        if lies_in_a_face(tri) {
            return true;
        }
        i += 1;
    }
    false
}

/// True when all three edges border one common cell face.
pub(super) const fn lies_in_a_face(tri: [usize; 3]) -> bool {
    let mut face = 0;
    while face < 6 {
        let (axis, side) = (face / 2, (face % 2) as u8);
        let mut all = true;
        let mut v = 0;
        while v < 3 {
            let (a, b) = EDGE_CORNERS[tri[v]];
            all = all && (a >> axis) & 1 == side && (b >> axis) & 1 == side;
            v += 1;
        }
        if all {
            return true;
        }
        face += 1;
    }
    false
}

const fn build_cases() -> [Case; 256] {
    let mut cases = [Case {
        edge_mask: 0,
        count: 0,
        tris: [[0; 3]; MAX_TRIANGLES_PER_CELL],
    }; 256];
    let mut config = 0;
    while config < 256 {
        cases[config] = build_case(config);
        config += 1;
    }
    cases
}
