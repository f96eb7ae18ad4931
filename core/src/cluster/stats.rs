//! Statistics of one frame rendered by the cluster (DESIGN.md "What is measured"): what each
//! worker reports when the frame ends, and the coordinator's sum of them.

use serde::{Deserialize, Serialize};

use crate::bundler::{Tier, TierStats};
use crate::render::cache::CacheCounters;
use crate::render::kernel::KernelCounters;

/// Traffic of one bundler tier.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct TierTraffic {
    /// Tier name: results, migrated, tasks.
    pub tier: String,
    /// Bundles, messages and bytes sent.
    #[serde(flatten)]
    pub sent: TierStats,
}

/// The tier counters of a bundler, most urgent tier first.
pub fn tier_traffic(stats: &crate::bundler::Stats) -> Vec<TierTraffic> {
    Tier::MOST_URGENT_FIRST
        .into_iter()
        .map(|t| TierTraffic {
            tier: tier_name(t).to_string(),
            sent: stats[t],
        })
        .collect()
}

/// Lower-case name of a tier.
pub fn tier_name(tier: Tier) -> &'static str {
    match tier {
        Tier::Results => "results",
        Tier::Migrated => "migrated",
        Tier::Tasks => "tasks",
    }
}

/// What one worker did for one frame.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WorkerFrameStats {
    /// The worker.
    pub worker_id: String,
    /// Threads it traced with.
    pub threads: usize,
    /// Rays it created and traced.
    pub rays: KernelCounters,
    /// Its domain cache.
    pub cache: CacheCounters,
    /// Rays it sent to other workers.
    pub rays_sent: u64,
    /// Ray bytes it sent to other workers (wire format).
    pub bytes_sent: u64,
    /// Rays it received from other workers.
    pub rays_received: u64,
    /// Rays that did not fit its queue memory and went to disk for a while.
    #[serde(default)]
    pub rays_spilled: u64,
    /// Predictive schedule: verdicts that settled no waiting ray (stale after a fault, or
    /// not for a ray born here).
    #[serde(default)]
    pub verdicts_refused: u64,
    /// Hybrid schedule: queued rays it handed to idle workers as demand-driven tasks (sent in
    /// the tasks tier; also counted in `rays_sent`).
    #[serde(default)]
    pub rays_shared: u64,
    /// Bundles sent to peers, per tier.
    pub tiers: Vec<TierTraffic>,
    /// Seconds spent in passes (tracing, issuing camera rays, domain loads).
    pub busy_seconds: f64,
    /// Of `busy_seconds`, the time spent mapping and checking domains.
    #[serde(default)]
    pub load_seconds: f64,
    /// Seconds from the frame's start to its end on this worker.
    pub frame_seconds: f64,
    /// Fraction of the frame spent not tracing.
    pub idle_fraction: f64,
    /// CPU seconds its tracing threads used during the frame (passes: tracing, issuing
    /// camera rays, checking loaded domains). Below `busy_seconds - load_seconds` when the
    /// threads waited for a core; 0 when not measured (older workers, other systems).
    #[serde(default)]
    pub trace_cpu_seconds: f64,
    /// CPU seconds the whole worker process used during the frame (tracing, the network,
    /// bundling, prefetches); 0 when not measured.
    #[serde(default)]
    pub cpu_seconds: f64,
    /// Seconds with no pass to run while rays were queued here for domains the round's plan
    /// did not let it trace (waiting for the next plan, or for a prefetch to land).
    #[serde(default)]
    pub idle_queued_seconds: f64,
    /// Seconds with no pass to run, nothing queued, and rays of its own waiting for their
    /// copies' verdicts (predictive).
    #[serde(default)]
    pub idle_verdicts_seconds: f64,
    /// Seconds with no pass to run and nothing queued or waiting: waiting for peers' rays
    /// or the frame's end.
    #[serde(default)]
    pub idle_empty_seconds: f64,
    /// Seconds finished passes waited for the worker's event loop to take them up (part of
    /// neither busy nor idle time).
    #[serde(default)]
    pub pass_wait_seconds: f64,
    /// Seconds passes handed to the tracing pool waited for a tracing thread to start them
    /// (part of neither busy nor idle time; on a machine with fewer cores than busy threads,
    /// the operating system's wake-up of the thread).
    #[serde(default)]
    pub pass_start_wait_seconds: f64,
    /// Passes the worker ran in the frame.
    #[serde(default)]
    pub passes: u64,
    /// Peak resident memory of the process, bytes.
    pub peak_rss_bytes: u64,
}

fn is_zero(n: &u64) -> bool {
    *n == 0
}

fn one() -> u32 {
    1
}

impl WorkerFrameStats {
    /// One report per worker: a progressive frame's workers report once per subframe, and
    /// a worker's reports are summed into one (its peak memory and cache peak are the
    /// largest, its idle fraction recomputed over the summed times). Workers keep the order
    /// of their first report.
    pub fn merge_by_worker(reports: Vec<WorkerFrameStats>) -> Vec<WorkerFrameStats> {
        let mut merged: Vec<WorkerFrameStats> = Vec::new();
        for r in reports {
            match merged.iter_mut().find(|m| m.worker_id == r.worker_id) {
                Some(m) => m.add(&r),
                None => merged.push(r),
            }
        }
        merged
    }

    fn add(&mut self, o: &WorkerFrameStats) {
        self.threads = self.threads.max(o.threads);
        self.rays.add(&o.rays);
        self.cache.add(&o.cache);
        self.rays_sent += o.rays_sent;
        self.bytes_sent += o.bytes_sent;
        self.rays_received += o.rays_received;
        self.rays_spilled += o.rays_spilled;
        self.verdicts_refused += o.verdicts_refused;
        self.rays_shared += o.rays_shared;
        for t in &o.tiers {
            match self.tiers.iter_mut().find(|x| x.tier == t.tier) {
                Some(x) => x.sent.add(&t.sent),
                None => self.tiers.push(t.clone()),
            }
        }
        self.busy_seconds += o.busy_seconds;
        self.load_seconds += o.load_seconds;
        self.trace_cpu_seconds += o.trace_cpu_seconds;
        self.cpu_seconds += o.cpu_seconds;
        self.idle_queued_seconds += o.idle_queued_seconds;
        self.idle_verdicts_seconds += o.idle_verdicts_seconds;
        self.idle_empty_seconds += o.idle_empty_seconds;
        self.pass_wait_seconds += o.pass_wait_seconds;
        self.pass_start_wait_seconds += o.pass_start_wait_seconds;
        self.passes += o.passes;
        self.frame_seconds += o.frame_seconds;
        self.idle_fraction =
            (1.0 - self.busy_seconds / self.frame_seconds.max(1e-9)).clamp(0.0, 1.0);
        self.peak_rss_bytes = self.peak_rss_bytes.max(o.peak_rss_bytes);
    }
}

/// One subframe's share of a frame's cost (a one-pass frame is one subframe).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SubframeCost {
    /// Its first sample of every pixel.
    pub first_sample: u32,
    /// Its samples per pixel.
    pub samples: u32,
    /// When its last tile came back, seconds from the frame's start (so the time to the first
    /// preview is the first subframe's).
    pub done_seconds: f64,
    /// Domain loads, summed over the workers that reported it.
    pub loads: u64,
}

/// What a frame cost and produced across the cluster.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ClusterStats {
    /// The job.
    pub job_id: String,
    /// Scene name as submitted.
    pub scene: String,
    /// Schedule name.
    pub schedule: String,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Samples per pixel.
    pub spp: u32,
    /// Maximum bounces.
    pub max_depth: u32,
    /// Workers that took part.
    pub workers: usize,
    /// Workers left out of the frame, each with its reason ("worker W: why").
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub left_out: Vec<String>,
    /// Messages of tile results refused as impossible (forged credit, or tiles the sender
    /// was given no ray of); each dropped its sender.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub refused_results: u64,
    /// Tracing threads over all workers.
    pub threads: usize,
    /// Domains in the scene.
    pub domains: usize,
    /// Wall time from the frame's start to its last tile, seconds.
    pub wall_seconds: f64,
    /// Ray counts, summed over workers.
    pub rays: KernelCounters,
    /// Domain cache counters, summed over workers (peak resident: the largest).
    pub cache: CacheCounters,
    /// Ray segments traced per second of wall time.
    pub rays_per_s: f64,
    /// `rays_per_s` divided by the threads.
    pub rays_per_s_per_core: f64,
    /// Scheduling rounds.
    pub rounds: u64,
    /// Subframes the samples were rendered in (1: one pass).
    #[serde(default = "one")]
    pub subframes: u32,
    /// What each subframe cost, in sample order (one entry for a one-pass frame): what a
    /// progressive frame pays per subframe, and which subframes found their domains loaded.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub subframe_costs: Vec<SubframeCost>,
    /// Rays sent between workers.
    pub rays_migrated: u64,
    /// Of them, rays handed from busy workers to idle ones as demand-driven tasks (hybrid).
    #[serde(default)]
    pub rays_shared: u64,
    /// Ray bytes sent between workers.
    pub bytes_migrated: u64,
    /// Bundles per tier, summed over workers.
    pub tiers: Vec<TierTraffic>,
    /// Per worker.
    pub per_worker: Vec<WorkerFrameStats>,
    /// Largest peak RSS of a worker, bytes.
    pub peak_rss_bytes: u64,
    /// xxh3-64 of the fixed-point pixel sums, 16 hex digits.
    pub image_hash: String,
}

impl ClusterStats {
    /// Adds the workers' reports into the cluster totals.
    pub fn absorb(&mut self, workers: Vec<WorkerFrameStats>) {
        for w in &workers {
            self.threads += w.threads;
            self.rays.add(&w.rays);
            self.cache.add(&w.cache);
            self.rays_migrated += w.rays_sent;
            self.rays_shared += w.rays_shared;
            self.bytes_migrated += w.bytes_sent;
            self.peak_rss_bytes = self.peak_rss_bytes.max(w.peak_rss_bytes);
            for t in &w.tiers {
                match self.tiers.iter_mut().find(|x| x.tier == t.tier) {
                    Some(x) => x.sent.add(&t.sent),
                    None => self.tiers.push(t.clone()),
                }
            }
        }
        self.workers = workers.len();
        self.rays_per_s = self.rays.segments() as f64 / self.wall_seconds.max(1e-9);
        self.rays_per_s_per_core = self.rays_per_s / self.threads.max(1) as f64;
        self.per_worker = workers;
    }
}
