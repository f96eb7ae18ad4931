//! `rayfarm bench-api`: the job API under load. Starts a local cluster on a tiny generated
//! scene, fills the job store with finished jobs, then lets many clients at once submit,
//! watch, list and fetch, and reports each call's latency (median, 99th percentile, most).
//! The frames are tiny on purpose: what is measured is the coordinator's API, not tracing.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::Args;
use comfy_table::{Table, presets::UTF8_FULL_CONDENSED};
use rayfarm_core::prepare::generate::{NbodyOptions, prepare_nbody};
use rayfarm_node::proto::{self, JobState};
use tokio::task::JoinSet;

use crate::client::{Coordinator, code_name, runtime};
use crate::local_cluster::{ClusterConfig, JobInFlight, with_local_cluster};

/// Options of `rayfarm bench-api`.
#[derive(Args, Clone, Debug)]
pub struct BenchApiArgs {
    /// Where the scene and the coordinator's data go, kept for the next run (whose store then
    /// needs no filling) [default: a temporary directory, removed after].
    #[arg(long)]
    pub dir: Option<PathBuf>,
    /// Clients calling the API at once, each on its own connection.
    #[arg(long, default_value_t = 100)]
    pub clients: usize,
    /// Jobs each client submits, watches to their end, lists and fetches.
    #[arg(long, default_value_t = 5)]
    pub rounds: usize,
    /// Finished jobs in the store before the clients start.
    #[arg(long, default_value_t = 10_000)]
    pub fill: usize,
    /// Width and height of every frame (1 sample, no bounce).
    #[arg(long, default_value_t = 8)]
    pub size: u32,
    /// Also write the latencies as CSV (call, calls, p50_ms, p99_ms, max_ms, refused).
    #[arg(long)]
    pub csv: Option<PathBuf>,
}

/// Jobs the filler keeps in flight at once (well under the per-user quota it is given).
const FILL_IN_FLIGHT: usize = 32;

/// The calls measured, in the table's order.
const CALLS: [&str; 5] = [
    "SubmitJob",
    "WatchJob (first event)",
    "job (submit to end)",
    "ListJobs (newest 100)",
    "FetchResultStream (whole PNG)",
];

/// One client's measurements: latencies by call, and calls refused (`RESOURCE_EXHAUSTED`,
/// retried after a pause).
#[derive(Default)]
struct Samples {
    latencies: BTreeMap<&'static str, Vec<Duration>>,
    refused: BTreeMap<&'static str, usize>,
}

impl Samples {
    fn add(&mut self, call: &'static str, took: Duration) {
        self.latencies.entry(call).or_default().push(took);
    }

    fn merge(&mut self, other: Samples) {
        for (call, mut l) in other.latencies {
            self.latencies.entry(call).or_default().append(&mut l);
        }
        for (call, n) in other.refused {
            *self.refused.entry(call).or_default() += n;
        }
    }
}

pub fn run(a: BenchApiArgs) -> anyhow::Result<()> {
    if a.clients == 0 || a.rounds == 0 {
        bail!("--clients and --rounds must be at least 1");
    }
    let temp;
    let dir = match &a.dir {
        Some(d) => d.clone(),
        None => {
            temp = tempfile::tempdir().context("making a temporary directory")?;
            temp.path().to_path_buf()
        }
    };
    let scene = dir.join("scenes").join("speck");
    if !scene.join("scene.toml").exists() {
        let options = NbodyOptions {
            name: "speck".into(),
            triangles: 1000,
            seed: 1,
            domains: 1,
            max_memory: None,
            force: true,
        };
        prepare_nbody(&scene, &options).context("preparing the benchmark's scene")?;
    }
    let mut config = ClusterConfig::for_scene(&scene, &dir.join("data"), 1, 64 << 20, 1)?;
    // Every client is the same anonymous user on the same address: neither the per-user quota
    // nor the per-address connection cap may be what is measured.
    config.coordinator_extra = vec![
        "--max-jobs-per-user".into(),
        "100000".into(),
        "--max-connections-per-peer".into(),
        (a.clients + FILL_IN_FLIGHT + 16).to_string().into(),
    ];
    let in_flight = JobInFlight::default();
    let samples = runtime()?.block_on(with_local_cluster(&config, &in_flight, async |url| {
        // A store kept in --dir from an earlier run needs only the jobs it lacks.
        let stored = Coordinator::connect(&url).await?.jobs(None).await?.len();
        let start = Instant::now();
        fill(&url, a.fill.saturating_sub(stored), a.size).await?;
        eprintln!(
            "{} finished jobs in the store ({stored} from before) after {:.1} s",
            a.fill.max(stored),
            start.elapsed().as_secs_f64()
        );
        let start = Instant::now();
        let mut clients = JoinSet::new();
        for _ in 0..a.clients {
            let (url, rounds, size) = (url.clone(), a.rounds, a.size);
            clients.spawn(async move { client(&url, rounds, size).await });
        }
        let mut all = Samples::default();
        while let Some(done) = clients.join_next().await {
            all.merge(done.context("a client task failed")??);
        }
        eprintln!(
            "{} clients x {} jobs in {:.1} s",
            a.clients,
            a.rounds,
            start.elapsed().as_secs_f64()
        );
        Ok(all)
    }))?;
    let rows = rows(samples);
    println!(
        "job API latency: {} clients x {} jobs of {}x{}, {} finished jobs stored before",
        a.clients, a.rounds, a.size, a.size, a.fill
    );
    println!("{}", table(&rows));
    if let Some(path) = &a.csv {
        write_csv(path, &rows)?;
    }
    Ok(())
}

/// A tiny frame of the default scene.
fn spec(size: u32) -> proto::JobSpec {
    proto::JobSpec {
        width: size,
        height: size,
        spp: 1,
        max_depth: 0,
        ..Default::default()
    }
}

/// Submits `jobs` jobs, [`FILL_IN_FLIGHT`] at a time, and waits for all to succeed.
async fn fill(url: &str, jobs: usize, size: u32) -> anyhow::Result<()> {
    let mut tasks = JoinSet::new();
    for lane in 0..FILL_IN_FLIGHT.min(jobs) {
        let url = url.to_string();
        let mine = (jobs - lane).div_ceil(FILL_IN_FLIGHT);
        tasks.spawn(async move {
            let mut coord = Coordinator::connect(&url).await?;
            for _ in 0..mine {
                let id = coord.submit(spec(size)).await?;
                wait_end(&mut coord, &id).await?;
            }
            anyhow::Ok(())
        });
    }
    while let Some(done) = tasks.join_next().await {
        done.context("a filling task failed")??;
    }
    Ok(())
}

/// Follows `id` to its end; fails unless it succeeded.
async fn wait_end(coord: &mut Coordinator, id: &str) -> anyhow::Result<()> {
    let mut events = coord.watch(id).await?;
    while let Some(event) = events.message().await? {
        match event.state() {
            JobState::Succeeded => return Ok(()),
            JobState::Failed | JobState::Cancelled => {
                bail!("job {id} ended {:?}: {}", event.state(), event.error)
            }
            _ => {}
        }
    }
    bail!("the watch of job {id} ended before the job")
}

/// One client: `rounds` times submit a job, watch it to its end, list the newest jobs and
/// fetch the image, timing each call.
async fn client(url: &str, rounds: usize, size: u32) -> anyhow::Result<Samples> {
    let mut coord = Coordinator::connect(url).await?;
    let mut s = Samples::default();
    for _ in 0..rounds {
        let submitted = Instant::now();
        let id = coord.submit(spec(size)).await?;
        s.add(CALLS[0], submitted.elapsed());
        let watched = Instant::now();
        let mut events = coord.watch(&id).await?;
        let mut first = true;
        loop {
            let event = events
                .message()
                .await?
                .with_context(|| format!("the watch of job {id} ended before the job"))?;
            if first {
                s.add(CALLS[1], watched.elapsed());
                first = false;
            }
            match event.state() {
                JobState::Succeeded => break,
                JobState::Failed | JobState::Cancelled => {
                    bail!("job {id} ended {:?}: {}", event.state(), event.error)
                }
                _ => {}
            }
        }
        s.add(CALLS[2], submitted.elapsed());
        let listed = Instant::now();
        let jobs = coord.jobs(Some(100)).await?;
        s.add(CALLS[3], listed.elapsed());
        if jobs.len() != 100 {
            bail!("ListJobs gave {} jobs, not 100", jobs.len());
        }
        fetch(&mut coord, &id, &mut s).await?;
    }
    Ok(s)
}

/// Fetches `id`'s PNG whole, retrying after a pause while the coordinator refuses for want of
/// fetch slots; times the fetch that succeeds, from its first attempt.
async fn fetch(coord: &mut Coordinator, id: &str, s: &mut Samples) -> anyhow::Result<()> {
    let start = Instant::now();
    loop {
        match fetch_once(coord, id).await {
            Ok(()) => {
                s.add(CALLS[4], start.elapsed());
                return Ok(());
            }
            // Refused for want of slots (the call's error names its status code first).
            Err(e)
                if e.to_string()
                    .starts_with(code_name(tonic::Code::ResourceExhausted)) =>
            {
                *s.refused.entry(CALLS[4]).or_default() += 1;
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            Err(e) => return Err(e),
        }
    }
}

/// One streamed fetch of `id`'s PNG, its bytes counted against the size sent first.
async fn fetch_once(coord: &mut Coordinator, id: &str) -> anyhow::Result<()> {
    let mut stream = coord.fetch_stream(id, proto::ImageFormat::Png, 0).await?;
    let (mut total, mut got) = (None, 0u64);
    while let Some(chunk) = stream.message().await? {
        total = total.or(chunk.header.map(|h| h.total_bytes));
        got += chunk.data.len() as u64;
    }
    if Some(got) != total {
        bail!("fetched {got} bytes of job {id}, not the {total:?} announced");
    }
    Ok(())
}

/// A measured call's summary.
struct Row {
    call: &'static str,
    calls: usize,
    p50: Duration,
    p99: Duration,
    max: Duration,
    refused: usize,
}

fn rows(mut s: Samples) -> Vec<Row> {
    CALLS
        .iter()
        .filter_map(|&call| {
            let mut l = s.latencies.remove(call)?;
            l.sort();
            let at = |q: f64| l[((l.len() - 1) as f64 * q).round() as usize];
            Some(Row {
                call,
                calls: l.len(),
                p50: at(0.5),
                p99: at(0.99),
                max: at(1.0),
                refused: s.refused.get(call).copied().unwrap_or(0),
            })
        })
        .collect()
}

fn ms(d: Duration) -> String {
    format!("{:.2}", d.as_secs_f64() * 1e3)
}

fn table(rows: &[Row]) -> Table {
    let mut t = Table::new();
    t.load_preset(UTF8_FULL_CONDENSED).set_header(vec![
        "call", "calls", "p50 ms", "p99 ms", "max ms", "refused",
    ]);
    for r in rows {
        t.add_row(vec![
            r.call.to_string(),
            r.calls.to_string(),
            ms(r.p50),
            ms(r.p99),
            ms(r.max),
            r.refused.to_string(),
        ]);
    }
    t
}

fn write_csv(path: &std::path::Path, rows: &[Row]) -> anyhow::Result<()> {
    let mut f = std::fs::File::create(path).with_context(|| format!("{}", path.display()))?;
    writeln!(f, "call,calls,p50_ms,p99_ms,max_ms,refused")?;
    for r in rows {
        writeln!(
            f,
            "{},{},{},{},{},{}",
            r.call,
            r.calls,
            ms(r.p50),
            ms(r.p99),
            ms(r.max),
            r.refused
        )?;
    }
    Ok(())
}
