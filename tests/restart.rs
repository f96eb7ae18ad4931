//! A coordinator that crashes and comes back on the same address and data directory keeps its
//! jobs: finished ones stay fetchable, queued ones stay queued in order, the frame that was
//! running starts over and renders the image of `rayfarm render --local` to the bit. The
//! workers reconnect by themselves, a client following the job rides out the outage, and a
//! client calling meanwhile is told the coordinator is UNAVAILABLE.

use std::fs::File;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use rayfarm_tests::{
    Cluster, START_TIMEOUT, WorkerOpts, bin, domain_bytes, hash_of, job, jobs, local_hash,
    prepare_nbody, s, wait_child, wait_until,
};

/// A small frame: a second or so.
const SMALL: [&str; 8] = [
    "--width", "96", "--height", "72", "--spp", "2", "--depth", "3",
];

/// A frame of many rounds on one-domain caches (several seconds), so a crash lands mid-frame.
const BIG: [&str; 8] = [
    "--width", "320", "--height", "240", "--spp", "16", "--depth", "3",
];

fn prepare(root: &Path, name: &str) -> PathBuf {
    prepare_nbody(root, name, 60_000, 16)
}

fn submit(cluster: &Cluster, frame: &[&str]) -> String {
    let mut args = vec!["submit"];
    args.extend_from_slice(frame);
    let out = cluster.rayfarm_ok(&args);
    String::from_utf8_lossy(&out.stdout).trim().to_string()
}

/// `rayfarm fetch` of a finished job; returns the hash of its statistics.
fn fetch(cluster: &Cluster, id: &str) -> String {
    let png = cluster.dir().join(format!("{id}.png"));
    let json = cluster.dir().join(format!("{id}.json"));
    cluster.rayfarm_ok(&["fetch", id, "-o", s(&png), "--stats-json", s(&json)]);
    hash_of(&json)
}

fn ms(job: &serde_json::Value, field: &str) -> i64 {
    job[field]
        .as_i64()
        .unwrap_or_else(|| panic!("{field} of {job}"))
}

/// Worker ids the coordinator lists, sorted.
fn worker_ids(cluster: &Cluster) -> Vec<String> {
    let status = cluster.status();
    let mut ids: Vec<String> = status["workers"]
        .as_array()
        .expect("workers")
        .iter()
        .map(|w| w["worker_id"].as_str().expect("worker id").to_string())
        .collect();
    ids.sort();
    ids
}

#[test]
fn restart_the_coordinator_mid_frame_queued_and_finished_jobs_survive() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare(root.path(), "nb");
    let small_hash = local_hash(&scene, &SMALL);
    let big_hash = local_hash(&scene, &BIG);
    let cache = domain_bytes(&scene).1;
    let mut cluster = Cluster::start(root.path(), Some("nb"), &vec![WorkerOpts::cache(cache); 2]);
    let workers_before = worker_ids(&cluster);

    // D and E finish before the crash; E's image will be lost from the disk meanwhile.
    let d = submit(&cluster, &SMALL);
    let e = submit(&cluster, &SMALL);
    cluster.rayfarm_ok(&["watch", &e, "--quiet"]);
    let d_hash = fetch(&cluster, &d);
    assert_eq!(d_hash, small_hash);

    // A runs, followed by a client that must ride out the crash; B and C wait behind it.
    let a_png = cluster.dir().join("a.png");
    let a_json = cluster.dir().join("a.json");
    let a_err = cluster.dir().join("a-client.stderr");
    let mut a_client = Command::new(bin("rayfarm"))
        .args(["submit", "--wait", "--quiet", "-o", s(&a_png)])
        .args(["--stats-json", s(&a_json)])
        .args(BIG)
        .env("RAYFARM_COORDINATOR", cluster.coordinator_url())
        .stdout(Stdio::null())
        .stderr(File::create(&a_err).expect("client stderr file"))
        .spawn()
        .expect("start rayfarm submit --wait");
    let mut a = String::new();
    wait_until(
        "job A to be a few rounds in",
        Duration::from_secs(60),
        || {
            let status = cluster.status();
            a = status["running_job_id"].as_str().unwrap_or("").to_string();
            !a.is_empty() && a != d && a != e && status["round"].as_u64() >= Some(3)
        },
    );
    let b = submit(&cluster, &SMALL);
    let c = submit(&cluster, &SMALL);
    let before = jobs(&cluster);
    assert_eq!(job(&before, &a)["state"], "running");
    assert_eq!(job(&before, &b)["state"], "queued");
    assert_eq!(job(&before, &c)["state"], "queued");
    let a_first_start = ms(job(&before, &a), "started_unix_ms");

    cluster.kill_coordinator();
    // Meanwhile a client is told plainly that the coordinator is not there.
    let out = cluster.rayfarm(&["jobs"]);
    assert!(!out.status.success(), "jobs succeeded with no coordinator");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("UNAVAILABLE")
            && stderr.contains("unreachable")
            && stderr.contains(cluster.coordinator_url()),
        "{stderr}"
    );
    let e_exr = cluster.data_dir().join("jobs").join(&e).join("image.exr");
    std::fs::remove_file(&e_exr).expect("remove E's image");
    assert!(cluster.data_dir().join("rayfarm.redb").is_file());

    cluster.restart_coordinator();
    let after = jobs(&cluster);
    assert_eq!(job(&after, &d)["state"], "succeeded");
    assert_eq!(job(&after, &b)["state"], "queued");
    assert_eq!(job(&after, &c)["state"], "queued");
    let a_state = job(&after, &a)["state"].clone();
    assert!(
        a_state == "queued" || a_state == "running",
        "A is {a_state}"
    );
    let lost = job(&after, &e);
    assert_eq!(lost["state"], "failed");
    let why = lost["error"].as_str().unwrap_or("");
    assert!(why.contains(s(&e_exr)) && why.contains("gone"), "{why}");
    // A finished job is fetchable from the restarted coordinator, with the same image.
    assert_eq!(fetch(&cluster, &d), d_hash);

    // The same worker processes come back by themselves.
    cluster.wait_for_workers(2, START_TIMEOUT);
    assert_eq!(worker_ids(&cluster), workers_before);

    // A starts over and ends with the image of the clean local render; its client followed
    // it through the restart.
    let ok = wait_child(&mut a_client, "the client of A", Duration::from_secs(300));
    let client_err = std::fs::read_to_string(&a_err).unwrap_or_default();
    assert!(ok, "submit --wait of A failed:\n{client_err}");
    assert!(
        client_err.contains("UNAVAILABLE") && client_err.contains("following job"),
        "the client did not say it reconnected:\n{client_err}"
    );
    assert_eq!(hash_of(&a_json), big_hash);

    for id in [&b, &c] {
        cluster.rayfarm_ok(&["watch", id, "--quiet"]);
        assert_eq!(fetch(&cluster, id), small_hash, "job {id}");
    }
    let end = jobs(&cluster);
    for id in [&a, &b, &c, &d] {
        assert_eq!(job(&end, id)["state"], "succeeded", "job {id}");
    }
    let (a, b, c) = (job(&end, &a), job(&end, &b), job(&end, &c));
    assert!(
        ms(a, "started_unix_ms") > a_first_start,
        "A's frame did not start again"
    );
    assert!(ms(a, "started_unix_ms") <= ms(b, "started_unix_ms"));
    assert!(ms(b, "started_unix_ms") <= ms(c, "started_unix_ms"));
    assert!(ms(b, "finished_unix_ms") <= ms(c, "finished_unix_ms"));
}

#[test]
fn a_damaged_job_database_stops_the_coordinator_naming_the_file() {
    let dir = tempfile::tempdir().expect("temp dir");
    let db = dir.path().join("rayfarm.redb");
    let junk = b"not a job database\n".repeat(300);
    std::fs::write(&db, &junk).expect("write junk");
    let out = Command::new(bin("rayfarm-coordinator"))
        .args(["--listen", "127.0.0.1:0", "--data-dir", s(dir.path())])
        .env("RUST_LOG", "warn")
        .output()
        .expect("run the coordinator");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "the coordinator started:\n{stderr}");
    assert!(
        stderr.contains(s(&db)) && stderr.contains("cannot be opened"),
        "{stderr}"
    );
    assert!(
        !String::from_utf8_lossy(&out.stdout).contains("listening on"),
        "it listened before refusing"
    );
    assert_eq!(
        std::fs::read(&db).expect("read"),
        junk,
        "the file was changed"
    );
}

#[test]
fn a_job_whose_frame_kills_the_coordinator_three_times_fails_and_the_queue_moves_on() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare(root.path(), "nb");
    let small_hash = local_hash(&scene, &SMALL);
    let cache = domain_bytes(&scene).1;
    let mut cluster = Cluster::start(root.path(), Some("nb"), &vec![WorkerOpts::cache(cache); 2]);
    let done = submit(&cluster, &SMALL);
    cluster.rayfarm_ok(&["watch", &done, "--quiet"]);

    // P stands for a job that brings the coordinator down whenever its frame runs.
    let p = submit(&cluster, &BIG);
    let q = submit(&cluster, &SMALL);
    for attempt in 1..=3 {
        wait_until(
            &format!("P's frame to start ({attempt})"),
            Duration::from_secs(120),
            || cluster.status()["running_job_id"] == p.as_str(),
        );
        cluster.kill_coordinator();
        cluster.restart_coordinator();
    }
    // The third restart does not start P again: it fails, and Q renders as it would have.
    cluster.rayfarm_ok(&["watch", &q, "--quiet"]);
    assert_eq!(fetch(&cluster, &q), small_hash);
    let end = jobs(&cluster);
    let failed = job(&end, &p);
    assert_eq!(failed["state"], "failed");
    let why = failed["error"].as_str().unwrap_or("");
    assert!(
        why.contains("started 3 times") && why.contains("--max-attempts is 3"),
        "{why}"
    );
    // Nothing else is lost.
    assert_eq!(job(&end, &q)["state"], "succeeded");
    assert_eq!(fetch(&cluster, &done), small_hash);
}
