//! A worker's state for the frame it is working on: one ray queue per domain, the tiles whose
//! camera rays it still has to issue, and this round's plan (which domains it traces, and who
//! holds the others).
//!
//! Whether the coordinator must hear this worker's queues again is the frame's own state
//! ([`Report`]): every method that changes what a report would say, or what the coordinator
//! counted here, makes one due, and only [`Frame::take_report`] sends it, so no handler can
//! forget either.

use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use tracing::debug;

use rayfarm_core::ray::RayRecord;
use rayfarm_core::render::speculation::Outcome;
use rayfarm_core::schedule::speculation_depth::Depth;
use rayfarm_core::schedule::speculative::{
    GenerationCounts, QueueView, last_generation, next_queue, scheduled_generation,
};
use rayfarm_core::schedule::static_plans::demand_loads_fit;
use rayfarm_core::tile::TileGrid;
use rayfarm_core::wire::{BatchLimits, VerdictRecord};
use rayfarm_proto as proto;

pub use super::counters::{FrameCounters, IdleKind};
use super::plan::{HolderLine, Mode, Plan};
use super::queues::{DomainQueues, QueueError, RaySpill};
use super::speculation::Speculation;
use crate::Time;
use crate::queue_report::Heard;

/// The frame being rendered.
pub struct Frame<S> {
    pub job_id: String,
    pub grid: TileGrid,
    /// Samples per pixel.
    pub spp: u32,
    pub limits: BatchLimits,
    /// Bytes of every domain file, by domain id.
    pub domain_bytes: std::sync::Arc<[u64]>,
    /// Tiles whose camera rays this worker issues, in order, not yet issued.
    to_issue: VecDeque<u32>,
    /// The schedule, this round's plan, the tiles' epochs: where each ray goes.
    plan: Plan,
    queues: DomainQueues<S>,
    /// Rays queued per domain and generation (an upper bound after a fault dropped rays).
    generations: GenerationCounts,
    /// Under the predictive schedule, the rays born here waiting for their copies' verdicts.
    speculation: Option<Speculation>,
    report: Report,
    /// What the coordinator has heard of the queues here: a report names what differs.
    heard: Heard,
    /// Until when a report of running dry waits for the work the last plan sends here (rays
    /// moved from other workers' queues): none once a pass has run since that plan.
    report_held: Option<Time>,
    /// A peer's rays of epochs newer than this worker knows for their tiles, waiting for the
    /// coordinator's bump that announces those epochs (see [`Frame::set_aside_newer`]).
    ahead: Vec<RayRecord>,
    pub counters: FrameCounters,
    pub started: Time,
    /// Whether domains are loaded ahead of need (see [`Frame::next_prefetch`]).
    prefetch: bool,
    /// Domains a prefetch was asked for since the last plan: not asked for again before the
    /// next one (a load the cache had no room for would otherwise be asked for forever).
    prefetched: BTreeSet<u32>,
}

/// More bytes of rays of unannounced epochs than a worker holds: it leaves the frame, since
/// dropping them would lose their credit and the frame would never end.
#[derive(Debug, PartialEq, Eq)]
pub struct AheadFull {
    pub held: u64,
    pub cap: u64,
}

impl std::fmt::Display for AheadFull {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "peers sent {} bytes of rays of tile epochs the coordinator has not announced here \
             (at most {} are held until its epoch bump arrives)",
            self.held, self.cap
        )
    }
}

/// Whether the coordinator has this worker's current state.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Report {
    /// Something changed since the last report (or none was sent yet).
    Due,
    /// The last report is current.
    Sent,
}

/// What a frame is made of, as opened from its StartFrame and the scene.
pub struct FrameParts<S> {
    pub mode: Mode,
    pub job_id: String,
    pub grid: TileGrid,
    pub spp: u32,
    pub limits: BatchLimits,
    pub domain_bytes: std::sync::Arc<[u64]>,
    /// Tiles whose camera rays this worker issues, in order.
    pub to_issue: Vec<u32>,
    pub queues: DomainQueues<S>,
    /// This worker's key in the frame's roster, which follows the StartFrame: until it comes
    /// ([`Frame::set_roster`]), the frame names no peer and its rays for others stay here.
    pub me: u32,
    pub started: Time,
    /// The round in progress (a worker joining mid-frame reports for it at once).
    pub round: u64,
    /// Tiles whose epoch is not 0, with their epochs.
    pub epochs: HashMap<u32, u32>,
    /// Domains mapped here now.
    pub resident: Vec<u32>,
    /// Predictive schedule placing rays speculatively: how far ahead rays are copied.
    pub speculation: Option<Depth>,
    /// Load domains ahead of need (`JobSpec.prefetch`; only the dynamic and predictive
    /// schedules plan one step ahead).
    pub prefetch: bool,
}

impl<S: RaySpill> Frame<S> {
    /// A frame of `parts`, before its first plan.
    pub fn new(parts: FrameParts<S>) -> Self {
        let FrameParts {
            mode,
            job_id,
            grid,
            spp,
            limits,
            domain_bytes,
            to_issue,
            queues,
            me,
            started,
            round,
            epochs,
            resident,
            speculation,
            prefetch,
        } = parts;
        let tiles = grid.count() as usize;
        let roster = std::sync::Arc::new(HashMap::new());
        let mut plan = Plan::new(mode, tiles, queues.domains(), me, roster.clone());
        plan.round = round;
        plan.set_resident(resident);
        for (tile, epoch) in epochs {
            if let Some(e) = plan.epochs.get_mut(tile as usize) {
                *e = epoch;
            }
        }
        Frame {
            job_id,
            grid,
            spp,
            limits,
            domain_bytes,
            to_issue: to_issue.into(),
            plan,
            generations: GenerationCounts::default(),
            speculation: speculation.map(|depth| Speculation::new(me, roster, depth)),
            queues,
            report: Report::Due,
            heard: Heard::default(),
            report_held: None,
            ahead: Vec::new(),
            counters: FrameCounters::default(),
            started,
            prefetch: prefetch && matches!(mode, Mode::Dynamic | Mode::Predictive),
            prefetched: BTreeSet::new(),
        }
    }

    /// Under hybrid, whether demand-driven rays may load domains: only while the cache has
    /// room for every owned domain plus the largest other (`demand_loads_fit`, the rule the
    /// coordinator checks for every worker), so that they never push owned (data-parallel)
    /// data out. Otherwise they migrate like the rest.
    /// Returns the domains to pin in the cache (the owned ones when demand loads may use
    /// the rest).
    pub fn decide_demand_loads(&mut self, cache_bytes: u64) -> Vec<u32> {
        // Only hybrid decides: the other schedules skip the sizes' walk, which runs on every
        // plan (over 8,192 domains, 4% of a 256-worker dynamic run: perf, README "Simulator").
        if !matches!(self.plan.mode, Mode::Hybrid { .. }) {
            return Vec::new();
        }
        let sizes = &self.domain_bytes;
        let size = |d: u32| sizes.get(d as usize).copied().unwrap_or(0);
        let owned: u64 = self.plan.work_on().iter().map(|&d| size(d)).sum();
        let largest = sizes.iter().copied().max().unwrap_or(0);
        let Mode::Hybrid {
            demand_loads,
            rounds,
        } = &mut self.plan.mode
        else {
            return Vec::new();
        };
        // By rounds, the plan fills the cache with what the coordinator chose: a demand load
        // would push it out.
        *demand_loads = !*rounds && demand_loads_fit(cache_bytes, owned, largest);
        if *demand_loads {
            self.plan.work_on().iter().copied().collect()
        } else {
            Vec::new()
        }
    }

    /// Adopts a round's plan; with nothing to trace, the report of running dry under it waits
    /// until `hold_until` for the work it sends here (`RoundPlan.report_hold_ms`).
    pub fn set_plan<'a>(
        &mut self,
        round: u64,
        work_on: impl IntoIterator<Item = u32>,
        holders: impl IntoIterator<Item = HolderLine<'a>>,
        delta: bool,
        hold_until: Option<Time>,
    ) {
        self.plan.set_round(round, work_on, holders, delta);
        self.prefetched.clear();
        self.report = Report::Due;
        self.report_held = hold_until;
    }

    /// A pass starts: what the last plan sent here has come (or the worker had work anyway),
    /// so running dry after it is reported at once.
    pub fn pass_started(&mut self) {
        self.report_held = None;
    }

    /// Until when the report of running dry waits, if it waits at `now` (see
    /// [`Frame::set_plan`]).
    pub fn report_held(&self, now: Time) -> Option<Time> {
        self.report_held.filter(|&t| now < t)
    }

    /// Records the coordinator's guess of this worker's next domains.
    pub fn set_next(&mut self, next: impl IntoIterator<Item = u32>) {
        self.plan.set_next(next);
    }

    /// Whether this frame loads domains ahead of need.
    pub fn prefetches(&self) -> bool {
        self.prefetch
    }

    /// The domain to load ahead of need now, if any, with the domains the load must not push
    /// out of the cache (the plan's and the one `tracing` now). First the plan's domains not
    /// mapped yet, fullest queue here first (a pass would load them one at a time between
    /// traces), then the coordinator's guesses of this worker's next domains that no one
    /// else holds now (a guess another worker took meanwhile would be a wasted load).
    /// Each domain is asked for once per plan.
    pub fn next_prefetch(&mut self, tracing: Option<u32>) -> Option<(u32, Vec<u32>)> {
        if !self.prefetch {
            return None;
        }
        let plan = &self.plan;
        let tried = &self.prefetched;
        let wanted =
            |d: &u32| Some(*d) != tracing && !plan.resident().contains(d) && !tried.contains(d);
        let planned = plan
            .work_on()
            .iter()
            .copied()
            .filter(wanted)
            .max_by_key(|&d| (self.queues.len(d), std::cmp::Reverse(d)));
        let guess = || {
            plan.next()
                .iter()
                .copied()
                .filter(wanted)
                .find(|&d| !plan.is_held_elsewhere(d) && !plan.work_on().contains(&d))
        };
        let domain = planned.or_else(guess)?;
        let keep: BTreeSet<u32> = plan.work_on().iter().copied().chain(tracing).collect();
        self.prefetched.insert(domain);
        let keep = keep.into_iter().collect();
        Some((domain, keep))
    }

    /// Whether rays queued here for `domain` are this worker's to trace now (a pass waits
    /// for a prefetch of it rather than load it a second time).
    pub fn has_work_for(&self, domain: u32) -> bool {
        self.plan.traces(domain) && self.queues.len(domain) > 0
    }

    /// The schedule, this round's plan, the tiles' epochs.
    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    /// Adopts new holders of the domains (another worker's plan changed; `delta` as
    /// [`Plan::set_holders`]); the rays that leave for them are [`Frame::take_for_peers`]'s.
    pub fn set_holders<'a>(
        &mut self,
        holders: impl IntoIterator<Item = HolderLine<'a>>,
        delta: bool,
    ) {
        self.plan.set_holders(holders, delta);
    }

    /// Records which domains are mapped here now, least recently used first.
    pub fn set_resident(&mut self, by_use: impl IntoIterator<Item = u32>) {
        self.plan.set_resident(by_use);
    }

    /// More tiles whose camera rays to issue here (those outside the frame are ignored).
    pub fn hand_out(&mut self, tiles: impl IntoIterator<Item = u32>) {
        let count = self.grid.count();
        self.to_issue
            .extend(tiles.into_iter().filter(|&t| t < count));
        self.report = Report::Due;
    }

    /// Tiles whose camera rays the next pass issues, with their epochs: while fewer than
    /// `wave_rays` rays are queued here (rays waiting for verdicts count too: they bound the
    /// groups' memory).
    pub fn next_primaries(&mut self, wave_rays: usize) -> Vec<(u32, u32)> {
        let mut primaries = Vec::new();
        let waiting = self.speculation.as_ref().map_or(0, |s| s.waiting());
        let mut queued = self.queued_total() + waiting;
        while queued < wave_rays
            && let Some(tile) = self.to_issue.pop_front()
        {
            primaries.push((tile, self.plan.epochs[tile as usize]));
            queued += self.grid.tile_pixel_count(tile) * self.spp as usize;
        }
        primaries
    }

    /// The speculation groups, under the predictive schedule.
    pub fn speculation(&self) -> Option<&Speculation> {
        self.speculation.as_ref()
    }

    /// Predictive: the rays whose verdicts are all in, for the next pass to conclude.
    pub fn take_to_conclude(&mut self) -> Option<Vec<(RayRecord, Outcome)>> {
        let spec = self.speculation.as_mut()?;
        Some(std::mem::take(&mut spec.to_conclude))
    }

    /// Adopts a new roster (the frame's first, or a worker joined: holders may name it);
    /// predictive: returns the held verdicts that now have an address.
    pub fn set_roster(
        &mut self,
        roster: HashMap<u32, String>,
    ) -> Vec<(String, Vec<VerdictRecord>)> {
        let roster = std::sync::Arc::new(roster);
        self.plan.set_roster(roster.clone());
        self.speculation
            .as_mut()
            .map(|s| s.set_roster(roster))
            .unwrap_or_default()
    }

    /// Predictive: settles verdicts from a peer for rays born here (concluding them makes new
    /// work). Returns false if this frame places no rays speculatively.
    pub fn settle(&mut self, verdicts: &[VerdictRecord]) -> bool {
        let Some(spec) = self.speculation.as_mut() else {
            return false;
        };
        spec.settle(verdicts);
        self.report = Report::Due;
        true
    }

    /// Predictive: the copies of the next windows of rays whose last window did not end
    /// them, to route like any copy.
    pub fn take_next_windows(&mut self) -> Vec<RayRecord> {
        self.speculation
            .as_mut()
            .map(|s| std::mem::take(&mut s.next_windows))
            .unwrap_or_default()
    }

    /// What a pass's rays become: as they are, or, speculating, the copies of the rays born
    /// of a current tile (the rest would wait forever), with the pass's verdicts addressed.
    pub fn born(
        &mut self,
        rays: Vec<RayRecord>,
        paths: Vec<Vec<u32>>,
        verdicts: Vec<(u32, VerdictRecord)>,
    ) -> (Vec<RayRecord>, BTreeMap<String, Vec<VerdictRecord>>) {
        let Some(spec) = self.speculation.as_mut() else {
            return (rays, BTreeMap::new());
        };
        let plan = &self.plan;
        // Nearly always every ray is current: then they are taken as they are, not copied.
        let (born, paths): (Vec<RayRecord>, Vec<Vec<u32>>) =
            if rays.iter().all(|r| plan.is_current(r.tile, r.epoch)) {
                (rays, paths)
            } else {
                rays.into_iter()
                    .zip(paths)
                    .filter(|(r, _)| plan.is_current(r.tile, r.epoch))
                    .unzip()
            };
        let mut copies = spec.spread(&born, paths);
        let to_peers = spec.address(verdicts);
        // This pass's own verdicts may have ended windows here.
        copies.append(&mut spec.next_windows);
        // Copies queued here for domains no one traces yet must be reported.
        self.report = Report::Due;
        (copies, to_peers)
    }

    /// This worker's queues for the coordinator, if it has not heard them since they changed:
    /// whole in the frame's first report, what changed since the last in the others.
    pub fn take_report(&mut self) -> Option<proto::QueueReport> {
        if self.report == Report::Sent {
            return None;
        }
        self.report = Report::Sent;
        let oldest = match self.plan.mode {
            Mode::Predictive => self.oldest_generations(),
            _ => Default::default(),
        };
        let named = self.heard.report(self.queue_sizes(), oldest);
        Some(proto::QueueReport {
            job_id: self.job_id.clone(),
            round: self.plan.round,
            resident_domains: self.plan.resident_by_use().to_vec(),
            queued_rays: named.queued_rays,
            oldest_generation: named.oldest_generation,
            delta: named.delta,
            cleared_domains: named.cleared_domains,
            oldest_waiting: self
                .speculation
                .as_ref()
                .and_then(|s| s.oldest_waiting())
                .map(u32::from),
        })
    }

    /// Queues each ray of the current epoch here or returns it, grouped by the peer it goes
    /// to; rays of an older epoch are dropped.
    pub fn route(
        &mut self,
        rays: Vec<RayRecord>,
    ) -> Result<BTreeMap<String, Vec<RayRecord>>, QueueError> {
        // New rays here change what the coordinator should know at the round's end.
        if !rays.is_empty() {
            self.report = Report::Due;
        }
        let sorted = self.plan.sort(rays);
        for (d, rays) in sorted.local {
            for r in &rays {
                self.generations.add(d, r.generation());
            }
            self.queues.push_owned(d, rays)?;
        }
        Ok(sorted.peers)
    }

    /// Takes every queued ray that now has a holder elsewhere, grouped by peer. It looks at
    /// the domains with rays queued here, not at every domain held elsewhere: this runs on
    /// every plan and holders message, and at 1,024 workers over 8,192 domains walking the
    /// held ones took two thirds of a simulated predictive frame's time (perf, README).
    ///
    /// Under the domain, dynamic and predictive schedules it looks only at the domains whose
    /// holders, plan or residency changed since its last walk (`Plan::take_changed`): a ray
    /// queued here then was kept because it was not forwarded, and stays so until one of
    /// those changes. At 256 workers every round's holders message to each member walked
    /// every queue (a tenth of a dynamic run: perf, README "Simulator"). Image-plane and
    /// hybrid keep rays that are forwarded (hybrid's camera rays on demand loads): they walk
    /// every queue as before, since taking those out and routing them back is what they did.
    pub fn take_for_peers(&mut self) -> Result<BTreeMap<String, Vec<RayRecord>>, QueueError> {
        let changed = self.plan.take_changed();
        let leaves = |d: u32| self.plan.is_held_elsewhere(d) && self.plan.forwards(d);
        let domains: Vec<u32> = match changed {
            Some(changed)
                if matches!(
                    self.plan.mode,
                    Mode::Domain | Mode::Dynamic | Mode::Predictive
                ) =>
            {
                changed
                    .into_iter()
                    .filter(|&d| self.queues.has_queue(d) && leaves(d))
                    .collect()
            }
            _ => self.queues.non_empty().filter(|&d| leaves(d)).collect(),
        };
        // Sized once: extended domain by domain from empty, the list was regrown and copied.
        let total = domains.iter().map(|&d| self.queues.len(d) as usize).sum();
        let mut queued = Vec::with_capacity(total);
        for d in domains {
            let len = self.queues.len(d) as usize;
            queued.extend(self.queues.take(d, len)?);
            self.generations.clear(d);
        }
        // Copies of rays born here that a nearer domain already ended need not travel.
        if let Some(spec) = self.speculation.as_mut() {
            queued.retain(|copy| !spec.skip(copy));
        }
        // The coordinator counted these rays here: it must hear they left. Those this worker
        // still keeps go back to its queues.
        self.route(queued)
    }

    /// Takes up to `max` rays of the queue to trace next among those this worker traces now,
    /// other than `loading` (a prefetch is loading it): the fullest (ties: the lower domain
    /// id; prefetching, mapped domains first, so the others load meanwhile), or under the
    /// predictive schedule `speculative::next_queue`.
    pub fn take_work(
        &mut self,
        max: usize,
        loading: Option<u32>,
    ) -> Result<Option<(u32, Vec<RayRecord>)>, QueueError> {
        loop {
            let Some((d, mut rays)) = self.take_queue(max, loading)? else {
                return Ok(None);
            };
            // Copies of rays born here that a nearer domain already ended need no tracing.
            if let Some(spec) = self.speculation.as_mut() {
                rays.retain(|copy| !spec.skip(copy));
            }
            if !rays.is_empty() {
                return Ok(Some((d, rays)));
            }
        }
    }

    /// [`Frame::take_work`]'s choice of queue, the rays taken as they are.
    fn take_queue(
        &mut self,
        max: usize,
        loading: Option<u32>,
    ) -> Result<Option<(u32, Vec<RayRecord>)>, QueueError> {
        // Hybrid traces its own domains' (data-parallel) queues before demand-driven work.
        let first = |d: u32| {
            matches!(self.plan.mode, Mode::Hybrid { .. }) && self.plan.work_on().contains(&d)
        };
        // Prefetching, a mapped domain is traced while the next one loads.
        let mapped = |d: u32| self.prefetch && self.plan.resident().contains(&d);
        let queues = || {
            self.queues
                .non_empty()
                .filter(|&d| self.plan.traces(d) && Some(d) != loading)
                .map(|d| (d, self.queues.len(d)))
        };
        let hybrid = matches!(self.plan.mode, Mode::Hybrid { .. });
        let next = if self.plan.mode != Mode::Predictive && !hybrid && !self.prefetch {
            // Neither rule above applies: the fullest traceable queue, the lower domain of
            // equal ones, as the walk below would choose, without walking every queue.
            self.queues
                .fullest_first()
                .find(|&(d, _)| self.plan.traces(d) && Some(d) != loading)
                .map(|(d, _)| d)
        } else if self.plan.mode == Mode::Predictive {
            next_queue(queues().map(|(domain, rays)| QueueView {
                domain,
                rays,
                oldest: self.scheduled_generation(domain).unwrap_or(0),
                resident: self.plan.resident().contains(&domain),
                from_eye: 0,
            }))
        } else {
            queues()
                .max_by_key(|&(d, len)| (first(d), mapped(d), len, std::cmp::Reverse(d)))
                .map(|(d, _)| d)
        };
        let Some(d) = next else {
            return Ok(None);
        };
        let rays = self.queues.take(d, max)?;
        self.forget_generations(d, &rays);
        Ok(Some((d, rays)))
    }

    /// Hybrid: up to `max` queued rays to hand to an idle peer that has `theirs` mapped (a
    /// demand-driven task), never more than half of what is queued here, so this worker stays
    /// busy too, and never rays of the domain a pass traces now (`tracing`). First every ray
    /// of the domains mapped there, fullest queue first: they cost the peer no load. Then,
    /// while coherent rays may load domains here (`demand_loads`, which the peer decides
    /// alike), the queues of domains neither planned nor mapped here that hold only camera
    /// rays and their first shadow rays (generation 0), whole: this worker would have to load
    /// those itself, so the peer's load replaces one here rather than adding one. Rays carry their tile's credit, so where
    /// they are traced changes no sum.
    pub fn take_tasks(
        &mut self,
        theirs: &BTreeSet<u32>,
        max: usize,
        tracing: Option<u32>,
    ) -> Result<Vec<RayRecord>, QueueError> {
        let Mode::Hybrid { demand_loads, .. } = self.plan.mode else {
            return Ok(Vec::new());
        };
        let mut budget = max.min(self.queued_total() / 2);
        let mut by_size: Vec<(u64, u32)> = self
            .queues
            .non_empty()
            .filter(|&d| Some(d) != tracing)
            .map(|d| (self.queues.len(d), d))
            .collect();
        by_size.sort_by_key(|&(len, d)| (std::cmp::Reverse(len), d));
        let mut given = Vec::new();
        for &(_, d) in by_size.iter().filter(|(_, d)| theirs.contains(d)) {
            if budget == 0 {
                break;
            }
            let rays = self.queues.take(d, budget)?;
            self.forget_generations(d, &rays);
            budget -= rays.len();
            given.extend(rays);
        }
        let loads_here = |d: u32| !self.plan.planned_or_resident(d) && !theirs.contains(&d);
        let costly: Vec<u32> = by_size
            .iter()
            .map(|&(_, d)| d)
            .filter(|&d| demand_loads && loads_here(d))
            .collect();
        for d in costly {
            let len = self.queues.len(d) as usize;
            if len > budget {
                continue;
            }
            // Handed over whole or not at all: a domain split between the two would be loaded
            // by both (the simulator at 16 workers: 13% more loads when split).
            let rays = self.queues.take(d, len)?;
            if rays.iter().any(|r| r.generation() != 0) {
                self.queues.push_owned(d, rays)?;
                continue;
            }
            self.generations.clear(d);
            budget -= rays.len();
            given.extend(rays);
        }
        if !given.is_empty() {
            self.report = Report::Due;
        }
        Ok(given)
    }

    /// Rays taken out of `domain`'s queue leave its generation counts.
    fn forget_generations(&mut self, domain: u32, rays: &[RayRecord]) {
        if self.queues.len(domain) == 0 {
            self.generations.clear(domain);
        } else {
            for r in rays {
                self.generations.remove(domain, r.generation());
            }
        }
    }

    /// The oldest generation queued per non-empty queue, as the oldest-generation rule counts
    /// it ([`Frame::scheduled_generation`]).
    pub fn oldest_generations(&self) -> BTreeMap<u32, u32> {
        self.queues
            .non_empty()
            .filter_map(|d| Some((d, u32::from(self.scheduled_generation(d)?))))
            .collect()
    }

    /// The generation `domain`'s queue counts as for the oldest-generation rule: when rays
    /// are placed speculatively, a few stragglers of the oldest generation for a domain not
    /// in memory count as the next one, unless that is the frame's last
    /// (`speculative::scheduled_generation`), here and in the reports the coordinator plans
    /// from, so both wait for that generation's visit.
    fn scheduled_generation(&self, domain: u32) -> Option<u16> {
        let (oldest, of_oldest) = self.generations.oldest_with_count(domain)?;
        Some(if self.speculation.is_some() {
            scheduled_generation(
                oldest,
                of_oldest,
                self.plan.resident().contains(&domain),
                last_generation(self.limits.max_depth),
            )
        } else {
            oldest
        })
    }

    /// Rays queued here, over all domains.
    pub fn queued_total(&self) -> usize {
        self.queues.total() as usize
    }

    /// Why this worker has no pass to run now (it is asked only then).
    pub fn idle_kind(&self) -> IdleKind {
        if self.queued_total() > 0 {
            IdleKind::Queued
        } else if self.speculation().is_some_and(|s| s.waiting() > 0) {
            IdleKind::Verdicts
        } else {
            IdleKind::Empty
        }
    }

    /// Rays queued per domain, non-empty queues only.
    pub fn queue_sizes(&self) -> BTreeMap<u32, u64> {
        self.queues
            .non_empty()
            .map(|d| (d, self.queues.len(d)))
            .collect()
    }

    /// Bytes of rays queued in memory and spilled to disk now.
    pub fn queue_bytes(&self) -> (u64, u64) {
        self.queues.bytes()
    }

    /// Rays spilled so far in this frame.
    pub fn spilled(&self) -> u64 {
        self.queues.spilled_total
    }

    /// Sends nothing more to `peers` (they are gone); their domains' rays wait here for the
    /// next plan.
    pub fn forget_peers(&mut self, peers: &[String]) {
        if let Some(s) = self.speculation.as_mut() {
            s.retain_current(&self.plan.epochs, peers);
        }
        self.plan.forget_peers(peers);
    }

    /// Sets aside a peer's rays of epochs newer than this worker knows for their tiles and
    /// returns the others. The coordinator's bump after a loss reaches workers at different
    /// times, and a peer that heard it first may already send rays of the new epoch (its
    /// hand-outs): dropping them as stale would lose their credit for good and the frame would
    /// never end. Raising the tile's epoch on the peer's word instead would let one forged ray
    /// drop a tile's real rays here. So they wait for the bump ([`Frame::take_announced`]); the
    /// coordinator sends it to every worker of the frame. At most `cap` bytes wait.
    pub fn set_aside_newer(
        &mut self,
        rays: Vec<RayRecord>,
        cap: u64,
    ) -> Result<Vec<RayRecord>, AheadFull> {
        let epochs = &self.plan.epochs;
        let is_newer = |r: &RayRecord| epochs.get(r.tile as usize).is_some_and(|&e| r.epoch > e);
        // Nearly always none is: the batch goes on as it came, not copied ray by ray.
        if !rays.iter().any(is_newer) {
            return Ok(rays);
        }
        let (newer, known): (Vec<RayRecord>, Vec<RayRecord>) = rays.into_iter().partition(is_newer);
        debug!(
            rays = newer.len(),
            "a peer's rays are of epochs not announced here yet: held for the bump"
        );
        self.ahead.extend(newer);
        let held = std::mem::size_of_val(self.ahead.as_slice()) as u64;
        if held > cap {
            return Err(AheadFull { held, cap });
        }
        Ok(known)
    }

    /// The set-aside rays whose epochs a bump has now announced, to route; those the tile
    /// has moved past are dropped, the rest wait on.
    pub fn take_announced(&mut self) -> Vec<RayRecord> {
        let epochs = &self.plan.epochs;
        let current = |r: &RayRecord| epochs.get(r.tile as usize).copied();
        self.ahead
            .retain(|r| current(r).is_some_and(|e| r.epoch >= e));
        let (announced, ahead) = std::mem::take(&mut self.ahead)
            .into_iter()
            .partition(|r| current(r) == Some(r.epoch));
        self.ahead = ahead;
        announced
    }

    /// Drops queued rays of the given tiles older than their new epochs. Their camera rays
    /// are not issued here any more: the coordinator deals them again.
    pub fn bump_epochs(&mut self, bumps: &BTreeMap<u32, u32>) -> Result<(), QueueError> {
        self.plan.bump_epochs(bumps);
        self.to_issue.retain(|t| !bumps.contains_key(t));
        self.report = Report::Due;
        // The coordinator forgot every member's report at the loss: the next is whole.
        self.heard = Heard::default();
        if let Some(s) = self.speculation.as_mut() {
            s.retain_current(&self.plan.epochs, &[]);
        }
        let plan = &self.plan;
        self.queues.retain(|r| plan.is_current(r.tile, r.epoch))
    }
}
