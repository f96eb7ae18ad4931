//! Counters of what the bundler emitted and refused, per tier.

use std::ops::Index;

use super::Tier;

/// Counters of one tier.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct TierStats {
    /// Bundles emitted.
    pub bundles: u64,
    /// Messages emitted.
    pub messages: u64,
    /// Bytes emitted.
    pub bytes: u64,
    /// Pushes refused (backpressure or too large).
    pub rejected: u64,
}

impl TierStats {
    /// Counts one bundle emitted.
    pub(super) fn record(&mut self, bundle_messages: usize, bundle_bytes: usize) {
        self.bundles += 1;
        self.messages += bundle_messages as u64;
        self.bytes += bundle_bytes as u64;
    }

    /// Adds `other` into `self`.
    pub fn add(&mut self, other: &TierStats) {
        self.bundles += other.bundles;
        self.messages += other.messages;
        self.bytes += other.bytes;
        self.rejected += other.rejected;
    }
}

/// Counters of all tiers; index with a [`Tier`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Stats {
    pub(super) tiers: [TierStats; Tier::COUNT],
}

impl Stats {
    /// Sum over all tiers.
    pub fn total(&self) -> TierStats {
        let mut total = TierStats::default();
        self.tiers.iter().for_each(|t| total.add(t));
        total
    }
}

impl Index<Tier> for Stats {
    type Output = TierStats;

    fn index(&self, tier: Tier) -> &TierStats {
        &self.tiers[tier.index()]
    }
}
