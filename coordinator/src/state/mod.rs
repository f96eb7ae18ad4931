//! The coordinator's state and everything that changes it: jobs and their queue, registered
//! workers, the running frame and frames being finished. Handlers of both gRPC services call
//! in here; every method takes the lock briefly and sends on unbounded channels, never
//! awaiting while holding it. Job records are handed to the store's writer (`journal`) under
//! the lock, in order, and written outside it; a frame's scene is read and its film file
//! created outside it too, before the frame starts.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use rayfarm_core::cluster::scene_ref;
use rayfarm_core::cluster::stats::{ClusterStats, WorkerFrameStats};
use rayfarm_core::scene::Manifest;
use rayfarm_core::schedule::dynamic::Options;
use rayfarm_node::job::{frame_spec, schedule_name, state_name};
use rayfarm_node::proto::{
    self, JobState, PROTOCOL_VERSION, Schedule, coordinator_message::Body,
    worker_message::Body as FromWorker,
};
use rayfarm_node::security::User;
use tokio::sync::{mpsc, oneshot, watch};
use tonic::Status;
use tracing::{error, info, info_span, warn};

use rayfarm_machine::coordinator::{Member, Outgoing, Rounds, RunningFrame, accusation_grace};

use crate::admission::{Needs, free_disk};
use crate::journal::{Journal, Then};
use crate::preview::Previews;
use crate::queue::JobQueue;
use crate::results;
use crate::running::{Running, now};
use crate::store::{Store, StoreError, StoredJob};

mod frames;
mod jobs;
mod workers;

use frames::{end_frame, publish_progress, send};
use jobs::spec_cost;

/// How the coordinator is set up.
#[derive(Clone, Debug)]
pub struct Config {
    pub data_dir: PathBuf,
    pub scene_root: PathBuf,
    /// Scenes may be absolute paths (else names under `scene_root` only).
    pub allow_absolute_scenes: bool,
    pub default_scene: Option<String>,
    /// Most jobs one user may have queued or running.
    pub max_jobs_per_user: usize,
    /// Most pixels x samples one user may have queued or running.
    pub max_pixel_samples_per_user: u64,
    /// Heartbeat interval asked of workers.
    pub heartbeat: Duration,
    /// A worker silent this long is dropped.
    pub worker_timeout: Duration,
    /// How long a finished frame waits for the workers' statistics.
    pub report_timeout: Duration,
    /// Extensions of the dynamic schedule.
    pub schedule_options: Options,
    /// How the dynamic schedule's rounds advance.
    pub rounds: Rounds,
    /// Admission: the most a frame may need of each figure (`admission::Needs`).
    pub max_frame_bytes: u64,
    /// Starts of a job's frame after which it fails instead of starting again.
    pub max_attempts: u32,
}

/// What workers and clients are told once the coordinator is stopping.
pub const SHUTTING_DOWN: &str = "the coordinator is shutting down";

/// Where a worker's messages go.
pub type WorkerTx = mpsc::UnboundedSender<Result<proto::CoordinatorMessage, Status>>;

struct Job {
    summary: proto::JobSummary,
    /// Pixels times samples per pixel: what the job weighs against its owner's quota.
    cost: u64,
    seq: u64,
    /// Frames started so far (see [`StoredJob::attempts`]).
    attempts: u32,
    /// The epoch every tile of its next frame starts at, at least: one past the highest
    /// epoch an earlier frame of it used in this process. A frame that lost every worker
    /// bumped epochs with each loss; a worker dropped from it may still send rays and
    /// results of those epochs, which the restarted frame must never take for its own.
    epoch_floor: u32,
    /// Times each worker (by id) was lost during this job's frames, in this process.
    workers_lost: BTreeMap<String, u32>,
    progress: watch::Sender<proto::WatchJobResponse>,
    image_hash: String,
    stats_json: String,
    /// Previews of its latest frame, kept while it runs and for the last
    /// [`KEPT_PREVIEWS`] frames started.
    preview: Option<Arc<Previews>>,
}

/// Frames whose previews stay in memory once they end (each a PNG of at most 1024 pixels
/// a side).
const KEPT_PREVIEWS: usize = 4;

/// Workers lost remembered for the dashboard, newest last.
const KEPT_LOST_WORKERS: usize = 32;

/// A worker the coordinator dropped, as the dashboard lists it.
#[derive(Clone, Debug, serde::Serialize)]
pub struct LostWorker {
    pub worker_id: String,
    pub peer_address: String,
    /// When it was dropped, Unix milliseconds.
    pub lost_unix_ms: i64,
    pub reason: String,
}

impl Job {
    fn stored(&self) -> StoredJob {
        StoredJob {
            summary: Some(self.summary.clone()),
            seq: self.seq,
            attempts: self.attempts,
            image_hash: self.image_hash.clone(),
            stats_json: self.stats_json.clone(),
        }
    }
}

struct WorkerEntry {
    id: String,
    peer_address: String,
    cache_bytes: u64,
    tx: WorkerTx,
    last_seen: Instant,
    last_report: Option<proto::QueueReport>,
    /// Its latest heartbeat: its loads, rays traced and queue bytes.
    heartbeat: proto::Heartbeat,
    /// Why it declined its last frame ("job ID: reason"); empty once it reports a frame.
    left_out: String,
}

/// A frame (or a progressive job's subframe) that has ended, waiting for its workers'
/// statistics, by frame id.
struct Finishing {
    /// The job it is (a frame of).
    job: String,
    waiting: BTreeSet<u32>,
    reports: Vec<WorkerFrameStats>,
    done: Option<oneshot::Sender<()>>,
}

struct State {
    /// Where every job change is written through to, in order, outside this state's lock.
    journal: Journal,
    /// Frame starts so far, and the latest whose record is on disk: until it is, messages to
    /// workers wait in `held` (in order), so no worker hears of a frame before its start is
    /// stored (a frame that kills the coordinator counts against the job's attempts).
    starts: u64,
    stored_starts: u64,
    held: Vec<(u64, Outgoing)>,
    /// The job whose frame is being prepared off the lock (`try_start`, `begin`).
    preparing: Option<String>,
    jobs: BTreeMap<String, Job>,
    /// Every job's id by its sequence number, so a page of the list is a range, not a sort.
    by_seq: BTreeMap<u64, String>,
    queue: JobQueue,
    seq: u64,
    workers: BTreeMap<u32, WorkerEntry>,
    next_key: u32,
    running: Option<Running>,
    finishing: BTreeMap<String, Finishing>,
    /// Set by [`Coordinator::shut_down`]: no worker attaches and no frame starts any more.
    stopping: bool,
    /// Jobs holding previews, in the order their frames started (at most [`KEPT_PREVIEWS`]).
    previewed: VecDeque<String>,
    /// The latest workers dropped (at most [`KEPT_LOST_WORKERS`]).
    lost: VecDeque<LostWorker>,
}

/// A page of the job list: at most `size` jobs, newest first, from sequence number `from_seq`
/// down.
#[derive(Clone, Copy, Debug)]
pub struct JobPage {
    pub size: usize,
    pub from_seq: u64,
}

impl JobPage {
    /// The newest `size` jobs.
    pub fn newest(size: usize) -> Self {
        JobPage {
            size,
            from_seq: u64::MAX,
        }
    }
}

impl State {
    fn add_job(&mut self, id: String, job: Job) {
        self.by_seq.insert(job.seq, id.clone());
        self.jobs.insert(id, job);
    }
}

/// See the module documentation.
pub struct Coordinator {
    config: Config,
    state: Mutex<State>,
}

fn unix_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

fn is_terminal(state: JobState) -> bool {
    matches!(
        state,
        JobState::Succeeded | JobState::Failed | JobState::Cancelled
    )
}

impl Coordinator {
    /// A coordinator with the jobs of the store in `config.data_dir`: queued jobs queued in
    /// their old order, a job that was running queued again in its place (its frame starts
    /// over; partial sums lived only in the old process), finished jobs fetchable.
    pub fn open(config: Config) -> Result<Arc<Self>, StoreError> {
        let store = Store::open(&config.data_dir)?;
        let loaded = store.load()?;
        let journal = Journal::start(store).map_err(|e| StoreError::Writer {
            path: config.data_dir.clone(),
            reason: e.to_string(),
        })?;
        let mut st = State {
            journal,
            starts: 0,
            stored_starts: 0,
            held: Vec::new(),
            preparing: None,
            jobs: BTreeMap::new(),
            by_seq: BTreeMap::new(),
            queue: JobQueue::default(),
            seq: loaded.seq,
            workers: BTreeMap::new(),
            next_key: 0,
            running: None,
            finishing: BTreeMap::new(),
            stopping: false,
            previewed: VecDeque::new(),
            lost: VecDeque::new(),
        };
        for stored in loaded.jobs {
            restore(&mut st, &config.data_dir, stored);
        }
        info!(
            store = %st.journal.path().display(),
            jobs = st.jobs.len(),
            queued = st.jobs.values().filter(|j| j.summary.state() == JobState::Queued).count(),
            "job store opened"
        );
        Ok(Arc::new(Coordinator {
            config,
            state: Mutex::new(st),
        }))
    }

    /// Sets the gauges that are read off the state (jobs by state, workers), for a scrape.
    pub fn refresh_metrics(&self) {
        let mut by_state = [0i64; 5];
        let workers = {
            let st = self.lock();
            for job in st.jobs.values() {
                let i = match job.summary.state() {
                    JobState::Queued | JobState::Unspecified => 0,
                    JobState::Running => 1,
                    JobState::Succeeded => 2,
                    JobState::Failed => 3,
                    JobState::Cancelled => 4,
                };
                by_state[i] += 1;
            }
            st.workers.len()
        };
        let m = rayfarm_node::metrics::coordinator();
        for (gauge, n) in m.jobs.iter().zip(by_state) {
            gauge.set(n);
        }
        m.workers.set(workers as i64);
    }

    pub fn config(&self) -> &Config {
        &self.config
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A handler that panicked mid-update is a bug; keep serving the other jobs.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Stops for good (SIGTERM or Ctrl-C): tells every worker the coordinator is going away
    /// (its control stream ends with `UNAVAILABLE`, so it reconnects with backoff to the next
    /// coordinator), abandons the running frame, and closes the job database so a successor
    /// can open it at once. Nothing is lost: every job change is already on disk, and the job
    /// that was running is still recorded as running, so the next coordinator on this data
    /// directory queues it again at fresh tile epochs.
    pub fn shut_down(&self) {
        let mut st = self.lock();
        st.stopping = true;
        for (_, worker) in std::mem::take(&mut st.workers) {
            let _ = worker.tx.send(Err(Status::unavailable(SHUTTING_DOWN)));
        }
        if let Some(frame) = st.running.take() {
            info!(job = %frame.job_id, "job interrupted: it starts over when a coordinator opens this data directory again");
        }
        let closed = st.journal.close();
        drop(st);
        // Outside the lock: the writer may be releasing held messages, which takes it.
        let _ = closed.recv();
    }
}

fn not_found(id: &str) -> Status {
    Status::not_found(format!("no job {id}"))
}

fn set_state(st: &mut State, id: &str, state: JobState, error: &str) {
    set_state_then(st, id, state, error, None);
}

/// [`set_state`], calling `then` once the change is on disk.
fn set_state_then(st: &mut State, id: &str, state: JobState, error: &str, then: Option<Then>) {
    let Some(job) = st.jobs.get_mut(id) else {
        return;
    };
    job.summary.state = state as i32;
    job.summary.error = error.to_string();
    info!(job = %id, user = %job.summary.owner, state = state_name(state), "job state");
    if is_terminal(state) {
        job.summary.finished_unix_ms = unix_ms();
    }
    if state == JobState::Failed {
        error!(job = %id, error, "job failed");
    }
    let stats_json = job.stats_json.clone();
    let preview_sequence = job.preview.as_ref().map_or(0, |p| p.sequence());
    // Handed over under the lock, so the store sees the changes in the order they happened.
    // Once per state change; a failed write is logged and the job goes on (the change is
    // lost only if the coordinator restarts before the next write of this job).
    match then {
        Some(then) => st.journal.put_then(job.stored(), then),
        None => st.journal.put(job.stored()),
    }
    job.progress.send_modify(|p| {
        p.state = state as i32;
        p.error = error.to_string();
        p.stats_json = stats_json;
        p.preview_sequence = p.preview_sequence.max(preview_sequence);
        if state == JobState::Succeeded {
            p.tiles_done = p.tiles_total;
            p.subframes_done = p.subframes;
            p.eta_seconds = 0.0;
        }
    });
}

/// A job's progress channel, starting at `state`.
fn progress_channel(
    id: &str,
    state: JobState,
    error: &str,
    stats_json: &str,
) -> watch::Sender<proto::WatchJobResponse> {
    watch::channel(proto::WatchJobResponse {
        job_id: id.to_string(),
        state: state as i32,
        eta_seconds: if state == JobState::Succeeded {
            0.0
        } else {
            -1.0
        },
        error: error.to_string(),
        stats_json: stats_json.to_string(),
        ..Default::default()
    })
    .0
}

/// Takes one stored job into the state of a starting coordinator.
fn restore(st: &mut State, data_dir: &std::path::Path, stored: StoredJob) {
    let Some(summary) = stored.summary.clone() else {
        warn!(seq = stored.seq, "a stored job without a summary; skipped");
        return;
    };
    let id = summary.job_id.clone();
    let priority = summary.spec.as_ref().map_or(0, |s| s.priority);
    let mut job = Job {
        cost: summary.spec.as_ref().map_or(0, spec_cost),
        progress: progress_channel(&id, summary.state(), &summary.error, &stored.stats_json),
        summary,
        seq: stored.seq,
        attempts: stored.attempts,
        epoch_floor: 0,
        workers_lost: BTreeMap::new(),
        image_hash: stored.image_hash,
        stats_json: stored.stats_json,
        preview: None,
    };
    let mut changed = None;
    match job.summary.state() {
        JobState::Queued | JobState::Unspecified => st.queue.push(id.clone(), priority, job.seq),
        JobState::Running => {
            // Its frame died with the old process; it starts over, ahead of later jobs of its
            // priority since it keeps its sequence number.
            info!(job = %id, "job was running when the coordinator stopped: queued again");
            st.queue.push(id.clone(), priority, job.seq);
            changed = Some((JobState::Queued, String::new()));
        }
        JobState::Succeeded => {
            let missing = [proto::ImageFormat::Png, proto::ImageFormat::Exr]
                .into_iter()
                .map(|f| results::image_path(data_dir, &id, f))
                .find(|p| !p.is_file());
            if let Some(path) = missing {
                let error = format!("its result file {} is gone", path.display());
                warn!(job = %id, %error, "finished job without its result");
                changed = Some((JobState::Failed, error));
            }
        }
        JobState::Failed | JobState::Cancelled => {}
    }
    if let Some((state, error)) = changed {
        job.summary.state = state as i32;
        job.summary.error = error;
        if state == JobState::Failed {
            job.summary.finished_unix_ms = unix_ms();
        }
        job.progress = progress_channel(&id, state, &job.summary.error, &job.stats_json);
        st.journal.put(job.stored());
    }
    st.add_job(id, job);
}

#[cfg(test)]
mod tests;
