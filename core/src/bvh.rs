//! The per-domain bounding volume hierarchy. `obvhs` builds a binary tree; we collapse it into
//! an 8-wide tree whose nodes hold their children's boxes side by side (one SIMD lane per
//! child), with leaves of [`TriangleBlock`]s (four triangles as structure-of-arrays), store
//! both flat in the domain file, and traverse them here with a domain's hit interval and the
//! triangle-id tie-break (which `obvhs`'s own traversal cannot express).
//!
//! Three kernels traverse the same tree: AVX2 + FMA (all eight boxes of a node in one
//! register), SSE (two halves of four) and scalar (one box at a time), chosen at run time by
//! [`Kernel::selected`] and forced with `RAYFARM_KERNEL=avx2|sse|scalar`. Every kernel finds
//! the same nearest hit to the bit: the triangle test has the same operations in every lane
//! and kernel, the boxes are padded so that no rounding of the box test (FMA or not) can drop
//! the subtree holding a hit, and ties are broken by the scene-wide triangle id, so the
//! visiting order, which differs between kernels, never decides the winner.

use std::sync::OnceLock;
use std::time::Duration;

use bytemuck::{Pod, Zeroable};
use glam::{Vec3, Vec3A};

use crate::geometry::{Aabb, BLOCK, PackedTriangle, ShearedRay, TriangleBlock, nearer};

mod packet;

pub use packet::PACKET;
use packet::{PacketStack, nearest_packet};

/// Width of a node.
pub const WIDTH: usize = 8;

/// What a child slot holds, in [`BvhNode::meta`].
pub const SLOT_EMPTY: u32 = 0;
/// An inner child: `child` is a node index.
pub const SLOT_INNER: u32 = u32::MAX;

/// Most triangles in one leaf of a built tree (two blocks).
pub const MAX_LEAF_TRIANGLES: u32 = 8;
/// Most blocks a leaf may name in a file, so a corrupt file cannot make one leaf huge.
pub const MAX_LEAF_BLOCKS: u32 = 16;

/// One node of the 8-wide BVH: the eight children's boxes as structure-of-arrays (`bounds[0..3]`
/// minima x, y, z; `bounds[3..6]` maxima), then per child its index and what it is. A leaf
/// child (`meta` = block count, 1..) holds blocks `child .. child + meta` of the domain's
/// block array; an empty slot has an inverted box (minimum +inf, maximum -inf) that no ray
/// can enter.
#[repr(C, align(64))]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct BvhNode {
    /// Box minima (x, y, z) then maxima (x, y, z), one lane per child.
    pub bounds: [[f32; WIDTH]; 6],
    /// Node index (inner) or first block (leaf) per child.
    pub child: [u32; WIDTH],
    /// [`SLOT_EMPTY`], [`SLOT_INNER`], or a leaf's block count.
    pub meta: [u32; WIDTH],
}

const _: () = assert!(std::mem::size_of::<BvhNode>() == 256);

/// Relative padding of every box: the triangle test and the box test round differently, and a
/// box that misses a hit by one ulp would make the nearest hit depend on the tree.
const BOX_PAD: f32 = 1e-5;

/// A built tree: nodes and leaf blocks.
pub struct Built {
    /// Nodes, root first.
    pub nodes: Vec<BvhNode>,
    /// Leaf blocks.
    pub blocks: Vec<TriangleBlock>,
}

/// Builds the BVH over `triangles` and reorders them into leaf order (blocks hold them in
/// runs of that order).
pub fn build(triangles: &mut Vec<PackedTriangle>) -> Built {
    if triangles.is_empty() {
        return Built {
            nodes: Vec::new(),
            blocks: Vec::new(),
        };
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
    // The slow preset's wider PLOC search and longer reinsertion took 1-3% fewer instructions
    // per ray than medium on the built-in scene and 3-6% fewer on the CT isosurface, for about
    // 2.5x the build time (4 s for 872k triangles, paid once, in `prepare`; README, "Benchmarks").
    let mut params = obvhs::BvhBuildParams::slow_build();
    // Spatial pre-splits clip references to sub-boxes; our padding argument needs whole-triangle boxes.
    params.pre_split = false;
    // Leaves of up to two blocks, and a collapse that favours them (cost of a node visit
    // relative to a triangle test). With `widen` cutting leaves into free slots, these took
    // fewer instructions per ray than leaves of up to three blocks with cost 6 (README,
    // "Benchmarks").
    params.max_prims_per_leaf = MAX_LEAF_TRIANGLES;
    params.collapse_traversal_cost = 4.0;
    let bvh = obvhs::bvh2::builder::build_bvh2_from_tris(&tris, params, &mut Duration::default());
    drop(tris);
    let reordered: Vec<PackedTriangle> = bvh
        .primitive_indices
        .iter()
        .map(|&i| triangles[i as usize])
        .collect();
    *triangles = reordered;
    widen(&bvh.nodes, triangles)
}

const EMPTY_NODE: BvhNode = BvhNode {
    bounds: [
        [f32::INFINITY; WIDTH],
        [f32::INFINITY; WIDTH],
        [f32::INFINITY; WIDTH],
        [f32::NEG_INFINITY; WIDTH],
        [f32::NEG_INFINITY; WIDTH],
        [f32::NEG_INFINITY; WIDTH],
    ],
    child: [0; WIDTH],
    meta: [SLOT_EMPTY; WIDTH],
};

/// A child of a wide node being filled: a binary inner node still to open or to become a wide
/// node, or a run of triangles that becomes a leaf.
#[derive(Clone, Copy)]
enum Kid {
    Inner(usize),
    Leaf { start: usize, count: usize },
}

/// Collapses a binary tree into an 8-wide one: each wide node takes its binary node's two
/// children and keeps opening the largest inner child until it has eight. Slots still free
/// then go to the leaves: the largest leaf of more than one block is cut in two at a block
/// boundary, so each part gets its own (tighter) box, tested in the same SIMD box test as its
/// siblings at no extra node visit. Leaves become runs of blocks.
fn widen(bin: &[obvhs::bvh2::node::Bvh2Node], tris: &[PackedTriangle]) -> Built {
    let mut out = vec![EMPTY_NODE];
    let mut blocks = Vec::with_capacity(tris.len().div_ceil(BLOCK) + 1);
    let kid = |k: usize| {
        let n = &bin[k];
        if n.prim_count > 0 {
            Kid::Leaf {
                start: n.first_index as usize,
                count: n.prim_count as usize,
            }
        } else {
            Kid::Inner(k)
        }
    };
    let leaf_box = |start: usize, count: usize| {
        let mut b = Aabb::EMPTY;
        for t in &tris[start..start + count] {
            for v in t.vertices() {
                b.grow(v);
            }
        }
        b
    };
    let kid_box = |k: Kid| match k {
        Kid::Inner(i) => Aabb {
            min: bin[i].aabb.min.into(),
            max: bin[i].aabb.max.into(),
        },
        Kid::Leaf { start, count } => leaf_box(start, count),
    };
    // (binary node whose children fill the wide node, wide node index); the root's own
    // binary node fills the root.
    let mut todo = vec![(None, 0usize)];
    let mut kids = Vec::with_capacity(WIDTH);
    while let Some((b, w)) = todo.pop() {
        kids.clear();
        match b.map_or(kid(0), Kid::Inner) {
            Kid::Inner(b) => {
                let first = bin[b].first_index as usize;
                kids.extend([kid(first), kid(first + 1)]);
            }
            leaf => kids.push(leaf),
        }
        while kids.len() < WIDTH {
            let open = kids
                .iter()
                .enumerate()
                .filter_map(|(i, k)| match k {
                    Kid::Inner(n) => Some((i, bin[*n].aabb.half_area())),
                    Kid::Leaf { .. } => None,
                })
                .max_by(|a, b| a.1.total_cmp(&b.1))
                .map(|(i, _)| i);
            let Some(i) = open else { break };
            let Kid::Inner(k) = kids.swap_remove(i) else {
                unreachable!("only inner children are opened")
            };
            let f = bin[k].first_index as usize;
            kids.extend([kid(f), kid(f + 1)]);
        }
        while kids.len() < WIDTH {
            let cut = kids
                .iter()
                .enumerate()
                .filter_map(|(i, k)| match *k {
                    Kid::Leaf { start, count } if count > BLOCK => {
                        Some((i, half_area(&leaf_box(start, count))))
                    }
                    _ => None,
                })
                .max_by(|a, b| a.1.total_cmp(&b.1))
                .map(|(i, _)| i);
            let Some(i) = cut else { break };
            let Kid::Leaf { start, count } = kids[i] else {
                unreachable!("only leaves are cut")
            };
            let head = count.div_ceil(BLOCK).div_ceil(2) * BLOCK;
            kids[i] = Kid::Leaf { start, count: head };
            kids.push(Kid::Leaf {
                start: start + head,
                count: count - head,
            });
        }
        for (slot, &k) in kids.iter().enumerate() {
            let bounds = kid_box(k);
            match k {
                Kid::Leaf { start, count } => {
                    let first = blocks.len() as u32;
                    for b in (0..count).step_by(BLOCK) {
                        blocks.push(TriangleBlock::new(tris, start + b, (count - b).min(BLOCK)));
                    }
                    let n = blocks.len() as u32 - first;
                    set_slot(&mut out[w], slot, &bounds, first, n);
                }
                Kid::Inner(k) => {
                    let index = out.len();
                    out.push(EMPTY_NODE);
                    set_slot(&mut out[w], slot, &bounds, index as u32, SLOT_INNER);
                    todo.push((Some(k), index));
                }
            }
        }
    }
    Built { nodes: out, blocks }
}

fn half_area(b: &Aabb) -> f32 {
    let e = Vec3::from(b.max) - Vec3::from(b.min);
    e.x * e.y + e.y * e.z + e.z * e.x
}

fn set_slot(node: &mut BvhNode, slot: usize, b: &Aabb, child: u32, meta: u32) {
    let min = Vec3::from(b.min);
    let max = Vec3::from(b.max);
    let pad = (min.abs().max(max.abs()) * BOX_PAD).max(Vec3::splat(1e-30));
    let (lo, hi) = (min - pad, max + pad);
    for a in 0..3 {
        node.bounds[a][slot] = lo[a];
        node.bounds[a + 3][slot] = hi[a];
    }
    node.child[slot] = child;
    node.meta[slot] = meta;
}

/// The deepest tree accepted, so a corrupt file cannot make traversal stacks huge.
pub const MAX_DEPTH: usize = 96;

/// Checks that `nodes` form one tree over `blocks` no deeper than [`MAX_DEPTH`], so traversal
/// can index without bounds failures; returns the depth.
pub fn validate(nodes: &[BvhNode], blocks: &[TriangleBlock]) -> Result<usize, String> {
    if nodes.is_empty() {
        return if blocks.is_empty() {
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
                count if count > MAX_LEAF_BLOCKS => {
                    return Err(format!(
                        "BVH node {i} has a leaf of {count} blocks (at most {MAX_LEAF_BLOCKS})"
                    ));
                }
                count => {
                    let end = c + count as usize;
                    if end > blocks.len() {
                        return Err(format!(
                            "BVH node {i} names blocks up to {end} of {}",
                            blocks.len()
                        ));
                    }
                }
            }
        }
    }
    Ok(deepest)
}

/// The nodes and leaf blocks of one domain's tree, checked by [`validate`]: traversal relies
/// on that check to index them without bounds tests.
#[derive(Clone, Copy, Debug)]
pub struct Bvh<'a> {
    nodes: &'a [BvhNode],
    blocks: &'a [TriangleBlock],
}

impl<'a> Bvh<'a> {
    /// The tree of `nodes` and `blocks`, if [`validate`] accepts it.
    pub fn new(nodes: &'a [BvhNode], blocks: &'a [TriangleBlock]) -> Result<Self, String> {
        validate(nodes, blocks)?;
        Ok(Bvh { nodes, blocks })
    }

    /// A tree the caller has validated (a loaded domain file).
    pub(crate) fn trusted(nodes: &'a [BvhNode], blocks: &'a [TriangleBlock]) -> Self {
        Bvh { nodes, blocks }
    }

    /// Nodes, root first.
    pub fn nodes(&self) -> &'a [BvhNode] {
        self.nodes
    }

    /// Leaf blocks.
    pub fn blocks(&self) -> &'a [TriangleBlock] {
        self.blocks
    }

    /// The triangle `hit` names (a hit of this tree), read back from its block for shading.
    ///
    /// # Panics
    /// If `hit` names a block this tree does not have (a hit of another tree).
    #[inline]
    pub fn triangle(&self, hit: &Hit) -> PackedTriangle {
        self.blocks[hit.block as usize].lane(hit.lane as usize)
    }

    /// Every triangle of the tree once, in leaf order (a block's repeated padding lanes are
    /// left out): for tools and rebuilds, which need the mesh the blocks hold.
    pub fn triangles(&self) -> impl Iterator<Item = PackedTriangle> + 'a {
        self.blocks.iter().flat_map(|b| {
            (0..BLOCK)
                .filter(move |&lane| !b.is_repeat(lane))
                .map(move |lane| b.lane(lane))
        })
    }

    /// Node `i`.
    ///
    /// # Safety
    /// `i` must be a child index read from this tree's nodes (or 0): [`validate`] checked those.
    #[inline(always)]
    unsafe fn node(&self, i: u32) -> &'a BvhNode {
        // SAFETY: as the caller promises.
        unsafe { self.nodes.get_unchecked(i as usize) }
    }

    /// A leaf's blocks.
    ///
    /// # Safety
    /// `first` and `count` must be a leaf child's `child` and `meta` from this tree's nodes.
    #[inline(always)]
    unsafe fn leaf(&self, first: u32, count: u32) -> &'a [TriangleBlock] {
        // SAFETY: as the caller promises; `validate` checked every leaf's range.
        unsafe {
            self.blocks
                .get_unchecked(first as usize..first as usize + count as usize)
        }
    }
}

/// A ray prepared for box and triangle tests.
#[derive(Clone, Copy, Debug)]
pub struct TraceRay {
    sheared: ShearedRay,
    inv: [f32; 3],
    origin_inv: [f32; 3],
    /// Per axis, the `bounds` row the ray enters through (minimum if it travels up the axis).
    near_row: [usize; 3],
    far_row: [usize; 3],
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
        let o = origin.to_array();
        // Rows 0..3 are minima, 3..6 maxima: a ray travelling down an axis enters at the
        // maximum. A select per axis rather than a branch: rays' signs are unpredictable.
        let rows = |a: usize| {
            let down = if inv[a] >= 0.0 { 0 } else { 3 };
            (a + down, a + 3 - down)
        };
        let r = [rows(0), rows(1), rows(2)];
        TraceRay {
            sheared: ShearedRay::new(origin, dir),
            inv,
            origin_inv: [o[0] * inv[0], o[1] * inv[1], o[2] * inv[2]],
            near_row: [r[0].0, r[1].0, r[2].0],
            far_row: [r[0].1, r[1].1, r[2].1],
        }
    }
}

/// The nearest hit of a ray in a BVH: where, and which triangle ([`Bvh::triangle`] reads it).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Distance along the ray direction.
    pub t: f32,
    /// The leaf block holding the triangle.
    pub block: u32,
    /// The triangle's lane in that block.
    pub lane: u32,
    /// Scene-wide triangle id.
    pub id: u64,
}

/// Which instructions traverse the tree. All give the same hits to the bit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kernel {
    /// One box and one triangle at a time: runs anywhere, the reference.
    Scalar,
    /// Four boxes (two halves of a node) and four triangles at a time, SSE2: any x86-64.
    Sse,
    /// Eight boxes at a time with AVX2 and FMA, four triangles with SSE.
    Avx2,
}

impl Kernel {
    /// Every kernel, slowest first.
    pub const ALL: [Kernel; 3] = [Kernel::Scalar, Kernel::Sse, Kernel::Avx2];

    /// The name `RAYFARM_KERNEL` takes.
    pub fn name(self) -> &'static str {
        match self {
            Kernel::Scalar => "scalar",
            Kernel::Sse => "sse",
            Kernel::Avx2 => "avx2",
        }
    }

    /// The kernel named `name` (as `RAYFARM_KERNEL` spells it).
    pub fn parse(name: &str) -> Result<Kernel, String> {
        Kernel::ALL
            .into_iter()
            .find(|k| k.name() == name.trim().to_ascii_lowercase())
            .ok_or_else(|| format!("RAYFARM_KERNEL={name:?}: expected avx2, sse or scalar"))
    }

    /// Whether this CPU can run the kernel.
    pub fn supported(self) -> bool {
        match self {
            Kernel::Scalar => true,
            #[cfg(target_arch = "x86_64")]
            Kernel::Sse => true,
            #[cfg(target_arch = "x86_64")]
            Kernel::Avx2 => is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma"),
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }

    /// The fastest kernel this CPU runs.
    pub fn detect() -> Kernel {
        Kernel::ALL
            .into_iter()
            .rev()
            .find(|k| k.supported())
            .unwrap_or(Kernel::Scalar)
    }

    /// The process's kernel: `RAYFARM_KERNEL` if set to one this CPU runs, else [`Kernel::detect`].
    /// Decided once; a value that cannot be honoured is reported and the detected kernel used.
    pub fn selected() -> Kernel {
        static SELECTED: OnceLock<Kernel> = OnceLock::new();
        *SELECTED.get_or_init(|| {
            let detected = Kernel::detect();
            let Ok(value) = std::env::var("RAYFARM_KERNEL") else {
                return detected;
            };
            match Kernel::parse(&value) {
                Ok(k) if k.supported() => {
                    tracing::info!(kernel = k.name(), "traversal kernel forced");
                    k
                }
                Ok(k) => {
                    tracing::warn!(
                        forced = k.name(),
                        kernel = detected.name(),
                        "this CPU cannot run the forced traversal kernel"
                    );
                    detected
                }
                Err(e) => {
                    tracing::warn!(kernel = detected.name(), "{e}");
                    detected
                }
            }
        })
    }
}

/// Whether packets are on for this process: `RAYFARM_PACKETS=0` (or `off`) turns them off, to
/// measure them or rule them out; decided once.
pub fn packets_selected() -> bool {
    static ON: OnceLock<bool> = OnceLock::new();
    *ON.get_or_init(|| match std::env::var("RAYFARM_PACKETS") {
        Ok(v) if matches!(v.trim(), "0" | "off" | "false" | "no") => {
            tracing::info!("ray packets off");
            false
        }
        _ => true,
    })
}

/// A child to visit: node index or first block, its `meta`, and its entry distance.
#[derive(Clone, Copy)]
struct Entry {
    child: u32,
    meta: u32,
    near: f32,
}

/// Traversal state reused across rays: zeroing a fresh stack for every ray cost more than
/// traversing a coherent ray's whole path.
pub struct Traverser {
    stack: Stack,
    packet_stack: PacketStack,
    kernel: Kernel,
    packets: bool,
}

impl Default for Traverser {
    fn default() -> Self {
        Self::new()
    }
}

impl Traverser {
    /// A traverser running [`Kernel::selected`].
    pub fn new() -> Self {
        Self::with_kernel(Kernel::selected()).expect("the selected kernel is supported")
    }

    /// A traverser running `kernel`, if this CPU can.
    pub fn with_kernel(kernel: Kernel) -> Option<Self> {
        kernel.supported().then(|| Traverser {
            stack: Stack::new(),
            packet_stack: PacketStack::new(),
            kernel,
            packets: packets_selected(),
        })
    }

    /// Whether [`Traverser::nearest_hits`] traces packets (the default, unless
    /// `RAYFARM_PACKETS=0`) or one ray at a time; the hits are the same either way.
    pub fn packets(&self) -> bool {
        self.packets
    }

    /// Turns packets on or off for this traverser.
    pub fn set_packets(&mut self, on: bool) {
        self.packets = on;
    }

    /// The kernel this traverser runs.
    pub fn kernel(&self) -> Kernel {
        self.kernel
    }

    /// Nearest hit with `t0 <= t <= t1`, ties broken by the lower scene-wide id.
    pub fn nearest_hit(&mut self, bvh: Bvh, ray: &TraceRay, t0: f32, t1: f32) -> Option<Hit> {
        if bvh.nodes.is_empty() {
            return None;
        }
        let stack = &mut self.stack;
        match self.kernel {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: a traverser holds only a kernel this CPU supports (`with_kernel`).
            Kernel::Avx2 => unsafe { x86::nearest_avx2(stack, bvh, ray, t0, t1) },
            #[cfg(target_arch = "x86_64")]
            Kernel::Sse => nearest::<x86::Sse>(stack, bvh, ray, t0, t1),
            _ => nearest::<Scalar>(stack, bvh, ray, t0, t1),
        }
    }

    /// The nearest hits of neighbouring, coherent rays (a tile's camera rays), each within its
    /// own `t0[i] <= t <= t1[i]`, into `out`: traced as packets of [`PACKET`] in lock step, or
    /// one at a time if packets are off. The same hits as [`Traverser::nearest_hit`] per ray.
    ///
    /// # Panics
    /// If the four slices differ in length.
    pub fn nearest_hits(
        &mut self,
        bvh: Bvh,
        rays: &[TraceRay],
        t0: &[f32],
        t1: &[f32],
        out: &mut [Option<Hit>],
    ) {
        let n = rays.len();
        assert!(
            t0.len() == n && t1.len() == n && out.len() == n,
            "every ray needs an interval and a place for its hit"
        );
        if !self.packets || bvh.nodes.is_empty() || n < 2 {
            for i in 0..n {
                out[i] = self.nearest_hit(bvh, &rays[i], t0[i], t1[i]);
            }
            return;
        }
        let (stack, single) = (&mut self.packet_stack, &mut self.stack);
        for start in (0..n).step_by(PACKET) {
            let at = start..(start + PACKET).min(n);
            let (r, a, b) = (&rays[at.clone()], &t0[at.clone()], &t1[at.clone()]);
            let o = &mut out[at];
            match self.kernel {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: a traverser holds only a kernel this CPU supports (`with_kernel`).
                Kernel::Avx2 => unsafe { x86::nearest_packet_avx2(stack, single, bvh, r, a, b, o) },
                #[cfg(target_arch = "x86_64")]
                Kernel::Sse => nearest_packet::<x86::Sse>(stack, single, bvh, r, a, b, o),
                _ => nearest_packet::<Scalar>(stack, single, bvh, r, a, b, o),
            }
        }
    }

    /// Whether anything is hit with `t0 <= t <= t1` (shadow rays).
    pub fn any_hit(&mut self, bvh: Bvh, ray: &TraceRay, t0: f32, t1: f32) -> bool {
        if bvh.nodes.is_empty() {
            return false;
        }
        let stack = &mut self.stack;
        match self.kernel {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: as in `nearest_hit`.
            Kernel::Avx2 => unsafe { x86::any_avx2(stack, bvh, ray, t0, t1) },
            #[cfg(target_arch = "x86_64")]
            Kernel::Sse => any::<x86::Sse>(stack, bvh, ray, t0, t1),
            _ => any::<Scalar>(stack, bvh, ray, t0, t1),
        }
    }
}

/// The box and triangle tests of one instruction set; the traversal loops are written once over it.
trait Isa {
    /// The ray with its values broadcast to this set's registers.
    type Ray;
    fn prepare(ray: &TraceRay) -> Self::Ray;
    /// Entry distances into the node's eight child boxes within `[t0, t1]`, and a bit mask of
    /// the children that are entered.
    fn slab(node: &BvhNode, ray: &Self::Ray, t0: f32, t1: f32) -> ([f32; WIDTH], u32);
    /// [`Isa::slab`] for a packet: lowers `nearest` to the entry distance of each entered
    /// child and returns the entered mask.
    #[inline(always)]
    fn slab_nearest(
        node: &BvhNode,
        ray: &Self::Ray,
        t0: f32,
        t1: f32,
        nearest: &mut [f32; WIDTH],
    ) -> u32 {
        let (near, mask) = Self::slab(node, ray, t0, t1);
        for (lane, (n, &d)) in nearest.iter_mut().zip(&near).enumerate() {
            if mask >> lane & 1 != 0 {
                *n = n.min(d);
            }
        }
        mask
    }
    /// The watertight test of a block's four lanes (infinity for a miss), and a bit mask of
    /// the lanes whose hit lies in `[t0, t1]`.
    fn block(block: &TriangleBlock, ray: &Self::Ray, t0: f32, t1: f32) -> ([f32; BLOCK], u32);
}

struct Scalar;

impl Isa for Scalar {
    type Ray = TraceRay;

    #[inline(always)]
    fn prepare(ray: &TraceRay) -> TraceRay {
        *ray
    }

    #[inline(always)]
    fn slab(node: &BvhNode, ray: &TraceRay, t0: f32, t1: f32) -> ([f32; WIDTH], u32) {
        let mut out = [0.0; WIDTH];
        let mut mask = 0;
        for (lane, entry) in out.iter_mut().enumerate() {
            let (mut near, mut far) = (t0, t1);
            for a in 0..3 {
                let tn = node.bounds[ray.near_row[a]][lane] * ray.inv[a] - ray.origin_inv[a];
                let tf = node.bounds[ray.far_row[a]][lane] * ray.inv[a] - ray.origin_inv[a];
                near = near.max(tn);
                far = far.min(tf);
            }
            *entry = near;
            mask |= ((near <= far) as u32) << lane;
        }
        (out, mask)
    }

    #[inline(always)]
    fn block(block: &TriangleBlock, ray: &TraceRay, t0: f32, t1: f32) -> ([f32; BLOCK], u32) {
        block.intersect_scalar(&ray.sheared, t0, t1)
    }
}

/// Asks the cache for the nodes and first leaf blocks of the children in `mask`.
#[inline(always)]
fn prefetch_children(bvh: Bvh, node: &BvhNode, mut mask: u32) {
    #[cfg(target_arch = "x86_64")]
    while mask != 0 {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        let slot = mask.trailing_zeros() as usize;
        mask &= mask - 1;
        let (child, meta) = (node.child[slot] as usize, node.meta[slot]);
        let base = if meta == SLOT_INNER {
            bvh.nodes.as_ptr().wrapping_add(child).cast::<i8>()
        } else {
            bvh.blocks.as_ptr().wrapping_add(child).cast::<i8>()
        };
        // Four lines whatever the child: a node's four, or a block's three and the first of
        // the leaf's next block; no loop or branch on the kind.
        // SAFETY: a prefetch never faults; the address is only a hint.
        unsafe {
            _mm_prefetch::<_MM_HINT_T0>(base);
            _mm_prefetch::<_MM_HINT_T0>(base.wrapping_add(64));
            _mm_prefetch::<_MM_HINT_T0>(base.wrapping_add(128));
            _mm_prefetch::<_MM_HINT_T0>(base.wrapping_add(192));
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (bvh, node, mask);
}

/// Tests a leaf's blocks (`first` is the index of the first), keeping the nearest hit (ties
/// to the lower id).
#[inline(always)]
fn leaf_nearest<K: Isa>(
    blocks: &[TriangleBlock],
    first: u32,
    ray: &K::Ray,
    t0: f32,
    best: &mut Hit,
) {
    for (k, b) in (first..).zip(blocks) {
        // Candidates come as a mask from the test itself: most lanes miss.
        let (ts, mut lanes) = K::block(b, ray, t0, best.t);
        while lanes != 0 {
            let lane = lanes.trailing_zeros() as usize;
            lanes &= lanes - 1;
            let (t, id) = (ts[lane], b.id(lane));
            if nearer(t, id, best.t, best.id) {
                *best = Hit {
                    t,
                    block: k,
                    lane: lane as u32,
                    id,
                };
            }
        }
    }
}

/// The traversal stack: sized for the deepest valid tree, so pushes need no capacity test.
struct Stack {
    entries: Box<[Entry]>,
    len: usize,
}

/// Entries a traversal can hold: each level leaves at most `WIDTH - 1` siblings waiting.
const STACK_ENTRIES: usize = MAX_DEPTH * (WIDTH - 1) + 1;

impl Stack {
    fn new() -> Self {
        Stack {
            entries: vec![
                Entry {
                    child: 0,
                    meta: 0,
                    near: 0.0,
                };
                STACK_ENTRIES
            ]
            .into_boxed_slice(),
            len: 0,
        }
    }

    /// # Safety
    /// Fewer than [`STACK_ENTRIES`] entries may be held: true of a traversal of a tree no
    /// deeper than [`MAX_DEPTH`] (a validated one), which pushes at most `WIDTH - 1` per level.
    #[inline(always)]
    unsafe fn push(&mut self, e: Entry) {
        // SAFETY: as the caller promises.
        unsafe { *self.entries.get_unchecked_mut(self.len) = e };
        self.len += 1;
    }

    #[inline(always)]
    fn pop(&mut self) -> Option<Entry> {
        self.len = self.len.checked_sub(1)?;
        // SAFETY: `len` was below the number held.
        Some(unsafe { *self.entries.get_unchecked(self.len) })
    }
}

/// Ordered traversal: the nearest entered child is visited next, the others wait on the stack
/// with their entry distance (sorted, the nearest on top), so a subtree beyond the best hit is
/// skipped unopened; equal distances are still visited, for the id tie-break.
#[inline(always)]
fn nearest<K: Isa>(stack: &mut Stack, bvh: Bvh, ray: &TraceRay, t0: f32, t1: f32) -> Option<Hit> {
    let r = K::prepare(ray);
    let mut best = Hit {
        t: t1,
        block: u32::MAX,
        lane: 0,
        id: u64::MAX,
    };
    let root = Entry {
        child: 0,
        meta: SLOT_INNER,
        near: t0,
    };
    descend::<K>(stack, bvh, &r, t0, root, &mut best);
    (best.block != u32::MAX).then_some(best)
}

/// The ordered traversal of the subtree at `start` (the whole tree from the root; a packet's
/// ray that is left alone, from where it was left), improving `best` (ties to the lower id).
#[inline(always)]
fn descend<K: Isa>(
    stack: &mut Stack,
    bvh: Bvh,
    r: &K::Ray,
    t0: f32,
    start: Entry,
    best_out: &mut Hit,
) {
    let mut best = *best_out;
    stack.len = 0;
    let mut cur = start;
    loop {
        if cur.meta == SLOT_INNER {
            // SAFETY: the root or a child index of a validated tree.
            let node = unsafe { bvh.node(cur.child) };
            let (near, mut mask) = K::slab(node, r, t0, best.t);
            if mask != 0 {
                let slot = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                let first = Entry {
                    child: node.child[slot],
                    meta: node.meta[slot],
                    near: near[slot],
                };
                if mask == 0 {
                    cur = first;
                    continue;
                }
                // Every entered child's memory is asked for now, so the cache misses of the
                // siblings overlap with the work on the nearest.
                prefetch_children(bvh, node, mask | 1 << slot);
                if mask & (mask - 1) == 0 {
                    // Two entered children, the commonest case: one comparison orders them.
                    let slot = mask.trailing_zeros() as usize;
                    let second = Entry {
                        child: node.child[slot],
                        meta: node.meta[slot],
                        near: near[slot],
                    };
                    let (nearer, farther) = if second.near < first.near {
                        (second, first)
                    } else {
                        (first, second)
                    };
                    // SAFETY: a validated tree's traversal holds fewer than STACK_ENTRIES.
                    unsafe { stack.push(farther) };
                    cur = nearer;
                    continue;
                }
                // Insert the entered children so the stack stays sorted within this node's
                // run, farthest deepest; the nearest becomes `cur`.
                let base = stack.len;
                // SAFETY: a validated tree's traversal holds fewer than STACK_ENTRIES.
                unsafe { stack.push(first) };
                while mask != 0 {
                    let slot = mask.trailing_zeros() as usize;
                    mask &= mask - 1;
                    let entry = Entry {
                        child: node.child[slot],
                        meta: node.meta[slot],
                        near: near[slot],
                    };
                    let mut at = stack.len;
                    // SAFETY: as above.
                    unsafe { stack.push(entry) };
                    let e = &mut stack.entries[..stack.len];
                    while at > base && e[at - 1].near < entry.near {
                        e[at] = e[at - 1];
                        at -= 1;
                    }
                    e[at] = entry;
                }
                if let Some(e) = stack.pop() {
                    cur = e;
                    continue;
                }
            }
        } else {
            // SAFETY: a leaf child's range of a validated tree.
            let blocks = unsafe { bvh.leaf(cur.child, cur.meta) };
            leaf_nearest::<K>(blocks, cur.child, r, t0, &mut best);
        }
        loop {
            match stack.pop() {
                None => {
                    *best_out = best;
                    return;
                }
                Some(e) if e.near > best.t => continue,
                Some(e) => {
                    cur = e;
                    break;
                }
            }
        }
    }
}

/// Whether a leaf's blocks hold a hit in `[t0, t1]`.
#[inline(always)]
fn leaf_any<K: Isa>(blocks: &[TriangleBlock], ray: &K::Ray, t0: f32, t1: f32) -> bool {
    blocks.iter().any(|b| K::block(b, ray, t0, t1).1 != 0)
}

/// Shadow-ray traversal: no order and no distances kept; a node's leaf children are tested at
/// once (a blocker ends the ray), its inner children wait on the stack.
#[inline(always)]
fn any<K: Isa>(stack: &mut Stack, bvh: Bvh, ray: &TraceRay, t0: f32, t1: f32) -> bool {
    let r = K::prepare(ray);
    stack.len = 0;
    let mut node = 0u32;
    loop {
        // SAFETY: the root or a child index of a validated tree.
        let n = unsafe { bvh.node(node) };
        let (_, mut mask) = K::slab(n, &r, t0, t1);
        if mask & (mask - 1) != 0 {
            prefetch_children(bvh, n, mask);
        }
        while mask != 0 {
            let slot = mask.trailing_zeros() as usize;
            mask &= mask - 1;
            let (child, meta) = (n.child[slot], n.meta[slot]);
            if meta == SLOT_INNER {
                // SAFETY: a validated tree's traversal holds fewer than STACK_ENTRIES.
                unsafe {
                    stack.push(Entry {
                        child,
                        meta,
                        near: 0.0,
                    })
                };
            } else {
                // SAFETY: a leaf child's range of a validated tree.
                let blocks = unsafe { bvh.leaf(child, meta) };
                if leaf_any::<K>(blocks, &r, t0, t1) {
                    return true;
                }
            }
        }
        match stack.pop() {
            Some(e) => node = e.child,
            None => return false,
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    //! The SSE and AVX2 box tests; the triangle test is SSE in both
    //! ([`TriangleBlock::intersect_sse`]).

    use std::arch::x86_64::*;

    use super::packet::{PacketStack, nearest_packet};
    use super::{Bvh, BvhNode, Hit, Isa, Stack, TraceRay, WIDTH, any, nearest};
    use crate::geometry::{BLOCK, ShearedSse, TriangleBlock};

    /// Four lanes at a time: a node's two halves in turn.
    pub struct Sse;

    pub struct SseRay {
        tri: ShearedSse,
        inv: [__m128; 3],
        origin_inv: [__m128; 3],
        near_row: [usize; 3],
        far_row: [usize; 3],
    }

    impl Isa for Sse {
        type Ray = SseRay;

        #[inline(always)]
        fn prepare(ray: &TraceRay) -> SseRay {
            // SAFETY: SSE2 is part of x86-64.
            unsafe {
                SseRay {
                    tri: ShearedSse::new(&ray.sheared),
                    inv: ray.inv.map(|v| _mm_set1_ps(v)),
                    origin_inv: ray.origin_inv.map(|v| _mm_set1_ps(v)),
                    near_row: ray.near_row,
                    far_row: ray.far_row,
                }
            }
        }

        #[inline(always)]
        fn slab(node: &BvhNode, r: &SseRay, t0: f32, t1: f32) -> ([f32; WIDTH], u32) {
            let mut out = [0.0f32; WIDTH];
            let mut mask = 0;
            // SAFETY: SSE2 is part of x86-64; loads read the node's 64-byte aligned rows.
            unsafe {
                for half in 0..2 {
                    let at = half * 4;
                    let plane = |row: usize, a: usize| {
                        // SAFETY: rows are below 6 (`TraceRay::new`), `at` is 0 or 4.
                        let b = _mm_load_ps(node.bounds.get_unchecked(row).as_ptr().add(at));
                        _mm_sub_ps(_mm_mul_ps(b, r.inv[a]), r.origin_inv[a])
                    };
                    let near = _mm_max_ps(
                        _mm_max_ps(plane(r.near_row[0], 0), plane(r.near_row[1], 1)),
                        _mm_max_ps(plane(r.near_row[2], 2), _mm_set1_ps(t0)),
                    );
                    let far = _mm_min_ps(
                        _mm_min_ps(plane(r.far_row[0], 0), plane(r.far_row[1], 1)),
                        _mm_min_ps(plane(r.far_row[2], 2), _mm_set1_ps(t1)),
                    );
                    _mm_storeu_ps(out[at..].as_mut_ptr(), near);
                    mask |= (_mm_movemask_ps(_mm_cmple_ps(near, far)) as u32) << at;
                }
            }
            (out, mask)
        }

        #[inline(always)]
        fn block(block: &TriangleBlock, r: &SseRay, t0: f32, t1: f32) -> ([f32; BLOCK], u32) {
            // SAFETY: SSE2 is part of x86-64.
            unsafe { block.intersect_sse(&r.tri, t0, t1) }
        }
    }

    /// All eight lanes at once, box planes with one fused multiply-subtract each.
    struct Avx2;

    struct Avx2Ray {
        tri: ShearedSse,
        inv: [__m256; 3],
        origin_inv: [__m256; 3],
        near_row: [usize; 3],
        far_row: [usize; 3],
    }

    impl Isa for Avx2 {
        type Ray = Avx2Ray;

        #[inline(always)]
        fn prepare(ray: &TraceRay) -> Avx2Ray {
            // SAFETY: only reached from the `avx2,fma` functions below.
            unsafe {
                Avx2Ray {
                    tri: ShearedSse::new(&ray.sheared),
                    inv: ray.inv.map(|v| _mm256_set1_ps(v)),
                    origin_inv: ray.origin_inv.map(|v| _mm256_set1_ps(v)),
                    near_row: ray.near_row,
                    far_row: ray.far_row,
                }
            }
        }

        #[inline(always)]
        fn slab(node: &BvhNode, r: &Avx2Ray, t0: f32, t1: f32) -> ([f32; WIDTH], u32) {
            let mut out = [0.0f32; WIDTH];
            // SAFETY: only reached from the `avx2,fma` functions below; loads read the node's
            // 64-byte aligned rows.
            let mask = unsafe {
                let plane = |row: usize, a: usize| {
                    // SAFETY: rows are below 6 (`TraceRay::new`).
                    let b = _mm256_load_ps(node.bounds.get_unchecked(row).as_ptr());
                    _mm256_fmsub_ps(b, r.inv[a], r.origin_inv[a])
                };
                let near = _mm256_max_ps(
                    _mm256_max_ps(plane(r.near_row[0], 0), plane(r.near_row[1], 1)),
                    _mm256_max_ps(plane(r.near_row[2], 2), _mm256_set1_ps(t0)),
                );
                let far = _mm256_min_ps(
                    _mm256_min_ps(plane(r.far_row[0], 0), plane(r.far_row[1], 1)),
                    _mm256_min_ps(plane(r.far_row[2], 2), _mm256_set1_ps(t1)),
                );
                _mm256_storeu_ps(out.as_mut_ptr(), near);
                _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(near, far)) as u32
            };
            (out, mask)
        }

        #[inline(always)]
        fn slab_nearest(
            node: &BvhNode,
            r: &Avx2Ray,
            t0: f32,
            t1: f32,
            nearest: &mut [f32; WIDTH],
        ) -> u32 {
            // SAFETY: only reached from the `avx2,fma` functions below; loads read the node's
            // 64-byte aligned rows and `nearest`'s eight floats.
            unsafe {
                let plane = |row: usize, a: usize| {
                    // SAFETY: rows are below 6 (`TraceRay::new`).
                    let b = _mm256_load_ps(node.bounds.get_unchecked(row).as_ptr());
                    _mm256_fmsub_ps(b, r.inv[a], r.origin_inv[a])
                };
                let near = _mm256_max_ps(
                    _mm256_max_ps(plane(r.near_row[0], 0), plane(r.near_row[1], 1)),
                    _mm256_max_ps(plane(r.near_row[2], 2), _mm256_set1_ps(t0)),
                );
                let far = _mm256_min_ps(
                    _mm256_min_ps(plane(r.far_row[0], 0), plane(r.far_row[1], 1)),
                    _mm256_min_ps(plane(r.far_row[2], 2), _mm256_set1_ps(t1)),
                );
                let entered = _mm256_cmp_ps::<_CMP_LE_OQ>(near, far);
                let held = _mm256_loadu_ps(nearest.as_ptr());
                let lower = _mm256_min_ps(held, near);
                _mm256_storeu_ps(nearest.as_mut_ptr(), _mm256_blendv_ps(held, lower, entered));
                _mm256_movemask_ps(entered) as u32
            }
        }

        #[inline(always)]
        fn block(block: &TriangleBlock, r: &Avx2Ray, t0: f32, t1: f32) -> ([f32; BLOCK], u32) {
            // SAFETY: SSE2 is part of x86-64.
            unsafe { block.intersect_sse(&r.tri, t0, t1) }
        }
    }

    /// # Safety
    /// The CPU must support AVX2 and FMA.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn nearest_avx2(
        stack: &mut Stack,
        bvh: Bvh,
        ray: &TraceRay,
        t0: f32,
        t1: f32,
    ) -> Option<Hit> {
        nearest::<Avx2>(stack, bvh, ray, t0, t1)
    }

    /// # Safety
    /// The CPU must support AVX2 and FMA.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn nearest_packet_avx2(
        stack: &mut PacketStack,
        single: &mut Stack,
        bvh: Bvh,
        rays: &[TraceRay],
        t0: &[f32],
        t1: &[f32],
        out: &mut [Option<Hit>],
    ) {
        nearest_packet::<Avx2>(stack, single, bvh, rays, t0, t1, out)
    }

    /// # Safety
    /// The CPU must support AVX2 and FMA.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn any_avx2(stack: &mut Stack, bvh: Bvh, ray: &TraceRay, t0: f32, t1: f32) -> bool {
        any::<Avx2>(stack, bvh, ray, t0, t1)
    }
}

#[cfg(test)]
mod tests {
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
}
