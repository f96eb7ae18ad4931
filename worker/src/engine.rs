//! The worker's engine: one task that owns the frame state and reacts to the coordinator's
//! messages, to ray bundles from peers and to finished passes. Tracing runs on a rayon pool,
//! one pass at a time, while the engine keeps routing and reporting.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use bytes::Bytes;
use rayfarm_core::bundler::{Bundle, Bundler, BundlerConfig, PushErrorKind, Tier};
use rayfarm_core::camera::PinholeCamera;
use rayfarm_core::cluster::scene_ref;
use rayfarm_core::cluster::stats::{WorkerFrameStats, tier_traffic};
use rayfarm_core::frame::TileGrid;
use rayfarm_core::ray::RayRecord;
use rayfarm_core::render::SceneView;
use rayfarm_core::render::cache::{CacheCounters, DomainCache, StorageModel};
use rayfarm_core::render::stats::peak_rss_bytes;
use rayfarm_core::scene::Manifest;
use rayfarm_core::wire::{self, BatchLimits, VerdictRecord};
use rayfarm_node::job;
use rayfarm_node::proto::{self, Schedule, coordinator_message::Body as FromCoordinator};
use tokio::sync::mpsc;
use tracing::{debug, error, info, info_span, warn};

use crate::frame::{Frame, Mode};
use crate::pass::{self, FrameView, PassError, PassInput, PassOutput};
use crate::peers::PeerLinks;
use crate::queues::{DomainQueues, QueueError};
use rayfarm_machine::worker::Speculation;

/// Rays per encoded batch sent to a peer (160 KiB).
const BATCH_RAYS: usize = 2048;

/// Most bytes of bundles held for frames not started here yet. Peers run ahead of this
/// worker's StartFrame by a round trip at most; past this, a peer is sending for a frame
/// that will not come, and its bundles are dropped.
const EARLY_BYTES: usize = 256 << 20;

/// Bundles held for a frame that has not started here within this are dropped: a peer does
/// not run that far ahead of a StartFrame that is coming.
const EARLY_TIMEOUT: Duration = Duration::from_secs(30);

/// Bundles that arrived for one job this worker has not started yet.
struct EarlyBundles {
    /// When the first arrived (see [`EARLY_TIMEOUT`]).
    since: Instant,
    /// Every byte they hold, ids and bookkeeping included (see [`early_cost`]).
    bytes: usize,
    bundles: Vec<(String, proto::Tier, Vec<Bytes>)>,
}

/// What holding one early bundle costs: its batches, its sender and job ids, and the
/// per-batch and per-bundle bookkeeping.
fn early_cost(sender: &str, job_id: &str, batches: &[Bytes]) -> usize {
    let batch_bytes: usize = batches
        .iter()
        .map(|b| b.len() + std::mem::size_of::<Bytes>())
        .sum();
    batch_bytes
        + sender.len()
        + job_id.len()
        + std::mem::size_of::<(String, proto::Tier, Vec<Bytes>)>()
}

/// What the engine needs to know about itself.
#[derive(Clone, Debug)]
pub struct EngineConfig {
    pub worker_id: String,
    /// Address peers reach this worker at.
    pub advertise: String,
    pub scene_root: PathBuf,
    /// Scenes may be absolute paths (else names under `scene_root` only).
    pub allow_absolute_scenes: bool,
    pub cache_bytes: u64,
    pub threads: usize,
    /// Camera rays are issued while fewer than this many rays are queued here.
    pub wave_rays: usize,
    /// Most rays traced in one pass.
    pub pass_rays: usize,
    pub bundler: BundlerConfig,
    /// Emulated storage speed charged on every domain load (benchmarks).
    pub storage: StorageModel,
    /// Most bytes of queued rays held in memory; the rest spill to `spill_dir`.
    pub queue_bytes: u64,
    /// Most bytes of rays spilled to disk before the frame fails.
    pub spill_bytes: u64,
    pub spill_dir: PathBuf,
}

/// Something the engine reacts to.
pub enum Event {
    /// A message from the coordinator.
    Control(proto::CoordinatorMessage),
    /// The control stream ended; frame state is dropped (the coordinator forgets this worker).
    Disconnected,
    /// A bundle from a peer, not yet decoded: ray batches, or in the results tier verdicts.
    PeerBundle {
        sender: String,
        job_id: String,
        tier: proto::Tier,
        batches: Vec<Bytes>,
    },
    /// A peer stopped acknowledging bundles (see `peers::LinkLimits`).
    PeerUnresponsive { peer: String, reason: String },
    /// A pass of the frame of `job_id` finished.
    PassDone {
        job_id: String,
        result: Result<PassOutput, PassError>,
    },
}

/// What identifies a scene to the cache: its directory and its manifest.
type SceneKey = (PathBuf, Manifest);

/// The engine. See the module documentation.
pub struct Engine {
    config: EngineConfig,
    pool: Arc<rayon::ThreadPool>,
    events: mpsc::UnboundedSender<Event>,
    to_coordinator: mpsc::UnboundedSender<proto::WorkerMessage>,
    peers: PeerLinks,
    bundler: Bundler<String>,
    clock: Instant,
    frame: Option<Frame>,
    /// The scene the cache serves (its directory and its manifest, which names every domain
    /// file's checksum, so a scene re-prepared in place is a new scene), and the cache.
    cache: Option<(SceneKey, Arc<Mutex<DomainCache>>)>,
    pass_running: bool,
    /// Bundles that arrived for a job this worker has not started yet.
    early: BTreeMap<String, EarlyBundles>,
    /// Sum of `bytes` over `early`, kept up to date (never recounted per bundle).
    early_bytes: usize,
    /// Recently ended jobs: their late bundles are dropped.
    ended: Vec<String>,
}

impl Engine {
    pub fn new(
        config: EngineConfig,
        events: mpsc::UnboundedSender<Event>,
        to_coordinator: mpsc::UnboundedSender<proto::WorkerMessage>,
        peers: PeerLinks,
    ) -> anyhow::Result<Self> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(config.threads.max(1))
            .thread_name(|i| format!("trace-{i}"))
            .build()?;
        let bundler = Bundler::new(config.bundler)?;
        Ok(Engine {
            config,
            pool: Arc::new(pool),
            events,
            to_coordinator,
            peers,
            bundler,
            clock: Instant::now(),
            frame: None,
            cache: None,
            pass_running: false,
            early: BTreeMap::new(),
            early_bytes: 0,
            ended: Vec::new(),
        })
    }

    /// Runs until the event channel closes.
    pub async fn run(mut self, mut events: mpsc::UnboundedReceiver<Event>) {
        loop {
            let deadline = self.bundler.next_deadline().map(|d| self.clock + d);
            tokio::select! {
                event = events.recv() => match event {
                    Some(event) => self.handle(event),
                    None => break,
                },
                _ = sleep_until(deadline), if deadline.is_some() => self.send_due_bundles(),
            }
            self.pump();
        }
    }

    fn now(&self) -> Duration {
        self.clock.elapsed()
    }

    fn handle(&mut self, event: Event) {
        match event {
            Event::Control(msg) => match msg.body {
                Some(FromCoordinator::Registered(r)) => {
                    info!(
                        heartbeat_ms = r.heartbeat_ms,
                        "registered with the coordinator"
                    );
                }
                Some(FromCoordinator::StartFrame(s)) => self.start_frame(s),
                Some(FromCoordinator::RoundPlan(p)) => self.round_plan(p),
                Some(FromCoordinator::EpochBump(b)) => {
                    let bumped = match self.frame.as_mut().filter(|f| f.job_id == b.job_id) {
                        Some(f) => {
                            warn!(tiles = b.epochs.len(), lost = ?b.lost_peers, "epochs bumped");
                            f.forget_peers(&b.lost_peers);
                            self.peers.drop_peers(&b.lost_peers);
                            f.bump_epochs(&b.epochs.into_iter().collect())
                        }
                        None => Ok(()),
                    };
                    if let Err(e) = bumped {
                        self.queue_failed(e);
                    }
                }
                Some(FromCoordinator::EndFrame(e)) => self.end_frame(&e.job_id),
                Some(FromCoordinator::Holders(h)) => self.holders(h),
                Some(FromCoordinator::Roster(r)) => self.roster(r),
                Some(FromCoordinator::HandOutTiles(h)) => {
                    if let Some(f) = self.frame.as_mut().filter(|f| f.job_id == h.job_id) {
                        let tiles = f.shared.grid.count();
                        f.to_issue
                            .extend(h.tiles.into_iter().filter(|&t| t < tiles));
                        f.reported = false;
                    }
                }
                None => warn!("empty message from the coordinator"),
            },
            Event::Disconnected => {
                if let Some(f) = self.frame.take() {
                    warn!(job = %f.job_id, "lost the coordinator: dropping the frame");
                }
            }
            Event::PeerBundle {
                sender,
                job_id,
                tier,
                batches,
            } => self.peer_bundle(sender, job_id, tier, batches),
            Event::PeerUnresponsive { peer, reason } => {
                self.peers.drop_peers(std::slice::from_ref(&peer));
                self.send(proto::worker_message::Body::PeerUnresponsive(
                    proto::PeerUnresponsive {
                        peer_address: peer,
                        reason,
                    },
                ));
            }
            Event::PassDone { job_id, result } => {
                self.pass_running = false;
                // A pass of a frame that has ended since is of no use.
                if self.frame.as_ref().is_some_and(|f| f.job_id == job_id) {
                    match result {
                        Ok(out) => self.pass_done(out),
                        Err(e) => self.pass_failed(&e),
                    }
                }
            }
        }
    }

    fn start_frame(&mut self, s: proto::StartFrame) {
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
        match self.open_frame(&s) {
            Ok(mut frame) => {
                if let Some((_, cache)) = &self.cache {
                    frame.cache_at_start = lock(cache).counters();
                }
                info!(tiles = s.primary_tiles.len(), "frame started");
                self.frame = Some(frame);
                let early = self.take_early(&s.job_id);
                for (sender, tier, batches) in early {
                    self.peer_bundle(sender, s.job_id.clone(), tier, batches);
                }
            }
            Err(e) => {
                error!(error = %format_args!("{e:#}"), "cannot take part in the frame");
                self.mark_ended(&s.job_id);
                self.send(proto::worker_message::Body::FrameReport(
                    proto::FrameReport {
                        job_id: s.job_id.clone(),
                        stats_json: String::new(),
                        error: format!("worker {}: {e:#}", self.config.worker_id),
                        declined: true,
                    },
                ));
            }
        }
    }

    fn open_frame(&mut self, s: &proto::StartFrame) -> anyhow::Result<Frame> {
        let spec = s
            .spec
            .as_ref()
            .ok_or_else(|| anyhow::anyhow!("StartFrame without a job spec"))?;
        let dir = scene_ref::resolve(
            &self.config.scene_root,
            &spec.scene,
            self.config.allow_absolute_scenes,
        )?;
        if !dir.is_dir() {
            // Each node names its own mount point of the shared storage.
            anyhow::bail!(
                "scene {:?} not found: {} is not a directory (is --scene-root {} where this \
                 node sees the scenes?)",
                spec.scene,
                dir.display(),
                self.config.scene_root.display()
            );
        }
        let manifest = Manifest::load(&dir)?;
        let frame = job::frame_spec(spec, &manifest.camera).map_err(anyhow::Error::msg)?;
        let grid = TileGrid::new(frame.width, frame.height, s.tile_size)
            .ok_or_else(|| anyhow::anyhow!("bad tile size {}", s.tile_size))?;
        if s.primary_tiles.iter().any(|&t| t >= grid.count()) {
            anyhow::bail!("primary tiles outside the frame's {} tiles", grid.count());
        }
        let camera = PinholeCamera::new(
            frame.camera.as_ref().unwrap_or(&manifest.camera),
            frame.width,
            frame.height,
        );
        let view = SceneView::new(&manifest, frame.max_depth as u16);
        let limits = BatchLimits {
            domains: manifest.domains.len() as u32,
            pixels: frame.width * frame.height,
            max_depth: frame.max_depth as u16,
            materials: manifest.materials.len() as u32,
            max_records: 1 << 20,
        };
        // Keyed by the manifest too: the domains mapped for an older version of the scene in
        // this directory are never traced for the new one (their files were replaced by a
        // rename, so the old mappings stay intact for passes still holding them).
        let scene_key = (dir, manifest.clone());
        if self.cache.as_ref().is_none_or(|(key, _)| *key != scene_key) {
            if self.cache.is_some() {
                info!(scene = %spec.scene, "scene changed on disk: opening it afresh");
            }
            let cache = DomainCache::new(&scene_key.0, &manifest, self.config.cache_bytes)
                .with_storage(self.config.storage);
            self.cache = Some((scene_key, Arc::new(Mutex::new(cache))));
        } else if let Some((_, cache)) = &self.cache {
            let mut cache = lock(cache);
            cache.pin([]);
            if spec.cold_cache {
                cache.clear();
            }
        }
        let mode = match Schedule::try_from(spec.schedule) {
            Ok(Schedule::ImagePlane) => Mode::ImagePlane,
            Ok(Schedule::Domain) => Mode::Domain,
            Ok(Schedule::Dynamic | Schedule::Unspecified) => Mode::Dynamic,
            Ok(Schedule::Predictive) => Mode::Predictive,
            // Decided again with each plan, once the owned domains are known.
            Ok(Schedule::Hybrid) => Mode::Hybrid {
                demand_loads: false,
            },
            Err(_) => anyhow::bail!("unknown schedule {}", spec.schedule),
        };
        let shared = Arc::new(FrameView {
            view,
            camera,
            grid,
            spp: frame.spp,
        });
        let queues = DomainQueues::new(
            manifest.domains.len(),
            self.config.queue_bytes,
            self.config.spill_bytes,
            &self.config.spill_dir,
        )
        .with_context(|| format!("spill directory {}", self.config.spill_dir.display()))?;
        let mut frame = Frame::new(
            mode,
            s.job_id.clone(),
            shared,
            limits,
            s.primary_tiles.clone(),
            queues,
            self.config.advertise.clone(),
        );
        frame.plan.round = s.round;
        if mode == Mode::Predictive {
            frame.speculation = Some(Speculation::new(s.worker_key, s.roster.clone()));
        }
        for (&tile, &epoch) in &s.epochs {
            if let Some(e) = frame.plan.epochs.get_mut(tile as usize) {
                *e = epoch;
            }
        }
        Ok(frame)
    }

    fn round_plan(&mut self, p: proto::RoundPlan) {
        let Some(frame) = self.frame.as_mut().filter(|f| f.job_id == p.job_id) else {
            debug!(job = %p.job_id, "plan for a frame not running here");
            return;
        };
        let _span = info_span!("round", round = p.round).entered();
        frame.set_plan(
            p.round,
            p.work_on.iter().copied(),
            p.holders.into_iter().map(|h| (h.domain, h.workers)),
        );
        if let Some((_, cache)) = &self.cache {
            let mut cache = lock(cache);
            for d in &p.evict {
                cache.evict(*d);
            }
            frame.plan.set_resident(cache.resident());
            let pinned = frame.decide_demand_loads(self.config.cache_bytes, &cache.domain_bytes());
            cache.pin(pinned);
        }
        debug!(work_on = ?p.work_on, evict = ?p.evict, "round plan");
        let job_id = frame.job_id.clone();
        match frame.take_for_peers() {
            Ok(out) => {
                for (peer, rays) in out {
                    self.send_rays(&job_id, peer, &rays);
                }
                self.send_due_bundles();
            }
            Err(e) => self.queue_failed(e),
        }
    }

    /// Another worker's plan changed: rays waiting here for its domains go to it now.
    fn holders(&mut self, h: proto::Holders) {
        let Some(frame) = self.frame.as_mut().filter(|f| f.job_id == h.job_id) else {
            return;
        };
        frame
            .plan
            .set_holders(h.holders.into_iter().map(|h| (h.domain, h.workers)));
        let job_id = frame.job_id.clone();
        match frame.take_for_peers() {
            Ok(out) => {
                // The coordinator counted these rays here: it must hear they left.
                if !out.is_empty() {
                    frame.reported = false;
                }
                for (peer, rays) in out {
                    self.send_rays(&job_id, peer, &rays);
                }
                self.send_due_bundles();
            }
            Err(e) => self.queue_failed(e),
        }
    }

    /// A worker joined the frame: verdicts held for it can go.
    fn roster(&mut self, r: proto::Roster) {
        let Some(frame) = self.frame.as_mut().filter(|f| f.job_id == r.job_id) else {
            return;
        };
        let Some(spec) = frame.speculation.as_mut() else {
            return;
        };
        let job_id = frame.job_id.clone();
        for (peer, verdicts) in spec.set_roster(r.members) {
            self.send_verdicts(&job_id, peer, &verdicts);
        }
        self.send_due_bundles();
    }

    /// Removes and returns the early bundles of `job_id`.
    fn take_early(&mut self, job_id: &str) -> Vec<(String, proto::Tier, Vec<Bytes>)> {
        let Some(early) = self.early.remove(job_id) else {
            return Vec::new();
        };
        self.early_bytes -= early.bytes;
        early.bundles
    }

    /// Drops the early bundles of jobs that have not started within [`EARLY_TIMEOUT`].
    fn expire_early(&mut self) {
        let expired: Vec<String> = self
            .early
            .iter()
            .filter(|(_, e)| e.since.elapsed() > EARLY_TIMEOUT)
            .map(|(job, _)| job.clone())
            .collect();
        for job in expired {
            let dropped = self.take_early(&job);
            warn!(
                job = %rayfarm_node::bounds::shown(&job),
                bundles = dropped.len(),
                "dropping bundles for a frame that did not start here within {EARLY_TIMEOUT:?}"
            );
        }
    }

    fn end_frame(&mut self, job_id: &str) {
        self.mark_ended(job_id);
        let Some(frame) = self.frame.take_if(|f| f.job_id == job_id) else {
            return;
        };
        let c = &frame.counters;
        let frame_seconds = frame.started.elapsed().as_secs_f64();
        let busy_seconds = c.busy.as_secs_f64();
        let cache = self
            .cache
            .as_ref()
            .map(|(_, cache)| since(&frame.cache_at_start, &lock(cache).counters()))
            .unwrap_or_default();
        let stats = WorkerFrameStats {
            worker_id: self.config.worker_id.clone(),
            threads: self.pool.current_num_threads(),
            rays: c.rays,
            cache,
            rays_sent: c.rays_sent,
            bytes_sent: c.bytes_sent,
            rays_received: c.rays_received,
            rays_spilled: frame.spilled(),
            verdicts_refused: frame.speculation.as_ref().map_or(0, |s| s.refused),
            tiers: tier_traffic(self.bundler.stats()),
            busy_seconds,
            load_seconds: cache.load_nanos as f64 / 1e9,
            frame_seconds,
            idle_fraction: (1.0 - busy_seconds / frame_seconds.max(1e-9)).clamp(0.0, 1.0),
            peak_rss_bytes: peak_rss_bytes(),
        };
        info!(job = %job_id, segments = c.rays.segments(), busy_seconds, "frame ended");
        self.send(proto::worker_message::Body::FrameReport(
            proto::FrameReport {
                job_id: job_id.to_string(),
                stats_json: serde_json::to_string(&stats).unwrap_or_default(),
                error: String::new(),
                declined: false,
            },
        ));
    }

    /// Leaves the running frame for a reason of this worker's own (the coordinator deals its
    /// tiles to the others), rather than failing the job.
    fn decline_frame(&mut self, error: String) {
        self.end_with_error(error, true);
    }

    /// A domain this worker cannot load (missing, damaged) leaves it out of the frame; if it
    /// is the same for every worker, the job fails with all their reasons. But a scene whose
    /// manifest changed on disk since the frame opened it was re-prepared in place: its new
    /// domain files do not match the manifest the frame traces by, and tracing on would mix
    /// the two versions, so the frame fails for everyone, naming the scene.
    fn pass_failed(&mut self, e: &PassError) {
        let replaced = self.cache.as_ref().and_then(|((dir, manifest), _)| {
            (Manifest::load(dir).ok().as_ref() != Some(manifest)).then(|| dir.clone())
        });
        match replaced {
            Some(dir) => self.end_with_error(
                format!(
                    "scene {} was replaced on disk while its frame ran (re-prepared in \
                     place?): {e}; submit the job again to render the new version",
                    dir.display()
                ),
                false,
            ),
            None => self.decline_frame(e.to_string()),
        }
    }

    /// A full or failing spill directory is this worker's problem: it leaves the frame. Rays
    /// beyond every budget fail the frame (more workers would help, not fewer).
    fn queue_failed(&mut self, e: QueueError) {
        match e {
            QueueError::Io(_) => self.decline_frame(format!(
                "spill directory {}: {e}",
                self.config.spill_dir.display()
            )),
            QueueError::Full { .. } => self.end_with_error(e.to_string(), false),
        }
    }

    /// Drops the bundles parked for `job_id` and those that arrive late for it.
    fn mark_ended(&mut self, job_id: &str) {
        self.take_early(job_id);
        self.ended.push(job_id.to_string());
        if self.ended.len() > 16 {
            self.ended.remove(0);
        }
    }

    fn end_with_error(&mut self, error: String, declined: bool) {
        if let Some(frame) = self.frame.take() {
            // Peers go on sending rays until they hear this worker left: none is kept.
            self.mark_ended(&frame.job_id);
            error!(job = %frame.job_id, %error, declined, "frame ended with an error on this worker");
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

    fn peer_bundle(
        &mut self,
        sender: String,
        job_id: String,
        tier: proto::Tier,
        batches: Vec<Bytes>,
    ) {
        let Some(frame) = self.frame.as_mut().filter(|f| f.job_id == job_id) else {
            if self.ended.contains(&job_id) {
                return;
            }
            self.expire_early();
            // A job's first early bundle also pays for its id as the map's key.
            let key_bytes = if self.early.contains_key(&job_id) {
                0
            } else {
                job_id.len()
            };
            let bytes = early_cost(&sender, &job_id, &batches) + key_bytes;
            let held = self.early_bytes;
            if held + bytes > EARLY_BYTES {
                error!(
                    sender = %rayfarm_node::bounds::shown(&sender),
                    job = %rayfarm_node::bounds::shown(&job_id),
                    bytes, held,
                    "dropping a bundle for a frame not started here: {EARLY_BYTES} bytes are held already"
                );
                return;
            }
            let early = self.early.entry(job_id).or_insert_with(|| EarlyBundles {
                since: Instant::now(),
                bytes: 0,
                bundles: Vec::new(),
            });
            early.bytes += bytes;
            self.early_bytes += bytes;
            early.bundles.push((sender, tier, batches));
            return;
        };
        if tier == proto::Tier::Results {
            return self.peer_verdicts(&sender, batches);
        }
        let mut forward: BTreeMap<String, Vec<RayRecord>> = BTreeMap::new();
        for batch in batches {
            let rays = match wire::decode_batch(&batch, &frame.limits) {
                Ok(rays) => rays,
                Err(e) => {
                    error!(%sender, error = %e, "dropping a malformed ray batch from a peer");
                    continue;
                }
            };
            frame.counters.rays_received += rays.len() as u64;
            match frame.route(rays) {
                Ok(out) => {
                    for (peer, mut rays) in out {
                        forward.entry(peer).or_default().append(&mut rays);
                    }
                }
                Err(e) => return self.queue_failed(e),
            }
        }
        // New rays here change what the coordinator should know at the round's end.
        frame.reported = false;
        for (peer, rays) in forward {
            self.send_rays(&job_id, peer, &rays);
        }
    }

    /// Verdicts from a peer for rays born here.
    fn peer_verdicts(&mut self, sender: &str, batches: Vec<Bytes>) {
        let Some(frame) = self.frame.as_mut() else {
            return;
        };
        let Some(spec) = frame.speculation.as_mut() else {
            warn!(%sender, "dropping verdicts: this frame places no rays speculatively");
            return;
        };
        for batch in batches {
            match wire::decode_verdicts(&batch, &frame.limits) {
                Ok(verdicts) => spec.settle(&verdicts),
                Err(e) => error!(%sender, error = %e, "dropping a malformed verdict batch"),
            }
        }
        // Concluding them makes new work, which the coordinator should hear of.
        frame.reported = false;
    }

    fn pass_done(&mut self, out: PassOutput) {
        let Some(frame) = self.frame.as_mut() else {
            return;
        };
        frame.counters.rays.add(&out.counters);
        frame.counters.busy += out.busy;
        if let Some((_, cache)) = &self.cache {
            frame.plan.set_resident(lock(cache).resident());
        }
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
        let job_id = frame.job_id.clone();
        let (rays, verdicts) = match frame.speculation.as_mut() {
            Some(spec) => {
                // Rays born of a tile restarted while the pass ran would wait forever.
                let (born, paths): (Vec<RayRecord>, Vec<Vec<u32>>) = out
                    .rays
                    .into_iter()
                    .zip(out.paths)
                    .filter(|(r, _)| frame.plan.is_current(r.tile, r.epoch))
                    .unzip();
                let copies = spec.spread(&born, &paths);
                // Copies queued here for domains no one traces yet must be reported.
                frame.reported = false;
                (copies, spec.address(out.verdicts))
            }
            None => (out.rays, BTreeMap::new()),
        };
        for (peer, verdicts) in verdicts {
            self.send_verdicts(&job_id, peer, &verdicts);
        }
        let Some(frame) = self.frame.as_mut() else {
            return;
        };
        let out_rays = match frame.route(rays) {
            Ok(r) => r,
            Err(e) => return self.queue_failed(e),
        };
        for (peer, rays) in out_rays {
            self.send_rays(&job_id, peer, &rays);
        }
        self.send_due_bundles();
    }

    /// Starts the next pass, or, with nothing to do, sends everything pending and tells the
    /// coordinator this worker's queues (the end of its round).
    fn pump(&mut self) {
        if self.pass_running {
            return;
        }
        let Some(frame) = self.frame.as_mut() else {
            return;
        };
        let mut primaries = Vec::new();
        // Rays born here and waiting for verdicts count too: they bound the groups' memory.
        let waiting = frame.speculation.as_ref().map_or(0, |s| s.waiting());
        let mut queued = frame.queued_total() + waiting;
        while queued < self.config.wave_rays
            && let Some(tile) = frame.to_issue.pop_front()
        {
            primaries.push((tile, frame.plan.epochs[tile as usize]));
            queued += frame.shared.grid.tile_pixel_count(tile) * frame.shared.spp as usize;
        }
        let trace = match frame.take_work(self.config.pass_rays) {
            Ok(t) => t,
            Err(e) => return self.queue_failed(e),
        };
        let speculative = frame
            .speculation
            .as_mut()
            .map(|s| std::mem::take(&mut s.to_conclude));
        let concluding = speculative.as_ref().is_some_and(|c| !c.is_empty());
        if primaries.is_empty() && trace.is_none() && !concluding {
            self.report_idle();
            return;
        }
        let Some((_, cache)) = &self.cache else {
            return;
        };
        let input = PassInput {
            frame: frame.shared.clone(),
            primaries,
            trace,
            speculative,
            cache: cache.clone(),
        };
        self.pass_running = true;
        let pool = self.pool.clone();
        let events = self.events.clone();
        let job_id = frame.job_id.clone();
        tokio::task::spawn_blocking(move || {
            let result = pool.install(|| pass::run(input));
            // The engine may be gone at shutdown; nothing is left to do then.
            let _ = events.send(Event::PassDone { job_id, result });
        });
    }

    fn report_idle(&mut self) {
        let bundles = self.bundler.flush_all(self.now());
        self.send_bundles(bundles);
        let Some(frame) = self.frame.as_mut() else {
            return;
        };
        if frame.reported {
            return;
        }
        frame.reported = true;
        let resident = self
            .cache
            .as_ref()
            .map(|(_, c)| lock(c).resident())
            .unwrap_or_default();
        let report = proto::QueueReport {
            job_id: frame.job_id.clone(),
            round: frame.plan.round,
            resident_domains: resident,
            queued_rays: frame.queue_sizes().into_iter().collect(),
            oldest_generation: match frame.plan.mode {
                Mode::Predictive => frame.oldest_generations().into_iter().collect(),
                _ => Default::default(),
            },
            oldest_waiting: frame
                .speculation
                .as_ref()
                .and_then(|s| s.oldest_waiting())
                .map(u32::from),
        };
        debug!(
            round = frame.plan.round,
            queued = frame.queued_total(),
            "round done here"
        );
        self.send(proto::worker_message::Body::QueueReport(report));
    }

    fn send(&self, body: proto::worker_message::Body) {
        // If the control stream is gone the engine learns it from Event::Disconnected.
        let _ = self
            .to_coordinator
            .send(proto::WorkerMessage { body: Some(body) });
    }

    /// Queues rays for a peer in the bundler's migrated-ray tier.
    fn send_rays(&mut self, job_id: &str, peer: String, rays: &[RayRecord]) {
        if let Some(frame) = self.frame.as_mut() {
            frame.counters.rays_sent += rays.len() as u64;
        }
        for chunk in rays.chunks(BATCH_RAYS) {
            let msg = Bytes::from(wire::encode_batch(chunk));
            if let Some(frame) = self.frame.as_mut() {
                frame.counters.bytes_sent += msg.len() as u64;
            }
            self.push_bundled(job_id, &peer, Tier::Migrated, msg);
        }
    }

    fn push_bundled(&mut self, job_id: &str, peer: &String, tier: Tier, mut msg: Bytes) {
        loop {
            match self.bundler.push(peer.clone(), tier, msg, self.now()) {
                Ok(()) => break,
                Err(e) if matches!(e.kind, PushErrorKind::PeerFull { .. }) => {
                    // The peer's bulk queue is full: send what it holds, then retry.
                    let bundles = self.bundler.flush_peer(peer);
                    self.send_bundles_for(job_id, bundles);
                    msg = e.into_message();
                }
                Err(e) => {
                    error!(%peer, error = %e, "batch refused by the bundler");
                    break;
                }
            }
        }
    }

    /// Queues verdicts for a peer in the bundler's results tier (they free its memory).
    fn send_verdicts(&mut self, job_id: &str, peer: String, verdicts: &[VerdictRecord]) {
        for chunk in verdicts.chunks(BATCH_RAYS) {
            let msg = Bytes::from(wire::encode_verdicts(chunk));
            if let Some(frame) = self.frame.as_mut() {
                frame.counters.bytes_sent += msg.len() as u64;
            }
            self.push_bundled(job_id, &peer, Tier::Results, msg);
        }
    }

    fn send_due_bundles(&mut self) {
        let bundles = self.bundler.poll(self.now());
        self.send_bundles(bundles);
    }

    fn send_bundles(&mut self, bundles: Vec<Bundle<String>>) {
        let Some(job_id) = self.frame.as_ref().map(|f| f.job_id.clone()) else {
            return;
        };
        self.send_bundles_for(&job_id, bundles);
    }

    fn send_bundles_for(&mut self, job_id: &str, bundles: Vec<Bundle<String>>) {
        for b in bundles {
            self.peers.send(&b.peer, job_id, b.tier, b.messages);
        }
    }
}

/// Cache counters of a frame: what changed since its start (the peak is the process's).
fn since(start: &CacheCounters, now: &CacheCounters) -> CacheCounters {
    CacheCounters {
        loads: now.loads - start.loads,
        bytes_loaded: now.bytes_loaded - start.bytes_loaded,
        evictions: now.evictions - start.evictions,
        peak_resident_bytes: now.peak_resident_bytes,
        load_nanos: now.load_nanos - start.load_nanos,
    }
}

fn lock(cache: &Mutex<DomainCache>) -> std::sync::MutexGuard<'_, DomainCache> {
    // A poisoned lock means a pass panicked; the cache's own state is still consistent.
    cache.lock().unwrap_or_else(|p| p.into_inner())
}

async fn sleep_until(deadline: Option<Instant>) {
    match deadline {
        Some(d) => tokio::time::sleep_until(d.into()).await,
        None => std::future::pending().await,
    }
}
