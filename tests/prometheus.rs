//! A real Prometheus (Debian's `prometheus`) scrapes a local cluster through a frame; its
//! query API must then say that the workers' `rayfarm_domain_loads_total`, summed, is the
//! frame's domain loads.
//!
//! Skipped, with a `SKIPPED` line, where `prometheus` is not installed; `.ci/run` installs it.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use rayfarm_tests::{
    Cluster, ClusterOpts, WorkerOpts, fixed_port, prepare_nbody, s, stats_field, submit_wait,
    try_http_request,
};

/// How long Prometheus may take to start, and to have scraped the frame's end.
const PROMETHEUS_TIMEOUT: Duration = Duration::from_secs(90);

/// Where the `prometheus` program is, if installed.
fn find_prometheus() -> Option<PathBuf> {
    let path = std::env::var("PATH").unwrap_or_default();
    path.split(':')
        .chain(["/usr/bin", "/usr/sbin"])
        .map(|dir| PathBuf::from(dir).join("prometheus"))
        .find(|p| p.is_file())
}

/// A Prometheus server, killed when dropped.
struct Prometheus {
    child: Child,
    addr: String,
    log: PathBuf,
}

impl Drop for Prometheus {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        if std::thread::panicking() {
            let log = std::fs::read_to_string(&self.log).unwrap_or_default();
            let tail: Vec<&str> = log.lines().rev().take(30).collect();
            eprintln!(
                "prometheus log (last lines, newest first):\n{}",
                tail.join("\n")
            );
        }
    }
}

/// The value of the single-sample result of PromQL `query`, if there is one yet.
fn query(addr: &str, query: &str) -> Option<f64> {
    let path = format!("/api/v1/query?query={}", encode(query));
    let (status, body) = try_http_request(addr, "GET", &path, &[], "").ok()?;
    if status != 200 {
        return None;
    }
    let json: serde_json::Value = serde_json::from_str(&body).ok()?;
    let value = json.pointer("/data/result/0/value/1")?.as_str()?;
    value.parse().ok()
}

/// Percent-encodes a query string value.
fn encode(text: &str) -> String {
    text.bytes()
        .map(|b| match b {
            b'a'..=b'z' | b'A'..=b'Z' | b'0'..=b'9' | b'_' | b'-' | b'.' => (b as char).to_string(),
            _ => format!("%{b:02X}"),
        })
        .collect()
}

#[test]
fn prometheus_scrapes_the_frames_domain_loads() {
    let Some(program) = find_prometheus() else {
        println!("SKIPPED: prometheus is not installed (apt-get install prometheus)");
        return;
    };
    let root = tempfile::tempdir().unwrap();
    prepare_nbody(root.path(), "scene", 3000, 4);
    let http = ["--http", "127.0.0.1:0"];
    let opts = ClusterOpts {
        coordinator_args: http.iter().map(|s| s.to_string()).collect(),
        ..ClusterOpts::default()
    };
    let workers = vec![WorkerOpts::default().args(&http); 2];
    let cluster = Cluster::start_with(root.path(), Some("scene"), &opts, &workers);
    let targets: Vec<String> = std::iter::once(cluster.coordinator_http())
        .chain((0..2).map(|i| cluster.worker_http(i)))
        .map(|a| format!("'{}'", a.expect("an http address")))
        .collect();

    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("prometheus.yml");
    std::fs::write(
        &config,
        format!(
            "global:\n  scrape_interval: 1s\n  scrape_timeout: 1s\nscrape_configs:\n  - \
             job_name: rayfarm\n    static_configs:\n      - targets: [{}]\n",
            targets.join(", ")
        ),
    )
    .unwrap();
    let addr = format!("127.0.0.1:{}", fixed_port());
    let log = dir.path().join("prometheus.log");
    let child = Command::new(program)
        .arg(format!("--config.file={}", s(&config)))
        .arg(format!(
            "--storage.tsdb.path={}",
            s(&dir.path().join("data"))
        ))
        .arg(format!("--web.listen-address={addr}"))
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .expect("start prometheus");
    let prometheus = Prometheus { child, addr, log };

    let stats = submit_wait(
        &cluster,
        &[
            "--width", "96", "--height", "64", "--spp", "2", "--depth", "3",
        ],
        "p",
    );
    let loads = stats_field(&stats, "/cache/loads").as_u64().unwrap() as f64;
    assert!(loads > 0.0);

    // Polled until Prometheus has scraped every target since the frame ended.
    let q = "sum(rayfarm_domain_loads_total)";
    let start = Instant::now();
    loop {
        let seen = [
            query(&prometheus.addr, q),
            query(&prometheus.addr, "sum(up)"),
            query(&prometheus.addr, "sum(rayfarm_frames_committed_total)"),
        ];
        if seen == [Some(loads), Some(3.0), Some(1.0)] {
            break;
        }
        assert!(
            start.elapsed() < PROMETHEUS_TIMEOUT,
            "{q}, sum(up), frames committed are {seen:?}; the frame's loads {loads}"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}
