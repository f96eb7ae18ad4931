//! Outbound message bundling with priority tiers, per peer.
//!
//! Sending every small message on its own wastes per-message overhead, while holding
//! everything back for a big bundle delays the messages that other workers are waiting on.
//! Following the hybrid scheduler's buffering scheme, messages are sorted into four tiers;
//! each tier has its own size and age limits, so data requests leave at once, results (which
//! free memory on arrival) leave quickly, and bulk ray traffic is bundled the most.
//!
//! The bundler is pure: it performs no I/O and reads no clock. The caller passes the current
//! time as a [`Duration`] since an arbitrary epoch of its choosing (for instance the start of
//! the worker process) and sends the [`Bundle`]s it gets back. Time is treated as
//! monotonic: a `now` earlier than one seen before is taken to mean the latest one seen, so
//! a stepping clock can never make a message look younger than it is.

use std::collections::{BTreeMap, VecDeque};
use std::error::Error;
use std::fmt;
use std::ops::Index;
use std::time::Duration;

use bytes::Bytes;

/// Priority tier of an outbound message.
///
/// A lower number is MORE urgent: `Control` (0) is the most urgent, `Tasks` (3) the least.
/// The derived `Ord` follows the number, so sorting ascending puts the most urgent first.
/// Prefer [`Tier::is_more_urgent_than`] over comparing tiers with `<` in calling code.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[repr(u8)]
pub enum Tier {
    /// Control messages and data (domain) requests: sent at once, never bundled for long.
    Control = 0,
    /// Tile results and returned credit: sent fast because their arrival frees memory.
    Results = 1,
    /// Data-parallel rays migrated to the owner of their domain.
    Migrated = 2,
    /// Demand-driven tasks: bundled the most.
    Tasks = 3,
}

impl Tier {
    /// Number of tiers.
    pub const COUNT: usize = 4;

    /// All tiers, most urgent first; this is the order in which bundles are emitted.
    pub const MOST_URGENT_FIRST: [Tier; Tier::COUNT] =
        [Tier::Control, Tier::Results, Tier::Migrated, Tier::Tasks];

    /// Position of the tier in per-tier arrays (its number, 0 = most urgent).
    pub const fn index(self) -> usize {
        self as usize
    }

    /// Tier with the given number, if any.
    pub const fn from_index(index: usize) -> Option<Tier> {
        match index {
            0 => Some(Tier::Control),
            1 => Some(Tier::Results),
            2 => Some(Tier::Migrated),
            3 => Some(Tier::Tasks),
            _ => None,
        }
    }

    /// True if `self` must be sent before `other` when both are due.
    pub const fn is_more_urgent_than(self, other: Tier) -> bool {
        (self as u8) < (other as u8)
    }

    /// True for the bulk ray tiers that the per-peer byte cap applies to.
    ///
    /// Control and result messages are exempt: refusing them would stall exactly the
    /// messages that unblock peers and free memory, and they never sit for long anyway.
    pub const fn is_capped(self) -> bool {
        matches!(self, Tier::Migrated | Tier::Tasks)
    }
}

/// When a tier's pending messages for one peer are flushed.
///
/// A tier is due when its pending bytes reach `max_bytes` or its oldest message has waited
/// `max_age`. `max_bytes` is also the largest bundle the tier emits, except that a single
/// message larger than it travels alone (messages are never split).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TierPolicy {
    /// Size trigger and bundle size limit, in bytes. Must be positive.
    pub max_bytes: usize,
    /// Age trigger; zero means "due as soon as anything is pending".
    pub max_age: Duration,
}

impl TierPolicy {
    /// Policy that sends at once, packing what is pending into bundles of up to `max_bytes`.
    pub const fn immediate(max_bytes: usize) -> Self {
        TierPolicy {
            max_bytes,
            max_age: Duration::ZERO,
        }
    }

    /// True if the tier is due whenever it has anything pending.
    pub const fn is_immediate(&self) -> bool {
        self.max_age.is_zero()
    }
}

/// Configuration of a [`Bundler`]: one policy per tier and an optional per-peer byte cap.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BundlerConfig {
    /// Policy per tier, indexed by [`Tier::index`].
    pub policies: [TierPolicy; Tier::COUNT],
    /// Most bytes of capped (bulk) tiers, see [`Tier::is_capped`], pending for one peer;
    /// `None` leaves memory unbounded.
    pub peer_cap_bytes: Option<usize>,
}

const KIB: usize = 1024;
const MIB: usize = 1024 * KIB;

impl Default for BundlerConfig {
    /// Control: immediate, 64 KiB bundles. Results: 16 KiB / 1 ms. Migrated: 256 KiB / 5 ms.
    /// Tasks: 1 MiB / 20 ms. Peer cap: 8 MiB of bulk traffic.
    fn default() -> Self {
        BundlerConfig {
            policies: [
                TierPolicy::immediate(64 * KIB),
                TierPolicy {
                    max_bytes: 16 * KIB,
                    max_age: Duration::from_millis(1),
                },
                TierPolicy {
                    max_bytes: 256 * KIB,
                    max_age: Duration::from_millis(5),
                },
                TierPolicy {
                    max_bytes: MIB,
                    max_age: Duration::from_millis(20),
                },
            ],
            peer_cap_bytes: Some(8 * MIB),
        }
    }
}

impl BundlerConfig {
    /// Policy of one tier.
    pub fn policy(&self, tier: Tier) -> TierPolicy {
        self.policies[tier.index()]
    }

    /// Returns the configuration with `tier`'s policy replaced.
    pub fn with_policy(mut self, tier: Tier, policy: TierPolicy) -> Self {
        self.policies[tier.index()] = policy;
        self
    }

    /// Returns the configuration with the per-peer cap replaced.
    pub fn with_peer_cap(mut self, peer_cap_bytes: Option<usize>) -> Self {
        self.peer_cap_bytes = peer_cap_bytes;
        self
    }

    /// Checks that the configuration makes sense; [`Bundler::new`] calls this.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.validate_sizes()?;
        self.validate_ages()?;
        self.validate_cap()
    }

    fn validate_sizes(&self) -> Result<(), ConfigError> {
        match Tier::MOST_URGENT_FIRST
            .into_iter()
            .find(|&tier| self.policy(tier).max_bytes == 0)
        {
            Some(tier) => Err(ConfigError::ZeroMaxBytes { tier }),
            None => Ok(()),
        }
    }

    fn validate_ages(&self) -> Result<(), ConfigError> {
        let control = self.policy(Tier::Control);
        if !control.is_immediate() {
            return Err(ConfigError::ControlNotImmediate {
                max_age: control.max_age,
            });
        }
        for pair in Tier::MOST_URGENT_FIRST.windows(2) {
            let (urgent, bulk) = (pair[0], pair[1]);
            if self.policy(urgent).max_age > self.policy(bulk).max_age {
                return Err(ConfigError::UrgencyInversion {
                    more_urgent: urgent,
                    less_urgent: bulk,
                });
            }
        }
        Ok(())
    }

    fn validate_cap(&self) -> Result<(), ConfigError> {
        let Some(cap) = self.peer_cap_bytes else {
            return Ok(());
        };
        if cap == 0 {
            return Err(ConfigError::ZeroPeerCap);
        }
        // A cap below a bulk tier's bundle size would block pushes before the size trigger
        // could ever fire, leaving that tier to crawl along on its age trigger.
        let capped = Tier::MOST_URGENT_FIRST
            .into_iter()
            .filter(|t| t.is_capped());
        for tier in capped {
            let max_bytes = self.policy(tier).max_bytes;
            if cap < max_bytes {
                return Err(ConfigError::PeerCapBelowBundle {
                    tier,
                    max_bytes,
                    cap,
                });
            }
        }
        Ok(())
    }
}

/// A [`BundlerConfig`] that makes no sense.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConfigError {
    /// A tier has `max_bytes == 0`; it could never hold a message.
    ZeroMaxBytes {
        /// Offending tier.
        tier: Tier,
    },
    /// The control tier has a nonzero `max_age`; control must be sent at once.
    ControlNotImmediate {
        /// The configured age.
        max_age: Duration,
    },
    /// A more urgent tier waits longer than a less urgent one.
    UrgencyInversion {
        /// The tier that should be faster.
        more_urgent: Tier,
        /// The tier that is faster instead.
        less_urgent: Tier,
    },
    /// The per-peer cap is zero; nothing bulk could ever be sent.
    ZeroPeerCap,
    /// The per-peer cap is smaller than a capped tier's `max_bytes`.
    PeerCapBelowBundle {
        /// Offending tier.
        tier: Tier,
        /// That tier's `max_bytes`.
        max_bytes: usize,
        /// The configured cap.
        cap: usize,
    },
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ConfigError::ZeroMaxBytes { tier } => {
                write!(f, "tier {tier:?}: max_bytes must be positive")
            }
            ConfigError::ControlNotImmediate { max_age } => write!(
                f,
                "tier Control must be sent at once, but has max_age {max_age:?} (use zero)"
            ),
            ConfigError::UrgencyInversion {
                more_urgent,
                less_urgent,
            } => write!(
                f,
                "tier {more_urgent:?} is more urgent than {less_urgent:?} \
                 but has a longer max_age"
            ),
            ConfigError::ZeroPeerCap => write!(f, "peer_cap_bytes must be positive or None"),
            ConfigError::PeerCapBelowBundle {
                tier,
                max_bytes,
                cap,
            } => write!(
                f,
                "peer_cap_bytes {cap} is below tier {tier:?} max_bytes {max_bytes}; \
                 the size trigger could never fire"
            ),
        }
    }
}

impl Error for ConfigError {}

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
    fn record(&mut self, bundle_messages: usize, bundle_bytes: usize) {
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
    tiers: [TierStats; Tier::COUNT],
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

/// One pending message and when it was pushed.
#[derive(Debug)]
struct Pending {
    payload: Bytes,
    arrived: Duration,
}

/// Pending messages of one peer and tier, oldest first.
#[derive(Debug, Default)]
struct TierQueue {
    messages: VecDeque<Pending>,
    bytes: usize,
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
    fn deadline(&self, policy: &TierPolicy, already: Duration) -> Option<Duration> {
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
enum Drain {
    /// Only while the queue is due at this time.
    Due(Duration),
    /// Everything.
    All,
}

/// All pending messages of one peer.
#[derive(Debug, Default)]
struct PeerQueues {
    tiers: [TierQueue; Tier::COUNT],
    /// Bytes pending in capped tiers, compared against the cap.
    capped_bytes: usize,
}

impl PeerQueues {
    fn push(&mut self, tier: Tier, payload: Bytes, arrived: Duration) {
        if tier.is_capped() {
            self.capped_bytes += payload.len();
        }
        self.tiers[tier.index()].push(payload, arrived);
    }

    fn next_bundle(
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

    fn is_empty(&self) -> bool {
        self.tiers.iter().all(|q| q.messages.is_empty())
    }
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
    /// Nothing is sent here: call [`Bundler::poll`] afterwards (at once for `Control`).
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

    /// Removes and returns the bundles due at `now`: all due `Control` bundles of all peers,
    /// then all due `Results` bundles, and so on. Afterwards no tier of any peer is due.
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
