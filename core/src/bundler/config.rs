//! The tiers, what makes each due (size and age), and the per-peer cap, checked once.

use std::error::Error;
use std::fmt;
use std::time::Duration;

/// Priority tier of an outbound message.
///
/// A lower number is MORE urgent: `Results` (0) is the most urgent, `Tasks` (2) the least.
/// The derived `Ord` follows the number, so sorting ascending puts the most urgent first.
/// Prefer [`Tier::is_more_urgent_than`] over comparing tiers with `<` in calling code.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[repr(u8)]
///
/// There is no tier for requests: a peer's domain request is its own call (`FetchDomain`,
/// a stream of the domain's bytes, far too large to sit in a bundle), and tile results go to
/// the coordinator on the worker's control stream, not to peers.
pub enum Tier {
    /// Verdicts of speculative copies going back to their ray's group: sent fast, because the
    /// group holds its ray (and its pixel's credit) until they are in.
    Results = 0,
    /// Data-parallel rays migrated to the owner of their domain.
    Migrated = 1,
    /// Demand-driven tasks: bundled the most.
    Tasks = 2,
}

impl Tier {
    /// Number of tiers.
    pub const COUNT: usize = 3;

    /// All tiers, most urgent first; this is the order in which bundles are emitted.
    pub const MOST_URGENT_FIRST: [Tier; Tier::COUNT] = [Tier::Results, Tier::Migrated, Tier::Tasks];

    /// Position of the tier in per-tier arrays (its number, 0 = most urgent).
    pub const fn index(self) -> usize {
        self as usize
    }

    /// Tier with the given number, if any.
    pub const fn from_index(index: usize) -> Option<Tier> {
        match index {
            0 => Some(Tier::Results),
            1 => Some(Tier::Migrated),
            2 => Some(Tier::Tasks),
            _ => None,
        }
    }

    /// True if `self` must be sent before `other` when both are due.
    pub const fn is_more_urgent_than(self, other: Tier) -> bool {
        (self as u8) < (other as u8)
    }

    /// True for the bulk ray tiers that the per-peer byte cap applies to.
    ///
    /// Verdicts are exempt: refusing them would stall exactly the messages that unblock
    /// peers (a group holds its ray until they are in), and they never sit for long anyway.
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

/// Bytes in a kibibyte, for the default limits.
pub(super) const KIB: usize = 1024;
/// Bytes in a mebibyte.
pub(super) const MIB: usize = 1024 * KIB;

impl Default for BundlerConfig {
    /// Results: 16 KiB / 1 ms. Migrated: 256 KiB / 5 ms. Tasks: 1 MiB / 20 ms. Peer cap:
    /// 8 MiB of bulk traffic.
    fn default() -> Self {
        BundlerConfig {
            policies: [
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
