//! `rayfarm watch ID`, and the progress display every command that waits for a job shares
//! (`submit --wait`, `demo`): one progress bar fed by the coordinator's WatchJob stream, and one
//! rule for what a job's end means (succeeded is success; failed or cancelled is an error).
//! `watch --preview FILE` also keeps FILE the job's latest preview.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, anyhow, bail};
use clap::Args;
use clap::builder::BoolishValueParser;
use indicatif::{ProgressBar, ProgressFinish, ProgressStyle};
use rayfarm_core::cluster::stats::ClusterStats;
use rayfarm_node::proto::{self, JobState};

use crate::client::{Coordinator, CoordinatorArgs, is_unavailable, runtime};
use crate::table::{cluster_stats_table, worker_stats_table};

/// Options of `rayfarm watch`.
#[derive(Args, Clone, Debug)]
pub struct WatchArgs {
    #[command(flatten)]
    pub coordinator: CoordinatorArgs,
    /// The job to watch (as printed by `rayfarm submit`).
    pub job_id: String,
    /// No progress bar and no statistics table; only the final state.
    #[arg(long, env = "RAYFARM_QUIET", value_parser = BoolishValueParser::new())]
    pub quiet: bool,
    /// Keep this PNG file the job's latest preview while it renders (the tiles committed so
    /// far; frames over 1024 pixels a side shrunk), replaced whole each time (written beside
    /// it, then renamed). Once the job succeeds it holds the final image's preview.
    #[arg(long, value_name = "FILE")]
    pub preview: Option<PathBuf>,
    #[command(flatten)]
    pub reconnect: ReconnectArgs,
}

/// How long a command following a job rides out a lost coordinator.
#[derive(Args, Clone, Debug)]
pub struct ReconnectArgs {
    /// When the coordinator goes away mid-watch (stopped, restarting), keep reconnecting for
    /// this many seconds, then follow the same job again (a restarted coordinator keeps its
    /// jobs); 0 gives up at once.
    #[arg(
        long,
        env = "RAYFARM_RECONNECT_TIMEOUT",
        value_name = "SECONDS",
        default_value_t = 120.0
    )]
    pub reconnect_timeout: f64,
}

impl ReconnectArgs {
    /// The timeout as a duration; an error names the flag.
    pub fn ride_out(&self) -> anyhow::Result<Duration> {
        Duration::try_from_secs_f64(self.reconnect_timeout)
            .map_err(|e| anyhow!("--reconnect-timeout {}: {e}", self.reconnect_timeout))
    }
}

pub fn run(a: WatchArgs) -> anyhow::Result<()> {
    let ride_out = a.reconnect.ride_out()?;
    runtime()?.block_on(async {
        let mut coord = a.coordinator.connect().await?;
        let end = follow(
            &mut coord,
            &a.job_id,
            a.quiet,
            ride_out,
            a.preview.as_deref(),
        )
        .await?;
        println!("job {}: {}", end.job_id, state_name(end.state()));
        if end.state() == JobState::Succeeded && !a.quiet && !end.stats_json.is_empty() {
            let stats = parse_stats(&end.stats_json)?;
            print_stats(&stats);
        }
        ended_ok(&end)
    })
}

pub use rayfarm_node::job::state_name;

/// Whether a job in `state` will not change any more.
pub fn is_final(state: JobState) -> bool {
    matches!(
        state,
        JobState::Succeeded | JobState::Failed | JobState::Cancelled
    )
}

/// Follows job `job_id` with a progress bar on stderr (none when `quiet`) until it ends;
/// returns its last event, which carries the final state, the error or the statistics.
///
/// When the coordinator goes away (unreachable, or the connection breaks), `coord` reconnects
/// with backoff for up to `ride_out` and the same job is followed again: a restarted
/// coordinator still has it. The time counts from the loss until an event arrives again, so
/// a coordinator that answers but never gets as far as an event does not keep this going.
pub async fn follow(
    coord: &mut Coordinator,
    job_id: &str,
    quiet: bool,
    ride_out: Duration,
    preview: Option<&Path>,
) -> anyhow::Result<proto::WatchJobResponse> {
    let bar = progress_bar(quiet)?;
    let mut preview = preview.map(|path| PreviewFile {
        path: path.to_path_buf(),
        written: None,
    });
    let mut lost_at: Option<tokio::time::Instant> = None;
    loop {
        let mut heard = false;
        let lost = match follow_once(coord, job_id, &bar, &mut heard, preview.as_mut()).await {
            Ok(end) => {
                bar.finish_and_clear();
                return Ok(end);
            }
            Err(e) if is_unavailable(&e) && !ride_out.is_zero() => e,
            Err(e) => return Err(e),
        };
        if heard || lost_at.is_none() {
            lost_at = Some(tokio::time::Instant::now());
        }
        let deadline = lost_at.unwrap_or_else(tokio::time::Instant::now) + ride_out;
        bar.suspend(|| {
            eprintln!(
                "warning: {lost:#}; reconnecting for up to {}s",
                ride_out.as_secs_f64()
            )
        });
        bar.set_message("reconnecting");
        coord.reconnect(deadline).await.with_context(|| {
            format!(
                "watching job {job_id}: the coordinator did not come back within {}s",
                ride_out.as_secs_f64()
            )
        })?;
        bar.suspend(|| {
            eprintln!(
                "reconnected to {}; following job {job_id} again",
                coord.url()
            )
        });
    }
}

/// One watch stream of `job_id`, until the job ends or the stream fails; `heard` is set once
/// an event arrived.
async fn follow_once(
    coord: &mut Coordinator,
    job_id: &str,
    bar: &ProgressBar,
    heard: &mut bool,
    mut preview: Option<&mut PreviewFile>,
) -> anyhow::Result<proto::WatchJobResponse> {
    let mut stream = coord
        .watch(job_id)
        .await
        .with_context(|| format!("watching job {job_id}"))?;
    // A queued job sends no events: check now and then that it has workers to wait for.
    let mut check = tokio::time::interval(NO_WORKER_CHECK);
    let mut queued = false;
    let mut warned = false;
    loop {
        let message = tokio::select! {
            m = stream.message() => m,
            _ = check.tick(), if queued && !warned => {
                if coord.cluster_status().await.is_ok_and(|s| s.workers.is_empty()) {
                    bar.suspend(|| {
                        eprintln!(
                            "warning: no worker is attached to the coordinator at {}: job \
                             {job_id} stays queued until one attaches (see `rayfarm status`)",
                            coord.url()
                        )
                    });
                    bar.set_message("queued: no workers");
                    warned = true;
                }
                continue;
            }
        };
        let event = match message {
            Ok(Some(event)) => event,
            Ok(None) => {
                bail!("the coordinator ended the watch of job {job_id} before the job ended")
            }
            Err(status) => {
                return Err(coord.rpc_error(&status)).context(format!("watching job {job_id}"));
            }
        };
        *heard = true;
        queued = event.state() == JobState::Queued;
        show(bar, &event);
        if let Some(preview) = preview.as_deref_mut() {
            preview.update(coord, &event, bar).await?;
        }
        if is_final(event.state()) {
            return Ok(event);
        }
    }
}

/// `--preview FILE` and the sequence number of the preview last written to it.
struct PreviewFile {
    path: PathBuf,
    written: Option<u64>,
}

impl PreviewFile {
    /// Writes the job's latest preview if `event` says a newer one exists than the file
    /// holds. A preview the coordinator cannot give is a warning; a file that cannot be
    /// written, an error.
    async fn update(
        &mut self,
        coord: &mut Coordinator,
        event: &proto::WatchJobResponse,
        bar: &ProgressBar,
    ) -> anyhow::Result<()> {
        let newer = self.written.is_none_or(|w| event.preview_sequence > w);
        if !newer || event.state() == JobState::Queued {
            return Ok(());
        }
        let preview = match coord.preview(&event.job_id).await {
            Ok(p) => p,
            Err(e) => {
                bar.suspend(|| eprintln!("warning: no preview of {}: {e:#}", event.job_id));
                // Not asked again for this event's number.
                self.written = Some(event.preview_sequence);
                return Ok(());
            }
        };
        write_atomically(&self.path, &preview.png)
            .await
            .with_context(|| format!("writing the preview to {}", self.path.display()))?;
        self.written = Some(preview.sequence);
        Ok(())
    }
}

/// Replaces `path` with `bytes` whole: written to a file beside it, then renamed over it, so
/// a reader never sees half an image.
async fn write_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let name = path
        .file_name()
        .ok_or_else(|| std::io::Error::new(std::io::ErrorKind::InvalidInput, "not a file name"))?;
    let mut temp_name = std::ffi::OsString::from(".");
    temp_name.push(name);
    temp_name.push(".part");
    let temp = path.with_file_name(temp_name);
    tokio::fs::write(&temp, bytes).await?;
    tokio::fs::rename(&temp, path).await
}

/// How long a queued job is followed before checking that the cluster has workers.
const NO_WORKER_CHECK: Duration = Duration::from_secs(2);

/// Succeeded is `Ok`; a failed or cancelled job is an error saying so (with the job's own
/// error message).
pub fn ended_ok(end: &proto::WatchJobResponse) -> anyhow::Result<()> {
    match end.state() {
        JobState::Succeeded => Ok(()),
        JobState::Failed if end.error.is_empty() => Err(anyhow!("job {} failed", end.job_id)),
        JobState::Failed => Err(anyhow!("job {} failed: {}", end.job_id, end.error)),
        JobState::Cancelled => Err(anyhow!("job {} was cancelled", end.job_id)),
        other => Err(anyhow!(
            "job {} has not ended (state {})",
            end.job_id,
            state_name(other)
        )),
    }
}

/// Statistics JSON from the coordinator, as `ClusterStats`.
pub fn parse_stats(json: &str) -> anyhow::Result<ClusterStats> {
    serde_json::from_str(json).context("the coordinator sent statistics this CLI cannot read")
}

/// Prints the cluster and per-worker statistics tables.
pub fn print_stats(stats: &ClusterStats) {
    println!("{}", cluster_stats_table(stats));
    if !stats.per_worker.is_empty() {
        println!("{}", worker_stats_table(&stats.per_worker));
    }
}

/// A progress bar on stderr that clears itself however the wait ends (even when the future
/// waiting is dropped, e.g. on Ctrl-C). Hidden when `quiet` (indicatif also hides it when
/// stderr is not a terminal).
fn progress_bar(quiet: bool) -> anyhow::Result<ProgressBar> {
    let bar = if quiet {
        ProgressBar::hidden()
    } else {
        // No length until the coordinator says how many tiles: an empty bar, not a full one.
        ProgressBar::no_length()
    };
    let bar = bar.with_finish(ProgressFinish::AndClear).with_style(
        ProgressStyle::with_template("{spinner} [{bar:30}] {pos}/{len} tiles  {msg}")
            .map_err(anyhow::Error::msg)?
            .progress_chars("=> "),
    );
    bar.enable_steady_tick(Duration::from_millis(120));
    bar.set_message("connecting");
    Ok(bar)
}

fn show(bar: &ProgressBar, e: &proto::WatchJobResponse) {
    if e.tiles_total > 0 {
        bar.set_length(u64::from(e.tiles_total));
    }
    bar.set_position(u64::from(e.tiles_done));
    bar.set_message(progress_message(e));
}

/// The text beside the bar: the state while queued, rate, round and ETA while running
/// (and which subframe, for a progressive job: the bar counts its tiles).
fn progress_message(e: &proto::WatchJobResponse) -> String {
    let subframe = if e.subframes > 1 {
        let current = (e.subframes_done + 1).min(e.subframes);
        format!("subframe {current}/{}  ", e.subframes)
    } else {
        String::new()
    };
    match e.state() {
        JobState::Running => format!(
            "{subframe}{:.2} Mrays/s  round {}  eta {}",
            e.rays_per_second / 1e6,
            e.round,
            eta(e.eta_seconds)
        ),
        state => state_name(state).to_string(),
    }
}

/// Seconds as "42s", "3m05s", "1h02m"; unknown (negative or not finite) as "?".
fn eta(seconds: f64) -> String {
    if !seconds.is_finite() || seconds < 0.0 {
        return "?".into();
    }
    let s = seconds.round() as u64;
    match s {
        0..60 => format!("{s}s"),
        60..3600 => format!("{}m{:02}s", s / 60, s % 60),
        _ => format!("{}h{:02}m", s / 3600, s % 3600 / 60),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn event(state: JobState, error: &str) -> proto::WatchJobResponse {
        proto::WatchJobResponse {
            job_id: "j7".into(),
            state: state as i32,
            error: error.into(),
            ..Default::default()
        }
    }

    #[test]
    fn failed_and_cancelled_jobs_are_errors_with_the_reason() {
        assert!(ended_ok(&event(JobState::Succeeded, "")).is_ok());
        let e = ended_ok(&event(JobState::Failed, "worker w2 lost")).unwrap_err();
        assert_eq!(e.to_string(), "job j7 failed: worker w2 lost");
        let e = ended_ok(&event(JobState::Cancelled, "")).unwrap_err();
        assert_eq!(e.to_string(), "job j7 was cancelled");
        assert!(ended_ok(&event(JobState::Running, "")).is_err());
    }

    #[test]
    fn progress_text_shows_rate_round_and_eta() {
        let e = proto::WatchJobResponse {
            state: JobState::Running as i32,
            rays_per_second: 12_345_678.0,
            round: 9,
            eta_seconds: 185.0,
            ..Default::default()
        };
        assert_eq!(progress_message(&e), "12.35 Mrays/s  round 9  eta 3m05s");
        let progressive = proto::WatchJobResponse {
            subframes_done: 2,
            subframes: 5,
            ..e.clone()
        };
        assert_eq!(
            progress_message(&progressive),
            "subframe 3/5  12.35 Mrays/s  round 9  eta 3m05s"
        );
        assert_eq!(progress_message(&event(JobState::Queued, "")), "queued");
        assert_eq!(eta(-1.0), "?");
        assert_eq!(eta(f64::NAN), "?");
        assert_eq!(eta(7200.0), "2h00m");
    }
}
