//! `/metrics` for real: a local cluster started with `--http` on every process renders a
//! frame; the coordinator's and the workers' `/metrics` are fetched, checked as OpenMetrics
//! text, checked to hold every metric README.md's table documents, and their counts compared
//! with the frame's statistics.

use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

use rayfarm_tests::{
    Cluster, ClusterOpts, WorkerOpts, http_get, http_request, prepare_nbody, stats_field,
    submit_wait, wait_until,
};

/// One parsed sample line: metric name, labels as written, value.
#[derive(Debug)]
struct Sample {
    name: String,
    labels: String,
    value: f64,
}

/// Parses OpenMetrics text strictly enough to catch a broken exposition: every line is a
/// `# HELP`, `# TYPE`, `# UNIT` of a family, or a sample of a declared family; values are
/// numbers; `# EOF` ends it, once.
fn parse(text: &str) -> Vec<Sample> {
    let mut families: BTreeMap<String, String> = BTreeMap::new();
    let mut samples = Vec::new();
    let mut ended = false;
    for line in text.lines() {
        assert!(!ended, "text after # EOF: {line:?}");
        if line == "# EOF" {
            ended = true;
            continue;
        }
        if let Some(rest) = line.strip_prefix("# ") {
            let mut parts = rest.splitn(3, ' ');
            let (kind, name, value) = (
                parts.next().unwrap_or(""),
                parts.next().unwrap_or(""),
                parts.next().unwrap_or(""),
            );
            assert!(valid_name(name), "bad family name in {line:?}");
            match kind {
                "TYPE" => {
                    let types = ["counter", "gauge", "histogram", "info", "unknown"];
                    assert!(types.contains(&value), "bad type in {line:?}");
                    families.insert(name.to_string(), value.to_string());
                }
                "HELP" => assert!(!value.is_empty(), "empty help in {line:?}"),
                "UNIT" => assert!(name.ends_with(&format!("_{value}")), "{line:?}"),
                _ => panic!("unknown comment {line:?}"),
            }
            continue;
        }
        let (series, value) = line
            .rsplit_once(' ')
            .unwrap_or_else(|| panic!("no value in {line:?}"));
        let value: f64 = value
            .parse()
            .unwrap_or_else(|_| panic!("bad value in {line:?}"));
        let (name, labels) = match series.split_once('{') {
            Some((name, labels)) => {
                let labels = labels
                    .strip_suffix('}')
                    .unwrap_or_else(|| panic!("unclosed labels in {line:?}"));
                for pair in labels.split(',') {
                    let (k, v) = pair
                        .split_once('=')
                        .unwrap_or_else(|| panic!("bad label in {line:?}"));
                    assert!(valid_name(k), "bad label name in {line:?}");
                    assert!(
                        v.len() >= 2 && v.starts_with('"') && v.ends_with('"'),
                        "unquoted label value in {line:?}"
                    );
                }
                (name, labels)
            }
            None => (series, ""),
        };
        assert!(valid_name(name), "bad metric name in {line:?}");
        let family = [
            "_total", "_bucket", "_count", "_sum", "_created", "_info", "",
        ]
        .iter()
        .find_map(|suffix| {
            let base = name.strip_suffix(suffix)?;
            families.get(base).map(|t| (base, t))
        });
        let (_, kind) = family.unwrap_or_else(|| panic!("sample of no declared family: {line:?}"));
        if kind == "counter" {
            assert!(
                name.ends_with("_total") || name.ends_with("_created"),
                "{line:?}"
            );
            assert!(value >= 0.0, "negative counter {line:?}");
        }
        assert!(name.starts_with("rayfarm_"), "no rayfarm_ prefix: {line:?}");
        samples.push(Sample {
            name: name.to_string(),
            labels: labels.to_string(),
            value,
        });
    }
    assert!(ended, "no # EOF at the end");
    samples
}

fn valid_name(name: &str) -> bool {
    !name.is_empty()
        && !name.starts_with(|c: char| c.is_ascii_digit())
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == ':')
}

/// The sum of a metric's samples (over its labels).
fn sum(samples: &[Sample], name: &str) -> f64 {
    samples
        .iter()
        .filter(|s| s.name == name)
        .map(|s| s.value)
        .sum()
}

/// The metric names README.md's metrics table documents.
fn documented() -> Vec<String> {
    let readme = include_str!("../README.md");
    let names: Vec<String> = readme
        .lines()
        .filter_map(|l| l.strip_prefix("| `rayfarm_"))
        .map(|rest| format!("rayfarm_{}", rest.split('`').next().unwrap_or("")))
        .collect();
    assert!(names.len() >= 20, "README documents only {names:?}");
    names
}

#[test]
fn metrics_are_valid_documented_and_agree_with_the_frame() {
    let root = tempfile::tempdir().unwrap();
    prepare_nbody(root.path(), "scene", 3000, 4);
    let http = ["--http", "127.0.0.1:0"];
    let opts = ClusterOpts {
        coordinator_args: http.iter().map(|s| s.to_string()).collect(),
        ..ClusterOpts::default()
    };
    let workers = vec![WorkerOpts::cache(1 << 30).args(&http); 2];
    let cluster = Cluster::start_with(root.path(), Some("scene"), &opts, &workers);
    let coordinator = cluster
        .coordinator_http()
        .expect("coordinator http address");
    let worker_addrs: Vec<String> = (0..2)
        .map(|i| {
            cluster
                .worker_http(i)
                .expect("worker http address")
                .to_string()
        })
        .collect();

    let frame = [
        "--width", "96", "--height", "64", "--spp", "2", "--depth", "3",
    ];
    let stats = submit_wait(&cluster, &frame, "m");

    let coordinator_samples = parse(&http_get(coordinator, "/metrics"));
    let worker_samples: Vec<Vec<Sample>> = worker_addrs
        .iter()
        .map(|a| parse(&http_get(a, "/metrics")))
        .collect();

    // Every documented metric is exported by the coordinator or by every worker.
    let names = |samples: &[Sample]| -> BTreeSet<String> {
        samples.iter().map(|s| s.name.clone()).collect()
    };
    let on_coordinator = names(&coordinator_samples);
    for name in documented() {
        let present =
            |set: &BTreeSet<String>| set.contains(&name) || set.contains(&format!("{name}_count"));
        let on_workers = worker_samples.iter().all(|w| present(&names(w)));
        assert!(
            present(&on_coordinator) || on_workers,
            "{name} is documented but not exported"
        );
    }

    // The workers' counts are the frame's.
    let total = |name: &str| worker_samples.iter().map(|w| sum(w, name)).sum::<f64>();
    let loads = stats_field(&stats, "/cache/loads").as_u64().unwrap();
    assert!(loads > 0);
    assert_eq!(total("rayfarm_domain_loads_total"), loads as f64);
    assert_eq!(
        total("rayfarm_domain_load_bytes_total"),
        stats_field(&stats, "/cache/bytes_loaded").as_u64().unwrap() as f64
    );
    let segments = stats_field(&stats, "/rays/radiance_segments")
        .as_u64()
        .unwrap()
        + stats_field(&stats, "/rays/shadow_segments")
            .as_u64()
            .unwrap();
    assert_eq!(total("rayfarm_ray_segments_traced_total"), segments as f64);
    let primary: f64 = worker_samples
        .iter()
        .flat_map(|w| w.iter())
        .filter(|s| s.name == "rayfarm_rays_created_total" && s.labels == "kind=\"primary\"")
        .map(|s| s.value)
        .sum();
    assert_eq!(
        primary,
        (96 * 64 * 2) as f64,
        "a camera ray per pixel sample"
    );
    assert_eq!(
        total("rayfarm_rays_sent_total"),
        stats_field(&stats, "/rays_migrated").as_u64().unwrap() as f64
    );

    // The coordinator's counts are the frame's.
    assert_eq!(
        sum(&coordinator_samples, "rayfarm_frames_committed_total"),
        1.0
    );
    assert_eq!(
        sum(&coordinator_samples, "rayfarm_rounds_total"),
        stats_field(&stats, "/rounds").as_u64().unwrap() as f64
    );
    let tiles = sum(&coordinator_samples, "rayfarm_tiles_committed_total");
    assert!(tiles >= 1.0, "tiles committed: {tiles}");
    let jobs = |state: &str| {
        coordinator_samples
            .iter()
            .find(|s| s.name == "rayfarm_jobs" && s.labels == format!("state=\"{state}\""))
            .map(|s| s.value)
    };
    assert_eq!(jobs("succeeded"), Some(1.0));
    assert_eq!(jobs("running"), Some(0.0));
    assert_eq!(sum(&coordinator_samples, "rayfarm_workers"), 2.0);

    // A refused call is counted by its code: a job for a scene that does not exist.
    let before = sum(&coordinator_samples, "rayfarm_rpc_errors_total");
    let refused = cluster.rayfarm(&["submit", "--scene", "no-such-scene", "--quiet"]);
    assert!(!refused.status.success());
    wait_until("the refusal counted", Duration::from_secs(10), || {
        sum(
            &parse(&http_get(coordinator, "/metrics")),
            "rayfarm_rpc_errors_total",
        ) > before
    });

    // Anything but /metrics is not found; a request with oversized headers is refused.
    assert_eq!(
        http_request(&worker_addrs[0], "GET", "/nothing", &[], "").0,
        404
    );
    let huge = "x".repeat(64 << 10);
    let big = std::panic::catch_unwind(|| {
        http_request(&worker_addrs[0], "GET", "/metrics", &[("x-big", &huge)], "").0
    });
    assert!(!matches!(big, Ok(200)), "oversized headers were served");
}
