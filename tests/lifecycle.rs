//! How processes stop. A coordinator with workers attached stops within seconds of SIGTERM
//! or SIGINT (what systemd, docker and Kubernetes send), releases its job database so a
//! successor starts on the same data directory at once, and that successor finishes the
//! interrupted job with the image of `render --local`. `rayfarm demo` and `rayfarm bench`
//! take their local cluster down with them on SIGTERM and SIGHUP (and, on Linux, even on
//! SIGKILL), and bench leaves no temporary directory behind.

use std::path::{Path, PathBuf};
use std::process::Child;
use std::time::Duration;

use rayfarm_tests::{
    Cluster, START_TIMEOUT, WorkerOpts, job, jobs, local_hash, prepare_nbody, s, signal_pid,
    spawn_rayfarm, wait_line, wait_until,
};

/// A frame of a few seconds on two workers, so a signal lands mid-frame.
const LONG: [&str; 8] = [
    "--width", "256", "--height", "192", "--spp", "32", "--depth", "3",
];

/// What "stops promptly" means.
const STOP_WITHIN: Duration = Duration::from_secs(5);

#[test]
fn a_coordinator_with_workers_attached_stops_on_sigterm_and_sigint_and_a_successor_finishes_the_job()
 {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 20_000, 4);
    let expected = local_hash(&scene, &LONG);
    let mut cluster = Cluster::start(root.path(), Some("nb"), &vec![WorkerOpts::default(); 2]);
    let mut args = vec!["submit"];
    args.extend_from_slice(&LONG);
    let out = cluster.rayfarm_ok(&args);
    let id = String::from_utf8_lossy(&out.stdout).trim().to_string();
    wait_until("the job running", START_TIMEOUT, || {
        job(&jobs(&cluster), &id)["state"] == "running"
    });

    for signal in ["-TERM", "-INT"] {
        let (status, took) = cluster.stop_coordinator(signal, STOP_WITHIN);
        assert!(
            status.success(),
            "kill {signal}: the coordinator ended with {status}"
        );
        assert!(took < STOP_WITHIN, "kill {signal}: took {took:?}");
        // The same data directory: the database was released, the job kept.
        cluster.restart_coordinator();
        let log = cluster.coordinator_log();
        assert!(!log.contains("in use by another process"), "{log}");
        cluster.wait_for_workers(2, START_TIMEOUT);
    }
    let json = cluster.dir().join("after.json");
    let png = cluster.dir().join("after.png");
    cluster.rayfarm_ok(&["watch", &id, "--quiet"]);
    cluster.rayfarm_ok(&["fetch", &id, "-o", s(&png), "--stats-json", s(&json)]);
    assert_eq!(rayfarm_tests::hash_of(&json), expected);
}

/// Processes whose command line mentions `marker` (a test's own temporary path), but not
/// `except`.
fn processes_mentioning(marker: &Path, except: u32) -> Vec<String> {
    let marker = marker.to_string_lossy().into_owned();
    let mut found = Vec::new();
    for entry in std::fs::read_dir("/proc").expect("/proc").flatten() {
        let Ok(pid) = entry.file_name().to_string_lossy().parse::<u32>() else {
            continue;
        };
        if pid == except {
            continue;
        }
        let Ok(cmdline) = std::fs::read(entry.path().join("cmdline")) else {
            continue;
        };
        let cmdline = String::from_utf8_lossy(&cmdline).replace('\0', " ");
        if cmdline.contains(&marker) {
            found.push(format!("{pid}: {cmdline}"));
        }
    }
    found
}

/// Waits up to `timeout` for `child` to exit; its status.
fn wait_exit(child: &mut Child, timeout: Duration) -> std::process::ExitStatus {
    let start = std::time::Instant::now();
    loop {
        if let Some(status) = child.try_wait().expect("poll child") {
            return status;
        }
        if start.elapsed() > timeout {
            let _ = child.kill();
            panic!("rayfarm did not exit within {timeout:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Entries of `dir` whose names start with `prefix`.
fn entries(dir: &Path, prefix: &str) -> Vec<PathBuf> {
    std::fs::read_dir(dir)
        .map(|d| {
            d.flatten()
                .map(|e| e.path())
                .filter(|p| {
                    p.file_name()
                        .is_some_and(|n| n.to_string_lossy().starts_with(prefix))
                })
                .collect()
        })
        .unwrap_or_default()
}

#[test]
fn demo_stopped_by_sigterm_sighup_or_sigkill_leaves_no_process_behind() {
    let root = tempfile::tempdir().expect("temp dir");
    let dir = root.path().join("demo");
    let demo = [
        "demo",
        "--dir",
        s(&dir),
        "--triangles",
        "20000",
        "--domains",
        "4",
        "--workers",
        "2",
        "--width",
        "320",
        "--height",
        "240",
        "--spp",
        "256",
    ];
    for signal in ["-TERM", "-HUP", "-KILL"] {
        let (mut child, lines) = spawn_rayfarm(&demo, &[]);
        wait_line(&lines, "submitted");
        signal_pid(child.id(), signal);
        let status = wait_exit(&mut child, Duration::from_secs(15));
        assert!(
            !status.success(),
            "kill {signal}: the demo should not report success"
        );
        if signal != "-KILL" {
            // It stopped its cluster itself (and said why) before exiting.
            // The stderr reader ends with the demo's stderr.
            let rest: Vec<String> = lines.iter().collect();
            let rest = rest.join("\n");
            assert!(
                rest.contains("interrupted by SIG"),
                "kill {signal}:\n{rest}"
            );
        }
        wait_until(
            &format!("the cluster's processes gone after kill {signal}"),
            STOP_WITHIN,
            || processes_mentioning(&dir, child.id()).is_empty(),
        );
        // Nothing half-written: the image of an interrupted demo is not there, nor any
        // staging directory of prepare.
        assert!(!dir.join("demo.png").exists());
        assert!(entries(&dir, ".").is_empty(), "{:?}", entries(&dir, "."));
    }
}

#[test]
fn bench_stopped_by_sigterm_leaves_no_process_and_no_temporary_directory() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 20_000, 4);
    let tmp = root.path().join("tmp");
    std::fs::create_dir(&tmp).expect("tmp dir");
    let (mut child, lines) = spawn_rayfarm(
        &[
            "bench",
            "--scene",
            s(&scene),
            "--workers",
            "2",
            "--schedules",
            "dynamic",
            "--repeats",
            "1",
            "--width",
            "320",
            "--height",
            "240",
            "--spp",
            "256",
        ],
        &[("TMPDIR", s(&tmp))],
    );
    wait_line(&lines, "starting a local cluster");
    // The coordinator names the temporary directory, the workers the scene's root.
    wait_until("the bench's cluster", START_TIMEOUT, || {
        processes_mentioning(root.path(), child.id()).len() >= 3
    });
    signal_pid(child.id(), "-TERM");
    let status = wait_exit(&mut child, Duration::from_secs(15));
    assert!(!status.success(), "the bench should not report success");
    wait_until("the bench's processes gone", STOP_WITHIN, || {
        processes_mentioning(root.path(), child.id()).is_empty()
    });
    assert!(
        entries(&tmp, "rayfarm-bench-").is_empty(),
        "{:?}",
        entries(&tmp, "")
    );
}

#[test]
fn a_prepare_killed_mid_write_leaves_its_staging_directory_to_the_next_prepare_of_that_scene() {
    let root = tempfile::tempdir().expect("temp dir");
    let out = root.path().join("big");
    // Large enough to still be writing when the kill lands.
    let (mut child, _lines) = spawn_rayfarm(
        &[
            "prepare",
            "--generate",
            "nbody",
            "--triangles",
            "1000000",
            "--domains",
            "64",
            "--out",
            s(&out),
        ],
        &[],
    );
    wait_until("prepare's staging directory", START_TIMEOUT, || {
        !entries(root.path(), ".big.staging-").is_empty()
    });
    signal_pid(child.id(), "-KILL");
    wait_exit(&mut child, STOP_WITHIN);
    let abandoned = entries(root.path(), ".big.staging-");
    assert_eq!(abandoned.len(), 1, "{abandoned:?}");
    // A staging directory of a live process (a concurrent prepare) and a symlink named like an
    // abandoned one stay.
    let live = root
        .path()
        .join(format!(".big.staging-{}", std::process::id()));
    std::fs::create_dir(&live).expect("live staging dir");
    let target = root.path().join("kept");
    std::fs::create_dir(&target).expect("kept dir");
    let link = root.path().join(".big.staging-999999999");
    std::os::unix::fs::symlink(&target, &link).expect("symlink");

    prepare_nbody(root.path(), "big", 20_000, 4);
    assert!(!abandoned[0].exists(), "{:?} still there", abandoned[0]);
    assert!(live.is_dir());
    assert!(link.symlink_metadata().is_ok() && target.is_dir());
    assert!(out.join("scene.toml").is_file());
}
