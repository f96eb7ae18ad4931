//! Which workers may send results of which tile: a result is credit coming home, and credit
//! only reaches a worker in rays it was given.
//!
//! A tile's rays reach a worker in two ways. Its camera rays are dealt to exactly one worker
//! per epoch (at the frame's start, in a hand-out, or re-dealt after a loss). Every later ray
//! goes where its domain is held, and under the schedules that route rays (dynamic,
//! predictive, domain, hybrid) a ray of any tile may enter any domain: a worker that has been
//! named a holder of some domain may legitimately retire rays of every tile. Nor can a holder
//! named only in an earlier round be ruled out, since peers route by the holders they last
//! heard of, which may be a round behind. So what can be checked is:
//!
//! - a worker never named a holder in this frame may send results only for tiles whose camera
//!   rays were dealt to it at the tile's current epoch (under image-plane, that is every
//!   worker, and the check is exact);
//! - a worker named a holder may send results of any tile (the ledger's credit and pixel
//!   bounds still apply).
//!
//! Results of an older epoch than the tile's are ignored by the ledger whoever sends them, so
//! only the current epoch's dealing is kept: one key per tile.

use std::collections::BTreeSet;

/// See the module documentation.
#[derive(Clone, Debug, Default)]
pub struct Grants {
    /// By tile: the worker its camera rays went to at its current epoch, if dealt yet.
    dealt: Vec<Option<u32>>,
    /// Workers named a holder of some domain in this frame.
    holders: BTreeSet<u32>,
}

impl Grants {
    /// Nothing dealt yet of `tiles` tiles.
    pub fn new(tiles: u32) -> Self {
        Grants {
            dealt: vec![None; tiles as usize],
            holders: BTreeSet::new(),
        }
    }

    /// `tiles`' camera rays are dealt to `key` at their current epochs.
    pub fn deal(&mut self, key: u32, tiles: &[u32]) {
        for &t in tiles {
            if let Some(d) = self.dealt.get_mut(t as usize) {
                *d = Some(key);
            }
        }
    }

    /// `tiles` entered a new epoch whose camera rays are nobody's until dealt again.
    pub fn withdraw(&mut self, tiles: impl IntoIterator<Item = u32>) {
        for t in tiles {
            if let Some(d) = self.dealt.get_mut(t as usize) {
                *d = None;
            }
        }
    }

    /// `key` was named a holder of a domain: peers may send it rays of any tile.
    pub fn name_holder(&mut self, key: u32) {
        self.holders.insert(key);
    }

    /// Whether `key` may send results of `tile` at the tile's current epoch.
    pub fn may_send(&self, key: u32, tile: u32) -> bool {
        self.holders.contains(&key) || self.dealt.get(tile as usize) == Some(&Some(key))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_dealt_worker_or_a_holder_may_send_a_tiles_results() {
        let mut g = Grants::new(4);
        assert!(!g.may_send(0, 1), "nothing dealt yet");
        g.deal(0, &[0, 1]);
        g.deal(1, &[2, 3]);
        assert!(g.may_send(0, 1) && !g.may_send(1, 1) && g.may_send(1, 3));
        // Re-dealt after a loss: the new epoch is the new worker's only.
        g.withdraw([1]);
        assert!(!g.may_send(0, 1));
        g.deal(1, &[1]);
        assert!(g.may_send(1, 1) && !g.may_send(0, 1));
        // A holder may be sent rays of any tile; out-of-range tiles are nobody's.
        g.name_holder(2);
        assert!((0..4).all(|t| g.may_send(2, t)) && !g.may_send(0, 9));
    }
}
