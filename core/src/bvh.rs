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

use bytemuck::{Pod, Zeroable};
use glam::{Vec3, Vec3A};

use crate::geometry::{BLOCK, NormalBlock, PackedTriangle, ShearedRay, TriangleBlock};

mod build;
pub mod counters;
mod packet;
mod sah;
mod select;
mod traverse;
#[cfg(target_arch = "x86_64")]
mod x86;

pub use build::{Builder, Built, build, build_with};
pub use packet::PACKET;
pub use select::{Kernel, packets_selected};
pub use traverse::Traverser;
use traverse::{
    Entry, Isa, STACK_ENTRIES, Stack, any, descend, leaf_nearest, nearest, prefetch_children,
};

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
    /// Corner shading normals, one per block, or empty (facet normals): shading only,
    /// traversal never reads them.
    normals: &'a [NormalBlock],
}

impl<'a> Bvh<'a> {
    /// The tree of `nodes` and `blocks`, if [`validate`] accepts it.
    pub fn new(nodes: &'a [BvhNode], blocks: &'a [TriangleBlock]) -> Result<Self, String> {
        validate(nodes, blocks)?;
        Ok(Bvh {
            nodes,
            blocks,
            normals: &[],
        })
    }

    /// A tree the caller has validated (a loaded domain file), with its corner shading
    /// `normals` (empty, or one per block: the caller checked).
    pub(crate) fn trusted(
        nodes: &'a [BvhNode],
        blocks: &'a [TriangleBlock],
        normals: &'a [NormalBlock],
    ) -> Self {
        Bvh {
            nodes,
            blocks,
            normals,
        }
    }

    /// The corner shading normals of the triangle `hit` names, if the tree has them and they
    /// are set for it (a smooth surface's; else shading uses the facet normal).
    #[inline]
    pub fn vertex_normals(&self, hit: &Hit) -> Option<[Vec3; 3]> {
        self.normals
            .get(hit.block as usize)
            .and_then(|b| b.lane(hit.lane as usize))
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

/// Bytes from one `bounds` row of a [`BvhNode`] to the next.
const ROW_BYTES: u32 = (WIDTH * std::mem::size_of::<f32>()) as u32;

/// Per octant of a ray's direction (bit `a` set if it travels up axis `a`), the byte offsets
/// into a node's `bounds` of the rows it enters through (x, y, z) and leaves through (x, y,
/// z): rows 0..3 are minima, 3..6 maxima, and a ray travelling down an axis enters at the
/// maximum. A table, so a ray's set-up is one load instead of a select per row, and the
/// kernels add an offset to a node's address instead of scaling a row index per node visit.
const ROW_OFFSETS: [[u32; 6]; 8] = {
    let mut table = [[0; 6]; 8];
    let mut octant = 0;
    while octant < 8 {
        let mut a = 0;
        while a < 3 {
            let down = if octant >> a & 1 != 0 { 0 } else { 3 };
            table[octant][a] = (a as u32 + down) * ROW_BYTES;
            table[octant][3 + a] = (a as u32 + 3 - down) * ROW_BYTES;
            a += 1;
        }
        octant += 1;
    }
    table
};

/// A ray prepared for box and triangle tests.
#[derive(Clone, Copy, Debug)]
pub struct TraceRay {
    sheared: ShearedRay,
    inv: [f32; 3],
    origin_inv: [f32; 3],
    /// Byte offsets into a node's `bounds` of the rows the ray enters through (per axis),
    /// then of those it leaves through: [`ROW_OFFSETS`] of its octant, each below
    /// `6 * ROW_BYTES` (the kernels read node rows at these offsets without a check).
    rows: [u32; 6],
}

impl TraceRay {
    /// Prepares a ray; `dir` need not be normalised.
    ///
    /// The three axes at once in SSE lanes (glam's `Vec3A`): the same divisions and products
    /// per axis as one at a time, so the same bits, in fewer instructions than the scalar
    /// form with a branch per axis (this runs once per ray, and rays are short).
    #[inline]
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        let d = Vec3A::from(dir);
        // A zero component would give 0 * inf = NaN in the slab test; a tiny stand-in keeps every
        // product finite and only moves the (padded) box test, never the triangle test.
        let tiny = Vec3A::splat(1e-30);
        let safe = Vec3A::select(d.abs().cmplt(tiny), tiny.copysign(d), d);
        let inv = Vec3A::ONE / safe;
        let origin_inv = Vec3A::from(origin) * inv;
        // The rows from one comparison's bits and a table rather than a branch per axis:
        // rays' signs are unpredictable.
        let up = inv.cmpge(Vec3A::ZERO).bitmask() as usize & 7;
        TraceRay {
            sheared: ShearedRay::new(origin, dir),
            inv: inv.to_array(),
            origin_inv: origin_inv.to_array(),
            rows: ROW_OFFSETS[up],
        }
    }

    /// The `bounds` row index of the ray's entry (`k` 0..3, per axis) or exit (3..6) plane.
    #[inline(always)]
    fn row(&self, k: usize) -> usize {
        (self.rows[k] / ROW_BYTES) as usize
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

#[cfg(test)]
mod tests;
