//! Where a scalar field's samples sit: a regular lattice ([`Lattice`], the samples) and its
//! placement in space ([`Grid`]), with the one formula for lattice positions that marching and
//! samplers share.

use glam::Vec3;
use std::ops::Range;

/// A scalar field known at the points of a regular lattice.
///
/// Implementations must be pure: the same `(i, j, k)` must always give the same
/// bits, because neighbouring sub-boxes sample shared points independently.
pub trait Lattice {
    /// The sample at lattice point `(i, j, k)`.
    fn value(&self, i: u32, j: u32, k: u32) -> f32;
}

impl<L: Lattice + ?Sized> Lattice for &L {
    fn value(&self, i: u32, j: u32, k: u32) -> f32 {
        (**self).value(i, j, k)
    }
}

/// Placement of a lattice in space: point `(i, j, k)` sits at
/// `origin + (i, j, k) * spacing`, for `i < dims[0]`, `j < dims[1]`, `k < dims[2]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Grid {
    /// Position of lattice point `(0, 0, 0)`.
    pub origin: Vec3,
    /// Distance between neighbouring lattice points along each axis.
    pub spacing: Vec3,
    /// Number of lattice points along each axis.
    pub dims: [u32; 3],
}

impl Grid {
    /// An `n`×`n`×`n` lattice spanning the unit cube `[0, 1]^3`.
    pub fn unit_cube(n: u32) -> Self {
        let step = 1.0 / n.saturating_sub(1).max(1) as f32;
        Grid {
            origin: Vec3::ZERO,
            spacing: Vec3::splat(step),
            dims: [n; 3],
        }
    }

    /// Position of lattice point `(i, j, k)`.
    ///
    /// This is the only formula used for lattice positions, so every caller
    /// (marching, samplers) agrees on them bit for bit.
    pub fn point(&self, i: u32, j: u32, k: u32) -> Vec3 {
        Vec3::new(
            axis_coord(self.origin.x, self.spacing.x, i),
            axis_coord(self.origin.y, self.spacing.y, j),
            axis_coord(self.origin.z, self.spacing.z, k),
        )
    }

    /// Number of cells along each axis (one fewer than points, never negative).
    pub fn cell_dims(&self) -> [u32; 3] {
        self.dims.map(|d| d.saturating_sub(1))
    }

    /// The cell ranges covering the whole grid, for [`march`](super::march).
    pub fn all_cells(&self) -> [Range<u32>; 3] {
        self.cell_dims().map(|d| 0..d)
    }

    /// Linear index of cell `(i, j, k)`, x fastest; the basis of triangle ids.
    pub fn cell_index(&self, i: u32, j: u32, k: u32) -> u64 {
        let [nx, ny, _] = self.cell_dims().map(u64::from);
        u64::from(i) + nx * (u64::from(j) + ny * u64::from(k))
    }

    /// The lattice's value at `p` by trilinear interpolation in the cell holding it (`p`
    /// clamped into the grid): how a scalar known at the lattice points is read at a
    /// surface's vertex. A corner of zero weight is not read, so a non-finite sample beside a
    /// vertex on a cell's face does not spill into it.
    pub fn interpolate(&self, lattice: &impl Lattice, p: Vec3) -> f32 {
        let mut base = [0u32; 3];
        let mut frac = [0.0f32; 3];
        for a in 0..3 {
            let n = self.dims[a];
            if n < 2 {
                continue;
            }
            let x = ((p[a] - self.origin[a]) / self.spacing[a]).clamp(0.0, (n - 1) as f32);
            // A NaN coordinate casts to 0 and keeps a NaN fraction: the value is NaN.
            base[a] = (x.floor() as u32).min(n - 2);
            frac[a] = x - base[a] as f32;
        }
        let mut sum = 0.0;
        for c in 0..8u32 {
            let mut weight = 1.0;
            let mut q = [0u32; 3];
            for a in 0..3 {
                let upper = (c >> a) & 1 == 1;
                q[a] = (base[a] + u32::from(upper)).min(self.dims[a].saturating_sub(1));
                weight *= if upper { frac[a] } else { 1.0 - frac[a] };
            }
            if weight != 0.0 {
                sum += weight * lattice.value(q[0], q[1], q[2]);
            }
        }
        sum
    }

    /// Cell ranges whose cells may hold triangles touching `b` (one cell more each side, so
    /// rounding never leaves one out): what to march for the part of a surface in a box.
    pub fn cells_touching(&self, b: &crate::geometry::Aabb) -> [Range<u32>; 3] {
        let dims = self.cell_dims();
        [0, 1, 2].map(|a| {
            let lo = ((b.min[a] - self.origin[a]) / self.spacing[a]).floor() - 1.0;
            let hi = ((b.max[a] - self.origin[a]) / self.spacing[a]).ceil() + 1.0;
            let lo = lo.clamp(0.0, dims[a] as f32) as u32;
            let hi = hi.clamp(0.0, dims[a] as f32) as u32;
            lo..hi.max(lo)
        })
    }
}

/// Coordinate of lattice index `i` along one axis: the one formula, so positions agree bit
/// for bit wherever they are computed.
pub(super) fn axis_coord(origin: f32, spacing: f32, i: u32) -> f32 {
    origin + spacing * i as f32
}
