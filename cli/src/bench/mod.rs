//! The arithmetic of `rayfarm bench`, kept pure so it can be tested without a cluster: the
//! order of the runs, medians and ratios per schedule, the lower bound on a frame's time and
//! each schedule's efficiency against it, and the check that every image is the same.
//!
//! `cmd::bench` runs the frames and feeds the results here; [`report`] turns the summaries
//! into the table, [`csv_out`] into one CSV row per run and [`chart`] into a PNG.

pub mod chart;
pub mod csv_out;
pub mod progressive;
pub mod report;

use rayfarm_core::bundler::Tier;
use rayfarm_core::cluster::stats::{ClusterStats, tier_name};

/// The schedule the domain-load ratios are measured against (the paper's algorithm).
pub const REFERENCE_SCHEDULE: &str = "dynamic";

/// One frame of the bench: which schedule in which repeat, and what came of it.
#[derive(Clone, Debug)]
pub struct RunOutcome {
    /// 1-based position in the whole bench.
    pub run: usize,
    /// 1-based repeat.
    pub repeat: usize,
    /// Schedule name.
    pub schedule: String,
    /// The job, once submitted.
    pub job_id: Option<String>,
    /// Seconds from submission to the job's last event, as this client saw it.
    pub client_seconds: f64,
    /// The frame's statistics, or why the run failed.
    pub result: Result<ClusterStats, String>,
}

impl RunOutcome {
    /// The statistics of a successful run.
    pub fn stats(&self) -> Option<&ClusterStats> {
        self.result.as_ref().ok()
    }
}

/// The runs of a bench as (repeat, schedule index), 1-based repeats: every schedule once per
/// repeat, the order rotated by one each repeat (a,b,c; b,c,a; c,a,b; ...), so that slow drift
/// of the machine (heat, other load) falls on every schedule alike.
pub fn run_order(schedules: usize, repeats: usize) -> Vec<(usize, usize)> {
    (0..repeats)
        .flat_map(|r| (0..schedules).map(move |i| (r + 1, (i + r) % schedules)))
        .collect()
}

/// The median of `values` (the mean of the middle two for an even count); `None` when empty.
pub fn median(values: &[f64]) -> Option<f64> {
    let mut v: Vec<f64> = values.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    match n {
        0 => None,
        _ if n % 2 == 1 => Some(v[n / 2]),
        _ => Some((v[n / 2 - 1] + v[n / 2]) / 2.0),
    }
}

/// Median, least and largest of some measurements.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Spread {
    pub median: f64,
    pub min: f64,
    pub max: f64,
}

/// The spread of `values`; `None` when empty.
pub fn spread(values: &[f64]) -> Option<Spread> {
    Some(Spread {
        median: median(values)?,
        min: values.iter().copied().fold(f64::INFINITY, f64::min),
        max: values.iter().copied().fold(f64::NEG_INFINITY, f64::max),
    })
}

/// `value / reference`, or `None` when the reference is zero, negative or not finite (no
/// meaningful ratio).
pub fn ratio(value: f64, reference: f64) -> Option<f64> {
    (reference.is_finite() && reference > 0.0 && value.is_finite()).then(|| value / reference)
}

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

/// What one schedule's successful runs measured (medians unless said otherwise).
#[derive(Clone, Debug, PartialEq)]
pub struct Measured {
    /// Wall time of the frame (the coordinator's: frame start to last tile), seconds.
    pub wall: Spread,
    pub domain_loads: f64,
    pub bytes_loaded: f64,
    /// Of the loads, those whose bytes came from peers, and those bytes.
    pub peer_loads: f64,
    pub bytes_from_peers: f64,
    /// Of the loads, prefetches; of those, used by a pass and wasted (left unused).
    pub prefetches: f64,
    pub prefetches_used: f64,
    pub prefetches_wasted: f64,
    /// Ray segments traced.
    pub segments: f64,
    pub rays_migrated: f64,
    pub bytes_migrated: f64,
    /// Bundles sent per tier, most urgent first ([`Tier::MOST_URGENT_FIRST`]).
    pub bundles: [f64; Tier::COUNT],
    pub rounds: f64,
    /// Mean over all workers of all runs.
    pub idle_fraction: f64,
    /// Largest over all workers of all runs, bytes.
    pub peak_rss_bytes: u64,
    /// Where a worker's frame went, the mean over all workers of all runs.
    pub split: TimeSplit,
}

/// Where a worker's frame time went, seconds: the parts add up to `frame`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TimeSplit {
    /// From the frame's start to its end on the worker.
    pub frame: f64,
    /// In passes, tracing on a core (the tracing threads' CPU time; 0 when not measured,
    /// then all of the passes' ray work is in `trace_wait`).
    pub trace_cpu: f64,
    /// In passes, ray work waiting for a core (wall less CPU time).
    pub trace_wait: f64,
    /// In passes, loading domains (mapping, checking, the emulated storage).
    pub load: f64,
    /// No pass to run: rays queued for domains the plan did not give it.
    pub idle_queued: f64,
    /// No pass to run: nothing queued, own rays waiting for verdicts.
    pub idle_verdicts: f64,
    /// No pass to run: nothing queued or waiting.
    pub idle_empty: f64,
    /// A finished pass waiting for the worker's event loop to take it up.
    pub pass_wait: f64,
    /// A pass handed to the tracing pool waiting for a tracing thread to start it.
    pub start_wait: f64,
    /// The rest: before the first pass, and from taking up a finished pass to handing the
    /// next to the tracing pool (the event loop handling it, a core not had meanwhile).
    pub other: f64,
    /// Not a part: CPU seconds the worker process used outside its tracing threads (event
    /// loop, network, bundling, prefetches), overlapping the parts above.
    pub other_cpu: f64,
    /// Not a part: the passes the worker ran.
    pub passes: f64,
}

impl TimeSplit {
    /// One worker's frame.
    pub fn of(w: &rayfarm_core::cluster::stats::WorkerFrameStats) -> Self {
        let work = (w.busy_seconds - w.load_seconds).max(0.0);
        let trace_cpu = w.trace_cpu_seconds.min(work);
        let idle = w.idle_queued_seconds
            + w.idle_verdicts_seconds
            + w.idle_empty_seconds
            + w.pass_wait_seconds
            + w.pass_start_wait_seconds;
        TimeSplit {
            frame: w.frame_seconds,
            trace_cpu,
            trace_wait: work - trace_cpu,
            load: w.load_seconds,
            idle_queued: w.idle_queued_seconds,
            idle_verdicts: w.idle_verdicts_seconds,
            idle_empty: w.idle_empty_seconds,
            pass_wait: w.pass_wait_seconds,
            start_wait: w.pass_start_wait_seconds,
            other: (w.frame_seconds - w.busy_seconds - idle).max(0.0),
            other_cpu: (w.cpu_seconds - w.trace_cpu_seconds).max(0.0),
            passes: w.passes as f64,
        }
    }

    /// The mean of some splits; the default when there are none.
    pub fn mean(splits: &[TimeSplit]) -> Self {
        let n = splits.len().max(1) as f64;
        let sum = |f: fn(&TimeSplit) -> f64| splits.iter().map(f).sum::<f64>() / n;
        TimeSplit {
            frame: sum(|s| s.frame),
            trace_cpu: sum(|s| s.trace_cpu),
            trace_wait: sum(|s| s.trace_wait),
            load: sum(|s| s.load),
            idle_queued: sum(|s| s.idle_queued),
            idle_verdicts: sum(|s| s.idle_verdicts),
            idle_empty: sum(|s| s.idle_empty),
            pass_wait: sum(|s| s.pass_wait),
            start_wait: sum(|s| s.start_wait),
            other: sum(|s| s.other),
            other_cpu: sum(|s| s.other_cpu),
            passes: sum(|s| s.passes),
        }
    }
}

/// One schedule's row: how many runs succeeded, the errors of the others, and the measures.
#[derive(Clone, Debug, PartialEq)]
pub struct ScheduleSummary {
    pub schedule: String,
    pub runs: usize,
    pub ok: usize,
    /// Distinct errors of the failed runs, in order of first appearance.
    pub errors: Vec<String>,
    /// `None` when every run failed.
    pub measured: Option<Measured>,
}

/// Bundles sent on `tier`, summed over workers (the statistics already sum them).
pub fn tier_bundles(stats: &ClusterStats, tier: Tier) -> u64 {
    stats
        .tiers
        .iter()
        .filter(|t| t.tier == tier_name(tier))
        .map(|t| t.sent.bundles)
        .sum()
}

/// One summary per schedule, in the order given.
pub fn summarize(schedules: &[String], runs: &[RunOutcome]) -> Vec<ScheduleSummary> {
    schedules
        .iter()
        .map(|name| {
            let mine: Vec<&RunOutcome> = runs.iter().filter(|r| &r.schedule == name).collect();
            let mut errors: Vec<String> = Vec::new();
            for e in mine.iter().filter_map(|r| r.result.as_ref().err()) {
                if !errors.contains(e) {
                    errors.push(e.clone());
                }
            }
            let ok: Vec<&ClusterStats> = mine.iter().filter_map(|r| r.stats()).collect();
            ScheduleSummary {
                schedule: name.clone(),
                runs: mine.len(),
                ok: ok.len(),
                errors,
                measured: measure(&ok),
            }
        })
        .collect()
}

/// The measures of some successful runs of one schedule; `None` when there are none.
fn measure(ok: &[&ClusterStats]) -> Option<Measured> {
    let med =
        |f: &dyn Fn(&ClusterStats) -> f64| median(&ok.iter().map(|s| f(s)).collect::<Vec<_>>());
    let wall = spread(&ok.iter().map(|s| s.wall_seconds).collect::<Vec<_>>())?;
    let idle: Vec<f64> = ok
        .iter()
        .flat_map(|s| s.per_worker.iter().map(|w| w.idle_fraction))
        .collect();
    let mut bundles = [0.0; Tier::COUNT];
    for (b, tier) in bundles.iter_mut().zip(Tier::MOST_URGENT_FIRST) {
        *b = med(&|s| tier_bundles(s, tier) as f64)?;
    }
    Some(Measured {
        wall,
        domain_loads: med(&|s| s.cache.loads as f64)?,
        bytes_loaded: med(&|s| s.cache.bytes_loaded as f64)?,
        peer_loads: med(&|s| s.cache.peer_loads as f64)?,
        bytes_from_peers: med(&|s| s.cache.bytes_from_peers as f64)?,
        prefetches: med(&|s| s.cache.prefetches as f64)?,
        prefetches_used: med(&|s| s.cache.prefetches_used as f64)?,
        prefetches_wasted: med(&|s| s.cache.prefetches_wasted as f64)?,
        segments: med(&|s| s.rays.segments() as f64)?,
        rays_migrated: med(&|s| s.rays_migrated as f64)?,
        bytes_migrated: med(&|s| s.bytes_migrated as f64)?,
        bundles,
        rounds: med(&|s| s.rounds as f64)?,
        idle_fraction: if idle.is_empty() {
            0.0
        } else {
            idle.iter().sum::<f64>() / idle.len() as f64
        },
        peak_rss_bytes: ok
            .iter()
            .flat_map(|s| {
                s.per_worker
                    .iter()
                    .map(|w| w.peak_rss_bytes)
                    .chain([s.peak_rss_bytes])
            })
            .max()
            .unwrap_or(0),
        split: TimeSplit::mean(
            &ok.iter()
                .flat_map(|s| s.per_worker.iter().map(TimeSplit::of))
                .collect::<Vec<_>>(),
        ),
    })
}

/// The least median wall time over the schedules that have one.
pub fn best_median(summaries: &[ScheduleSummary]) -> Option<f64> {
    summaries
        .iter()
        .filter_map(|s| s.measured.as_ref().map(|m| m.wall.median))
        .min_by(f64::total_cmp)
}

/// The median domain loads of the reference schedule, when it ran successfully.
pub fn reference_loads(summaries: &[ScheduleSummary]) -> Option<f64> {
    summaries
        .iter()
        .find(|s| s.schedule == REFERENCE_SCHEDULE)
        .and_then(|s| s.measured.as_ref())
        .map(|m| m.domain_loads)
}

/// Whether every successful run made the same image.
#[derive(Clone, Debug, PartialEq)]
pub enum HashCheck {
    /// No run succeeded: nothing to compare.
    NoImages,
    /// `count` images, all with hash `hash`.
    Identical { count: usize, hash: String },
    /// Each distinct hash with the runs ("run 3 (domain, repeat 1)") that made it, the most
    /// common first.
    Differ(Vec<(String, Vec<String>)>),
}

/// Compares the image hashes of every successful run.
pub fn check_hashes(runs: &[RunOutcome]) -> HashCheck {
    let mut groups: Vec<(String, Vec<String>)> = Vec::new();
    for r in runs {
        let Some(s) = r.stats() else { continue };
        let label = format!("run {} ({}, repeat {})", r.run, r.schedule, r.repeat);
        match groups.iter_mut().find(|(h, _)| *h == s.image_hash) {
            Some((_, labels)) => labels.push(label),
            None => groups.push((s.image_hash.clone(), vec![label])),
        }
    }
    match groups.len() {
        0 => HashCheck::NoImages,
        1 => {
            let (hash, labels) = groups.remove(0);
            HashCheck::Identical {
                count: labels.len(),
                hash,
            }
        }
        _ => {
            // Stable: equal counts keep their first-seen order.
            groups.sort_by_key(|(_, labels)| std::cmp::Reverse(labels.len()));
            HashCheck::Differ(groups)
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use rayfarm_core::bundler::TierStats;
    use rayfarm_core::cluster::stats::{TierTraffic, WorkerFrameStats};
    use rayfarm_core::render::cache::CacheCounters;
    use rayfarm_core::render::kernel::KernelCounters;

    use super::*;

    /// Statistics of a two-worker frame: `wall` seconds, `loads` loads split over the workers,
    /// each worker busy `busy` seconds of which `load` loading, on one thread.
    pub(crate) fn stats(wall: f64, loads: u64, busy: f64, load: f64, hash: &str) -> ClusterStats {
        let worker = |id: &str, idle: f64, rss: u64| WorkerFrameStats {
            worker_id: id.into(),
            threads: 1,
            rays: KernelCounters {
                radiance_segments: 1000,
                shadow_segments: 500,
                ..Default::default()
            },
            cache: CacheCounters {
                loads: loads / 2,
                bytes_loaded: loads / 2 * 1024,
                ..Default::default()
            },
            rays_sent: 10,
            bytes_sent: 800,
            tiers: vec![TierTraffic {
                tier: "migrated".into(),
                sent: TierStats {
                    bundles: 3,
                    messages: 5,
                    bytes: 800,
                    rejected: 0,
                },
            }],
            busy_seconds: busy,
            load_seconds: load,
            frame_seconds: wall,
            idle_fraction: idle,
            peak_rss_bytes: rss,
            ..Default::default()
        };
        let mut s = ClusterStats {
            schedule: "dynamic".into(),
            wall_seconds: wall,
            rounds: 7,
            image_hash: hash.into(),
            ..Default::default()
        };
        s.absorb(vec![worker("a", 0.1, 100), worker("b", 0.3, 300)]);
        s
    }

    pub(crate) fn outcome(
        run: usize,
        schedule: &str,
        result: Result<ClusterStats, String>,
    ) -> RunOutcome {
        RunOutcome {
            run,
            repeat: 1,
            schedule: schedule.into(),
            job_id: Some(format!("j{run}")),
            client_seconds: 1.0,
            result,
        }
    }

    #[test]
    fn the_order_rotates_by_one_each_repeat() {
        assert_eq!(
            run_order(3, 3),
            vec![
                (1, 0),
                (1, 1),
                (1, 2),
                (2, 1),
                (2, 2),
                (2, 0),
                (3, 2),
                (3, 0),
                (3, 1)
            ]
        );
        // Past the number of schedules the rotation wraps around.
        assert_eq!(
            run_order(2, 3),
            vec![(1, 0), (1, 1), (2, 1), (2, 0), (3, 0), (3, 1)]
        );
        assert_eq!(run_order(1, 2), vec![(1, 0), (2, 0)]);
        assert!(run_order(0, 3).is_empty());
    }

    #[test]
    fn medians_and_spreads() {
        assert_eq!(median(&[]), None);
        assert_eq!(median(&[3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(
            spread(&[2.0, 5.0, 1.0]),
            Some(Spread {
                median: 2.0,
                min: 1.0,
                max: 5.0
            })
        );
        assert_eq!(spread(&[]), None);
    }

    #[test]
    fn ratios_refuse_a_zero_reference() {
        assert_eq!(ratio(6.0, 2.0), Some(3.0));
        assert_eq!(ratio(6.0, 0.0), None);
        assert_eq!(ratio(6.0, f64::NAN), None);
        assert_eq!(efficiency(1.0, 4.0), Some(0.25));
    }

    #[test]
    fn ray_work_is_busy_less_loading_per_thread() {
        // Two workers, one thread each, busy 3 s of which 1 s loading: 2 s of work each.
        assert_eq!(ray_work_seconds(&stats(5.0, 4, 3.0, 1.0, "h")), 2.0);
        // Old workers report no load time: all busy time counts as work.
        assert_eq!(ray_work_seconds(&stats(5.0, 4, 3.0, 0.0, "h")), 3.0);
    }

    /// Inputs for two workers of unbounded cache and no storage cost: only compute counts.
    pub(crate) fn inputs(domain_bytes: Vec<u64>, bandwidth: Option<f64>) -> BoundInputs {
        BoundInputs {
            domain_bytes,
            workers: 0,
            cache_bytes: None,
            bandwidth,
            max_depth: 3,
            cores: None,
        }
    }

    #[test]
    fn the_bound_takes_the_least_work_and_the_scene_at_storage_speed() {
        let runs = vec![
            outcome(1, "dynamic", Ok(stats(5.0, 4, 3.0, 1.0, "h"))),
            outcome(2, "domain", Ok(stats(9.0, 40, 4.0, 0.5, "h"))),
            outcome(3, "image-plane", Err("UNIMPLEMENTED".into())),
        ];
        let b = bound(&runs, &inputs(vec![100 << 20], None)).unwrap();
        assert_eq!(b.compute_seconds, 2.0);
        assert!(!b.compute_is_cpu);
        assert_eq!(b.load_seconds, 0.0);
        assert_eq!(b.seconds(), 2.0);
        assert_eq!(b.workers, 2);
        // Unbounded caches: each domain once, 100 MiB. The runs loaded less (4 and 40 KiB),
        // so the bound takes the fewest bytes a run loaded: 4 KiB over two workers at
        // 512 B/s each = 4 s.
        assert_eq!(b.model_bytes, 100 << 20);
        assert_eq!(b.load_bytes, 4 * 1024);
        let b = bound(&runs, &inputs(vec![100 << 20], Some(512.0))).unwrap();
        assert_eq!(b.load_seconds, 4.0);
        assert_eq!(b.seconds(), 4.0);
        // A scene smaller than what the runs loaded: its bytes at both workers' bandwidth.
        let b = bound(&runs, &inputs(vec![2048], Some(512.0))).unwrap();
        assert_eq!((b.load_bytes, b.load_seconds), (2048, 2.0));
        assert_eq!(bound(&runs[2..], &inputs(vec![1], None)), None);
    }

    #[test]
    fn unavoidable_loads_are_each_domain_once_and_per_generation_what_the_caches_cannot_keep() {
        let d = [100, 100, 100, 100];
        // Unbounded caches or caches holding the scene: every domain once.
        assert_eq!(unavoidable_load_bytes(&d, 4, None, 5), 400);
        assert_eq!(unavoidable_load_bytes(&d, 2, Some(200), 5), 400);
        assert_eq!(unavoidable_load_bytes(&d, 4, Some(1000), 5), 400);
        // Two workers of one domain each keep 200 of 400 bytes across each of 4 steps.
        assert_eq!(unavoidable_load_bytes(&d, 2, Some(100), 5), 400 + 4 * 200);
        // A cache smaller than every domain keeps nothing: the scene once per generation.
        assert_eq!(unavoidable_load_bytes(&d, 8, Some(99), 5), 5 * 400);
        // Only domains that fit a cache can be kept: 300 fits nowhere.
        assert_eq!(
            unavoidable_load_bytes(&[300, 50, 50], 4, Some(100), 2),
            400 + 300
        );
        // One generation: each domain once, whatever the caches.
        assert_eq!(unavoidable_load_bytes(&d, 1, Some(1), 1), 400);
        assert_eq!(generations(3), 5);
        assert_eq!(generations(0), 2);
    }

    #[test]
    fn the_compute_term_counts_cpu_over_the_cores_there_are() {
        let cpu = |s: &mut ClusterStats, secs: &[f64]| {
            for (w, &c) in s.per_worker.iter_mut().zip(secs) {
                w.trace_cpu_seconds = c;
            }
        };
        // Two workers of one thread busy 3 s (1 s loading) each in wall time; 1.5 s of CPU
        // each: they shared one core.
        let mut s = stats(5.0, 4, 3.0, 1.0, "h");
        assert_eq!(ray_work_cpu_seconds(&s), None);
        assert_eq!(compute_seconds(&s, Some(1)), 2.0);
        cpu(&mut s, &[1.5, 1.5]);
        assert_eq!(ray_work_cpu_seconds(&s), Some(3.0));
        // Two threads on one core: 3 s; on two (or more) cores: 1.5 s.
        assert_eq!(compute_seconds(&s, Some(1)), 3.0);
        assert_eq!(compute_seconds(&s, Some(2)), 1.5);
        assert_eq!(compute_seconds(&s, Some(16)), 1.5);
        assert_eq!(compute_seconds(&s, None), 1.5);
        // A worker that did not measure: back to wall time per thread.
        cpu(&mut s, &[1.5, 0.0]);
        assert_eq!(compute_seconds(&s, Some(1)), 2.0);
        // The bound takes the least over runs and says which kind it is.
        let mut t = stats(5.0, 4, 3.0, 1.0, "h");
        cpu(&mut t, &[0.5, 0.5]);
        let runs = vec![outcome(1, "dynamic", Ok(s)), outcome(2, "domain", Ok(t))];
        let b = bound(
            &runs,
            &BoundInputs {
                cores: Some(1),
                ..inputs(vec![1], None)
            },
        )
        .unwrap();
        assert_eq!(b.compute_seconds, 1.0);
        assert!(b.compute_is_cpu);
    }

    #[test]
    fn the_load_term_reads_the_unavoidable_bytes_at_every_workers_bandwidth() {
        // Four workers, 48 domains of 1 KiB, caches of 2 KiB, depth 3 (5 generations): the
        // scene once (48 KiB) and 4 x (48 - 8) KiB again = 208 KiB, at 4 x 1 KiB/s = 52 s;
        // the run loaded more (1000 KiB), so the model stands.
        let mut s = stats(100.0, 1000, 3.0, 1.0, "h");
        s.workers = 4;
        let runs = vec![outcome(1, "predictive", Ok(s))];
        let b = bound(
            &runs,
            &BoundInputs {
                domain_bytes: vec![1024; 48],
                workers: 4,
                cache_bytes: Some(2048),
                bandwidth: Some(1024.0),
                max_depth: 3,
                cores: Some(2),
            },
        )
        .unwrap();
        assert_eq!(b.model_bytes, 208 * 1024);
        assert_eq!(b.load_bytes, 208 * 1024);
        assert_eq!(b.load_seconds, 52.0);
        assert_eq!(b.seconds(), 52.0);
    }

    #[test]
    fn a_workers_frame_splits_into_parts_that_add_up() {
        let w = WorkerFrameStats {
            frame_seconds: 10.0,
            busy_seconds: 6.0,
            load_seconds: 2.0,
            trace_cpu_seconds: 3.0,
            idle_queued_seconds: 1.0,
            idle_verdicts_seconds: 1.5,
            idle_empty_seconds: 0.5,
            pass_wait_seconds: 0.25,
            pass_start_wait_seconds: 0.125,
            passes: 7,
            cpu_seconds: 4.0,
            ..Default::default()
        };
        let s = TimeSplit::of(&w);
        assert_eq!((s.trace_cpu, s.trace_wait, s.load), (3.0, 1.0, 2.0));
        assert_eq!(
            (s.idle_queued, s.idle_verdicts, s.idle_empty),
            (1.0, 1.5, 0.5)
        );
        assert_eq!(
            (s.pass_wait, s.start_wait, s.other, s.other_cpu, s.passes),
            (0.25, 0.125, 0.625, 1.0, 7.0)
        );
        let parts = s.trace_cpu
            + s.trace_wait
            + s.load
            + s.idle_queued
            + s.idle_verdicts
            + s.idle_empty
            + s.pass_wait
            + s.start_wait
            + s.other;
        assert_eq!(parts, s.frame);
        let m = TimeSplit::mean(&[s, TimeSplit::default()]);
        assert_eq!((m.frame, m.trace_cpu, m.other), (5.0, 1.5, 0.3125));
        assert_eq!(TimeSplit::mean(&[]), TimeSplit::default());
    }

    #[test]
    fn summaries_take_medians_of_the_successful_runs_and_keep_the_errors() {
        let runs = vec![
            outcome(1, "dynamic", Ok(stats(3.0, 4, 1.0, 0.0, "h"))),
            outcome(2, "domain", Err("job j2 failed: boom".into())),
            outcome(3, "dynamic", Ok(stats(1.0, 8, 1.0, 0.0, "h"))),
            outcome(4, "domain", Err("job j4 failed: boom".into())),
            outcome(5, "dynamic", Ok(stats(2.0, 6, 1.0, 0.0, "h"))),
            outcome(6, "domain", Err("job j4 failed: boom".into())),
        ];
        let names = vec!["dynamic".to_string(), "domain".to_string()];
        let s = summarize(&names, &runs);
        assert_eq!((s[0].runs, s[0].ok), (3, 3));
        let m = s[0].measured.as_ref().unwrap();
        assert_eq!(
            m.wall,
            Spread {
                median: 2.0,
                min: 1.0,
                max: 3.0
            }
        );
        assert_eq!(m.domain_loads, 6.0);
        assert_eq!(m.bytes_loaded, 6.0 * 1024.0);
        assert_eq!(m.segments, 3000.0);
        assert_eq!(m.rays_migrated, 20.0);
        assert_eq!(m.bundles, [0.0, 6.0, 0.0]);
        assert_eq!(m.rounds, 7.0);
        assert!((m.idle_fraction - 0.2).abs() < 1e-12);
        assert_eq!(m.peak_rss_bytes, 300);
        assert_eq!((s[1].runs, s[1].ok), (3, 0));
        assert_eq!(s[1].measured, None);
        assert_eq!(
            s[1].errors,
            vec!["job j2 failed: boom", "job j4 failed: boom"]
        );
        assert_eq!(best_median(&s), Some(2.0));
        assert_eq!(reference_loads(&s), Some(6.0));
        assert_eq!(reference_loads(&s[1..]), None);
    }

    #[test]
    fn hashes_are_identical_or_grouped_by_image() {
        let ok = |run, schedule, hash| outcome(run, schedule, Ok(stats(1.0, 2, 1.0, 0.0, hash)));
        assert_eq!(check_hashes(&[]), HashCheck::NoImages);
        let same = [ok(1, "dynamic", "aa"), ok(2, "domain", "aa")];
        assert_eq!(
            check_hashes(&same),
            HashCheck::Identical {
                count: 2,
                hash: "aa".into()
            }
        );
        let differ = [
            ok(1, "dynamic", "aa"),
            ok(2, "domain", "bb"),
            outcome(3, "hybrid", Err("x".into())),
            ok(4, "dynamic", "bb"),
        ];
        assert_eq!(
            check_hashes(&differ),
            HashCheck::Differ(vec![
                (
                    "bb".into(),
                    vec![
                        "run 2 (domain, repeat 1)".into(),
                        "run 4 (dynamic, repeat 1)".into()
                    ]
                ),
                ("aa".into(), vec!["run 1 (dynamic, repeat 1)".into()]),
            ])
        );
    }
}
