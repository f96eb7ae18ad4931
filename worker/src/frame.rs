//! A worker's state for the frame it is working on: one ray queue per domain, the tiles whose
//! camera rays it still has to issue, and this round's plan (which domains it traces, and who
//! holds the others).

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use rayfarm_core::ray::RayRecord;
use rayfarm_core::render::KernelCounters;
use rayfarm_core::render::cache::CacheCounters;
use rayfarm_core::schedule::speculative::{GenerationCounts, QueueView, next_queue};
use rayfarm_core::wire::BatchLimits;

use crate::pass::FrameView;
use crate::queues::{DomainQueues, QueueError};
use crate::speculation::Speculation;

/// Counters of one frame on this worker.
#[derive(Default)]
pub struct FrameCounters {
    pub rays: KernelCounters,
    pub rays_sent: u64,
    pub bytes_sent: u64,
    pub rays_received: u64,
    pub busy: Duration,
}

/// Where this frame's rays are traced: the job's schedule as the worker sees it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// Image-plane (Fig. 3): rays never leave this worker; any domain is loaded on demand.
    ImagePlane,
    /// Domain (Fig. 4): this worker traces the domains it owns; rays go to the owners.
    Domain,
    /// Dynamic (Figs. 5-6): the planned domains, plus any domain still mapped here; rays go
    /// to this round's holders.
    Dynamic,
    /// Predictive (Park et al.): dynamic rounds, with each new ray queued in every domain
    /// along it at once (`speculation`) and the oldest generation traced first.
    Predictive,
    /// Hybrid (Reinhard et al.): camera rays and their shadow rays, coherent, are traced by
    /// the worker whose tile they are, loading what they need (`demand_loads`; off when the
    /// cache is too small, then they migrate too); incoherent rays migrate to the domains'
    /// owners. Owned domains' queues go first (data-parallel first).
    Hybrid { demand_loads: bool },
}

/// The frame being rendered.
pub struct Frame {
    pub mode: Mode,
    pub job_id: String,
    pub shared: Arc<FrameView>,
    pub limits: BatchLimits,
    /// Tiles whose camera rays this worker issues, in order, not yet issued.
    pub to_issue: VecDeque<u32>,
    /// Current epoch of every tile: rays of older epochs are dropped.
    pub epochs: Vec<u32>,
    queues: DomainQueues,
    /// Rays queued per domain and generation (an upper bound after a fault dropped rays).
    generations: GenerationCounts,
    /// Under the predictive schedule, the rays born here waiting for their copies' verdicts.
    pub speculation: Option<Speculation>,
    pub round: u64,
    work_on: BTreeSet<u32>,
    /// Domains mapped here now. Rays for them are traced here even when the plan gave the
    /// domain to no one or to another worker: any worker may trace any ray of a domain it
    /// has, and doing so costs neither a load nor a transfer.
    resident: BTreeSet<u32>,
    /// Other workers holding each domain this round.
    holders: BTreeMap<u32, Vec<String>>,
    /// Whether the coordinator has this worker's current state (no report is due).
    pub reported: bool,
    pub counters: FrameCounters,
    /// The domain cache's counters when the frame started.
    pub cache_at_start: CacheCounters,
    pub started: Instant,
}

/// Where a routed ray goes.
enum Destination {
    /// Queued here.
    Local,
    /// To the worker at this peer address.
    Peer(String),
}

impl Frame {
    pub fn new(
        mode: Mode,
        job_id: String,
        shared: Arc<FrameView>,
        limits: BatchLimits,
        to_issue: Vec<u32>,
        queues: DomainQueues,
    ) -> Self {
        let tiles = shared.grid.count() as usize;
        Frame {
            mode,
            job_id,
            shared,
            limits,
            to_issue: to_issue.into(),
            epochs: vec![0; tiles],
            generations: GenerationCounts::new(queues.domains() as usize),
            speculation: None,
            queues,
            round: 0,
            work_on: BTreeSet::new(),
            resident: BTreeSet::new(),
            holders: BTreeMap::new(),
            reported: false,
            counters: FrameCounters::default(),
            cache_at_start: CacheCounters::default(),
            started: Instant::now(),
        }
    }

    /// Under hybrid, whether demand-driven rays may load domains: only while the cache has
    /// room for every owned domain plus the largest other, so that they never push owned
    /// (data-parallel) data out. Otherwise they migrate like the rest.
    /// Returns the domains to pin in the cache (the owned ones when demand loads may use
    /// the rest).
    pub fn decide_demand_loads(&mut self, cache_bytes: u64, domain_bytes: &[u64]) -> Vec<u32> {
        let Mode::Hybrid { demand_loads } = &mut self.mode else {
            return Vec::new();
        };
        let size = |d: u32| domain_bytes.get(d as usize).copied().unwrap_or(0);
        let owned: u64 = self.work_on.iter().map(|&d| size(d)).sum();
        let largest = domain_bytes.iter().copied().max().unwrap_or(0);
        *demand_loads = cache_bytes >= owned + largest;
        if *demand_loads {
            self.work_on.iter().copied().collect()
        } else {
            Vec::new()
        }
    }

    /// Adopts a round's plan; `me` is this worker's peer address (not a destination).
    pub fn set_plan(
        &mut self,
        round: u64,
        work_on: impl IntoIterator<Item = u32>,
        holders: impl IntoIterator<Item = (u32, Vec<String>)>,
        me: &str,
    ) {
        self.round = round;
        self.work_on = work_on.into_iter().collect();
        self.set_holders(holders, me);
        self.reported = false;
    }

    /// Adopts new holders of the domains, keeping this worker's own plan.
    pub fn set_holders(&mut self, holders: impl IntoIterator<Item = (u32, Vec<String>)>, me: &str) {
        self.holders = holders
            .into_iter()
            .map(|(d, mut ws)| {
                ws.retain(|w| w != me);
                (d, ws)
            })
            .filter(|(_, ws)| !ws.is_empty())
            .collect();
    }

    /// Records which domains are mapped here now.
    pub fn set_resident(&mut self, resident: impl IntoIterator<Item = u32>) {
        self.resident = resident.into_iter().collect();
    }

    fn planned_or_resident(&self, domain: u32) -> bool {
        self.work_on.contains(&domain) || self.resident.contains(&domain)
    }

    /// Whether this worker may trace the queue of `domain` now.
    fn traces(&self, domain: u32) -> bool {
        match self.mode {
            // Every ray queued under hybrid was kept here on purpose (see `keeps`).
            Mode::ImagePlane | Mode::Hybrid { .. } => true,
            Mode::Domain => self.work_on.contains(&domain),
            Mode::Dynamic | Mode::Predictive => self.planned_or_resident(domain),
        }
    }

    /// Whether `ray` stays on this worker.
    fn keeps(&self, ray: &RayRecord) -> bool {
        match self.mode {
            Mode::Hybrid { demand_loads } => {
                self.planned_or_resident(ray.domain) || (demand_loads && ray.depth == 0)
            }
            _ => self.traces(ray.domain),
        }
    }

    /// Whether a ray belongs to the current epoch of its tile.
    fn is_current(&self, ray: &RayRecord) -> bool {
        self.epochs.get(ray.tile as usize) == Some(&ray.epoch)
    }

    /// Where a ray goes this round: here if this worker traces the domain or no
    /// one does (it waits for a later round), else to one of its holders, chosen by pixel so
    /// that a hot domain's rays spread evenly over its holders.
    fn destination(&self, ray: &RayRecord) -> Destination {
        if self.keeps(ray) {
            return Destination::Local;
        }
        match self.holders.get(&ray.domain) {
            Some(ws) => Destination::Peer(ws[ray.pixel as usize % ws.len()].clone()),
            None => Destination::Local,
        }
    }

    /// Queues each ray of the current epoch here or returns it, grouped by the peer it goes
    /// to; rays of an older epoch are dropped.
    pub fn route(
        &mut self,
        rays: Vec<RayRecord>,
    ) -> Result<BTreeMap<String, Vec<RayRecord>>, QueueError> {
        let mut out: BTreeMap<String, Vec<RayRecord>> = BTreeMap::new();
        let mut local: BTreeMap<u32, Vec<RayRecord>> = BTreeMap::new();
        for ray in rays {
            if !self.is_current(&ray) || ray.domain >= self.queues.domains() {
                continue;
            }
            match self.destination(&ray) {
                Destination::Peer(p) => out.entry(p).or_default().push(ray),
                Destination::Local => local.entry(ray.domain).or_default().push(ray),
            }
        }
        for (d, rays) in local {
            self.queues.push(d, &rays)?;
            for r in &rays {
                self.generations.add(d, r.generation());
            }
        }
        Ok(out)
    }

    /// Takes every queued ray that now has a holder elsewhere, grouped by peer.
    pub fn take_for_peers(&mut self) -> Result<BTreeMap<String, Vec<RayRecord>>, QueueError> {
        let domains: Vec<u32> = self
            .holders
            .keys()
            .copied()
            .filter(|&d| !self.planned_or_resident(d) && d < self.queues.domains())
            .collect();
        let mut queued = Vec::new();
        for d in domains {
            let len = self.queues.len(d) as usize;
            queued.extend(self.queues.take(d, len)?);
            self.generations.clear(d);
        }
        // Rays this worker still keeps go back to its queues.
        self.route(queued)
    }

    /// Takes up to `max` rays of the queue to trace next among those this worker traces now:
    /// the fullest (ties: the lower domain id), or under the predictive schedule
    /// `speculative::next_queue`.
    pub fn take_work(&mut self, max: usize) -> Result<Option<(u32, Vec<RayRecord>)>, QueueError> {
        // Hybrid traces its own domains' (data-parallel) queues before demand-driven work.
        let first = |d: u32| matches!(self.mode, Mode::Hybrid { .. }) && self.work_on.contains(&d);
        let queues = (0..self.queues.domains())
            .filter(|&d| self.traces(d))
            .map(|d| (d, self.queues.len(d)))
            .filter(|&(_, len)| len > 0);
        let next = if self.mode == Mode::Predictive {
            next_queue(queues.map(|(domain, rays)| QueueView {
                domain,
                rays,
                oldest: self.generations.oldest(domain).unwrap_or(0),
                resident: self.resident.contains(&domain),
            }))
        } else {
            queues
                .max_by_key(|&(d, len)| (first(d), len, std::cmp::Reverse(d)))
                .map(|(d, _)| d)
        };
        let Some(d) = next else {
            return Ok(None);
        };
        let rays = self.queues.take(d, max)?;
        if self.queues.len(d) == 0 {
            self.generations.clear(d);
        } else {
            for r in &rays {
                self.generations.remove(d, r.generation());
            }
        }
        Ok(Some((d, rays)))
    }

    /// The oldest generation queued per non-empty queue.
    pub fn oldest_generations(&self) -> BTreeMap<u32, u32> {
        (0..self.queues.domains())
            .filter(|&d| self.queues.len(d) > 0)
            .filter_map(|d| Some((d, u32::from(self.generations.oldest(d)?))))
            .collect()
    }

    /// Rays queued here, over all domains.
    pub fn queued_total(&self) -> usize {
        self.queues.total() as usize
    }

    /// Rays queued per domain, non-empty queues only.
    pub fn queue_sizes(&self) -> BTreeMap<u32, u64> {
        (0..self.queues.domains())
            .map(|d| (d, self.queues.len(d)))
            .filter(|&(_, n)| n > 0)
            .collect()
    }

    /// Rays spilled to disk so far in this frame.
    pub fn spilled(&self) -> u64 {
        self.queues.spilled_total
    }

    /// Sends nothing more to `peers` (they are gone); their domains' rays wait here for the
    /// next plan.
    pub fn forget_peers(&mut self, peers: &[String]) {
        if let Some(s) = self.speculation.as_mut() {
            s.retain_current(&self.epochs, peers);
        }
        for holders in self.holders.values_mut() {
            holders.retain(|h| !peers.contains(h));
        }
        self.holders.retain(|_, hs| !hs.is_empty());
    }

    /// Drops queued rays of the given tiles older than their new epochs. Their camera rays
    /// are not issued here any more: the coordinator deals them again.
    pub fn bump_epochs(&mut self, bumps: &BTreeMap<u32, u32>) -> Result<(), QueueError> {
        for (&tile, &epoch) in bumps {
            if let Some(e) = self.epochs.get_mut(tile as usize) {
                *e = (*e).max(epoch);
            }
        }
        self.to_issue.retain(|t| !bumps.contains_key(t));
        self.reported = false;
        if let Some(s) = self.speculation.as_mut() {
            s.retain_current(&self.epochs, &[]);
        }
        let epochs = &self.epochs;
        self.queues
            .retain(|r| epochs.get(r.tile as usize) == Some(&r.epoch))
    }
}
