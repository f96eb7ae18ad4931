//! Counts of a traversal's work on this thread (node visits, leaf visits, block tests), to
//! compare trees and layouts by what a ray touches rather than by time. Compiled in only with
//! the `counters` feature: without it the calls in the loops are empty and vanish.

#[cfg(feature = "counters")]
use std::cell::Cell;

/// What the traversals on one thread have done since the last [`take`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Counts {
    /// Inner nodes whose eight boxes were tested.
    pub nodes: u64,
    /// Leaves whose blocks were tested.
    pub leaves: u64,
    /// Triangle blocks tested.
    pub blocks: u64,
}

#[cfg(feature = "counters")]
thread_local! {
    static COUNTS: Cell<Counts> = const { Cell::new(Counts { nodes: 0, leaves: 0, blocks: 0 }) };
}

/// Whether this build counts (the `counters` feature).
pub const ENABLED: bool = cfg!(feature = "counters");

/// This thread's counts since the last call (all zero without the `counters` feature).
pub fn take() -> Counts {
    #[cfg(feature = "counters")]
    {
        COUNTS.with(|c| c.take())
    }
    #[cfg(not(feature = "counters"))]
    Counts::default()
}

/// Adds to this thread's counts.
#[inline(always)]
pub(super) fn add(nodes: u64, leaves: u64, blocks: u64) {
    #[cfg(feature = "counters")]
    COUNTS.with(|c| {
        let mut v = c.get();
        v.nodes += nodes;
        v.leaves += leaves;
        v.blocks += blocks;
        c.set(v);
    });
    #[cfg(not(feature = "counters"))]
    let _ = (nodes, leaves, blocks);
}
