//! A procedural, cosmology-like density field: clustered particles splatted
//! with a compact kernel, whose iso-surface looks like blobby halos along
//! filaments.
//!
//! Everything is derived from a seed with a hand-written generator and only
//! IEEE-exact operations (`+ - * /`, `sqrt`, comparisons), never `sin`, `ln`
//! or `powf`, whose results may differ between math libraries: every machine
//! of a render farm must see the very same field.

use crate::isosurface::{Grid, Lattice, march};
use glam::{DMat3, DQuat, DVec3, Vec3, Vec4};

/// Number of halo (cluster) centres: a few hundred gives many separate and
/// merging blobs at any particle count.
const CLUSTERS: usize = 320;
/// Superclusters group the halo centres, so halos crowd into walls and knots
/// with voids between, as in the cosmic web.
const SUPERCLUSTERS: usize = 48;
/// Share of halos placed anywhere rather than in a supercluster: isolated
/// blobs between the crowded regions.
const FIELD_HALO_FRACTION: f64 = 0.4;
/// Spread (standard deviation) of halo centres around their supercluster.
const SUPERCLUSTER_SPREAD: f64 = 0.07;
/// Halo masses follow a Pareto tail: mass = 1/u for u in [MIN_U, 1), so a few
/// halos are up to 1/MIN_U times heavier than the typical one.
const MIN_U: f64 = 0.03;
/// Scale radius of a unit-mass halo; it grows as mass^(1/4).
const HALO_SCALE: f64 = 0.012;
/// Shortest halo axis relative to the longest, before volume normalisation.
const MIN_AXIS: f64 = 0.55;
/// Halo particles are drawn out to this many scale radii.
const HALO_EXTENT: f64 = 4.0;
/// Share of particles strung along filaments between neighbouring halos.
const FILAMENT_FRACTION: f64 = 0.12;
/// Each halo links to at most this many nearest halos...
const FILAMENT_LINKS: usize = 2;
/// ...and only to those closer than this.
const FILAMENT_MAX_LENGTH: f64 = 0.16;
/// Thickness (standard deviation) of filaments.
const FILAMENT_WIDTH: f64 = 0.004;
/// Halo centres stay this far from the cube's faces.
const CENTRE_MARGIN: f64 = 0.1;
/// Extra clearance beyond the kernel radius kept free of particles along the
/// faces, so the surface never touches the cube's boundary.
const EDGE_CLEARANCE: f64 = 0.01;
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

/// The particle positions of `NbodyField::new(seed, particles)`, halo by
/// halo, then filament by filament.
fn draw_positions(seed: u64, particles: usize, radius: f64) -> Vec<[f32; 3]> {
    let mut rng = SplitMix64(seed);
    let halos = draw_halos(&mut rng);
    let filaments = link_filaments(&halos);
    let margin = radius + EDGE_CLEARANCE;
    let bounds = Bounds {
        lo: margin,
        hi: 1.0 - margin,
    };
    let on_filaments = if filaments.is_empty() {
        0
    } else {
        (particles as f64 * FILAMENT_FRACTION) as usize
    };
    let masses: Vec<f64> = halos.iter().map(|h| h.mass).collect();
    let lengths: Vec<f64> = filaments.iter().map(Filament::length).collect();
    let mut out = Vec::with_capacity(particles);
    for (halo, n) in halos
        .iter()
        .zip(apportion(particles - on_filaments, &masses))
    {
        halo.scatter(&mut rng, n, bounds, &mut out);
    }
    for (filament, n) in filaments.iter().zip(apportion(on_filaments, &lengths)) {
        filament.scatter(&mut rng, n, bounds, &mut out);
    }
    out
}

/// Splits `total` into whole shares proportional to `weights`, adding up to
/// exactly `total` (rounding the running sum, so no share drifts).
fn apportion(total: usize, weights: &[f64]) -> Vec<usize> {
    let sum: f64 = weights.iter().sum();
    let mut running = 0.0;
    let mut given = 0;
    weights
        .iter()
        .enumerate()
        .map(|(i, w)| {
            running += w;
            let upto = if i + 1 == weights.len() {
                total
            } else {
                ((running / sum * total as f64).round() as usize).min(total)
            };
            let share = upto.saturating_sub(given);
            given = given.max(upto);
            share
        })
        .collect()
}

/// The box particles must stay in: `[lo, hi]^3`.
#[derive(Clone, Copy)]
struct Bounds {
    lo: f64,
    hi: f64,
}

impl Bounds {
    fn contains(self, p: DVec3) -> bool {
        p.cmpge(DVec3::splat(self.lo)).all() && p.cmple(DVec3::splat(self.hi)).all()
    }

    fn clamp(self, p: DVec3) -> DVec3 {
        p.clamp(DVec3::splat(self.lo), DVec3::splat(self.hi))
    }
}

fn to_f32(p: DVec3) -> [f32; 3] {
    p.as_vec3().to_array()
}

/// Kernel radius for `particles` particles: shrinks as the count grows so a
/// kernel overlaps about the same number of particles whatever the count.
fn kernel_radius(particles: usize) -> f64 {
    let r = RADIUS_FACTOR / cube_root(particles.max(1) as f64);
    r.clamp(0.002, 0.1)
}

/// Cube root by bisection: slower than `cbrt` but bit-identical everywhere.
fn cube_root(x: f64) -> f64 {
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

/// splitmix64 (Steele, Lea & Flood): tiny, fast and well mixed, and fixed
/// here so the field cannot change with a dependency's version.
struct SplitMix64(u64);

impl SplitMix64 {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1), from the top 53 bits.
    fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    fn unit3(&mut self) -> DVec3 {
        DVec3::new(self.unit(), self.unit(), self.unit())
    }

    /// Approximately standard normal: sum of four uniforms (Irwin–Hall),
    /// avoiding the logarithm and cosine of Box–Muller.
    fn normal(&mut self) -> f64 {
        let s = self.unit() + self.unit() + self.unit() + self.unit();
        (s - 2.0) * 3.0f64.sqrt()
    }

    fn normal3(&mut self) -> DVec3 {
        DVec3::new(self.normal(), self.normal(), self.normal())
    }

    /// A random rotation, from a normalised 4D normal vector (no trigonometry).
    fn rotation(&mut self) -> DMat3 {
        loop {
            let q = DQuat::from_xyzw(self.normal(), self.normal(), self.normal(), self.normal());
            if q.length_squared() > 1e-6 {
                return DMat3::from_quat(q.normalize());
            }
        }
    }
}

/// The additive recurrence ("R3" sequence) `x += (1/g, 1/g², 1/g³) mod 1`,
/// g the real root of x⁴ = x + 1: points fill the unit cube far more evenly
/// than random ones, so halos built from it have little shot noise and their
/// iso-surfaces come out smooth at a modest particle count.
struct Kronecker(DVec3);

impl Kronecker {
    const STEP: DVec3 = DVec3::new(
        0.819_172_513_396_164_5,
        0.671_043_606_703_789_3,
        0.549_700_477_901_970_2,
    );

    fn next(&mut self) -> DVec3 {
        let p = self.0 + Self::STEP;
        // Exact, unlike a general `fract`, as every coordinate is below 2.
        self.0 = DVec3::select(p.cmpge(DVec3::ONE), p - DVec3::ONE, p);
        self.0
    }
}

/// One dark-matter-halo-like cluster.
struct Halo {
    centre: DVec3,
    /// Core radius `a` of the profile.
    scale: f64,
    mass: f64,
    /// Rotation times axis stretch: halos are ellipsoids, not spheres.
    shape: DMat3,
}

impl Halo {
    /// Appends `n` particles in `bounds`. The enclosed share of particles
    /// within radius r is (r/(a+r))³: a flat core with a heavy r⁻⁴ tail
    /// (Hernquist-like outside the core).
    fn scatter(&self, rng: &mut SplitMix64, n: usize, bounds: Bounds, out: &mut Vec<[f32; 3]>) {
        let mut sequence = Kronecker(rng.unit3());
        // Truncates the profile at HALO_EXTENT·a without changing its shape inside.
        let reach = HALO_EXTENT / (1.0 + HALO_EXTENT);
        let mut placed = 0;
        let mut tries = 0;
        while placed < n && tries < 64 * n + 64 {
            tries += 1;
            let v = sequence.next() * 2.0 - DVec3::ONE;
            let rho = v.length();
            if rho > 1.0 || rho == 0.0 {
                continue;
            }
            // rho³ is uniform over the ball; mapping it through the profile's
            // inverse keeps the sequence's evenness.
            let s = reach * rho;
            let r = self.scale * s / (1.0 - s);
            let p = self.centre + self.shape * (v * (r / rho));
            if bounds.contains(p) {
                out.push(to_f32(p));
                placed += 1;
            }
        }
        // Only a halo almost entirely outside the bounds gets here.
        out.extend((placed..n).map(|_| to_f32(bounds.clamp(self.centre))));
    }
}

fn draw_halos(rng: &mut SplitMix64) -> Vec<Halo> {
    let span = (CENTRE_MARGIN, 1.0 - CENTRE_MARGIN);
    let uniform = |rng: &mut SplitMix64| DVec3::splat(span.0) + rng.unit3() * (span.1 - span.0);
    let hubs: Vec<DVec3> = (0..SUPERCLUSTERS).map(|_| uniform(rng)).collect();
    (0..CLUSTERS)
        .map(|i| {
            let centre = if rng.unit() < FIELD_HALO_FRACTION {
                uniform(rng)
            } else {
                let offset = rng.normal3() * SUPERCLUSTER_SPREAD;
                (hubs[i % SUPERCLUSTERS] + offset).clamp(DVec3::splat(span.0), DVec3::splat(span.1))
            };
            let mass = 1.0 / rng.range(MIN_U, 1.0);
            let axes = DVec3::new(1.0, rng.range(MIN_AXIS, 1.0), rng.range(MIN_AXIS, 1.0));
            // Same volume as the sphere of the unstretched profile.
            let axes = axes / cube_root(axes.x * axes.y * axes.z);
            Halo {
                centre,
                scale: HALO_SCALE * mass.sqrt().sqrt(),
                mass,
                shape: rng.rotation() * DMat3::from_diagonal(axes),
            }
        })
        .collect()
}

/// A straight filament between two halo centres.
struct Filament {
    from: DVec3,
    to: DVec3,
}

impl Filament {
    fn length(&self) -> f64 {
        self.from.distance(self.to)
    }

    /// Appends `n` particles spread evenly along the filament (stratified)
    /// with a normal scatter across it.
    fn scatter(&self, rng: &mut SplitMix64, n: usize, bounds: Bounds, out: &mut Vec<[f32; 3]>) {
        for i in 0..n {
            let t = (i as f64 + rng.unit()) / n as f64;
            let along = self.from.lerp(self.to, t);
            // Redraw the rare particles scattered out of the box rather than
            // clamping them, which would pile them up on the box's faces.
            let p = (0..16)
                .map(|_| along + rng.normal3() * FILAMENT_WIDTH)
                .find(|&p| bounds.contains(p))
                .unwrap_or_else(|| bounds.clamp(along));
            out.push(to_f32(p));
        }
    }
}

/// Links every halo to its nearest neighbours within reach (each pair once).
fn link_filaments(halos: &[Halo]) -> Vec<Filament> {
    let mut pairs = Vec::new();
    for (i, a) in halos.iter().enumerate() {
        let mut near: Vec<(f64, usize)> = halos
            .iter()
            .enumerate()
            .filter(|&(j, _)| j != i)
            .map(|(j, b)| (a.centre.distance_squared(b.centre), j))
            .filter(|&(d, _)| d < FILAMENT_MAX_LENGTH * FILAMENT_MAX_LENGTH)
            .collect();
        near.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
        pairs.extend(
            near.iter()
                .take(FILAMENT_LINKS)
                .map(|&(_, j)| (i.min(j), i.max(j))),
        );
    }
    pairs.sort_unstable();
    pairs.dedup();
    pairs
        .into_iter()
        .map(|(i, j)| Filament {
            from: halos[i].centre,
            to: halos[j].centre,
        })
        .collect()
}

/// Samples an [`NbodyField`] at the points of a [`Grid`], for [`march`].
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

/// Points per axis of a cube grid over `[0, 1]^3` whose marching at `iso`
/// should yield roughly `target_triangles` triangles.
///
/// Marches coarse grids of 32³ and 64³ cells and extrapolates from their
/// triangle counts. A smooth surface's count grows with the square of the
/// resolution, but finer grids also resolve small blobs and wrinkles the
/// coarse ones miss; the growth between the two coarse grids measures that,
/// and the extrapolation uses it. Deterministic, like the field itself.
pub fn resolution_for_triangles(field: &NbodyField, iso: f32, target_triangles: u64) -> u32 {
    const COARSE: u32 = 64;
    let fine = count_triangles(field, iso, COARSE + 1) as f64;
    let coarse = count_triangles(field, iso, COARSE / 2 + 1) as f64;
    if fine == 0.0 || coarse == 0.0 {
        return COARSE + 1;
    }
    // Growth exponent between 32 and 64 cells, kept near the smooth-surface 2.
    let exponent = log2(fine / coarse).clamp(1.5, 3.0);
    let scale = exp2(log2(target_triangles.max(1) as f64 / fine) / exponent);
    let cells = (f64::from(COARSE) * scale).round();
    (cells as u32).saturating_add(1).clamp(2, 1 << 16)
}

fn count_triangles(field: &NbodyField, iso: f32, n: u32) -> u64 {
    let sampled = SampledField {
        field,
        grid: Grid::unit_cube(n),
    };
    let mut count = 0;
    march(
        &sampled.grid,
        &sampled,
        iso,
        sampled.grid.all_cells(),
        |_| count += 1,
    );
    count
}

/// Base-2 logarithm of a positive finite `x` from its exponent bits and an
/// atanh series, so the result does not depend on the platform's libm.
fn log2(x: f64) -> f64 {
    debug_assert!(x > 0.0 && x.is_finite());
    let bits = x.to_bits();
    let exponent = ((bits >> 52) & 0x7ff) as i64 - 1023;
    let mantissa = f64::from_bits((bits & ((1 << 52) - 1)) | (1023 << 52));
    // ln(m) = 2·atanh(z), z = (m-1)/(m+1) ≤ 1/3: 30 terms are ample.
    let z = (mantissa - 1.0) / (mantissa + 1.0);
    let (mut term, mut series) = (z, 0.0);
    for k in 0..30 {
        series += term / f64::from(2 * k + 1);
        term *= z * z;
    }
    exponent as f64 + 2.0 * series / std::f64::consts::LN_2
}

/// 2^y for moderate `y`, by repeated squaring for the integer part and a
/// Taylor series for the fraction (same reason as [`log2`]).
fn exp2(y: f64) -> f64 {
    let whole = y.floor();
    let frac_ln = (y - whole) * std::f64::consts::LN_2;
    let (mut term, mut series) = (1.0, 0.0);
    for k in 1..30 {
        series += term;
        term *= frac_ln / f64::from(k);
    }
    let mut power = 1.0;
    for _ in 0..(whole.abs().min(1023.0) as u32) {
        power *= 2.0;
    }
    if whole < 0.0 {
        series / power
    } else {
        series * power
    }
}

#[cfg(test)]
mod tests;
