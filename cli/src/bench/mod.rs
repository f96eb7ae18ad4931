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

use rayfarm_core::cluster::stats::ClusterStats;

/// Tier names in the order the statistics and the table show them.
pub const TIERS: [&str; 4] = ["control", "results", "migrated", "tasks"];

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
pub fn ray_work_seconds(stats: &ClusterStats) -> f64 {
    let work: f64 = stats
        .per_worker
        .iter()
        .map(|w| (w.busy_seconds - w.load_seconds).max(0.0))
        .sum();
    let threads = if stats.threads > 0 {
        stats.threads
    } else {
        stats.per_worker.iter().map(|w| w.threads).sum()
    };
    work / threads.max(1) as f64
}

/// The yardstick of the bench: no frame can take less than the larger of its two terms.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bound {
    /// The least ray work per thread over all successful runs of the bench (one bound for
    /// every schedule, so a schedule is not rewarded for wasting less of its own time).
    pub compute_seconds: f64,
    /// Reading every domain of the scene once at the storage bandwidth (0 when no bandwidth
    /// was given).
    pub load_seconds: f64,
}

impl Bound {
    /// The bound itself: the larger term.
    pub fn seconds(&self) -> f64 {
        self.compute_seconds.max(self.load_seconds)
    }
}

/// The bound of a bench: `None` when no run succeeded. `scene_bytes` is the size of all the
/// scene's domain files, `bandwidth` the storage bandwidth in bytes per second.
pub fn bound(runs: &[RunOutcome], scene_bytes: u64, bandwidth: Option<f64>) -> Option<Bound> {
    let compute_seconds = runs
        .iter()
        .filter_map(RunOutcome::stats)
        .map(ray_work_seconds)
        .min_by(f64::total_cmp)?;
    let load_seconds = match bandwidth {
        Some(b) if b > 0.0 => scene_bytes as f64 / b,
        _ => 0.0,
    };
    Some(Bound {
        compute_seconds,
        load_seconds,
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
    /// Of the loads, prefetches; of those, used by a pass and wasted (left unused).
    pub prefetches: f64,
    pub prefetches_used: f64,
    pub prefetches_wasted: f64,
    /// Ray segments traced.
    pub segments: f64,
    pub rays_migrated: f64,
    pub bytes_migrated: f64,
    /// Bundles sent per tier, in [`TIERS`] order.
    pub bundles: [f64; 4],
    pub rounds: f64,
    /// Mean over all workers of all runs.
    pub idle_fraction: f64,
    /// Largest over all workers of all runs, bytes.
    pub peak_rss_bytes: u64,
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
pub fn tier_bundles(stats: &ClusterStats, tier: &str) -> u64 {
    stats
        .tiers
        .iter()
        .filter(|t| t.tier == tier)
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
    let mut bundles = [0.0; 4];
    for (b, tier) in bundles.iter_mut().zip(TIERS) {
        *b = med(&|s| tier_bundles(s, tier) as f64)?;
    }
    Some(Measured {
        wall,
        domain_loads: med(&|s| s.cache.loads as f64)?,
        bytes_loaded: med(&|s| s.cache.bytes_loaded as f64)?,
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

    #[test]
    fn the_bound_takes_the_least_work_and_the_scene_at_storage_speed() {
        let runs = vec![
            outcome(1, "dynamic", Ok(stats(5.0, 4, 3.0, 1.0, "h"))),
            outcome(2, "domain", Ok(stats(9.0, 40, 4.0, 0.5, "h"))),
            outcome(3, "image-plane", Err("UNIMPLEMENTED".into())),
        ];
        let b = bound(&runs, 100 << 20, None).unwrap();
        assert_eq!(b.compute_seconds, 2.0);
        assert_eq!(b.load_seconds, 0.0);
        assert_eq!(b.seconds(), 2.0);
        // 100 MiB at 20 MiB/s: 5 s, more than the compute term.
        let b = bound(&runs, 100 << 20, Some(20.0 * 1048576.0)).unwrap();
        assert_eq!(b.load_seconds, 5.0);
        assert_eq!(b.seconds(), 5.0);
        assert_eq!(bound(&runs[2..], 1, None), None);
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
        assert_eq!(m.bundles, [0.0, 0.0, 6.0, 0.0]);
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
