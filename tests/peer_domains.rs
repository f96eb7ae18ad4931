//! Domains from peers on a real cluster: workers on slow emulated storage, rendering a job
//! that loads domains from peers (`submit --peer-domains`), take domains from each other and
//! still render the image of `rayfarm render --local`; a serving worker killed mid-transfer,
//! and a worker that serves bad bytes, oversized files or stalls, cost time, not the image:
//! the loads fall back to storage.

use std::time::Duration;

use rayfarm_tests::{
    Cluster, WorkerOpts, domain_bytes, hash_of, http_get, local_hash, prepare_nbody, s,
    stats_field, submit_wait, wait_until,
};

/// A frame of many rounds, so that domains change hands between workers.
const FRAME: [&str; 8] = [
    "--width", "160", "--height", "120", "--spp", "4", "--depth", "3",
];

/// Frames a test renders, each the local image, until the plans made the event it needs
/// happen (a load from a peer, worker 0 asked for a domain it holds). The plans decide who
/// asks whom, and most asks find the domain gone (a load asks the domain's former holders
/// too, which have mostly evicted it): over 20 frames of this scene at 8 MiB/s, one frame in
/// ten took no bytes from peers and one in four asked worker 0 for nothing it held; at
/// 1 MiB/s, 6 frames of 12. Sixteen frames all missing: about 1 in 65,000 at the worst rate.
const ATTEMPTS: usize = 16;

/// Slow enough storage that a peer on loopback is cheaper, fast enough for a quick test.
const STORAGE: &str = "8MiB/s";

/// Workers with caches of about three domains on storage of `storage` bandwidth, worker `i`
/// with the variables `env` names for it.
fn workers(largest: u64, n: usize, storage: &str, env: &[(usize, &str, &str)]) -> Vec<WorkerOpts> {
    (0..n)
        .map(|i| {
            let mut w = WorkerOpts::cache(largest * 3)
                .threads(1)
                .arg("--storage-bandwidth", storage)
                .env(
                    "RUST_LOG",
                    "info,rayfarm_worker::domains=debug,rayfarm_core::render::cache=debug",
                );
            for (_, k, v) in env.iter().filter(|(j, _, _)| *j == i) {
                w = w.env(k, v);
            }
            w
        })
        .collect()
}

/// `submit --wait` of `FRAME` loading domains from peers, under `schedule`.
fn render(cluster: &Cluster, schedule: &str, tag: &str) -> std::path::PathBuf {
    let mut frame = vec!["--peer-domains", "--cold-cache", "--schedule", schedule];
    frame.extend_from_slice(&FRAME);
    submit_wait(cluster, &frame, tag)
}

fn counter(json: &std::path::Path, name: &str) -> u64 {
    stats_field(json, &format!("/cache/{name}"))
        .as_u64()
        .unwrap_or_else(|| panic!("{name} is not a number"))
}

#[test]
fn peers_serve_domains_and_the_image_is_the_local_one() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 60_000, 16);
    let (_, largest) = domain_bytes(&scene);
    let expected = local_hash(&scene, &FRAME);
    let opts: Vec<WorkerOpts> = workers(largest, 3, STORAGE, &[])
        .into_iter()
        .map(|w| w.arg("--http", "127.0.0.1:0"))
        .collect();
    let cluster = Cluster::start(root.path(), Some("nb"), &opts);
    // Dynamic rounds give dry workers copies of the domains other workers hold (the
    // predictive schedule's plans rarely do here: its loads find no holder), but a frame's
    // peer loads are few (20 frames: 0-5 of 86-109 loads, 27-53 refusals). Frames, no peer
    // failing, until one took bytes from peers.
    let (mut arrived, mut last) = (0, String::new());
    for attempt in 0..ATTEMPTS {
        let json = render(&cluster, "dynamic", &format!("dynamic-{attempt}"));
        assert_eq!(hash_of(&json), expected, "attempt {attempt}");
        assert_eq!(counter(&json, "peer_failures"), 0, "attempt {attempt}");
        let (from_peers, loaded) = (
            counter(&json, "bytes_from_peers"),
            counter(&json, "bytes_loaded"),
        );
        assert!(
            from_peers < loaded,
            "{from_peers} of {loaded} bytes from peers"
        );
        arrived += from_peers;
        last = stats_field(&json, "/cache").to_string();
        if from_peers > 0 {
            break;
        }
    }
    assert!(
        arrived > 0,
        "no bytes from peers in {ATTEMPTS} frames, the last's cache: {last}"
    );
    // The same frame without the option loads everything from storage.
    let json = submit_wait(
        &cluster,
        &[&["--cold-cache", "--schedule", "dynamic"][..], &FRAME].concat(),
        "off",
    );
    assert_eq!(hash_of(&json), expected);
    assert_eq!(counter(&json, "bytes_from_peers"), 0);
    // Served bytes are counted where they left (a transfer the requester gave up on after
    // its last chunk counts there only, so at least as many as arrived).
    let served: u64 = (0..3)
        .map(|i| {
            let addr = cluster.worker_http(i).expect("worker --http");
            let metrics = http_get(addr, "/metrics");
            metrics
                .lines()
                .find_map(|l| l.strip_prefix("rayfarm_domain_served_bytes_total "))
                .and_then(|v| v.trim().parse::<f64>().ok())
                .unwrap_or_else(|| panic!("no served bytes in {metrics}")) as u64
        })
        .sum();
    assert!(
        served >= arrived,
        "{served} bytes served, {arrived} arrived"
    );
}

#[test]
fn a_serving_peer_killed_mid_transfer_costs_a_load_from_storage_not_the_image() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 60_000, 16);
    let (_, largest) = domain_bytes(&scene);
    let expected = local_hash(&scene, &FRAME);
    // Worker 0 serves slowly (a chunk every 300 ms), so a transfer from it lasts long enough
    // to be cut by its death; storage is slow enough that peers are still worth asking.
    let opts = workers(
        largest,
        3,
        "1MiB/s",
        &[(0, "RAYFARM_FAULT_SERVE_DOMAINS", "slow")],
    );
    let mut cluster = Cluster::start(root.path(), Some("nb"), &opts);
    // Whether anyone asks worker 0 depends on the plans: frames, each the local image, until
    // worker 0 is serving a domain while one runs; then it is killed there.
    let mut json = None;
    for attempt in 0..ATTEMPTS {
        let stats = cluster.dir().join(format!("killed-{attempt}.json"));
        let png = cluster.dir().join(format!("killed-{attempt}.png"));
        let mut waiter = std::process::Command::new(rayfarm_tests::bin("rayfarm"))
            .args([
                "submit",
                "--wait",
                "--quiet",
                "-o",
                s(&png),
                "--stats-json",
                s(&stats),
            ])
            .args(["--peer-domains", "--cold-cache", "--schedule", "dynamic"])
            .args(FRAME)
            .env("RAYFARM_COORDINATOR", cluster.coordinator_url())
            .stdout(std::process::Stdio::null())
            .spawn()
            .expect("start rayfarm submit");
        let serving = || cluster.worker_log(0).contains("serving a domain to a peer");
        let mut ended = false;
        wait_until(
            "worker 0 serving or the frame's end",
            Duration::from_secs(120),
            || {
                ended = waiter.try_wait().ok().flatten().is_some();
                ended || serving()
            },
        );
        if !ended && serving() {
            cluster.kill_worker(0);
            let ok = rayfarm_tests::wait_child(&mut waiter, "the frame", Duration::from_secs(180));
            assert!(ok, "the frame failed after its serving peer was killed");
            assert_eq!(hash_of(&stats), expected);
            json = Some(stats);
            break;
        }
        assert!(rayfarm_tests::wait_child(
            &mut waiter,
            "the frame",
            Duration::from_secs(10)
        ));
        assert_eq!(hash_of(&stats), expected, "attempt {attempt}");
    }
    let json =
        json.unwrap_or_else(|| panic!("worker 0 never served a domain in {ATTEMPTS} frames"));
    // A survivor saw its transfer break and loaded from storage instead.
    let fell_back = (1..3).any(|i| {
        cluster
            .worker_log(i)
            .contains("loading a domain from a peer failed: from storage instead")
    });
    assert!(fell_back, "no worker fell back to storage");
    assert!(counter(&json, "peer_failures") > 0);
}

#[test]
fn a_hostile_peer_is_refused_and_the_load_goes_to_storage() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 60_000, 16);
    let (_, largest) = domain_bytes(&scene);
    let expected = local_hash(&scene, &FRAME);
    // What a requester's log says when it refuses each kind of bad peer.
    for (fault, refusal) in [
        ("corrupt", "corrupt file"),
        ("oversize", "the manifest says"),
        ("slow", "a stalled peer"),
    ] {
        let opts = workers(
            largest,
            3,
            STORAGE,
            &[(0, "RAYFARM_FAULT_SERVE_DOMAINS", fault)],
        );
        let cluster = Cluster::start(root.path(), Some("nb"), &opts);
        let bad = format!("peer={}", cluster.worker_addr(0));
        // Which worker asks worker 0 for a domain depends on the plans: a few frames, each
        // the local image, until one did.
        let mut seen = false;
        for attempt in 0..ATTEMPTS {
            let json = render(&cluster, "dynamic", &format!("{fault}-{attempt}"));
            assert_eq!(hash_of(&json), expected, "{fault}");
            let logs = [cluster.worker_log(1), cluster.worker_log(2)];
            let lines = || logs.iter().flat_map(|l| l.lines());
            // Nothing from the bad peer was ever kept.
            let kept: Vec<&str> = lines()
                .filter(|l| l.contains("domain fetched from a peer") && l.contains(&bad))
                .collect();
            assert!(
                kept.is_empty(),
                "{fault}: kept a bad peer's domain: {kept:?}"
            );
            let refused: Vec<&str> = lines()
                .filter(|l| l.contains("loading a domain from a peer failed"))
                .collect();
            assert!(
                refused.iter().all(|l| l.contains(&bad)),
                "{fault}: a good peer failed: {refused:?}"
            );
            if refused.iter().any(|l| l.contains(refusal)) {
                assert!(counter(&json, "peer_failures") > 0, "{fault}");
                seen = true;
                break;
            }
        }
        assert!(
            seen,
            "{fault}: no worker refused the bad peer for {refusal:?}"
        );
    }
}
