//! One row per schedule: how many of its runs succeeded, their distinct errors, and the
//! medians of what the successful ones measured, down to where a worker's frame time went.

use rayfarm_core::bundler::Tier;
use rayfarm_core::cluster::stats::{ClusterStats, tier_name};

use super::{REFERENCE_SCHEDULE, RunOutcome, Spread, median, spread};

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
