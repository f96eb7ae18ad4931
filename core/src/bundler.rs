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
mod tests {
    use super::*;

    const MS: Duration = Duration::from_millis(1);
    const US: Duration = Duration::from_micros(1);

    fn at(ms: u64) -> Duration {
        Duration::from_millis(ms)
    }

    fn bundler() -> Bundler<u32> {
        Bundler::new(BundlerConfig::default()).expect("default config is valid")
    }

    fn msg(len: usize) -> Vec<u8> {
        vec![7; len]
    }

    fn tagged(tag: u8, len: usize) -> Bytes {
        Bytes::from(vec![tag; len])
    }

    #[test]
    fn default_config_is_valid_and_ordered() {
        let config = BundlerConfig::default();
        assert_eq!(config.validate(), Ok(()));
        assert!(config.policy(Tier::Control).is_immediate());
        assert!(Tier::Control.is_more_urgent_than(Tier::Results));
        assert!(!Tier::Tasks.is_more_urgent_than(Tier::Migrated));
        for (i, tier) in Tier::MOST_URGENT_FIRST.into_iter().enumerate() {
            assert_eq!(Tier::from_index(i), Some(tier));
            assert_eq!(tier.index(), i);
        }
        assert_eq!(Tier::from_index(Tier::COUNT), None);
    }

    #[test]
    fn nonsense_configs_are_rejected() {
        let base = BundlerConfig::default();
        let zero = base.with_policy(
            Tier::Migrated,
            TierPolicy {
                max_bytes: 0,
                max_age: MS,
            },
        );
        assert_eq!(
            zero.validate(),
            Err(ConfigError::ZeroMaxBytes {
                tier: Tier::Migrated
            })
        );
        assert!(
            zero.validate()
                .unwrap_err()
                .to_string()
                .contains("Migrated")
        );

        let slow_control = base.with_policy(
            Tier::Control,
            TierPolicy {
                max_bytes: 10,
                max_age: MS,
            },
        );
        assert!(matches!(
            slow_control.validate(),
            Err(ConfigError::ControlNotImmediate { .. })
        ));

        let inverted = base.with_policy(
            Tier::Results,
            TierPolicy {
                max_bytes: 10,
                max_age: at(10),
            },
        );
        assert_eq!(
            inverted.validate(),
            Err(ConfigError::UrgencyInversion {
                more_urgent: Tier::Results,
                less_urgent: Tier::Migrated
            })
        );

        assert_eq!(
            base.with_peer_cap(Some(0)).validate(),
            Err(ConfigError::ZeroPeerCap)
        );
        assert!(matches!(
            base.with_peer_cap(Some(MIB - 1)).validate(),
            Err(ConfigError::PeerCapBelowBundle {
                tier: Tier::Tasks,
                ..
            })
        ));
        assert_eq!(base.with_peer_cap(None).validate(), Ok(()));
        assert!(Bundler::<u32>::new(zero).is_err());
    }

    #[test]
    fn control_is_never_stuck_behind_bulk_traffic() {
        let mut b = bundler();
        for peer in 0..40 {
            for _ in 0..8 {
                b.push(peer, Tier::Tasks, msg(256 * KIB), at(0)).unwrap();
                b.push(peer, Tier::Migrated, msg(128 * KIB), at(0)).unwrap();
            }
        }
        b.push(39, Tier::Control, msg(32), at(100)).unwrap();
        let out = b.poll(at(100));
        assert_eq!(out[0].peer, 39);
        assert_eq!(out[0].tier, Tier::Control);
        assert_eq!(out[0].messages, vec![Bytes::from(msg(32))]);
        assert!(out[1..].iter().all(|bundle| bundle.tier != Tier::Control));
        assert!(out.len() > 40);
    }

    #[test]
    fn control_is_due_at_once() {
        let mut b = bundler();
        b.push(1, Tier::Control, msg(1), at(5)).unwrap();
        assert_eq!(b.next_deadline(), Some(at(5)));
        let out = b.poll(at(5));
        assert_eq!(out.len(), 1);
        assert!(b.is_empty());
    }

    #[test]
    fn size_trigger_fires_exactly_at_max_bytes_for_each_tier() {
        for tier in [Tier::Results, Tier::Migrated, Tier::Tasks] {
            let mut b = bundler();
            let max = b.config().policy(tier).max_bytes;
            b.push(1, tier, msg(max - 1), at(0)).unwrap();
            assert!(b.poll(at(0)).is_empty(), "{tier:?} flushed below max_bytes");
            b.push(1, tier, msg(1), at(0)).unwrap();
            let out = b.poll(at(0));
            assert_eq!(out.len(), 1, "{tier:?}");
            assert_eq!((out[0].bytes, out[0].messages.len()), (max, 2));
            assert!(b.is_empty());
        }
    }

    #[test]
    fn age_trigger_fires_exactly_at_max_age_for_each_tier() {
        for tier in Tier::MOST_URGENT_FIRST {
            let mut b = bundler();
            let age = b.config().policy(tier).max_age;
            let start = at(3);
            b.push(1, tier, msg(10), start).unwrap();
            assert_eq!(b.next_deadline(), Some(start + age));
            if !age.is_zero() {
                assert!(
                    b.poll(start + age - US).is_empty(),
                    "{tier:?} flushed early"
                );
            }
            let out = b.poll(start + age);
            assert_eq!(out.len(), 1, "{tier:?}");
            assert_eq!(out[0].tier, tier);
        }
    }

    #[test]
    fn urgent_tiers_come_first_across_all_peers() {
        let mut b = bundler();
        for peer in [3, 1, 2] {
            for tier in Tier::MOST_URGENT_FIRST.into_iter().rev() {
                b.push(peer, tier, msg(10), at(0)).unwrap();
            }
        }
        let order: Vec<(Tier, u32)> = b
            .flush_all(at(0))
            .iter()
            .map(|bundle| (bundle.tier, bundle.peer))
            .collect();
        let mut expected = Vec::new();
        for tier in Tier::MOST_URGENT_FIRST {
            expected.extend([1, 2, 3].map(|peer| (tier, peer)));
        }
        assert_eq!(order, expected);
    }

    #[test]
    fn oversized_message_travels_alone_and_whole() {
        let mut b = bundler();
        let max = b.config().policy(Tier::Migrated).max_bytes;
        b.push(1, Tier::Migrated, tagged(1, 10), at(0)).unwrap();
        b.push(1, Tier::Migrated, tagged(2, max + 5), at(0))
            .unwrap();
        b.push(1, Tier::Migrated, tagged(3, 10), at(0)).unwrap();
        let out = b.poll(at(0));
        // The giant made the tier due by size; the small tail waits for its own trigger.
        assert_eq!(out.len(), 2);
        assert_eq!(out[0].messages, vec![tagged(1, 10)]);
        assert_eq!(out[1].messages, vec![tagged(2, max + 5)]);
        assert_eq!(out[1].bytes, max + 5);
        assert_eq!(b.pending_bytes(&1, Tier::Migrated), 10);
        let rest = b.flush_all(at(0));
        assert_eq!(rest[0].messages, vec![tagged(3, 10)]);
    }

    #[test]
    fn due_tier_is_packed_into_bundles_within_max_bytes() {
        let mut b = bundler();
        let max = b.config().policy(Tier::Results).max_bytes;
        for i in 0..10 {
            b.push(1, Tier::Results, tagged(i, max / 4), at(0)).unwrap();
        }
        let out = b.poll(at(1));
        let sizes: Vec<usize> = out.iter().map(|bundle| bundle.messages.len()).collect();
        assert_eq!(sizes, vec![4, 4, 2]);
        let flat: Vec<Bytes> = out.into_iter().flat_map(|bundle| bundle.messages).collect();
        assert_eq!(
            flat,
            (0..10).map(|i| tagged(i, max / 4)).collect::<Vec<_>>()
        );
    }

    #[test]
    fn flush_all_empties_everything() {
        let mut b = bundler();
        for peer in 0..5 {
            for tier in Tier::MOST_URGENT_FIRST {
                b.push(peer, tier, msg(100), at(0)).unwrap();
            }
        }
        let out = b.flush_all(at(0));
        assert_eq!(out.len(), 20);
        assert!(b.is_empty());
        assert_eq!(b.pending_messages(), 0);
        assert_eq!(b.next_deadline(), None);
        assert!(b.poll(at(1000)).is_empty());
    }

    #[test]
    fn next_deadline_is_the_earliest_age_flush() {
        let mut b = bundler();
        assert_eq!(b.next_deadline(), None);
        b.push(1, Tier::Tasks, msg(10), at(0)).unwrap();
        b.push(2, Tier::Migrated, msg(10), at(10)).unwrap();
        assert_eq!(b.next_deadline(), Some(at(15)));
        assert!(b.poll(at(15) - US).is_empty());
        let out = b.poll(at(15));
        assert_eq!((out.len(), out[0].peer), (1, 2));
        assert_eq!(b.next_deadline(), Some(at(20)));
        b.push(3, Tier::Results, msg(10), at(18)).unwrap();
        assert_eq!(b.next_deadline(), Some(at(19)));
    }

    #[test]
    fn next_deadline_is_now_when_due_by_size() {
        let mut b = bundler();
        b.push(1, Tier::Tasks, msg(MIB), at(7)).unwrap();
        assert_eq!(b.next_deadline(), Some(at(7)));
    }

    #[test]
    fn backpressure_hands_the_message_back() {
        let config = BundlerConfig::default().with_peer_cap(Some(MIB));
        let mut b: Bundler<u32> = Bundler::new(config).unwrap();
        b.push(1, Tier::Migrated, msg(MIB - 10), at(0)).unwrap();
        let err = b.push(1, Tier::Tasks, tagged(9, 11), at(0)).unwrap_err();
        assert_eq!(
            err.kind,
            PushErrorKind::PeerFull {
                pending: MIB - 10,
                cap: MIB
            }
        );
        assert_eq!(err.clone().into_message(), tagged(9, 11));
        assert!(err.to_string().contains("full"));
        // Other peers and the urgent tiers are unaffected.
        b.push(2, Tier::Tasks, msg(11), at(0)).unwrap();
        b.push(1, Tier::Control, msg(MIB), at(0)).unwrap();
        b.push(1, Tier::Results, msg(MIB), at(0)).unwrap();
        assert_eq!(b.stats()[Tier::Tasks].rejected, 1);
        // Once the bulk tier is sent there is room again.
        b.poll(at(0));
        b.push(1, Tier::Tasks, err.into_message(), at(0)).unwrap();
        let too_big = b.push(1, Tier::Tasks, msg(MIB + 1), at(0)).unwrap_err();
        assert!(matches!(
            too_big.kind,
            PushErrorKind::MessageTooLarge { len, .. } if len == MIB + 1
        ));
    }

    #[test]
    fn stats_count_bundles_messages_and_bytes() {
        let mut b = bundler();
        b.push(1, Tier::Control, msg(3), at(0)).unwrap();
        b.push(1, Tier::Control, msg(4), at(0)).unwrap();
        b.push(2, Tier::Tasks, msg(5), at(0)).unwrap();
        b.poll(at(0));
        assert_eq!(
            b.stats()[Tier::Control],
            TierStats {
                bundles: 1,
                messages: 2,
                bytes: 7,
                rejected: 0
            }
        );
        assert_eq!(b.stats()[Tier::Tasks], TierStats::default());
        b.flush_all(at(0));
        assert_eq!(b.stats()[Tier::Tasks].bytes, 5);
        assert_eq!(b.stats().total().messages, 3);
        assert_eq!(b.stats().total().bundles, 2);
    }

    #[test]
    fn clock_never_runs_backwards() {
        let mut b = bundler();
        b.poll(at(100));
        // A stale timestamp is read as the latest one, so the message is not "born early".
        b.push(1, Tier::Tasks, msg(1), at(0)).unwrap();
        assert_eq!(b.next_deadline(), Some(at(120)));
        assert!(b.poll(at(119)).is_empty());
        assert_eq!(b.poll(at(120)).len(), 1);
    }

    #[test]
    fn flush_peer_returns_only_that_peers_messages() {
        let mut b = bundler();
        b.push(1, Tier::Tasks, tagged(1, 5), at(0)).unwrap();
        b.push(1, Tier::Control, tagged(2, 5), at(0)).unwrap();
        b.push(2, Tier::Tasks, tagged(3, 5), at(0)).unwrap();
        let out = b.flush_peer(&1);
        let tiers: Vec<Tier> = out.iter().map(|bundle| bundle.tier).collect();
        assert_eq!(tiers, vec![Tier::Control, Tier::Tasks]);
        assert!(out.iter().all(|bundle| bundle.peer == 1));
        assert_eq!(b.pending_messages(), 1);
        assert!(b.flush_peer(&1).is_empty());
        assert_eq!(b.stats().total().messages, 2);
    }

    mod model {
        //! Property tests against a plain reference model of the pending queues.

        use super::super::*;
        use proptest::prelude::*;
        use std::collections::{BTreeMap, HashSet, VecDeque};

        const CAP: usize = 12_000;

        fn config() -> BundlerConfig {
            let policy = |max_bytes, ms| TierPolicy {
                max_bytes,
                max_age: Duration::from_millis(ms),
            };
            BundlerConfig {
                policies: [
                    TierPolicy::immediate(600),
                    policy(1_000, 1),
                    policy(4_000, 3),
                    policy(8_000, 7),
                ],
                peer_cap_bytes: Some(CAP),
            }
        }

        #[derive(Debug, Clone)]
        enum Op {
            Push { peer: u8, tier: usize, len: usize },
            Poll,
            FlushAll,
            FlushPeer { peer: u8 },
        }

        fn op() -> impl Strategy<Value = (Op, u64)> {
            let len = prop_oneof![8usize..200, 8usize..3_000, 3_000usize..14_000];
            let op = prop_oneof![
                8 => (0u8..4, 0usize..Tier::COUNT, len)
                    .prop_map(|(peer, tier, len)| Op::Push { peer, tier, len }),
                4 => Just(Op::Poll),
                1 => Just(Op::FlushAll),
                1 => (0u8..4).prop_map(|peer| Op::FlushPeer { peer }),
            ];
            (op, 0u64..2_500)
        }

        /// Reference model: per (peer, tier) the accepted messages with arrival times.
        #[derive(Default)]
        struct Model {
            queues: BTreeMap<(u8, Tier), VecDeque<(Bytes, Duration)>>,
            emitted: [TierStats; Tier::COUNT],
            rejected: [u64; Tier::COUNT],
            accepted: HashSet<u64>,
            seen: HashSet<u64>,
        }

        impl Model {
            fn queue_due(&self, key: (u8, Tier), now: Duration) -> bool {
                let policy = config().policy(key.1);
                let Some(queue) = self.queues.get(&key) else {
                    return false;
                };
                let bytes: usize = queue.iter().map(|(m, _)| m.len()).sum();
                queue.front().is_some_and(|(_, arrived)| {
                    bytes >= policy.max_bytes || now >= *arrived + policy.max_age
                })
            }

            fn capped_bytes(&self, peer: u8) -> usize {
                self.queues
                    .iter()
                    .filter(|((p, tier), _)| *p == peer && tier.is_capped())
                    .flat_map(|(_, queue)| queue.iter().map(|(m, _)| m.len()))
                    .sum()
            }

            /// Checks one emitted bundle against the model and consumes its messages.
            fn take(&mut self, bundle: &Bundle<u8>, due_at: Option<Duration>) {
                let key = (bundle.peer, bundle.tier);
                if let Some(now) = due_at {
                    assert!(self.queue_due(key, now), "bundle emitted before due");
                }
                let max = config().policy(bundle.tier).max_bytes;
                assert!(!bundle.messages.is_empty());
                assert!(bundle.bytes <= max || bundle.messages.len() == 1);
                let sum: usize = bundle.messages.iter().map(Bytes::len).sum();
                assert_eq!(sum, bundle.bytes);
                let queue = self.queues.get_mut(&key).expect("bundle for empty queue");
                for message in &bundle.messages {
                    let (expected, _) = queue.pop_front().expect("more messages than pushed");
                    assert_eq!(message, &expected, "order within (peer, tier) broken");
                    assert!(self.seen.insert(id(message)), "message emitted twice");
                }
                // Greedy packing: the next message would not have fitted.
                if let Some((next, _)) = queue.front() {
                    assert!(bundle.bytes + next.len() > max);
                }
                let stats = &mut self.emitted[bundle.tier.index()];
                stats.record(bundle.messages.len(), bundle.bytes);
            }

            fn check_order(bundles: &[Bundle<u8>]) {
                for pair in bundles.windows(2) {
                    let urgency = |b: &Bundle<u8>| (b.tier, b.peer);
                    assert!(urgency(&pair[0]) <= urgency(&pair[1]), "tier order broken");
                }
            }
        }

        fn id(message: &Bytes) -> u64 {
            u64::from_le_bytes(message[..8].try_into().unwrap())
        }

        fn message(id: u64, len: usize) -> Bytes {
            let mut bytes = vec![0xAB; len];
            bytes[..8].copy_from_slice(&id.to_le_bytes());
            Bytes::from(bytes)
        }

        fn apply(b: &mut Bundler<u8>, model: &mut Model, op: Op, now: Duration, next_id: u64) {
            match op {
                Op::Push { peer, tier, len } => {
                    let tier = Tier::from_index(tier).unwrap();
                    let payload = message(next_id, len);
                    let over = tier.is_capped() && model.capped_bytes(peer) + len > CAP;
                    match b.push(peer, tier, payload.clone(), now) {
                        Ok(()) => {
                            assert!(!over, "push accepted over the cap");
                            model.accepted.insert(next_id);
                            let queue = model.queues.entry((peer, tier)).or_default();
                            queue.push_back((payload, now));
                        }
                        Err(err) => {
                            assert!(over, "push refused under the cap");
                            assert_eq!(err.message, payload, "refused message altered");
                            model.rejected[tier.index()] += 1;
                        }
                    }
                }
                Op::Poll => {
                    let out = b.poll(now);
                    Model::check_order(&out);
                    out.iter().for_each(|bundle| model.take(bundle, Some(now)));
                    let keys: Vec<_> = model.queues.keys().copied().collect();
                    for key in keys {
                        assert!(!model.queue_due(key, now), "due queue left behind");
                    }
                }
                Op::FlushAll => {
                    let out = b.flush_all(now);
                    Model::check_order(&out);
                    out.iter().for_each(|bundle| model.take(bundle, None));
                    assert!(model.queues.values().all(VecDeque::is_empty));
                }
                Op::FlushPeer { peer } => {
                    let out = b.flush_peer(&peer);
                    assert!(out.iter().all(|bundle| bundle.peer == peer));
                    Model::check_order(&out);
                    out.iter().for_each(|bundle| model.take(bundle, None));
                }
            }
        }

        fn check_invariants(b: &Bundler<u8>, model: &Model) {
            for peer in 0..4 {
                assert!(b.capped_pending_bytes(&peer) <= CAP);
                assert_eq!(b.capped_pending_bytes(&peer), model.capped_bytes(peer));
            }
            let pending: usize = model.queues.values().map(VecDeque::len).sum();
            assert_eq!(b.pending_messages(), pending);
            for tier in Tier::MOST_URGENT_FIRST {
                let mut expected = model.emitted[tier.index()];
                expected.rejected = model.rejected[tier.index()];
                assert_eq!(b.stats()[tier], expected, "stats drifted");
            }
        }

        proptest! {
            #![proptest_config(ProptestConfig::with_cases(256))]

            #[test]
            fn every_message_comes_out_once_in_order_and_only_when_due(
                ops in proptest::collection::vec(op(), 1..120)
            ) {
                let mut b = Bundler::new(config()).unwrap();
                let mut model = Model::default();
                let mut now = Duration::ZERO;
                for (next_id, (op, step_us)) in (0u64..).zip(ops) {
                    now += Duration::from_micros(step_us);
                    apply(&mut b, &mut model, op, now, next_id);
                    check_invariants(&b, &model);
                }
                // The deadline is exact: nothing just before it, something at it.
                if let Some(deadline) = b.next_deadline() {
                    if deadline > now {
                        prop_assert!(b.poll(deadline - Duration::from_micros(1)).is_empty());
                    }
                    let out = b.poll(deadline);
                    prop_assert!(!out.is_empty());
                    // The bundler reads a stale `deadline` as the latest time it has seen.
                    let effective = deadline.max(now);
                    out.iter().for_each(|bundle| model.take(bundle, Some(effective)));
                }
                let rest = b.flush_all(now);
                rest.iter().for_each(|bundle| model.take(bundle, None));
                check_invariants(&b, &model);
                prop_assert!(b.is_empty());
                prop_assert_eq!(&model.seen, &model.accepted);
            }
        }
    }
}
