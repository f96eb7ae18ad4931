//! `rayfarm status`: the workers the coordinator knows, what they hold and what is queued for
//! them, and the running job. `--wait-workers N` waits until at least N workers are registered,
//! which scripts (and `demo`, and the integration tests) need before submitting.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use anyhow::bail;
use clap::Args;
use comfy_table::{ContentArrangement, Table, presets::UTF8_FULL_CONDENSED};
use rayfarm_node::proto;
use serde_json::json;

use crate::client::{Coordinator, CoordinatorArgs, runtime};

/// Options of `rayfarm status`.
#[derive(Args, Clone, Debug)]
pub struct StatusArgs {
    #[command(flatten)]
    pub coordinator: CoordinatorArgs,
    /// Print the status as JSON instead of tables.
    #[arg(long)]
    pub json: bool,
    /// First wait until at least this many workers are registered.
    #[arg(long, value_name = "N")]
    pub wait_workers: Option<usize>,
    /// Give up waiting for --wait-workers after this many seconds.
    #[arg(long, value_name = "SECONDS", default_value_t = 30.0)]
    pub timeout: f64,
}

pub fn run(a: StatusArgs) -> anyhow::Result<()> {
    let status = runtime()?.block_on(async {
        let mut coord = a.coordinator.connect().await?;
        match a.wait_workers {
            Some(n) => {
                let timeout = Duration::try_from_secs_f64(a.timeout)
                    .map_err(|e| anyhow::anyhow!("--timeout {}: {e}", a.timeout))?;
                wait_for_workers(&mut coord, n, timeout).await
            }
            None => coord.cluster_status().await,
        }
    })?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&status_json(&status))?);
        return Ok(());
    }
    if status.workers.is_empty() {
        println!("no workers registered");
    } else {
        println!("{}", workers_table(&status.workers));
        for w in status.workers.iter().filter(|w| !w.left_out.is_empty()) {
            println!("worker {} left out of {}", w.worker_id, w.left_out);
        }
    }
    if status.running_job_id.is_empty() {
        println!("no job running");
    } else {
        println!(
            "running job {}, round {}",
            status.running_job_id, status.round
        );
    }
    Ok(())
}

/// Polls the cluster status (with a short, growing pause) until at least `n` workers are
/// registered; returns that status. Errors after `timeout`, saying how many there were.
pub async fn wait_for_workers(
    coord: &mut Coordinator,
    n: usize,
    timeout: Duration,
) -> anyhow::Result<proto::GetClusterStatusResponse> {
    let deadline = Instant::now() + timeout;
    let mut pause = Duration::from_millis(20);
    loop {
        let status = coord.cluster_status().await?;
        if status.workers.len() >= n {
            return Ok(status);
        }
        if Instant::now() >= deadline {
            bail!(
                "{} workers registered with the coordinator at {} after {:.0?}; waited for {n}",
                status.workers.len(),
                coord.url(),
                timeout
            );
        }
        tokio::time::sleep(pause.min(deadline.saturating_duration_since(Instant::now()))).await;
        pause = (pause * 2).min(Duration::from_millis(250));
    }
}

/// One row per worker.
pub fn workers_table(workers: &[proto::WorkerStatus]) -> Table {
    let mut t = Table::new();
    t.load_preset(UTF8_FULL_CONDENSED)
        .set_content_arrangement(ContentArrangement::Dynamic)
        .set_header(vec![
            "worker",
            "peer address",
            "resident domains",
            "queued rays",
            "queues (domain:rays)",
            "last seen",
        ]);
    for w in workers {
        let total: u64 = w.queued_rays.values().sum();
        t.add_row(vec![
            w.worker_id.clone(),
            w.peer_address.clone(),
            ranges(&w.resident_domains),
            total.to_string(),
            queues(&w.queued_rays, 8),
            format!("{} ms", w.last_seen_ms),
        ]);
    }
    t
}

/// Domain ids compactly: "0-3,7,9-10" ("-" when none).
pub fn ranges(ids: &[u32]) -> String {
    let mut ids = ids.to_vec();
    ids.sort_unstable();
    ids.dedup();
    let mut parts = Vec::new();
    let mut i = 0;
    while i < ids.len() {
        let start = ids[i];
        let mut end = start;
        while i + 1 < ids.len() && ids[i + 1] == end + 1 {
            i += 1;
            end = ids[i];
        }
        parts.push(if start == end {
            start.to_string()
        } else {
            format!("{start}-{end}")
        });
        i += 1;
    }
    if parts.is_empty() {
        "-".into()
    } else {
        parts.join(",")
    }
}

/// The non-empty queues, fullest first, as "3:1200 5:40"; past `max` entries, "+N more".
pub fn queues(queued: &HashMap<u32, u64>, max: usize) -> String {
    let mut q: Vec<(u32, u64)> = queued
        .iter()
        .filter(|&(_, &rays)| rays > 0)
        .map(|(&d, &r)| (d, r))
        .collect();
    q.sort_unstable_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    let mut parts: Vec<String> = q
        .iter()
        .take(max)
        .map(|(d, r)| format!("{d}:{r}"))
        .collect();
    if q.len() > max {
        parts.push(format!("+{} more", q.len() - max));
    }
    if parts.is_empty() {
        "-".into()
    } else {
        parts.join(" ")
    }
}

/// The status as JSON for scripts.
pub fn status_json(s: &proto::GetClusterStatusResponse) -> serde_json::Value {
    let workers: Vec<serde_json::Value> = s
        .workers
        .iter()
        .map(|w| {
            let mut queued: Vec<(u32, u64)> = w.queued_rays.iter().map(|(&d, &r)| (d, r)).collect();
            queued.sort_unstable();
            let queued: serde_json::Map<String, serde_json::Value> = queued
                .into_iter()
                .map(|(d, r)| (d.to_string(), r.into()))
                .collect();
            json!({
                "worker_id": w.worker_id,
                "peer_address": w.peer_address,
                "resident_domains": w.resident_domains,
                "queued_rays": queued,
                "last_seen_ms": w.last_seen_ms,
                "left_out": w.left_out,
            })
        })
        .collect();
    json!({
        "workers": workers,
        "running_job_id": s.running_job_id,
        "round": s.round,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn domain_lists_and_queues_are_compact() {
        assert_eq!(ranges(&[9, 0, 1, 2, 3, 7, 10, 3]), "0-3,7,9-10");
        assert_eq!(ranges(&[]), "-");
        let q: HashMap<u32, u64> = [(3, 1200), (5, 40), (6, 0), (1, 40)].into();
        assert_eq!(queues(&q, 8), "3:1200 1:40 5:40");
        assert_eq!(queues(&q, 1), "3:1200 +2 more");
        assert_eq!(queues(&HashMap::new(), 8), "-");
    }

    #[test]
    fn the_worker_table_and_json_show_each_worker() {
        let status = proto::GetClusterStatusResponse {
            workers: vec![proto::WorkerStatus {
                worker_id: "w1".into(),
                peer_address: "127.0.0.1:7001".into(),
                resident_domains: vec![0, 1, 2],
                queued_rays: [(2, 500), (4, 25)].into(),
                ..Default::default()
            }],
            running_job_id: "j1".into(),
            ..Default::default()
        };
        let text = workers_table(&status.workers).to_string();
        for want in ["w1", "127.0.0.1:7001", "0-2", "525", "2:500 4:25", "0 ms"] {
            assert!(text.contains(want), "{want:?} missing in\n{text}");
        }
        let v = status_json(&status);
        assert_eq!(v["workers"][0]["queued_rays"]["4"], 25);
        assert_eq!(v["running_job_id"], "j1");
    }
}
