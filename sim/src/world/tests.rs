//! The simulator's workers sharing one mapping of a domain give the figures of workers that
//! each map their own, to the digit, under every schedule.

use std::sync::Arc;
use std::time::Duration;

use rayfarm_core::prepare::generate::{NbodyOptions, prepare_nbody};
use rayfarm_core::scene::Manifest;
use rayfarm_proto::Schedule;

use super::{Outcome, SimConfig, simulate};
use crate::faults::FaultPlan;
use crate::node::{QueueCaps, Scene};

/// Four workers rendering a 48x32 frame of the scene in `dir` with caches of `cache_bytes`, the
/// default model, small passes, and prefetch under dynamic.
fn four_workers(dir: &std::path::Path, schedule: Schedule, cache_bytes: u64) -> SimConfig {
    SimConfig {
        scene: dir.to_path_buf(),
        workers: 4,
        schedule,
        warm_up: Vec::new(),
        width: 48,
        height: 32,
        spp: 1,
        depth: 3,
        cache_bytes,
        wave_rays: 1 << 20,
        pass_rays: 512,
        links: Default::default(),
        cost: Default::default(),
        storage: Default::default(),
        measure: false,
        caps: QueueCaps {
            queue_bytes: 512 << 20,
            spill_bytes: 8 << 30,
        },
        ack_deadline: Duration::from_millis(10),
        disk_latency: Duration::from_millis(2),
        heartbeat: Duration::from_millis(20),
        holders_interval: Duration::ZERO,
        report_hold: crate::ReportHold::DEFAULT,
        copy_rays: 1,
        worker_timeout: Duration::from_millis(200),
        speculation: String::new(),
        prefetch: schedule == Schedule::Dynamic,
        max_events: super::default_max_events(4),
        replay_coordinator: false,
        timing_seed: None,
    }
}

/// A clean run of `schedule` on four workers whose caches hold about three domains of the
/// scene in `dir`, so they load, evict and load again.
fn run(dir: &std::path::Path, schedule: Schedule, shared: bool) -> (Outcome, Arc<Scene>) {
    let manifest = Manifest::load(dir).unwrap();
    let largest = manifest.domains.iter().map(|d| d.bytes).max().unwrap();
    let mut scene = Scene::new(dir.to_path_buf(), manifest);
    if !shared {
        scene.mappings = None;
    }
    let scene = Arc::new(scene);
    let config = four_workers(dir, schedule, largest * 3);
    let hour = Duration::from_secs(3600);
    let outcome = simulate(&config, scene.clone(), &FaultPlan::clean(), hour, None).unwrap();
    (outcome, scene)
}

/// The 6,000-triangle scene in 16 domains that these tests render, made under `root`.
fn sixteen_domains(root: &std::path::Path) -> std::path::PathBuf {
    let dir = root.join("nb");
    let options = NbodyOptions {
        name: "nb".into(),
        triangles: 6000,
        seed: 5,
        domains: 16,
        max_memory: None,
        force: false,
    };
    prepare_nbody(&dir, &options).unwrap();
    dir
}

/// The five schedules.
const EVERY_SCHEDULE: [Schedule; 5] = [
    Schedule::ImagePlane,
    Schedule::Domain,
    Schedule::Dynamic,
    Schedule::Hybrid,
    Schedule::Predictive,
];

/// [`sixteen_domains`] opened for simulating, with its largest domain's size.
fn sixteen_domains_opened(root: &std::path::Path) -> (std::path::PathBuf, Arc<Scene>, u64) {
    let dir = sixteen_domains(root);
    let manifest = Manifest::load(&dir).unwrap();
    let largest = manifest.domains.iter().map(|d| d.bytes).max().unwrap();
    let scene = Arc::new(Scene::new(dir.clone(), manifest));
    (dir, scene, largest)
}

#[test]
fn shared_mappings_change_no_figure_and_map_each_domain_once_for_all_workers() {
    let root = tempfile::tempdir().unwrap();
    let dir = sixteen_domains(root.path());
    for schedule in EVERY_SCHEDULE {
        let (own, _) = run(&dir, schedule, false);
        let (shared, scene) = run(&dir, schedule, true);
        assert!(
            own.violations.is_empty(),
            "{schedule:?}: {:?}",
            own.violations
        );
        assert!(own.image_hash.is_some(), "{schedule:?} finished");
        assert!(
            own.loads > 16,
            "{schedule:?}: the caches reload ({})",
            own.loads
        );
        assert_eq!(own, shared, "{schedule:?}");
        // Never more maps than loads; under image-plane every worker reads the same domains,
        // and one a worker holds is not mapped again for another.
        let maps = scene.mappings.as_ref().unwrap().maps();
        let most = if schedule == Schedule::ImagePlane {
            shared.loads - 1
        } else {
            shared.loads
        };
        assert!(
            maps <= most,
            "{schedule:?}: {maps} maps for {} loads",
            shared.loads
        );
    }
}

/// A clean run of the predictive schedule on four workers at the workers' own wave and pass
/// sizes (1,048,576 and 262,144 rays, as `rayfarm bench` runs them): each wave's verdicts and
/// copies leave in bursts of a hundred bundles and more a peer, with the default model's
/// prices and the default deadline (10 ms).
fn burst_run(dir: &std::path::Path) -> Outcome {
    let manifest = Manifest::load(dir).unwrap();
    let scene = Arc::new(Scene::new(dir.to_path_buf(), manifest));
    let config = SimConfig {
        width: 256,
        height: 256,
        pass_rays: 1 << 18,
        prefetch: false,
        ..four_workers(dir, Schedule::Predictive, 64 << 20)
    };
    let hour = Duration::from_secs(3600);
    simulate(&config, scene, &FaultPlan::clean(), hour, None).unwrap()
}

#[test]
fn a_run_without_faults_reports_no_peer_unresponsive_under_bursts_of_bundles() {
    let root = tempfile::tempdir().unwrap();
    let dir = root.path().join("nb");
    let options = NbodyOptions {
        name: "nb".into(),
        triangles: 20_000,
        seed: 5,
        domains: 16,
        max_memory: None,
        force: false,
    };
    prepare_nbody(&dir, &options).unwrap();
    let o = burst_run(&dir);
    assert!(o.violations.is_empty(), "{:?}", o.violations);
    assert!(o.image_hash.is_some(), "finished");
    // The bursts are there: hundreds of thousands of rays change hands in megabytes of
    // bundles.
    assert!(o.rays_migrated > 100_000, "{}", o.rays_migrated);
    assert!(o.peer_bytes > 10 << 20, "{}", o.peer_bytes);
    // Every peer is healthy: a report is a deadline missed only because the simulated
    // acknowledgement waited for what the real one does not (the receiving engine's other
    // work, the sender's own backlog, the bulk on the receiver's NIC).
    assert_eq!(
        o.peers_reported, 0,
        "peers reported unresponsive in a clean run"
    );
}

#[test]
fn a_replayed_coordinator_plans_the_runs_rounds_again_alone_unless_it_crashed() {
    let root = tempfile::tempdir().unwrap();
    let (dir, scene, largest) = sixteen_domains_opened(root.path());
    let hour = Duration::from_secs(3600);
    for schedule in [Schedule::Dynamic, Schedule::Predictive] {
        let config = SimConfig {
            replay_coordinator: true,
            ..four_workers(&dir, schedule, largest * 3)
        };
        let o = simulate(&config, scene.clone(), &FaultPlan::clean(), hour, None).unwrap();
        let r = o.coordinator_replayed.clone().expect("replayed");
        assert!(r.repeated, "{schedule:?}: {r:?}");
        assert!(
            r.planning.rounds > 1 && r.planning.rounds == o.rounds,
            "{r:?}"
        );
        assert!(
            r.calls > r.planning.rounds && r.reports > Duration::ZERO,
            "{r:?}"
        );
        // Not asked: nothing kept, nothing replayed, the same figures otherwise.
        let plain = four_workers(&dir, schedule, largest * 3);
        let p = simulate(&plain, scene.clone(), &FaultPlan::clean(), hour, None).unwrap();
        assert_eq!(p.coordinator_replayed, None);
        assert_eq!(
            Outcome {
                coordinator_replayed: None,
                ..o.clone()
            },
            p
        );
        // A coordinator that crashed is not replayed: its restart began from its disk.
        let span = o.frame_time.unwrap();
        let crash = FaultPlan {
            faults: vec![crate::faults::Fault::CrashCoordinator {
                at: rayfarm_machine::Time(0) + span / 2,
                down: span / 10,
            }],
            ..FaultPlan::clean()
        };
        let c = simulate(&config, scene.clone(), &crash, hour, None).unwrap();
        assert_eq!(c.coordinator_crashes, 1);
        assert_eq!(c.coordinator_replayed, None);
    }
}

/// Waits for the tracing thread drawn from a timing seed move the frame's time but not its
/// image, and one seed gives the same run every time.
#[test]
fn timing_seeds_move_the_frame_and_keep_its_image() {
    let root = tempfile::tempdir().unwrap();
    let (dir, scene, largest) = sixteen_domains_opened(root.path());
    let mut config = four_workers(&dir, Schedule::Dynamic, largest * 3);
    config.cost.pass_start = Duration::from_micros(500);
    config.cost.cores = Some(2);
    let hour = Duration::from_secs(3600);
    let run = |seed: Option<u64>| {
        let config = SimConfig {
            timing_seed: seed,
            ..config.clone()
        };
        let out = simulate(&config, scene.clone(), &FaultPlan::clean(), hour, None).unwrap();
        assert!(out.violations.is_empty(), "{seed:?}: {:?}", out.violations);
        out
    };
    let fixed = run(None);
    let drawn: Vec<Outcome> = (0..4).map(|seed| run(Some(seed))).collect();
    for (seed, out) in drawn.iter().enumerate() {
        assert_eq!(out.image_hash, fixed.image_hash, "seed {seed}");
    }
    let times: std::collections::BTreeSet<_> = drawn.iter().map(|o| o.frame_time).collect();
    assert!(times.len() > 1, "the seeds' frames all took {times:?}");
    assert_eq!(run(Some(2)), drawn[2], "a seed repeats");
}

/// A worker's frame is told in parts that do not overlap: with shared cores and a wait for
/// the tracing thread, the parts add up to the frame under every schedule.
#[test]
fn a_workers_frame_is_the_sum_of_its_parts() {
    let root = tempfile::tempdir().unwrap();
    let (dir, scene, largest) = sixteen_domains_opened(root.path());
    for schedule in EVERY_SCHEDULE {
        let mut config = four_workers(&dir, schedule, largest * 3);
        config.cost.pass_start = Duration::from_micros(300);
        config.cost.cores = Some(2);
        let hour = Duration::from_secs(3600);
        let out = simulate(&config, scene.clone(), &FaultPlan::clean(), hour, None).unwrap();
        let t = out.time;
        assert_eq!(t.frames, 4, "{schedule:?}: a frame a worker");
        let parts: Duration = t.parts().iter().map(|&(_, d)| d).sum();
        let (parts, frame) = (parts.as_secs_f64(), t.frame.as_secs_f64());
        assert!(
            (parts - frame).abs() <= frame * 0.01,
            "{schedule:?}: parts {parts} s against frames of {frame} s: {t:?}"
        );
        assert!(t.loading > Duration::ZERO && t.thread_wait > Duration::ZERO);
    }
}

/// A peer bundle's wait for the engine (`CostModel::bundle_take`) slows a frame whose rays
/// move between workers and changes no image, fixed or drawn from a timing seed.
#[test]
fn a_bundles_wait_for_the_engine_slows_the_frame_not_its_image() {
    let root = tempfile::tempdir().unwrap();
    let (dir, scene, largest) = sixteen_domains_opened(root.path());
    let hour = Duration::from_secs(3600);
    let run = |take_us: u64, seed: Option<u64>| {
        let mut config = four_workers(&dir, Schedule::Predictive, largest * 3);
        config.cost.bundle_take = Duration::from_micros(take_us);
        config.timing_seed = seed;
        let out = simulate(&config, scene.clone(), &FaultPlan::clean(), hour, None).unwrap();
        assert!(
            out.violations.is_empty(),
            "{take_us} us: {:?}",
            out.violations
        );
        out
    };
    let (plain, slowed, drawn) = (run(0, None), run(2000, None), run(2000, Some(3)));
    assert!(plain.rays_migrated > 0);
    assert_eq!(slowed.image_hash, plain.image_hash);
    assert_eq!(drawn.image_hash, plain.image_hash);
    assert!(
        slowed.frame_time > plain.frame_time,
        "{:?} against {:?}",
        slowed.frame_time,
        plain.frame_time
    );
    assert_ne!(
        drawn.frame_time, slowed.frame_time,
        "the seed draws the waits"
    );
}
