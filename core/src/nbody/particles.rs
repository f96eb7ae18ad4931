//! Where the particles are: halo centres grouped into superclusters, particles scattered in
//! each halo by its mass and strung along filaments between neighbouring halos, all drawn from
//! the seed by a fixed generator with IEEE-exact operations only.

use glam::{DMat3, DQuat, DVec3};

use super::cube_root;

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

/// The particle positions of `NbodyField::new(seed, particles)`, halo by
/// halo, then filament by filament.
pub(super) fn draw_positions(seed: u64, particles: usize, radius: f64) -> Vec<[f32; 3]> {
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
pub(super) fn apportion(total: usize, weights: &[f64]) -> Vec<usize> {
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

/// A point as the particles are stored, in f32.
fn to_f32(p: DVec3) -> [f32; 3] {
    p.as_vec3().to_array()
}

/// splitmix64 (Steele, Lea & Flood): tiny, fast and well mixed, and fixed
/// here so the field cannot change with a dependency's version.
pub(super) struct SplitMix64(pub(super) u64);

impl SplitMix64 {
    pub(super) fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1), from the top 53 bits.
    pub(super) fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    pub(super) fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    pub(super) fn unit3(&mut self) -> DVec3 {
        DVec3::new(self.unit(), self.unit(), self.unit())
    }

    /// Approximately standard normal: sum of four uniforms (Irwin–Hall),
    /// avoiding the logarithm and cosine of Box–Muller.
    pub(super) fn normal(&mut self) -> f64 {
        let s = self.unit() + self.unit() + self.unit() + self.unit();
        (s - 2.0) * 3.0f64.sqrt()
    }

    pub(super) fn normal3(&mut self) -> DVec3 {
        DVec3::new(self.normal(), self.normal(), self.normal())
    }

    /// A random rotation, from a normalised 4D normal vector (no trigonometry).
    pub(super) fn rotation(&mut self) -> DMat3 {
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
