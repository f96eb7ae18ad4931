//! The triangle test is watertight: a ray through a shared edge or vertex of a closed mesh
//! always hits one of the triangles that share it, so surfaces have no pinholes.

use glam::Vec3;
use rayfarm_core::bvh::{self, Builder, Bvh, Kernel, TraceRay, Traverser};
use rayfarm_core::geometry::{PackedTriangle, nearer};

/// A closed, subdivided octahedron: every edge is shared by two triangles with identical bits.
fn closed_mesh(levels: u32) -> Vec<[[f32; 3]; 3]> {
    let p = [Vec3::X, Vec3::Y, Vec3::Z, -Vec3::X, -Vec3::Y, -Vec3::Z];
    let mut tris: Vec<[Vec3; 3]> = vec![
        [p[0], p[1], p[2]],
        [p[1], p[3], p[2]],
        [p[3], p[4], p[2]],
        [p[4], p[0], p[2]],
        [p[1], p[0], p[5]],
        [p[3], p[1], p[5]],
        [p[4], p[3], p[5]],
        [p[0], p[4], p[5]],
    ];
    for _ in 0..levels {
        // Midpoints are computed from the two end points in a fixed order, so both triangles
        // of an edge get the same bits.
        let mid = |a: Vec3, b: Vec3| {
            let (lo, hi) = if a.to_array() < b.to_array() {
                (a, b)
            } else {
                (b, a)
            };
            ((lo + hi) * 0.5).normalize() * 1.3
        };
        tris = tris
            .iter()
            .flat_map(|&[a, b, c]| {
                let (ab, bc, ca) = (mid(a, b), mid(b, c), mid(c, a));
                [[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]
            })
            .collect();
    }
    tris.iter().map(|t| t.map(|v| v.to_array())).collect()
}

#[test]
fn rays_through_vertices_and_edges_of_a_closed_mesh_never_escape() {
    let mesh = closed_mesh(4);
    let packed: Vec<PackedTriangle> = mesh
        .iter()
        .enumerate()
        .map(|(i, t)| PackedTriangle::new(t, i as u64, 0))
        .collect();
    let origins = [
        Vec3::ZERO,
        Vec3::new(0.1, -0.05, 0.02),
        Vec3::new(-0.3, 0.2, 0.1),
    ];
    let mut targets = Vec::new();
    for t in &mesh {
        let [a, b, c] = t.map(Vec3::from);
        targets.extend([a, b, c, (a + b) * 0.5, (b + c) * 0.5, (c + a) * 0.5]);
    }
    let mut escaped = 0;
    for o in origins {
        for &target in &targets {
            let d = (target - o).normalize();
            if !packed.iter().any(|t| t.intersect(o, d).is_some()) {
                escaped += 1;
            }
        }
    }
    assert_eq!(
        escaped,
        0,
        "{escaped} of {} rays slipped through an edge or vertex",
        targets.len() * origins.len()
    );
}

/// The same rays through the BVH of every builder on every traversal kernel: each finds a hit,
/// any-hit agrees, and the hit is the brute-force nearest (ties to the lower id) to the bit,
/// whichever tree holds the triangles.
#[test]
fn every_kernel_finds_the_brute_force_nearest_hit_through_vertices_and_edges() {
    let mesh = closed_mesh(4);
    let original: Vec<PackedTriangle> = mesh
        .iter()
        .enumerate()
        .map(|(i, t)| PackedTriangle::new(t, i as u64, 0))
        .collect();
    let trees = Builder::ALL.map(|builder| {
        let mut packed = original.clone();
        (builder, bvh::build_with(builder, &mut packed))
    });
    let origins = [
        Vec3::ZERO,
        Vec3::new(0.1, -0.05, 0.02),
        Vec3::new(-0.3, 0.2, 0.1),
    ];
    let mut checked = 0;
    for (builder, built) in &trees {
        let tree = Bvh::new(&built.nodes, &built.blocks).unwrap();
        for kernel in Kernel::ALL.into_iter().filter(|k| k.supported()) {
            let mut traverser = Traverser::with_kernel(kernel).unwrap();
            for o in origins {
                for t in &mesh {
                    let [a, b, c] = t.map(Vec3::from);
                    for target in [a, b, c, (a + b) * 0.5, (b + c) * 0.5, (c + a) * 0.5] {
                        let d = (target - o).normalize();
                        let mut expect: Option<(f32, u64)> = None;
                        for tri in &original {
                            if let Some(t) = tri.intersect(o, d) {
                                let (bt, bid) = expect.unwrap_or((f32::INFINITY, u64::MAX));
                                if nearer(t, tri.id(), bt, bid) {
                                    expect = Some((t, tri.id()));
                                }
                            }
                        }
                        let ray = TraceRay::new(o, d);
                        let got = traverser
                            .nearest_hit(tree, &ray, 0.0, f32::INFINITY)
                            .map(|h| (h.t.to_bits(), h.id));
                        assert_eq!(
                            got,
                            expect.map(|(t, id)| (t.to_bits(), id)),
                            "{builder:?} {kernel:?} o={o:?} d={d:?}"
                        );
                        assert!(got.is_some(), "{kernel:?}: o={o:?} d={d:?} escaped");
                        assert!(traverser.any_hit(tree, &ray, 0.0, f32::INFINITY));
                        checked += 1;
                    }
                }
            }
        }
    }
    assert!(checked > 0);
}

/// The same rays as packets (each origin's rays through neighbouring vertices and edges, eight
/// at a time, the last packet partial) on every kernel: each finds the brute-force nearest hit
/// to the bit, as a single ray does, with packets on and off.
#[test]
fn every_kernel_s_packets_find_the_brute_force_nearest_hit_through_vertices_and_edges() {
    let mesh = closed_mesh(4);
    let original: Vec<PackedTriangle> = mesh
        .iter()
        .enumerate()
        .map(|(i, t)| PackedTriangle::new(t, i as u64, 0))
        .collect();
    let mut packed = original.clone();
    let built = bvh::build(&mut packed);
    let tree = Bvh::new(&built.nodes, &built.blocks).unwrap();
    let origins = [
        Vec3::ZERO,
        Vec3::new(0.1, -0.05, 0.02),
        Vec3::new(-0.3, 0.2, 0.1),
    ];
    for kernel in Kernel::ALL.into_iter().filter(|k| k.supported()) {
        for packets in [true, false] {
            let mut traverser = Traverser::with_kernel(kernel).unwrap();
            traverser.set_packets(packets);
            for o in origins {
                let mut rays = Vec::new();
                let mut expect = Vec::new();
                // 9 targets short of a multiple of 8: the last packet is partial.
                for t in mesh.iter().skip(3) {
                    let [a, b, c] = t.map(Vec3::from);
                    for target in [a, b, c, (a + b) * 0.5, (b + c) * 0.5, (c + a) * 0.5] {
                        let d = (target - o).normalize();
                        let mut best: Option<(f32, u64)> = None;
                        for tri in &original {
                            if let Some(t) = tri.intersect(o, d) {
                                let (bt, bid) = best.unwrap_or((f32::INFINITY, u64::MAX));
                                if nearer(t, tri.id(), bt, bid) {
                                    best = Some((t, tri.id()));
                                }
                            }
                        }
                        rays.push(TraceRay::new(o, d));
                        expect.push(best.map(|(t, id)| (t.to_bits(), id)));
                    }
                }
                assert_ne!(rays.len() % bvh::PACKET, 0);
                let t0 = vec![0.0; rays.len()];
                let t1 = vec![f32::INFINITY; rays.len()];
                let mut out = vec![None; rays.len()];
                traverser.nearest_hits(tree, &rays, &t0, &t1, &mut out);
                let got: Vec<_> = out
                    .iter()
                    .map(|h| h.map(|h| (h.t.to_bits(), h.id)))
                    .collect();
                assert_eq!(got, expect, "{kernel:?}, packets {packets}, o={o:?}");
                assert!(got.iter().all(Option::is_some), "{kernel:?}: a ray escaped");
            }
        }
    }
}
