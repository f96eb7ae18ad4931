//! The nearest hit found domain by domain equals the nearest hit of one BVH over the whole
//! mesh, ties included: this is what lets a scene be cut into domains without changing a pixel.

use std::ops::ControlFlow;
use std::path::Path;

use glam::Vec3;
use proptest::prelude::*;
use rayfarm_core::bvh::{Hit, Kernel, TraceRay, Traverser};
use rayfarm_core::mesh::TriangleMesh;
use rayfarm_core::prepare::prepare_mesh;
use rayfarm_core::scene::{DomainData, Manifest};

/// Random triangles in the unit cube plus a fan sharing vertices (so ties on shared edges occur).
fn mesh(seed: u64, n: usize) -> TriangleMesh {
    let mut s = seed;
    let mut next = move || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((s >> 40) as f32) / (1u64 << 24) as f32
    };
    let mut m = TriangleMesh::default();
    for _ in 0..n {
        let c = [next(), next(), next()];
        let base = m.positions.len() as u32;
        for _ in 0..3 {
            m.positions
                .push([0, 1, 2].map(|a| c[a] + (next() - 0.5) * 0.2));
        }
        m.triangles.push([base, base + 1, base + 2]);
    }
    // A fan around the cube's center: many triangles share each edge.
    let hub = m.positions.len() as u32;
    m.positions.push([0.5, 0.5, 0.5]);
    for k in 0..24 {
        let a = k as f32 / 24.0 * std::f32::consts::TAU;
        m.positions
            .push([0.5 + 0.4 * a.cos(), 0.5 + 0.4 * a.sin(), 0.5]);
    }
    for k in 0..24u32 {
        m.triangles.push([hub, hub + 1 + k, hub + 1 + (k + 1) % 24]);
    }
    m
}

struct Loaded {
    manifest: Manifest,
    domains: Vec<DomainData>,
}

fn load(dir: &Path) -> Loaded {
    let manifest = Manifest::load(dir).unwrap();
    let domains = (0..manifest.domains.len() as u32)
        .map(|d| manifest.open_domain(dir, d, true).unwrap())
        .collect();
    Loaded { manifest, domains }
}

/// The kernels this CPU runs: every test below holds on each.
fn kernels() -> Vec<Kernel> {
    Kernel::ALL.into_iter().filter(|k| k.supported()).collect()
}

fn traverser(k: Kernel) -> Traverser {
    Traverser::with_kernel(k).unwrap()
}

/// Distance bits and id: kernels must agree to the bit, not within a tolerance.
fn bits(hit: Option<(f32, u64)>) -> Option<(u32, u64)> {
    hit.map(|(t, id)| (t.to_bits(), id))
}

fn by_domains(s: &Loaded, o: Vec3, d: Vec3, k: Kernel) -> Option<(f32, u64)> {
    let tree = s.manifest.domain_tree();
    let ray = TraceRay::new(o, d);
    let mut found = None;
    tree.walk(o, d, 0.0, f32::INFINITY, |dom, a, b| {
        let data = &s.domains[dom as usize];
        match traverser(k).nearest_hit(data.bvh(), &ray, a, b) {
            Some(Hit { t, id, .. }) => {
                found = Some((t, id));
                ControlFlow::Break(())
            }
            None => ControlFlow::Continue(()),
        }
    });
    found
}

fn whole(s: &Loaded, o: Vec3, d: Vec3, k: Kernel) -> Option<(f32, u64)> {
    let data = &s.domains[0];
    traverser(k)
        .nearest_hit(data.bvh(), &TraceRay::new(o, d), 0.0, f32::INFINITY)
        .map(|h| (h.t, h.id))
}

fn scenes() -> (tempfile::TempDir, Loaded, Vec<Loaded>) {
    let tmp = tempfile::tempdir().unwrap();
    let m = mesh(7, 3000);
    let one = tmp.path().join("d1");
    prepare_mesh(&m, "t", &one, 1, false).unwrap();
    let many = [8u32, 27, 64]
        .iter()
        .map(|&n| {
            let p = tmp.path().join(format!("d{n}"));
            prepare_mesh(&m, "t", &p, n, false).unwrap();
            load(&p)
        })
        .collect();
    let one = load(&one);
    (tmp, one, many)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    #[test]
    fn domain_by_domain_nearest_hit_equals_whole_mesh(seed in any::<u64>()) {
        thread_local! {
            static SCENES: (tempfile::TempDir, Loaded, Vec<Loaded>) = scenes();
        }
        SCENES.with(|(_, one, many)| {
            let mut s = seed | 1;
            let mut next = move || {
                s ^= s << 13; s ^= s >> 7; s ^= s << 17;
                ((s >> 40) as f32) / (1u64 << 24) as f32
            };
            let mut hits = 0;
            for _ in 0..500 {
                // Origins inside and outside the mesh, directions everywhere, some axis-aligned.
                let o = Vec3::new(next(), next(), next()) * 1.6 - 0.3;
                let mut d = Vec3::new(next(), next(), next()) * 2.0 - 1.0;
                if next() < 0.1 { d = Vec3::new(d.x, 0.0, 0.0); }
                if next() < 0.1 { d.z = 0.0; }
                if d.length_squared() < 1e-6 { continue; }
                let d = d.normalize();
                let expect = whole(one, o, d, Kernel::Scalar);
                hits += expect.is_some() as usize;
                for k in kernels() {
                    prop_assert_eq!(bits(whole(one, o, d, k)), bits(expect), "{:?} o={:?} d={:?}", k, o, d);
                    let data = &one.domains[0];
                    let blocked = traverser(k).any_hit(data.bvh(), &TraceRay::new(o, d), 0.0, f32::INFINITY);
                    prop_assert_eq!(blocked, expect.is_some(), "{:?} any-hit o={:?} d={:?}", k, o, d);
                    for s in many {
                        prop_assert_eq!(bits(by_domains(s, o, d, k)), bits(expect), "{:?}, {} domains, o={:?} d={:?}", k, s.domains.len(), o, d);
                    }
                }
            }
            prop_assert!(hits > 50);
            Ok(())
        })?;
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(32))]
    /// Packets give single rays' hits to the bit on every kernel, and single shadow rays are
    /// blocked exactly where a nearest hit exists: rays from one origin through a small cone (coherent, as camera rays) and scattered ones (a packet that diverges at
    /// once), each with its own interval, in runs that end in a partial packet.
    #[test]
    fn packets_find_the_single_ray_nearest_hits(seed in any::<u64>()) {
        thread_local! {
            static SCENES: (tempfile::TempDir, Loaded, Vec<Loaded>) = scenes();
        }
        SCENES.with(|(_, one, _)| {
            let mut s = seed | 1;
            let mut next = move || {
                s ^= s << 13; s ^= s >> 7; s ^= s << 17;
                ((s >> 40) as f32) / (1u64 << 24) as f32
            };
            let bvh = one.domains[0].bvh();
            let mut hits = 0;
            for spread in [0.02f32, 0.3, 2.0] {
                let o = Vec3::new(next(), next(), next()) * 1.6 - 0.3;
                let centre = Vec3::new(0.5, 0.5, 0.5) - o;
                let (mut rays, mut t0, mut t1) = (Vec::new(), Vec::new(), Vec::new());
                for _ in 0..61 {
                    let j = Vec3::new(next(), next(), next()) * 2.0 - 1.0;
                    let d = (centre.normalize_or(Vec3::X) + j * spread).normalize_or(Vec3::Y);
                    rays.push(TraceRay::new(o, d));
                    let a = if next() < 0.3 { next() * 0.5 } else { 0.0 };
                    t0.push(a);
                    t1.push(if next() < 0.3 { a + next() } else { f32::INFINITY });
                }
                for k in kernels() {
                    let mut single = traverser(k);
                    let expect: Vec<_> = (0..rays.len())
                        .map(|i| single.nearest_hit(bvh, &rays[i], t0[i], t1[i]))
                        .collect();
                    let mut packed = traverser(k);
                    packed.set_packets(true);
                    let mut out = vec![None; rays.len()];
                    packed.nearest_hits(bvh, &rays, &t0, &t1, &mut out);
                    prop_assert_eq!(&out, &expect, "{:?}, spread {}", k, spread);
                    hits += expect.iter().flatten().count();
                    // Shadow rays: blocked exactly when the ray has a nearest hit in its
                    // interval.
                    let blocked: Vec<bool> = (0..rays.len())
                        .map(|i| single.any_hit(bvh, &rays[i], t0[i], t1[i]))
                        .collect();
                    let hit: Vec<bool> = expect.iter().map(Option::is_some).collect();
                    prop_assert_eq!(&blocked, &hit, "{:?} any-hit against hits, spread {}", k, spread);
                }
            }
            prop_assert!(hits > 0);
            Ok(())
        })?;
    }
}
