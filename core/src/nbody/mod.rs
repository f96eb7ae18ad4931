//! A procedural, cosmology-like density field: clustered particles splatted
//! with a compact kernel, whose iso-surface looks like blobby halos along
//! filaments.
//!
//! Everything is derived from a seed with a hand-written generator and only
//! IEEE-exact operations (`+ - * /`, `sqrt`, comparisons), never `sin`, `ln`
//! or `powf`, whose results may differ between math libraries: every machine
//! of a render farm must see the very same field.
//!
//! Three ideas, a module each: where the particles are (`particles`: halos along filaments,
//! drawn from the seed), the density they make and its lookup structure (here), and how fine a
//! grid gives a wanted triangle count (`resolution`).

use crate::isosurface::{Grid, Lattice};
use glam::{Vec3, Vec4};

mod particles;
mod resolution;

use particles::{SplitMix64, draw_positions};
pub use resolution::resolution_for_triangles;

/// Kernel radius times the cube root of the particle count: sets how many
/// particles overlap a kernel, trading smooth blobs against query cost.
const RADIUS_FACTOR: f64 = 1.0;
/// Share of the cube's volume the suggested iso-surface should enclose.
const TARGET_FILL: f64 = 0.10;
/// Lowest suggested iso: above a lone particle's peak density of 1, so stray
/// particles do not show up as specks.
const MIN_ISO: f32 = 1.4;
/// Density samples used to calibrate the suggested iso value.
const CALIBRATION_SAMPLES: usize = 1 << 16;
/// Lane numbers, to mask the lanes of a SIMD group past the end of a run.
const LANE_INDEX: Vec4 = Vec4::new(0.0, 1.0, 2.0, 3.0);
/// Padding after the particle arrays, so a 4-lane load never runs off them.
const SIMD_SPARE: usize = 3;
/// Limit on the particle grid's resolution, bounding its memory.
const MAX_GRID_CELLS: u32 = 400;

/// Clustered particles in the unit cube, splatted with the compact kernel
/// `(1 - r²/h²)³` (radius `h`); the field is their summed density, so a lone
/// particle peaks at 1.
///
/// Built from a seed and a particle count alone, identically on every machine.
#[derive(Clone, Debug)]
pub struct NbodyField {
    radius: f32,
    inv_radius_sq: f32,
    /// Particle grid cells per axis: at least `radius` wide along y and z,
    /// half that along x, where narrower cells trim the particles visited
    /// at no cost in memory.
    cells: [u32; 3],
    /// Cells per unit length along each axis (`cells` as floats).
    cell_scale: Vec3,
    /// Width of a cell along z.
    cell_size_z: f32,
    /// `starts[b]..starts[b + 1]` indexes the coordinates of band `b`. Band
    /// `(x, y, z)` (x fastest) holds the particles of cells `(x, y-1..=y+1, z)`,
    /// so all particles a query can reach lie in three contiguous runs, one per
    /// z layer; the price is storing each particle three times.
    starts: Vec<u32>,
    /// Particle coordinates in band order, one array per axis so four
    /// particles load as one SIMD vector.
    xs: Vec<f32>,
    ys: Vec<f32>,
    zs: Vec<f32>,
    particles: usize,
    iso: f32,
}

impl NbodyField {
    /// Draws `particles` particles from `seed`: a few hundred halos with
    /// heavy-tailed masses and radial profiles, grouped into superclusters,
    /// plus filaments between near halos. All particles lie inside the unit
    /// cube with a margin wider than the kernel, so the density (and hence any
    /// positive iso-surface) vanishes near the cube's faces.
    pub fn new(seed: u64, particles: usize) -> Self {
        let radius = kernel_radius(particles);
        let positions = draw_positions(seed, particles, radius);
        let mut field = Self::index(&positions, radius as f32);
        field.iso = field.calibrate_iso(seed);
        field
    }

    /// Buckets particles into bands of a grid of cells at least one kernel
    /// radius wide (counting sort, stable, so the summation order and so every
    /// bit of the density depends only on the seed).
    fn index(positions: &[[f32; 3]], radius: f32) -> Self {
        let g = ((1.0 / radius) as u32).clamp(1, MAX_GRID_CELLS);
        let cells = [2 * g, g, g];
        let cell_scale = Vec3::from_array(cells.map(|c| c as f32));
        let bands_of = |p: &[f32; 3]| {
            let [x, y, z] = cell_of(Vec3::from_array(*p), cell_scale, cells).map(|c| c as usize);
            let [gx, g] = [cells[0] as usize, g as usize];
            (y.saturating_sub(1)..=(y + 1).min(g - 1)).map(move |band_y| x + gx * (band_y + g * z))
        };
        let mut starts = vec![0u32; cells.iter().map(|&c| c as usize).product::<usize>() + 1];
        for band in positions.iter().flat_map(bands_of) {
            starts[band + 1] += 1;
        }
        for b in 1..starts.len() {
            starts[b] = starts[b - 1]
                .checked_add(starts[b])
                .expect("more than u32::MAX particle copies");
        }
        // Spare entries let the last SIMD group of a run read past its end.
        let len = starts[starts.len() - 1] as usize + SIMD_SPARE;
        let (mut xs, mut ys, mut zs) = (vec![0.0; len], vec![0.0; len], vec![0.0; len]);
        let mut fill = starts.clone();
        for p in positions {
            for band in bands_of(p) {
                let i = fill[band] as usize;
                (xs[i], ys[i], zs[i]) = (p[0], p[1], p[2]);
                fill[band] += 1;
            }
        }
        NbodyField {
            radius,
            inv_radius_sq: 1.0 / (radius * radius),
            cells,
            cell_scale,
            cell_size_z: 1.0 / cell_scale.z,
            starts,
            xs,
            ys,
            zs,
            particles: positions.len(),
            iso: 0.0,
        }
    }

    /// Kernel radius `h`: particles further than this from `p` do not add to
    /// `density(p)`.
    pub fn kernel_radius(&self) -> f32 {
        self.radius
    }

    /// Number of particles.
    pub fn particle_count(&self) -> usize {
        self.particles
    }

    /// Summed kernel density at `p`: `Σ (1 - |p - x|²/h²)³` over particles `x`
    /// within `h`. Pure and deterministic (fixed summation order); zero
    /// outside the cube and near its faces.
    pub fn density(&self, p: Vec3) -> f32 {
        if !p.is_finite() {
            return 0.0;
        }
        let [x0, y0, z0] = self.first_cell(p);
        let [x1, y1, z1] = self.last_cell(p);
        if x0 > x1 || y0 > y1 || z0 > z1 {
            return 0.0;
        }
        // Cells are at least h wide along y, so the band centred on p's own
        // row covers every row within reach.
        let band_y = cell_of(p, self.cell_scale, self.cells)[1] as i32;
        let h_sq = self.radius * self.radius;
        let [gx, g, _] = self.cells.map(|c| c as i32);
        let mut lanes = Vec4::ZERO;
        for z in z0..=z1 {
            // Layers out of reach would only add zeros.
            if sq(self.gap_z(p.z, z)) < h_sq {
                // Bands x0..=x1 of one (y, z) are contiguous (x fastest).
                let row = (z * g + band_y) * gx;
                let start = self.starts[(row + x0) as usize] as usize;
                let end = self.starts[(row + x1 + 1) as usize] as usize;
                lanes += self.run_lanes(p, start, end);
            }
        }
        // A fixed reduction order keeps the result identical everywhere.
        (lanes.x + lanes.y) + (lanes.z + lanes.w)
    }

    /// Per-lane kernel sums over the particles `start..end`.
    fn run_lanes(&self, p: Vec3, start: usize, end: usize) -> Vec4 {
        let whole = start + (end - start) / 4 * 4;
        let mut lanes = Vec4::ZERO;
        let groups = self.xs[start..whole]
            .chunks_exact(4)
            .zip(self.ys[start..whole].chunks_exact(4))
            .zip(self.zs[start..whole].chunks_exact(4));
        for ((x, y), z) in groups {
            let d_sq = self.dist_sq4(
                p,
                Vec4::from_slice(x),
                Vec4::from_slice(y),
                Vec4::from_slice(z),
            );
            lanes += self.kernel4(d_sq);
        }
        if whole < end {
            // The arrays carry spare entries, so the last group may read past
            // `end`; its lanes beyond `end` are masked out.
            let tail = whole..whole + 4;
            let d_sq = self.dist_sq4(
                p,
                Vec4::from_slice(&self.xs[tail.clone()]),
                Vec4::from_slice(&self.ys[tail.clone()]),
                Vec4::from_slice(&self.zs[tail]),
            );
            let live = LANE_INDEX.cmplt(Vec4::splat((end - whole) as f32));
            lanes += Vec4::select(live, self.kernel4(d_sq), Vec4::ZERO);
        }
        lanes
    }

    fn dist_sq4(&self, p: Vec3, x: Vec4, y: Vec4, z: Vec4) -> Vec4 {
        sq4(x - p.x) + sq4(y - p.y) + sq4(z - p.z)
    }

    /// `(1 - d²/h²)³`, zero beyond `h`, on four squared distances. Computed
    /// for every particle visited: most are out of reach, and a branch on that
    /// would be mispredicted constantly.
    fn kernel4(&self, d_sq: Vec4) -> Vec4 {
        let t = (Vec4::ONE - d_sq * self.inv_radius_sq).max(Vec4::ZERO);
        t * t * t
    }

    /// Lowest grid cell per axis that particles within `h` of `p` can be in
    /// (may exceed `last_cell` when `p` is far outside the cube).
    fn first_cell(&self, p: Vec3) -> [i32; 3] {
        let lo = (p - self.radius) * self.cell_scale;
        // Truncation equals floor wherever the clamp does not override it, and
        // `floor` is a libm call on baseline x86-64 (no SSE4.1).
        lo.to_array().map(|v| (v as i32).max(0))
    }

    fn last_cell(&self, p: Vec3) -> [i32; 3] {
        let hi = (p + self.radius) * self.cell_scale;
        let max = self.cells.map(|c| c as i32 - 1);
        // Truncating a negative `v` toward zero may admit cell 0 for a point
        // out of reach; the kernel then adds exact zeros, so that is harmless.
        let hi = hi.to_array();
        [0, 1, 2].map(|a| (hi[a] as i32).min(max[a]))
    }

    /// Distance along z from coordinate `v` to grid layer `c`.
    fn gap_z(&self, v: f32, c: i32) -> f32 {
        let lo = c as f32 * self.cell_size_z;
        let hi = lo + self.cell_size_z;
        (lo - v).max(v - hi).max(0.0)
    }

    /// An iso value whose surface encloses about 10% of the cube's volume, or
    /// less where that would take an iso below 1.4: lower values let pairs of
    /// stray particles (a lone one peaks at 1) show up as specks, and the
    /// surface gets rough where few particles overlap. Lower `iso` values
    /// fill more (around 15% at 0.8) with rougher, more merged surfaces.
    pub fn suggested_iso(&self) -> f32 {
        self.iso
    }

    /// Picks the iso value from the density distribution at random points.
    fn calibrate_iso(&self, seed: u64) -> f32 {
        let mut rng = SplitMix64(seed ^ 0x5eed_ca1b_0000_0001);
        let mut samples: Vec<f32> = (0..CALIBRATION_SAMPLES)
            .map(|_| {
                let p = [rng.unit(), rng.unit(), rng.unit()].map(|v| v as f32);
                self.density(Vec3::from_array(p))
            })
            .collect();
        samples.sort_unstable_by(f32::total_cmp);
        let rank = ((1.0 - TARGET_FILL) * CALIBRATION_SAMPLES as f64) as usize;
        samples[rank].max(MIN_ISO)
    }
}

/// The grid cell containing `p`, clamped into the grid.
fn cell_of(p: Vec3, cell_scale: Vec3, cells: [u32; 3]) -> [u32; 3] {
    let scaled = (p * cell_scale).to_array();
    // Float-to-int casts saturate, so negative coordinates land in cell 0.
    [0, 1, 2].map(|a| (scaled[a] as u32).min(cells[a] - 1))
}

fn sq(v: f32) -> f32 {
    v * v
}

fn sq4(v: Vec4) -> Vec4 {
    v * v
}

/// Kernel radius for `particles` particles: shrinks as the count grows so a
/// kernel overlaps about the same number of particles whatever the count.
fn kernel_radius(particles: usize) -> f64 {
    let r = RADIUS_FACTOR / cube_root(particles.max(1) as f64);
    r.clamp(0.002, 0.1)
}

/// Cube root by bisection: slower than `cbrt` but bit-identical everywhere.
pub(super) fn cube_root(x: f64) -> f64 {
    let (mut lo, mut hi) = (0.0, x.max(1.0));
    for _ in 0..80 {
        let mid = 0.5 * (lo + hi);
        if mid * mid * mid < x {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// Samples an [`NbodyField`] at the points of a [`Grid`], for [`march`](crate::isosurface::march).
pub struct SampledField<'a> {
    /// The field sampled.
    pub field: &'a NbodyField,
    /// Where the lattice points are.
    pub grid: Grid,
}

impl Lattice for SampledField<'_> {
    fn value(&self, i: u32, j: u32, k: u32) -> f32 {
        self.field.density(self.grid.point(i, j, k))
    }
}

#[cfg(test)]
mod tests;
