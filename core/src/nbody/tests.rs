use super::particles::apportion;
use super::resolution::{count_triangles, exp2, log2};
use super::*;
use crate::isosurface::march;

fn field() -> NbodyField {
    NbodyField::new(7, 200_000)
}

fn random_point(rng: &mut SplitMix64) -> Vec3 {
    rng.unit3().as_vec3()
}

#[test]
fn same_seed_same_bits() {
    let (a, b, c) = (
        NbodyField::new(3, 20_000),
        NbodyField::new(3, 20_000),
        NbodyField::new(4, 20_000),
    );
    assert_eq!(a.suggested_iso().to_bits(), b.suggested_iso().to_bits());
    let mut rng = SplitMix64(5);
    let mut differs = false;
    for _ in 0..1000 {
        let p = random_point(&mut rng);
        assert_eq!(a.density(p).to_bits(), b.density(p).to_bits());
        assert_eq!(a.density(p).to_bits(), a.density(p).to_bits());
        differs |= a.density(p) != c.density(p);
    }
    assert!(differs, "seed does not matter");
}

#[test]
fn density_matches_brute_force() {
    let (seed, n) = (11, 30_000);
    let f = NbodyField::new(seed, n);
    let positions = draw_positions(seed, n, kernel_radius(n));
    let mut rng = SplitMix64(99);
    let mut nonzero = 0;
    for _ in 0..3000 {
        let p = random_point(&mut rng);
        let brute: f64 = positions
            .iter()
            .map(|q| {
                let d_sq = Vec3::from_array(*q).distance_squared(p);
                f64::from((1.0 - d_sq * f.inv_radius_sq).max(0.0)).powi(3)
            })
            .sum();
        let fast = f64::from(f.density(p));
        assert!(
            (fast - brute).abs() <= 1e-4 * brute.max(1.0),
            "{fast} vs {brute} at {p}"
        );
        nonzero += usize::from(brute > 0.0);
    }
    assert!(
        nonzero > 300,
        "too few points near particles to mean anything"
    );
}

#[test]
fn particles_keep_clear_of_the_faces() {
    let (seed, n) = (7, 200_000);
    let positions = draw_positions(seed, n, kernel_radius(n));
    assert_eq!(positions.len(), n);
    assert_eq!(field().particle_count(), n);
    let lo = kernel_radius(n) as f32;
    for q in &positions {
        assert!(q.iter().all(|&c| c > lo && c < 1.0 - lo), "{q:?}");
    }
    let f = field();
    let far = [
        Vec3::ZERO,
        Vec3::ONE,
        Vec3::splat(0.5).with_x(0.0),
        Vec3::splat(-3.0),
        Vec3::splat(7.0),
    ];
    for p in far.into_iter().chain([Vec3::NAN, Vec3::INFINITY]) {
        assert_eq!(f.density(p), 0.0, "at {p}");
    }
}

#[test]
fn suggested_iso_fills_a_fair_share_of_the_cube() {
    let f = field();
    let iso = f.suggested_iso();
    assert!(iso >= MIN_ISO);
    let mut rng = SplitMix64(1234);
    let n = 40_000;
    let inside = (0..n)
        .filter(|_| f.density(random_point(&mut rng)) > iso)
        .count();
    let fill = inside as f64 / n as f64;
    assert!((0.07..=0.3).contains(&fill), "fill {fill}");
}

#[test]
fn surface_is_many_separate_blobs() {
    // Count connected inside regions on a 64³ lattice: clustered halos
    // should give many, not one sponge or a few spheres.
    let f = field();
    let n = 64usize;
    let grid = Grid::unit_cube(n as u32);
    let inside: Vec<bool> = (0..n * n * n)
        .map(|l| {
            let (i, j, k) = (l % n, (l / n) % n, l / (n * n));
            f.density(grid.point(i as u32, j as u32, k as u32)) > f.suggested_iso()
        })
        .collect();
    let blobs = count_components(&inside, n);
    assert!(blobs >= 20, "only {blobs} blobs");
}

fn count_components(inside: &[bool], n: usize) -> usize {
    let mut seen = vec![false; inside.len()];
    let mut blobs = 0;
    for start in 0..inside.len() {
        if !inside[start] || seen[start] {
            continue;
        }
        blobs += 1;
        seen[start] = true;
        let mut stack = vec![start];
        while let Some(l) = stack.pop() {
            let (i, j, k) = (l % n, (l / n) % n, l / (n * n));
            let neighbours = [
                (i > 0).then(|| l - 1),
                (i + 1 < n).then(|| l + 1),
                (j > 0).then(|| l - n),
                (j + 1 < n).then(|| l + n),
                (k > 0).then(|| l - n * n),
                (k + 1 < n).then(|| l + n * n),
            ];
            for m in neighbours.into_iter().flatten() {
                if inside[m] && !seen[m] {
                    seen[m] = true;
                    stack.push(m);
                }
            }
        }
    }
    blobs
}

#[test]
fn resolution_lands_within_2x_of_the_target() {
    let f = field();
    let iso = f.suggested_iso();
    let n = resolution_for_triangles(&f, iso, 100_000);
    let got = count_triangles(&f, iso, n);
    assert!(
        (50_000..=200_000).contains(&got),
        "n = {n} gave {got} triangles"
    );
}

#[test]
fn deterministic_log_and_exp_are_accurate() {
    for x in [1e-9, 0.3, 1.0, 1.5, 2.0, 7.0, 123_456.0, 1e12] {
        assert!((log2(x) - x.log2()).abs() < 1e-12, "log2({x})");
    }
    for y in [-20.5, -1.0, -0.25, 0.0, 0.5, 1.0, 3.7, 30.2] {
        let rel = (exp2(y) - y.exp2()).abs() / y.exp2();
        assert!(rel < 1e-13, "exp2({y})");
    }
    assert!((cube_root(1e6) - 100.0).abs() < 1e-9);
}

#[test]
fn apportion_adds_up() {
    assert_eq!(apportion(12, &[1.0, 1.0, 2.0]), [3, 3, 6]);
    let shares = apportion(1001, &[0.3, 5.0, 0.01, 2.2, 7.0]);
    assert_eq!(shares.iter().sum::<usize>(), 1001);
    assert_eq!(apportion(0, &[1.0, 2.0]), [0, 0]);
}

#[test]
fn tiny_and_empty_fields_work() {
    let empty = NbodyField::new(1, 0);
    assert_eq!(empty.density(Vec3::splat(0.5)), 0.0);
    assert!(empty.suggested_iso() >= MIN_ISO);
    let tiny = NbodyField::new(1, 10);
    assert_eq!(tiny.particle_count(), 10);
    assert!(tiny.density(Vec3::splat(0.5)).is_finite());
}

#[test]
fn sampled_field_marches_to_a_closed_surface() {
    let f = NbodyField::new(5, 50_000);
    let sampled = SampledField {
        field: &f,
        grid: Grid::unit_cube(48),
    };
    let mut edges = std::collections::HashMap::new();
    march(
        &sampled.grid,
        &sampled,
        f.suggested_iso(),
        sampled.grid.all_cells(),
        |t| {
            let v = t.vertices.map(|p| p.map(f32::to_bits));
            for i in 0..3 {
                *edges.entry((v[i], v[(i + 1) % 3])).or_insert(0) += 1;
            }
        },
    );
    assert!(!edges.is_empty());
    for (&(a, b), &n) in &edges {
        assert_eq!(edges.get(&(b, a)), Some(&n), "open edge");
    }
}
