//! One CSV row per run of `rayfarm bench`, failed runs included (with their error and empty
//! measures), so the numbers behind the table can be analysed or re-plotted elsewhere.

use std::path::Path;

use anyhow::Context;
use serde::Serialize;

use rayfarm_core::bundler::Tier;
use rayfarm_core::cluster::stats::{ClusterStats, SubframeCost, WorkerFrameStats};

use super::{RunOutcome, ray_work_seconds, tier_bundles};

/// What every row repeats: how the bench was set up.
#[derive(Clone, Debug, Default)]
pub struct Setup {
    pub scene: String,
    /// Worker processes; `None` when an existing cluster was used (each row then says how many
    /// workers took part, when the run succeeded).
    pub workers: Option<usize>,
    pub cache_bytes_per_worker: Option<u64>,
    pub threads_per_worker: Option<usize>,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub depth: u32,
    /// `--replicate` as given; empty for the coordinator's default.
    pub replicate: String,
    /// `--storage-bandwidth` as given; empty when not.
    pub storage_bandwidth: String,
    /// `--storage-latency` as given; empty when not.
    pub storage_latency: String,
}

/// One row. Field names are the column names.
#[derive(Debug, Serialize)]
struct Row<'a> {
    run: usize,
    repeat: usize,
    schedule: &'a str,
    ok: bool,
    error: &'a str,
    job_id: &'a str,
    wall_seconds: Option<f64>,
    client_seconds: f64,
    domain_loads: Option<u64>,
    bytes_loaded: Option<u64>,
    /// Of the loads, those whose bytes came from peers, and those bytes.
    peer_loads: Option<u64>,
    bytes_from_peers: Option<u64>,
    /// Loads that asked peers, which refused at once or failed (then storage).
    peer_refusals: Option<u64>,
    peer_failures: Option<u64>,
    /// Of the loads, those made ahead of need, and of those the used and the wasted ones.
    prefetches: Option<u64>,
    prefetches_used: Option<u64>,
    prefetches_wasted: Option<u64>,
    segments: Option<u64>,
    rays_migrated: Option<u64>,
    bytes_migrated: Option<u64>,
    rays_spilled: Option<u64>,
    bundles_results: Option<u64>,
    bundles_migrated: Option<u64>,
    bundles_tasks: Option<u64>,
    rounds: Option<u64>,
    /// Per subframe, in order, `+`-separated: loads, and seconds from the frame's start to
    /// its last tile (one entry for a one-pass frame).
    subframe_loads: String,
    subframe_done_seconds: String,
    idle_fraction: Option<f64>,
    peak_rss_bytes: Option<u64>,
    busy_seconds: Option<f64>,
    load_seconds: Option<f64>,
    ray_work_seconds: Option<f64>,
    /// Passes of every worker, and the seconds they waited for a tracing thread in all
    /// (what `rayfarm sim --pass-start-us` charges a pass, on average).
    passes: Option<u64>,
    pass_start_wait_seconds: Option<f64>,
    /// CPU seconds of every worker process in its frame, and of those its tracing threads'.
    cpu_seconds: Option<f64>,
    trace_cpu_seconds: Option<f64>,
    /// Seconds every worker spent idle, by why (rays queued the plan did not give it, its
    /// rays waiting for verdicts, nothing queued), and its finished passes waited for its
    /// event loop: with the above, the parts of a worker's frame the bench tabulates.
    idle_queued_seconds: Option<f64>,
    idle_verdicts_seconds: Option<f64>,
    idle_empty_seconds: Option<f64>,
    pass_wait_seconds: Option<f64>,
    /// Every worker's frame, start to end, summed.
    frame_seconds: Option<f64>,
    threads: Option<usize>,
    image_hash: &'a str,
    scene: &'a str,
    workers: Option<usize>,
    cache_bytes_per_worker: Option<u64>,
    threads_per_worker: Option<usize>,
    width: u32,
    height: u32,
    spp: u32,
    depth: u32,
    replicate: &'a str,
    storage_bandwidth: &'a str,
    storage_latency: &'a str,
}

fn row<'a>(r: &'a RunOutcome, setup: &'a Setup) -> Row<'a> {
    let s = r.stats();
    let bundles = |tier: Tier| s.map(|s| tier_bundles(s, tier));
    let idle = s.and_then(|s| {
        let n = s.per_worker.len();
        (n > 0).then(|| s.per_worker.iter().map(|w| w.idle_fraction).sum::<f64>() / n as f64)
    });
    Row {
        run: r.run,
        repeat: r.repeat,
        schedule: &r.schedule,
        ok: s.is_some(),
        error: r.result.as_ref().err().map_or("", String::as_str),
        job_id: r.job_id.as_deref().unwrap_or(""),
        wall_seconds: s.map(|s| s.wall_seconds),
        client_seconds: r.client_seconds,
        domain_loads: s.map(|s| s.cache.loads),
        bytes_loaded: s.map(|s| s.cache.bytes_loaded),
        peer_loads: s.map(|s| s.cache.peer_loads),
        bytes_from_peers: s.map(|s| s.cache.bytes_from_peers),
        peer_refusals: s.map(|s| s.cache.peer_refusals),
        peer_failures: s.map(|s| s.cache.peer_failures),
        prefetches: s.map(|s| s.cache.prefetches),
        prefetches_used: s.map(|s| s.cache.prefetches_used),
        prefetches_wasted: s.map(|s| s.cache.prefetches_wasted),
        segments: s.map(|s| s.rays.segments()),
        rays_migrated: s.map(|s| s.rays_migrated),
        bytes_migrated: s.map(|s| s.bytes_migrated),
        rays_spilled: summed(s, |w| w.rays_spilled),
        bundles_results: bundles(Tier::Results),
        bundles_migrated: bundles(Tier::Migrated),
        bundles_tasks: bundles(Tier::Tasks),
        rounds: s.map(|s| s.rounds),
        subframe_loads: per_subframe(s, |c| c.loads.to_string()),
        subframe_done_seconds: per_subframe(s, |c| format!("{:.3}", c.done_seconds)),
        idle_fraction: idle,
        peak_rss_bytes: s.map(|s| s.peak_rss_bytes),
        busy_seconds: summed(s, |w| w.busy_seconds),
        load_seconds: summed(s, |w| w.load_seconds),
        ray_work_seconds: s.map(ray_work_seconds),
        passes: summed(s, |w| w.passes),
        pass_start_wait_seconds: summed(s, |w| w.pass_start_wait_seconds),
        cpu_seconds: summed(s, |w| w.cpu_seconds),
        trace_cpu_seconds: summed(s, |w| w.trace_cpu_seconds),
        idle_queued_seconds: summed(s, |w| w.idle_queued_seconds),
        idle_verdicts_seconds: summed(s, |w| w.idle_verdicts_seconds),
        idle_empty_seconds: summed(s, |w| w.idle_empty_seconds),
        pass_wait_seconds: summed(s, |w| w.pass_wait_seconds),
        frame_seconds: summed(s, |w| w.frame_seconds),
        threads: s.map(|s| s.threads),
        image_hash: s.map_or("", |s| s.image_hash.as_str()),
        scene: &setup.scene,
        workers: setup.workers.or(s.map(|s| s.workers)),
        cache_bytes_per_worker: setup.cache_bytes_per_worker,
        threads_per_worker: setup.threads_per_worker,
        width: setup.width,
        height: setup.height,
        spp: setup.spp,
        depth: setup.depth,
        replicate: &setup.replicate,
        storage_bandwidth: &setup.storage_bandwidth,
        storage_latency: &setup.storage_latency,
    }
}

/// The sum over a run's workers of one of their figures; `None` for a failed run.
fn summed<T: std::iter::Sum<T>>(
    s: Option<&ClusterStats>,
    figure: impl Fn(&WorkerFrameStats) -> T,
) -> Option<T> {
    s.map(|s| s.per_worker.iter().map(figure).sum())
}

/// One figure of each subframe, joined by `+`; empty for a failed run.
fn per_subframe(s: Option<&ClusterStats>, f: impl Fn(&SubframeCost) -> String) -> String {
    s.map_or_else(String::new, |s| {
        s.subframe_costs.iter().map(f).collect::<Vec<_>>().join("+")
    })
}

/// Writes the runs as CSV, a header and one row per run, to `out`.
pub fn write_runs(
    out: impl std::io::Write,
    runs: &[RunOutcome],
    setup: &Setup,
) -> anyhow::Result<()> {
    let mut w = csv::Writer::from_writer(out);
    for r in runs {
        w.serialize(row(r, setup))
            .with_context(|| format!("writing the CSV row of run {}", r.run))?;
    }
    w.flush().context("writing the CSV")?;
    Ok(())
}

/// Writes the runs as CSV to the file `path`.
pub fn write_runs_file(path: &Path, runs: &[RunOutcome], setup: &Setup) -> anyhow::Result<()> {
    let file =
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    write_runs(std::io::BufWriter::new(file), runs, setup)
        .with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::super::tests::{outcome, stats};
    use super::*;

    #[test]
    fn one_row_per_run_with_a_header_and_failures_left_empty() {
        let mut measured = stats(2.5, 4, 3.0, 1.0, "00ff");
        for w in &mut measured.per_worker {
            (w.passes, w.pass_start_wait_seconds) = (40, 0.25);
            (w.cpu_seconds, w.trace_cpu_seconds) = (0.75, 0.5);
            (w.idle_queued_seconds, w.idle_verdicts_seconds) = (0.125, 0.0625);
            (w.idle_empty_seconds, w.pass_wait_seconds) = (0.25, 0.03125);
        }
        let runs = vec![
            outcome(1, "dynamic", Ok(measured)),
            outcome(2, "domain", Err("UNIMPLEMENTED: x, \"y\"".into())),
        ];
        let setup = Setup {
            scene: "nbody".into(),
            workers: Some(4),
            cache_bytes_per_worker: Some(1 << 20),
            threads_per_worker: Some(1),
            width: 64,
            height: 48,
            spp: 2,
            depth: 3,
            storage_bandwidth: "100MiB/s".into(),
            ..Default::default()
        };
        let mut out = Vec::new();
        write_runs(&mut out, &runs, &setup).unwrap();
        let text = String::from_utf8(out).unwrap();
        let mut reader = csv::Reader::from_reader(text.as_bytes());
        let header = reader.headers().unwrap().clone();
        for col in [
            "run",
            "repeat",
            "schedule",
            "ok",
            "error",
            "wall_seconds",
            "domain_loads",
            "bytes_loaded",
            "segments",
            "rays_migrated",
            "bytes_migrated",
            "bundles_results",
            "bundles_migrated",
            "bundles_tasks",
            "rounds",
            "idle_fraction",
            "peak_rss_bytes",
            "image_hash",
            "workers",
            "cache_bytes_per_worker",
            "width",
            "height",
            "spp",
            "depth",
        ] {
            assert!(
                header.iter().any(|h| h == col),
                "no column {col}: {header:?}"
            );
        }
        // One column per tier there is: the retired control tier has none.
        assert!(!header.iter().any(|h| h == "bundles_control"));
        let rows: Vec<csv::StringRecord> = reader.records().map(Result::unwrap).collect();
        assert_eq!(rows.len(), 2);
        let get = |r: &csv::StringRecord, col: &str| {
            let i = header.iter().position(|h| h == col).unwrap();
            r[i].to_string()
        };
        assert_eq!(get(&rows[0], "ok"), "true");
        assert_eq!(get(&rows[0], "wall_seconds"), "2.5");
        assert_eq!(get(&rows[0], "domain_loads"), "4");
        assert_eq!(get(&rows[0], "bundles_migrated"), "6");
        assert_eq!(get(&rows[0], "ray_work_seconds"), "2.0");
        assert_eq!(get(&rows[0], "passes"), "80", "both workers' passes");
        assert_eq!(get(&rows[0], "pass_start_wait_seconds"), "0.5");
        assert_eq!(get(&rows[0], "cpu_seconds"), "1.5");
        assert_eq!(get(&rows[0], "trace_cpu_seconds"), "1.0");
        assert_eq!(get(&rows[0], "idle_queued_seconds"), "0.25");
        assert_eq!(get(&rows[0], "idle_verdicts_seconds"), "0.125");
        assert_eq!(get(&rows[0], "idle_empty_seconds"), "0.5");
        assert_eq!(get(&rows[0], "pass_wait_seconds"), "0.0625");
        assert_eq!(
            get(&rows[0], "frame_seconds"),
            "5.0",
            "two workers' frames of 2.5 s"
        );
        assert_eq!(get(&rows[0], "image_hash"), "00ff");
        assert_eq!(get(&rows[0], "storage_bandwidth"), "100MiB/s");
        assert_eq!(get(&rows[1], "ok"), "false");
        assert_eq!(get(&rows[1], "error"), "UNIMPLEMENTED: x, \"y\"");
        assert_eq!(get(&rows[1], "wall_seconds"), "");
        assert_eq!(get(&rows[1], "workers"), "4");
    }
}
