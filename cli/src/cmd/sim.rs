//! `rayfarm sim`: the cluster simulated in this process on virtual time (`rayfarm-sim`): a
//! clean run per schedule, its figures and image hash, and with `--faults` a run per seed
//! whose invariants are checked. Exits non-zero naming every seed that broke one, with the
//! command that replays it.

use std::io::Write;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, bail};
use clap::Args;
use rayfarm_node::job::{parse_schedule, schedule_name};
use rayfarm_node::proto::Schedule;
use rayfarm_sim::node::QueueCaps;
use rayfarm_sim::world::open_scene;
use rayfarm_sim::{CostModel, FaultPlan, Outcome, RECONNECT, SimConfig, simulate};
use rayon::prelude::*;

use crate::units;
use crate::view::FrameArgs;

/// Options of `rayfarm sim`.
#[derive(Args, Clone, Debug)]
pub struct SimArgs {
    /// Scene directory (holding scene.toml).
    #[arg(long)]
    pub scene: PathBuf,
    /// Workers at the start.
    #[arg(long, default_value_t = 3)]
    pub workers: usize,
    /// Schedule, or several separated by commas (image-plane, domain, dynamic, hybrid,
    /// predictive).
    #[arg(long, default_value = "dynamic")]
    pub schedule: String,
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
    /// Run every seed of --seeds with its faults and check the invariants.
    #[arg(long)]
    pub faults: bool,
    /// Seeds to run with --faults: A..B (B excluded) or one seed.
    #[arg(long, default_value = "0..100", value_parser = parse_seeds)]
    pub seeds: std::ops::Range<u64>,
    /// Liveness bound of a faulty run in virtual microseconds [default: twenty clean frames
    /// and every deadline twice].
    #[arg(long)]
    pub bound_us: Option<u64>,
    /// Also write one row per run here (CSV).
    #[arg(long)]
    pub csv: Option<PathBuf>,
}

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

/// Virtual deadlines of the simulated cluster: scaled to frames of milliseconds.
const ACK_DEADLINE: Duration = Duration::from_millis(10);
const HEARTBEAT: Duration = Duration::from_millis(20);
const WORKER_TIMEOUT: Duration = Duration::from_millis(200);
/// A job record's write to the coordinator's store (a redb commit with its fsync).
const DISK_LATENCY: Duration = Duration::from_millis(2);

impl SimArgs {
    fn config(&self, schedule: Schedule) -> SimConfig {
        SimConfig {
            scene: self.scene.clone(),
            workers: self.workers,
            schedule,
            width: self.frame.width,
            height: self.frame.height,
            spp: self.frame.spp,
            depth: self.frame.depth,
            cache_bytes: self.cache_bytes,
            wave_rays: self.wave_rays.max(1),
            pass_rays: self.pass_rays.max(1),
            links: Default::default(),
            cost: CostModel {
                threads: self.threads.max(1),
                ..CostModel::default()
            },
            caps: QueueCaps {
                queue_bytes: 512 << 20,
                spill_bytes: 8 << 30,
            },
            ack_deadline: ACK_DEADLINE,
            heartbeat: HEARTBEAT,
            worker_timeout: WORKER_TIMEOUT,
            disk_latency: DISK_LATENCY,
        }
    }

    /// The command that replays `seed` of `schedule` alone.
    fn replay(&self, schedule: Schedule, seed: u64) -> String {
        format!(
            "rayfarm sim --scene {} --workers {} --schedule {} --width {} --height {} --spp {} \
             --depth {} --cache-bytes {} --wave-rays {} --pass-rays {} --threads {} --faults \
             --seeds {seed}..{}{}",
            self.scene.display(),
            self.workers,
            schedule_name(schedule),
            self.frame.width,
            self.frame.height,
            self.frame.spp,
            self.frame.depth,
            self.cache_bytes,
            self.wave_rays,
            self.pass_rays,
            self.threads,
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
fn bound(clean: Duration) -> Duration {
    clean * 20 + (ACK_DEADLINE + WORKER_TIMEOUT + Duration::from_secs(2)) * 2 + RECONNECT
}

const CLEAN_BOUND: Duration = Duration::from_secs(3600);

pub fn run(a: SimArgs) -> anyhow::Result<()> {
    if a.workers == 0 {
        bail!("--workers must be at least 1");
    }
    let schedules: Vec<Schedule> = a
        .schedule
        .split(',')
        .map(|s| parse_schedule(s.trim()).map_err(anyhow::Error::msg))
        .collect::<anyhow::Result<_>>()?;
    let scene = open_scene(&a.scene)
        .map_err(anyhow::Error::msg)
        .with_context(|| format!("scene {}", a.scene.display()))?;
    let mut csv = match &a.csv {
        Some(p) => {
            let mut f =
                std::fs::File::create(p).with_context(|| format!("creating {}", p.display()))?;
            writeln!(
                f,
                "schedule,seed,faults,virtual_ms,loads,segments,peer_bytes,messages,rounds,image_hash,violations"
            )?;
            Some(f)
        }
        None => None,
    };
    println!(
        "{:<12} {:>12} {:>7} {:>10} {:>12} {:>9} {:>7}  image hash",
        "schedule", "virtual ms", "loads", "segments", "peer bytes", "messages", "rounds"
    );
    let mut failed: Vec<String> = Vec::new();
    for &schedule in &schedules {
        let config = a.config(schedule);
        let clean = simulate(
            &config,
            scene.clone(),
            &FaultPlan::clean(),
            CLEAN_BOUND,
            None,
        )
        .map_err(anyhow::Error::msg)?;
        print_row(schedule, &clean);
        if let Some(f) = csv.as_mut() {
            write_csv(f, schedule, "clean", "none", &clean)?;
        }
        if !clean.violations.is_empty() || clean.frame_time.is_none() {
            for v in &clean.violations {
                eprintln!("{}: clean run: {v}", schedule_name(schedule));
            }
            failed.push(format!("{} clean run", schedule_name(schedule)));
            continue;
        }
        if !a.faults {
            continue;
        }
        let span = clean.frame_time.unwrap_or_default();
        let hash = clean.image_hash.clone();
        let bound = a.bound_us.map_or(bound(span), Duration::from_micros);
        let runs: Vec<(FaultPlan, Result<Outcome, String>)> = a
            .seeds
            .clone()
            .into_par_iter()
            .map(|seed| {
                let plan = FaultPlan::from_seed(seed, a.workers, span);
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
                write_csv(f, schedule, &plan.seed.to_string(), &plan.describe(), out)?;
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
                eprintln!("  replay: {}", a.replay(schedule, plan.seed));
                failed.push(format!("{} seed {}", schedule_name(schedule), plan.seed));
            }
        }
        summary.print(schedule, &a.seeds);
    }
    if !failed.is_empty() {
        bail!("invariants broken: {}", failed.join(", "));
    }
    Ok(())
}

fn print_row(schedule: Schedule, o: &Outcome) {
    println!(
        "{:<12} {:>12.3} {:>7} {:>10} {:>12} {:>9} {:>7}  {}",
        schedule_name(schedule),
        o.frame_time.map_or(f64::NAN, |t| t.as_secs_f64() * 1e3),
        o.loads,
        o.segments,
        o.peer_bytes,
        o.messages,
        o.rounds,
        o.image_hash.as_deref().unwrap_or("-")
    );
}

fn write_csv(
    f: &mut std::fs::File,
    schedule: Schedule,
    seed: &str,
    faults: &str,
    o: &Outcome,
) -> anyhow::Result<()> {
    let violations: Vec<String> = o.violations.iter().map(|v| v.to_string()).collect();
    let quote = |s: &str| format!("\"{}\"", s.replace('"', "\"\""));
    writeln!(
        f,
        "{},{},{},{:.6},{},{},{},{},{},{},{}",
        schedule_name(schedule),
        seed,
        quote(faults),
        o.frame_time.map_or(f64::NAN, |t| t.as_secs_f64() * 1e3),
        o.loads,
        o.segments,
        o.peer_bytes,
        o.messages,
        o.rounds,
        o.image_hash.as_deref().unwrap_or(""),
        quote(&violations.join("; "))
    )?;
    Ok(())
}

/// What the fault runs of one schedule came to.
#[derive(Default)]
struct Summary {
    runs: u64,
    failed: u64,
    kills: u64,
    mid_pass: u64,
    mid_load: u64,
    in_flight: u64,
    /// Coordinator crashes, and frames started again after them or after losing every
    /// worker.
    crashes: u64,
    restarted_frames: u64,
    events: u64,
    /// Slowest faulty frame over the clean one.
    worst: f64,
}

impl Summary {
    fn add(&mut self, o: &Outcome, clean: Duration) {
        self.runs += 1;
        self.failed += u64::from(!o.violations.is_empty());
        self.kills += o.kills.total;
        self.mid_pass += o.kills.mid_pass;
        self.mid_load += o.kills.mid_load;
        self.in_flight += o.kills.bundles_in_flight;
        self.crashes += o.coordinator_crashes;
        self.restarted_frames += o.frames.saturating_sub(1);
        self.events += o.events;
        if let Some(t) = o.frame_time {
            self.worst = self
                .worst
                .max(t.as_secs_f64() / clean.as_secs_f64().max(1e-12));
        }
    }

    fn print(&self, schedule: Schedule, seeds: &std::ops::Range<u64>) {
        println!(
            "{}: seeds {}..{}: {} runs, {} failed; {} kills ({} mid-pass, {} mid-load, {} with \
             bundles in flight); {} coordinator crashes, {} frames started again; {} events; \
             slowest frame {:.2}x the clean one",
            schedule_name(schedule),
            seeds.start,
            seeds.end,
            self.runs,
            self.failed,
            self.kills,
            self.mid_pass,
            self.mid_load,
            self.in_flight,
            self.crashes,
            self.restarted_frames,
            self.events,
            self.worst
        );
    }
}
