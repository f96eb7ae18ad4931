//! One ray queue per domain with a memory cap: past the cap, rays spill to a [`RaySpill`]
//! store and come back when their domain is traced, so nothing is dropped and memory stays
//! bounded. Past the spill cap the frame cannot proceed within its budgets, and says so.
//!
//! The store is a trait so that the machine touches no file: the worker binary spills to
//! local files, tests and the simulator to memory ([`MemorySpill`]).

mod memory;

use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::fmt;

use rayfarm_core::ray::RayRecord;

use memory::Parts;

/// Bytes of one queued ray.
pub const RAY_BYTES: u64 = std::mem::size_of::<RayRecord>() as u64;

/// Where rays that do not fit in memory wait, per domain, first in first out.
pub trait RaySpill {
    /// Appends `rays` to the back of `domain`'s spilled rays.
    fn append(&mut self, domain: u32, rays: &[RayRecord]) -> Result<(), String>;
    /// Takes the `n` rays at the front of `domain`'s spilled rays (the queue never asks for
    /// more than it appended and has not taken back).
    fn take_front(&mut self, domain: u32, n: usize) -> Result<Vec<RayRecord>, String>;
}

/// A [`RaySpill`] in memory: for tests and the simulator, where only the accounting matters.
/// Only domains with rays spilled have an entry.
#[derive(Default)]
pub struct MemorySpill {
    domains: BTreeMap<u32, VecDeque<RayRecord>>,
}

impl RaySpill for MemorySpill {
    fn append(&mut self, domain: u32, rays: &[RayRecord]) -> Result<(), String> {
        if !rays.is_empty() {
            self.domains.entry(domain).or_default().extend(rays);
        }
        Ok(())
    }

    fn take_front(&mut self, domain: u32, n: usize) -> Result<Vec<RayRecord>, String> {
        let q = self
            .domains
            .get_mut(&domain)
            .filter(|q| q.len() >= n)
            .ok_or_else(|| format!("domain {domain}: fewer than {n} rays spilled"))?;
        let taken = q.drain(..n).collect();
        if q.is_empty() {
            self.domains.remove(&domain);
        }
        Ok(taken)
    }
}

/// Why rays could not be queued.
#[derive(Debug, Clone, PartialEq)]
pub enum QueueError {
    /// Memory and spill caps are both full.
    Full { mem_cap: u64, spill_cap: u64 },
    /// The spill store failed.
    Spill(String),
}

impl fmt::Display for QueueError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            QueueError::Full { mem_cap, spill_cap } => write!(
                f,
                "queued rays exceed the worker's budgets: {mem_cap} bytes in memory and \
                 {spill_cap} bytes spilled to disk (raise --queue-bytes or --spill-bytes, or \
                 give the frame more workers)"
            ),
            QueueError::Spill(e) => write!(f, "spilling rays to disk: {e}"),
        }
    }
}

impl std::error::Error for QueueError {}

/// See the module documentation. Only domains with rays queued have an entry, so a worker's
/// queues take memory for its rays, not for the scene's domain count.
pub struct DomainQueues<S> {
    /// Number of domains of the scene.
    domains: u32,
    /// Rays of each domain in memory (no empty entry).
    mem: BTreeMap<u32, Parts>,
    /// Rays of each domain in the spill store (no zero entry).
    spilled: BTreeMap<u32, u64>,
    spill: S,
    mem_rays: u64,
    mem_cap_rays: u64,
    spill_rays: u64,
    spill_cap_rays: u64,
    /// Every non-empty queue as (rays, Reverse(domain)): the fullest queue is the last, so a
    /// pass's choice need not walk every queue (a worker of a 1,024-worker image-plane
    /// simulation has rays for hundreds of domains, and the walk was 28% of the run).
    by_len: BTreeSet<(u64, Reverse<u32>)>,
    /// Rays ever spilled, for the statistics.
    pub spilled_total: u64,
}

impl<S: RaySpill> DomainQueues<S> {
    /// Queues for `domains` domains holding at most `mem_cap` bytes of rays in memory and
    /// `spill_cap` bytes in `spill`.
    pub fn new(domains: usize, mem_cap: u64, spill_cap: u64, spill: S) -> Self {
        DomainQueues {
            domains: domains as u32,
            mem: BTreeMap::new(),
            spilled: BTreeMap::new(),
            spill,
            mem_rays: 0,
            mem_cap_rays: (mem_cap / RAY_BYTES).max(1),
            spill_rays: 0,
            spill_cap_rays: spill_cap / RAY_BYTES,
            by_len: BTreeSet::new(),
            spilled_total: 0,
        }
    }

    /// Moves `domain` in `by_len` from `before` rays to what it holds now.
    fn reindex(&mut self, domain: u32, before: u64) {
        let now = self.len(domain);
        if now == before {
            return;
        }
        if before > 0 {
            self.by_len.remove(&(before, Reverse(domain)));
        }
        if now > 0 {
            self.by_len.insert((now, Reverse(domain)));
        }
    }

    /// Domains with rays queued, the fullest first (of equal ones the lower domain first).
    pub fn fullest_first(&self) -> impl Iterator<Item = (u32, u64)> + '_ {
        self.by_len.iter().rev().map(|&(n, Reverse(d))| (d, n))
    }

    /// Bytes of rays queued in memory and in the spill store now.
    pub fn bytes(&self) -> (u64, u64) {
        (self.mem_rays * RAY_BYTES, self.spill_rays * RAY_BYTES)
    }

    /// [`DomainQueues::push`] of a vector the caller gives up: when nothing of the domain's
    /// queue is spilled and it all fits in memory, the vector joins the queue as it is
    /// instead of being copied (routing hands every ray a worker keeps to this, 2.3 M a frame
    /// on a predictive worker).
    pub fn push_owned(&mut self, domain: u32, rays: Vec<RayRecord>) -> Result<(), QueueError> {
        let before = self.len(domain);
        let room = self.mem_cap_rays.saturating_sub(self.mem_rays) as usize;
        let pushed = if !self.spilled.contains_key(&domain) && rays.len() <= room {
            self.mem_rays += rays.len() as u64;
            if !rays.is_empty() {
                self.mem.entry(domain).or_default().push_owned(rays);
            }
            Ok(())
        } else {
            self.push_unindexed(domain, &rays)
        };
        self.reindex(domain, before);
        pushed
    }

    /// Queues `rays`, each for its `domain` (which must be below the domain count).
    pub fn push(&mut self, domain: u32, rays: &[RayRecord]) -> Result<(), QueueError> {
        let before = self.len(domain);
        let pushed = self.push_unindexed(domain, rays);
        self.reindex(domain, before);
        pushed
    }

    fn push_unindexed(&mut self, domain: u32, rays: &[RayRecord]) -> Result<(), QueueError> {
        let room = self.mem_cap_rays.saturating_sub(self.mem_rays) as usize;
        // Rays already spilled for this domain keep their place in line.
        let in_memory = if self.spilled.contains_key(&domain) {
            0
        } else {
            room.min(rays.len())
        };
        if in_memory > 0 {
            self.mem.entry(domain).or_default().push(&rays[..in_memory]);
        }
        self.mem_rays += in_memory as u64;
        let rest = &rays[in_memory..];
        if rest.is_empty() {
            return Ok(());
        }
        let n = rest.len() as u64;
        if self.spill_rays + n > self.spill_cap_rays {
            return Err(QueueError::Full {
                mem_cap: self.mem_cap_rays * RAY_BYTES,
                spill_cap: self.spill_cap_rays * RAY_BYTES,
            });
        }
        self.spill.append(domain, rest).map_err(QueueError::Spill)?;
        *self.spilled.entry(domain).or_default() += n;
        self.spill_rays += n;
        self.spilled_total += n;
        Ok(())
    }

    /// Takes up to `max` rays of `domain`: from memory first, then back from the spill store.
    pub fn take(&mut self, domain: u32, max: usize) -> Result<Vec<RayRecord>, QueueError> {
        let before = self.len(domain);
        let taken = self.take_unindexed(domain, max);
        self.reindex(domain, before);
        taken
    }

    fn take_unindexed(&mut self, domain: u32, max: usize) -> Result<Vec<RayRecord>, QueueError> {
        let mut out = match self.mem.get_mut(&domain) {
            Some(q) if q.len() > max => q.take_back(max),
            Some(_) => self
                .mem
                .remove(&domain)
                .map(|mut q| q.take_back(usize::MAX))
                .unwrap_or_default(),
            None => Vec::new(),
        };
        self.mem_rays -= out.len() as u64;
        let spilled = self.spilled.get(&domain).copied().unwrap_or(0);
        let n = ((max - out.len()) as u64).min(spilled);
        if n > 0 {
            let back = self
                .spill
                .take_front(domain, n as usize)
                .map_err(QueueError::Spill)?;
            if n == spilled {
                self.spilled.remove(&domain);
            } else {
                self.spilled.insert(domain, spilled - n);
            }
            self.spill_rays -= n;
            out.extend(back);
        }
        Ok(out)
    }

    /// Rays queued for `domain`, in memory and spilled.
    pub fn len(&self, domain: u32) -> u64 {
        self.mem.get(&domain).map_or(0, |q| q.len() as u64)
            + self.spilled.get(&domain).copied().unwrap_or(0)
    }

    /// Whether `domain` is one of [`DomainQueues::non_empty`]'s.
    pub fn has_queue(&self, domain: u32) -> bool {
        self.mem.contains_key(&domain) || self.spilled.contains_key(&domain)
    }

    /// Domains with rays queued (in memory or spilled), ascending.
    pub fn non_empty(&self) -> impl Iterator<Item = u32> + '_ {
        let mut mem = self.mem.keys().copied().peekable();
        let mut spilled = self.spilled.keys().copied().peekable();
        // A merge of two ascending key lists, each domain once.
        std::iter::from_fn(
            move || match (mem.peek().copied(), spilled.peek().copied()) {
                (Some(a), Some(b)) => {
                    if a <= b {
                        mem.next();
                    }
                    if b <= a {
                        spilled.next();
                    }
                    Some(a.min(b))
                }
                (Some(_), None) => mem.next(),
                (None, _) => spilled.next(),
            },
        )
    }

    /// Number of domains.
    pub fn domains(&self) -> u32 {
        self.domains
    }

    /// Rays queued over all domains.
    pub fn total(&self) -> u64 {
        self.mem_rays + self.spill_rays
    }

    /// Keeps only the rays `keep` accepts (in memory and spilled).
    pub fn retain(&mut self, keep: impl Fn(&RayRecord) -> bool) -> Result<(), QueueError> {
        let domains: Vec<u32> = self.non_empty().collect();
        for d in domains {
            let len = self.len(d) as usize;
            let rays = self.take(d, len)?;
            let kept: Vec<RayRecord> = rays.into_iter().filter(|r| keep(r)).collect();
            self.push(d, &kept)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ray(pixel: u32) -> RayRecord {
        RayRecord {
            pixel,
            ..bytemuck::Zeroable::zeroed()
        }
    }

    fn queues(domains: usize, mem_rays: u64, spill_rays: u64) -> DomainQueues<MemorySpill> {
        let spill = MemorySpill::default();
        DomainQueues::new(domains, mem_rays * RAY_BYTES, spill_rays * RAY_BYTES, spill)
    }

    /// The index of queues by length names the same fullest queue as a walk of every queue,
    /// through pushes, spills and takes.
    #[test]
    fn the_fullest_queue_is_the_walks_choice() {
        let mut q = queues(16, 40, 1000);
        let mut x: u64 = 7;
        for step in 0..500u32 {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let d = ((x >> 33) % 16) as u32;
            let n = ((x >> 45) % 9) as usize;
            if step % 3 == 2 {
                q.take(d, n).unwrap();
            } else {
                let rays: Vec<RayRecord> = (0..n as u32).map(ray).collect();
                q.push(d, &rays).unwrap();
            }
            let walk: Vec<(u32, u64)> = {
                let mut v: Vec<(u32, u64)> = q.non_empty().map(|d| (d, q.len(d))).collect();
                v.sort_by_key(|&(d, n)| (Reverse(n), d));
                v
            };
            assert_eq!(q.fullest_first().collect::<Vec<_>>(), walk, "step {step}");
        }
        assert!(q.fullest_first().count() > 0);
    }

    #[test]
    fn rays_past_the_memory_cap_spill_and_all_come_back() {
        let mut q = queues(2, 4, 100);
        let rays: Vec<RayRecord> = (0..10).map(ray).collect();
        q.push(0, &rays).unwrap();
        q.push(1, &rays[..3]).unwrap();
        assert_eq!((q.len(0), q.len(1), q.total()), (10, 3, 13));
        assert_eq!(q.spilled_total, 9, "only 4 fit in memory");
        let mut back: Vec<u32> = Vec::new();
        while q.len(0) > 0 {
            back.extend(q.take(0, 3).unwrap().iter().map(|r| r.pixel));
        }
        back.sort_unstable();
        assert_eq!(back, (0..10).collect::<Vec<_>>());
        assert_eq!(q.take(1, 10).unwrap().len(), 3);
        assert_eq!(q.total(), 0);
    }

    #[test]
    fn past_both_caps_the_error_names_the_budgets() {
        let mut q = queues(1, 2, 3);
        let rays: Vec<RayRecord> = (0..5).map(ray).collect();
        q.push(0, &rays).unwrap();
        let err = q.push(0, &rays[..1]).unwrap_err().to_string();
        let memory = format!("{} bytes in memory", 2 * RAY_BYTES);
        assert!(
            err.contains("--queue-bytes") && err.contains(&memory),
            "{err}"
        );
    }

    #[test]
    fn only_domains_with_rays_are_listed_in_memory_or_spilled() {
        let mut q = queues(1000, 3, 100);
        let rays: Vec<RayRecord> = (0..4).map(ray).collect();
        q.push(700, &rays[..2]).unwrap();
        // One more fits in memory, the rest of domain 5 spills; domain 9 spills whole.
        q.push(5, &rays).unwrap();
        q.push(9, &rays[..1]).unwrap();
        assert_eq!(q.non_empty().collect::<Vec<_>>(), [5, 9, 700]);
        assert_eq!((q.mem.len(), q.spilled.len()), (2, 2));
        q.take(5, 10).unwrap();
        q.take(700, 1).unwrap();
        assert_eq!(q.non_empty().collect::<Vec<_>>(), [9, 700]);
        q.take(9, 1).unwrap();
        q.take(700, 1).unwrap();
        assert_eq!(q.non_empty().count(), 0);
        assert!(
            q.mem.is_empty() && q.spilled.is_empty(),
            "no empty entries kept"
        );
        assert_eq!((q.domains(), q.total()), (1000, 0));
    }

    #[test]
    fn an_owned_push_queues_as_a_copying_push_does() {
        // Into an empty queue, behind queued rays, past the memory cap: the same lines.
        let rays: Vec<RayRecord> = (0..6).map(ray).collect();
        let (mut owned, mut copied) = (queues(2, 8, 100), queues(2, 8, 100));
        for (d, range) in [(0, 0..3), (0, 3..6), (1, 0..6)] {
            owned.push_owned(d, rays[range.clone()].to_vec()).unwrap();
            copied.push(d, &rays[range]).unwrap();
        }
        assert_eq!(owned.bytes(), copied.bytes());
        assert_eq!(owned.spilled_total, 4, "8 fit in memory");
        // The index of queues by length, which picks the next queue to trace, sees them too.
        assert_eq!(
            owned.fullest_first().collect::<Vec<_>>(),
            copied.fullest_first().collect::<Vec<_>>()
        );
        assert_eq!(owned.fullest_first().count(), 2);
        for d in [0, 1] {
            let pixels = |q: &mut DomainQueues<MemorySpill>| -> Vec<u32> {
                let mut out = Vec::new();
                while q.len(d) > 0 {
                    out.extend(q.take(d, 4).unwrap().iter().map(|r| r.pixel));
                }
                out
            };
            assert_eq!(pixels(&mut owned), pixels(&mut copied), "domain {d}");
        }
        assert_eq!((owned.total(), owned.bytes()), (0, (0, 0)));
    }

    #[test]
    fn retain_filters_spilled_rays_too() {
        let mut q = queues(1, 2, 100);
        q.push(0, &(0..8).map(ray).collect::<Vec<_>>()).unwrap();
        q.retain(|r| r.pixel % 2 == 0).unwrap();
        let mut left: Vec<u32> = q.take(0, 100).unwrap().iter().map(|r| r.pixel).collect();
        left.sort_unstable();
        assert_eq!(left, [0, 2, 4, 6]);
    }
}
