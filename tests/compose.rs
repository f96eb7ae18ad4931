//! The docker-compose cluster of `deploy/`, built from scratch (no registry) and driven from
//! the host's `rayfarm` CLI: its image equals `render --local`'s; then a worker container is
//! killed mid-frame, and another is taken off the compose network mid-frame past the worker
//! timeout and put back (`docker network disconnect`/`connect`); the test reports what the
//! cluster did, and the next job runs on every worker left. Security is on as the compose
//! file ships it (mutual TLS, a certificate of its own for each worker, bound to its id and
//! peer host): the host CLI takes the CA, a client certificate and the user token out of the
//! cluster's `secrets` volume, and without the token it is refused. Skipped, saying so, where no Docker engine or
//! compose tool is present.

use std::path::Path;
use std::process::{Command, Output};
use std::time::{Duration, Instant};

use rayfarm_tests::{bin, rayfarm_ok, repo_root, s, stats_field};

/// `docker compose` (v2) or `docker-compose` (v1), whichever works here.
fn compose_tool() -> Option<Vec<String>> {
    let works = |cmd: &[&str]| {
        Command::new(cmd[0])
            .args(&cmd[1..])
            .output()
            .is_ok_and(|o| o.status.success())
    };
    if !works(&["docker", "info"]) {
        return None;
    }
    if works(&["docker", "compose", "version"]) {
        Some(vec!["docker".into(), "compose".into()])
    } else if works(&["docker-compose", "version"]) {
        Some(vec!["docker-compose".into()])
    } else {
        None
    }
}

/// A compose project that is taken down, volumes and all, whatever happens to the test.
struct Project {
    tool: Vec<String>,
    name: String,
    env: Vec<(&'static str, String)>,
}

impl Project {
    fn run(&self, args: &[&str]) -> Output {
        let file = repo_root().join("deploy/docker-compose.yml");
        Command::new(&self.tool[0])
            .args(&self.tool[1..])
            .args(["-p", &self.name, "-f", s(&file)])
            .args(args)
            .envs(self.env.iter().map(|(k, v)| (k, v)))
            .output()
            .expect("run compose")
    }

    fn ok(&self, args: &[&str]) -> String {
        let out = self.run(args);
        assert!(
            out.status.success(),
            "compose {} failed:\n{}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    }
}

impl Drop for Project {
    fn drop(&mut self) {
        if std::thread::panicking() {
            let logs = self.run(&["logs", "--tail", "30"]);
            eprintln!("{}", String::from_utf8_lossy(&logs.stdout));
        }
        self.run(&["down", "-v", "--remove-orphans"]);
    }
}

fn hash_of(stats: &Path) -> String {
    stats_field(stats, "/image_hash")
        .as_str()
        .expect("hash")
        .to_string()
}

/// The frame during which a worker container is killed: a few seconds of work.
const SECOND: [&str; 8] = [
    "--width", "320", "--height", "240", "--spp", "16", "--depth", "3",
];

#[test]
fn the_compose_cluster_renders_the_local_image_even_when_a_worker_is_killed() {
    let Some(tool) = compose_tool() else {
        eprintln!("SKIPPED: no Docker engine with a compose tool here");
        return;
    };
    let tag = "rayfarm:compose-test";
    // The binaries under test, as built: a cargo build from inside `cargo test` sees another
    // environment and rebuilt the workspace (minutes of CI).
    let binaries = bin("rayfarm");
    let built = Command::new(repo_root().join("deploy/build-image.sh"))
        .arg(tag)
        .env(
            "RAYFARM_BINARIES",
            binaries.parent().expect("the binaries' directory"),
        )
        .output()
        .expect("run deploy/build-image.sh");
    assert!(
        built.status.success(),
        "building the image failed:\n{}",
        String::from_utf8_lossy(&built.stderr)
    );
    let project = Project {
        tool,
        name: format!("rayfarm-test-{}", std::process::id()),
        env: vec![
            ("RAYFARM_IMAGE", tag.to_string()),
            ("RAYFARM_PORT", "0".to_string()),
            ("RAYFARM_HTTP_PORT", "0".to_string()),
            ("RAYFARM_TRIANGLES", "60000".to_string()),
            ("RAYFARM_DOMAINS", "8".to_string()),
            // Small caches: workers must send each other rays across the compose network.
            ("RAYFARM_CACHE_BYTES", "2MiB".to_string()),
        ],
    };
    project.ok(&["config", "-q"]);
    let started = Instant::now();
    project.ok(&["up", "-d"]);
    let port = project.ok(&["port", "coordinator", "50051"]);
    let url = port.trim().to_string();
    // The CA, the client certificate and the token, copied out of the coordinator's view of
    // the `secrets` volume as a user would (deploy/README.md). The published address is named
    // by no certificate: the CLI checks for the cluster's name instead.
    let dir = tempfile::tempdir().expect("temp dir");
    let coordinator = project.ok(&["ps", "-q", "coordinator"]).trim().to_string();
    for file in [
        "ca.pem",
        "node-client.pem",
        "node-client-key.pem",
        "user-tokens",
    ] {
        let copied = Command::new("docker")
            .args(["cp", &format!("{coordinator}:/secrets/{file}")])
            .arg(dir.path().join(file))
            .output()
            .expect("docker cp");
        assert!(
            copied.status.success(),
            "docker cp {file}: {}",
            String::from_utf8_lossy(&copied.stderr)
        );
    }
    let ca = dir.path().join("ca.pem");
    let tokens = dir.path().join("user-tokens");
    let (client_cert, client_key) = (
        dir.path().join("node-client.pem"),
        dir.path().join("node-client-key.pem"),
    );
    // Mutual TLS: the CLI presents the client certificate too.
    let client_env = [
        ("RAYFARM_COORDINATOR", url.as_str()),
        ("RAYFARM_TLS_CA", s(&ca)),
        ("RAYFARM_TLS_DOMAIN", "rayfarm"),
        ("RAYFARM_TLS_CERT", s(&client_cert)),
        ("RAYFARM_TLS_KEY", s(&client_key)),
        ("RAYFARM_TOKEN_FILE", s(&tokens)),
    ];
    let cli = |args: &[&str]| {
        let out = Command::new(bin("rayfarm"))
            .args(args)
            .envs(client_env)
            .output()
            .expect("run rayfarm");
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let (ok, err) = cli(&["status", "--wait-workers", "4", "--timeout", "60"]);
    assert!(ok, "4 workers never registered: {err}");
    // The dashboard over HTTPS on its published port: no client certificate asked for, even
    // under mutual TLS; its API wants the user token.
    let http = project.ok(&["port", "coordinator", "8080"]);
    let http_port = http.trim().rsplit(':').next().expect("a port").to_string();
    let curl = |path: &str, token: bool| {
        let mut c = Command::new("curl");
        c.args([
            "-s",
            "-o",
            "/dev/null",
            "-w",
            "%{http_code}",
            "--cacert",
            s(&ca),
        ])
        .args(["--resolve", &format!("rayfarm:{http_port}:127.0.0.1")])
        .arg(format!("https://rayfarm:{http_port}{path}"));
        if token {
            let text = std::fs::read_to_string(&tokens).expect("tokens");
            let token = text
                .lines()
                .find(|l| !l.starts_with('#') && !l.trim().is_empty())
                .and_then(|l| l.split_whitespace().next())
                .expect("a token")
                .to_string();
            c.args(["-H", &format!("Authorization: Bearer {token}")]);
        }
        let out = c.output().expect("run curl");
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    assert_eq!(curl("/", false), "200", "the dashboard page");
    assert_eq!(curl("/api/jobs", false), "401", "the API without a token");
    assert_eq!(curl("/api/jobs", true), "200", "the API with the token");
    // Each worker registered under its own certificate's name, at the host it names.
    let status = Command::new(bin("rayfarm"))
        .args(["status", "--json"])
        .envs(client_env)
        .output()
        .expect("status");
    let status: serde_json::Value = serde_json::from_slice(&status.stdout).expect("status json");
    let mut registered: Vec<(String, String)> = status["workers"]
        .as_array()
        .expect("workers")
        .iter()
        .map(|w| {
            let field = |k: &str| w[k].as_str().unwrap_or_default().to_string();
            (field("worker_id"), field("peer_address"))
        })
        .collect();
    registered.sort();
    let expected: Vec<(String, String)> = (1..=4)
        .map(|n| (format!("worker-{n}"), format!("worker-{n}:7000")))
        .collect();
    assert_eq!(registered, expected);
    let anonymous = Command::new(bin("rayfarm"))
        .arg("jobs")
        .envs(client_env[..5].iter().copied())
        .output()
        .expect("run rayfarm");
    let err = String::from_utf8_lossy(&anonymous.stderr);
    assert!(
        !anonymous.status.success() && err.contains("UNAUTHENTICATED"),
        "a client without a token was not refused: {err}"
    );
    eprintln!(
        "compose cluster up in {:.1} s",
        started.elapsed().as_secs_f64()
    );

    // The same scene, generated on the host with the same seed, is the reference.
    let scene = dir.path().join("nbody");
    rayfarm_ok(&[
        "prepare",
        "--generate",
        "nbody",
        "--triangles",
        "60000",
        "--domains",
        "8",
        "--seed",
        "1",
        "--name",
        "nbody",
        "--out",
        s(&scene),
    ]);
    let frame = [
        "--width", "160", "--height", "120", "--spp", "2", "--depth", "3",
    ];
    let local = dir.path().join("local.json");
    let local_png = dir.path().join("local.png");
    let mut args = vec!["render", "--local", "--scene", s(&scene), "--quiet"];
    args.extend(["--out", s(&local_png), "--stats-json", s(&local)]);
    args.extend_from_slice(&frame);
    rayfarm_ok(&args);
    let remote = dir.path().join("compose.json");
    let png = dir.path().join("compose.png");
    let mut args = vec![
        "submit",
        "--wait",
        "--quiet",
        "-o",
        s(&png),
        "--stats-json",
        s(&remote),
    ];
    args.extend_from_slice(&frame);
    let (ok, err) = cli(&args);
    assert!(ok, "the compose cluster failed the frame: {err}");
    assert_eq!(hash_of(&remote), hash_of(&local));
    let migrated = stats_field(&remote, "/rays_migrated").as_u64().unwrap_or(0);
    eprintln!("compose frame identical; {migrated} rays crossed between worker containers");
    assert!(migrated > 0);

    // A job of `frame`, submitted, once the coordinator runs it.
    let submit_running = |frame: &[&str]| {
        let out = Command::new(bin("rayfarm"))
            .arg("submit")
            .args(frame)
            .envs(client_env)
            .output()
            .expect("submit");
        assert!(out.status.success(), "submit failed");
        let job = String::from_utf8_lossy(&out.stdout).trim().to_string();
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let listed = Command::new(bin("rayfarm"))
                .args(["jobs", "--json"])
                .envs(client_env)
                .output()
                .expect("jobs");
            let jobs: serde_json::Value =
                serde_json::from_slice(&listed.stdout).expect("jobs json");
            let running = jobs.as_array().is_some_and(|js| {
                js.iter()
                    .any(|j| j["job_id"] == job.as_str() && j["state"] == "running")
            });
            if running {
                return job;
            }
            assert!(Instant::now() < deadline, "the frame never started");
            std::thread::sleep(Duration::from_millis(50));
        }
    };

    // A second, longer frame; one worker container is killed while it runs.
    let job = submit_running(&SECOND);
    let victim = project.ok(&["ps", "-q", "worker-2"]).trim().to_string();
    assert!(!victim.is_empty(), "no worker-2 container");
    let killed = Command::new("docker")
        .args(["kill", &victim])
        .output()
        .expect("docker kill");
    assert!(killed.status.success());
    let (finished, err) = cli(&["watch", &job, "--quiet"]);
    assert!(
        finished,
        "the frame did not survive the killed worker: {err}"
    );
    let json = dir.path().join("second.json");
    let second_png = dir.path().join("second.png");
    let (ok, err) = cli(&[
        "fetch",
        &job,
        "-o",
        s(&second_png),
        "--stats-json",
        s(&json),
    ]);
    assert!(ok, "{err}");
    // The reference for the second frame, rendered on the host.
    let second_local = dir.path().join("second-local.json");
    let second_local_png = dir.path().join("second-local.png");
    let mut args = vec!["render", "--local", "--scene", s(&scene), "--quiet"];
    args.extend([
        "--out",
        s(&second_local_png),
        "--stats-json",
        s(&second_local),
    ]);
    args.extend_from_slice(&SECOND);
    rayfarm_ok(&args);
    assert_eq!(hash_of(&json), hash_of(&second_local));
    eprintln!(
        "REPORT: a worker container killed mid-frame; the frame finished on {} workers, \
         image identical to render --local ({})",
        stats_field(&json, "/workers"),
        hash_of(&json)
    );

    // A third frame like the second; worker-3's container drops off the compose network while
    // it runs (`docker network disconnect`, as a host whose link goes), past the coordinator's
    // worker timeout, and comes back under its name.
    let victim = project.ok(&["ps", "-q", "worker-3"]).trim().to_string();
    let inspect = Command::new("docker")
        .args([
            "inspect",
            "-f",
            "{{range $k, $v := .NetworkSettings.Networks}}{{$k}} {{end}}",
            &victim,
        ])
        .output()
        .expect("docker inspect");
    let network = String::from_utf8_lossy(&inspect.stdout)
        .split_whitespace()
        .next()
        .expect("worker-3 on a network")
        .to_string();
    let job = submit_running(&SECOND);
    let docker = |args: &[&str]| {
        let out = Command::new("docker").args(args).output().expect("docker");
        assert!(
            out.status.success(),
            "docker {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr)
        );
    };
    let cut_at = Instant::now();
    docker(&["network", "disconnect", &network, &victim]);
    // The coordinator notices within its worker timeout (10 s) that heartbeats stopped.
    let lost = loop {
        let logs = Command::new("docker")
            .args(["logs", &coordinator])
            .output()
            .expect("docker logs");
        let text = String::from_utf8_lossy(&logs.stderr).into_owned()
            + &String::from_utf8_lossy(&logs.stdout);
        if text
            .lines()
            .any(|l| l.contains("worker lost") && l.contains("worker-3"))
        {
            break true;
        }
        if cut_at.elapsed() > Duration::from_secs(30) {
            break false;
        }
        std::thread::sleep(Duration::from_millis(200));
    };
    docker(&[
        "network", "connect", "--alias", "worker-3", &network, &victim,
    ]);
    let cut_for = cut_at.elapsed();
    let (finished, err) = cli(&["watch", &job, "--quiet"]);
    assert!(
        finished,
        "the frame did not survive the disconnected worker: {err}"
    );
    let third = dir.path().join("third.json");
    let third_png = dir.path().join("third.png");
    let (ok, err) = cli(&[
        "fetch",
        &job,
        "-o",
        s(&third_png),
        "--stats-json",
        s(&third),
    ]);
    assert!(ok, "{err}");
    assert_eq!(hash_of(&third), hash_of(&second_local));
    // Back on the network, worker-3 registers again and the next job has it.
    let (ok, err) = cli(&["status", "--wait-workers", "3", "--timeout", "60"]);
    assert!(ok, "worker-3 did not come back: {err}");
    let last = dir.path().join("last.json");
    let last_png = dir.path().join("last.png");
    let mut args = vec!["submit", "--wait", "--quiet", "-o", s(&last_png)];
    args.extend(["--stats-json", s(&last)]);
    args.extend_from_slice(&frame);
    let (ok, err) = cli(&args);
    assert!(ok, "the job after the reconnect failed: {err}");
    assert_eq!(hash_of(&last), hash_of(&local));
    assert_eq!(
        stats_field(&last, "/workers"),
        3,
        "the job after the reconnect"
    );
    eprintln!(
        "REPORT: worker-3 off the compose network for {:.1} s ({}); the frame finished on {} \
         workers, identical; the next job ran on {} workers, worker-3 among them",
        cut_for.as_secs_f64(),
        if lost {
            "declared lost by the coordinator"
        } else {
            "never declared lost"
        },
        stats_field(&third, "/workers"),
        stats_field(&last, "/workers"),
    );
    eprintln!("compose test took {:.1} s", started.elapsed().as_secs_f64());
}
