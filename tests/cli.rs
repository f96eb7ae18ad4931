//! What a newcomer types, and what they should see (issue 14): each check runs the real
//! `rayfarm` against a real cluster or real files and reads what a person would read.

use std::process::Command;
use std::time::{Duration, Instant};

use rayfarm_tests::{
    Cluster, START_TIMEOUT, WorkerOpts, bin, hash_of, job, jobs, local_hash, prepare_nbody,
    rayfarm_err, rayfarm_ok, s, signal_pid, stats_field, wait_line,
};

/// A frame of well under a second.
const SMALL: [&str; 8] = [
    "--width", "64", "--height", "48", "--spp", "1", "--depth", "2",
];

fn stderr_of(out: &std::process::Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn cluster_commands_say_what_happens_and_what_to_do() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 20_000, 4);
    // No workers yet.
    let mut cluster = Cluster::start(root.path(), Some("nb"), &[]);
    let url = cluster.coordinator_url().to_string();

    // A job with nobody to render it: the job id at once, a warning that no worker is
    // attached, and on Ctrl-C what became of the job.
    let mut args = vec!["submit", "--wait", "--coordinator", &url];
    args.extend_from_slice(&SMALL);
    let mut waiter = Command::new(bin("rayfarm"))
        .args(&args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("start submit --wait");
    let stderr = waiter.stderr.take().expect("stderr");
    let (tx, lines) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        use std::io::BufRead;
        for l in std::io::BufReader::new(stderr)
            .lines()
            .map_while(Result::ok)
        {
            let _ = tx.send(l);
        }
    });
    wait_line(&lines, "no worker is attached");
    signal_pid(waiter.id(), "-INT");
    let out = waiter.wait_with_output().expect("submit --wait output");
    assert!(!out.status.success());
    let stdout = String::from_utf8_lossy(&out.stdout);
    let id = stdout
        .lines()
        .next()
        .and_then(|l| l.strip_prefix("job "))
        .unwrap_or_else(|| panic!("no job id first on stdout: {stdout}"))
        .to_string();
    let rest: Vec<String> = lines.iter().collect();
    let rest = rest.join("\n");
    for words in [
        "goes on",
        &format!("rayfarm cancel {id}"),
        &format!("rayfarm fetch {id}"),
    ] {
        assert!(rest.contains(words), "{words:?} not in:\n{rest}");
    }

    // Two workers: waiting for one returns at once.
    cluster.add_worker(&WorkerOpts::default());
    cluster.add_worker(&WorkerOpts::default());
    cluster.wait_for_workers(2, START_TIMEOUT);
    let start = Instant::now();
    cluster.rayfarm_ok(&["status", "--wait-workers", "1", "--timeout", "20"]);
    assert!(start.elapsed() < Duration::from_secs(10));

    // The job Ctrl-C left behind went on and finished; cancelling it now is an error.
    cluster.rayfarm_ok(&["watch", &id, "--quiet"]);
    let out = cluster.rayfarm(&["cancel", &id]);
    assert!(!out.status.success());
    assert!(
        stderr_of(&out).contains("had already succeeded"),
        "{}",
        stderr_of(&out)
    );

    // `jobs --json | head -1` ends quietly.
    let piped = Command::new("sh")
        .arg("-c")
        .arg(format!(
            "'{}' jobs --json | head -1",
            bin("rayfarm").display()
        ))
        .env("RAYFARM_COORDINATOR", &url)
        .output()
        .expect("sh");
    assert!(piped.status.success(), "{}", stderr_of(&piped));
    assert!(
        !stderr_of(&piped).contains("panicked"),
        "{}",
        stderr_of(&piped)
    );
    assert_eq!(String::from_utf8_lossy(&piped.stdout).trim(), "[");
    // The same with a reader that is gone before the first line: deterministic EPIPE.
    let mut early = Command::new(bin("rayfarm"))
        .args(["jobs", "--json"])
        .env("RAYFARM_COORDINATOR", &url)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("start jobs");
    drop(early.stdout.take());
    let out = early.wait_with_output().expect("jobs output");
    assert!(out.status.success(), "{}: {}", out.status, stderr_of(&out));
    assert!(stderr_of(&out).is_empty(), "{}", stderr_of(&out));

    // An output that cannot be written is refused before anything is queued.
    let before = jobs(&cluster).len();
    let nodir = root.path().join("nodir/x.png");
    let out = cluster.rayfarm(&["submit", "--wait", "-o", s(&nodir)]);
    assert!(
        stderr_of(&out).contains("does not exist"),
        "{}",
        stderr_of(&out)
    );
    assert_eq!(jobs(&cluster).len(), before);

    // One camera check: flags refused as they are parsed, a camera that needs the scene's
    // view refused by the coordinator, and a good --up renders the same on both paths.
    for (flags, words) in [
        (&["--fov", "0"][..], "outside (0, 180)"),
        (&["--up", "0,0,0"], "no direction"),
        (&["--up", "0,-0.32,-2.4"], "along the view"),
    ] {
        let mut args = vec!["submit"];
        args.extend_from_slice(flags);
        let out = cluster.rayfarm(&args);
        assert!(!out.status.success(), "{flags:?} was accepted");
        assert!(
            stderr_of(&out).contains(words),
            "{flags:?}: {}",
            stderr_of(&out)
        );
    }
    let mut frame = SMALL.to_vec();
    frame.extend(["--up", "1,0,0"]);
    let sideways = local_hash(&scene, &frame);
    assert_ne!(sideways, local_hash(&scene, &SMALL), "--up changed nothing");
    let json = root.path().join("up.json");
    let png = root.path().join("up.png");
    let mut args = vec![
        "submit",
        "--wait",
        "--quiet",
        "-o",
        s(&png),
        "--stats-json",
        s(&json),
    ];
    args.extend_from_slice(&frame);
    cluster.rayfarm_ok(&args);
    assert_eq!(hash_of(&json), sideways);

    // Boolean environment twins take 1.
    let out = cluster.rayfarm_as(
        &[("RAYFARM_COORDINATOR", &url), ("RAYFARM_COLD_CACHE", "1")],
        &["submit", "--width", "32", "--height", "32", "--spp", "1"],
    );
    assert!(out.status.success(), "{}", stderr_of(&out));
    let cold = String::from_utf8_lossy(&out.stdout).trim().to_string();
    assert_eq!(job(&jobs(&cluster), &cold)["cold_cache"], true);

    // A worker's port is not a coordinator, and the error says so.
    let worker = format!("http://{}", cluster.worker_addr(0));
    let out = cluster.rayfarm(&["jobs", "--coordinator", &worker]);
    assert!(
        stderr_of(&out).contains("a rayfarm coordinator?"),
        "{}",
        stderr_of(&out)
    );

    // A coordinator restarted in plain text is not mistaken for one that wants TLS.
    cluster.kill_coordinator();
    cluster.restart_coordinator();
    cluster.wait_for_workers(2, START_TIMEOUT);
    let log = cluster.worker_log(0);
    assert!(!log.contains("give --tls-ca"), "{log}");
}

#[test]
fn local_commands_check_their_limits_and_name_what_to_fix() {
    let tmp = tempfile::tempdir().expect("temp dir");
    let dir = tmp.path();
    let missing = dir.join("missing.ply");
    let empty = dir.join("empty.obj");
    std::fs::write(&empty, "").expect("empty obj");
    let raw = dir.join("ct.raw");
    std::fs::write(&raw, [0u8; 8]).expect("raw");
    let bare = dir.join("bare");
    std::fs::create_dir(&bare).expect("bare dir");
    let out = |name: &str| dir.join(name);

    let e = rayfarm_err(&["prepare", s(&missing), "--out", s(&out("a"))]);
    assert_eq!(e.matches("os error 2").count(), 1, "{e}");
    let e = rayfarm_err(&["prepare", s(&empty), "--out", s(&out("b"))]);
    assert!(e.contains("empty.obj") && e.contains("no triangles"), "{e}");
    let e = rayfarm_err(&["prepare", s(&raw), "--out", s(&out("c"))]);
    assert!(e.contains("--dims"), "{e}");
    let e = rayfarm_err(&["render", "--local", "--scene", s(&bare)]);
    assert!(e.contains("rayfarm prepare"), "{e}");
    let e = rayfarm_err(&["health", "127.0.0.1:1"]);
    assert_eq!(e.matches("tcp connect error").count(), 1, "{e}");
    for domains in ["0", "70000"] {
        let e = rayfarm_err(&[
            "prepare",
            "--generate",
            "nbody",
            "--triangles",
            "1000",
            "--domains",
            domains,
            "--out",
            s(&out("d")),
        ]);
        assert!(e.contains("1..=65536"), "{domains}: {e}");
    }
    let one = rayfarm_ok(&[
        "prepare",
        "--generate",
        "nbody",
        "--triangles",
        "1000",
        "--domains",
        "1",
        "--out",
        s(&out("one")),
    ]);
    let text = String::from_utf8_lossy(&one.stdout);
    assert!(
        text.contains("in 1 domain,") && text.contains("MiB ("),
        "{text}"
    );

    // RAYFARM_WIDTH and friends work for render as for submit.
    let json = out("env.json");
    let rendered = Command::new(bin("rayfarm"))
        .args(["render", "--local", "--scene", s(&out("one")), "--quiet"])
        .args(["--out", s(&out("env.png")), "--stats-json", s(&json)])
        .envs([
            ("RAYFARM_WIDTH", "40"),
            ("RAYFARM_HEIGHT", "30"),
            ("RAYFARM_SPP", "1"),
        ])
        .output()
        .expect("render");
    assert!(rendered.status.success(), "{}", stderr_of(&rendered));
    assert_eq!(stats_field(&json, "/width"), 40);
    assert_eq!(stats_field(&json, "/height"), 30);
}

#[test]
fn bench_api_loads_a_local_cluster_and_reports_every_call() {
    let dir = tempfile::tempdir().expect("temp dir");
    let csv = dir.path().join("api.csv");
    let out = rayfarm_ok(&[
        "bench-api",
        "--dir",
        s(dir.path()),
        "--clients",
        "6",
        "--rounds",
        "2",
        "--fill",
        "100",
        "--csv",
        s(&csv),
    ]);
    let table = String::from_utf8_lossy(&out.stdout);
    let csv = std::fs::read_to_string(&csv).expect("the CSV");
    for call in ["SubmitJob", "WatchJob", "ListJobs", "FetchResultStream"] {
        assert!(table.contains(call), "{table}");
        // Six clients, two jobs each: twelve calls of every kind.
        let row = csv
            .lines()
            .find(|l| l.starts_with(call))
            .unwrap_or_else(|| panic!("no {call} row in {csv}"));
        assert_eq!(row.split(',').nth(1), Some("12"), "{row}");
    }
}
