//! Marching cubes over a lattice-sampled scalar field, with triangle ids that
//! do not depend on how the grid is split into sub-boxes.
//!
//! Three ideas, a module each: where the field's samples sit ([`grid`]: the lattice and its
//! placement in space), marching a sub-box of cells into triangles (here), and the case tables
//! (`cases`), which are not typed in but derived at compile time from one rule applied face
//! by face. Deriving them per face is what makes neighbouring cells agree on ambiguous faces,
//! which the classic 256-entry table (with its complementary-case shortcut) does not
//! guarantee.

use glam::Vec3;
use std::ops::Range;

mod cases;
pub mod grid;

use cases::{CASES, Case, EDGE_CORNERS};
use grid::axis_coord;
pub use grid::{Grid, Lattice};
/// Most triangles one cell can produce; triangle ids reserve this many per cell.
pub const MAX_TRIANGLES_PER_CELL: usize = 5;

/// One output triangle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IsoTriangle {
    /// Stable and unique across the whole grid: `cell_linear_index * 5 + k`,
    /// `k` being the triangle's index within its cell's case, so the same
    /// triangle gets the same id whichever sub-range of cells produced it.
    /// Ids of dropped degenerate triangles are simply absent.
    pub id: u64,
    /// Corner positions; the right-hand-rule normal points toward lower values.
    pub vertices: [[f32; 3]; 3],
    /// With [`march_smooth`]: each corner's shading normal, minus the field's gradient there
    /// (toward lower values, as the facet normal), unit length; `[0.0; 3]` where the
    /// gradient vanishes or is not finite (shading then falls back to the facet normal).
    pub normals: Option<[[f32; 3]; 3]>,
}

/// Marches the cells whose cell coordinates lie in `cells` (half-open ranges per
/// axis, a sub-box of the grid's cells), calling `emit` for each triangle of the
/// surface `value == iso`.
///
/// "Inside" is `value > iso` (so NaN is outside); triangles are wound so their
/// normal points out of the inside, toward lower values. Memory use is two
/// z-layers of samples of the sub-box, never the whole grid. Each lattice point
/// of the sub-box is sampled exactly once.
///
/// # Panics
/// If a range reaches past the grid's cells.
pub fn march(
    grid: &Grid,
    lattice: &impl Lattice,
    iso: f32,
    cells: [Range<u32>; 3],
    emit: impl FnMut(IsoTriangle),
) {
    march_impl(grid, lattice, iso, cells, false, emit);
}

/// [`march`], with smooth shading normals at the vertices: the field's gradient by central
/// differences at the two lattice points of a vertex's edge (one-sided on the grid's faces, in
/// world units, so anisotropic spacing tilts it correctly), interpolated along the edge as the
/// vertex is. A vertex's normal depends only on its edge and the lattice, so every sub-box
/// that marches the edge gives it the same bits; the gradient reads lattice points up to one
/// beyond the cells marched (a brick's ghost samples).
pub fn march_smooth(
    grid: &Grid,
    lattice: &impl Lattice,
    iso: f32,
    cells: [Range<u32>; 3],
    emit: impl FnMut(IsoTriangle),
) {
    march_impl(grid, lattice, iso, cells, true, emit);
}

fn march_impl(
    grid: &Grid,
    lattice: &impl Lattice,
    iso: f32,
    cells: [Range<u32>; 3],
    smooth: bool,
    mut emit: impl FnMut(IsoTriangle),
) {
    let cell_dims = grid.cell_dims();
    for (axis, (range, &limit)) in cells.iter().zip(&cell_dims).enumerate() {
        assert!(
            range.end <= limit || range.is_empty(),
            "cell range {range:?} on axis {axis} exceeds the grid's {limit} cells"
        );
    }
    if cells.iter().any(Range::is_empty) {
        return;
    }
    let slab = Slab::new(grid, &cells);
    let mut lower = vec![0.0; slab.layer_len()];
    let mut upper = vec![0.0; slab.layer_len()];
    slab.sample_layer(lattice, cells[2].start, &mut lower);
    for k in cells[2].clone() {
        slab.sample_layer(lattice, k + 1, &mut upper);
        let gradients = smooth.then_some(lattice);
        slab.march_layer(grid, iso, k, [&lower, &upper], gradients, &mut emit);
        // The top samples of this slab are the bottom samples of the next one.
        std::mem::swap(&mut lower, &mut upper);
    }
}

/// Per-call constants for marching one sub-box slab by slab.
struct Slab {
    x: Range<u32>,
    y: Range<u32>,
    /// Coordinates of the sub-box's lattice points along x and along y.
    xs: Vec<f32>,
    ys: Vec<f32>,
}

impl Slab {
    fn new(grid: &Grid, cells: &[Range<u32>; 3]) -> Self {
        let coords = |origin, spacing, r: &Range<u32>| {
            (r.start..=r.end)
                .map(|i| axis_coord(origin, spacing, i))
                .collect()
        };
        Slab {
            x: cells[0].clone(),
            y: cells[1].clone(),
            xs: coords(grid.origin.x, grid.spacing.x, &cells[0]),
            ys: coords(grid.origin.y, grid.spacing.y, &cells[1]),
        }
    }

    fn row_len(&self) -> usize {
        self.xs.len()
    }

    fn layer_len(&self) -> usize {
        self.xs.len() * self.ys.len()
    }

    fn sample_layer(&self, lattice: &impl Lattice, k: u32, out: &mut [f32]) {
        let points = (self.y.start..=self.y.end)
            .flat_map(|j| (self.x.start..=self.x.end).map(move |i| (i, j)));
        for (slot, (i, j)) in out.iter_mut().zip(points) {
            *slot = lattice.value(i, j, k);
        }
    }

    fn march_layer<L: Lattice>(
        &self,
        grid: &Grid,
        iso: f32,
        k: u32,
        layers: [&[f32]; 2],
        gradients: Option<&L>,
        emit: &mut impl FnMut(IsoTriangle),
    ) {
        let zs = [k, k + 1].map(|kk| axis_coord(grid.origin.z, grid.spacing.z, kk));
        for (dj, j) in self.y.clone().enumerate() {
            for (di, i) in self.x.clone().enumerate() {
                let values = self.corner_values(layers, di, dj);
                let config = (0..8).fold(0, |acc, c| acc | (usize::from(values[c] > iso) << c));
                // Most cells are empty: skip them before touching positions.
                if CASES[config].count == 0 {
                    continue;
                }
                let cell = Cell {
                    values,
                    xs: [self.xs[di], self.xs[di + 1]],
                    ys: [self.ys[dj], self.ys[dj + 1]],
                    zs,
                };
                let id_base = grid.cell_index(i, j, k) * MAX_TRIANGLES_PER_CELL as u64;
                let normals = gradients.map(|lattice| Gradients {
                    grid,
                    lattice,
                    corner: [i, j, k],
                });
                march_cell(&cell, &CASES[config], iso, id_base, normals, emit);
            }
        }
    }

    /// Samples at the corners of the cell whose lowest corner is at offset
    /// `(di, dj)` within the sub-box.
    fn corner_values(&self, layers: [&[f32]; 2], di: usize, dj: usize) -> [f32; 8] {
        let near = dj * self.row_len() + di;
        let far = near + self.row_len();
        let [lo, hi] = layers;
        [
            lo[near],
            lo[near + 1],
            lo[far],
            lo[far + 1],
            hi[near],
            hi[near + 1],
            hi[far],
            hi[far + 1],
        ]
    }
}

/// One cell: corner `c` is at lattice offset `(c & 1, (c >> 1) & 1, c >> 2)`,
/// with sample `values[c]` and position `(xs[c & 1], ys[(c >> 1) & 1], zs[c >> 2])`.
struct Cell {
    values: [f32; 8],
    xs: [f32; 2],
    ys: [f32; 2],
    zs: [f32; 2],
}

impl Cell {
    fn point(&self, c: usize) -> [f32; 3] {
        [self.xs[c & 1], self.ys[(c >> 1) & 1], self.zs[c >> 2]]
    }
}

/// What a cell needs to give its vertices smooth normals: the lattice around it and where
/// its corner 0 is.
struct Gradients<'a, L> {
    grid: &'a Grid,
    lattice: &'a L,
    corner: [u32; 3],
}

impl<L: Lattice> Gradients<'_, L> {
    /// The field's gradient at the cell's corner `c` (see [`gradient_at`]).
    fn at_corner(&self, c: usize) -> [f32; 3] {
        let [i, j, k] = self.corner;
        let p = [
            i + (c & 1) as u32,
            j + ((c >> 1) & 1) as u32,
            k + (c >> 2) as u32,
        ];
        gradient_at(self.grid, self.lattice, p)
    }
}

/// The gradient of the field at lattice point `p`, in world units: central differences
/// inside the grid, one-sided differences on its faces (a grid one point thick along an axis
/// has no slope along it).
pub fn gradient_at(grid: &Grid, lattice: &impl Lattice, p: [u32; 3]) -> [f32; 3] {
    let spacing = grid.spacing.to_array();
    std::array::from_fn(|axis| {
        let n = grid.dims[axis];
        let at = |offset: u32, back: bool| {
            let mut q = p;
            q[axis] = if back {
                p[axis] - offset
            } else {
                p[axis] + offset
            };
            lattice.value(q[0], q[1], q[2])
        };
        let (hi, lo, steps) = match (p[axis] > 0, p[axis] + 1 < n) {
            (true, true) => (at(1, false), at(1, true), 2.0),
            (false, true) => (at(1, false), at(0, false), 1.0),
            (true, false) => (at(0, false), at(1, true), 1.0),
            (false, false) => return 0.0,
        };
        (hi - lo) / (steps * spacing[axis])
    })
}

/// The field's gradient magnitude at each lattice point ([`gradient_at`]'s length), itself a
/// lattice: how sharp the field's boundary is there (a CT's bone against soft tissue).
pub struct GradientMagnitude<'a, L> {
    /// Where the lattice points are (the gradient is in world units).
    pub grid: &'a Grid,
    /// The field.
    pub lattice: &'a L,
}

impl<L: Lattice> Lattice for GradientMagnitude<'_, L> {
    fn value(&self, i: u32, j: u32, k: u32) -> f32 {
        Vec3::from(gradient_at(self.grid, self.lattice, [i, j, k])).length()
    }
}

/// Emits the triangles of one cell of case `case`, with smooth normals when `gradients` is given.
fn march_cell<L: Lattice>(
    cell: &Cell,
    case: &Case,
    iso: f32,
    id_base: u64,
    gradients: Option<Gradients<L>>,
    emit: &mut impl FnMut(IsoTriangle),
) {
    let mut edge_points = [[0.0f32; 3]; 12];
    let mut edge_normals = [[0.0f32; 3]; 12];
    let mut corner_gradients: [Option<[f32; 3]>; 8] = [None; 8];
    for (e, &(lo, hi)) in EDGE_CORNERS.iter().enumerate() {
        if case.edge_mask & (1 << e) != 0 {
            let (lo, hi) = (usize::from(lo), usize::from(hi));
            let t = edge_t(cell.values[lo], cell.values[hi], iso);
            edge_points[e] = lerp(cell.point(lo), cell.point(hi), t);
            if let Some(g) = &gradients {
                let mut corner =
                    |c: usize| *corner_gradients[c].get_or_insert_with(|| g.at_corner(c));
                let (ga, gb) = (corner(lo), corner(hi));
                edge_normals[e] = outward_unit(lerp(ga, gb, t));
            }
        }
    }
    for (t, tri) in case.tris[..usize::from(case.count)].iter().enumerate() {
        let vertices = tri.map(|e| edge_points[usize::from(e)]);
        if has_area(&vertices) {
            emit(IsoTriangle {
                id: id_base + t as u64,
                vertices,
                normals: gradients
                    .as_ref()
                    .map(|_| tri.map(|e| edge_normals[usize::from(e)])),
            });
        }
    }
}

/// Minus `gradient`, made unit length: the normal toward lower values; zero if the gradient
/// vanishes or is not finite.
fn outward_unit(gradient: [f32; 3]) -> [f32; 3] {
    let v = -Vec3::from(gradient);
    let len = v.length();
    if len.is_finite() && len > 0.0 {
        (v / len).to_array()
    } else {
        [0.0; 3]
    }
}

/// Where along the edge from the lower lattice point (sample `va`) to the upper one (`vb`)
/// the surface crosses it, as a fraction.
///
/// Callers always pass the lower lattice point first, and the result depends on nothing
/// else, so every cell sharing the edge gets the same bits (for the vertex and its normal).
fn edge_t(va: f32, vb: f32, iso: f32) -> f32 {
    let t = (iso - va) / (vb - va);
    // Only non-finite samples can push t out of [0, 1] (or make it NaN);
    // the midpoint keeps the vertex on the edge and still canonical.
    if (0.0..=1.0).contains(&t) { t } else { 0.5 }
}

fn lerp(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    [0, 1, 2].map(|i| a[i] + t * (b[i] - a[i]))
}

/// False for zero-area triangles (repeated or collinear vertices), which arise
/// when samples equal `iso` exactly and several edge vertices land on a corner.
fn has_area(v: &[[f32; 3]; 3]) -> bool {
    // In f64, differences of nearby f32 coordinates are exact and their
    // products nearly so: a normal of exactly zero really is degenerate.
    let d = |p: usize, axis: usize| f64::from(v[p][axis]) - f64::from(v[0][axis]);
    let (ux, uy, uz) = (d(1, 0), d(1, 1), d(1, 2));
    let (wx, wy, wz) = (d(2, 0), d(2, 1), d(2, 2));
    let n = [uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx];
    n.iter().any(|&c| c != 0.0)
}

#[cfg(test)]
mod tests;
