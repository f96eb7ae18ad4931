//! The coordinator's shell around its machine (`rayfarm_machine::coordinator::Coordinator`,
//! which holds the workers, the job queue, the job records and the frames, and does no I/O).
//! Handlers of both gRPC services call in here: each takes the lock, hands the machine one
//! event with the time, and carries out the actions it returns (`actions`) without awaiting:
//! messages go on unbounded channels, job records to the store's writer (`journal`, written
//! outside the lock), a frame's scene is read and its film created on a thread of its own,
//! results written on another, and each answers the machine with an event when done. What
//! only the shell holds: the workers' channels, each job's progress channel and previews,
//! and the films of frames being prepared, running or finishing.

use std::collections::{BTreeMap, VecDeque};
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use rayfarm_core::cluster::scene_ref;
use rayfarm_core::scene::Manifest;
use rayfarm_core::schedule::dynamic::Options;
use rayfarm_machine::coordinator::cluster::{self, Input, JobRecord, ReportHold, is_terminal};
use rayfarm_machine::coordinator::{Coordinator as Machine, Rounds};
use rayfarm_node::job::{frame_spec, schedule_name, state_name};
use rayfarm_node::proto::{self, JobState, Schedule, worker_message::Body as FromWorker};
use rayfarm_node::security::User;
use tokio::sync::{mpsc, watch};
use tonic::Status;
use tracing::{error, info, warn};

use crate::admission::{Needs, free_disk};
use crate::journal::{Journal, Reader};
use crate::preview::Previews;
use crate::results;
use crate::running::{Running, now};
use crate::store::{Store, StoreError, StoredJob};

mod actions;
mod frames;
mod jobs;
mod workers;

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
    /// Busy workers are told new holders at most once per this interval.
    pub holders_interval: Duration,
    /// Under asynchronous rounds, how long a planned worker with nothing to trace waits for
    /// the rays its plan moves to it before it reports again.
    pub report_hold: ReportHold,
    /// Admission: the most a frame may need of each figure (`admission::Needs`).
    pub max_frame_bytes: u64,
    /// Starts of a job's frame after which it fails instead of starting again.
    pub max_attempts: u32,
}

/// What workers and clients are told once the coordinator is stopping.
pub const SHUTTING_DOWN: &str = "the coordinator is shutting down";

/// Where a worker's messages go: shared with every member told the same (a holders flush
/// makes one message per view class, `rayfarm_machine::coordinator::Outgoing`), so carrying
/// the machine's actions out under the state's lock costs a reference a worker; the worker's
/// stream task copies the message out (`Arc::unwrap_or_clone`) and encodes it.
pub type WorkerTx = mpsc::UnboundedSender<Result<Arc<proto::CoordinatorMessage>, Status>>;

/// What the shell keeps of a job beside its record in the machine.
struct JobView {
    progress: watch::Sender<proto::WatchJobResponse>,
    /// Previews of its latest frame, kept while it runs and for the last
    /// [`KEPT_PREVIEWS`] frames started.
    preview: Option<Arc<Previews>>,
}

/// Frames whose previews stay in memory once they end (each a PNG of at most 1024 pixels
/// a side).
const KEPT_PREVIEWS: usize = 4;

/// Finished jobs whose progress channel (with their statistics) stays in memory, newest last:
/// a watcher or fetch right after the end is answered from it while the store's writer may
/// still be writing the final record. Older ones are answered from the store, so memory does
/// not grow with the jobs a coordinator has finished.
const KEPT_FINISHED_VIEWS: usize = 64;

/// A worker the coordinator dropped, as the dashboard lists it.
#[derive(Clone, Debug, serde::Serialize)]
pub struct LostWorker {
    pub worker_id: String,
    pub peer_address: String,
    /// When it was dropped, Unix milliseconds.
    pub lost_unix_ms: i64,
    pub reason: String,
}

struct State {
    machine: Machine,
    /// Where every job record goes, in order, written outside this state's lock.
    journal: Journal,
    /// Each registered worker's control stream.
    senders: BTreeMap<u32, WorkerTx>,
    views: BTreeMap<String, JobView>,
    /// Films of frames being prepared, running or finishing, by job.
    films: BTreeMap<String, Running>,
    /// Jobs holding previews, in the order their frames started (at most [`KEPT_PREVIEWS`]).
    previewed: VecDeque<String>,
    /// Finished jobs with a view, in the order they finished (at most
    /// [`KEPT_FINISHED_VIEWS`]).
    finished: VecDeque<String>,
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

/// See the module documentation.
pub struct Coordinator {
    config: Config,
    state: Mutex<State>,
    /// Reads finished jobs' records (their statistics) outside the state's lock.
    store: Reader,
}

fn unix_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

/// The machine's set-up from the shell's.
fn machine_config(config: &Config) -> cluster::Config {
    cluster::Config {
        heartbeat: config.heartbeat,
        worker_timeout: config.worker_timeout,
        report_timeout: config.report_timeout,
        schedule_options: config.schedule_options,
        rounds: config.rounds,
        holders_interval: config.holders_interval,
        report_hold: config.report_hold,
        max_attempts: config.max_attempts,
        max_jobs_per_user: config.max_jobs_per_user,
        max_pixel_samples_per_user: config.max_pixel_samples_per_user,
        // The machine's times count from `now()`'s origin.
        unix_origin_ms: unix_ms() - (now().0 / 1_000_000) as i64,
    }
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
        let store = journal.reader();
        let mut st = State {
            machine: Machine::new(machine_config(&config), loaded.seq),
            journal,
            senders: BTreeMap::new(),
            views: BTreeMap::new(),
            films: BTreeMap::new(),
            previewed: VecDeque::new(),
            finished: VecDeque::new(),
        };
        // What the restore changes (a finished job whose images are gone now fails) is on
        // disk before anyone can ask: finished jobs are answered from the store.
        let mut restored = Vec::new();
        for stored in loaded.jobs {
            let Some(record) = stored.into_record() else {
                continue;
            };
            // A finished job's images must still be there (a file check, off the machine).
            let missing = (record.state() == JobState::Succeeded)
                .then(|| {
                    [proto::ImageFormat::Png, proto::ImageFormat::Exr]
                        .into_iter()
                        .map(|f| results::image_path(&config.data_dir, record.id(), f))
                        .find(|p| !p.is_file())
                })
                .flatten()
                .map(|p| p.display().to_string());
            let id = record.id().to_string();
            let actions = st.machine.restore(now(), record, missing);
            for a in actions {
                if let cluster::Action::Persist { record, .. } = a {
                    let (written, wait) = std::sync::mpsc::channel();
                    let then = Box::new(move |r| drop(written.send(r)));
                    st.journal.put_then(StoredJob::from_record(&record), then);
                    restored.push(wait);
                }
            }
            // Finished jobs are answered from the store (see `KEPT_FINISHED_VIEWS`).
            if let Some(record) = st.machine.job(&id).filter(|r| !is_terminal(r.state())) {
                let view = JobView {
                    progress: progress_channel(record),
                    preview: None,
                };
                st.views.insert(id, view);
            }
        }
        for wait in restored {
            if let Ok(Err(e)) = wait.recv() {
                warn!(error = %e, "a restored job's record was not saved");
            }
        }
        let counts = st.machine.job_counts();
        info!(
            store = %st.journal.path().display(),
            queued = counts.queued,
            finished = counts.succeeded + counts.failed + counts.cancelled,
            "job store opened"
        );
        Ok(Arc::new(Coordinator {
            config,
            state: Mutex::new(st),
            store,
        }))
    }

    /// Sets the gauges that are read off the state (jobs by state, workers), for a scrape.
    pub fn refresh_metrics(&self) {
        let (counts, workers) = {
            let st = self.lock();
            (st.machine.job_counts(), st.machine.workers().count())
        };
        let by_state = [
            counts.queued,
            counts.running,
            counts.succeeded,
            counts.failed,
            counts.cancelled,
        ];
        let m = rayfarm_node::metrics::coordinator();
        for (gauge, n) in m.jobs.iter().zip(by_state) {
            gauge.set(n as i64);
        }
        m.workers.set(workers as i64);
    }

    pub fn config(&self) -> &Config {
        &self.config
    }

    /// Runs `call` on a blocking thread, as a request handler must for the calls that may
    /// read the job store (a job finished long ago is only there).
    pub async fn off_runtime<T: Send + 'static>(
        self: &Arc<Self>,
        call: impl FnOnce(&Arc<Coordinator>) -> Result<T, Status> + Send + 'static,
    ) -> Result<T, Status> {
        let this = self.clone();
        tokio::task::spawn_blocking(move || call(&this))
            .await
            .map_err(|e| Status::internal(format!("the request failed: {e}")))?
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A handler that panicked mid-update is a bug; keep serving the other jobs.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Hands the machine `input` and carries out what it decides.
    fn feed(self: &Arc<Self>, st: &mut State, input: Input) {
        let began = Instant::now();
        let actions = st.machine.handle(now(), input);
        self.carry_out(st, actions, began);
    }

    /// Stops for good (SIGTERM or Ctrl-C): tells every worker the coordinator is going away
    /// (its control stream ends with `UNAVAILABLE`, so it reconnects with backoff to the next
    /// coordinator), abandons the running frame, and closes the job database so a successor
    /// can open it at once. Nothing is lost: every job change is already on disk, and the job
    /// that was running is still recorded as running, so the next coordinator on this data
    /// directory queues it again at fresh tile epochs.
    pub fn shut_down(self: &Arc<Self>) {
        let mut st = self.lock();
        self.feed(&mut st, Input::ShutDown);
        let closed = st.journal.close();
        drop(st);
        // Outside the lock: the writer may be releasing held messages, which takes it.
        let _ = closed.recv();
    }
}

fn not_found(id: &str) -> Status {
    Status::not_found(format!("no job {id}"))
}

/// A job's progress channel, starting at its record's state.
fn progress_channel(record: &JobRecord) -> watch::Sender<proto::WatchJobResponse> {
    let state = record.state();
    watch::channel(proto::WatchJobResponse {
        job_id: record.id().to_string(),
        state: state as i32,
        eta_seconds: if state == JobState::Succeeded {
            0.0
        } else {
            -1.0
        },
        error: record.summary.error.clone(),
        stats_json: record.stats_json.clone(),
        ..Default::default()
    })
    .0
}

#[cfg(test)]
mod tests;
