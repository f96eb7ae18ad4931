//! `rayfarm sim`: the cluster simulated in this process on virtual time (`rayfarm-sim`): a
//! clean run per worker count and schedule, its figures and image hash, and with `--faults` a
//! run per seed whose invariants are checked. Exits non-zero naming every seed that broke
//! one, with the command that replays it. `rayfarm sim calibrate` measures the cost model's
//! prices on this machine and writes the file `--cost` reads.
//!
//! The parts: this module holds the options and the runs, [`calibrate`] the measurement of the
//! prices, [`report`] the table, the CSV rows and the summary of the fault seeds.

use std::io::Write;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, bail};
use clap::{Args, Subcommand};
use rayfarm_node::job::{parse_schedule, schedule_name};
use rayfarm_node::proto::Schedule;
use rayfarm_sim::net::LinkModel;
use rayfarm_sim::node::QueueCaps;
use rayfarm_sim::world::open_scene;
use rayfarm_sim::{
    ComputeCost, CostModel, FaultPlan, Outcome, RECONNECT, ReportHold, SimConfig, StorageModel,
    default_max_events, simulate,
};
use rayon::prelude::*;

use crate::units;
use crate::view::FrameArgs;

mod calibrate;
mod chart;
mod report;
mod transport;

pub use calibrate::CalibrateArgs;
use calibrate::run_calibrate;
pub use chart::ChartArgs;
use chart::run_chart;
use report::{Spread, Summary, print_row, write_csv};

/// Options of `rayfarm sim`.
#[derive(Args, Clone, Debug)]
#[command(args_conflicts_with_subcommands = true)]
pub struct SimArgs {
    #[command(subcommand)]
    pub command: Option<SimCommand>,
    /// Scene directory (holding scene.toml).
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Workers at the start, or several counts separated by commas (e.g. 64,256,1024): a run
    /// of every schedule at each.
    #[arg(long, default_value = "3", value_parser = parse_counts)]
    pub workers: Counts,
    /// Schedule, or several separated by commas (image-plane, domain, dynamic, hybrid,
    /// predictive).
    #[arg(long, default_value = "dynamic")]
    pub schedule: String,
    #[command(flatten)]
    pub model: ModelArgs,
    /// Jobs of the same frame the same workers render before the measured one, each with its
    /// schedule, separated by commas (e.g. image-plane): the measured job starts with the
    /// domains they left mapped and the machines they left, as on a farm that has rendered
    /// before. Every job's image is checked; faults fall anywhere in the sequence.
    #[arg(long, value_delimiter = ',', value_parser = parse_schedule_arg)]
    pub warm_up: Vec<Schedule>,
    /// Run every seed of --seeds with its faults and check the invariants.
    #[arg(long)]
    pub faults: bool,
    /// Seeds to run with --faults: A..B (B excluded) or one seed.
    #[arg(long, default_value = "0..100", value_parser = parse_seeds)]
    pub seeds: std::ops::Range<u64>,
    /// After each clean run, run the frame again once per seed of A..B (or one seed) with
    /// each pass's wait for its tracing thread (`--pass-start-us`, its mean) and each peer
    /// bundle's wait for the engine (`--bundle-take-us`) drawn at random from the seed: how
    /// far the frame's time, loads and rays migrated move with timing alone, as a real
    /// cluster's repeats move (`rayfarm bench --repeats`). Prints every run and the medians
    /// with their range; every image must be the clean run's.
    #[arg(long, value_parser = parse_seeds, conflicts_with = "faults")]
    pub timing_seeds: Option<std::ops::Range<u64>>,
    /// Liveness bound of a faulty run in virtual microseconds [default: twenty clean frames
    /// and every deadline twice].
    #[arg(long)]
    pub bound_us: Option<u64>,
    /// Also write one row per run here (CSV).
    #[arg(long)]
    pub csv: Option<PathBuf>,
    /// After each clean run, hand every call the coordinator machine was given to a new
    /// machine alone, in order, and print the CPU it takes: what a process that only
    /// coordinates spends on the frame, beside the busy time the cost model charged. The
    /// calls are kept in memory during the run.
    #[arg(long)]
    pub replay_coordinator: bool,
}

/// What `rayfarm sim` does besides simulating.
#[derive(Subcommand, Clone, Debug)]
pub enum SimCommand {
    /// Measure the cost model's prices on this machine (per-segment trace cost, radiance and
    /// shadow apart, per camera and volume sample, per pass, per planning round) and write
    /// them to the file `rayfarm sim --cost` reads.
    Calibrate(Box<CalibrateArgs>),
    /// Draw domain loads and simulated frame time against the worker count, a line per
    /// schedule, from the CSV files of earlier runs.
    Chart(ChartArgs),
}

/// The simulated frame, the workers' settings and the cost model (every price and bandwidth a
/// flag; the defaults describe a commodity cluster: 10 Gb/s Ethernet, a parallel file system of
/// 10 GB/s aggregate with each node's link at 1.25 GB/s, and cores priced as this project's
/// VM measured them).
#[derive(Args, Clone, Debug)]
pub struct ModelArgs {
    #[command(flatten)]
    pub frame: FrameArgs,
    /// Each worker's domain cache budget, e.g. 512MiB.
    #[arg(long, value_parser = units::bytes, default_value = "4GiB")]
    pub cache_bytes: u64,
    /// Camera rays a worker issues while fewer rays than this are queued on it.
    #[arg(long, default_value_t = 4096)]
    pub wave_rays: usize,
    /// Most rays a worker traces in one pass.
    #[arg(long, default_value_t = 2048)]
    pub pass_rays: usize,
    /// Tracing threads each worker is costed with (the cost model's divisor).
    #[arg(long, default_value_t = 1)]
    pub threads: u32,
    /// Cores shared by all simulated workers: every pass's computing and its shell's
    /// handling of bundles and finished passes are sliced between them, as the operating
    /// system slices them (as when the whole cluster runs on one machine, like `rayfarm
    /// bench`'s); off by default, each worker on machines of its own.
    #[arg(long)]
    pub cores: Option<u32>,
    /// Microseconds a pass waits after the worker hands it over before a tracing thread
    /// starts it (delay, no core time): 0 for workers with cores of their own; where the
    /// whole cluster shares a few cores, what `rayfarm bench` measures as "pass waiting for
    /// a tracing thread" over its passes (about 1,000 with 8 workers on 2 cores).
    #[arg(long, default_value_t = 0)]
    pub pass_start_us: u64,
    /// Microseconds a peer bundle waits, after its stream has decoded and acknowledged it,
    /// for the worker's engine to take it in (delay, no core time): 0 for workers with cores
    /// of their own; where the whole cluster shares a few cores, the mean the workers' debug
    /// logs show from a machine's send to the receiver's machine taking the bundle, less the
    /// simulator's own under the same model (`bench/validation/transit.py` reads both).
    #[arg(long, default_value_t = 0)]
    pub bundle_take_us: u64,
    /// Prices of computing, from `rayfarm sim calibrate` [default: the ones measured on this
    /// project's VM, README "Simulator"].
    #[arg(long)]
    pub cost: Option<PathBuf>,
    /// Aggregate bandwidth of the shared storage, shared by every reader, bytes per second
    /// (binary units: 1GiB/s) [default: 10 GB/s, a few parallel file system servers].
    #[arg(long, value_parser = rayfarm_core::units::parse_rate, default_value = "10000000000")]
    pub storage_bandwidth: u64,
    /// Most bytes per second one node reads from the storage; 0 for no cap [default: 1.25
    /// GB/s, a 10 Gb/s link].
    #[arg(long, value_parser = units::bytes, default_value = "1250000000")]
    pub node_storage_bandwidth: u64,
    /// Microseconds to open one domain on the storage.
    #[arg(long, default_value_t = 1000)]
    pub storage_latency_us: u64,
    /// Charge every domain load this many bytes instead of the domain's size here (e.g. the
    /// paper's 650 GB over its domains), so this scene stands for a larger one.
    #[arg(long, value_parser = units::bytes)]
    pub charge_domain_bytes: Option<u64>,
    /// One-way network latency of a message, microseconds.
    #[arg(long, default_value_t = 100)]
    pub net_latency_us: u64,
    /// Bytes per second each node's NIC sends [default: 1.25 GB/s, 10 Gb/s Ethernet].
    #[arg(long, value_parser = rayfarm_core::units::parse_rate, default_value = "1250000000")]
    pub nic_bandwidth: u64,
    /// The predictive schedule's speculation setting (as `submit --speculation`: full, none,
    /// ahead:N, predicted, predicted:P); other schedules ignore it [default: full].
    #[arg(long, value_parser = check_speculation)]
    pub speculation: Option<String>,
    /// Workers load their next domains while they trace (as `submit --prefetch`; the dynamic
    /// and predictive schedules): a prefetch's bytes come over the node's storage line.
    #[arg(long)]
    pub prefetch: bool,
    /// Most events one run may take before it stops unfinished [default: 1,000,000 a worker,
    /// at least 20,000,000].
    #[arg(long)]
    pub max_events: Option<u64>,
    /// Heartbeat period of the simulated workers, milliseconds; the deadlines follow it: a
    /// worker silent for ten periods is dropped, a peer that leaves a bundle unacknowledged
    /// for half a period is reported. The default suits frames of milliseconds; a frame of
    /// simulated minutes wants about a second, since every heartbeat is an event and a
    /// message (1,024 workers at 20 ms are 51,200 a virtual second).
    #[arg(long, default_value_t = 20, value_parser = clap::value_parser!(u64).range(4..=3_600_000))]
    pub heartbeat_ms: u64,
    /// A peer that leaves a bundle unacknowledged this many milliseconds is reported, as the
    /// worker's `--peer-ack-timeout-ms` [default: half a heartbeat]. The workers' own wave
    /// sizes send bursts whose decoding on one stream takes longer than half a heartbeat;
    /// the real worker waits 30 s (30000).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..=86_400_000))]
    pub peer_ack_timeout_ms: Option<u64>,
    /// A busy worker is told of new holders at most once per this many milliseconds, as the
    /// coordinator's `--holders-interval-ms` [default: 0, after every round, the coordinator's
    /// default]. Every asynchronous round changes some holders, and one message a round to
    /// every busy worker was 91% of a 256-worker dynamic frame's messages; a frame of
    /// simulated minutes may take 100 (README "Simulator": what it saves and what it costs).
    #[arg(long, value_parser = clap::value_parser!(u64).range(0..=60_000))]
    pub holders_interval_ms: Option<u64>,
    /// The dynamic schedule copies a busy domain onto a free cache slot only if every holder
    /// keeps at least this many of its rays, as the coordinator's `--copy-rays` (the same
    /// default).
    #[arg(long, default_value_t = rayfarm_core::schedule::dynamic::DEFAULT_COPY_RAYS)]
    pub copy_rays: u64,
    /// A worker planned by an asynchronous round with nothing to trace yet waits up to this
    /// many milliseconds for the rays its plan moves to it before it reports again, as the
    /// coordinator's `--report-hold-ms` [default: the coordinator's, 50]. 0 reports at once
    /// (README "Simulator": what that cost at 256 workers and more).
    #[arg(long, value_parser = clap::value_parser!(u64).range(0..=10_000))]
    pub report_hold_ms: Option<u64>,
    /// ...or this many microseconds for each worker of the frame when that is longer, as the
    /// coordinator's `--report-hold-per-worker-us` [default: the coordinator's, 100].
    #[arg(long, value_parser = clap::value_parser!(u64).range(0..=10_000))]
    pub report_hold_per_worker_us: Option<u64>,
}

impl ModelArgs {
    /// The report hold the flags ask for, the coordinator's default where they are silent.
    fn report_hold(&self) -> ReportHold {
        let default = ReportHold::DEFAULT;
        ReportHold {
            least: self
                .report_hold_ms
                .map_or(default.least, Duration::from_millis),
            per_member: self
                .report_hold_per_worker_us
                .map_or(default.per_member, Duration::from_micros),
        }
    }
}

fn check_speculation(s: &str) -> Result<String, String> {
    rayfarm_core::schedule::speculation_depth::parse_setting(s).map(|_| s.to_string())
}

impl ModelArgs {
    fn cost(&self) -> anyhow::Result<CostModel> {
        let compute = match &self.cost {
            Some(p) => ComputeCost::load(p).map_err(anyhow::Error::msg)?,
            None => ComputeCost::default(),
        };
        Ok(CostModel {
            compute,
            threads: self.threads.max(1),
            cores: self.cores.map(|c| c.max(1)),
            pass_start: Duration::from_micros(self.pass_start_us),
            bundle_take: Duration::from_micros(self.bundle_take_us),
        })
    }

    fn storage(&self) -> StorageModel {
        StorageModel {
            latency: Duration::from_micros(self.storage_latency_us),
            aggregate_bytes_per_second: self.storage_bandwidth,
            node_bytes_per_second: Some(self.node_storage_bandwidth).filter(|&b| b > 0),
            charge_domain_bytes: self.charge_domain_bytes,
        }
    }

    /// The flags that give this model, for a replay command.
    fn flags(&self) -> String {
        let mut f = format!(
            "--width {} --height {} --spp {} --depth {} --cache-bytes {} --wave-rays {} \
             --pass-rays {} --threads {} --storage-bandwidth {} --node-storage-bandwidth {} \
             --storage-latency-us {} --net-latency-us {} --nic-bandwidth {}",
            self.frame.width,
            self.frame.height,
            self.frame.spp,
            self.frame.depth,
            self.cache_bytes,
            self.wave_rays,
            self.pass_rays,
            self.threads,
            self.storage_bandwidth,
            self.node_storage_bandwidth,
            self.storage_latency_us,
            self.net_latency_us,
            self.nic_bandwidth
        );
        if let Some(b) = self.charge_domain_bytes {
            f.push_str(&format!(" --charge-domain-bytes {b}"));
        }
        if let Some(c) = self.cores {
            f.push_str(&format!(" --cores {c}"));
        }
        if self.pass_start_us > 0 {
            f.push_str(&format!(" --pass-start-us {}", self.pass_start_us));
        }
        if self.bundle_take_us > 0 {
            f.push_str(&format!(" --bundle-take-us {}", self.bundle_take_us));
        }
        if let Some(p) = &self.cost {
            f.push_str(&format!(" --cost {}", p.display()));
        }
        if let Some(s) = &self.speculation {
            f.push_str(&format!(" --speculation {s}"));
        }
        if self.prefetch {
            f.push_str(" --prefetch");
        }
        if let Some(n) = self.max_events {
            f.push_str(&format!(" --max-events {n}"));
        }
        if self.heartbeat_ms != DEFAULT_HEARTBEAT_MS {
            f.push_str(&format!(" --heartbeat-ms {}", self.heartbeat_ms));
        }
        if let Some(ms) = self.peer_ack_timeout_ms {
            f.push_str(&format!(" --peer-ack-timeout-ms {ms}"));
        }
        if let Some(ms) = self.holders_interval_ms {
            f.push_str(&format!(" --holders-interval-ms {ms}"));
        }
        if let Some(ms) = self.report_hold_ms {
            f.push_str(&format!(" --report-hold-ms {ms}"));
        }
        if let Some(us) = self.report_hold_per_worker_us {
            f.push_str(&format!(" --report-hold-per-worker-us {us}"));
        }
        f
    }

    /// The deadlines of the simulated cluster, from the heartbeat period (the
    /// acknowledgement's as given, if it is).
    fn deadlines(&self) -> Deadlines {
        let mut d = Deadlines::from_heartbeat(Duration::from_millis(self.heartbeat_ms));
        if let Some(ms) = self.peer_ack_timeout_ms {
            d.ack = Duration::from_millis(ms);
        }
        if let Some(ms) = self.holders_interval_ms {
            d.holders = Duration::from_millis(ms);
        }
        d
    }

    fn config(
        &self,
        scene: &std::path::Path,
        workers: usize,
        schedule: Schedule,
    ) -> anyhow::Result<SimConfig> {
        Ok(SimConfig {
            scene: scene.to_path_buf(),
            workers,
            schedule,
            warm_up: Vec::new(),
            width: self.frame.width,
            height: self.frame.height,
            spp: self.frame.spp,
            depth: self.frame.depth,
            cache_bytes: self.cache_bytes,
            wave_rays: self.wave_rays.max(1),
            pass_rays: self.pass_rays.max(1),
            links: LinkModel {
                latency: Duration::from_micros(self.net_latency_us),
                bytes_per_second: self.nic_bandwidth,
            },
            cost: self.cost()?,
            storage: self.storage(),
            measure: false,
            caps: QueueCaps {
                queue_bytes: 512 << 20,
                spill_bytes: 8 << 30,
            },
            ack_deadline: self.deadlines().ack,
            heartbeat: self.deadlines().heartbeat,
            worker_timeout: self.deadlines().worker_timeout,
            holders_interval: self.deadlines().holders,
            report_hold: self.report_hold(),
            copy_rays: self.copy_rays,
            disk_latency: DISK_LATENCY,
            speculation: match schedule {
                Schedule::Predictive => self.speculation.clone().unwrap_or_default(),
                _ => String::new(),
            },
            prefetch: self.prefetch,
            max_events: self
                .max_events
                .unwrap_or_else(|| default_max_events(workers)),
            replay_coordinator: false,
            timing_seed: None,
        })
    }
}

fn parse_schedule_arg(s: &str) -> Result<Schedule, String> {
    parse_schedule(s.trim())
}

/// Worker counts, as given.
#[derive(Clone, Debug)]
pub struct Counts(pub Vec<usize>);

fn parse_counts(s: &str) -> Result<Counts, String> {
    let counts: Vec<usize> = s
        .split(',')
        .map(|c| {
            c.trim()
                .parse::<usize>()
                .ok()
                .filter(|&n| (1..=MAX_WORKERS).contains(&n))
                .ok_or_else(|| format!("worker count {c:?}: give 1 to {MAX_WORKERS}"))
        })
        .collect::<Result<_, _>>()?;
    Ok(Counts(counts))
}

/// Most simulated workers in one run.
const MAX_WORKERS: usize = 65_536;

fn parse_seeds(s: &str) -> Result<std::ops::Range<u64>, String> {
    let bad = || format!("seeds {s:?}: give A..B (B excluded) or one seed");
    match s.split_once("..") {
        Some((a, b)) => {
            let (a, b) = (a.parse().map_err(|_| bad())?, b.parse().map_err(|_| bad())?);
            if a >= b {
                return Err(format!("seeds {s:?}: empty range"));
            }
            Ok(a..b)
        }
        None => {
            let a: u64 = s.parse().map_err(|_| bad())?;
            Ok(a..a.saturating_add(1))
        }
    }
}

/// `--heartbeat-ms`'s default: deadlines scaled to frames of milliseconds (20 ms heartbeats,
/// a worker dropped after 200 ms of silence, a peer reported after 10 ms without an
/// acknowledgement), the ones every fault seed of `tests/sim.rs` was drawn with.
const DEFAULT_HEARTBEAT_MS: u64 = 20;

/// Virtual deadlines of the simulated cluster, all following the heartbeat period so that a
/// frame of simulated minutes need not carry millisecond heartbeats.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Deadlines {
    heartbeat: Duration,
    /// A worker silent this long is dropped: ten heartbeats.
    worker_timeout: Duration,
    /// A peer that acknowledges nothing this long is reported: half a heartbeat.
    ack: Duration,
    /// Busy workers are told new holders at most once per this: after every round unless
    /// `--holders-interval-ms` says otherwise (at 8 workers 1-2 ms made the predictive frame
    /// 13% longer, README "Simulator").
    holders: Duration,
}

impl Deadlines {
    fn from_heartbeat(heartbeat: Duration) -> Self {
        Deadlines {
            heartbeat,
            worker_timeout: heartbeat * 10,
            ack: heartbeat / 2,
            holders: Duration::ZERO,
        }
    }
}

/// A job record's write to the coordinator's store (a redb commit with its fsync).
const DISK_LATENCY: Duration = Duration::from_millis(2);

impl SimArgs {
    /// The command that replays `seed` of `schedule` at `workers` alone.
    fn replay(
        &self,
        scene: &std::path::Path,
        workers: usize,
        schedule: Schedule,
        seed: u64,
    ) -> String {
        let warm_up = if self.warm_up.is_empty() {
            String::new()
        } else {
            let names: Vec<&str> = self.warm_up.iter().map(|&s| schedule_name(s)).collect();
            format!(" --warm-up {}", names.join(","))
        };
        format!(
            "rayfarm sim --scene {} --workers {workers} --schedule {}{warm_up} {} --faults --seeds {seed}..{}{}",
            scene.display(),
            schedule_name(schedule),
            self.model.flags(),
            seed + 1,
            self.bound_us
                .map_or(String::new(), |b| format!(" --bound-us {b}"))
        )
    }
}

/// The liveness bound of a faulty run whose clean run took `clean`: twenty clean frames, time
/// for every deadline to expire twice (the accusation grace is 2 s), and for the workers to
/// register again after a coordinator crash (their reconnect delay; the crashed coordinator
/// is down less than a clean frame).
fn bound(clean: Duration, d: Deadlines) -> Duration {
    clean * 20 + (d.ack + d.worker_timeout + Duration::from_secs(2)) * 2 + RECONNECT
}

/// How long a clean run may take in virtual time: a day, since a domain charged at a stated
/// size (`--charge-domain-bytes`) makes frames of simulated hours (at 20 GiB a domain, 4
/// image-plane workers on a 1.25 GB/s link each take about an hour).
const CLEAN_BOUND: Duration = Duration::from_secs(24 * 3600);

pub fn run(a: SimArgs) -> anyhow::Result<()> {
    match a.command.clone() {
        Some(SimCommand::Calibrate(c)) => return run_calibrate(*c),
        Some(SimCommand::Chart(c)) => return run_chart(c),
        None => {}
    }
    let Some(scene_dir) = a.scene.clone() else {
        bail!("--scene is required");
    };
    if a.timing_seeds.is_some() && a.model.pass_start_us == 0 && a.model.bundle_take_us == 0 {
        bail!(
            "--timing-seeds draws each pass's wait for its tracing thread around \
             --pass-start-us and each bundle's wait for the engine around --bundle-take-us: \
             give one (what `rayfarm bench` measures as \"pass waiting for a tracing thread\")"
        );
    }
    let schedules: Vec<Schedule> = a
        .schedule
        .split(',')
        .map(|s| parse_schedule(s.trim()).map_err(anyhow::Error::msg))
        .collect::<anyhow::Result<_>>()?;
    let scene = open_scene(&scene_dir)
        .map_err(anyhow::Error::msg)
        .with_context(|| format!("scene {}", scene_dir.display()))?;
    let domains = scene.manifest.domains.len();
    let mut csv = match &a.csv {
        Some(p) => {
            let mut f =
                std::fs::File::create(p).with_context(|| format!("creating {}", p.display()))?;
            writeln!(
                f,
                "workers,schedule,seed,faults,virtual_ms,loads,bytes_loaded,segments,rays_migrated,peer_bytes,messages,rounds,planning_ms,wall_seconds,image_hash,violations,passes,{}",
                report::TIME_COLUMNS
            )?;
            Some(f)
        }
        None => None,
    };
    let storage = a.model.storage();
    println!(
        "scene {} ({domains} domains), {}x{}, {} spp, depth {}; storage {}/s aggregate{}, {} us a \
         domain{}; network {} us, {}/s per NIC",
        scene_dir.display(),
        a.model.frame.width,
        a.model.frame.height,
        a.model.frame.spp,
        a.model.frame.depth,
        units::human(storage.aggregate_bytes_per_second),
        storage
            .node_bytes_per_second
            .map_or(String::new(), |b| format!(
                ", {}/s per node",
                units::human(b)
            )),
        a.model.storage_latency_us,
        storage
            .charge_domain_bytes
            .map_or(String::new(), |b| format!(
                "; every domain load CHARGED {} (not its size here)",
                units::human(b)
            )),
        a.model.net_latency_us,
        units::human(a.model.nic_bandwidth),
    );
    if !a.warm_up.is_empty() {
        let names: Vec<&str> = a.warm_up.iter().map(|&s| schedule_name(s)).collect();
        println!(
            "each run renders the frame with {} first, on the same workers (virtual ms: to the \
             end of the last job)",
            names.join(", then ")
        );
    }
    println!(
        "{:<12} {:>7} {:>12} {:>7} {:>12} {:>10} {:>10} {:>12} {:>9} {:>7} {:>8}  image hash",
        "schedule",
        "workers",
        "virtual ms",
        "loads",
        "bytes loaded",
        "segments",
        "migrated",
        "peer bytes",
        "messages",
        "rounds",
        "plan %",
    );
    let mut failed: Vec<String> = Vec::new();
    for &workers in &a.workers.0 {
        for &schedule in &schedules {
            let config = SimConfig {
                warm_up: a.warm_up.clone(),
                replay_coordinator: a.replay_coordinator,
                ..a.model.config(&scene_dir, workers, schedule)?
            };
            let wall = std::time::Instant::now();
            let clean = simulate(
                &config,
                scene.clone(),
                &FaultPlan::clean(),
                CLEAN_BOUND,
                None,
            )
            .map_err(anyhow::Error::msg)?;
            let wall = wall.elapsed().as_secs_f64();
            print_row(schedule, workers, &clean, wall);
            if let Some(f) = csv.as_mut() {
                write_csv(f, workers, schedule, "clean", "none", &clean, wall)?;
            }
            if !clean.violations.is_empty() || clean.frame_time.is_none() {
                for v in &clean.violations {
                    eprintln!("{}: clean run: {v}", schedule_name(schedule));
                }
                failed.push(format!("{} clean run", schedule_name(schedule)));
                continue;
            }
            if let Some(seeds) = &a.timing_seeds {
                let runs: Vec<(u64, Result<Outcome, String>, f64)> = seeds
                    .clone()
                    .into_par_iter()
                    .map(|seed| {
                        let wall = std::time::Instant::now();
                        let config = SimConfig {
                            replay_coordinator: false,
                            timing_seed: Some(seed),
                            ..config.clone()
                        };
                        let out = simulate(
                            &config,
                            scene.clone(),
                            &FaultPlan::clean(),
                            CLEAN_BOUND,
                            clean.image_hash.as_deref(),
                        );
                        (seed, out, wall.elapsed().as_secs_f64())
                    })
                    .collect();
                let mut spread = Spread::default();
                for (seed, out, wall) in runs {
                    let out = out.map_err(|e| anyhow::anyhow!("timing seed {seed}: {e}"))?;
                    eprint!("timing seed {seed}: ");
                    print_row(schedule, workers, &out, wall);
                    if let Some(f) = csv.as_mut() {
                        let seed = seed.to_string();
                        write_csv(f, workers, schedule, &seed, "timing only", &out, wall)?;
                    }
                    for v in &out.violations {
                        eprintln!("{} timing seed {seed}: {v}", schedule_name(schedule));
                    }
                    if !out.violations.is_empty() || out.frame_time.is_none() {
                        failed.push(format!("{} timing seed {seed}", schedule_name(schedule)));
                    }
                    spread.add(&out);
                }
                spread.print(schedule, workers, seeds);
            }
            if !a.faults {
                continue;
            }
            let span = clean.frame_time.unwrap_or_default();
            let hash = clean.image_hash.clone();
            let bound = a
                .bound_us
                .map_or(bound(span, a.model.deadlines()), Duration::from_micros);
            // The seeds' coordinators are not replayed (a crash ends the recording anyway).
            let config = SimConfig {
                replay_coordinator: false,
                ..config.clone()
            };
            let runs: Vec<(FaultPlan, Result<Outcome, String>)> = a
                .seeds
                .clone()
                .into_par_iter()
                .map(|seed| {
                    let plan = FaultPlan::from_seed(seed, workers, span);
                    let out = simulate(&config, scene.clone(), &plan, bound, hash.as_deref());
                    (plan, out)
                })
                .collect();
            let mut summary = Summary::default();
            for (plan, out) in &runs {
                let out = out
                    .as_ref()
                    .map_err(|e| anyhow::anyhow!("seed {}: {e}", plan.seed))?;
                summary.add(out, span);
                if let Some(f) = csv.as_mut() {
                    write_csv(
                        f,
                        workers,
                        schedule,
                        &plan.seed.to_string(),
                        &plan.describe(),
                        out,
                        0.0,
                    )?;
                }
                if !out.violations.is_empty() {
                    eprintln!(
                        "FAILED seed {} ({}; faults: {}):",
                        plan.seed,
                        schedule_name(schedule),
                        plan.describe()
                    );
                    for v in &out.violations {
                        eprintln!("  {v}");
                    }
                    eprintln!(
                        "  replay: {}",
                        a.replay(&scene_dir, workers, schedule, plan.seed)
                    );
                    failed.push(format!("{} seed {}", schedule_name(schedule), plan.seed));
                }
            }
            summary.print(schedule, &a.seeds);
        }
    }
    // Measurements of this machine go to stderr: stdout is the simulation's, the same for
    // the same seed to the byte.
    eprintln!(
        "peak RSS of this process: {}",
        units::human(rayfarm_core::render::stats::peak_rss_bytes())
    );
    if !failed.is_empty() {
        bail!("invariants broken: {}", failed.join(", "));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The default heartbeat keeps the deadlines every fault seed was drawn with, and a longer
    /// one scales all of them.
    #[test]
    fn deadlines_follow_the_heartbeat() {
        let d = Deadlines::from_heartbeat(Duration::from_millis(DEFAULT_HEARTBEAT_MS));
        assert_eq!(d.heartbeat, Duration::from_millis(20));
        assert_eq!(d.worker_timeout, Duration::from_millis(200));
        assert_eq!(d.ack, Duration::from_millis(10));
        assert_eq!(d.holders, Duration::ZERO, "the coordinator's default");
        let d = Deadlines::from_heartbeat(Duration::from_secs(1));
        assert_eq!(d.worker_timeout, Duration::from_secs(10));
        assert_eq!(d.ack, Duration::from_millis(500));
        assert_eq!(
            bound(Duration::from_secs(1), d),
            Duration::from_secs(20) + Duration::from_millis(25_000) + RECONNECT
        );
    }
}
