//! `rayfarm jobs`: what the cluster has been asked to render, newest first, as a table for
//! people or JSON for scripts; `rayfarm jobs priority JOB N` changes a queued job's priority.

use std::time::{SystemTime, UNIX_EPOCH};

use anyhow::Context;
use clap::{Args, Subcommand};
use comfy_table::{ContentArrangement, Table, presets::UTF8_FULL_CONDENSED};
use rayfarm_node::job::schedule_name;
use rayfarm_node::proto::{self, JobState};
use serde_json::json;

use super::watch::state_name;
use crate::client::{CoordinatorArgs, runtime};

/// Options of `rayfarm jobs`.
#[derive(Args, Clone, Debug)]
pub struct JobsArgs {
    #[command(flatten)]
    pub coordinator: CoordinatorArgs,
    /// Print the jobs as JSON (one array) instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Show the newest N jobs; 0 shows every job.
    #[arg(long, default_value_t = 100)]
    pub limit: usize,
    #[command(subcommand)]
    pub action: Option<JobsAction>,
}

/// What to do to a job instead of listing them.
#[derive(Subcommand, Clone, Debug)]
pub enum JobsAction {
    /// Change a queued job's priority (higher runs first; equal ones in submission order):
    /// its owner or an admin may.
    Priority(PriorityArgs),
}

/// Options of `rayfarm jobs priority`.
#[derive(Args, Clone, Debug)]
pub struct PriorityArgs {
    #[command(flatten)]
    pub coordinator: CoordinatorArgs,
    /// The queued job.
    pub job_id: String,
    /// Its new priority.
    #[arg(allow_negative_numbers = true)]
    pub priority: i32,
}

fn set_priority(a: PriorityArgs) -> anyhow::Result<()> {
    let state = runtime()?.block_on(async {
        let mut coord = a.coordinator.connect().await?;
        coord
            .set_priority(&a.job_id, a.priority)
            .await
            .with_context(|| format!("changing the priority of job {}", a.job_id))
    })?;
    println!(
        "job {}: priority {} ({})",
        a.job_id,
        a.priority,
        state_name(state)
    );
    Ok(())
}

pub fn run(a: JobsArgs) -> anyhow::Result<()> {
    if let Some(JobsAction::Priority(p)) = a.action {
        return set_priority(p);
    }
    let jobs = runtime()?.block_on(async {
        let mut coord = a.coordinator.connect().await?;
        coord.jobs((a.limit > 0).then_some(a.limit)).await
    })?;
    if a.json {
        let list: Vec<serde_json::Value> = jobs.iter().map(job_json).collect();
        println!("{}", serde_json::to_string_pretty(&list)?);
    } else if jobs.is_empty() {
        println!("no jobs");
    } else {
        println!("{}", jobs_table(&jobs, now_unix_ms()));
    }
    Ok(())
}

/// Milliseconds since the Unix epoch, now.
pub fn now_unix_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
}

/// How much of a failed job's error the table shows.
const ERROR_CHARS: usize = 40;

/// The first `n` characters of `text`, with an ellipsis if there were more.
fn first_chars(text: &str, n: usize) -> String {
    let mut chars = text.chars();
    let head: String = chars.by_ref().take(n).collect();
    if chars.next().is_some() {
        format!("{head}...")
    } else {
        head
    }
}

/// The jobs as a table; times relative to `now_ms`.
pub fn jobs_table(jobs: &[proto::JobSummary], now_ms: i64) -> Table {
    let mut t = Table::new();
    t.load_preset(UTF8_FULL_CONDENSED)
        .set_content_arrangement(ContentArrangement::Dynamic)
        .set_header(vec![
            "job",
            "state",
            "scene",
            "size",
            "spp",
            "depth",
            "schedule",
            "priority",
            "submitted",
            "took",
        ]);
    for j in jobs {
        let spec = j.spec.clone().unwrap_or_default();
        let mut state = state_name(j.state()).to_string();
        if j.state() == JobState::Failed && !j.error.is_empty() {
            // The first words only: the whole error is in `jobs --json` and `watch`.
            state = format!("{state}: {}", first_chars(&j.error, ERROR_CHARS));
        }
        let scene = if spec.scene.is_empty() {
            "(default)".to_string()
        } else {
            spec.scene.clone()
        };
        let took = if j.started_unix_ms > 0 && j.finished_unix_ms >= j.started_unix_ms {
            format!(
                "{:.1} s",
                (j.finished_unix_ms - j.started_unix_ms) as f64 / 1e3
            )
        } else {
            String::new()
        };
        t.add_row(vec![
            j.job_id.clone(),
            state,
            scene,
            format!("{}x{}", spec.width, spec.height),
            spec.spp.to_string(),
            spec.max_depth.to_string(),
            schedule_name(spec.schedule()).to_string(),
            spec.priority.to_string(),
            if j.submitted_unix_ms > 0 {
                ago(now_ms, j.submitted_unix_ms)
            } else {
                String::new()
            },
            took,
        ]);
    }
    t
}

/// How long before `now_ms` the moment `then_ms` was: "12 s ago", "5 min ago", "3 h ago",
/// "2 d ago" ("just now" for clock skew into the future).
pub fn ago(now_ms: i64, then_ms: i64) -> String {
    let s = (now_ms - then_ms) / 1000;
    match s {
        ..0 => "just now".into(),
        0..60 => format!("{s} s ago"),
        60..3600 => format!("{} min ago", s / 60),
        3600..86400 => format!("{} h ago", s / 3600),
        _ => format!("{} d ago", s / 86400),
    }
}

fn job_json(j: &proto::JobSummary) -> serde_json::Value {
    let spec = j.spec.clone().unwrap_or_default();
    let camera = spec.camera.as_ref().map(|c| {
        json!({
            "eye": c.eye,
            "look_at": c.look_at,
            "up": c.up,
            "fov_y_degrees": c.fov_y_degrees,
        })
    });
    json!({
        "job_id": j.job_id,
        "state": state_name(j.state()),
        "error": j.error,
        "scene": spec.scene,
        "width": spec.width,
        "height": spec.height,
        "spp": spec.spp,
        "max_depth": spec.max_depth,
        "schedule": schedule_name(spec.schedule()),
        "priority": spec.priority,
        "cold_cache": spec.cold_cache,
        "camera": camera,
        "submitted_unix_ms": j.submitted_unix_ms,
        "started_unix_ms": j.started_unix_ms,
        "finished_unix_ms": j.finished_unix_ms,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(id: &str, state: JobState, submitted: i64) -> proto::JobSummary {
        proto::JobSummary {
            job_id: id.into(),
            spec: Some(proto::JobSpec {
                scene: "nbody".into(),
                width: 96,
                height: 72,
                spp: 2,
                max_depth: 3,
                schedule: proto::Schedule::Hybrid as i32,
                ..Default::default()
            }),
            state: state as i32,
            submitted_unix_ms: submitted,
            ..Default::default()
        }
    }

    #[test]
    fn the_table_shows_each_job_with_relative_times() {
        let now = 1_700_000_000_000;
        let mut failed = job("j2", JobState::Failed, now - 90_000);
        failed.error = "worker lost".into();
        let done = proto::JobSummary {
            started_unix_ms: now - 50_000,
            finished_unix_ms: now - 47_500,
            ..job("j1", JobState::Succeeded, now - 60_000)
        };
        let text = jobs_table(&[failed, done], now).to_string();
        for want in [
            "j1",
            "j2",
            "failed: worker lost",
            "succeeded",
            "96x72",
            "hybrid",
            "1 min ago",
            "2.5 s",
        ] {
            assert!(text.contains(want), "{want:?} missing in\n{text}");
        }
        assert_eq!(job_json(&job("j3", JobState::Queued, 0))["state"], "queued");
    }

    #[test]
    fn times_read_as_durations_ago() {
        assert_eq!(ago(10_000, 20_000), "just now");
        assert_eq!(ago(10_000, 0), "10 s ago");
        assert_eq!(ago(7_200_000, 0), "2 h ago");
        assert_eq!(ago(3 * 86_400_000, 0), "3 d ago");
    }
}
