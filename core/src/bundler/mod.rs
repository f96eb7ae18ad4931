//! Outbound message bundling with priority tiers, per peer.
//!
//! Sending every small message on its own wastes per-message overhead, while holding
//! everything back for a big bundle delays the messages that other workers are waiting on.
//! Following the hybrid scheduler's buffering scheme, messages are sorted into three tiers;
//! each tier has its own size and age limits, so verdicts (which a peer's held rays wait on)
//! leave quickly and bulk ray traffic is bundled the most. Requests have no tier: a peer
//! asks for a domain with its own call, whose answer (the domain's bytes) is far too large
//! for a bundle.
//!
//! The bundler is pure: it performs no I/O and reads no clock. The caller passes the current
//! time as a [`Duration`] since an arbitrary epoch of its choosing (for instance the start of
//! the worker process) and sends the [`Bundle`]s it gets back. Time is treated as
//! monotonic: a `now` earlier than one seen before is taken to mean the latest one seen, so
//! a stepping clock can never make a message look younger than it is.
//!
//! Three ideas, a module each: the tiers and their limits (`config`), a peer's pending
//! messages and how a bundle is cut from them (`queue`), and the counters (`stats`); the
//! bundler here routes pushes to peers and drains due bundles tier by tier.

use std::collections::BTreeMap;
use std::error::Error;
use std::fmt;
use std::time::Duration;

use bytes::Bytes;

mod config;
mod queue;
mod stats;

pub use config::{BundlerConfig, ConfigError, Tier, TierPolicy};
use queue::{Drain, PeerQueues};
pub use stats::{Stats, TierStats};

/// Why [`Bundler::push`] refused a message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PushErrorKind {
    /// Backpressure: the peer's capped bytes would exceed the cap. Retry after a
    /// [`Bundler::poll`] has sent some of them (see [`Bundler::next_deadline`]).
    PeerFull {
        /// Capped bytes already pending for the peer.
        pending: usize,
        /// The configured cap.
        cap: usize,
    },
    /// The message alone exceeds the cap; retrying cannot help, so split it.
    MessageTooLarge {
        /// The message's length.
        len: usize,
        /// The configured cap.
        cap: usize,
    },
}

/// A refused push. It hands the message back so that nothing is ever dropped.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PushError {
    /// Why the message was refused.
    pub kind: PushErrorKind,
    /// The refused message, untouched.
    pub message: Bytes,
}

impl PushError {
    /// Takes the refused message back.
    pub fn into_message(self) -> Bytes {
        self.message
    }
}

impl fmt::Display for PushError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.kind {
            PushErrorKind::PeerFull { pending, cap } => write!(
                f,
                "peer is full: {pending} bytes pending, cap {cap}, message {} bytes",
                self.message.len()
            ),
            PushErrorKind::MessageTooLarge { len, cap } => {
                write!(f, "message of {len} bytes exceeds the peer cap of {cap}")
            }
        }
    }
}

impl Error for PushError {}

/// Messages for one peer and tier that are to be sent together, in push order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Bundle<P> {
    /// Destination.
    pub peer: P,
    /// Tier all the messages were pushed in.
    pub tier: Tier,
    /// The messages, oldest first.
    pub messages: Vec<Bytes>,
    /// Sum of the messages' lengths.
    pub bytes: usize,
}

/// Per-peer, per-tier message bundler. See the module documentation.
///
/// `P` identifies a peer; bundles of the same tier are emitted in `P`'s order.
#[derive(Debug)]
pub struct Bundler<P> {
    config: BundlerConfig,
    peers: BTreeMap<P, PeerQueues>,
    stats: Stats,
    /// Latest time seen, so that time never runs backwards inside the bundler.
    clock: Duration,
}

impl<P: Ord + Clone> Bundler<P> {
    /// Creates an empty bundler after validating `config`.
    pub fn new(config: BundlerConfig) -> Result<Self, ConfigError> {
        config.validate()?;
        Ok(Bundler {
            config,
            peers: BTreeMap::new(),
            stats: Stats::default(),
            clock: Duration::ZERO,
        })
    }

    /// The configuration in use.
    pub fn config(&self) -> &BundlerConfig {
        &self.config
    }

    /// Queues `message` for `peer` in `tier`, arriving at `now`.
    ///
    /// Nothing is sent here: call [`Bundler::poll`] afterwards (at once for a tier whose
    /// policy is immediate).
    /// A refused message is handed back inside the error.
    pub fn push(
        &mut self,
        peer: P,
        tier: Tier,
        message: impl Into<Bytes>,
        now: Duration,
    ) -> Result<(), PushError> {
        let message = message.into();
        let now = self.observe(now);
        if let Err(kind) = self.admit(&peer, tier, message.len()) {
            self.stats.tiers[tier.index()].rejected += 1;
            return Err(PushError { kind, message });
        }
        self.peers.entry(peer).or_default().push(tier, message, now);
        Ok(())
    }

    /// Removes and returns the bundles due at `now`: all due `Results` bundles of all peers,
    /// then all due `Migrated` bundles, and so on. Afterwards no tier of any peer is due.
    pub fn poll(&mut self, now: Duration) -> Vec<Bundle<P>> {
        let now = self.observe(now);
        self.drain(Drain::Due(now))
    }

    /// Removes and returns every pending message, due or not, in the same order as
    /// [`Bundler::poll`]; for the end of a round or shutdown.
    pub fn flush_all(&mut self, now: Duration) -> Vec<Bundle<P>> {
        self.observe(now);
        self.drain(Drain::All)
    }

    /// Removes and returns every pending message for one peer, most urgent tier first;
    /// for a peer that is going away, so that its messages can be rerouted, not lost.
    pub fn flush_peer(&mut self, peer: &P) -> Vec<Bundle<P>> {
        let Some((peer, mut queues)) = self.peers.remove_entry(peer) else {
            return Vec::new();
        };
        let mut out = Vec::new();
        for tier in Tier::MOST_URGENT_FIRST {
            let policy = self.config.policy(tier);
            while let Some((messages, bytes)) = queues.next_bundle(tier, &policy, Drain::All) {
                self.stats.tiers[tier.index()].record(messages.len(), bytes);
                out.push(bundle(&peer, tier, messages, bytes));
            }
        }
        out
    }

    /// Earliest time at which [`Bundler::poll`] will return something if nothing more is
    /// pushed, or `None` if nothing is pending. The caller can sleep exactly until then.
    /// A result at or before the latest `now` passed in means "poll at once".
    pub fn next_deadline(&self) -> Option<Duration> {
        self.peers
            .values()
            .flat_map(|queues| {
                Tier::MOST_URGENT_FIRST.into_iter().filter_map(|tier| {
                    queues.tiers[tier.index()].deadline(&self.config.policy(tier), self.clock)
                })
            })
            .min()
    }

    /// Counters per tier.
    pub fn stats(&self) -> &Stats {
        &self.stats
    }

    /// Bytes pending for `peer` in `tier`.
    pub fn pending_bytes(&self, peer: &P, tier: Tier) -> usize {
        self.peers
            .get(peer)
            .map_or(0, |queues| queues.tiers[tier.index()].bytes)
    }

    /// Bytes pending for `peer` in capped tiers, the amount compared against the cap.
    pub fn capped_pending_bytes(&self, peer: &P) -> usize {
        self.peers.get(peer).map_or(0, |queues| queues.capped_bytes)
    }

    /// Number of messages pending over all peers and tiers.
    pub fn pending_messages(&self) -> usize {
        self.peers
            .values()
            .flat_map(|queues| queues.tiers.iter())
            .map(|queue| queue.messages.len())
            .sum()
    }

    /// True if nothing is pending.
    pub fn is_empty(&self) -> bool {
        self.peers.is_empty()
    }

    fn observe(&mut self, now: Duration) -> Duration {
        self.clock = self.clock.max(now);
        self.clock
    }

    fn admit(&self, peer: &P, tier: Tier, len: usize) -> Result<(), PushErrorKind> {
        let Some(cap) = self.config.peer_cap_bytes.filter(|_| tier.is_capped()) else {
            return Ok(());
        };
        if len > cap {
            return Err(PushErrorKind::MessageTooLarge { len, cap });
        }
        let pending = self.capped_pending_bytes(peer);
        if pending + len > cap {
            return Err(PushErrorKind::PeerFull { pending, cap });
        }
        Ok(())
    }

    /// Tier-major walk over all peers, so every urgent bundle precedes every bulk one.
    fn drain(&mut self, drain: Drain) -> Vec<Bundle<P>> {
        let mut out = Vec::new();
        for tier in Tier::MOST_URGENT_FIRST {
            let policy = self.config.policy(tier);
            let stats = &mut self.stats.tiers[tier.index()];
            for (peer, queues) in &mut self.peers {
                while let Some((messages, bytes)) = queues.next_bundle(tier, &policy, drain) {
                    stats.record(messages.len(), bytes);
                    out.push(bundle(peer, tier, messages, bytes));
                }
            }
        }
        // Forget idle peers so that memory follows the live peer set, not its history.
        self.peers.retain(|_, queues| !queues.is_empty());
        out
    }
}

fn bundle<P: Clone>(peer: &P, tier: Tier, messages: Vec<Bytes>, bytes: usize) -> Bundle<P> {
    Bundle {
        peer: peer.clone(),
        tier,
        messages,
        bytes,
    }
}

#[cfg(test)]
mod tests;
