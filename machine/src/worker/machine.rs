//! The worker as a state machine: [`Worker::handle`] takes an [`Event`] with the time it
//! happened and returns the [`Action`]s it calls for. It owns the frame (queues, plan,
//! speculation groups), the bundler and the bundles held for frames not started yet; the
//! shell owns the sockets, the domain cache, the tracing pool and the clock.

use std::sync::Arc;
use std::time::Duration;

use rayfarm_core::bundler::{Bundler, BundlerConfig, ConfigError};
use rayfarm_core::cluster::stats::{WorkerFrameStats, tier_traffic};
use rayfarm_core::schedule::speculation_depth::parse_setting;
use rayfarm_core::schedule::speculative::Generations;
use rayfarm_proto::{self as proto, Schedule, coordinator_message::Body as FromCoordinator};
use tracing::{debug, error, info, info_span, warn};

use super::early::EarlyBundles;
use super::events::{Action, Event, OpenedScene, PassFailed, PassOutput, PassWork};
use super::frame::{Frame, FrameParts};
use super::plan::{HolderLine, Mode};
use super::queues::{QueueError, RaySpill};
use crate::Time;

/// Most rays handed to an idle peer for one `ShareTasks`, whatever the coordinator asks
/// (about 6.5 MiB of records).
const MAX_TASK_RAYS: usize = 1 << 16;

/// Longest a plan may hold this worker's report of running dry (`RoundPlan.report_hold_ms`),
/// whatever the coordinator asks: a worker waiting longer for work that never comes would
/// stall its part of the frame.
const MAX_REPORT_HOLD_MS: u64 = 10_000;

/// Recently ended jobs remembered, so that their late bundles are dropped, not held.
const ENDED_KEPT: usize = 16;

/// What the worker machine needs to know about itself.
#[derive(Clone, Debug)]
pub struct WorkerConfig {
    pub worker_id: String,
    /// Address peers reach this worker at.
    pub advertise: String,
    /// The domain cache's budget (hybrid: whether demand loads fit).
    pub cache_bytes: u64,
    /// Camera rays are issued while fewer than this many rays are queued here.
    pub wave_rays: usize,
    /// Most rays traced in one pass.
    pub pass_rays: usize,
    pub bundler: BundlerConfig,
    /// Most bytes of bundles held for frames not started here yet.
    pub early_bytes: usize,
    /// Bundles held for a frame that has not started here within this are dropped.
    pub early_timeout: Duration,
    /// Most bytes of a peer's rays of epochs not announced here yet, waiting for the
    /// coordinator's bump (`Frame::set_aside_newer`); past it, this worker leaves the frame.
    pub ahead_bytes: u64,
}

impl WorkerConfig {
    /// The defaults of the worker binary for what it has no flag for.
    pub fn new(worker_id: String, advertise: String, cache_bytes: u64) -> Self {
        WorkerConfig {
            worker_id,
            advertise,
            cache_bytes,
            wave_rays: 1 << 20,
            pass_rays: 1 << 18,
            bundler: BundlerConfig::default(),
            early_bytes: 256 << 20,
            early_timeout: Duration::from_secs(30),
            ahead_bytes: 64 << 20,
        }
    }
}

/// See the module documentation.
pub struct Worker<S> {
    pub(super) config: WorkerConfig,
    pub(super) bundler: Bundler<String>,
    pub(super) frame: Option<Frame<S>>,
    pub(super) pass_running: bool,
    /// The domain the running pass traces, if it traces one.
    pub(super) tracing: Option<u32>,
    /// The domain a prefetch is loading, if one is under way.
    pub(super) prefetching: Option<u32>,
    /// Domains a plan evicted while the running pass traced them: evicted when it ends.
    pub(super) evict_after_pass: Vec<u32>,
    pub(super) early: EarlyBundles,
    /// Recently ended jobs: their late bundles are dropped.
    pub(super) ended: Vec<String>,
    /// The time of the event being handled.
    pub(super) now: Time,
    pub(super) actions: Vec<Action>,
}

impl<S: RaySpill> Worker<S> {
    pub fn new(config: WorkerConfig) -> Result<Self, ConfigError> {
        Ok(Worker {
            bundler: Bundler::new(config.bundler)?,
            early: EarlyBundles::new(config.early_bytes, config.early_timeout),
            config,
            frame: None,
            pass_running: false,
            tracing: None,
            prefetching: None,
            evict_after_pass: Vec::new(),
            ended: Vec::new(),
            now: Time::default(),
            actions: Vec::new(),
        })
    }

    /// The frame running here, if any.
    pub fn frame(&self) -> Option<&Frame<S>> {
        self.frame.as_ref()
    }

    /// Bytes of bundles held for frames not started yet.
    pub fn early_bytes(&self) -> usize {
        self.early.bytes()
    }

    /// When to send [`Event::Tick`] if nothing else happens first (a bundle falls due, or a
    /// report held for a plan's work is due).
    pub fn next_timeout(&self) -> Option<Time> {
        let bundles = self.bundler.next_deadline().map(Time::from_duration);
        // The end of a held report, unless a pass runs (its end reports or pumps anyway).
        let held = self
            .frame
            .as_ref()
            .filter(|_| !self.pass_running)
            .and_then(|f| f.report_held(self.now));
        bundles.into_iter().chain(held).min()
    }

    /// Reacts to `event`, which happened at `now`; then starts the next pass or reports the
    /// round's end here. Returns what the shell must do, in order.
    pub fn handle(&mut self, now: Time, event: Event<S>) -> Vec<Action> {
        self.now = self.now.max(now);
        match event {
            Event::Control(msg) => self.control(msg),
            Event::SharedControl(msg) => match &msg.body {
                Some(FromCoordinator::Holders(h)) => self.holders(h),
                _ => self.control(Arc::unwrap_or_clone(msg)),
            },
            Event::FrameOpened { start, opened } => self.start_frame(start, opened),
            Event::Disconnected => {
                if let Some(f) = self.frame.take() {
                    warn!(job = %f.job_id, "lost the coordinator: dropping the frame");
                }
            }
            Event::PeerBundle {
                sender,
                job_id,
                payload,
            } => self.peer_bundle(sender, job_id, payload),
            Event::PeerUnresponsive { peer, reason } => {
                self.actions.push(Action::DropPeers(vec![peer.clone()]));
                self.send(proto::worker_message::Body::PeerUnresponsive(
                    proto::PeerUnresponsive {
                        peer_address: peer,
                        reason,
                    },
                ));
            }
            Event::PassFinished {
                job_id,
                result,
                resident,
            } => {
                self.pass_running = false;
                self.tracing = None;
                // The plan's eviction of the domain this pass traced waited for the pass.
                let mut resident = resident;
                let evict = std::mem::take(&mut self.evict_after_pass);
                if !evict.is_empty() {
                    resident.retain(|d| !evict.contains(d));
                    self.actions.push(Action::Evict(evict));
                }
                // A pass of a frame that has ended since is of no use.
                if self.frame.as_ref().is_some_and(|f| f.job_id == job_id) {
                    match result {
                        Ok(out) => self.pass_done(out, resident),
                        Err(PassFailed::Load(e)) => self.decline_frame(e),
                        Err(PassFailed::SceneReplaced(e)) => self.fail_frame(e),
                    }
                }
            }
            Event::PrefetchDone {
                job_id,
                domain,
                result,
                resident,
            } => {
                self.prefetching = None;
                if let Some(f) = self.frame.as_mut().filter(|f| f.job_id == job_id) {
                    match result {
                        Ok(kept) => debug!(domain, kept, "prefetch done"),
                        Err(e) => warn!(domain, error = %e, "prefetch failed"),
                    }
                    f.set_resident(resident);
                    // As after a pass: a domain the load pushed out sends its rays on.
                    self.send_to_holders();
                }
            }
            Event::Tick => self.send_due_bundles(),
        }
        self.pump();
        std::mem::take(&mut self.actions)
    }

    fn control(&mut self, msg: proto::CoordinatorMessage) {
        match msg.body {
            Some(FromCoordinator::Registered(r)) => {
                info!(
                    heartbeat_ms = r.heartbeat_ms,
                    "registered with the coordinator"
                );
            }
            Some(FromCoordinator::StartFrame(s)) => {
                // The shell opens the scene first and sends Event::FrameOpened.
                error!(job = %s.job_id, "StartFrame reached the machine unopened: ignored");
            }
            Some(FromCoordinator::RoundPlan(p)) => self.round_plan(p),
            Some(FromCoordinator::EpochBump(b)) => {
                let Some(f) = self.frame.as_mut().filter(|f| f.job_id == b.job_id) else {
                    return;
                };
                warn!(tiles = b.epochs.len(), lost = ?b.lost_peers, "epochs bumped");
                f.forget_peers(&b.lost_peers);
                let bumped = f
                    .bump_epochs(&b.epochs.into_iter().collect())
                    .and_then(|()| {
                        let announced = f.take_announced();
                        f.route(announced)
                    });
                self.actions.push(Action::DropPeers(b.lost_peers));
                match bumped {
                    Ok(out) => {
                        for (peer, rays) in out {
                            self.send_rays(peer, &rays);
                        }
                    }
                    Err(e) => self.queue_failed(e),
                }
            }
            Some(FromCoordinator::EndFrame(e)) => self.end_frame(&e.job_id),
            Some(FromCoordinator::Holders(h)) => self.holders(&h),
            Some(FromCoordinator::Roster(r)) => self.roster(r),
            Some(FromCoordinator::ShareTasks(t)) => self.share_tasks(t),
            Some(FromCoordinator::HandOutTiles(h)) => {
                if let Some(f) = self.frame.as_mut().filter(|f| f.job_id == h.job_id) {
                    f.hand_out(h.tiles);
                }
            }
            None => warn!("empty message from the coordinator"),
        }
    }

    fn start_frame(&mut self, s: proto::StartFrame, opened: Result<OpenedScene<S>, String>) {
        let _span = info_span!("start_frame", job = %s.job_id).entered();
        if let Some(old) = self.frame.take() {
            warn!(job = %old.job_id, "a new frame replaces an unfinished one");
        }
        // The job may run again (a restarted coordinator, a worker taken back): its bundles
        // count from now on.
        self.ended.retain(|j| *j != s.job_id);
        // Bundles of an older frame are worthless now, and the counters start afresh.
        if let Ok(fresh) = Bundler::new(self.config.bundler) {
            self.bundler = fresh;
        }
        match opened.and_then(|scene| self.open_frame(&s, scene)) {
            Ok(frame) => {
                info!(tiles = s.primary_tiles.len(), "frame started");
                self.frame = Some(frame);
                for (sender, payload) in self.early.take(&s.job_id) {
                    self.peer_bundle(sender, s.job_id.clone(), payload);
                }
            }
            Err(e) => {
                error!(error = %e, "cannot take part in the frame");
                self.mark_ended(&s.job_id);
                self.send(proto::worker_message::Body::FrameReport(
                    proto::FrameReport {
                        job_id: s.job_id.clone(),
                        stats_json: String::new(),
                        error: format!("worker {}: {e}", self.config.worker_id),
                        declined: true,
                    },
                ));
            }
        }
    }

    fn open_frame(&self, s: &proto::StartFrame, scene: OpenedScene<S>) -> Result<Frame<S>, String> {
        let spec = s.spec.as_ref().ok_or("StartFrame without a job spec")?;
        let tiles = scene.grid.count();
        if s.primary_tiles.iter().any(|&t| t >= tiles) {
            return Err(format!("primary tiles outside the frame's {tiles} tiles"));
        }
        let mode = match Schedule::try_from(spec.schedule) {
            Ok(Schedule::ImagePlane) => Mode::ImagePlane,
            Ok(Schedule::Domain) => Mode::Domain,
            Ok(Schedule::Dynamic | Schedule::Unspecified) => Mode::Dynamic,
            Ok(Schedule::Predictive) => Mode::Predictive,
            // Demand loads are decided again with each plan, once the owned domains are known.
            Ok(Schedule::Hybrid) => Mode::Hybrid {
                demand_loads: false,
                rounds: s.hybrid_rounds,
            },
            Err(_) => return Err(format!("unknown schedule {}", spec.schedule)),
        };
        Ok(Frame::new(FrameParts {
            mode,
            job_id: s.job_id.clone(),
            grid: scene.grid,
            spp: scene.spp,
            limits: scene.limits,
            domain_bytes: scene.domain_bytes,
            to_issue: s.primary_tiles.clone(),
            prefetch: spec.prefetch,
            queues: scene.queues,
            me: s.worker_key,
            started: self.now,
            round: s.round,
            epochs: s.epochs.clone(),
            resident: scene.resident,
            speculation: match mode {
                Mode::Predictive => parse_setting(&spec.speculation)?,
                _ => None,
            },
        }))
    }

    fn round_plan(&mut self, p: proto::RoundPlan) {
        let Some(frame) = self.frame.as_mut().filter(|f| f.job_id == p.job_id) else {
            debug!(job = %p.job_id, "plan for a frame not running here");
            return;
        };
        // The domain a pass is tracing is evicted when the pass ends, not now: evicted under
        // the pass, it would be loaded again for that pass (handed over before the plan
        // came, on a cluster the pass may not have taken the domain from the cache yet: 13
        // such loads in one 4-worker big48 frame, most for a handful of rays). A plan that
        // works on it again keeps it.
        let tracing = self.tracing;
        self.evict_after_pass.retain(|d| !p.work_on.contains(d));
        let (later, evict): (Vec<u32>, Vec<u32>) =
            p.evict.iter().partition(|&&d| Some(d) == tracing);
        self.evict_after_pass.extend(later);
        let _span = info_span!("round", round = p.round).entered();
        // A whole map's packed part first (a delta has none): domain d's one holder's key
        // plus one, 0 for none there.
        let sole = if p.holders_delta {
            Vec::new()
        } else {
            p.sole_holders
        };
        let sole = sole
            .into_iter()
            .zip(0u32..)
            .filter(|&(k, _)| k != 0)
            .map(|(k, domain)| HolderLine {
                domain,
                workers: vec![k - 1].into(),
                lost: Default::default(),
            });
        let hold = Duration::from_millis(u64::from(p.report_hold_ms).min(MAX_REPORT_HOLD_MS));
        frame.set_plan(
            p.round,
            p.work_on.iter().copied(),
            sole.chain(p.holders.iter().map(line)),
            p.holders_delta,
            (!hold.is_zero()).then(|| self.now + hold),
        );
        // The cache as the machine knows it: mapped at the last pass's end, less what this plan
        // evicts (the cache changes only in passes and by these actions). A pass running now
        // may map one more; its PassFinished says so.
        let resident: Vec<u32> = frame
            .plan()
            .resident_by_use()
            .iter()
            .copied()
            .filter(|d| !p.evict.contains(d))
            .collect();
        frame.set_resident(resident);
        frame.set_next(p.next.iter().copied());
        let pinned = frame.decide_demand_loads(self.config.cache_bytes);
        debug!(work_on = ?p.work_on, evict = ?p.evict, after_the_pass = ?self.evict_after_pass, "round plan");
        self.actions.push(Action::Evict(evict));
        self.actions.push(Action::Pin(pinned));
        self.send_to_holders();
    }

    /// Another worker's plan changed: rays waiting here for its domains go to it now.
    fn holders(&mut self, h: &proto::Holders) {
        let Some(frame) = self.frame.as_mut().filter(|f| f.job_id == h.job_id) else {
            return;
        };
        frame.set_holders(h.holders.iter().map(line), h.delta);
        self.send_to_holders();
    }

    /// Sends every queued ray that now has a holder elsewhere.
    fn send_to_holders(&mut self) {
        let Some(frame) = self.frame.as_mut() else {
            return;
        };
        match frame.take_for_peers() {
            Ok(out) => {
                for (peer, rays) in out {
                    self.send_rays(peer, &rays);
                }
                self.send_due_bundles();
            }
            Err(e) => self.queue_failed(e),
        }
    }

    /// Hybrid: the coordinator asks this worker to hand part of its queue to an idle peer
    /// (`Frame::take_tasks` chooses what); the rays go at once in the tasks tier, and the
    /// coordinator hears how many went and how many are left here.
    fn share_tasks(&mut self, t: proto::ShareTasks) {
        let tracing = self.tracing;
        let Some(frame) = self.frame.as_mut().filter(|f| f.job_id == t.job_id) else {
            // Not running that frame (it ended here, or this worker sits it out): say it holds
            // nothing, so the coordinator asks another worker for the idle one at once rather
            // than leaving it unfed until its next report.
            debug!(job = %t.job_id, to = %t.to, "asked to share tasks of a frame not running here");
            let answer = proto::TasksShared {
                job_id: t.job_id,
                to: t.to,
                rays: 0,
                queued: 0,
            };
            return self.send(proto::worker_message::Body::TasksShared(answer));
        };
        let rays = if t.to == self.config.advertise {
            warn!("asked to share tasks with itself: ignored");
            Vec::new()
        } else {
            let theirs = t.receiver_domains.iter().copied().collect();
            let max = (t.max_rays as usize).min(MAX_TASK_RAYS);
            match frame.take_tasks(&theirs, max, tracing) {
                Ok(rays) => rays,
                Err(e) => return self.queue_failed(e),
            }
        };
        frame.counters.rays_shared += rays.len() as u64;
        let answer = proto::TasksShared {
            job_id: t.job_id,
            to: t.to.clone(),
            rays: rays.len() as u64,
            queued: frame.queued_total() as u64,
        };
        debug!(to = %t.to, rays = rays.len(), "shared tasks");
        if !rays.is_empty() {
            self.send_tasks(t.to.clone(), &rays);
            // The receiver is idle: its work leaves now, not when the tier falls due.
            let bundles = self.bundler.flush_peer(&t.to);
            self.send_bundles(bundles);
        }
        self.send(proto::worker_message::Body::TasksShared(answer));
    }

    /// The frame's workers (after its StartFrame, or a worker joined): rays and verdicts held
    /// for a peer the roster did not name can go.
    fn roster(&mut self, r: proto::Roster) {
        let Some(frame) = self.frame.as_mut().filter(|f| f.job_id == r.job_id) else {
            return;
        };
        for (peer, verdicts) in frame.set_roster(r.members) {
            self.send_verdicts(peer, &verdicts);
        }
        self.send_to_holders();
    }

    /// Drops the bundles held for `job_id` and those that arrive late for it.
    fn mark_ended(&mut self, job_id: &str) {
        self.early.take(job_id);
        self.ended.push(job_id.to_string());
        if self.ended.len() > ENDED_KEPT {
            self.ended.remove(0);
        }
    }

    fn end_frame(&mut self, job_id: &str) {
        self.mark_ended(job_id);
        let Some(mut frame) = self.frame.take_if(|f| f.job_id == job_id) else {
            return;
        };
        frame.counters.close_idle(self.now);
        let c = &frame.counters;
        let frame_seconds = self.now.since(frame.started).as_secs_f64();
        let busy_seconds = c.busy.as_secs_f64();
        let stats = WorkerFrameStats {
            worker_id: self.config.worker_id.clone(),
            rays: c.rays,
            rays_sent: c.rays_sent,
            bytes_sent: c.bytes_sent,
            rays_received: c.rays_received,
            rays_spilled: frame.spilled(),
            verdicts_refused: frame.speculation().map_or(0, |s| s.refused),
            rays_shared: c.rays_shared,
            passes: c.passes,
            tiers: tier_traffic(self.bundler.stats()),
            busy_seconds,
            frame_seconds,
            idle_fraction: (1.0 - busy_seconds / frame_seconds.max(1e-9)).clamp(0.0, 1.0),
            idle_queued_seconds: c.idle[0].as_secs_f64(),
            idle_verdicts_seconds: c.idle[1].as_secs_f64(),
            idle_empty_seconds: c.idle[2].as_secs_f64(),
            ..WorkerFrameStats::default()
        };
        info!(job = %job_id, segments = c.rays.segments(), busy_seconds, "frame ended");
        self.actions.push(Action::FrameEnded {
            job_id: job_id.to_string(),
            // Boxed: the statistics are many times the size of every other action.
            stats: Box::new(stats),
        });
    }

    /// Fails the running frame for everyone.
    fn fail_frame(&mut self, error: String) {
        self.end_with_error(error, false);
    }

    /// Leaves the running frame for a reason of this worker's own: the coordinator deals its
    /// tiles to the others.
    pub(super) fn decline_frame(&mut self, error: String) {
        self.end_with_error(error, true);
    }

    /// A full or failing spill store is this worker's problem: it leaves the frame. Rays past
    /// every budget fail the frame (more workers would help, not fewer).
    pub(super) fn queue_failed(&mut self, e: QueueError) {
        match e {
            QueueError::Spill(_) => self.decline_frame(e.to_string()),
            QueueError::Full { .. } => self.fail_frame(e.to_string()),
        }
    }

    fn end_with_error(&mut self, error: String, declined: bool) {
        if let Some(frame) = self.frame.take() {
            error!(job = %frame.job_id, %error, declined, "frame ended with an error on this worker");
            // Peers go on sending rays until they hear this worker left: none is kept.
            self.mark_ended(&frame.job_id);
            self.send(proto::worker_message::Body::FrameReport(
                proto::FrameReport {
                    job_id: frame.job_id,
                    stats_json: String::new(),
                    error: format!("worker {}: {error}", self.config.worker_id),
                    declined,
                },
            ));
        }
    }

    fn pass_done(&mut self, out: PassOutput, resident: Vec<u32>) {
        let Some(frame) = self.frame.as_mut() else {
            return;
        };
        frame.counters.rays.add(&out.counters);
        frame.counters.passes += 1;
        frame.counters.busy += out.busy;
        frame.set_resident(resident);
        if !out.results.is_empty() {
            let msg = proto::TileResults {
                job_id: frame.job_id.clone(),
                results: out.results,
                segments_traced: frame.counters.rays.segments(),
            };
            self.send(proto::worker_message::Body::TileResults(msg));
        }
        let Some(frame) = self.frame.as_mut() else {
            return;
        };
        let (rays, verdicts) = frame.born(out.rays, out.paths, out.verdicts);
        for (peer, verdicts) in verdicts {
            self.send_verdicts(peer, &verdicts);
        }
        let Some(frame) = self.frame.as_mut() else {
            return;
        };
        let out_rays = match frame.route(rays) {
            Ok(r) => r,
            Err(e) => return self.queue_failed(e),
        };
        for (peer, rays) in out_rays {
            self.send_rays(peer, &rays);
        }
        // What the pass's loads pushed out of the cache is no longer traced here: rays kept
        // for it go to its holders now, not at the next plan (which a member that reported
        // them may never get: the coordinator counts on them leaving).
        self.send_to_holders();
    }

    /// Starts the next pass, or, with nothing to do, sends everything pending and tells the
    /// coordinator this worker's queues (the end of its round); then starts loading the next
    /// domain ahead of need, if the frame prefetches.
    fn pump(&mut self) {
        self.pump_pass();
        self.prefetch();
    }

    /// Asks the shell to load the frame's next domain ahead of need, unless a prefetch is
    /// under way.
    fn prefetch(&mut self) {
        if self.prefetching.is_some() {
            return;
        }
        let Some(frame) = self.frame.as_mut() else {
            return;
        };
        let Some((domain, keep)) = frame.next_prefetch(self.tracing) else {
            return;
        };
        debug!(domain, "prefetching");
        self.prefetching = Some(domain);
        self.actions.push(Action::Prefetch {
            job_id: frame.job_id.clone(),
            domain,
            keep,
        });
    }

    fn pump_pass(&mut self) {
        if self.pass_running {
            return;
        }
        let loading = self.prefetching;
        let Some(frame) = self.frame.as_mut() else {
            return;
        };
        let primaries = frame.next_primaries(self.config.wave_rays);
        let trace = match frame.take_work(self.config.pass_rays, loading) {
            Ok(t) => t,
            Err(e) => return self.queue_failed(e),
        };
        let speculative = frame.take_to_conclude();
        let concluding = speculative.as_ref().is_some_and(|c| !c.is_empty());
        if primaries.is_empty() && trace.is_none() && !concluding {
            let (now, kind) = (self.now, frame.idle_kind());
            frame.counters.open_idle(now, kind);
            // A new plan's work may be on its way: the report waits for it (a tick at the
            // hold's end reports, `next_timeout`).
            if frame.report_held(now).is_some() {
                return;
            }
            // The domain being prefetched has work here: its load ends this wait.
            if !loading.is_some_and(|d| frame.has_work_for(d)) {
                self.report_idle();
            }
            return;
        }
        frame.counters.close_idle(self.now);
        frame.pass_started();
        self.pass_running = true;
        self.tracing = trace.as_ref().map(|(d, _)| *d);
        // `mapped`: false when the pass loads its domain; `generations`: its rays of each
        // generation, oldest first (bench/validation/generations.py reads both from a debug
        // log: which generation each load served). Evaluated only when debug is on.
        debug!(
            domain = ?self.tracing,
            rays = trace.as_ref().map_or(0, |(_, r)| r.len()),
            primaries = primaries.len(),
            mapped = ?trace.as_ref().map(|(d, _)| frame.plan().resident().contains(d)),
            generations = ?trace.as_ref().map(|(_, rays)| {
                rays.iter().map(|r| r.generation()).collect::<Generations>().counts().to_vec()
            }),
            "pass handed over"
        );
        let job_id = frame.job_id.clone();
        self.actions.push(Action::StartPass {
            job_id,
            work: PassWork {
                primaries,
                trace,
                speculative,
            },
        });
    }

    fn report_idle(&mut self) {
        let bundles = self.bundler.flush_all(self.bundler_now());
        self.send_bundles(bundles);
        let Some(frame) = self.frame.as_mut() else {
            return;
        };
        let Some(report) = frame.take_report() else {
            return;
        };
        debug!(
            round = report.round,
            queued = frame.queued_total(),
            "round done here"
        );
        self.send(proto::worker_message::Body::QueueReport(report));
    }

    fn send(&mut self, body: proto::worker_message::Body) {
        self.actions.push(Action::ToCoordinator(body));
    }
}

/// A holders message's line for one domain as the plan takes it.
fn line(h: &proto::DomainHolders) -> HolderLine<'_> {
    HolderLine {
        domain: h.domain,
        workers: h.workers.as_slice().into(),
        lost: h.lost.as_slice().into(),
    }
}
