//! Coherent rays together: up to eight rays (a tile's neighbouring camera rays) walk the tree
//! in lock step. Each node is fetched once for the packet; every ray still runs its own box
//! test (the same [`Isa::slab`] as a single ray, with its own interval and best hit), and the
//! children any of them enters are visited in one shared near-to-far order (by the nearest
//! entry among the rays that enter each). Leaves are tested ray by ray with the single-ray
//! triangle test. When only one ray of the packet is left in a subtree, it finishes that
//! subtree on its own with the single-ray traversal: the packet has diverged there.
//!
//! The hits are those of single rays to the bit: a ray's nearest hit is the lowest (distance,
//! id) over every triangle it hits in its interval, whatever order leaves are visited in, and a
//! ray only leaves a subtree out where its own box test does (padded boxes: never the subtree
//! holding a hit) or where the subtree's nearest entry is beyond its best hit so far.

use std::mem::MaybeUninit;

use super::{
    Bvh, Entry, Hit, Isa, SLOT_INNER, STACK_ENTRIES, Stack, TraceRay, WIDTH, descend, leaf_nearest,
    prefetch_children,
};

/// Most rays in a packet.
pub const PACKET: usize = 8;

/// A child the packet will visit: node index or first block, its `meta`, the rays that
/// entered it (bit per ray) and the nearest of their entry distances.
#[derive(Clone, Copy)]
struct PacketEntry {
    child: u32,
    meta: u32,
    rays: u32,
    near: f32,
}

/// The packet traversal's stack, sized like [`Stack`]: a packet pushes at most `WIDTH - 1`
/// children per level, as a single ray does.
pub(super) struct PacketStack {
    entries: Box<[PacketEntry]>,
    len: usize,
}

impl PacketStack {
    pub(super) fn new() -> Self {
        let empty = PacketEntry {
            child: 0,
            meta: 0,
            rays: 0,
            near: 0.0,
        };
        PacketStack {
            entries: vec![empty; STACK_ENTRIES].into_boxed_slice(),
            len: 0,
        }
    }

    /// # Safety
    /// As [`Stack::push`]: a validated tree's traversal holds fewer than [`STACK_ENTRIES`].
    #[inline(always)]
    unsafe fn push(&mut self, e: PacketEntry) {
        // SAFETY: as the caller promises.
        unsafe { *self.entries.get_unchecked_mut(self.len) = e };
        self.len += 1;
    }

    #[inline(always)]
    fn pop(&mut self) -> Option<PacketEntry> {
        self.len = self.len.checked_sub(1)?;
        // SAFETY: `len` was below the number held.
        Some(unsafe { *self.entries.get_unchecked(self.len) })
    }
}

/// Transposes an 8x8 bit matrix held as bit `8 * row + column`: rays' child masks (a byte
/// per ray) become children's ray masks (a byte per child).
#[inline(always)]
fn transpose8(mut x: u64) -> u64 {
    let t = (x ^ (x >> 7)) & 0x00AA_00AA_00AA_00AA;
    x ^= t ^ (t << 7);
    let t = (x ^ (x >> 14)) & 0x0000_CCCC_0000_CCCC;
    x ^= t ^ (t << 14);
    let t = (x ^ (x >> 28)) & 0x0000_0000_F0F0_F0F0;
    x ^= t ^ (t << 28);
    x
}

/// The nearest hits of `rays` (at most [`PACKET`]), each within its own `[t0, t1]`, written to
/// `out`; the same hits as [`super::Traverser::nearest_hit`] ray by ray.
#[inline(always)]
pub(super) fn nearest_packet<K: Isa>(
    stack: &mut PacketStack,
    single: &mut Stack,
    bvh: Bvh,
    rays: &[TraceRay],
    t0: &[f32],
    t1: &[f32],
    out: &mut [Option<Hit>],
) {
    let n = rays.len();
    assert!(
        (1..=PACKET).contains(&n) && t0.len() == n && t1.len() == n && out.len() == n,
        "a packet holds 1 to {PACKET} rays, each with an interval and a place for its hit"
    );
    // Prepared in place (a prepared ray is hundreds of bytes: an array of them built and then
    // moved cost a copy per packet); lanes past `n` stay unset and are never in a ray mask.
    let mut prepared: [MaybeUninit<K::Ray>; PACKET] = [const { MaybeUninit::uninit() }; PACKET];
    for (p, ray) in prepared.iter_mut().zip(rays) {
        p.write(K::prepare(ray));
    }
    // SAFETY: only the rays of a ray mask are read, and their lanes (below `n`) were written.
    let ray = |r: usize| unsafe { prepared.get_unchecked(r).assume_init_ref() };
    let t0: [f32; PACKET] = std::array::from_fn(|i| t0[i.min(n - 1)]);
    let mut best: [Hit; PACKET] = std::array::from_fn(|i| Hit {
        t: t1[i.min(n - 1)],
        block: u32::MAX,
        lane: 0,
        id: u64::MAX,
    });
    stack.len = 0;
    let mut cur = PacketEntry {
        child: 0,
        meta: SLOT_INNER,
        rays: (1u32 << n) - 1,
        near: f32::NEG_INFINITY,
    };
    'visit: loop {
        if cur.rays & (cur.rays - 1) == 0 {
            // One ray left here: it finishes the subtree alone.
            let r = cur.rays.trailing_zeros() as usize & (PACKET - 1);
            let start = Entry {
                child: cur.child,
                meta: cur.meta,
                near: cur.near,
            };
            descend::<K>(single, bvh, ray(r), t0[r], start, &mut best[r]);
        } else if cur.meta == SLOT_INNER {
            // SAFETY: the root or a child index of a validated tree.
            let node = unsafe { bvh.node(cur.child) };
            // A packet's node counts once: it is fetched once for all its rays.
            super::counters::add(1, 0, 0);
            let mut per_ray = 0u64;
            let mut entered = 0u32;
            let mut nearest = [f32::INFINITY; WIDTH];
            let mut rays = cur.rays;
            while rays != 0 {
                let r = rays.trailing_zeros() as usize & (PACKET - 1);
                rays &= rays - 1;
                let mask = K::slab_nearest(node, ray(r), t0[r], best[r].t, &mut nearest);
                per_ray |= (mask as u64) << (8 * r);
                entered |= mask;
            }
            let per_child = transpose8(per_ray);
            let entry = |slot: usize| PacketEntry {
                child: node.child[slot],
                meta: node.meta[slot],
                rays: (per_child >> (8 * slot)) as u32 & 0xff,
                near: nearest[slot],
            };
            let mut mask = entered;
            if mask != 0 {
                let slot = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                let first = entry(slot);
                if mask == 0 {
                    cur = first;
                    continue;
                }
                prefetch_children(bvh, node, entered);
                // Sorted insertion of the entered children, farthest deepest; the nearest
                // becomes `cur`.
                let base = stack.len;
                // SAFETY: a validated tree's traversal holds fewer than STACK_ENTRIES.
                unsafe { stack.push(first) };
                while mask != 0 {
                    let slot = mask.trailing_zeros() as usize;
                    mask &= mask - 1;
                    let e = entry(slot);
                    let mut at = stack.len;
                    // SAFETY: as above.
                    unsafe { stack.push(e) };
                    let held = &mut stack.entries[..stack.len];
                    while at > base && held[at - 1].near < e.near {
                        held[at] = held[at - 1];
                        at -= 1;
                    }
                    held[at] = e;
                }
                if let Some(e) = stack.pop() {
                    cur = e;
                    continue;
                }
            }
        } else {
            // SAFETY: a leaf child's range of a validated tree.
            let blocks = unsafe { bvh.leaf(cur.child, cur.meta) };
            let mut rays = cur.rays;
            while rays != 0 {
                let r = rays.trailing_zeros() as usize & (PACKET - 1);
                rays &= rays - 1;
                leaf_nearest::<K>(blocks, cur.child, ray(r), t0[r], &mut best[r]);
            }
        }
        // The next entry some ray still needs: one whose nearest entry is not beyond its best.
        while let Some(mut e) = stack.pop() {
            // Every lane at once, without a branch per ray (those outside the mask are dropped).
            let mut live = 0;
            for (r, b) in best.iter().enumerate() {
                live |= ((e.near <= b.t) as u32) << r;
            }
            live &= e.rays;
            if live != 0 {
                e.rays = live;
                cur = e;
                continue 'visit;
            }
        }
        break;
    }
    for (o, b) in out.iter_mut().zip(&best) {
        *o = (b.block != u32::MAX).then_some(*b);
    }
}

#[cfg(test)]
mod tests {
    use super::transpose8;

    #[test]
    fn transpose8_swaps_rows_and_columns() {
        let mut x = 0x0123_4567_89ab_cdefu64;
        for _ in 0..64 {
            let t = transpose8(x);
            for row in 0..8 {
                for col in 0..8 {
                    assert_eq!(t >> (8 * col + row) & 1, x >> (8 * row + col) & 1);
                }
            }
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
        }
    }
}
