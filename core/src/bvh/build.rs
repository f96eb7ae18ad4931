//! Building a domain's tree, by one of two [`Builder`]s: `obvhs` builds a binary tree over the
//! triangles, which is collapsed here into the 8-wide tree of [`BvhNode`]s over
//! [`TriangleBlock`] leaves; or `bvh::sah` builds the 8-wide tree directly.

use std::sync::OnceLock;
use std::time::Duration;

use glam::{Vec3, Vec3A};

use super::{BvhNode, MAX_LEAF_TRIANGLES, SLOT_EMPTY, SLOT_INNER, WIDTH};
use crate::geometry::{Aabb, BLOCK, PackedTriangle, TriangleBlock};

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

/// Builds the BVH over `triangles` with [`Builder::selected`] and reorders them into leaf
/// order (blocks hold them in runs of that order).
pub fn build(triangles: &mut Vec<PackedTriangle>) -> Built {
    build_with(Builder::selected(), triangles)
}

/// Builds the BVH over `triangles` with `builder` and reorders them into leaf order.
pub fn build_with(builder: Builder, triangles: &mut Vec<PackedTriangle>) -> Built {
    match builder {
        Builder::Ploc => build_ploc(triangles),
        Builder::Sah => super::sah::build(triangles),
    }
}

/// Which algorithm builds a domain's tree. Hits do not depend on it (ties go to the lower
/// triangle id, and boxes are padded), only the work per ray does.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Builder {
    /// `obvhs`'s PLOC binary tree, collapsed into 8-wide nodes.
    Ploc,
    /// Binned SAH, top-down, straight into 8-wide nodes (`bvh::sah`).
    Sah,
}

impl Builder {
    /// Every builder.
    pub const ALL: [Builder; 2] = [Builder::Ploc, Builder::Sah];

    /// The name `RAYFARM_BUILDER` takes.
    pub fn name(self) -> &'static str {
        match self {
            Builder::Ploc => "ploc",
            Builder::Sah => "sah",
        }
    }

    /// The builder named `name` (as `RAYFARM_BUILDER` spells it).
    pub fn parse(name: &str) -> Result<Builder, String> {
        Builder::ALL
            .into_iter()
            .find(|b| b.name() == name.trim().to_ascii_lowercase())
            .ok_or_else(|| format!("RAYFARM_BUILDER={name:?}: expected ploc or sah"))
    }

    /// The default builder: the one that measured fewer instructions per ray (README,
    /// "Benchmarks").
    pub const DEFAULT: Builder = Builder::Sah;

    /// The process's builder: `RAYFARM_BUILDER` if set (an unknown name is reported once and
    /// the default used), else [`Builder::DEFAULT`].
    pub fn selected() -> Builder {
        static CHOSEN: OnceLock<Builder> = OnceLock::new();
        *CHOSEN.get_or_init(|| match std::env::var("RAYFARM_BUILDER") {
            Ok(name) => Builder::parse(&name).unwrap_or_else(|e| {
                tracing::warn!("{e}; building with {}", Builder::DEFAULT.name());
                Builder::DEFAULT
            }),
            Err(_) => Builder::DEFAULT,
        })
    }
}

/// `obvhs`'s PLOC binary tree collapsed into 8-wide nodes.
fn build_ploc(triangles: &mut Vec<PackedTriangle>) -> Built {
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

pub(super) const EMPTY_NODE: BvhNode = BvhNode {
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

pub(super) fn set_slot(node: &mut BvhNode, slot: usize, b: &Aabb, child: u32, meta: u32) {
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
