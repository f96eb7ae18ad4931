//! Marching cubes: watertight, oriented, canonical across sub-boxes, smooth normals.

use super::cases::lies_in_a_face;
use super::*;
use proptest::prelude::*;
use std::cell::Cell as StdCell;
use std::collections::HashMap;

type Key = [u32; 3];

fn bits(p: [f32; 3]) -> Key {
    p.map(f32::to_bits)
}

fn collect(
    grid: &Grid,
    lattice: &impl Lattice,
    iso: f32,
    cells: [Range<u32>; 3],
) -> Vec<IsoTriangle> {
    let mut out = Vec::new();
    march(grid, lattice, iso, cells, |t| out.push(t));
    out
}

/// Sorted (id, vertex bits), the form in which two runs must agree exactly.
fn keyed(tris: &[IsoTriangle]) -> Vec<(u64, [Key; 3])> {
    let mut v: Vec<_> = tris.iter().map(|t| (t.id, t.vertices.map(bits))).collect();
    v.sort_unstable();
    v
}

fn directed_edges(tris: &[IsoTriangle]) -> HashMap<(Key, Key), u32> {
    let mut edges = HashMap::new();
    for t in tris {
        let v = t.vertices.map(bits);
        for i in 0..3 {
            *edges.entry((v[i], v[(i + 1) % 3])).or_insert(0) += 1;
        }
    }
    edges
}

/// Closed 2-manifold, consistently oriented: each edge is used once in
/// each direction, i.e. by exactly two triangles.
fn assert_closed_manifold(tris: &[IsoTriangle]) {
    let edges = directed_edges(tris);
    for (&(a, b), &n) in &edges {
        assert_eq!(n, 1, "edge {a:?}->{b:?} used {n} times");
        assert_eq!(
            edges.get(&(b, a)),
            Some(&1),
            "edge {a:?}->{b:?} has no twin"
        );
    }
}

/// Closed and consistently oriented, allowing surfaces that touch along
/// edges (possible where samples equal iso or triangles lie in a face).
fn assert_balanced(tris: &[IsoTriangle]) {
    let edges = directed_edges(tris);
    for (&(a, b), &n) in &edges {
        assert_ne!(a, b, "degenerate edge");
        assert_eq!(
            edges.get(&(b, a)).copied().unwrap_or(0),
            n,
            "unbalanced edge {a:?}->{b:?}"
        );
    }
}

fn to_vec3(p: [f32; 3]) -> Vec3 {
    Vec3::from_array(p)
}

fn area(tris: &[IsoTriangle]) -> f64 {
    tris.iter()
        .map(|t| {
            let [a, b, c] = t.vertices.map(to_vec3);
            f64::from((b - a).cross(c - a).length()) * 0.5
        })
        .sum()
}

/// Volume enclosed, positive when normals point outward. In f64 about the
/// first vertex, as tiny blobs far from the origin cancel badly in f32.
fn signed_volume(tris: &[IsoTriangle]) -> f64 {
    let Some(first) = tris.first() else {
        return 0.0;
    };
    let reference = first.vertices[0].map(f64::from);
    let rel = |p: [f32; 3]| [0, 1, 2].map(|i| f64::from(p[i]) - reference[i]);
    tris.iter()
        .map(|t| {
            let [a, b, c] = t.vertices.map(rel);
            let cross = [
                b[1] * c[2] - b[2] * c[1],
                b[2] * c[0] - b[0] * c[2],
                b[0] * c[1] - b[1] * c[0],
            ];
            (a[0] * cross[0] + a[1] * cross[1] + a[2] * cross[2]) / 6.0
        })
        .sum()
}

struct Sphere {
    grid: Grid,
    center: Vec3,
    radius: f32,
}

impl Lattice for Sphere {
    fn value(&self, i: u32, j: u32, k: u32) -> f32 {
        self.radius - self.grid.point(i, j, k).distance(self.center)
    }
}

fn sphere(n: u32) -> Sphere {
    Sphere {
        grid: Grid::unit_cube(n),
        center: Vec3::new(0.503, 0.498, 0.507),
        radius: 0.35,
    }
}

/// Samples from a table, x fastest.
struct Table {
    dims: [u32; 3],
    values: Vec<f32>,
}

impl Lattice for Table {
    fn value(&self, i: u32, j: u32, k: u32) -> f32 {
        let [nx, ny, _] = self.dims;
        self.values[(i + nx * (j + ny * k)) as usize]
    }
}

/// Surrounds `inner` (dims `d`) with a one-point border below any iso used,
/// so the surface cannot reach the grid's boundary and must be closed.
fn padded(d: [u32; 3], inner: &[f32]) -> (Grid, Table) {
    let dims = d.map(|n| n + 2);
    let mut values = vec![-1000.0; dims.iter().product::<u32>() as usize];
    for k in 0..d[2] {
        for j in 0..d[1] {
            for i in 0..d[0] {
                let dst = (i + 1) + dims[0] * ((j + 1) + dims[1] * (k + 1));
                values[dst as usize] = inner[(i + d[0] * (j + d[1] * k)) as usize];
            }
        }
    }
    let grid = Grid {
        origin: Vec3::new(-1.0, 2.0, 0.5),
        spacing: Vec3::new(0.5, 0.25, 1.0),
        dims,
    };
    (grid, Table { dims, values })
}

/// Splits each axis' cells at the given cut points (clamped into range)
/// and marches the resulting sub-boxes separately.
fn collect_split(
    grid: &Grid,
    lattice: &impl Lattice,
    iso: f32,
    cuts: [u32; 3],
) -> Vec<IsoTriangle> {
    let halves = |n: u32, cut: u32| {
        let c = cut.min(n);
        [0..c, c..n]
    };
    let [cx, cy, cz] = grid.cell_dims();
    let mut out = Vec::new();
    for x in halves(cx, cuts[0]) {
        for y in halves(cy, cuts[1]) {
            for z in halves(cz, cuts[2]) {
                out.extend(collect(grid, lattice, iso, [x.clone(), y.clone(), z]));
            }
        }
    }
    out
}

#[test]
fn tables_are_self_consistent() {
    assert_eq!(CASES[0].count, 0);
    assert_eq!(CASES[255].count, 0);
    for (config, case) in CASES.iter().enumerate() {
        let mut used = 0u16;
        for tri in &case.tris[..usize::from(case.count)] {
            for &e in tri {
                assert!(
                    case.edge_mask & (1 << e) != 0,
                    "config {config}: uncrossed edge {e}"
                );
                used |= 1 << e;
            }
        }
        assert_eq!(used, case.edge_mask, "config {config}: crossed edge unused");
    }
    assert_eq!(CASES[1].count, 1);
    let flat = CASES
        .iter()
        .flat_map(|c| c.tris[..usize::from(c.count)].iter())
        .filter(|t| lies_in_a_face(t.map(usize::from)))
        .count();
    assert_eq!(flat, 0, "triangles lying in a cell face");
}

#[test]
fn single_corner_normal_points_to_lower_values() {
    let (grid, table) = padded([1, 1, 1], &[1.0]);
    let tris = collect(&grid, &table, 0.0, grid.all_cells());
    assert_eq!(tris.len(), 8);
    assert!(signed_volume(&tris) > 0.0);
    assert_closed_manifold(&tris);
}

#[test]
fn sphere_is_closed_with_expected_area_and_volume() {
    let s = sphere(48);
    let tris = collect(&s.grid, &s, 0.0, s.grid.all_cells());
    assert_closed_manifold(&tris);
    let r = f64::from(s.radius);
    let expected_area = 4.0 * std::f64::consts::PI * r * r;
    let rel = (area(&tris) - expected_area).abs() / expected_area;
    assert!(rel < 0.01, "area off by {rel}");
    let expected_volume = 4.0 / 3.0 * std::f64::consts::PI * r * r * r;
    let rel = (signed_volume(&tris) - expected_volume).abs() / expected_volume;
    assert!(rel < 0.01, "volume off by {rel} (or normals point inward)");
}

#[test]
fn whole_grid_equals_eight_sub_boxes() {
    let s = sphere(33);
    let whole = collect(&s.grid, &s, 0.0, s.grid.all_cells());
    let split = collect_split(&s.grid, &s, 0.0, [13, 20, 7]);
    assert!(!whole.is_empty());
    assert_eq!(keyed(&whole), keyed(&split));
    let mut ids: Vec<u64> = whole.iter().map(|t| t.id).collect();
    ids.sort_unstable();
    ids.dedup();
    assert_eq!(ids.len(), whole.len(), "ids are not unique");
}

#[test]
fn smooth_normals_of_a_sphere_point_radially_outward() {
    let s = sphere(40);
    let mut tris = Vec::new();
    march_smooth(&s.grid, &s, 0.0, s.grid.all_cells(), |t| tris.push(t));
    assert!(!tris.is_empty());
    let mut worst = 1.0f32;
    for t in &tris {
        let normals = t.normals.expect("march_smooth gives normals");
        for (v, n) in t.vertices.iter().zip(normals) {
            let radial = (to_vec3(*v) - s.center).normalize();
            let n = to_vec3(n);
            assert!((n.length() - 1.0).abs() < 1e-5, "not unit: {n}");
            worst = worst.min(n.dot(radial));
        }
    }
    // Central differences of a distance field, interpolated along an edge: within a few
    // degrees of the true normal at this resolution (flat facets are off by ~10).
    assert!(
        worst > 0.995,
        "a normal is {} degrees off radial",
        worst.acos().to_degrees()
    );
    // Plain marching gives none, and the same triangles.
    let flat = collect(&s.grid, &s, 0.0, s.grid.all_cells());
    assert!(flat.iter().all(|t| t.normals.is_none()));
    assert_eq!(keyed(&flat), keyed(&tris));
}

#[test]
fn smooth_normals_follow_anisotropic_spacing() {
    // A plane tilted 45 degrees in world space, sampled on a grid twice as coarse in z:
    // value = x - z in world units, so the normal is (-1, 0, 1) / sqrt 2 whatever the
    // spacing (in lattice units it would lean towards z).
    let grid = Grid {
        origin: Vec3::ZERO,
        spacing: Vec3::new(0.5, 0.5, 1.0),
        dims: [12, 6, 8],
    };
    struct Tilted(Grid);
    impl Lattice for Tilted {
        fn value(&self, i: u32, j: u32, k: u32) -> f32 {
            let p = self.0.point(i, j, k);
            p.x - p.z + 0.3
        }
    }
    let want = Vec3::new(-1.0, 0.0, 1.0).normalize();
    let mut n = 0;
    march_smooth(&grid, &Tilted(grid), 0.0, grid.all_cells(), |t| {
        for v in t.normals.unwrap() {
            assert!(to_vec3(v).dot(want) > 0.9999, "{v:?}");
            n += 1;
        }
    });
    assert!(n > 0);
}

#[test]
fn smooth_normals_are_the_same_in_every_sub_box() {
    let s = sphere(33);
    let normals = |cells: [Range<u32>; 3], out: &mut Vec<(u64, [[u32; 3]; 3])>| {
        march_smooth(&s.grid, &s, 0.0, cells, |t| {
            out.push((t.id, t.normals.unwrap().map(bits)));
        });
    };
    let mut whole = Vec::new();
    normals(s.grid.all_cells(), &mut whole);
    let mut split = Vec::new();
    for x in [0..13, 13..32] {
        for y in [0..20, 20..32] {
            for z in [0..7, 7..32] {
                normals([x.clone(), y.clone(), z], &mut split);
            }
        }
    }
    whole.sort_unstable();
    split.sort_unstable();
    assert!(!whole.is_empty());
    assert_eq!(whole, split);
    // A vertex shared by triangles of different cells has one normal: every (position,
    // normal) pair agrees on the normal for the position.
    let mut by_vertex: HashMap<Key, [u32; 3]> = HashMap::new();
    march_smooth(&s.grid, &s, 0.0, s.grid.all_cells(), |t| {
        for (v, n) in t.vertices.iter().zip(t.normals.unwrap()) {
            let prev = by_vertex.entry(bits(*v)).or_insert(bits(n));
            assert_eq!(*prev, bits(n), "vertex {v:?} has two normals");
        }
    });
}

#[test]
fn gradient_is_one_sided_on_the_faces_and_zero_across_a_flat_grid() {
    let grid = Grid {
        origin: Vec3::ZERO,
        spacing: Vec3::new(2.0, 1.0, 1.0),
        dims: [4, 3, 1],
    };
    struct Squares;
    impl Lattice for Squares {
        fn value(&self, i: u32, j: u32, _k: u32) -> f32 {
            (i * i) as f32 + 10.0 * j as f32
        }
    }
    // x: (1 - 0) / 2 at the face, (4 - 0) / (2 * 2) inside, (9 - 4) / 2 at the far face.
    assert_eq!(gradient_at(&grid, &Squares, [0, 0, 0]), [0.5, 10.0, 0.0]);
    assert_eq!(gradient_at(&grid, &Squares, [1, 1, 0]), [1.0, 10.0, 0.0]);
    assert_eq!(gradient_at(&grid, &Squares, [3, 2, 0]), [2.5, 10.0, 0.0]);
}

#[test]
fn every_pair_of_adjacent_cells_is_watertight() {
    for axis in 0..3 {
        let mut d = [2u32; 3];
        d[axis] = 3;
        for config in 0u32..1 << 12 {
            let inner: Vec<f32> = (0..12)
                .map(|c| {
                    let jitter = ((c * 7 + config as usize) % 5) as f32 * 0.1;
                    if config >> c & 1 == 1 {
                        1.0 + jitter
                    } else {
                        -1.0 - jitter
                    }
                })
                .collect();
            let (grid, table) = padded(d, &inner);
            assert_closed_manifold(&collect(&grid, &table, 0.0, grid.all_cells()));
        }
    }
}

#[test]
fn samples_each_point_of_the_sub_box_once() {
    struct Counting(StdCell<u64>);
    impl Lattice for Counting {
        fn value(&self, i: u32, j: u32, k: u32) -> f32 {
            self.0.set(self.0.get() + 1);
            (i + j + k) as f32
        }
    }
    let grid = Grid::unit_cube(20);
    let lattice = Counting(StdCell::new(0));
    march(&grid, &lattice, 10.5, [2..7, 0..19, 5..9], |_| {});
    assert_eq!(lattice.0.get(), 6 * 20 * 5);
}

#[test]
fn empty_range_emits_nothing() {
    let s = sphere(10);
    assert!(collect(&s.grid, &s, 0.0, [3..3, 0..9, 0..9]).is_empty());
}

#[test]
#[should_panic(expected = "exceeds")]
fn range_past_the_grid_panics() {
    let s = sphere(10);
    collect(&s.grid, &s, 0.0, [0..10, 0..9, 0..9]);
}

#[test]
fn exact_iso_samples_emit_no_degenerate_triangles() {
    // Integer samples with iso 0 put many vertices exactly on lattice points.
    let d = [4u32, 5, 3];
    let inner: Vec<f32> = (0..60)
        .map(|n| [0.0, 1.0, -1.0, 0.0, 1.0][(n * 7 + n / 3) % 5])
        .collect();
    let (grid, table) = padded(d, &inner);
    let tris = collect(&grid, &table, 0.0, grid.all_cells());
    assert!(!tris.is_empty());
    assert!(tris.iter().all(|t| has_area(&t.vertices)));
    assert_balanced(&tris);
}

fn field_strategy(
    levels: std::ops::Range<i32>,
) -> impl Strategy<Value = ([u32; 3], Vec<f32>, [u32; 3])> {
    (1u32..6, 1u32..6, 1u32..6).prop_flat_map(move |(x, y, z)| {
        let n = (x * y * z) as usize;
        (
            Just([x, y, z]),
            proptest::collection::vec(levels.clone().prop_map(|v| v as f32), n),
            (0u32..8, 0u32..8, 0u32..8).prop_map(|(a, b, c)| [a, b, c]),
        )
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn random_fields_are_closed_and_split_invariant((d, values, cuts) in field_strategy(-9..10)) {
        // Half-integer iso never equals a sample: the generic case.
        let (grid, table) = padded(d, &values);
        let whole = collect(&grid, &table, 0.5, grid.all_cells());
        assert_closed_manifold(&whole);
        prop_assert_eq!(keyed(&whole), keyed(&collect_split(&grid, &table, 0.5, cuts)));
        let mut ids: Vec<u64> = whole.iter().map(|t| t.id).collect();
        ids.sort_unstable();
        ids.dedup();
        prop_assert_eq!(ids.len(), whole.len());
        prop_assert!(signed_volume(&whole) > 0.0 || whole.is_empty());
    }

    #[test]
    fn fields_hitting_iso_exactly_stay_closed((d, values, cuts) in field_strategy(-1..2)) {
        let (grid, table) = padded(d, &values);
        let whole = collect(&grid, &table, 0.0, grid.all_cells());
        prop_assert!(whole.iter().all(|t| has_area(&t.vertices)));
        assert_balanced(&whole);
        prop_assert_eq!(keyed(&whole), keyed(&collect_split(&grid, &table, 0.0, cuts)));
    }
}
