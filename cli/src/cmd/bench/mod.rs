//! `rayfarm bench`: every schedule side by side in one run, so the comparison of dynamic ray
//! scheduling with the static image-plane and domain schedules is reproducible with one
//! command on one machine at one time.
//!
//! It starts a local cluster exactly as `rayfarm demo` does (or uses an existing one), then
//! renders the same frame once per schedule per repeat, interleaved and with the order rotated
//! each repeat so slow drift of the machine falls on every schedule alike. Every frame starts
//! with cold caches (`JobSpec.cold_cache`), so every schedule pays for its own domain loads.
//! A schedule the coordinator refuses, or a frame that fails, is reported and the others go
//! on. At the end: a table of medians per schedule with the efficiency against the bound,
//! a check that every image is bit-identical, and optionally a CSV (one row per run) and a
//! PNG chart. The arithmetic lives in `crate::bench`, pure and tested.
//!
//! The parts: this module holds the options and starts (or finds) the cluster; [`plan`] checks
//! the options and the scene into the runs to make, [`runs`] renders them one by one on the
//! cluster, [`output`] prints the table and writes the CSV and the chart.

use std::path::PathBuf;

use anyhow::{Context, anyhow};
use clap::{Args, ValueEnum};
use rayfarm_core::progressive::Progressive;
use rayfarm_node::job::parse_schedule_setting;
use rayfarm_node::proto;
use rayfarm_node::security::ClientSecurity;

use crate::bench::csv_out::Setup;
use crate::client::{ClientAuthArgs, runtime};
use crate::local_cluster::{
    ClusterConfig, Interrupted, JobInFlight, interruptible, threads_per_worker, with_local_cluster,
};
use crate::units::{self};

mod output;
mod plan;
mod runs;

use output::report;
use plan::Plan;
use runs::{BenchRuns, bench};

/// Options of `rayfarm bench`.
#[derive(Args, Clone, Debug)]
pub struct BenchArgs {
    /// A prepared scene directory (`rayfarm prepare --out DIR`). The local cluster's scene
    /// root is its parent and the jobs name the scene by its directory name (a cluster given
    /// with --coordinator must see it by that name under its scene root).
    #[arg(long, env = "RAYFARM_SCENE")]
    pub scene: PathBuf,
    /// Worker processes of the local cluster (they share this machine's cores). Not used
    /// with --coordinator.
    #[arg(long, env = "RAYFARM_BENCH_WORKERS", default_value_t = 4,
          value_parser = clap::value_parser!(u32).range(1..=64))]
    pub workers: u32,
    /// Schedules to compare, comma-separated: dynamic, image-plane, domain, hybrid,
    /// predictive; the predictive schedule with a speculation setting as
    /// `predictive:SETTING` (none, full, ahead:N, predicted, predicted:P; see `submit
    /// --speculation`), so several settings run side by side.
    #[arg(long, env = "RAYFARM_BENCH_SCHEDULES", value_delimiter = ',',
          default_value = "dynamic,predictive,image-plane,domain",
          value_parser = parse_schedule_setting)]
    pub schedules: Vec<(proto::Schedule, String)>,
    /// Domain cache budget of each worker, e.g. 8MiB [default: a quarter of the scene, so
    /// domains are paged in and out as on a farm]. Not used with --coordinator.
    #[arg(long, env = "RAYFARM_CACHE_BYTES", value_parser = units::bytes)]
    pub cache_bytes: Option<u64>,
    /// Tracing threads of each worker [default: this machine's cores / workers, at least 1].
    /// Not used with --coordinator.
    #[arg(long, env = "RAYFARM_THREADS",
          value_parser = clap::value_parser!(u32).range(1..=4096))]
    pub threads: Option<u32>,
    /// Frames per schedule; each repeat runs every schedule once, the order rotated by one.
    #[arg(long, env = "RAYFARM_BENCH_REPEATS", default_value_t = 3,
          value_parser = clap::value_parser!(u32).range(1..=1000))]
    pub repeats: u32,
    /// Image width.
    #[arg(long, env = "RAYFARM_WIDTH", default_value_t = 512)]
    pub width: u32,
    /// Image height.
    #[arg(long, env = "RAYFARM_HEIGHT", default_value_t = 512)]
    pub height: u32,
    /// Samples per pixel.
    #[arg(long, env = "RAYFARM_SPP", default_value_t = 4)]
    pub spp: u32,
    /// Maximum bounces.
    #[arg(long, env = "RAYFARM_DEPTH", default_value_t = 3)]
    pub depth: u32,
    /// Also render every schedule progressively, in subframes (`doubling` or a number of
    /// samples per subframe, as `submit --progressive`): each schedule then has two rows
    /// side by side, one pass and `SCHEDULE+progressive`, and every image must still be the
    /// same.
    #[arg(long, env = "RAYFARM_BENCH_PROGRESSIVE", value_parser = Progressive::parse)]
    pub progressive: Option<Progressive>,
    /// Also render the dynamic and predictive schedules with prefetch (`submit
    /// --prefetch`: workers load their next domains while they trace): each then has a
    /// `SCHEDULE+prefetch` row beside its row without.
    #[arg(long, env = "RAYFARM_BENCH_PREFETCH", value_parser = clap::builder::BoolishValueParser::new())]
    pub prefetch: bool,
    /// Also render every schedule loading domains from peers (`submit --peer-domains`): each
    /// then has a `SCHEDULE+peers` row beside its row without (and its prefetch row's).
    #[arg(long, env = "RAYFARM_BENCH_PEER_DOMAINS", value_parser = clap::builder::BoolishValueParser::new())]
    pub peer_domains: bool,
    /// Also write one row per run (every measure; failed runs with their error) to this CSV
    /// file.
    #[arg(long, env = "RAYFARM_BENCH_CSV")]
    pub csv: Option<PathBuf>,
    /// Draw median time and median domain loads per schedule as a PNG bar chart here
    /// [default: beside the CSV, with .png for .csv; none without --csv].
    #[arg(long, env = "RAYFARM_BENCH_CHART")]
    pub chart: Option<PathBuf>,
    /// Benchmark the existing cluster at this address (http://HOST:PORT or HOST:PORT) instead
    /// of starting a local one; --workers, --cache-bytes, --threads, --replicate,
    /// --storage-latency and --keep-cluster-logs are then not used. (Its own variable, not
    /// RAYFARM_COORDINATOR, so that a shell set up for other commands does not silently
    /// benchmark a shared cluster.)
    #[arg(long, env = "RAYFARM_BENCH_COORDINATOR")]
    pub coordinator: Option<String>,
    /// TLS and token for --coordinator (a local cluster needs none and ignores them).
    #[command(flatten)]
    pub auth: ClientAuthArgs,
    /// Storage bandwidth of every worker it starts, e.g. 100MiB/s (passed on as the workers'
    /// --storage-bandwidth); also the bound's load term: the scene's bytes at this rate.
    #[arg(long, env = "RAYFARM_STORAGE_BANDWIDTH", value_parser = parse_rate)]
    pub storage_bandwidth: Option<Rate>,
    /// Storage latency of every domain load on the workers it starts, e.g. 5ms (passed on as
    /// the workers' --storage-latency).
    #[arg(long, env = "RAYFARM_STORAGE_LATENCY")]
    pub storage_latency: Option<String>,
    /// Domain copies beyond the paper's dynamic schedule, passed to the coordinator it starts
    /// as --replicate [default: the coordinator's, free-slots].
    #[arg(long, env = "RAYFARM_REPLICATE", value_enum)]
    pub replicate: Option<Replicate>,
    /// Keep the local cluster's data directory (logs, every frame's image and statistics)
    /// here [default: a temporary directory, kept only if the bench fails].
    #[arg(long, env = "RAYFARM_BENCH_LOGS")]
    pub keep_cluster_logs: Option<PathBuf>,
}

/// `--replicate` of the coordinator: copies of busy domains beyond the paper's algorithm.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum Replicate {
    /// The paper's Fig. 5 as written.
    None,
    /// Workers left idle get a copy of the busiest domain.
    Idle,
    /// Every free cache slot gets a copy of a wanted domain.
    FreeSlots,
}

impl Replicate {
    /// The flag value, as the coordinator spells it.
    fn name(self) -> &'static str {
        match self {
            Replicate::None => "none",
            Replicate::Idle => "idle",
            Replicate::FreeSlots => "free-slots",
        }
    }
}

/// A storage bandwidth as typed (passed on unchanged) and in bytes per second.
#[derive(Clone, Debug, PartialEq)]
pub struct Rate {
    pub text: String,
    pub bytes_per_second: u64,
}

/// Parses a bandwidth for clap: a byte size per second, "100MiB/s" (the "/s" may be left
/// out).
pub fn parse_rate(s: &str) -> Result<Rate, String> {
    Ok(Rate {
        text: s.trim().to_string(),
        bytes_per_second: rayfarm_core::units::parse_rate(s)?,
    })
}

pub fn run(a: BenchArgs) -> anyhow::Result<()> {
    let plan = Plan::new(&a)?;
    let (runs, setup) = match &a.coordinator {
        Some(url) => {
            let in_flight = JobInFlight::default();
            let security = a.auth.security()?;
            let session = bench(url, &security, &plan, &in_flight);
            let runs = runtime()?.block_on(interruptible(&in_flight, session))?;
            (runs, setup(&a, &plan, None))
        }
        None => run_local(&a, &plan)?,
    };
    report(&a, &plan, &runs.runs, &setup)?;
    match runs.stopped {
        Some(why) => Err(anyhow!("the bench {why}")),
        None => Ok(()),
    }
}

/// Runs the bench on a local cluster started for it and stopped after it. Its data directory
/// (logs, images) is `--keep-cluster-logs` or a temporary directory, which is kept when a run
/// failed so the logs can be read.
fn run_local(a: &BenchArgs, plan: &Plan) -> anyhow::Result<(BenchRuns, Setup)> {
    let workers = a.workers as usize;
    let threads = a
        .threads
        .map_or_else(|| threads_per_worker(workers), |t| t as usize);
    let cache_bytes = a.cache_bytes.unwrap_or((plan.scene_bytes / 4).max(1));
    let (data_dir, temp) = match &a.keep_cluster_logs {
        Some(dir) => (dir.clone(), None),
        None => {
            let t = tempfile::Builder::new()
                .prefix("rayfarm-bench-")
                .tempdir()
                .context("creating a temporary directory for the cluster")?;
            (t.path().to_path_buf(), Some(t))
        }
    };
    let mut config =
        ClusterConfig::for_scene(&plan.scene_dir, &data_dir, workers, cache_bytes, threads)?;
    config.coordinator_extra = coordinator_extra(a);
    config.worker_extra = worker_extra(a);
    let in_flight = JobInFlight::default();
    let result = runtime()?.block_on(with_local_cluster(&config, &in_flight, async |url| {
        bench(&url, &ClientSecurity::default(), plan, &in_flight).await
    }));
    // An interrupted bench was stopped on purpose: nothing to read, nothing kept.
    let interrupted = result.as_ref().is_err_and(|e| e.is::<Interrupted>());
    let failed = !interrupted
        && result.as_ref().map_or(true, |b| {
            b.stopped.is_some() || b.runs.iter().any(|r| r.result.is_err())
        });
    match temp {
        Some(t) if failed => eprintln!(
            "kept the cluster's logs and results in {}",
            t.keep().display()
        ),
        Some(_) => {}
        None => eprintln!(
            "the cluster's logs and results are in {}",
            data_dir.display()
        ),
    }
    Ok((
        result?,
        setup(a, plan, Some((workers, cache_bytes, threads))),
    ))
}

/// Flags for the coordinator the bench starts.
fn coordinator_extra(a: &BenchArgs) -> Vec<std::ffi::OsString> {
    a.replicate
        .map(|r| vec!["--replicate".into(), r.name().into()])
        .unwrap_or_default()
}

/// Flags for every worker the bench starts: the storage model, only when given (older
/// workers do not know the flags).
fn worker_extra(a: &BenchArgs) -> Vec<std::ffi::OsString> {
    let mut args: Vec<std::ffi::OsString> = Vec::new();
    if let Some(rate) = &a.storage_bandwidth {
        args.extend(["--storage-bandwidth".into(), rate.text.clone().into()]);
    }
    if let Some(latency) = &a.storage_latency {
        args.extend(["--storage-latency".into(), latency.into()]);
    }
    args
}

/// What every CSV row repeats. `local`: (workers, cache bytes, threads) of a cluster the bench
/// started.
fn setup(a: &BenchArgs, plan: &Plan, local: Option<(usize, u64, usize)>) -> Setup {
    Setup {
        scene: plan.scene_name.clone(),
        workers: local.map(|l| l.0),
        cache_bytes_per_worker: local.map(|l| l.1),
        threads_per_worker: local.map(|l| l.2),
        width: a.width,
        height: a.height,
        spp: a.spp,
        depth: a.depth,
        replicate: match (local, a.replicate) {
            (Some(_), Some(r)) => r.name().to_string(),
            _ => String::new(),
        },
        storage_bandwidth: a
            .storage_bandwidth
            .as_ref()
            .map(|r| r.text.clone())
            .unwrap_or_default(),
        storage_latency: match (local, &a.storage_latency) {
            (Some(_), Some(l)) => l.clone(),
            _ => String::new(),
        },
    }
}

#[cfg(test)]
mod tests;
