//! A simulated worker: the real worker machine with what its shell would own (the domain
//! cache over the real scene, the open frame's view for passes, the peer links' unacknowledged
//! bundles), and none of its I/O. The world (`world`) delivers its events and carries its
//! actions over the simulated network.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use rayfarm_core::progressive::Samples;
use rayfarm_core::render::cache::{DomainCache, PendingLoad, SharedMappings};
use rayfarm_core::render::local::FrameSpec;
use rayfarm_core::scene::Manifest;
use rayfarm_core::wire::BatchLimits;
use rayfarm_machine::Time;
use rayfarm_machine::pass::{self, FrameView, PassInput};
use rayfarm_machine::worker::{
    DomainQueues, MemorySpill, OpenedScene, PassOutput, PassWork, Worker, WorkerConfig,
};
use rayfarm_proto as proto;

use crate::calibrate::thread_cpu_ns;
use crate::cost::CostModel;
use crate::net::NodeId;
use crate::storage::SharedStorage;

/// The scene every simulated worker reads: one directory, one manifest, and what every
/// worker derives from them alike, shared so that the simulator's memory does not grow with
/// workers x domains.
pub struct Scene {
    pub dir: PathBuf,
    pub manifest: Arc<Manifest>,
    /// Bytes of every domain file, by domain id.
    pub domain_bytes: Arc<[u64]>,
    /// One mapping of a domain for every worker's cache that holds it, so the process's
    /// mappings follow domains, not workers x domains (1,024 workers of a hundred domains
    /// each are over Linux's 65,530 mappings a process). `None`: each cache maps its own, as
    /// a real worker does (the figures are the same either way; a test compares them).
    pub mappings: Option<Arc<SharedMappings>>,
    /// The view of the frame opened last (its job, tile size and samples): every worker of a
    /// frame opens the same one.
    frame_view: Mutex<Option<(FrameKey, Arc<FrameView>, BatchLimits)>>,
}

/// What a frame's view depends on besides the scene (a job's spec is fixed).
type FrameKey = (String, u32, Samples);

impl Scene {
    /// The scene of `manifest`, read from `dir`.
    pub fn new(dir: PathBuf, manifest: Manifest) -> Self {
        Scene {
            dir,
            domain_bytes: manifest.domains.iter().map(|d| d.bytes).collect(),
            manifest: Arc::new(manifest),
            mappings: Some(Arc::new(SharedMappings::new())),
            frame_view: Mutex::new(None),
        }
    }

    /// The view of `frame` of job `job_id`, opened once for all workers that open it.
    fn frame_view(
        &self,
        job_id: &str,
        frame: &FrameSpec,
        tile_size: u32,
        samples: Samples,
    ) -> Result<(Arc<FrameView>, BatchLimits), String> {
        let key = (job_id.to_string(), tile_size, samples);
        let mut held = self.frame_view.lock().unwrap_or_else(|p| p.into_inner());
        if let Some((k, view, limits)) = held.as_ref()
            && *k == key
        {
            return Ok((view.clone(), *limits));
        }
        let (view, limits) = FrameView::open(&self.manifest, frame, tile_size, samples)?;
        let view = Arc::new(view);
        *held = Some((key, view.clone(), limits));
        Ok((view, limits))
    }
}

/// How big a worker's queues may grow (the caps the invariants check).
#[derive(Clone, Copy, Debug)]
pub struct QueueCaps {
    pub queue_bytes: u64,
    pub spill_bytes: u64,
}

/// A worker's outbound link to one peer (the worker's `peers::run_link` task and its
/// stream): the bundles the peer has not acknowledged, oldest first, each with when the link
/// took it (the real link times a bundle from there), and when the link is done sending
/// the bundles it took so far.
#[derive(Default)]
pub struct PeerLink {
    pub owed: VecDeque<(u64, Time)>,
    /// Reported unresponsive since the link was last opened.
    pub reported: bool,
    /// When the link has encoded and handed to the NIC every bundle it took: the next one
    /// is sent after them (one stream a peer, in order), whatever the worker's shell does.
    pub sending_until: Time,
}

/// A finished pass: its output and the virtual time it took.
pub struct PassRun {
    pub result: Result<PassOutput, String>,
    pub took: std::time::Duration,
    /// Domains it had to load, and the part of `took` the loads took.
    pub loads: u64,
    pub load_time: std::time::Duration,
    /// CPU time of this thread the pass took on this machine, when measured (`calibrate`).
    pub cpu_ns: Option<u64>,
}

/// See the module documentation.
pub struct SimWorker {
    pub node: NodeId,
    pub id: String,
    pub address: String,
    pub cache_bytes: u64,
    /// Most bytes of bundles it may hold for frames not started.
    pub early_cap: usize,
    pub machine: Worker<MemorySpill>,
    /// False once killed: nothing reaches it or comes from it any more.
    pub alive: bool,
    /// It takes and acknowledges no peer bundle from this time on.
    pub stuck_from: Option<Time>,
    /// Its control stream was closed by the coordinator (it was dropped).
    pub disconnected: bool,
    /// Its control stream now (each registration opens a new one).
    pub conn: u64,
    /// The pass running now, if any: when it ends and when its domain loads end.
    pub pass_until: Option<(Time, Time)>,
    /// When a Tick is due.
    pub tick_at: Option<Time>,
    /// When its line to the storage is free: its loads, a pass's and a prefetch's, are read
    /// one after another.
    io_free_at: Time,
    /// When its shell (the worker's engine task) is done with what it was given so far:
    /// finished passes' outputs and peers' bundles are taken in one after another, beside
    /// its passes.
    pub msg_free_at: Time,
    pub links: BTreeMap<String, PeerLink>,
    /// By sender: when this worker's peer service is done decoding the bundles that sender's
    /// stream brought so far (one task a stream, bundles in order; each is acknowledged once
    /// decoded, before the engine takes it in).
    pub inbound: BTreeMap<NodeId, Time>,
    /// By sender: when the engine takes in the last bundle that sender's stream brought (in
    /// the order they came).
    pub taken_from: BTreeMap<NodeId, Time>,
    pub next_bundle: u64,
    scene: Arc<Scene>,
    cache: Arc<Mutex<DomainCache>>,
    frame: Option<(String, Arc<FrameView>)>,
    caps: QueueCaps,
}

impl SimWorker {
    /// Worker `id` at `address` on node `node`, with a cache of `cache_bytes` over `scene`.
    pub fn new(
        node: NodeId,
        config: WorkerConfig,
        scene: Arc<Scene>,
        caps: QueueCaps,
    ) -> Result<Self, String> {
        // Loads are priced by the storage model: the disk's page cache stays warm.
        let mut cache = DomainCache::shared(&scene.dir, scene.manifest.clone(), config.cache_bytes)
            .keep_page_cache();
        if let Some(m) = &scene.mappings {
            cache = cache.with_shared_mappings(m.clone());
        }
        Ok(SimWorker {
            node,
            id: config.worker_id.clone(),
            address: config.advertise.clone(),
            cache_bytes: config.cache_bytes,
            early_cap: config.early_bytes,
            machine: Worker::new(config).map_err(|e| e.to_string())?,
            alive: true,
            stuck_from: None,
            disconnected: false,
            conn: 0,
            pass_until: None,
            tick_at: None,
            io_free_at: Time(0),
            msg_free_at: Time(0),
            links: BTreeMap::new(),
            inbound: BTreeMap::new(),
            taken_from: BTreeMap::new(),
            next_bundle: 0,
            scene,
            cache: Arc::new(Mutex::new(cache)),
            frame: None,
            caps,
        })
    }

    /// Whether it is stuck on its peer port at `t`.
    pub fn is_stuck(&self, t: Time) -> bool {
        self.stuck_from.is_some_and(|s| s <= t)
    }

    /// What the shell reads for a StartFrame: the frame's view over the scene and its empty
    /// queues (in memory).
    pub fn open(&mut self, s: &proto::StartFrame) -> Result<OpenedScene<MemorySpill>, String> {
        let spec = s.spec.as_ref().ok_or("StartFrame without a job spec")?;
        let scene = self.scene.clone();
        let frame = rayfarm_node::job::frame_spec(spec, &scene.manifest.camera)?;
        let samples = rayfarm_node::job::start_samples(s, frame.spp)?;
        let (view, limits) = scene.frame_view(&s.job_id, &frame, s.tile_size, samples)?;
        let grid = view.grid;
        let spp = samples.count;
        self.frame = Some((s.job_id.clone(), view));
        let resident = self.lock().resident();
        Ok(OpenedScene {
            grid,
            spp,
            limits,
            domain_bytes: scene.domain_bytes.clone(),
            resident,
            queues: DomainQueues::new(
                scene.domain_bytes.len(),
                self.caps.queue_bytes,
                self.caps.spill_bytes,
                MemorySpill::default(),
            ),
        })
    }

    /// Runs a pass of `job_id` at `now`, on the real kernel, and prices it with `cost`, its
    /// loads read from `storage`; with `measure`, also the CPU time it took here.
    pub fn run_pass(
        &mut self,
        now: Time,
        job_id: &str,
        work: PassWork,
        cost: &CostModel,
        storage: &mut SharedStorage,
        measure: bool,
    ) -> PassRun {
        let Some((_, frame)) = self.frame.as_ref().filter(|(j, _)| j == job_id) else {
            return PassRun {
                result: Err("no scene open for the pass".into()),
                took: Default::default(),
                loads: 0,
                load_time: Default::default(),
                cpu_ns: None,
            };
        };
        let before = self.lock().counters();
        let input = PassInput {
            frame: frame.clone(),
            work,
            cache: self.cache.clone(),
        };
        let started = measure.then(thread_cpu_ns);
        let result = pass::run(input).map_err(|e| e.to_string());
        let cpu_ns = started.map(|s| thread_cpu_ns().saturating_sub(s));
        let after = self.lock().counters();
        let loads = after.loads - before.loads;
        let load_time = self.read(
            now,
            loads,
            after.bytes_loaded - before.bytes_loaded,
            storage,
        );
        let took = load_time
            + result
                .as_ref()
                .map_or(Default::default(), |o| cost.pass(&o.counters));
        let result = result.map(|mut o| {
            o.busy = took;
            o
        });
        PassRun {
            result,
            took,
            loads,
            load_time,
            cpu_ns,
        }
    }

    /// Reads `loads` domains of `bytes` from `storage` at `now` after the loads already on
    /// this node's line: how long until they are in.
    fn read(&mut self, now: Time, loads: u64, bytes: u64, storage: &mut SharedStorage) -> Duration {
        if loads == 0 {
            return Duration::ZERO;
        }
        let start = now.max(self.io_free_at);
        let done = start + storage.read(start, loads, bytes);
        self.io_free_at = done;
        done.since(now)
    }

    /// Starts a prefetch of `domain` at `now` if it fits without evicting `keep` (as the
    /// shell's cache decides): the load to finish with [`SimWorker::finish_prefetch`], and
    /// when its bytes are in (at once when there is nothing to load).
    pub fn begin_prefetch(
        &mut self,
        now: Time,
        domain: u32,
        keep: &BTreeSet<u32>,
        storage: &mut SharedStorage,
    ) -> (Option<PendingLoad>, Duration) {
        let pending = self.lock().begin_prefetch(domain, keep);
        let bytes = self.scene.domain_bytes.get(domain as usize).copied();
        match (pending, bytes) {
            (Some(p), Some(bytes)) => {
                let took = self.read(now, 1, bytes, storage);
                (Some(p), took)
            }
            _ => (None, Duration::ZERO),
        }
    }

    /// Maps a prefetched domain whose bytes are in: `Ok(true)` if it was kept (see
    /// `DomainCache::finish_prefetch`), `Ok(false)` if there was nothing to load.
    pub fn finish_prefetch(
        &mut self,
        pending: Option<PendingLoad>,
        keep: &BTreeSet<u32>,
    ) -> Result<bool, String> {
        let Some(pending) = pending else {
            return Ok(false);
        };
        let loaded = pending.read().map_err(|e| e.to_string())?;
        Ok(self.lock().finish_prefetch(loaded, keep))
    }

    /// Domains mapped now.
    pub fn resident(&self) -> Vec<u32> {
        self.lock().resident()
    }

    pub fn evict(&self, domains: &[u32]) {
        let mut c = self.lock();
        domains.iter().for_each(|&d| c.evict(d));
    }

    pub fn pin(&self, domains: Vec<u32>) {
        self.lock().pin(domains);
    }

    /// The cache's counters since the process started (a simulated worker runs one frame).
    pub fn cache_counters(&self) -> rayfarm_core::render::cache::CacheCounters {
        self.lock().counters()
    }

    /// Bytes of rays its running frame holds queued, and the most it may.
    pub fn queued_bytes(&self) -> (u64, u64) {
        let queued = self.machine.frame().map_or(0, |f| f.queued_total() as u64);
        (
            queued * rayfarm_machine::worker::queues::RAY_BYTES,
            self.caps.queue_bytes + self.caps.spill_bytes,
        )
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, DomainCache> {
        self.cache.lock().unwrap_or_else(|p| p.into_inner())
    }
}
