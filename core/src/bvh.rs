//! The per-domain bounding volume hierarchy. `obvhs` builds a binary tree; we collapse it into
//! a 4-wide tree whose nodes hold their children's boxes side by side (one SIMD lane per
//! child), store it flat in the domain file, and traverse it here with a domain's hit interval
//! and the triangle-id tie-break (which `obvhs`'s own traversal cannot express). Testing four
//! boxes in one go halves the depth and the per-box cost of a binary tree.

use std::time::Duration;

use bytemuck::{Pod, Zeroable};
use glam::{Vec3, Vec3A, Vec4};

use crate::geometry::{PackedTriangle, ShearedRay, nearer};

/// Width of a node.
pub const WIDTH: usize = 4;

/// What a child slot holds, in [`BvhNode::meta`].
pub const SLOT_EMPTY: u32 = 0;
/// An inner child: `child` is a node index.
pub const SLOT_INNER: u32 = u32::MAX;

/// One node of the 4-wide BVH: the four children's boxes as structure-of-arrays, then per
/// child its index and what it is. A leaf child (`meta` = triangle count, 1..) holds
/// triangles `child .. child + meta` of the domain's packed array; an empty slot has a box at
/// +infinity that no ray can enter.
#[repr(C, align(16))]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct BvhNode {
    /// Box minima, one lane per child: x, y, z.
    pub min: [[f32; WIDTH]; 3],
    /// Box maxima, one lane per child: x, y, z.
    pub max: [[f32; WIDTH]; 3],
    /// Node index (inner) or first triangle (leaf) per child.
    pub child: [u32; WIDTH],
    /// [`SLOT_EMPTY`], [`SLOT_INNER`], or a leaf's triangle count.
    pub meta: [u32; WIDTH],
}

const _: () = assert!(std::mem::size_of::<BvhNode>() == 128);

/// Relative padding of every box: the triangle test and the box test round differently, and a
/// box that misses a hit by one ulp would make the nearest hit depend on the tree.
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
    // Four triangles a leaf, one per child lane, measured fastest for 4-wide traversal
    // (README, "Benchmarks").
    params.max_prims_per_leaf = 4;
    let bvh = obvhs::bvh2::builder::build_bvh2_from_tris(&tris, params, &mut Duration::default());
    drop(tris);
    let reordered: Vec<PackedTriangle> = bvh
        .primitive_indices
        .iter()
        .map(|&i| triangles[i as usize])
        .collect();
    *triangles = reordered;
    widen(&bvh.nodes)
}

fn surface_area(n: &obvhs::bvh2::node::Bvh2Node) -> f32 {
    n.aabb.half_area()
}

/// Collapses a binary tree into a 4-wide one: each wide node takes its binary node's two
/// children and keeps opening the largest inner child until it has four.
fn widen(bin: &[obvhs::bvh2::node::Bvh2Node]) -> Vec<BvhNode> {
    let empty = BvhNode {
        min: [[f32::INFINITY; WIDTH]; 3],
        max: [[f32::INFINITY; WIDTH]; 3],
        child: [0; WIDTH],
        meta: [SLOT_EMPTY; WIDTH],
    };
    let mut out = vec![empty];
    // (binary node whose children fill the wide node, wide node index)
    let mut todo = Vec::new();
    if bin[0].prim_count > 0 {
        set_slot(&mut out[0], 0, &bin[0], SLOT_EMPTY);
        out[0].meta[0] = bin[0].prim_count;
        out[0].child[0] = bin[0].first_index;
        return out;
    }
    todo.push((0usize, 0usize));
    while let Some((b, w)) = todo.pop() {
        let first = bin[b].first_index as usize;
        let mut kids = vec![first, first + 1];
        while kids.len() < WIDTH {
            let open = kids
                .iter()
                .enumerate()
                .filter(|(_, k)| bin[**k].prim_count == 0)
                .max_by(|a, b| surface_area(&bin[*a.1]).total_cmp(&surface_area(&bin[*b.1])))
                .map(|(i, _)| i);
            let Some(i) = open else { break };
            let k = kids.swap_remove(i);
            let f = bin[k].first_index as usize;
            kids.extend([f, f + 1]);
        }
        for (slot, &k) in kids.iter().enumerate() {
            let n = &bin[k];
            if n.prim_count > 0 {
                set_slot(&mut out[w], slot, n, n.prim_count);
                out[w].child[slot] = n.first_index;
            } else {
                let index = out.len();
                out.push(empty);
                set_slot(&mut out[w], slot, n, SLOT_INNER);
                out[w].child[slot] = index as u32;
                todo.push((k, index));
            }
        }
    }
    out
}

fn set_slot(node: &mut BvhNode, slot: usize, n: &obvhs::bvh2::node::Bvh2Node, meta: u32) {
    let min = Vec3::from(n.aabb.min);
    let max = Vec3::from(n.aabb.max);
    let pad = (min.abs().max(max.abs()) * BOX_PAD).max(Vec3::splat(1e-30));
    let (lo, hi) = (min - pad, max + pad);
    for a in 0..3 {
        node.min[a][slot] = lo[a];
        node.max[a][slot] = hi[a];
    }
    node.meta[slot] = meta;
}

/// The deepest tree accepted, so a corrupt file cannot make traversal stacks huge.
pub const MAX_DEPTH: usize = 96;

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
        deepest = deepest.max(d);
        if d > MAX_DEPTH {
            return Err(format!("BVH deeper than {MAX_DEPTH}"));
        }
        let n = &nodes[i];
        for slot in 0..WIDTH {
            let c = n.child[slot] as usize;
            match n.meta[slot] {
                SLOT_EMPTY => {}
                SLOT_INNER => {
                    match seen.get_mut(c) {
                        Some(s) if !*s => *s = true,
                        Some(_) => return Err(format!("BVH node {c} is reached twice")),
                        None => {
                            return Err(format!("BVH node {i} names child {c} of {}", nodes.len()));
                        }
                    }
                    todo.push((c, d + 1));
                }
                count => {
                    let end = c + count as usize;
                    if end > triangle_count {
                        return Err(format!(
                            "BVH node {i} names triangles up to {end} of {triangle_count}"
                        ));
                    }
                }
            }
        }
    }
    Ok(deepest)
}

/// A ray prepared for box tests.
#[derive(Clone, Copy)]
pub struct TraceRay {
    sheared: ShearedRay,
    inv: [Vec4; 3],
    origin_inv: [Vec4; 3],
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
        let inv = [
            safe(dir.x).recip(),
            safe(dir.y).recip(),
            safe(dir.z).recip(),
        ];
        TraceRay {
            sheared: ShearedRay::new(origin, dir),
            inv: inv.map(Vec4::splat),
            origin_inv: [0, 1, 2].map(|a| Vec4::splat(origin[a] * inv[a])),
        }
    }

    /// Entry distances into the node's four child boxes within `[t0, t1]`, and a bit mask of
    /// the children that are entered.
    #[inline(always)]
    fn slab4(&self, node: &BvhNode, t0: f32, t1: f32) -> (Vec4, u32) {
        let mut near = Vec4::splat(t0);
        let mut far = Vec4::splat(t1);
        for a in 0..3 {
            // Not `mul_add`: without FMA in the target features it becomes a libm call.
            let lo = Vec4::from(node.min[a]) * self.inv[a] - self.origin_inv[a];
            let hi = Vec4::from(node.max[a]) * self.inv[a] - self.origin_inv[a];
            near = near.max(lo.min(hi));
            far = far.min(lo.max(hi));
        }
        // Empty slots sit at +infinity: their entry is infinite, so `near < inf` drops them.
        let hit = near.cmple(far) & near.cmplt(Vec4::splat(f32::INFINITY));
        (near, hit.bitmask())
    }
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

/// A child to visit: node index or first triangle, its `meta`, and its entry distance.
#[derive(Clone, Copy)]
struct Entry {
    child: u32,
    meta: u32,
    near: f32,
}

/// Traversal state reused across rays: zeroing a fresh stack for every ray cost more than
/// traversing a coherent ray's whole path.
pub struct Traverser {
    stack: Vec<Entry>,
}

impl Default for Traverser {
    fn default() -> Self {
        Self::new()
    }
}

impl Traverser {
    /// A traverser with a stack for trees of [`MAX_DEPTH`].
    pub fn new() -> Self {
        Traverser {
            stack: Vec::with_capacity(MAX_DEPTH * (WIDTH - 1) + 1),
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
        if nodes.is_empty() {
            return None;
        }
        let stack = &mut self.stack;
        stack.clear();
        stack.push(Entry {
            child: 0,
            meta: SLOT_INNER,
            near: t0,
        });
        // Entries keep their entry distance, so a subtree beyond the best hit is skipped unopened;
        // equal distances are still visited, for the id tie-break.
        while let Some(e) = stack.pop() {
            if e.near > best.t {
                continue;
            }
            if e.meta != SLOT_INNER {
                let first = e.child as usize;
                for (k, tri) in tris[first..first + e.meta as usize].iter().enumerate() {
                    let t = tri.intersect_t(&ray.sheared);
                    // A miss is infinity, which must not win against an unbounded t1.
                    if t >= t0 && t != f32::INFINITY && nearer(t, tri.id(), best.t, best.id) {
                        best = Hit {
                            t,
                            slot: (first + k) as u32,
                            id: tri.id(),
                        };
                    }
                }
                continue;
            }
            let node = &nodes[e.child as usize];
            let (near, mut mask) = ray.slab4(node, t0, best.t);
            let near = near.to_array();
            // Push the entered children farthest first, so the nearest is popped next.
            let base = stack.len();
            while mask != 0 {
                let slot = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                let entry = Entry {
                    child: node.child[slot],
                    meta: node.meta[slot],
                    near: near[slot],
                };
                let mut at = stack.len();
                stack.push(entry);
                while at > base && stack[at - 1].near < entry.near {
                    stack[at] = stack[at - 1];
                    at -= 1;
                }
                stack[at] = entry;
            }
        }
        (best.slot != u32::MAX).then_some(best)
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
        let stack = &mut self.stack;
        stack.clear();
        stack.push(Entry {
            child: 0,
            meta: SLOT_INNER,
            near: t0,
        });
        while let Some(e) = stack.pop() {
            if e.meta != SLOT_INNER {
                let first = e.child as usize;
                for tri in &tris[first..first + e.meta as usize] {
                    let t = tri.intersect_t(&ray.sheared);
                    if t >= t0 && t <= t1 && t != f32::INFINITY {
                        return true;
                    }
                }
                continue;
            }
            let node = &nodes[e.child as usize];
            let (_, mut mask) = ray.slab4(node, t0, t1);
            while mask != 0 {
                let slot = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                stack.push(Entry {
                    child: node.child[slot],
                    meta: node.meta[slot],
                    near: 0.0,
                });
            }
        }
        false
    }
}
