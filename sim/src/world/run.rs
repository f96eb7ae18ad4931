//! What one simulated run is given (the cluster, the frame and the model) and what it
//! produced (figures, the image, the invariants broken).

use std::path::PathBuf;
use std::time::Duration;

use rayfarm_proto::Schedule;

use crate::check::Violation;
use crate::cost::CostModel;
use crate::net::LinkModel;
use crate::node::QueueCaps;
use crate::storage::StorageModel;

/// What to simulate.
#[derive(Clone, Debug)]
pub struct SimConfig {
    pub scene: PathBuf,
    pub workers: usize,
    pub schedule: Schedule,
    /// Jobs of the same frame the same workers render first, in order, each with its
    /// schedule: the measured job starts with the caches (domains mapped) and the machines
    /// they left, as on a farm that has rendered before.
    pub warm_up: Vec<Schedule>,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub depth: u32,
    pub cache_bytes: u64,
    /// Camera rays are issued while fewer than this many rays are queued on a worker.
    pub wave_rays: usize,
    /// Most rays a worker traces in one pass.
    pub pass_rays: usize,
    pub links: LinkModel,
    pub cost: CostModel,
    pub storage: StorageModel,
    /// Measure each pass's CPU time on this machine (`calibrate`; the virtual times do not
    /// depend on it).
    pub measure: bool,
    pub caps: QueueCaps,
    /// A peer that acknowledges nothing for this long is reported unresponsive.
    pub ack_deadline: Duration,
    /// How long one job record takes to reach the coordinator's disk.
    pub disk_latency: Duration,
    pub heartbeat: Duration,
    pub worker_timeout: Duration,
    /// Busy workers are told new holders at most once per this interval (the coordinator's
    /// `--holders-interval-ms`).
    pub holders_interval: Duration,
    /// How long a planned worker with nothing to trace waits for its plan's rays before it
    /// reports again (the coordinator's `--report-hold-ms` and `--report-hold-per-worker-us`).
    pub report_hold: crate::ReportHold,
    /// The dynamic schedule copies a domain only if every holder keeps at least this many of
    /// its rays (the coordinator's `--copy-rays`, `Options::copy_rays`).
    pub copy_rays: u64,
    /// The predictive schedule's speculation setting (`JobSpec.speculation`; empty: full).
    pub speculation: String,
    /// Workers load their next domains while they trace (`JobSpec.prefetch`).
    pub prefetch: bool,
    /// Most events the run may take before it stops unfinished (`default_max_events`).
    pub max_events: u64,
    /// After the run, hand the coordinator machine's calls to a new machine alone and measure
    /// its CPU (`Outcome::coordinator_replayed`); the calls are kept in memory meanwhile.
    pub replay_coordinator: bool,
    /// Draw each pass's wait for its tracing thread (`CostModel::pass_start`) and each peer
    /// bundle's wait for the engine (`CostModel::bundle_take`) at random around their means
    /// from this seed, rather than waiting the mean every time:
    /// one of the timings a real cluster's shared cores give, so several seeds show how far
    /// a frame moves with timing alone. `None`: every wait is the mean.
    pub timing_seed: Option<u64>,
}

/// Kills by what the killed worker was doing.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Kills {
    pub total: u64,
    pub mid_pass: u64,
    pub mid_load: u64,
    /// With bundles it sent still unacknowledged.
    pub bundles_in_flight: u64,
}

/// What a run produced.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Outcome {
    /// Virtual time from the start to the last tile committed (of the last job).
    pub frame_time: Option<Duration>,
    pub image_hash: Option<String>,
    /// Domain loads of every worker (prefetches included).
    pub loads: u64,
    /// Of the loads, prefetches; of those, used by a pass and wasted (left unused).
    pub prefetches: u64,
    pub prefetches_used: u64,
    pub prefetches_wasted: u64,
    /// Ray segments traced, in every pass that finished.
    pub segments: u64,
    /// Passes the workers finished in their frames, as their frame statistics count them.
    pub passes: u64,
    /// Where the workers' frames went.
    pub time: FrameTime,
    /// Bytes of peer bundles sent.
    pub peer_bytes: u64,
    /// Rays sent to another worker, as the workers' frame reports count them.
    pub rays_migrated: u64,
    /// Times a worker reported a peer unresponsive (a bundle unacknowledged past the
    /// deadline): in a run without faults every one is a false alarm, and the coordinator
    /// drops the peer it accuses.
    pub peers_reported: u64,
    /// Messages of every kind.
    pub messages: u64,
    pub rounds: u64,
    pub events: u64,
    pub kills: Kills,
    pub coordinator_crashes: u64,
    /// Frames started (more than one a job after a coordinator crash or a loss of every
    /// worker).
    pub frames: u64,
    /// Jobs submitted (the warm-up ones and the measured one).
    pub jobs: u64,
    pub violations: Vec<Violation>,
    /// Virtual time the coordinator spent planning rounds and flushing holders (its busy time).
    pub coordinator_busy: Duration,
    /// The coordinator machine's calls replayed alone, when asked (`replay_coordinator`) and
    /// the coordinator never crashed.
    pub coordinator_replayed: Option<crate::coord::Replayed>,
    /// Bytes the storage was charged for.
    pub storage_bytes: u64,
    /// Every pass that loaded nothing, with the CPU time it took here, when measured.
    pub measured: Vec<MeasuredPass>,
    /// Every peer bundle received, with the CPU time its decoding and the machine's handling
    /// took here, when measured.
    pub measured_bundles: Vec<MeasuredBundle>,
    /// Every finished pass whose output the machine took, with what it held and the CPU time
    /// the machine's handling took here, when measured.
    pub measured_finished: Vec<MeasuredFinished>,
}

/// Where the simulated workers' frames went, summed over every worker's frame, in the parts
/// of `rayfarm bench`'s table of a worker's frame (so the two can be set side by side). The
/// idle parts are the worker machine's own counters; the rest is what the simulator charged.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FrameTime {
    /// Workers' frames ended (each worker's frame of each job).
    pub frames: u64,
    /// From each frame's start to its end on the worker.
    pub frame: Duration,
    /// Passes loading their domains (prefetches, which load beside the passes, aside).
    pub loading: Duration,
    /// Passes computing, each at a whole core.
    pub computing: Duration,
    /// What sharing the cores with other workers (`--cores`) stretched the computing by.
    pub core_wait: Duration,
    /// Passes handed over waiting for their tracing thread (`--pass-start-us`).
    pub thread_wait: Duration,
    /// Finished passes waiting for the worker's shell to take them in (it was handling
    /// bundles or an earlier pass), and its handling of them.
    pub shell_wait: Duration,
    /// No pass to run while rays were queued for domains the plan did not give this worker.
    pub idle_queued: Duration,
    /// No pass to run, nothing queued, rays of its own waiting for their copies' verdicts.
    pub idle_verdicts: Duration,
    /// No pass to run and nothing queued or waiting.
    pub idle_empty: Duration,
    /// The workers' shells' computing, as priced: bundles sent and received, finished passes
    /// taken in (it overlaps the parts above; `rayfarm bench`'s "worker CPU outside
    /// tracing").
    pub handling: Duration,
}

impl FrameTime {
    /// The parts a worker's frame is told in, named and ordered as `rayfarm bench` tells
    /// them; apart from overlaps none of them has, they add up to the frame.
    pub fn parts(&self) -> [(&'static str, Duration); 8] {
        [
            ("loading", self.loading),
            ("computing", self.computing),
            ("waiting for a core", self.core_wait),
            ("pass waiting for a tracing thread", self.thread_wait),
            ("finished pass waiting for the shell", self.shell_wait),
            ("idle: rays queued, not planned", self.idle_queued),
            ("idle: waiting for verdicts", self.idle_verdicts),
            ("idle: nothing queued", self.idle_empty),
        ]
    }

    /// Adds the machine's account of one worker's frame.
    pub fn add_frame(&mut self, stats: &rayfarm_core::cluster::stats::WorkerFrameStats) {
        let secs = |s: f64| Duration::from_secs_f64(s.max(0.0));
        self.frames += 1;
        self.frame += secs(stats.frame_seconds);
        self.idle_queued += secs(stats.idle_queued_seconds);
        self.idle_verdicts += secs(stats.idle_verdicts_seconds);
        self.idle_empty += secs(stats.idle_empty_seconds);
    }
}

/// A finished pass's output as a worker's shell hands it to the machine, and what the
/// machine's handling of it cost on this machine (`calibrate` fits the `finished_*` prices).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeasuredFinished {
    pub work: crate::cost::FinishedWork,
    pub cpu_ns: u64,
}

/// A peer bundle received and what decoding it and handing it to the worker machine cost on
/// this machine (`calibrate` fits the receiving prices to these); the first
/// [`KEPT_BUNDLES`] keep their batches, which `calibrate` times encoding and sending with.
#[derive(Clone, Debug, PartialEq)]
pub struct MeasuredBundle {
    pub tier: rayfarm_core::bundler::Tier,
    /// Bytes of its batches.
    pub bytes: usize,
    pub cpu_ns: u64,
    pub batches: Option<Vec<bytes::Bytes>>,
}

/// Measured bundles that keep their batches.
pub const KEPT_BUNDLES: usize = 2000;

/// A pass's work and what it cost on this machine (`calibrate` fits the prices to these).
#[derive(Clone, Debug, PartialEq)]
pub struct MeasuredPass {
    pub counters: rayfarm_core::render::KernelCounters,
    pub cpu_ns: u64,
}
