//! The traversal loops, written once over the box and triangle tests of an instruction set
//! ([`Isa`]): ordered nearest-hit, shadow any-hit, and the [`Traverser`] that holds their
//! stacks and dispatches to the selected kernel.

use super::packet::{PacketStack, nearest_packet};
#[cfg(target_arch = "x86_64")]
use super::x86;
use super::{
    Bvh, BvhNode, Hit, Kernel, MAX_DEPTH, PACKET, SLOT_INNER, TraceRay, WIDTH, counters,
    packets_selected,
};
use crate::geometry::{BLOCK, TriangleBlock, nearer};

/// A child to visit: node index or first block, its `meta`, and its entry distance.
#[derive(Clone, Copy)]
pub(super) struct Entry {
    pub(super) child: u32,
    pub(super) meta: u32,
    pub(super) near: f32,
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
    ///
    /// Only a dispatch, inlined into the caller: each kernel's loop is a function of its
    /// own, so the call into the selected one is the only call a ray makes (with the loops
    /// inlined here, this function had a large frame of its own to set up per ray).
    #[inline]
    pub fn nearest_hit(&mut self, bvh: Bvh, ray: &TraceRay, t0: f32, t1: f32) -> Option<Hit> {
        if bvh.nodes.is_empty() {
            return None;
        }
        let stack = &mut self.stack;
        match self.kernel {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: a traverser holds only a kernel this CPU supports (`with_kernel`).
            Kernel::Avx2 => unsafe { x86::nearest_avx2(stack, &bvh, ray, t0, t1) },
            #[cfg(target_arch = "x86_64")]
            Kernel::Sse => nearest_sse(stack, &bvh, ray, t0, t1),
            _ => nearest_scalar(stack, &bvh, ray, t0, t1),
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

    /// Whether anything is hit with `t0 <= t <= t1` (shadow rays). A dispatch, inlined as
    /// [`Traverser::nearest_hit`] is.
    #[inline]
    pub fn any_hit(&mut self, bvh: Bvh, ray: &TraceRay, t0: f32, t1: f32) -> bool {
        if bvh.nodes.is_empty() {
            return false;
        }
        let stack = &mut self.stack;
        match self.kernel {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: as in `nearest_hit`.
            Kernel::Avx2 => unsafe { x86::any_avx2(stack, &bvh, ray, t0, t1) },
            #[cfg(target_arch = "x86_64")]
            Kernel::Sse => any_sse(stack, &bvh, ray, t0, t1),
            _ => any_scalar(stack, &bvh, ray, t0, t1),
        }
    }
}

/// [`nearest`] with the SSE tests, out of line (see [`Traverser::nearest_hit`]).
#[cfg(target_arch = "x86_64")]
#[inline(never)]
fn nearest_sse(stack: &mut Stack, bvh: &Bvh, ray: &TraceRay, t0: f32, t1: f32) -> Option<Hit> {
    nearest::<x86::Sse>(stack, *bvh, ray, t0, t1)
}

/// [`nearest`] with the scalar tests, out of line.
#[inline(never)]
fn nearest_scalar(stack: &mut Stack, bvh: &Bvh, ray: &TraceRay, t0: f32, t1: f32) -> Option<Hit> {
    nearest::<Scalar>(stack, *bvh, ray, t0, t1)
}

/// [`any`] with the SSE tests, out of line.
#[cfg(target_arch = "x86_64")]
#[inline(never)]
fn any_sse(stack: &mut Stack, bvh: &Bvh, ray: &TraceRay, t0: f32, t1: f32) -> bool {
    any::<x86::Sse>(stack, *bvh, ray, t0, t1)
}

/// [`any`] with the scalar tests, out of line.
#[inline(never)]
fn any_scalar(stack: &mut Stack, bvh: &Bvh, ray: &TraceRay, t0: f32, t1: f32) -> bool {
    any::<Scalar>(stack, *bvh, ray, t0, t1)
}

/// The box and triangle tests of one instruction set; the traversal loops are written once over it.
pub(super) trait Isa {
    /// The ray with its values broadcast to this set's registers.
    type Ray: Copy;
    fn prepare(ray: &TraceRay) -> Self::Ray;
    /// `ray` for a run of node visits: [`Isa::slab`]'s values read anew from memory where
    /// that matters. The nearest-hit loop calls it whenever a run of node visits starts (at
    /// the root, and after a leaf when the next child is a node), so that to the register
    /// allocator the box test's values live only through the node visits and not across the
    /// leaf test (which needs every vector register): they are then loaded once per run
    /// instead of at every node visit.
    #[inline(always)]
    fn fresh(ray: &Self::Ray) -> Self::Ray {
        *ray
    }
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
    /// Keys that rank a node's children by entry distance, one per lane and all distinct: a
    /// distance's bits as a signed integer with its lowest three bits replaced by the slot.
    /// Among entered lanes (never NaN: `near <= far`) of non-negative distances a greater key
    /// is a farther child, except between distances within eight ulps, which are ordered by
    /// slot (negative distances, of an interval starting behind the origin, are ranked in
    /// reverse). Only the visiting order depends on this, which no hit does (ties go to the
    /// lower id); what matters is that the keys are distinct, so that ranks are a permutation.
    #[inline(always)]
    fn rank_keys(near: &[f32; WIDTH]) -> [i32; WIDTH] {
        std::array::from_fn(|lane| (near[lane].to_bits() as i32 & !7) | lane as i32)
    }
    /// The lanes whose key is greater than lane `slot`'s: the number of entered lanes among
    /// them is `slot`'s place in its entered siblings sorted farthest first.
    #[inline(always)]
    fn above(keys: &[i32; WIDTH], slot: usize) -> u32 {
        let mut lanes = 0;
        for (lane, &k) in keys.iter().enumerate() {
            lanes |= ((k > keys[slot]) as u32) << lane;
        }
        lanes
    }
    /// The watertight test of a block's four lanes (infinity for a miss), and a bit mask of
    /// the lanes whose hit lies in `[t0, t1]`.
    fn block(block: &TriangleBlock, ray: &Self::Ray, t0: f32, t1: f32) -> ([f32; BLOCK], u32);
}

pub(super) struct Scalar;

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
                let tn = node.bounds[ray.row(a)][lane] * ray.inv[a] - ray.origin_inv[a];
                let tf = node.bounds[ray.row(3 + a)][lane] * ray.inv[a] - ray.origin_inv[a];
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
pub(super) fn prefetch_children(bvh: Bvh, node: &BvhNode, mut mask: u32) {
    while mask != 0 {
        let slot = mask.trailing_zeros() as usize;
        mask &= mask - 1;
        prefetch_child(bvh, node, slot);
    }
}

/// Asks the cache for the four 64-byte lines from `base`, which need not point into anything
/// (a prefetch never faults, the address is only a hint).
#[inline(always)]
fn prefetch_lines(base: *const i8) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        // SAFETY: a prefetch never faults; the address is only a hint.
        unsafe {
            _mm_prefetch::<_MM_HINT_T0>(base);
            _mm_prefetch::<_MM_HINT_T0>(base.wrapping_add(64));
            _mm_prefetch::<_MM_HINT_T0>(base.wrapping_add(128));
            _mm_prefetch::<_MM_HINT_T0>(base.wrapping_add(192));
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = base;
}

/// Asks the cache for the four lines of node `index`, which need not exist (a prefetch of an
/// address past the nodes is harmless).
#[inline(always)]
pub(super) fn prefetch_node(bvh: Bvh, index: usize) {
    prefetch_lines(bvh.nodes.as_ptr().wrapping_add(index).cast::<i8>());
}

/// Asks the cache for the node or first leaf block of the child in `slot`: four lines
/// whatever the child, a node's four or a block's three and the first of the leaf's next
/// block (no loop or branch on the kind).
#[inline(always)]
pub(super) fn prefetch_child(bvh: Bvh, node: &BvhNode, slot: usize) {
    let (child, meta) = (node.child[slot] as usize, node.meta[slot]);
    let base = if meta == SLOT_INNER {
        bvh.nodes.as_ptr().wrapping_add(child).cast::<i8>()
    } else {
        bvh.blocks.as_ptr().wrapping_add(child).cast::<i8>()
    };
    prefetch_lines(base);
}

/// Tests a leaf's blocks (`first` is the index of the first), keeping the nearest hit (ties
/// to the lower id).
#[inline(always)]
pub(super) fn leaf_nearest<K: Isa>(
    blocks: &[TriangleBlock],
    first: u32,
    ray: &K::Ray,
    t0: f32,
    best: &mut Hit,
) {
    counters::add(0, 1, 0);
    for (k, b) in (first..).zip(blocks) {
        counters::add(0, 0, 1);
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
pub(super) struct Stack {
    entries: Box<[Entry]>,
    len: usize,
}

/// Entries a traversal can hold: each level leaves at most `WIDTH - 1` siblings waiting.
pub(super) const STACK_ENTRIES: usize = MAX_DEPTH * (WIDTH - 1) + 1;

impl Stack {
    pub(super) fn new() -> Self {
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
pub(super) fn nearest<K: Isa>(
    stack: &mut Stack,
    bvh: Bvh,
    ray: &TraceRay,
    t0: f32,
    t1: f32,
) -> Option<Hit> {
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
///
/// The stack is held as a pointer above its top entry, in a register, rather than as
/// [`Stack`]'s length: a length in the struct is written back at every push and pop (LLVM
/// cannot tell that the entries' stores leave it alone), and an index needs an address
/// computed from it at every access.
#[inline(always)]
pub(super) fn descend<K: Isa>(
    stack: &mut Stack,
    bvh: Bvh,
    r: &K::Ray,
    t0: f32,
    start: Entry,
    best_out: &mut Hit,
) {
    let mut best = *best_out;
    let bottom = stack.entries.as_mut_ptr();
    // One past the highest entry held; `bottom` when none is.
    let mut top = bottom;
    let mut cur = start;
    'next: loop {
        // Inner nodes, in a loop of their own until a leaf is reached: the box test's ray
        // registers are used only here, so the register allocator can keep them here and
        // save them only around the leaf test (which needs every vector register), rather than
        // reloading them at every node visit.
        let boxes = if cur.meta == SLOT_INNER {
            K::fresh(r)
        } else {
            *r
        };
        while cur.meta == SLOT_INNER {
            // SAFETY: the root or a child index of a validated tree.
            let node = unsafe { bvh.node(cur.child) };
            counters::add(1, 0, 0);
            // The SAH builder writes nodes depth first, so the node after this one is one of
            // its inner children (when it has any), and the one after that often a grandchild:
            // their memory is asked for now, before the box test says which child is
            // entered, so that where the ray goes that way the next two levels' cache misses
            // overlap with this node's work instead of following it one after the other.
            // Eight instructions a visit for 7-13% more incoherent rays a second (one level
            // ahead alone: 5-9%; README, "Benchmarks"). Hits do not depend on it.
            prefetch_node(bvh, cur.child as usize + 1);
            prefetch_node(bvh, cur.child as usize + 2);
            let (near, mut mask) = K::slab(node, &boxes, t0, best.t);
            if mask == 0 {
                // SAFETY: `top` and `bottom` bound the held entries.
                match unsafe { pop_within(&mut top, bottom, best.t) } {
                    Some(e) => {
                        cur = e;
                        continue;
                    }
                    None => break 'next,
                }
            }
            let first_slot = mask.trailing_zeros() as usize;
            mask &= mask - 1;
            if mask == 0 {
                cur = Entry {
                    child: node.child[first_slot],
                    meta: node.meta[first_slot],
                    near: near[first_slot],
                };
                continue;
            }
            if mask & (mask - 1) == 0 {
                // Two entered children, the commonest case: one comparison orders them,
                // and the farther one's memory is asked for now, so its cache misses
                // overlap with the work on the nearer (which is loaded at once anyway).
                // The order picks slots, not entries, so it is two conditional moves
                // rather than a branch (which way it goes is a coin toss per node).
                let slot = mask.trailing_zeros() as usize;
                let swap = near[slot] < near[first_slot];
                let near_slot = if swap { slot } else { first_slot };
                let far_slot = if swap { first_slot } else { slot };
                prefetch_child(bvh, node, far_slot);
                let entry = |s: usize| Entry {
                    child: node.child[s],
                    meta: node.meta[s],
                    near: near[s],
                };
                // SAFETY: a validated tree's traversal holds fewer than STACK_ENTRIES
                // (each level leaves at most WIDTH - 1 siblings), so `top` stays within
                // the stack's entries.
                unsafe {
                    top.write(entry(far_slot));
                    top = top.add(1);
                }
                cur = entry(near_slot);
                continue;
            }
            // The entered children go onto the stack sorted, farthest deepest, the nearest
            // on top (it becomes `cur`): each is written straight to its place, its rank
            // among its siblings (how many have a greater key: [`Isa::rank_keys`]), so there are no
            // compares between entries and no moves (an insertion sort's compares are
            // unpredictable branches). Every entered child's memory is asked for in the
            // same pass, so the cache misses of the siblings overlap with the work on the
            // nearest.
            let all = mask | 1 << first_slot;
            let keys = K::rank_keys(&near);
            let mut m = all;
            while m != 0 {
                let slot = m.trailing_zeros() as usize;
                m &= m - 1;
                prefetch_child(bvh, node, slot);
                let rank = (K::above(&keys, slot) & all).count_ones();
                let entry = Entry {
                    child: node.child[slot],
                    meta: node.meta[slot],
                    near: near[slot],
                };
                // SAFETY: `rank` is below the number of entered children, at most WIDTH,
                // and a validated tree's traversal holds fewer than STACK_ENTRIES.
                unsafe { top.add(rank as usize).write(entry) };
            }
            // SAFETY: the entered children were just written from `top` up; the nearest,
            // the highest, is visited now and the others stay held.
            unsafe {
                top = top.add(all.count_ones() as usize - 1);
                cur = top.read();
            }
        }
        // SAFETY: a leaf child's range of a validated tree.
        let blocks = unsafe { bvh.leaf(cur.child, cur.meta) };
        leaf_nearest::<K>(blocks, cur.child, r, t0, &mut best);
        // SAFETY: `top` and `bottom` bound the held entries.
        match unsafe { pop_within(&mut top, bottom, best.t) } {
            Some(e) => cur = e,
            None => break,
        }
    }
    *best_out = best;
}

/// Takes entries off the stack (`bottom` up to below `top`) until one no farther than `t`,
/// which it returns; `None` when the stack is empty.
///
/// # Safety
/// `bottom..top` must be the held entries of one stack.
#[inline(always)]
unsafe fn pop_within(top: &mut *mut Entry, bottom: *mut Entry, t: f32) -> Option<Entry> {
    while *top != bottom {
        // SAFETY: `top` is above `bottom`, so an entry is held below it.
        let e = unsafe {
            *top = top.sub(1);
            top.read()
        };
        if e.near <= t {
            return Some(e);
        }
    }
    None
}

/// Whether a leaf's blocks hold a hit in `[t0, t1]`.
#[inline(always)]
pub(super) fn leaf_any<K: Isa>(blocks: &[TriangleBlock], ray: &K::Ray, t0: f32, t1: f32) -> bool {
    counters::add(0, 1, 0);
    blocks.iter().any(|b| {
        counters::add(0, 0, 1);
        K::block(b, ray, t0, t1).1 != 0
    })
}

/// Shadow-ray traversal: no order and no distances kept; a node's leaf children are tested at
/// once (a blocker ends the ray), its inner children wait on the stack.
#[inline(always)]
pub(super) fn any<K: Isa>(stack: &mut Stack, bvh: Bvh, ray: &TraceRay, t0: f32, t1: f32) -> bool {
    let r = K::prepare(ray);
    any_from::<K>(stack, bvh, &r, t0, t1, 0)
}

/// [`any`] of the subtree under inner node `node` (the root, for a whole ray).
#[inline(always)]
pub(super) fn any_from<K: Isa>(
    stack: &mut Stack,
    bvh: Bvh,
    r: &K::Ray,
    t0: f32,
    t1: f32,
    mut node: u32,
) -> bool {
    stack.len = 0;
    loop {
        // SAFETY: the root or a child index of a validated tree.
        let n = unsafe { bvh.node(node) };
        counters::add(1, 0, 0);
        let (_, mut mask) = K::slab(n, r, t0, t1);
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
                if leaf_any::<K>(blocks, r, t0, t1) {
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
