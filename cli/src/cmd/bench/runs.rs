//! The bench's runs on a cluster: every frame of the plan submitted and followed in turn,
//! stopping when the cluster is no longer the one measured.

use std::time::{Duration, Instant};

use anyhow::{Context, anyhow, bail};
use rayfarm_core::cluster::stats::ClusterStats;
use rayfarm_node::proto;
use rayfarm_node::security::ClientSecurity;

use crate::bench::{RunOutcome, run_order};
use crate::client::Coordinator;
use crate::cmd::watch::{ended_ok, follow, parse_stats};
use crate::local_cluster::JobInFlight;
use crate::units::human;

use super::*;

/// The runs of a bench, and why it stopped before the last one, if it did.
pub(super) struct BenchRuns {
    pub(super) runs: Vec<RunOutcome>,
    pub(super) stopped: Option<String>,
}

/// Renders every run of the plan on the cluster at `url`, one at a time, with a line on
/// stderr per run. A failed run is recorded and the bench goes on, unless the cluster itself
/// is no longer the one measured (the coordinator stopped answering, or a worker left or
/// joined): then it stops, keeping the runs so far.
pub(super) async fn bench(
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
            prefetch: run.prefetch,
            peer_domains: run.peer_domains,
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
