//! What goes into the worker machine and what comes out: [`Event`]s, each with the time it
//! happened, and [`Action`]s for the shell to carry out. Everything here is plain data.

use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use rayfarm_core::bundler::Tier;
use rayfarm_core::cluster::stats::WorkerFrameStats;
use rayfarm_core::ray::RayRecord;
use rayfarm_core::render::KernelCounters;
use rayfarm_core::render::speculation::Outcome;
use rayfarm_core::tile::TileGrid;
use rayfarm_core::wire::{BatchLimits, VerdictRecord};
use rayfarm_proto as proto;

use super::queues::DomainQueues;

/// Something the worker reacts to.
// `FrameOpened` (its queues included) is the large variant and comes once a frame; events
// are handled one at a time and never stored in bulk, so boxing it would save nothing.
#[allow(clippy::large_enum_variant)]
pub enum Event<S> {
    /// A message from the coordinator other than StartFrame (see [`Event::FrameOpened`]).
    Control(proto::CoordinatorMessage),
    /// The same, shared with other workers (the simulator sends one holders message to a
    /// whole view class): the machine reads it in place instead of taking a copy.
    SharedControl(Arc<proto::CoordinatorMessage>),
    /// The coordinator's StartFrame, with what the shell read from the scene for it (or why
    /// it could not: the frame is declined).
    FrameOpened {
        start: proto::StartFrame,
        opened: Result<OpenedScene<S>, String>,
    },
    /// The control stream ended; frame state is dropped (the coordinator forgets this worker).
    Disconnected,
    /// A bundle from a peer.
    PeerBundle {
        sender: String,
        job_id: String,
        payload: Payload,
    },
    /// A peer stopped acknowledging bundles.
    PeerUnresponsive { peer: String, reason: String },
    /// A pass of the frame of `job_id` finished; `resident` are the domains mapped now, least
    /// recently used first.
    PassFinished {
        job_id: String,
        result: Result<PassOutput, PassFailed>,
        resident: Vec<u32>,
    },
    /// A prefetch of `domain` for the frame of `job_id` ended: `Ok(true)` it is mapped now,
    /// `Ok(false)` it was loaded but found no room (or was mapped already), `Err` it could
    /// not be loaded (a pass loading it will say so); `resident` are the domains mapped now,
    /// least recently used first.
    PrefetchDone {
        job_id: String,
        domain: u32,
        result: Result<bool, String>,
        resident: Vec<u32>,
    },
    /// Nothing happened but time passed (the deadline of [`super::Worker::next_timeout`]).
    Tick,
}

/// Why a pass produced nothing.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PassFailed {
    /// This worker could not load a domain (missing, damaged): it leaves the frame (declines);
    /// if it is the same for every worker, the job fails with all their reasons.
    Load(String),
    /// The scene's manifest changed on disk since the frame opened it (re-prepared in place):
    /// its new domain files do not match the frame's manifest and tracing on would mix the
    /// two versions, so the frame fails for everyone.
    SceneReplaced(String),
}

/// A peer bundle's batches, decoded once by the shell for any frame
/// (`wire::BatchLimits::any_frame`); the machine checks them against its frame's ranges only.
#[derive(Clone, Debug, PartialEq)]
pub enum Payload {
    /// Ray batches (every tier but results).
    Rays(Vec<Vec<RayRecord>>),
    /// Verdict batches (the results tier, predictive schedule).
    Verdicts(Vec<Vec<VerdictRecord>>),
}

impl Payload {
    /// Bytes held: the records and each batch's bookkeeping.
    pub fn bytes(&self) -> usize {
        fn held<T>(batches: &[Vec<T>]) -> usize {
            batches
                .iter()
                .map(|b| std::mem::size_of_val(b.as_slice()) + std::mem::size_of::<Vec<T>>())
                .sum()
        }
        match self {
            Payload::Rays(b) => held(b),
            Payload::Verdicts(b) => held(b),
        }
    }
}

/// What the shell read from the scene for a StartFrame.
pub struct OpenedScene<S> {
    pub grid: TileGrid,
    /// Samples of each pixel the frame issues (a progressive subframe's count, or the spp).
    pub spp: u32,
    pub limits: BatchLimits,
    /// Bytes of every domain file, by domain id.
    pub domain_bytes: std::sync::Arc<[u64]>,
    /// Domains mapped in the cache now, least recently used first.
    pub resident: Vec<u32>,
    /// The frame's (empty) ray queues, over the shell's spill store.
    pub queues: DomainQueues<S>,
}

/// Work for one pass.
#[derive(Debug, Default, PartialEq)]
pub struct PassWork {
    /// Tiles whose camera rays to issue, with the epoch they are issued in.
    pub primaries: Vec<(u32, u32)>,
    /// A domain and the rays queued for it.
    pub trace: Option<(u32, Vec<RayRecord>)>,
    /// Predictive schedule: the queued rays are speculative copies, and these rays, whose
    /// verdicts are all in, are concluded.
    pub speculative: Option<Vec<(RayRecord, Outcome)>>,
}

/// What a pass produced.
#[derive(Debug, Default)]
pub struct PassOutput {
    /// Rays that continue, each with the domain it continues in; speculative, the rays born
    /// (camera rays and the children of concluded rays), each with its first domain.
    pub rays: Vec<RayRecord>,
    /// Speculative: the domains along each born ray, in the order of `rays`.
    pub paths: Vec<Vec<u32>>,
    /// Speculative: each traced copy's verdict, with the worker it goes to.
    pub verdicts: Vec<(u32, VerdictRecord)>,
    /// Credit and pixel sums of the rays that retired, one entry per (tile, epoch).
    pub results: Vec<proto::TileResult>,
    pub counters: KernelCounters,
    /// Time the pass took, including a domain load.
    pub busy: Duration,
}

/// Something for the shell to do.
#[derive(Debug)]
pub enum Action {
    /// Send this message to the coordinator.
    ToCoordinator(proto::worker_message::Body),
    /// Send this bundle to the worker at `peer`.
    ToPeer {
        peer: String,
        job_id: String,
        tier: Tier,
        batches: Vec<Bytes>,
    },
    /// Close the links to these peers (they are gone).
    DropPeers(Vec<String>),
    /// Run a pass of the frame of `job_id`; answer with [`Event::PassFinished`]. The machine
    /// asks for one pass at a time.
    StartPass { job_id: String, work: PassWork },
    /// Load `domain` into the cache ahead of need, beside any pass, unless it is mapped or
    /// does not fit without evicting a domain of `keep` (the plan's and the one being
    /// traced); answer with [`Event::PrefetchDone`]. The machine asks for one at a time.
    Prefetch {
        job_id: String,
        domain: u32,
        keep: Vec<u32>,
    },
    /// Unmap these domains from the cache.
    Evict(Vec<u32>),
    /// Keep these domains mapped (none: pin nothing).
    Pin(Vec<u32>),
    /// The frame ended here: fill in what the shell knows (the cache's counters, load time,
    /// threads, memory), then send the coordinator its FrameReport.
    FrameEnded {
        job_id: String,
        stats: Box<WorkerFrameStats>,
    },
}
