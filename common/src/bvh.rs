//! The per-domain bounding volume hierarchy: built with `obvhs`, stored flat in the domain file
//! as plain 32-byte nodes, and traversed here with a domain's hit interval and the
//! triangle-id tie-break (which `obvhs`'s own traversal cannot express).

use std::time::Duration;

use bytemuck::{Pod, Zeroable};
use glam::{BVec4A, Vec3, Vec3A, Vec4};

use crate::geometry::{PackedTriangle, nearer};

/// One node of a binary BVH. Aligned so each half loads as one SIMD register. Inner nodes (`count == 0`) have children at `index` and
/// `index + 1`; leaves hold triangles `index .. index + count` of the domain's packed array.
#[repr(C, align(16))]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct BvhNode {
    /// Box minimum.
    pub min: [f32; 3],
    /// First child (inner) or first triangle (leaf).
    pub index: u32,
    /// Box maximum.
    pub max: [f32; 3],
    /// Triangle count; zero for inner nodes.
    pub count: u32,
}

impl BvhNode {
    /// The box as two SIMD vectors.
    #[inline(always)]
    pub fn bounds(&self) -> (Vec3A, Vec3A) {
        let halves: &[Vec4; 2] = bytemuck::cast_ref(self);
        (xyz(halves[0]), xyz(halves[1]))
    }
}

/// The first three lanes of `v`, the fourth zeroed bitwise: it holds an integer whose bits may
/// read as a denormal float, and arithmetic on denormals is very slow.
#[inline(always)]
pub fn xyz(v: Vec4) -> Vec3A {
    Vec3A::from_vec4(Vec4::select(
        BVec4A::new(true, true, true, false),
        v,
        Vec4::ZERO,
    ))
}

/// Relative padding of every node box: the triangle test and the box test round differently,
/// and a box that misses a hit by one ulp would make the nearest hit depend on the tree.
const BOX_PAD: f32 = 1e-5;

/// Builds the BVH over `triangles` and reorders them into leaf order, so leaves index the
/// packed array directly.
pub fn build(triangles: &mut Vec<PackedTriangle>) -> Vec<BvhNode> {
    if triangles.is_empty() {
        return Vec::new();
    }
    let tris: Vec<obvhs::triangle::Triangle> = triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.vertices();
            obvhs::triangle::Triangle {
                v0: Vec3A::from(a),
                v1: Vec3A::from(b),
                v2: Vec3A::from(c),
            }
        })
        .collect();
    let mut params = obvhs::BvhBuildParams::medium_build();
    // Spatial pre-splits clip references to sub-boxes; our padding argument needs whole-triangle boxes.
    params.pre_split = false;
    let bvh = obvhs::bvh2::builder::build_bvh2_from_tris(&tris, params, &mut Duration::default());
    drop(tris);
    let reordered: Vec<PackedTriangle> = bvh
        .primitive_indices
        .iter()
        .map(|&i| triangles[i as usize])
        .collect();
    *triangles = reordered;
    bvh.nodes
        .iter()
        .map(|n| {
            let min = Vec3::from(n.aabb.min);
            let max = Vec3::from(n.aabb.max);
            let pad = (min.abs().max(max.abs()) * BOX_PAD).max(Vec3::splat(1e-30));
            BvhNode {
                min: (min - pad).into(),
                index: n.first_index,
                max: (max + pad).into(),
                count: n.prim_count,
            }
        })
        .collect()
}

/// A ray prepared for box tests.
#[derive(Clone, Copy)]
pub struct TraceRay {
    origin: Vec3A,
    dir: Vec3A,
    inv_dir: Vec3A,
    origin_inv: Vec3A,
}

impl TraceRay {
    /// Prepares a ray; `dir` need not be normalised.
    #[inline]
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        // A zero component would give 0 * inf = NaN in the slab test; a tiny stand-in keeps every
        // product finite and only moves the (padded) box test, never the triangle test.
        let safe = |d: f32| {
            if d.abs() < 1e-30 {
                1e-30f32.copysign(d)
            } else {
                d
            }
        };
        let inv_dir = Vec3A::new(safe(dir.x), safe(dir.y), safe(dir.z)).recip();
        let origin = Vec3A::from(origin);
        TraceRay {
            origin,
            dir: Vec3A::from(dir),
            inv_dir,
            origin_inv: origin * inv_dir,
        }
    }

    /// Entry distance into the node's box within `[t0, t1]`, or infinity if it is missed.
    #[inline(always)]
    fn slab(&self, node: &BvhNode, t0: f32, t1: f32) -> f32 {
        let (lo, hi) = node.bounds();
        // Not `mul_add`: without FMA in the target features it becomes a libm call.
        let a = lo * self.inv_dir - self.origin_inv;
        let b = hi * self.inv_dir - self.origin_inv;
        // Plain comparisons, not f32::max/min: every operand is finite here, so the NaN
        // handling those carry would be a dozen wasted instructions per box.
        let near = max(a.min(b).max_element(), t0);
        let far = min(a.max(b).min_element(), t1);
        if near <= far { near } else { f32::INFINITY }
    }
}

#[inline(always)]
fn max(a: f32, b: f32) -> f32 {
    if a > b { a } else { b }
}

#[inline(always)]
fn min(a: f32, b: f32) -> f32 {
    if a < b { a } else { b }
}

/// The nearest hit of a ray in a BVH.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance along the ray direction.
    pub t: f32,
    /// Position of the triangle in the domain's packed array.
    pub slot: u32,
    /// Scene-wide triangle id.
    pub id: u64,
}

/// Traversal stack entries; `build` refuses trees deeper than half of this.
const STACK: usize = 256;

/// The deepest tree `build` accepts, so traversal stacks never overflow.
pub const MAX_DEPTH: usize = STACK / 2 - 1;

/// Checks that `nodes` form one tree over `triangle_count` triangles no deeper than
/// [`MAX_DEPTH`], so traversal can index without bounds failures; returns the depth.
pub fn validate(nodes: &[BvhNode], triangle_count: usize) -> Result<usize, String> {
    if nodes.is_empty() {
        return if triangle_count == 0 {
            Ok(0)
        } else {
            Err("triangles without a BVH".into())
        };
    }
    let mut seen = vec![false; nodes.len()];
    seen[0] = true;
    let mut deepest = 0;
    let mut todo = vec![(0usize, 1usize)];
    while let Some((i, d)) = todo.pop() {
        let n = &nodes[i];
        deepest = deepest.max(d);
        if d > MAX_DEPTH {
            return Err(format!("BVH deeper than {MAX_DEPTH}"));
        }
        if n.count > 0 {
            let end = n.index as usize + n.count as usize;
            if end > triangle_count {
                return Err(format!(
                    "BVH node {i} names triangles up to {end} of {triangle_count}"
                ));
            }
            continue;
        }
        for c in [n.index as usize, n.index as usize + 1] {
            match seen.get_mut(c) {
                Some(s) if !*s => *s = true,
                Some(_) => return Err(format!("BVH node {c} is reached twice")),
                None => return Err(format!("BVH node {i} names child {c} of {}", nodes.len())),
            }
            todo.push((c, d + 1));
        }
    }
    Ok(deepest)
}

/// Traversal state reused across rays: zeroing a fresh stack for every ray cost more than
/// traversing a coherent ray's whole path.
pub struct Traverser {
    near_stack: Vec<(u32, f32)>,
    any_stack: Vec<u32>,
}

impl Default for Traverser {
    fn default() -> Self {
        Self::new()
    }
}

impl Traverser {
    /// A traverser with stacks for trees of [`MAX_DEPTH`].
    pub fn new() -> Self {
        Traverser {
            near_stack: Vec::with_capacity(STACK),
            any_stack: Vec::with_capacity(STACK),
        }
    }

    /// Nearest hit with `t0 <= t <= t1`, ties broken by the lower scene-wide id.
    pub fn nearest_hit(
        &mut self,
        nodes: &[BvhNode],
        tris: &[PackedTriangle],
        ray: &TraceRay,
        t0: f32,
        t1: f32,
    ) -> Option<Hit> {
        let mut best = Hit {
            t: t1,
            slot: u32::MAX,
            id: u64::MAX,
        };
        let root = nodes.first()?;
        if ray.slab(root, t0, t1) == f32::INFINITY {
            return None;
        }
        // Each entry keeps its entry distance, so a subtree beyond the best hit is skipped unopened.
        let stack = &mut self.near_stack;
        stack.clear();
        let mut node = root;
        loop {
            if node.count > 0 {
                let first = node.index as usize;
                for (k, tri) in tris[first..first + node.count as usize].iter().enumerate() {
                    let t = tri.intersect_t(ray.origin, ray.dir);
                    // A miss is infinity, which must not win against an unbounded t1.
                    if t >= t0 && t != f32::INFINITY && nearer(t, tri.id(), best.t, best.id) {
                        best = Hit {
                            t,
                            slot: (first + k) as u32,
                            id: tri.id(),
                        };
                    }
                }
            } else {
                let i = node.index as usize;
                // Equal distances must still be visited for the id tie-break: compare with <=.
                let dl = ray.slab(&nodes[i], t0, best.t);
                let dr = ray.slab(&nodes[i + 1], t0, best.t);
                let (near, dn, far, df) = if dl <= dr {
                    (i, dl, i + 1, dr)
                } else {
                    (i + 1, dr, i, dl)
                };
                if dn != f32::INFINITY {
                    if df != f32::INFINITY {
                        stack.push((far as u32, df));
                    }
                    node = &nodes[near];
                    continue;
                }
            }
            loop {
                let Some((n, d)) = stack.pop() else {
                    return (best.slot != u32::MAX).then_some(best);
                };
                if d <= best.t {
                    node = &nodes[n as usize];
                    break;
                }
            }
        }
    }

    /// Whether anything is hit with `t0 <= t <= t1` (shadow rays).
    pub fn any_hit(
        &mut self,
        nodes: &[BvhNode],
        tris: &[PackedTriangle],
        ray: &TraceRay,
        t0: f32,
        t1: f32,
    ) -> bool {
        if nodes.is_empty() {
            return false;
        }
        let stack = &mut self.any_stack;
        stack.clear();
        stack.push(0);
        while let Some(n) = stack.pop() {
            let node = &nodes[n as usize];
            if ray.slab(node, t0, t1) == f32::INFINITY {
                continue;
            }
            if node.count > 0 {
                let first = node.index as usize;
                for tri in &tris[first..first + node.count as usize] {
                    let t = tri.intersect_t(ray.origin, ray.dir);
                    if t >= t0 && t <= t1 {
                        return true;
                    }
                }
            } else {
                stack.push(node.index);
                stack.push(node.index + 1);
            }
        }
        false
    }
}
