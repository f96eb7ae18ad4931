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

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, anyhow, bail};
use clap::{Args, ValueEnum};
use rayfarm_core::cluster::stats::ClusterStats;
use rayfarm_core::progressive::Progressive;
use rayfarm_core::scene::Manifest;
use rayfarm_node::job::{parse_schedule_setting, schedule_name};
use rayfarm_node::proto;
use rayfarm_node::security::ClientSecurity;

use super::watch::{ended_ok, follow, parse_stats};
use crate::bench::csv_out::{Setup, write_runs_file};
use crate::bench::progressive::{SUFFIX, compare, progressive_table};
use crate::bench::report::{bench_table, bound_footnote, hash_verdict};
use crate::bench::{HashCheck, RunOutcome, bound, check_hashes, run_order, summarize};
use crate::client::{ClientAuthArgs, Coordinator, runtime};
use crate::local_cluster::{
    ClusterConfig, Interrupted, JobInFlight, interruptible, scene_root_and_name,
    threads_per_worker, with_local_cluster,
};
use crate::units::{self, human};

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

/// What one row of the bench runs: a schedule, in one pass or subframes, with its
/// speculation setting.
#[derive(Clone, Debug)]
struct Run {
    schedule: proto::Schedule,
    progressive: Option<proto::Progressive>,
    speculation: String,
}

/// Everything the bench needs, checked before any process starts.
struct Plan {
    /// (name, schedule, progressive field), in the order given; with `--progressive`, each
    /// schedule's one-pass row is followed by its progressive one.
    schedules: Vec<(String, Run)>,
    repeats: usize,
    /// The job of every run, with its schedule left to fill in.
    spec: proto::JobSpec,
    scene_dir: PathBuf,
    scene_name: String,
    scene_bytes: u64,
    domains: usize,
    csv: Option<PathBuf>,
    chart: Option<PathBuf>,
}

impl Plan {
    fn new(a: &BenchArgs) -> anyhow::Result<Self> {
        let mut schedules: Vec<(String, Run)> = Vec::new();
        for (s, speculation) in &a.schedules {
            let mut name = schedule_name(*s).to_string();
            if !speculation.is_empty() {
                name = format!("{name}:{speculation}");
            }
            if schedules.iter().any(|(n, _)| *n == name) {
                bail!("--schedules names {name} twice");
            }
            let run = Run {
                schedule: *s,
                progressive: None,
                speculation: speculation.clone(),
            };
            schedules.push((name.clone(), run.clone()));
            if let Some(field) = a.progressive.and_then(Progressive::field) {
                let progressive = proto::Progressive {
                    subframe_spp: field,
                };
                let run = Run {
                    progressive: Some(progressive),
                    ..run
                };
                schedules.push((format!("{name}{SUFFIX}"), run));
            }
        }
        if schedules.is_empty() {
            bail!("--schedules names no schedule");
        }
        let chart = a
            .chart
            .clone()
            .or_else(|| a.csv.as_ref().map(|c| c.with_extension("png")));
        if let Some(chart) = &chart
            && !chart
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("png"))
        {
            bail!(
                "--chart {}: the chart is a PNG; name it .png",
                chart.display()
            );
        }
        for out in a.csv.iter().chain(&chart) {
            writable_parent(out)?;
        }
        let manifest = Manifest::load(&a.scene)
            .and_then(|m| m.check_domains(&a.scene, false).map(|()| m))
            .with_context(|| {
                format!(
                    "{} is not a usable prepared scene (make one with `rayfarm prepare`)",
                    a.scene.display()
                )
            })?;
        let (_, scene_name) = scene_root_and_name(&a.scene)?;
        Ok(Self {
            schedules,
            repeats: a.repeats as usize,
            spec: proto::JobSpec {
                scene: scene_name.clone(),
                camera: None,
                width: a.width,
                height: a.height,
                spp: a.spp,
                max_depth: a.depth,
                schedule: proto::Schedule::Dynamic as i32,
                priority: 0,
                cold_cache: true,
                progressive: None,
                speculation: String::new(),
            },
            scene_dir: a.scene.clone(),
            scene_name,
            scene_bytes: manifest.domains.iter().map(|d| d.bytes).sum(),
            domains: manifest.domains.len(),
            csv: a.csv.clone(),
            chart,
        })
    }

    fn names(&self) -> Vec<String> {
        self.schedules.iter().map(|(n, _)| n.clone()).collect()
    }
}

/// Creates the directory of an output file now, so a path that cannot be written is an error
/// before an hour of frames is spent, not after.
fn writable_parent(path: &Path) -> anyhow::Result<()> {
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(parent)
        .with_context(|| format!("{}: creating {}", path.display(), parent.display()))
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

/// The runs of a bench, and why it stopped before the last one, if it did.
struct BenchRuns {
    runs: Vec<RunOutcome>,
    stopped: Option<String>,
}

/// Renders every run of the plan on the cluster at `url`, one at a time, with a line on
/// stderr per run. A failed run is recorded and the bench goes on, unless the cluster itself
/// is no longer the one measured (the coordinator stopped answering, or a worker left or
/// joined): then it stops, keeping the runs so far.
async fn bench(
    url: &str,
    security: &ClientSecurity,
    plan: &Plan,
    in_flight: &JobInFlight,
) -> anyhow::Result<BenchRuns> {
    let mut coord = Coordinator::connect_with(url, security).await?;
    let status = coord
        .cluster_status()
        .await
        .context("asking the coordinator for its workers")?;
    if status.workers.is_empty() {
        bail!("no worker is registered with the coordinator at {url}");
    }
    let order = run_order(plan.schedules.len(), plan.repeats);
    eprintln!(
        "bench: {} schedules x {} repeats = {} frames of {} ({} domains, {}) at {}x{}, {} spp, \
         depth {}, cold caches, on {} workers (one line per frame: the coordinator's wall time, \
         domain loads, rounds)",
        plan.schedules.len(),
        plan.repeats,
        order.len(),
        plan.scene_name,
        plan.domains,
        human(plan.scene_bytes),
        plan.spec.width,
        plan.spec.height,
        plan.spec.spp,
        plan.spec.max_depth,
        status.workers.len()
    );
    let workers = status.workers.len();
    let mut runs = Vec::with_capacity(order.len());
    for (i, &(repeat, s)) in order.iter().enumerate() {
        if i > 0
            && let Some(why) = cluster_changed(&mut coord, workers).await
        {
            let stopped = format!("stopped after run {i} of {}: {why}", order.len());
            eprintln!("{stopped}");
            return Ok(BenchRuns {
                runs,
                stopped: Some(stopped),
            });
        }
        let (name, run) = &plan.schedules[s];
        eprint!(
            "run {}/{}: {name} (repeat {repeat}) ... ",
            i + 1,
            order.len()
        );
        let spec = proto::JobSpec {
            schedule: run.schedule as i32,
            progressive: run.progressive,
            speculation: run.speculation.clone(),
            ..plan.spec.clone()
        };
        let started = Instant::now();
        let (job_id, result) = run_one(&mut coord, spec, in_flight).await;
        let client_seconds = started.elapsed().as_secs_f64();
        eprintln!("{}", progress(&result));
        runs.push(RunOutcome {
            run: i + 1,
            repeat,
            schedule: name.clone(),
            job_id,
            client_seconds,
            result,
        });
    }
    Ok(BenchRuns {
        runs,
        stopped: None,
    })
}

/// Why the cluster is no longer the one the bench started on, if it is not: the coordinator
/// does not answer, or the number of registered workers changed.
async fn cluster_changed(coord: &mut Coordinator, workers: usize) -> Option<String> {
    match coord.cluster_status().await {
        Err(e) => Some(format!("{e:#}")),
        Ok(s) if s.workers.len() != workers => Some(format!(
            "{} workers are registered, the bench started with {workers}",
            s.workers.len()
        )),
        Ok(_) => None,
    }
}

/// Submits one frame and follows it to its end: its job id (once submitted) and its
/// statistics, or why it failed. A job left running by a broken watch is cancelled, so it
/// does not slow the next run.
async fn run_one(
    coord: &mut Coordinator,
    spec: proto::JobSpec,
    in_flight: &JobInFlight,
) -> (Option<String>, Result<ClusterStats, String>) {
    let job_id = match coord.submit(spec).await {
        Ok(id) => id,
        Err(e) => return (None, Err(format!("{e:#}"))),
    };
    in_flight.set(coord, &job_id);
    // The bench's coordinator is its own child: if it dies, the run is over.
    let end = match follow(coord, &job_id, true, Duration::ZERO, None).await {
        Ok(end) => end,
        Err(e) => {
            in_flight.cancel_quietly().await;
            return (Some(job_id), Err(format!("{e:#}")));
        }
    };
    in_flight.clear();
    let stats = ended_ok(&end).and_then(|()| {
        if end.stats_json.is_empty() {
            Err(anyhow!("job {job_id} ended without statistics"))
        } else {
            parse_stats(&end.stats_json)
        }
    });
    (Some(job_id), stats.map_err(|e| format!("{e:#}")))
}

/// The end of a run's progress line: "2.31 s, 48 loads, 12 rounds" or "failed: why".
fn progress(result: &Result<ClusterStats, String>) -> String {
    match result {
        Ok(s) if s.subframe_costs.len() > 1 => format!(
            "{:.2} s, {} loads ({} per subframe), {} rounds",
            s.wall_seconds,
            s.cache.loads,
            s.subframe_costs
                .iter()
                .map(|c| c.loads.to_string())
                .collect::<Vec<_>>()
                .join("+"),
            s.rounds
        ),
        Ok(s) => format!(
            "{:.2} s, {} loads, {} rounds",
            s.wall_seconds, s.cache.loads, s.rounds
        ),
        Err(e) => format!("failed: {e}"),
    }
}

/// Prints the table, the bound, the image check and the failures; writes the CSV and the
/// chart. An error if every run failed or the images differ.
fn report(a: &BenchArgs, plan: &Plan, runs: &[RunOutcome], setup: &Setup) -> anyhow::Result<()> {
    let summaries = summarize(&plan.names(), runs);
    let bandwidth = a
        .storage_bandwidth
        .as_ref()
        .map(|r| r.bytes_per_second as f64);
    let bound = bound(runs, plan.scene_bytes, bandwidth);
    let ok = runs.iter().filter(|r| r.result.is_ok()).count();
    println!("{}", describe(plan, setup, runs));
    println!("{}", bench_table(&summaries, bound.as_ref()));
    println!(
        "{}",
        bound_footnote(
            bound.as_ref(),
            ok,
            plan.scene_bytes,
            a.storage_bandwidth.as_ref().map(|r| r.text.as_str())
        )
    );
    for s in summaries
        .iter()
        .filter(|s| s.ok > 0 && !s.errors.is_empty())
    {
        println!(
            "note: {} of {} {} runs failed: {}",
            s.runs - s.ok,
            s.runs,
            s.schedule,
            s.errors.join("; ")
        );
    }
    if a.progressive.is_some() {
        println!(
            "progressive against one pass (medians; first preview: when the first subframe's \
             last tile came back, from the frame's start; loads per subframe: summed over \
             workers, with the subframe's samples per pixel):"
        );
        println!("{}", progressive_table(&compare(&plan.names(), runs)));
    }
    let check = check_hashes(runs);
    println!("{}", hash_verdict(&check));
    if let Some(csv) = &plan.csv {
        write_runs_file(csv, runs, setup)?;
        println!("wrote {}", csv.display());
    }
    if let Some(chart) = &plan.chart {
        if ok == 0 {
            eprintln!("no chart: no run succeeded");
        } else {
            crate::bench::chart::write_chart(chart, &chart_title(plan, setup, runs), &summaries)?;
            println!("wrote {}", chart.display());
        }
    }
    if ok == 0 {
        bail!("every run failed");
    }
    if matches!(check, HashCheck::Differ(_)) {
        bail!("the schedules rendered different images (listed above)");
    }
    Ok(())
}

/// Workers of the bench: those started, or those that took part in the first successful run
/// on an existing cluster.
fn workers_of(setup: &Setup, runs: &[RunOutcome]) -> Option<usize> {
    setup
        .workers
        .or_else(|| runs.iter().find_map(|r| r.stats().map(|s| s.workers)))
}

/// The line above the table: what was measured.
fn describe(plan: &Plan, setup: &Setup, runs: &[RunOutcome]) -> String {
    let workers = workers_of(setup, runs).map_or("?".to_string(), |w| w.to_string());
    let mut text = format!(
        "scene {} ({} domains, {}), {}x{}, {} spp, depth {}, {} workers",
        plan.scene_name,
        plan.domains,
        human(plan.scene_bytes),
        setup.width,
        setup.height,
        setup.spp,
        setup.depth,
        workers
    );
    if let (Some(t), Some(c)) = (setup.threads_per_worker, setup.cache_bytes_per_worker) {
        text.push_str(&format!(
            " x {t} thread{}, {} cache each",
            if t == 1 { "" } else { "s" },
            human(c)
        ));
    }
    if !setup.replicate.is_empty() {
        text.push_str(&format!(", replicate {}", setup.replicate));
    }
    if !setup.storage_bandwidth.is_empty() {
        text.push_str(&format!(", storage {}", setup.storage_bandwidth));
    }
    if !setup.storage_latency.is_empty() {
        text.push_str(&format!(" + {} per load", setup.storage_latency));
    }
    text.push_str(&format!(
        ", {} repeat{}, cold caches",
        plan.repeats,
        if plan.repeats == 1 { "" } else { "s" }
    ));
    text
}

/// The chart's title: scene, workers, cache.
fn chart_title(plan: &Plan, setup: &Setup, runs: &[RunOutcome]) -> String {
    let workers = workers_of(setup, runs).map_or("?".to_string(), |w| w.to_string());
    let cache = setup
        .cache_bytes_per_worker
        .map_or(String::new(), |c| format!(", {} cache each", human(c)));
    format!(
        "{} ({} domains, {}), {} workers{cache}, {}x{}, {} spp",
        plan.scene_name,
        plan.domains,
        human(plan.scene_bytes),
        workers,
        setup.width,
        setup.height,
        setup.spp
    )
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    #[derive(Parser)]
    struct T {
        #[command(flatten)]
        a: BenchArgs,
    }

    fn parse(args: &[&str]) -> Result<BenchArgs, String> {
        T::try_parse_from(
            ["bench", "--scene", "/s/nbody"]
                .into_iter()
                .chain(args.iter().copied()),
        )
        .map(|t| t.a)
        .map_err(|e| e.to_string())
    }

    #[test]
    fn defaults_compare_four_schedules_three_times_at_512() {
        let a = parse(&[]).unwrap();
        assert_eq!(
            a.schedules,
            [
                proto::Schedule::Dynamic,
                proto::Schedule::Predictive,
                proto::Schedule::ImagePlane,
                proto::Schedule::Domain
            ]
            .map(|s| (s, String::new()))
        );
        assert_eq!(
            (a.workers, a.repeats, a.width, a.height, a.spp, a.depth),
            (4, 3, 512, 512, 4, 3)
        );
        assert!(a.cache_bytes.is_none() && a.threads.is_none() && a.coordinator.is_none());
        assert!(coordinator_extra(&a).is_empty() && worker_extra(&a).is_empty());
        assert!(a.progressive.is_none());
        let p = parse(&["--progressive", "doubling"]).unwrap();
        assert_eq!(p.progressive, Some(Progressive::Doubling));
        assert!(parse(&["--progressive", "none"]).is_err());
    }

    #[test]
    fn storage_and_replication_flags_are_passed_through_only_when_given() {
        let a = parse(&[
            "--storage-bandwidth",
            "100MiB/s",
            "--storage-latency",
            "5ms",
            "--replicate",
            "none",
            "--cache-bytes",
            "8MiB",
            "--schedules",
            "domain,dynamic,predictive:predicted",
        ])
        .unwrap();
        assert_eq!(
            worker_extra(&a),
            [
                "--storage-bandwidth",
                "100MiB/s",
                "--storage-latency",
                "5ms"
            ]
            .map(std::ffi::OsString::from)
        );
        assert_eq!(
            coordinator_extra(&a),
            ["--replicate", "none"].map(std::ffi::OsString::from)
        );
        assert_eq!(a.cache_bytes, Some(8 << 20));
        assert_eq!(
            a.schedules,
            [
                (proto::Schedule::Domain, ""),
                (proto::Schedule::Dynamic, ""),
                (proto::Schedule::Predictive, "predicted")
            ]
            .map(|(s, setting)| (s, setting.to_string()))
        );
    }

    #[test]
    fn rates_take_units_and_an_optional_per_second() {
        assert_eq!(
            parse_rate("100MiB/s"),
            Ok(Rate {
                text: "100MiB/s".into(),
                bytes_per_second: 100 << 20
            })
        );
        assert_eq!(parse_rate("1GiB").unwrap().bytes_per_second, 1 << 30);
        assert!(parse_rate("fast").unwrap_err().contains("100MiB/s"));
        assert!(parse_rate("0/s").unwrap_err().contains("more than zero"));
    }

    #[test]
    fn bad_values_are_refused_by_the_parser() {
        assert!(
            parse(&["--schedules", "fastest"])
                .unwrap_err()
                .contains("known")
        );
        assert!(parse(&["--schedules", "dynamic:full"]).is_err());
        assert!(parse(&["--repeats", "0"]).is_err());
        assert!(parse(&["--replicate", "all"]).is_err());
    }

    #[test]
    fn a_plan_refuses_repeated_schedules_missing_scenes_and_non_png_charts() {
        let tmp = tempfile::tempdir().unwrap();
        let scene = tmp.path().join("nothing");
        let a = parse(&["--schedules", "dynamic,dynamic"]).unwrap();
        let err = Plan::new(&BenchArgs {
            scene: scene.clone(),
            ..a
        })
        .err()
        .unwrap()
        .to_string();
        assert!(err.contains("twice"), "{err}");
        let a = parse(&[]).unwrap();
        let err = format!(
            "{:#}",
            Plan::new(&BenchArgs {
                scene: scene.clone(),
                ..a
            })
            .err()
            .unwrap()
        );
        assert!(err.contains("not a usable prepared scene"), "{err}");
        let a = parse(&["--csv", "out.csv", "--chart", "chart.jpg"]).unwrap();
        let err = Plan::new(&BenchArgs { scene, ..a })
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("name it .png"), "{err}");
    }

    #[test]
    fn output_directories_are_made_up_front() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("a/b/out.csv");
        writable_parent(&out).unwrap();
        assert!(tmp.path().join("a/b").is_dir());
        assert!(writable_parent(Path::new("out.csv")).is_ok());
        let blocker = tmp.path().join("file");
        std::fs::write(&blocker, b"").unwrap();
        let err = format!(
            "{:#}",
            writable_parent(&blocker.join("out.csv")).unwrap_err()
        );
        assert!(err.contains("creating"), "{err}");
    }
}
