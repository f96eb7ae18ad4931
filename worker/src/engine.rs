//! The worker's shell around its machine (`rayfarm_machine::worker::Worker`): one task that
//! turns the coordinator's messages, peers' bundles and finished passes into the machine's
//! events, and carries out its actions: the control stream and peer links, passes on the
//! rayon pool, the domain cache. Opening a frame reads the scene's manifest here, so the
//! machine never touches a file.
//!
//! Apart from the event loop here, a module each: opening a frame's scene (`scene`), passes
//! and prefetches on their threads (`passes`), and what the engine adds to the metrics and a
//! frame's statistics (`counting`).

mod counting;
mod passes;
mod scene;

use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use rayfarm_core::bundler::BundlerConfig;
use rayfarm_core::render::cache::{CacheCounters, DomainCache, StorageModel};
use rayfarm_core::render::stats::peak_rss_bytes;
use rayfarm_machine::Time;
use rayfarm_machine::pass::FrameView;
use rayfarm_machine::worker::{
    self as machine, Action, PassFailed, PassOutput, Worker, WorkerConfig,
};
use rayfarm_node::cpu::ThreadClocks;
use rayfarm_node::metrics;
use rayfarm_node::proto::{self, coordinator_message::Body as FromCoordinator};
use tokio::sync::mpsc;

use crate::domains::PeerDomains;
use crate::peers::PeerLinks;
use crate::queues::FileSpill;
use counting::count_pass;
use scene::SceneKey;

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
    /// A message from the coordinator (a StartFrame is opened here before the machine sees it).
    Control(proto::CoordinatorMessage),
    /// A pass of the frame of `job_id` finished (the machine hears it with the domains mapped
    /// now).
    PassDone {
        job_id: String,
        result: Result<PassOutput, PassFailed>,
        /// When the pass ended (the time it then waits for the engine is counted).
        finished: Instant,
        /// How long it waited for a tracing thread after the engine handed it over.
        start_wait: std::time::Duration,
    },
    /// A prefetch of the frame of `job_id` ended (the machine hears it with the domains
    /// mapped now).
    PrefetchDone {
        job_id: String,
        domain: u32,
        result: Result<bool, String>,
    },
    /// Anything else, for the machine as it is: the control stream ended, a peer's bundle, a
    /// peer that stopped acknowledging.
    Machine(Box<machine::Event<FileSpill>>),
}

/// What the shell keeps of the frame it opened last: what passes read, and the cache's
/// counters at its start (the frame's statistics count from there).
struct OpenFrame {
    job_id: String,
    view: Arc<FrameView>,
    cache_at_start: CacheCounters,
    /// The tracing pool's and the process's CPU seconds when the frame opened.
    cpu_at_start: (f64, f64),
    /// How long finished passes of the frame waited for the engine to take them up.
    pass_waits: std::time::Duration,
    /// How long passes of the frame waited for a tracing thread to start them.
    pass_start_waits: std::time::Duration,
}

/// The engine. See the module documentation.
pub struct Engine {
    config: EngineConfig,
    pool: Arc<rayon::ThreadPool>,
    /// The CPU clocks of the pool's threads (the frame statistics' tracing CPU).
    trace_clocks: ThreadClocks,
    /// Finished passes and prefetches: the engine takes these before anything else queued,
    /// so a worker's next pass does not wait behind a backlog of peers' bundles (the
    /// predictive schedule's verdicts and copies arrive by the thousand).
    done: mpsc::UnboundedSender<Event>,
    done_rx: Option<mpsc::UnboundedReceiver<Event>>,
    to_coordinator: mpsc::UnboundedSender<proto::WorkerMessage>,
    peers: PeerLinks,
    machine: Worker<FileSpill>,
    clock: Instant,
    frame: Option<OpenFrame>,
    /// The scene the cache serves (its directory and its manifest, which names every domain
    /// file's checksum, so a scene re-prepared in place is a new scene), and the cache.
    cache: Option<(SceneKey, Arc<Mutex<DomainCache>>)>,
    /// The cache's counters when last added to the metrics.
    cache_counted: CacheCounters,
    /// Domains from and to peers: what loads use when a frame asks for it, the holders
    /// they may ask, and what this worker serves.
    domains: PeerDomains,
}

impl Engine {
    pub fn new(
        config: EngineConfig,
        to_coordinator: mpsc::UnboundedSender<proto::WorkerMessage>,
        peers: PeerLinks,
        domains: PeerDomains,
    ) -> anyhow::Result<Self> {
        let trace_clocks = ThreadClocks::new();
        let register = trace_clocks.clone();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(config.threads.max(1))
            .thread_name(|i| format!("trace-{i}"))
            .start_handler(move |_| register.register_current())
            .build()?;
        let machine = Worker::new(WorkerConfig {
            wave_rays: config.wave_rays,
            pass_rays: config.pass_rays,
            bundler: config.bundler,
            ..WorkerConfig::new(
                config.worker_id.clone(),
                config.advertise.clone(),
                config.cache_bytes,
            )
        })?;
        let (done, done_rx) = mpsc::unbounded_channel();
        Ok(Engine {
            config,
            pool: Arc::new(pool),
            trace_clocks,
            done,
            done_rx: Some(done_rx),
            to_coordinator,
            peers,
            machine,
            clock: Instant::now(),
            frame: None,
            cache: None,
            cache_counted: CacheCounters::default(),
            domains,
        })
    }

    /// Runs until the event channel closes.
    pub async fn run(mut self, mut events: mpsc::UnboundedReceiver<Event>) {
        let Some(mut done) = self.done_rx.take() else {
            return;
        };
        loop {
            let deadline = self
                .machine
                .next_timeout()
                .map(|t| self.clock + t.since(Time(0)));
            let event = tokio::select! {
                biased;
                // Never closed while the engine holds its sender.
                Some(event) = done.recv() => self.translate(event).await,
                event = events.recv() => match event {
                    Some(event) => self.translate(event).await,
                    None => break,
                },
                _ = sleep_until(deadline), if deadline.is_some() => machine::Event::Tick,
            };
            let now = Time::from_duration(self.clock.elapsed());
            let had_frame = self.machine.frame().is_some();
            for action in self.machine.handle(now, event) {
                self.execute(action);
            }
            if had_frame && self.machine.frame().is_none() {
                // What the frame freed goes back to the system, however it went: ended,
                // failed, declined, or dropped with the coordinator's stream.
                tokio::task::spawn_blocking(rayfarm_node::heap::release_free_memory);
                // Peers asking for its domains from now on are refused.
                self.domains.serving.set(None);
            }
            let (queued, spilled) = self.machine.frame().map_or((0, 0), |f| f.queue_bytes());
            let m = metrics::worker();
            m.queue_bytes.set(queued as i64);
            m.spill_bytes.set(spilled as i64);
        }
    }

    /// The machine's event for `event`: a StartFrame is opened first, a pass's result comes
    /// with the domains mapped now.
    async fn translate(&mut self, event: Event) -> machine::Event<FileSpill> {
        match event {
            Event::Control(msg) => match msg.body {
                Some(FromCoordinator::StartFrame(start)) => {
                    // Every cause, e.g. "spill directory D: No space left on device".
                    let opened = match self.read_scene(&start).await {
                        Ok(scene) => self.open_frame(&start, scene),
                        Err(e) => Err(e),
                    };
                    let opened = opened.map_err(|e| format!("{e:#}"));
                    machine::Event::FrameOpened { start, opened }
                }
                body => machine::Event::Control(proto::CoordinatorMessage { body }),
            },
            Event::Machine(event) => {
                if let machine::Event::PeerBundle {
                    payload: machine::Payload::Rays(batches),
                    ..
                } = event.as_ref()
                {
                    let rays: usize = batches.iter().map(Vec::len).sum();
                    metrics::worker().rays_received.inc_by(rays as u64);
                }
                *event
            }
            Event::PassDone {
                job_id,
                result,
                finished,
                start_wait,
            } => {
                if let Some(f) = self.frame.as_mut().filter(|f| f.job_id == job_id) {
                    f.pass_waits += finished.elapsed();
                    f.pass_start_waits += start_wait;
                }
                if let Ok(output) = &result {
                    count_pass(output);
                }
                self.count_cache();
                machine::Event::PassFinished {
                    job_id,
                    result,
                    resident: self.with_cache(|c| c.resident()).unwrap_or_default(),
                }
            }
            Event::PrefetchDone {
                job_id,
                domain,
                result,
            } => {
                self.count_cache();
                machine::Event::PrefetchDone {
                    job_id,
                    domain,
                    result,
                    resident: self.with_cache(|c| c.resident()).unwrap_or_default(),
                }
            }
        }
    }

    fn execute(&mut self, action: Action) {
        match action {
            Action::ToCoordinator(body) => {
                // If the control stream is gone the engine learns it from Event::Disconnected.
                let _ = self
                    .to_coordinator
                    .send(proto::WorkerMessage { body: Some(body) });
            }
            Action::ToPeer {
                peer,
                job_id,
                tier,
                batches,
            } => {
                let m = &metrics::worker().tiers[tier.index()];
                m.bundles.inc();
                for b in &batches {
                    m.bytes.inc_by(b.len() as u64);
                    m.rays.inc_by(rayfarm_core::wire::ray_count(b));
                }
                self.peers.send(&peer, &job_id, tier, batches)
            }
            Action::DropPeers(peers) => {
                metrics::worker().peers_lost.inc_by(peers.len() as u64);
                self.peers.drop_peers(&peers)
            }
            Action::StartPass { job_id, work } => self.start_pass(job_id, work),
            Action::Prefetch {
                job_id,
                domain,
                keep,
            } => self.prefetch(job_id, domain, keep),
            Action::Evict(domains) => {
                self.with_cache(|c| domains.iter().for_each(|&d| c.evict(d)));
            }
            Action::Pin(domains) => {
                self.with_cache(|c| c.pin(domains));
            }
            Action::FrameEnded { job_id, mut stats } => {
                self.count_cache();
                let mut start = CacheCounters::default();
                let mut cpu_at_start = (0.0, 0.0);
                if let Some(f) = self.frame.take_if(|f| f.job_id == job_id) {
                    (start, cpu_at_start) = (f.cache_at_start, f.cpu_at_start);
                    stats.pass_wait_seconds = f.pass_waits.as_secs_f64();
                    stats.pass_start_wait_seconds = f.pass_start_waits.as_secs_f64();
                }
                let cpu_now = self.cpu_now();
                stats.trace_cpu_seconds = (cpu_now.0 - cpu_at_start.0).max(0.0);
                stats.cpu_seconds = (cpu_now.1 - cpu_at_start.1).max(0.0);
                let cache = self
                    .with_cache(|c| c.counters().since(&start))
                    .unwrap_or_default();
                stats.cache = cache;
                stats.load_seconds = cache.load_nanos as f64 / 1e9;
                stats.threads = self.pool.current_num_threads();
                stats.peak_rss_bytes = peak_rss_bytes();
                let _ = self.to_coordinator.send(proto::WorkerMessage {
                    body: Some(proto::worker_message::Body::FrameReport(
                        proto::FrameReport {
                            job_id,
                            stats_json: serde_json::to_string(&stats).unwrap_or_default(),
                            error: String::new(),
                            declined: false,
                        },
                    )),
                });
            }
        }
    }

    fn with_cache<T>(&self, f: impl FnOnce(&mut DomainCache) -> T) -> Option<T> {
        self.cache.as_ref().map(|(_, c)| f(&mut lock(c)))
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
