//! A real cluster on loopback (a `rayfarm-coordinator` and `rayfarm-worker` processes, driven
//! with the `rayfarm` CLI as a user would) renders the image of `rayfarm render --local` to
//! the bit, whatever the number of workers, the cache budgets, the jobs around it and the
//! order in which messages arrive.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use rayfarm_tests::{
    Cluster, WorkerOpts, bin, domain_bytes, hash_of, job, jobs, local_hash, prepare_nbody,
    rayfarm_ok, s, stats_field, submit_wait, wait_child, wait_until,
};

/// A frame small enough to render in about a second, deep enough to bounce between domains.
const FRAME: [&str; 8] = [
    "--width", "96", "--height", "72", "--spp", "2", "--depth", "3",
];

/// A frame long enough for a test to act on the cluster while it renders.
const MANY_ROUNDS: [&str; 8] = [
    "--width", "192", "--height", "144", "--spp", "8", "--depth", "3",
];

/// Whether the coordinator is rendering a frame now.
fn frame_running(cluster: &Cluster) -> bool {
    cluster.status()["running_job_id"]
        .as_str()
        .is_some_and(|j| !j.is_empty())
}

/// Starts `rayfarm submit --wait` for `frame` in the background (the test acts meanwhile).
fn spawn_submit_wait(
    cluster: &Cluster,
    frame: &[&str],
    extra: &[&str],
    png: &Path,
    json: &Path,
) -> std::process::Child {
    Command::new(bin("rayfarm"))
        .args([
            "submit",
            "--wait",
            "--quiet",
            "-o",
            s(png),
            "--stats-json",
            s(json),
        ])
        .args(extra)
        .args(frame)
        .env("RAYFARM_COORDINATOR", cluster.coordinator_url())
        .stdout(Stdio::null())
        .spawn()
        .expect("start rayfarm submit")
}

fn submit(cluster: &Cluster, frame: &[&str], extra: &[&str]) -> String {
    let mut args = vec!["submit"];
    args.extend_from_slice(frame);
    args.extend_from_slice(extra);
    let out = cluster.rayfarm_ok(&args);
    String::from_utf8_lossy(&out.stdout).trim().to_string()
}

#[test]
fn one_two_and_four_workers_render_the_local_image() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 40_000, 8);
    let (_, largest) = domain_bytes(&scene);
    let expected = local_hash(&scene, &FRAME);
    // Caches of two domains make rays move between workers; caches that hold the scene let
    // every worker take copies of everything it needs.
    for (n, cache) in [
        (1, 2 * largest),
        (2, 2 * largest),
        (4, 2 * largest),
        (2, 1 << 30),
    ] {
        let workers = vec![WorkerOpts::cache(cache); n];
        let cluster = Cluster::start(root.path(), Some("nb"), &workers);
        let stats = submit_wait(&cluster, &FRAME, &format!("w{n}"));
        assert_eq!(hash_of(&stats), expected, "{n} workers, cache {cache}");
        assert_eq!(stats_field(&stats, "/workers"), n, "{n} workers took part");
        let migrated = stats_field(&stats, "/rays_migrated").as_u64().unwrap_or(0);
        if n > 1 && cache < 1 << 30 {
            assert!(migrated > 0, "{n} workers with small caches moved no rays");
            assert!(tier_bundles(&stats, "migrated") > Some(0));
        }
    }
}

#[test]
fn every_schedule_renders_the_local_image_with_one_to_four_workers() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 30_000, 8);
    let (_, largest) = domain_bytes(&scene);
    let expected = local_hash(&scene, &FRAME);
    for n in 1..=4 {
        // Two-domain caches: image-plane and domain must page, dynamic must plan.
        let cluster = Cluster::start(
            root.path(),
            Some("nb"),
            &vec![WorkerOpts::cache(2 * largest); n],
        );
        for schedule in ["image-plane", "domain", "dynamic", "hybrid", "predictive"] {
            let mut frame = FRAME.to_vec();
            frame.extend(["--schedule", schedule, "--cold-cache"]);
            let stats = submit_wait(&cluster, &frame, &format!("{schedule}-{n}"));
            assert_eq!(hash_of(&stats), expected, "{schedule} with {n} workers");
            assert_eq!(stats_field(&stats, "/schedule"), schedule);
            let migrated = stats_field(&stats, "/rays_migrated").as_u64();
            if schedule == "image-plane" {
                assert_eq!(
                    migrated,
                    Some(0),
                    "image-plane rays never leave their worker"
                );
            } else if n > 1 && schedule == "domain" {
                assert!(
                    migrated > Some(0),
                    "domain schedule with {n} workers moved no rays"
                );
            }
            // Verdicts of speculative copies travel in the results tier, and only they do.
            let verdict_bundles = tier_bundles(&stats, "results");
            match (schedule, n) {
                ("predictive", 2..) => assert!(verdict_bundles > Some(0), "{n} workers"),
                _ => assert_eq!(verdict_bundles, Some(0), "{schedule} with {n} workers"),
            }
        }
    }
}

#[test]
fn hybrid_hands_a_slow_workers_queued_rays_to_idle_workers_as_tasks() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 30_000, 8);
    let expected = local_hash(&scene, &MANY_ROUNDS);
    // Caches hold the scene, so camera rays load what they need where they were issued (the
    // hybrid schedule's demand-driven side); one worker's every load takes 300 ms, so it
    // still holds queued rays when the others have run out of tiles.
    let mut slow = WorkerOpts::cache(1 << 30);
    slow.args = vec!["--storage-latency".into(), "300ms".into()];
    let mut workers = vec![WorkerOpts::cache(1 << 30); 3];
    workers.insert(0, slow);
    let cluster = Cluster::start(root.path(), Some("nb"), &workers);
    let mut frame = MANY_ROUNDS.to_vec();
    frame.extend(["--schedule", "hybrid", "--cold-cache"]);
    let stats = submit_wait(&cluster, &frame, "tasks");
    assert_eq!(hash_of(&stats), expected);
    let shared = stats_field(&stats, "/rays_shared").as_u64().unwrap_or(0);
    let task_bundles = tier_bundles(&stats, "tasks").unwrap_or(0);
    eprintln!("{shared} rays handed over as tasks in {task_bundles} bundles");
    assert!(shared > 0, "no queued rays were handed to an idle worker");
    assert!(task_bundles > 0, "tasks travel in the tasks tier");
}

/// Bundles a frame's workers sent in the tier called `tier`, found by name; checks that the
/// statistics list the tiers there are, most urgent first.
fn tier_bundles(stats: &Path, tier: &str) -> Option<u64> {
    let tiers = stats_field(stats, "/tiers");
    let tiers = tiers.as_array()?;
    let names: Vec<&str> = tiers.iter().filter_map(|t| t["tier"].as_str()).collect();
    assert_eq!(
        names,
        ["results", "migrated", "tasks"],
        "the tiers in {stats:?}"
    );
    tiers.iter().find(|t| t["tier"] == tier)?["bundles"].as_u64()
}

/// Segments traced in a frame (radiance and shadow).
fn segments(stats: &Path) -> u64 {
    ["/rays/radiance_segments", "/rays/shadow_segments"]
        .iter()
        .map(|f| stats_field(stats, f).as_u64().expect(f))
        .sum()
}

#[test]
fn predictive_speculation_renders_the_local_image_at_every_setting_with_one_to_four_workers() {
    // How far ahead rays are copied only moves work between copies traced and verdicts' round
    // trips: the image is the local one whatever is predicted, and whatever order the
    // verdicts the prediction learns from arrive in.
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 30_000, 8);
    let (_, largest) = domain_bytes(&scene);
    let expected = local_hash(&scene, &FRAME);
    for n in 1..=4 {
        let cluster = Cluster::start(
            root.path(),
            Some("nb"),
            &vec![WorkerOpts::cache(2 * largest); n],
        );
        let mut traced = Vec::new();
        for setting in ["none", "full", "ahead:1", "predicted", "predicted:0.5"] {
            let mut frame = FRAME.to_vec();
            frame.extend(["--schedule", "predictive", "--cold-cache"]);
            frame.extend(["--speculation", setting]);
            let stats = submit_wait(&cluster, &frame, &format!("{setting}-{n}"));
            assert_eq!(hash_of(&stats), expected, "{setting} with {n} workers");
            let verdict_bundles = tier_bundles(&stats, "results");
            if setting == "none" {
                assert_eq!(verdict_bundles, Some(0), "no copies, no verdicts");
            } else if n > 1 {
                assert!(verdict_bundles > Some(0), "{setting} with {n} workers");
            }
            traced.push((setting, segments(&stats)));
        }
        // Copies beyond a hit are what full speculation pays (less those skipped once a
        // nearer domain ended the ray); one domain at a time pays none (the chained trace's
        // segments exactly), prediction some. At the default target prediction and full
        // speculation with skipping come within a fraction of a percent of each other here,
        // in either order, so the lower target is the one compared.
        let seg = |s: &str| traced.iter().find(|t| t.0 == s).unwrap().1;
        assert_eq!(seg("ahead:1"), seg("none"), "{n} workers: {traced:?}");
        assert!(
            seg("predicted:0.5") < seg("full"),
            "{n} workers: {traced:?}"
        );
        assert!(seg("predicted") >= seg("none"), "{n} workers: {traced:?}");
        assert!(seg("full") > seg("none"), "{n} workers: {traced:?}");
    }
}

#[test]
fn dynamic_rounds_with_a_barrier_render_the_local_image() {
    // The default is asynchronous rounds; Fig. 5's barrier rounds must agree to the bit.
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 30_000, 8);
    let (_, largest) = domain_bytes(&scene);
    let expected = local_hash(&scene, &FRAME);
    for n in [2, 4] {
        let cluster = Cluster::start_with_env(
            root.path(),
            Some("nb"),
            &[("RAYFARM_ROUNDS", "barrier")],
            &vec![WorkerOpts::cache(largest); n],
        );
        for schedule in ["dynamic", "predictive"] {
            let mut frame = FRAME.to_vec();
            frame.extend(["--schedule", schedule, "--cold-cache"]);
            let stats = submit_wait(&cluster, &frame, &format!("barrier-{schedule}-{n}"));
            assert_eq!(
                hash_of(&stats),
                expected,
                "{schedule}, barrier, {n} workers"
            );
            let rounds = stats_field(&stats, "/rounds").as_u64().unwrap_or(0);
            assert!(
                rounds > 1,
                "{schedule}: {n} workers planned {rounds} rounds"
            );
        }
    }
}

#[test]
fn a_scene_four_times_the_cluster_cache_renders_identically() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "big", 60_000, 16);
    let (total, largest) = domain_bytes(&scene);
    // Each cache holds the largest domain and no more.
    let workers = vec![WorkerOpts::cache(largest); 2];
    assert!(
        total >= 4 * 2 * largest,
        "scene {total} B is not 4x the caches' {} B",
        2 * largest
    );
    let expected = local_hash(&scene, &FRAME);
    let cluster = Cluster::start(root.path(), Some("big"), &workers);
    let stats = submit_wait(&cluster, &FRAME, "big");
    assert_eq!(hash_of(&stats), expected);
    let loads = stats_field(&stats, "/cache/loads").as_u64().expect("loads");
    let rounds = stats_field(&stats, "/rounds").as_u64().expect("rounds");
    eprintln!(
        "scene {total} B over caches of 2 x {largest} B: {loads} domain loads, {rounds} rounds"
    );
    assert!(
        loads >= 16,
        "every domain with geometry in view must be loaded at least once"
    );
}

#[test]
fn jobs_run_in_priority_order_then_submission_order() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 20_000, 4);
    // No worker yet: all three wait in the queue.
    let mut cluster = Cluster::start(root.path(), Some("nb"), &[]);
    let low = submit(&cluster, &FRAME, &["--priority", "1"]);
    let high = submit(&cluster, &FRAME, &["--priority", "9"]);
    let mid = submit(&cluster, &FRAME, &["--priority", "5"]);
    let listed = jobs(&cluster);
    for id in [&low, &high, &mid] {
        assert_eq!(job(&listed, id)["state"], "queued");
    }
    cluster.add_worker(&WorkerOpts::default());
    for id in [&low, &high, &mid] {
        cluster.rayfarm_ok(&["watch", id, "--quiet"]);
    }
    let listed = jobs(&cluster);
    let started = |id: &str| {
        job(&listed, id)["started_unix_ms"]
            .as_i64()
            .expect("started")
    };
    let finished = |id: &str| {
        job(&listed, id)["finished_unix_ms"]
            .as_i64()
            .expect("finished")
    };
    for id in [&low, &high, &mid] {
        assert_eq!(job(&listed, id)["state"], "succeeded");
    }
    assert!(started(&high) <= started(&mid) && started(&mid) <= started(&low));
    assert!(finished(&high) <= finished(&mid) && finished(&mid) <= finished(&low));
    // And the images are right.
    let expected = local_hash(&scene, &FRAME);
    for id in [&low, &high, &mid] {
        let png = cluster.dir().join(format!("{id}.png"));
        let out = cluster.rayfarm_ok(&["fetch", id, "-o", s(&png)]);
        assert!(String::from_utf8_lossy(&out.stdout).contains(&expected));
    }
}

#[test]
fn cancel_stops_the_running_job_and_the_cluster_takes_the_next() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 20_000, 4);
    let cluster = Cluster::start(root.path(), Some("nb"), &[WorkerOpts::default()]);
    // Minutes of work, so it is surely still running when cancelled.
    let long = submit(
        &cluster,
        &["--width", "256", "--height", "256", "--spp", "4096"],
        &[],
    );
    let next = submit(&cluster, &FRAME, &[]);
    wait_until("the long job to run", Duration::from_secs(30), || {
        job(&jobs(&cluster), &long)["state"] == "running"
    });
    let out = cluster.rayfarm_ok(&["cancel", &long]);
    assert!(String::from_utf8_lossy(&out.stdout).contains("cancelled"));
    let json = cluster.dir().join("next.json");
    let png = cluster.dir().join("next.png");
    cluster.rayfarm_ok(&["watch", &next, "--quiet"]);
    cluster.rayfarm_ok(&["fetch", &next, "-o", s(&png), "--stats-json", s(&json)]);
    assert_eq!(hash_of(&json), local_hash(&scene, &FRAME));
    let listed = jobs(&cluster);
    assert_eq!(job(&listed, &long)["state"], "cancelled");
    assert_eq!(job(&listed, &next)["state"], "succeeded");
    // A cancelled job has no result.
    let refused = cluster.rayfarm(&["fetch", &long, "-o", s(&png)]);
    assert!(!refused.status.success());
}

#[test]
fn a_worker_started_mid_frame_gets_work_in_the_next_round() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 60_000, 16);
    let (_, largest) = domain_bytes(&scene);
    // One-domain caches: many rounds, so the frame is still running when the worker joins.
    let frame = MANY_ROUNDS;
    let expected = local_hash(&scene, &frame);
    // Predictive: the others must learn where the newcomer's verdicts go.
    for schedule in ["dynamic", "predictive"] {
        let mut cluster = Cluster::start(root.path(), Some("nb"), &[WorkerOpts::cache(largest)]);
        let json = cluster.dir().join("join.json");
        let png = cluster.dir().join("join.png");
        let mut waiter =
            spawn_submit_wait(&cluster, &frame, &["--schedule", schedule], &png, &json);
        wait_until("round 2 of the frame", Duration::from_secs(60), || {
            cluster.status()["round"].as_u64() >= Some(2)
        });
        cluster.add_worker(&WorkerOpts::cache(largest));
        let ok = wait_child(&mut waiter, "the frame", Duration::from_secs(120));
        assert!(ok, "{schedule}: submit --wait failed");
        assert_eq!(hash_of(&json), expected, "{schedule}");
        let per_worker = stats_field(&json, "/per_worker");
        let per_worker = per_worker.as_array().expect("per-worker stats");
        assert_eq!(per_worker.len(), 2, "both workers report: {per_worker:?}");
        for w in per_worker {
            let traced = w["rays"]["radiance_segments"].as_u64().unwrap_or(0);
            assert!(
                traced > 0,
                "{schedule}: worker {} traced nothing",
                w["worker_id"]
            );
        }
    }
}

#[test]
fn random_message_delays_never_commit_a_tile_early() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 30_000, 8);
    let (_, largest) = domain_bytes(&scene);
    let expected = local_hash(&scene, &FRAME);
    for n in 0..20usize {
        let seed = n.to_string();
        let delays = [
            ("RAYFARM_FAULT_DELAY_MS", "3"),
            ("RAYFARM_FAULT_SEED", seed.as_str()),
        ];
        let worker = delays
            .iter()
            .fold(WorkerOpts::cache(2 * largest), |w, (k, v)| w.env(k, v));
        let cluster = Cluster::start_with_env(root.path(), Some("nb"), &delays, &vec![worker; 3]);
        // Half the seeds run predictive: verdicts arrive out of order too.
        let schedule = ["dynamic", "predictive"][n % 2];
        let mut frame = FRAME.to_vec();
        frame.extend(["--schedule", schedule]);
        let stats = submit_wait(&cluster, &frame, "delayed");
        assert_eq!(hash_of(&stats), expected, "seed {seed}, {schedule}");
    }
}

/// Runs `rayfarm` against the cluster expecting failure; returns stderr.
fn refused(cluster: &Cluster, args: &[&str]) -> String {
    let out = cluster.rayfarm(args);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(
        !out.status.success(),
        "rayfarm {} should have failed",
        args.join(" ")
    );
    stderr
}

#[test]
fn bad_jobs_get_precise_errors_and_the_cluster_renders_the_next() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 20_000, 4);
    // A copy of the scene with one domain file damaged after its checksum was taken.
    let broken = root.path().join("broken");
    std::fs::create_dir_all(&broken).expect("mkdir");
    for entry in std::fs::read_dir(&scene).expect("scene dir") {
        let entry = entry.expect("entry");
        std::fs::copy(entry.path(), broken.join(entry.file_name())).expect("copy");
    }
    let damaged = std::fs::read_dir(&broken)
        .expect("dir")
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.file_name().is_some_and(|n| n != "scene.toml"))
        .max_by_key(|p| std::fs::metadata(p).map(|m| m.len()).unwrap_or(0))
        .expect("a domain file");
    let mut bytes = std::fs::read(&damaged).expect("read");
    let last = bytes.len() - 1;
    bytes[last] ^= 0x40;
    std::fs::write(&damaged, &bytes).expect("write");
    // And a copy with that domain file cut short, as by an interrupted copy.
    let truncated = root.path().join("truncated");
    std::fs::create_dir_all(&truncated).expect("mkdir");
    for entry in std::fs::read_dir(&broken).expect("scene dir") {
        let entry = entry.expect("entry");
        std::fs::copy(entry.path(), truncated.join(entry.file_name())).expect("copy");
    }
    let cut = truncated.join(damaged.file_name().expect("name"));
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).expect("write");

    let cluster = Cluster::start(root.path(), Some("nb"), &[WorkerOpts::default()]);
    // Each command, and what its error must name.
    let cases: [(&[&str], &[&str]); 7] = [
        (&["--width", "0"], &["INVALID_ARGUMENT", "resolution"]),
        (&["--spp", "70000"], &["INVALID_ARGUMENT", "spp"]),
        (&["--width", "100000"], &["INVALID_ARGUMENT", "resolution"]),
        (&["--depth", "100000"], &["INVALID_ARGUMENT", "depth"]),
        (&["--schedule", "fastest"], &["unknown schedule"]),
        (
            &["--scene", "no-such-scene"],
            &["NOT_FOUND", "no-such-scene"],
        ),
        (&["--scene", "../etc"], &["INVALID_ARGUMENT", "scene root"]),
    ];
    for (args, names) in cases {
        let err = refused(&cluster, &[&["submit"], args].concat());
        assert!(names.iter().all(|n| err.contains(n)), "{args:?}: {err}");
    }
    let err = refused(&cluster, &["fetch", "job-that-never-was", "-o", "x.png"]);
    assert!(err.contains("NOT_FOUND"), "{err}");
    // Nothing was received, so no partial file is left to resume from.
    assert!(
        !std::path::Path::new("x.png.part").exists(),
        "a refused fetch left x.png.part"
    );
    // The damaged domain fails its job, naming the file, when a worker first loads it.
    let mut args = vec!["submit", "--scene", "broken", "--wait", "--quiet"];
    args.extend_from_slice(&FRAME);
    let err = refused(&cluster, &args);
    let file = damaged.file_name().and_then(|n| n.to_str()).expect("name");
    assert!(err.contains("failed") && err.contains(file), "{err}");
    let mut args = vec!["submit", "--scene", "truncated", "--wait", "--quiet"];
    args.extend_from_slice(&FRAME);
    let err = refused(&cluster, &args);
    assert!(err.contains("failed") && err.contains(file), "{err}");
    // The cluster is unharmed: the next job renders the reference image.
    let stats = submit_wait(&cluster, &FRAME, "after");
    assert_eq!(hash_of(&stats), local_hash(&scene, &FRAME));
    // A result larger than gRPC's default 4 MiB message limit still comes back whole.
    let exr = cluster.dir().join("big.exr");
    let big = [
        "--width", "1200", "--height", "1200", "--spp", "1", "--depth", "0",
    ];
    let mut args = vec!["submit", "--wait", "--quiet", "-o", s(&exr)];
    args.extend_from_slice(&big);
    cluster.rayfarm_ok(&args);
    assert!(std::fs::metadata(&exr).expect("exr written").len() > 4 << 20);
}

#[test]
fn the_demo_runs_a_local_cluster_and_matches_its_local_render() {
    let dir = tempfile::tempdir().expect("temp dir");
    let demo = |extra: &[&str]| {
        let mut args = vec![
            "demo",
            "--dir",
            s(dir.path()),
            "--triangles",
            "20000",
            "--domains",
            "8",
            "--width",
            "64",
            "--height",
            "48",
            "--spp",
            "1",
        ];
        args.extend_from_slice(extra);
        rayfarm_ok(&args);
        hash_of(&dir.path().join("demo-stats.json"))
    };
    let cluster = demo(&["--workers", "2"]);
    assert!(dir.path().join("demo.png").exists());
    assert_eq!(
        stats_field(&dir.path().join("demo-stats.json"), "/workers"),
        2
    );
    assert_eq!(cluster, demo(&["--local"]));
}

#[test]
fn queues_past_their_memory_cap_spill_to_disk_and_past_the_spill_cap_fail_clearly() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 30_000, 8);
    let (_, largest) = domain_bytes(&scene);
    // 64 KiB of queue memory: 819 rays, far fewer than a frame queues.
    let tight = WorkerOpts::cache(2 * largest).env("RAYFARM_QUEUE_BYTES", "64KiB");
    let cluster = Cluster::start(root.path(), Some("nb"), &vec![tight; 2]);
    let stats = submit_wait(&cluster, &FRAME, "spilled");
    assert_eq!(hash_of(&stats), local_hash(&scene, &FRAME));
    let per_worker = stats_field(&stats, "/per_worker");
    let spilled: u64 = per_worker
        .as_array()
        .expect("per-worker stats")
        .iter()
        .map(|w| w["rays_spilled"].as_u64().unwrap_or(0))
        .sum();
    assert!(spilled > 0, "nothing spilled: {per_worker}");
    drop(cluster);

    let starved = WorkerOpts::cache(2 * largest)
        .env("RAYFARM_QUEUE_BYTES", "8KiB")
        .env("RAYFARM_SPILL_BYTES", "16KiB");
    let cluster = Cluster::start(root.path(), Some("nb"), &[starved]);
    let mut args = vec!["submit", "--wait", "--quiet"];
    args.extend_from_slice(&FRAME);
    let err = refused(&cluster, &args);
    assert!(err.contains("exceed the worker's budgets"), "{err}");
    // The worker is still there for the next job.
    let status = cluster.status();
    assert_eq!(status["workers"].as_array().map(Vec::len), Some(1));
}

#[test]
fn a_worker_killed_mid_frame_costs_time_not_the_image() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 60_000, 16);
    let (_, largest) = domain_bytes(&scene);
    let frame = MANY_ROUNDS;
    let expected = local_hash(&scene, &frame);
    for schedule in ["dynamic", "domain", "hybrid", "image-plane", "predictive"] {
        // One-domain caches: many rounds, rays on every worker, so the kill lands mid-frame.
        let mut cluster = Cluster::start(
            root.path(),
            Some("nb"),
            &vec![WorkerOpts::cache(largest); 3],
        );
        let json = cluster.dir().join("killed.json");
        let png = cluster.dir().join("killed.png");
        let mut waiter =
            spawn_submit_wait(&cluster, &frame, &["--schedule", schedule], &png, &json);
        wait_until(
            &format!("the {schedule} frame to start"),
            Duration::from_secs(60),
            || frame_running(&cluster),
        );
        cluster.kill_worker(1);
        let ok = wait_child(&mut waiter, "the frame", Duration::from_secs(120));
        assert!(ok, "{schedule}: the frame failed after a worker was killed");
        assert_eq!(hash_of(&json), expected, "{schedule}");
        // The killed worker was a member and never reported: the frame really lost it.
        assert_eq!(stats_field(&json, "/workers"), 2, "{schedule}");
    }
}

#[test]
fn two_of_four_workers_killed_at_once_and_a_replacement_joining_keep_the_image() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 60_000, 16);
    let (_, largest) = domain_bytes(&scene);
    let frame = MANY_ROUNDS;
    let mut cluster = Cluster::start(
        root.path(),
        Some("nb"),
        &vec![WorkerOpts::cache(largest); 4],
    );
    let json = cluster.dir().join("two.json");
    let png = cluster.dir().join("two.png");
    let mut waiter = spawn_submit_wait(&cluster, &frame, &[], &png, &json);
    wait_until("round 1 of the frame", Duration::from_secs(60), || {
        cluster.status()["round"].as_u64() >= Some(1)
    });
    cluster.kill_worker(1);
    cluster.kill_worker(2);
    cluster.add_worker(&WorkerOpts::cache(largest));
    let ok = wait_child(&mut waiter, "the frame", Duration::from_secs(120));
    assert!(ok, "the frame failed after losing two workers");
    assert_eq!(hash_of(&json), local_hash(&scene, &frame));
    let reporting = stats_field(&json, "/workers").as_u64().unwrap_or(0);
    assert!(reporting <= 3, "the killed workers cannot have reported");
}

/// Counts the lines of `log` containing each of `needles`.
fn count_lines(log: &str, needles: &[&str]) -> Vec<usize> {
    needles
        .iter()
        .map(|n| log.lines().filter(|l| l.contains(n)).count())
        .collect()
}

#[test]
fn a_worker_killed_while_loading_tracing_or_sending_costs_time_not_the_image() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 60_000, 16);
    let (_, largest) = domain_bytes(&scene);
    let frame = MANY_ROUNDS;
    let expected = local_hash(&scene, &frame);
    let verbose =
        "info,rayfarm_core::render::cache=debug,rayfarm_worker=debug,rayfarm_machine::pass=debug";
    // Each kill point: how the victim runs so that it lingers there, and the log lines that
    // say it is there now (the first seen more often than the second).
    let points: [(&str, WorkerOpts, [&str; 2]); 3] = [
        (
            "loading a domain",
            WorkerOpts::cache(largest)
                .env("RUST_LOG", verbose)
                .arg("--storage-latency", "2s"),
            ["loading domain", "domain loaded"],
        ),
        (
            "tracing",
            WorkerOpts::cache(largest).env("RUST_LOG", verbose),
            ["tracing a queue", "queue traced"],
        ),
        (
            "with bundles in flight",
            WorkerOpts::cache(largest)
                .env("RUST_LOG", verbose)
                .env("RAYFARM_FAULT_DELAY_MS", "400")
                .env("RAYFARM_FAULT_SEED", "7"),
            ["bundle sent", "bundle acknowledged"],
        ),
    ];
    for (point, victim, [begun, ended]) in points {
        let mut workers = vec![WorkerOpts::cache(largest); 2];
        workers.push(victim);
        let mut cluster = Cluster::start(root.path(), Some("nb"), &workers);
        let json = cluster.dir().join("killed.json");
        let png = cluster.dir().join("killed.png");
        let mut waiter = spawn_submit_wait(&cluster, &frame, &[], &png, &json);
        wait_until(
            &format!("worker 2 {point}"),
            Duration::from_secs(60),
            || {
                let n = count_lines(&cluster.worker_log(2), &[begun, ended]);
                n[0] > n[1]
            },
        );
        cluster.kill_worker(2);
        let n = count_lines(&cluster.worker_log(2), &[begun, ended]);
        assert!(
            n[0] > n[1],
            "worker 2 was no longer {point} when killed: {n:?}"
        );
        let ok = wait_child(&mut waiter, "the frame", Duration::from_secs(120));
        assert!(ok, "the frame failed after a worker was killed {point}");
        assert_eq!(hash_of(&json), expected, "killed {point}");
        assert_eq!(stats_field(&json, "/workers"), 2, "killed {point}");
    }
}

#[test]
fn a_hung_worker_is_dropped_by_its_peers_and_rejoins_when_it_wakes() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 60_000, 16);
    let (_, largest) = domain_bytes(&scene);
    let frame = MANY_ROUNDS;
    let expected = local_hash(&scene, &frame);
    // The coordinator would wait two minutes for heartbeats: only the peers can notice.
    let worker = WorkerOpts::cache(largest).arg("--peer-ack-timeout-ms", "1000");
    let cluster = Cluster::start_with_env(
        root.path(),
        Some("nb"),
        &[("RAYFARM_WORKER_TIMEOUT_MS", "120000")],
        &vec![worker; 3],
    );
    let json = cluster.dir().join("hung.json");
    let png = cluster.dir().join("hung.png");
    // Under the domain schedule the hung worker owns domains for the whole frame, so its peers
    // keep sending it rays and must notice.
    let mut waiter = spawn_submit_wait(&cluster, &frame, &["--schedule", "domain"], &png, &json);
    wait_until("the frame to start", Duration::from_secs(60), || {
        frame_running(&cluster)
    });
    cluster.pause_worker(1);
    let ok = wait_child(&mut waiter, "the frame", Duration::from_secs(100));
    assert!(ok, "the frame failed with a hung worker");
    assert_eq!(hash_of(&json), expected, "with a hung worker");
    assert_eq!(stats_field(&json, "/workers"), 2);
    assert!(
        cluster.coordinator_log().contains("unresponsive to worker"),
        "the hung worker was not reported by a peer"
    );
    // Awake again, it finds its control stream closed, registers afresh and works.
    cluster.resume_worker(1);
    cluster.wait_for_workers(3, Duration::from_secs(60));
    let stats = submit_wait(&cluster, &frame, "after");
    assert_eq!(hash_of(&stats), expected, "after the hung worker came back");
    assert_eq!(stats_field(&stats, "/workers"), 3);
}
