//! A top-down binned surface-area-heuristic builder that writes 8-wide nodes directly, without
//! a binary tree in between: a node starts as one child holding all its triangles, and the
//! child with the largest box that can still be split is split in two by the best binned SAH
//! plane until the node has eight children; each child then becomes a leaf or a node of its
//! own. (The idea of Embree's BVH8 builder; the code is ours.)

use glam::Vec3A;

use super::build::{Built, EMPTY_NODE, set_slot};
use super::{MAX_LEAF_TRIANGLES, SLOT_INNER, WIDTH};
use crate::geometry::{Aabb, BLOCK, PackedTriangle, TriangleBlock};

/// Bins per axis of a split search: more bins find planes closer to the best sweep's, at a
/// cost per split that only the top levels of the tree feel.
const BINS: usize = 32;
/// Cost of visiting a node (one 8-wide box test and its stack work) relative to testing one
/// [`TriangleBlock`].
/// Costs of 0.5 and 2, and leaves of up to one or three blocks, moved instructions per ray by
/// less than 1% either way (README, "Benchmarks").
const NODE_COST: f32 = 1.0;
/// Cost of testing one block.
const BLOCK_COST: f32 = 1.0;
/// Depth past which splits are object medians: the SAH may cut one triangle off at a time on
/// pathological input, and a median keeps the tree within [`super::MAX_DEPTH`].
const MEDIAN_DEPTH: usize = 40;

/// A triangle's box and its index in the input, as the builder moves it between children.
#[derive(Clone, Copy)]
struct Prim {
    lo: Vec3A,
    hi: Vec3A,
    index: u32,
}

impl Prim {
    /// Twice the box centre: halving it would not change any comparison.
    #[inline]
    fn centre2(&self) -> Vec3A {
        self.lo + self.hi
    }
}

/// An axis-aligned box in SIMD form.
#[derive(Clone, Copy)]
struct Box3 {
    lo: Vec3A,
    hi: Vec3A,
}

impl Box3 {
    const EMPTY: Box3 = Box3 {
        lo: Vec3A::splat(f32::INFINITY),
        hi: Vec3A::splat(f32::NEG_INFINITY),
    };

    #[inline]
    fn grow(&mut self, lo: Vec3A, hi: Vec3A) {
        self.lo = self.lo.min(lo);
        self.hi = self.hi.max(hi);
    }

    #[inline]
    fn join(self, o: Box3) -> Box3 {
        Box3 {
            lo: self.lo.min(o.lo),
            hi: self.hi.max(o.hi),
        }
    }

    /// Half the surface area (zero for an empty box).
    #[inline]
    fn half_area(&self) -> f32 {
        let e = (self.hi - self.lo).max(Vec3A::ZERO);
        e.x * e.y + e.y * e.z + e.z * e.x
    }
}

/// The blocks a leaf of `n` triangles takes: the SAH counts tests of blocks, not triangles.
#[inline]
fn blocks(n: usize) -> f32 {
    n.div_ceil(BLOCK) as f32
}

/// A run `prims[start..end]` with its box: a child of a node being filled.
#[derive(Clone, Copy)]
struct Run {
    start: usize,
    end: usize,
    bounds: Box3,
}

impl Run {
    fn len(&self) -> usize {
        self.end - self.start
    }
}

/// The best binary split found for a run: the plane, and the SAH cost of the two sides
/// (areas times blocks, without the node's own cost).
struct Split {
    axis: usize,
    /// Prims whose bin is below this go left.
    bin: usize,
    lo: f32,
    scale: f32,
    cost: f32,
}

/// Builds the tree over `triangles` and reorders them into leaf order.
pub(super) fn build(triangles: &mut Vec<PackedTriangle>) -> Built {
    if triangles.is_empty() {
        return Built {
            nodes: Vec::new(),
            blocks: Vec::new(),
        };
    }
    let mut prims: Vec<Prim> = triangles
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let [a, b, c] = t.vertices().map(Vec3A::from);
            Prim {
                lo: a.min(b).min(c),
                hi: a.max(b).max(c),
                index: i as u32,
            }
        })
        .collect();
    let bounds = bounds_of(&prims);
    let mut b = Builder {
        tris: triangles,
        nodes: vec![EMPTY_NODE],
        blocks: Vec::with_capacity(triangles.len().div_ceil(BLOCK) + 1),
        order: Vec::with_capacity(triangles.len()),
        leaf: Vec::with_capacity(MAX_LEAF_TRIANGLES as usize),
    };
    let root = Run {
        start: 0,
        end: prims.len(),
        bounds,
    };
    if root.len() <= MAX_LEAF_TRIANGLES as usize && !b.worth_a_node(&mut prims, root) {
        // One small leaf under a root of one child.
        b.fill(&mut prims, 0, &[root], 1);
    } else {
        b.node(&mut prims, 0, root, 1);
    }
    let Builder {
        nodes,
        blocks,
        order,
        ..
    } = b;
    let reordered: Vec<PackedTriangle> = order.iter().map(|&i| triangles[i as usize]).collect();
    *triangles = reordered;
    Built { nodes, blocks }
}

fn bounds_of(prims: &[Prim]) -> Box3 {
    prims.iter().fold(Box3::EMPTY, |mut b, p| {
        b.grow(p.lo, p.hi);
        b
    })
}

struct Builder<'a> {
    tris: &'a [PackedTriangle],
    nodes: Vec<super::BvhNode>,
    blocks: Vec<TriangleBlock>,
    /// Input indices of the triangles in leaf order, as blocks are written.
    order: Vec<u32>,
    /// A leaf's triangles gathered for its blocks.
    leaf: Vec<PackedTriangle>,
}

impl Builder<'_> {
    /// Fills wide node `w` with the triangles of `run`: splits the children until there are
    /// [`WIDTH`] or none can be split, then writes them.
    fn node(&mut self, prims: &mut [Prim], w: usize, run: Run, depth: usize) {
        let mut kids = [run; WIDTH];
        let mut n = 1;
        while n < WIDTH {
            // The largest box among children of more than one block: splitting a block's
            // worth of triangles would only add a block test.
            let pick = (0..n).filter(|&i| kids[i].len() > BLOCK).max_by(|&a, &b| {
                kids[a]
                    .bounds
                    .half_area()
                    .total_cmp(&kids[b].bounds.half_area())
            });
            let Some(i) = pick else { break };
            let (l, r) = split(prims, kids[i], depth);
            kids[i] = l;
            kids[n] = r;
            n += 1;
        }
        self.fill(prims, w, &kids[..n], depth);
    }

    /// Writes `kids` into node `w`: a child small enough, and for which a node of its own does
    /// not pay, becomes a leaf; the others become nodes, filled depth first.
    fn fill(&mut self, prims: &mut [Prim], w: usize, kids: &[Run], depth: usize) {
        for (slot, &k) in kids.iter().enumerate() {
            let b = Aabb {
                min: k.bounds.lo.to_array(),
                max: k.bounds.hi.to_array(),
            };
            if k.len() <= MAX_LEAF_TRIANGLES as usize && !self.worth_a_node(prims, k) {
                let first = self.blocks.len() as u32;
                self.leaf.clear();
                for p in &prims[k.start..k.end] {
                    self.order.push(p.index);
                    self.leaf.push(self.tris[p.index as usize]);
                }
                for s in (0..k.len()).step_by(BLOCK) {
                    self.blocks
                        .push(TriangleBlock::new(&self.leaf, s, (k.len() - s).min(BLOCK)));
                }
                let count = self.blocks.len() as u32 - first;
                set_slot(&mut self.nodes[w], slot, &b, first, count);
            } else {
                let index = self.nodes.len();
                self.nodes.push(EMPTY_NODE);
                set_slot(&mut self.nodes[w], slot, &b, index as u32, SLOT_INNER);
                self.node(prims, index, k, depth + 1);
            }
        }
    }

    /// Whether a run small enough for a leaf costs less as a node: the node's visit and the
    /// best split's two sides against the run's blocks tested at once.
    fn worth_a_node(&self, prims: &mut [Prim], run: Run) -> bool {
        if run.len() <= BLOCK {
            return false;
        }
        let area = run.bounds.half_area();
        let leaf = area * blocks(run.len()) * BLOCK_COST;
        match find_split(&prims[run.start..run.end]) {
            Some(s) => NODE_COST * area + s.cost * BLOCK_COST < leaf,
            None => false,
        }
    }
}

/// Splits `run` in two by the best binned SAH plane (an object median past [`MEDIAN_DEPTH`],
/// or when every centre coincides), reordering its prims so each side is a run.
fn split(prims: &mut [Prim], run: Run, depth: usize) -> (Run, Run) {
    let slice = &mut prims[run.start..run.end];
    let plane = if depth > MEDIAN_DEPTH {
        None
    } else {
        find_split(slice)
    };
    let mid = match plane {
        Some(s) => partition(slice, |p| {
            bin_of(p.centre2()[s.axis], s.lo, s.scale) < s.bin
        }),
        None => median(slice),
    };
    let (left, right) = slice.split_at(mid);
    (
        Run {
            start: run.start,
            end: run.start + mid,
            bounds: bounds_of(left),
        },
        Run {
            start: run.start + mid,
            end: run.end,
            bounds: bounds_of(right),
        },
    )
}

/// Splits at a block boundary near the middle of the longest axis of the centres' box, so
/// both sides are non-empty whatever the input.
fn median(slice: &mut [Prim]) -> usize {
    let c = slice.iter().fold(Box3::EMPTY, |mut b, p| {
        b.grow(p.centre2(), p.centre2());
        b
    });
    let e = c.hi - c.lo;
    let axis = if e.x >= e.y && e.x >= e.z {
        0
    } else if e.y >= e.z {
        1
    } else {
        2
    };
    let mid = (slice.len() / 2).div_ceil(BLOCK) * BLOCK;
    let mid = mid.clamp(1, slice.len() - 1);
    slice.select_nth_unstable_by(mid, |a, b| a.centre2()[axis].total_cmp(&b.centre2()[axis]));
    mid
}

#[inline]
fn bin_of(c: f32, lo: f32, scale: f32) -> usize {
    // `as` saturates: a centre on the upper bound lands past the last bin and is clamped.
    (((c - lo) * scale) as usize).min(BINS - 1)
}

/// Moves the prims for which `left` holds to the front; returns how many there are.
fn partition(slice: &mut [Prim], left: impl Fn(&Prim) -> bool) -> usize {
    let mut i = 0;
    let mut j = slice.len();
    loop {
        while i < j && left(&slice[i]) {
            i += 1;
        }
        while i < j && !left(&slice[j - 1]) {
            j -= 1;
        }
        if i >= j {
            return i;
        }
        slice.swap(i, j - 1);
        i += 1;
        j -= 1;
    }
}

/// The binned SAH's best plane over the three axes, if the centres are not all one point.
fn find_split(prims: &[Prim]) -> Option<Split> {
    let centres = prims.iter().fold(Box3::EMPTY, |mut b, p| {
        b.grow(p.centre2(), p.centre2());
        b
    });
    let extent = centres.hi - centres.lo;
    let mut scale = [0.0f32; 3];
    for a in 0..3 {
        if extent[a] > 0.0 {
            // Slightly below BINS / extent so the largest centre stays in the last bin.
            scale[a] = BINS as f32 * (1.0 - 1e-6) / extent[a];
        }
    }
    if scale == [0.0; 3] {
        return None;
    }
    let mut bins = [[(Box3::EMPTY, 0usize); BINS]; 3];
    for p in prims {
        let c = p.centre2();
        for a in 0..3 {
            let k = bin_of(c[a], centres.lo[a], scale[a]);
            let bin = &mut bins[a][k];
            bin.0.grow(p.lo, p.hi);
            bin.1 += 1;
        }
    }
    let mut best: Option<Split> = None;
    for (a, bins) in bins.iter().enumerate() {
        if scale[a] == 0.0 {
            continue;
        }
        // Right side's cost for each first bin, swept from the top.
        let mut right = [0.0f32; BINS];
        let (mut rb, mut rn) = (Box3::EMPTY, 0);
        for k in (1..BINS).rev() {
            rb = rb.join(bins[k].0);
            rn += bins[k].1;
            right[k] = rb.half_area() * blocks(rn);
        }
        let (mut lb, mut ln) = (Box3::EMPTY, 0);
        for k in 1..BINS {
            lb = lb.join(bins[k - 1].0);
            ln += bins[k - 1].1;
            if ln == 0 || ln == prims.len() {
                continue;
            }
            let cost = lb.half_area() * blocks(ln) + right[k];
            if best.as_ref().is_none_or(|b| cost < b.cost) {
                best = Some(Split {
                    axis: a,
                    bin: k,
                    lo: centres.lo[a],
                    scale: scale[a],
                    cost,
                });
            }
        }
    }
    best
}
