//! A peer's pending messages, a queue per tier, and how a bundle is cut from a queue: the
//! longest run of oldest messages that fits the tier's size, never splitting a message.

use std::collections::VecDeque;
use std::time::Duration;

use bytes::Bytes;

use super::{Tier, TierPolicy};

/// One pending message and when it was pushed.
#[derive(Debug)]
pub(super) struct Pending {
    payload: Bytes,
    arrived: Duration,
}

/// Pending messages of one peer and tier, oldest first.
#[derive(Debug, Default)]
pub(super) struct TierQueue {
    pub(super) messages: VecDeque<Pending>,
    /// Sum of the messages' lengths.
    pub(super) bytes: usize,
}

impl TierQueue {
    fn push(&mut self, payload: Bytes, arrived: Duration) {
        self.bytes += payload.len();
        self.messages.push_back(Pending { payload, arrived });
    }

    fn is_due(&self, policy: &TierPolicy, now: Duration) -> bool {
        self.messages.front().is_some_and(|oldest| {
            self.bytes >= policy.max_bytes || now >= oldest.arrived.saturating_add(policy.max_age)
        })
    }

    /// When the queue becomes due if nothing else is pushed; `already` if it is due by size.
    pub(super) fn deadline(&self, policy: &TierPolicy, already: Duration) -> Option<Duration> {
        let oldest = self.messages.front()?;
        if self.bytes >= policy.max_bytes {
            return Some(already);
        }
        Some(oldest.arrived.saturating_add(policy.max_age))
    }

    /// Takes the longest run of oldest messages fitting in `max_bytes`, or the oldest message
    /// alone if it does not fit by itself (messages are never split).
    fn cut(&mut self, max_bytes: usize) -> Option<(Vec<Bytes>, usize)> {
        let first = self.messages.pop_front()?;
        let mut bytes = first.payload.len();
        let mut messages = vec![first.payload];
        while let Some(next) = self.messages.front() {
            let grown = bytes + next.payload.len();
            if grown > max_bytes {
                break;
            }
            bytes = grown;
            messages.extend(self.messages.pop_front().map(|p| p.payload));
        }
        self.bytes -= bytes;
        Some((messages, bytes))
    }
}

/// Which pending messages a drain takes.
#[derive(Debug, Clone, Copy)]
pub(super) enum Drain {
    /// Only while the queue is due at this time.
    Due(Duration),
    /// Everything.
    All,
}

/// All pending messages of one peer.
#[derive(Debug, Default)]
pub(super) struct PeerQueues {
    pub(super) tiers: [TierQueue; Tier::COUNT],
    /// Bytes pending in capped tiers, compared against the cap.
    pub(super) capped_bytes: usize,
}

impl PeerQueues {
    pub(super) fn push(&mut self, tier: Tier, payload: Bytes, arrived: Duration) {
        if tier.is_capped() {
            self.capped_bytes += payload.len();
        }
        self.tiers[tier.index()].push(payload, arrived);
    }

    pub(super) fn next_bundle(
        &mut self,
        tier: Tier,
        policy: &TierPolicy,
        drain: Drain,
    ) -> Option<(Vec<Bytes>, usize)> {
        let queue = &mut self.tiers[tier.index()];
        if let Drain::Due(now) = drain
            && !queue.is_due(policy, now)
        {
            return None;
        }
        let (messages, bytes) = queue.cut(policy.max_bytes)?;
        if tier.is_capped() {
            self.capped_bytes -= bytes;
        }
        Some((messages, bytes))
    }

    pub(super) fn is_empty(&self) -> bool {
        self.tiers.iter().all(|q| q.messages.is_empty())
    }
}
