use rayfarm_core::bundler::TierStats;
use rayfarm_core::cluster::stats::{TierTraffic, WorkerFrameStats};
use rayfarm_core::render::cache::CacheCounters;
use rayfarm_core::render::kernel::KernelCounters;

use super::lower_bound::{compute_seconds, ray_work_cpu_seconds, unavoidable_load_bytes};
use super::summary::TimeSplit;
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
