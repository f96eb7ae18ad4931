//! The yardstick of `rayfarm bench`: the least time a frame can take, the larger of its ray
//! work spread over the cores there are and the domain bytes no schedule can avoid loading
//! read at the workers' storage bandwidth, and each run's efficiency against it.

use rayfarm_core::cluster::stats::ClusterStats;

use super::{RunOutcome, ratio};

/// Ray work of one frame in seconds per thread: the time its workers spent in passes, less
/// the time spent loading domains, summed over workers and divided by the threads that traced
/// (the frame's time if that work were spread perfectly over the threads, nothing else to do).
/// Wall time: on a machine with fewer cores than threads it includes waiting for a core.
pub fn ray_work_seconds(stats: &ClusterStats) -> f64 {
    let work: f64 = stats
        .per_worker
        .iter()
        .map(|w| (w.busy_seconds - w.load_seconds).max(0.0))
        .sum();
    work / total_threads(stats).max(1) as f64
}

/// The threads that traced the frame, all workers together.
fn total_threads(stats: &ClusterStats) -> usize {
    if stats.threads > 0 {
        stats.threads
    } else {
        stats.per_worker.iter().map(|w| w.threads).sum()
    }
}

/// CPU seconds the frame's tracing threads used, summed over workers: the ray work without
/// the waiting for a core. `None` unless every worker measured it (older workers report 0).
pub fn ray_work_cpu_seconds(stats: &ClusterStats) -> Option<f64> {
    (!stats.per_worker.is_empty() && stats.per_worker.iter().all(|w| w.trace_cpu_seconds > 0.0))
        .then(|| stats.per_worker.iter().map(|w| w.trace_cpu_seconds).sum())
}

/// The least time the frame's ray work can take: its CPU seconds spread over the cores that
/// can run them, `min(threads, cores)` (`cores`: `None` when not known, e.g. a cluster on
/// other machines; then the threads). Without CPU figures, the wall-time ray work per thread
/// ([`ray_work_seconds`]).
pub fn compute_seconds(stats: &ClusterStats, cores: Option<usize>) -> f64 {
    let threads = total_threads(stats).max(1);
    match ray_work_cpu_seconds(stats) {
        Some(cpu) => cpu / cores.map_or(threads, |c| threads.min(c.max(1))) as f64,
        None => ray_work_seconds(stats),
    }
}

/// Domain bytes no schedule can avoid loading in a frame of `generations` ray generations on
/// `workers` workers with `cache_bytes` each (`None`: unbounded caches), every generation
/// needing every domain: each domain once, and for each later generation again whatever the
/// cluster's caches could not keep across the step (a generation's rays exist only once the
/// one before it has been traced, so a domain evicted meanwhile is read again). The caches
/// keep at most `workers * cache_bytes`, and only of domains that fit one cache. A model: a
/// schedule that works on several generations at once could keep fewer domains apart, which
/// is why [`bound`] never takes more than the fewest bytes a run really loaded.
pub fn unavoidable_load_bytes(
    domain_bytes: &[u64],
    workers: usize,
    cache_bytes: Option<u64>,
    generations: u32,
) -> u64 {
    let scene: u64 = domain_bytes.iter().sum();
    let Some(cache) = cache_bytes else {
        return scene;
    };
    let fitting: u64 = domain_bytes.iter().filter(|&&b| b <= cache).sum();
    let kept = fitting.min(cache.saturating_mul(workers as u64));
    let again = scene - kept;
    scene.saturating_add(again.saturating_mul(u64::from(generations.saturating_sub(1))))
}

/// Ray generations of a frame of bounce depth `max_depth`: radiance rays of depth 0 to
/// `max_depth` and the shadow rays of the last hits (`RayRecord::generation`).
pub fn generations(max_depth: u32) -> u32 {
    max_depth.saturating_add(2)
}

/// What the bound knows of the scene, the cluster and the frame.
#[derive(Clone, Debug, PartialEq)]
pub struct BoundInputs {
    /// Bytes of each domain file of the scene.
    pub domain_bytes: Vec<u64>,
    /// Workers loading domains; 0: as many as the runs report.
    pub workers: usize,
    /// Cache of each worker, bytes; `None`: not known (a cluster the bench did not start).
    pub cache_bytes: Option<u64>,
    /// Storage bandwidth of each worker, bytes per second (each reads at this rate beside
    /// the others, as `--storage-bandwidth` emulates); `None`: loads cost nothing.
    pub bandwidth: Option<f64>,
    /// Bounce depth of the frame.
    pub max_depth: u32,
    /// Cores the workers share; `None`: not known (then every thread counts as a core).
    pub cores: Option<usize>,
}

/// The yardstick of the bench: no frame can take less than the larger of its two terms.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bound {
    /// The least ray work over all successful runs of the bench, spread over the cores that
    /// can trace it ([`compute_seconds`]; one bound for every schedule, so a schedule is not
    /// rewarded for wasting less of its own time).
    pub compute_seconds: f64,
    /// Whether `compute_seconds` is CPU time (every worker measured it) or wall time.
    pub compute_is_cpu: bool,
    /// Reading `load_bytes` at all workers' storage bandwidth together (0 when no bandwidth
    /// was given).
    pub load_seconds: f64,
    /// The unavoidable bytes ([`unavoidable_load_bytes`]), at most the fewest any run loaded.
    pub load_bytes: u64,
    /// [`unavoidable_load_bytes`] before that cap.
    pub model_bytes: u64,
    /// The workers reading them.
    pub workers: usize,
}

impl Bound {
    /// The bound itself: the larger term.
    pub fn seconds(&self) -> f64 {
        self.compute_seconds.max(self.load_seconds)
    }
}

/// The bound of a bench: `None` when no run succeeded.
pub fn bound(runs: &[RunOutcome], inputs: &BoundInputs) -> Option<Bound> {
    let ok: Vec<&ClusterStats> = runs.iter().filter_map(RunOutcome::stats).collect();
    let least = ok
        .iter()
        .map(|s| {
            (
                compute_seconds(s, inputs.cores),
                ray_work_cpu_seconds(s).is_some(),
            )
        })
        .min_by(|a, b| a.0.total_cmp(&b.0))?;
    let workers = match inputs.workers {
        0 => ok.iter().map(|s| s.workers).max().unwrap_or(0),
        w => w,
    }
    .max(1);
    let model_bytes = unavoidable_load_bytes(
        &inputs.domain_bytes,
        workers,
        inputs.cache_bytes,
        generations(inputs.max_depth),
    );
    let load_bytes = ok
        .iter()
        .map(|s| s.cache.bytes_loaded)
        .chain([model_bytes])
        .min()
        .unwrap_or(model_bytes);
    let load_seconds = match inputs.bandwidth {
        Some(b) if b > 0.0 => load_bytes as f64 / (b * workers as f64),
        _ => 0.0,
    };
    Some(Bound {
        compute_seconds: least.0,
        compute_is_cpu: least.1,
        load_seconds,
        load_bytes,
        model_bytes,
        workers,
    })
}

/// How close a frame came to the bound: bound / wall time (1 is perfect).
pub fn efficiency(bound_seconds: f64, wall_seconds: f64) -> Option<f64> {
    ratio(bound_seconds, wall_seconds)
}
