use super::*;

#[test]
fn kernel_names_parse_and_unknown_ones_are_refused() {
    for k in Kernel::ALL {
        assert_eq!(Kernel::parse(k.name()), Ok(k));
    }
    assert_eq!(Kernel::parse(" AVX2 "), Ok(Kernel::Avx2));
    let e = Kernel::parse("avx512").unwrap_err();
    assert!(e.contains("avx2, sse or scalar"), "{e}");
    assert!(Kernel::Scalar.supported());
    assert!(Kernel::detect().supported());
}

/// Triangles whose boxes and centres coincide, or line up on one axis, give the binned SAH
/// nothing to choose from: the SAH builder must still split them (by medians), stay within
/// the depth a file may have, and hold every triangle once.
#[test]
fn the_sah_builder_splits_coincident_and_collinear_triangles() {
    use crate::geometry::PackedTriangle;
    let same = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
    let cases: [Vec<[[f32; 3]; 3]>; 2] = [
        vec![same; 1000],
        (0..1000)
            .map(|i| {
                // Boxes growing geometrically along x: the SAH's best cut is one triangle off.
                let x = 1.01f32.powi(i);
                [[x, 0.0, 0.0], [x * 1.001, 0.0, 0.0], [x, 1.0, 0.0]]
            })
            .collect(),
    ];
    for tris in cases {
        let mut packed: Vec<PackedTriangle> = tris
            .iter()
            .enumerate()
            .map(|(i, v)| PackedTriangle::new(v, i as u64, 0))
            .collect();
        let built = build_with(Builder::Sah, &mut packed);
        let depth = validate(&built.nodes, &built.blocks).unwrap();
        assert!(depth <= MAX_DEPTH);
        let bvh = Bvh::new(&built.nodes, &built.blocks).unwrap();
        let mut ids: Vec<u64> = bvh.triangles().map(|t| t.id()).collect();
        ids.sort_unstable();
        assert_eq!(ids, (0..tris.len() as u64).collect::<Vec<_>>());
        let leaf: Vec<u64> = packed.iter().map(PackedTriangle::id).collect();
        let listed: Vec<u64> = bvh.triangles().map(|t| t.id()).collect();
        assert_eq!(leaf, listed, "the input is reordered into leaf order");
    }
}

#[test]
fn builder_names_parse_and_unknown_ones_are_refused() {
    for b in Builder::ALL {
        assert_eq!(Builder::parse(b.name()), Ok(b));
    }
    assert!(Builder::parse("lbvh").unwrap_err().contains("ploc or sah"));
}

/// `TraceRay::new` computes its three axes in SSE lanes; every field must equal the per-axis
/// scalar form it replaced (the same division and product per axis, the same rows), including
/// zero, negative zero, tiny, huge and infinite components.
#[test]
fn trace_ray_set_up_equals_the_per_axis_form() {
    let values = [
        0.0f32,
        -0.0,
        1e-31,
        -1e-31,
        1e-30,
        -1e-30,
        0.3,
        -0.7,
        1.0,
        -1.0,
        3.4e38,
        -3.4e38,
        f32::INFINITY,
        f32::NEG_INFINITY,
        1.17e-38,
    ];
    let origin = Vec3::new(0.25, -13.5, 1e6);
    for &x in &values {
        for &y in &values {
            for &z in &values {
                let dir = Vec3::new(x, y, z);
                let r = TraceRay::new(origin, dir);
                let d = dir.to_array();
                let o = origin.to_array();
                for a in 0..3 {
                    let safe = if d[a].abs() < 1e-30 {
                        1e-30f32.copysign(d[a])
                    } else {
                        d[a]
                    };
                    let inv = safe.recip();
                    assert_eq!(r.inv[a].to_bits(), inv.to_bits(), "{dir:?} axis {a}");
                    let oi = o[a] * inv;
                    assert_eq!(r.origin_inv[a].to_bits(), oi.to_bits(), "{dir:?} axis {a}");
                    let down = if inv >= 0.0 { 0 } else { 3 };
                    assert_eq!(r.row(a), a + down, "{dir:?} axis {a}");
                    assert_eq!(r.row(3 + a), a + 3 - down, "{dir:?} axis {a}");
                }
            }
        }
    }
}

/// The nearest-hit loop prefetches node `i + 1` whenever it visits node `i`, betting that it is
/// one of `i`'s children: the SAH builder writes nodes depth first, so every node with an inner
/// child has one right after it.
#[test]
fn the_sah_builder_writes_an_inner_child_right_after_its_parent() {
    use crate::geometry::PackedTriangle;
    let mut packed: Vec<PackedTriangle> = (0..4000)
        .map(|i| {
            let (x, y) = ((i % 64) as f32, (i / 64) as f32);
            let z = ((i * 7919) % 101) as f32 * 0.01;
            let v = [[x, y, z], [x + 1.0, y, z], [x, y + 1.0, z + 0.5]];
            PackedTriangle::new(&v, i as u64, 0)
        })
        .collect();
    let built = build_with(Builder::Sah, &mut packed);
    validate(&built.nodes, &built.blocks).unwrap();
    let mut with_inner = 0;
    for (i, n) in built.nodes.iter().enumerate() {
        let inner: Vec<u32> = (0..WIDTH)
            .filter(|&s| n.meta[s] == SLOT_INNER)
            .map(|s| n.child[s])
            .collect();
        if !inner.is_empty() {
            with_inner += 1;
            assert!(
                inner.contains(&(i as u32 + 1)),
                "node {i}: inner children {inner:?}"
            );
        }
    }
    assert!(with_inner > 10, "the test needs a tree of several levels");
}

/// With the `counters` feature, a ray's node visits, leaf visits and block tests are counted.
#[cfg(feature = "counters")]
#[test]
fn counters_count_what_a_ray_touches() {
    use crate::geometry::PackedTriangle;
    let mut packed = vec![PackedTriangle::new(
        &[[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]],
        0,
        0,
    )];
    let built = build_with(Builder::Sah, &mut packed);
    let bvh = Bvh::new(&built.nodes, &built.blocks).unwrap();
    let ray = TraceRay::new(Vec3::new(0.2, 0.2, 0.0), Vec3::Z);
    for kernel in Kernel::ALL.into_iter().filter(|k| k.supported()) {
        counters::take();
        let hit = Traverser::with_kernel(kernel)
            .unwrap()
            .nearest_hit(bvh, &ray, 0.0, 10.0);
        assert!(hit.is_some());
        let c = counters::take();
        assert_eq!((c.nodes, c.leaves, c.blocks), (1, 1, 1), "{kernel:?}");
    }
}
