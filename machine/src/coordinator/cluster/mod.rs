//! The coordinator as one machine: the registered workers (registration, refusals of a
//! duplicate id or address, heartbeats and their loss, peers' accusations), the job queue and
//! every job's record, and the frames (started when the cluster is free, finished when their
//! workers' statistics are in, failed, cancelled, re-queued). It owns no socket, clock,
//! thread or file: each event comes in with its time ([`Coordinator::handle`], or a method
//! where the caller needs an answer: [`Coordinator::register`], [`Coordinator::submit`],
//! [`Coordinator::cancel`], [`Coordinator::set_priority`]) and the machine answers with
//! [`Action`]s: messages to workers, streams to close, job records to persist, a frame's scene
//! to read, tiles to write, results to write. The process shell (`rayfarm-coordinator`) and
//! the simulator (`rayfarm-sim`) drive this same value.
//!
//! Modules: `workers` (registration, messages, loss, the periodic tick), `jobs` (submission,
//! quotas, cancel, priority, records), `frames` (starting, holding a start's messages until its
//! record is stored, finishing and failing frames).

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::time::Duration;

use rayfarm_core::cluster::stats::{ClusterStats, SubframeCost, WorkerFrameStats};
use rayfarm_core::render::local::FrameSpec;
use rayfarm_core::schedule::dynamic::Options;
use rayfarm_proto::{self as proto, JobState, worker_message::Body as FromWorker};

use super::frame::{CommittedTile, Outgoing, Rounds, RunningFrame};
pub use super::frame::{FlushWork, PlanningWork};
use super::queue::JobQueue;
use crate::Time;
use crate::queue_report;

mod frames;
mod jobs;
mod workers;

pub use jobs::PriorityRefused;
pub use workers::Refusal;

/// How long a worker planned by an asynchronous round, with nothing to trace, waits for the
/// rays its plan moves to it before it reports again (`RoundPlan.report_hold_ms`): at least
/// `least`, and `per_member` for each member of the frame.
///
/// A held worker reports at most once a hold, so idle members send the coordinator at most
/// members / hold reports a second, each of which may cost a round. A hold that grows with
/// the members keeps that rate at most 1 / `per_member` however large the cluster (10,000 a
/// second by default), while a small cluster keeps the short `least` (a longer hold there
/// only delays a worker that ran out of rays).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ReportHold {
    /// The hold of any frame (the coordinator's `--report-hold-ms`).
    pub least: Duration,
    /// The hold for each member of the frame (`--report-hold-per-worker-us`).
    pub per_member: Duration,
}

impl ReportHold {
    /// Workers report at once.
    pub const NONE: ReportHold = ReportHold {
        least: Duration::ZERO,
        per_member: Duration::ZERO,
    };

    /// 50 ms, or 0.1 ms a member past 500 members: at 1,024 simulated dynamic workers 50 ms
    /// kept the coordinator busy 5.09% of the frame, 100 ms 3.62% (README "Simulator").
    pub const DEFAULT: ReportHold = ReportHold {
        least: Duration::from_millis(50),
        per_member: Duration::from_micros(100),
    };

    /// The hold of a frame of `members` members.
    pub fn for_members(self, members: usize) -> Duration {
        let n = u32::try_from(members).unwrap_or(u32::MAX);
        self.least.max(self.per_member.saturating_mul(n))
    }
}

/// How the coordinator machine is set up.
#[derive(Clone, Debug)]
pub struct Config {
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
    /// Busy members of a frame are told new holders at most once per this interval (with
    /// their next plan if sooner); zero tells them after every round. See
    /// `RunningFrame::flush_holders`.
    pub holders_interval: Duration,
    /// Under asynchronous rounds, how long a planned worker with nothing to trace waits for
    /// the rays its plan moves to it before it reports again (`RoundPlan.report_hold_ms`).
    pub report_hold: ReportHold,
    /// Starts of a job's frame after which it fails instead of starting again (and losses of
    /// one worker during one job after which the job fails).
    pub max_attempts: u32,
    /// Most jobs one user may have queued or running.
    pub max_jobs_per_user: usize,
    /// Most pixels x samples one user may have queued or running.
    pub max_pixel_samples_per_user: u64,
    /// Unix milliseconds at `Time(0)`: job records carry wall-clock times, and the machine
    /// reads no clock (the simulator passes 0).
    pub unix_origin_ms: i64,
}

/// A job as the store keeps it (the shell's store encodes it).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct JobRecord {
    /// The job as the API lists it (spec, state, times, error, owner).
    pub summary: proto::JobSummary,
    /// Submission sequence number: equal priorities run in this order.
    pub seq: u64,
    /// Frames of this job started so far, across restarts.
    pub attempts: u32,
    /// One past the highest tile epoch any frame of this job announced to workers: the
    /// epoch its next frame starts at, at least, so that rays and results of an abandoned
    /// frame still in flight are never taken for the new frame's, whether it was abandoned by
    /// losing every worker or by the coordinator's death. Stored before workers hear of a
    /// new epoch (at a frame's start, and when a loss bumps epochs).
    pub epoch_floor: u32,
    pub image_hash: String,
    /// The finished frame's statistics (JSON). Only the job's final record carries them, to
    /// the store; the machine keeps none, so [`Coordinator::job`] gives a finished job's
    /// record without them (memory does not grow with finished jobs).
    pub stats_json: String,
}

impl JobRecord {
    pub fn state(&self) -> JobState {
        self.summary.state()
    }

    pub fn id(&self) -> &str {
        &self.summary.job_id
    }
}

/// A job and what the machine keeps of it beyond its record.
struct Job {
    record: JobRecord,
    /// Pixels times samples per pixel: what the job weighs against its owner's quota.
    cost: u64,
    /// Times each worker (by id) was lost during this job's frames, in this process.
    workers_lost: BTreeMap<String, u32>,
}

/// A registered worker.
#[derive(Clone, Debug)]
pub struct Registered {
    pub id: String,
    pub peer_address: String,
    pub cache_bytes: u64,
    /// When its last message came.
    pub last_seen: Time,
    /// What its latest queue report said, for the cluster status.
    pub last_report: ReportedQueues,
    /// Its latest heartbeat: its loads, rays traced and queue bytes.
    pub heartbeat: proto::Heartbeat,
    /// Why it declined its last frame ("job ID: reason"); empty once it reports a frame.
    pub left_out: String,
}

/// A worker's latest queue report as the cluster status shows it. Copied into lists that keep
/// their memory, not cloned as a message: every report of a predictive frame at 4,096 workers
/// names about 150 queues, and cloning its maps for the status (and dropping the last copy) was
/// a sixth of the coordinator's CPU there (perf of `rayfarm sim --replay-coordinator`).
#[derive(Clone, Debug, Default)]
pub struct ReportedQueues {
    /// Domains in its memory, least recently used first.
    pub resident_domains: Vec<u32>,
    /// Rays it holds per domain, ascending by domain.
    pub queued_rays: Vec<(u32, u64)>,
}

impl ReportedQueues {
    /// Takes `report`'s figures in place of the last: all of them from a whole report, the
    /// queues it names from one that names only what changed (`QueueReport.delta`), as `read`.
    fn take(&mut self, report: &proto::QueueReport, read: &queue_report::Read) {
        self.resident_domains.clone_from(&report.resident_domains);
        let queue_report::Read::Changes(changes) = read else {
            self.queued_rays.clear();
            self.queued_rays
                .extend(report.queued_rays.iter().map(|(&d, &n)| (d, n)));
            return;
        };
        for &(d, (rays, _)) in changes {
            let at = self.queued_rays.binary_search_by_key(&d, |&(d, _)| d);
            match (at, rays) {
                (Ok(i), Some(n)) => self.queued_rays[i].1 = n,
                (Err(i), Some(n)) => self.queued_rays.insert(i, (d, n)),
                (Ok(i), None) => {
                    self.queued_rays.remove(i);
                }
                (Err(_), None) => {}
            }
        }
    }
}

/// A worker the coordinator dropped, as the dashboard lists it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LostWorker {
    pub worker_id: String,
    pub peer_address: String,
    /// When it was dropped, Unix milliseconds.
    pub lost_unix_ms: i64,
    pub reason: String,
}

/// Workers lost remembered for the dashboard, newest last.
pub const KEPT_LOST_WORKERS: usize = 32;

/// Finished jobs the machine keeps, the latest: a client that saw a job finish asks for its
/// result at once, perhaps before its final record is stored. Older finished jobs are
/// forgotten once their final record is known to be stored (the shell reads them from the
/// store), so the machine's memory does not grow with the jobs it has finished.
pub const KEPT_FINISHED_JOBS: usize = 64;

/// How many jobs are in each state, finished ones included (those the machine has
/// forgotten too), for the metrics.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct JobCounts {
    pub queued: u64,
    pub running: u64,
    pub succeeded: u64,
    pub failed: u64,
    pub cancelled: u64,
}

/// Why a worker's control stream is closed.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Closing {
    /// It ended from the worker's side, or the worker is dropped without a word (its peers
    /// reported it): the stream just ends.
    Dropped,
    /// It sent no heartbeat within the timeout.
    NoHeartbeat,
    /// Its tile results could not be right.
    Refused(String),
    /// The coordinator is stopping.
    ShuttingDown,
}

/// A frame's figures for its watchers.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Progress {
    pub tiles_done: u32,
    pub tiles_total: u32,
    /// Subframes committed, and in all (1 for a one-pass frame).
    pub subframes_done: u32,
    pub subframes: u32,
    pub round: u64,
    pub rays_per_second: f64,
    /// Seconds, or -1 while unknown.
    pub eta_seconds: f64,
}

/// What the shell read for a frame's start: the frame checked against its scene's camera,
/// and the bytes of each domain file. (The shell created the film its tiles go to.)
#[derive(Clone, Debug)]
pub struct OpenedFrame {
    pub frame: FrameSpec,
    pub domain_bytes: Vec<u64>,
}

/// Counts for the shell's metrics.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Tally {
    /// Rounds planned, with what they planned (the time the event took is planning time).
    Rounds(PlanningWork),
    /// A holders flush made, with what it walked and made (`FlushWork`): the coordinator's
    /// time too, priced apart from the rounds by the simulator.
    HoldersFlushed(FlushWork),
    TilesCommitted(u64),
    /// A subframe of a frame committed (a one-pass frame is one subframe).
    SubframeCommitted,
    FrameCommitted,
    FrameFailed,
    WorkerLost,
}

/// Something that happened, with no answer owed to its caller.
#[derive(Clone, Debug)]
pub enum Input {
    /// A message of a registered worker (by its key).
    WorkerMessage { key: u32, body: FromWorker },
    /// A worker's control stream ended, from its side.
    WorkerGone { key: u32, why: String },
    /// Time passed: silent workers are dropped, accusations judged, finished frames whose
    /// reports are overdue written.
    Tick,
    /// The scene of the frame asked for by [`Action::PrepareFrame`] was read (or why not).
    FrameOpened {
        job_id: String,
        opened: Result<OpenedFrame, String>,
    },
    /// The record persisted with `barrier: Some(barrier)` is stored.
    Stored { barrier: u64 },
    /// The first record of a submitted job is stored (or why not: the job is forgotten).
    Recorded {
        job_id: String,
        result: Result<(), String>,
    },
    /// The results asked for by [`Action::WriteResults`] are written: (statistics JSON,
    /// image hash), or why not.
    ResultsWritten {
        job_id: String,
        result: Result<(String, String), String>,
    },
    /// The job's frame cannot go on (its film could not be written).
    Fail { job_id: String, error: String },
    /// The coordinator stops: every worker's stream closes, the running frame is abandoned
    /// (its job stays recorded as running, so the next coordinator queues it again).
    ShutDown,
}

/// Something for the shell to do, in order.
#[derive(Debug)]
pub enum Action {
    /// This message to the worker with this key.
    Send(Outgoing),
    /// Close this worker's control stream (it is no longer registered).
    Close {
        key: u32,
        closing: Closing,
    },
    /// Write this job record (after every record before it). With a `barrier`, answer
    /// [`Input::Stored`] once it is on disk: messages to workers decided after it wait for
    /// it (a frame's start, or new epochs after a loss, are stored before workers hear).
    Persist {
        record: JobRecord,
        barrier: Option<u64>,
    },
    /// The running frame's figures changed.
    Progress {
        job_id: String,
        progress: Progress,
    },
    /// Read the job's scene and create its film; answer [`Input::FrameOpened`].
    PrepareFrame {
        job_id: String,
        spec: proto::JobSpec,
    },
    /// The prepared frame of this job started (this is its `attempt`-th start).
    FrameStarted {
        job_id: String,
        attempt: u32,
    },
    /// Add these committed tiles, of `samples` samples a pixel, to the job's film (whose
    /// previews then show `subframes_done` whole subframes); on failure answer
    /// [`Input::Fail`].
    WriteTiles {
        job_id: String,
        tiles: Vec<CommittedTile>,
        samples: u32,
        subframes_done: u32,
    },
    /// The job's film is not needed any more (its frame was abandoned or never started).
    Discard {
        job_id: String,
    },
    /// Write the finished job's images and statistics; answer [`Input::ResultsWritten`].
    WriteResults {
        job_id: String,
        stats: Box<ClusterStats>,
    },
    Tally(Tally),
}

/// A frame whose tiles are all in, waiting for its workers' statistics, by the frame id the
/// workers know (a progressive job's committed subframes each have one: their reports are
/// summed into the job's statistics when its last subframe is written).
struct Finishing {
    /// The job it is a frame (or subframe) of.
    job: String,
    /// The job's statistics but the workers': for its last subframe only.
    stats: Option<ClusterStats>,
    /// This subframe's samples and time; its loads are summed from `reports` at the end.
    cost: SubframeCost,
    waiting: BTreeSet<u32>,
    reports: Vec<WorkerFrameStats>,
    /// When it stops waiting.
    deadline: Time,
}

/// See the module documentation.
pub struct Coordinator {
    config: Config,
    jobs: BTreeMap<String, Job>,
    /// Every job's id by its sequence number, so a page of the list is a range, not a sort.
    by_seq: BTreeMap<u64, String>,
    queue: JobQueue,
    /// The highest sequence number handed out.
    seq: u64,
    workers: BTreeMap<u32, Registered>,
    next_key: u32,
    /// The job whose frame is being prepared by the shell.
    preparing: Option<String>,
    running: Option<RunningFrame>,
    finishing: BTreeMap<String, Finishing>,
    /// Records persisted with a barrier so far, and the latest stored: until it is, messages
    /// to workers wait in `held` (in order), so no worker hears of a frame or of its new
    /// epochs before the record is stored (a frame that kills the coordinator counts against
    /// the job's attempts, and the next frame starts above every epoch announced).
    barriers: u64,
    stored_barriers: u64,
    held: Vec<(u64, Outgoing)>,
    /// Set by [`Input::ShutDown`]: no worker attaches and no frame starts any more.
    stopping: bool,
    /// The latest workers dropped (at most [`KEPT_LOST_WORKERS`]).
    lost: VecDeque<LostWorker>,
    /// Finished jobs still held, oldest first, each with the barrier whose storing proves
    /// its final record stored (records are stored in the order they are made).
    finished: VecDeque<(String, u64)>,
    /// Jobs finished in each state since the store began: succeeded, failed, cancelled.
    ended: [u64; 3],
    /// Whether a queue report was taken since the last [`Coordinator::plan`].
    reports_taken: bool,
}

/// Whether a job in `state` has ended (succeeded, failed or cancelled): it never changes
/// again.
pub fn is_terminal(state: JobState) -> bool {
    matches!(
        state,
        JobState::Succeeded | JobState::Failed | JobState::Cancelled
    )
}

impl Coordinator {
    /// A coordinator with no jobs yet whose sequence numbers go on from `seq`; the stored
    /// jobs come in through [`restore`](Self::restore).
    pub fn new(config: Config, seq: u64) -> Self {
        Coordinator {
            config,
            jobs: BTreeMap::new(),
            by_seq: BTreeMap::new(),
            queue: JobQueue::default(),
            seq,
            workers: BTreeMap::new(),
            next_key: 0,
            preparing: None,
            running: None,
            finishing: BTreeMap::new(),
            barriers: 0,
            stored_barriers: 0,
            held: Vec::new(),
            stopping: false,
            lost: VecDeque::new(),
            finished: VecDeque::new(),
            ended: [0; 3],
            reports_taken: false,
        }
    }

    pub fn config(&self) -> &Config {
        &self.config
    }

    /// Handles one event at `now`: [`Coordinator::take`] then [`Coordinator::plan`].
    pub fn handle(&mut self, now: Time, input: Input) -> Vec<Action> {
        let mut out = self.take(now, input);
        out.extend(self.plan(now));
        out
    }

    /// Takes one event at `now` without planning the round its reports ask for: a shell that
    /// has several inputs at hand (a busy coordinator's, received while it planned) takes them
    /// all, then calls [`Coordinator::plan`] once, so one round plans every member that ran
    /// dry among them. Planning each report apart cost 1.74 M rounds over a 1,024-worker
    /// frame, the coordinator busy 39% of it (README "Simulator").
    pub fn take(&mut self, now: Time, input: Input) -> Vec<Action> {
        let mut out = Vec::new();
        match input {
            Input::WorkerMessage { key, body } => self.worker_message(now, key, body, &mut out),
            Input::WorkerGone { key, why } => self.lose(now, key, &why, Closing::Dropped, &mut out),
            Input::Tick => self.tick(now, &mut out),
            Input::FrameOpened { job_id, opened } => self.begin(now, &job_id, opened, &mut out),
            Input::Stored { barrier } => self.release_held(barrier, &mut out),
            Input::Recorded { job_id, result } => self.recorded(now, &job_id, result, &mut out),
            Input::ResultsWritten { job_id, result } => {
                self.results_written(now, &job_id, result, &mut out)
            }
            Input::Fail { job_id, error } => self.fail_job(now, &job_id, &error, &mut out),
            Input::ShutDown => self.shut_down(&mut out),
        }
        out
    }

    /// Plans the round the reports taken since the last asked for (one round, whatever their
    /// number), publishes the progress they brought, and sends the holders flush if it is due.
    pub fn plan(&mut self, now: Time) -> Vec<Action> {
        let mut out = self.plan_round(now);
        out.extend(self.flush(now));
        out
    }

    /// [`Coordinator::plan`] without the holders flush (then [`Coordinator::flush`]): for
    /// timing rounds and flushes apart (`synthetic::SteadyFrame::handle_round`, which `rayfarm
    /// sim calibrate` prices flushes by).
    pub fn plan_round(&mut self, now: Time) -> Vec<Action> {
        let mut out = Vec::new();
        if std::mem::take(&mut self.reports_taken)
            && let Some(f) = self.running.as_mut()
        {
            let before = f.planning;
            let plans = f.plan_asked();
            workers::tally_rounds(f, &before, &mut out);
            self.send(plans, &mut out);
            self.publish_progress(now, &mut out);
        }
        out
    }

    /// The running frame's holders flush, if it is due at `now` (what [`Coordinator::plan`]
    /// does after the round).
    pub fn flush(&mut self, now: Time) -> Vec<Action> {
        let mut out = Vec::new();
        self.flush_holders(now, &mut out);
        out
    }

    /// The running frame's holders flush, if it is due: checked after every event, so while
    /// workers talk to the coordinator (every heartbeat at least) a flush leaves within its
    /// interval; the tick is the backstop ([`Coordinator::next_deadline`]).
    fn flush_holders(&mut self, now: Time, out: &mut Vec<Action>) {
        let Some(frame) = self.running.as_mut() else {
            return;
        };
        let before = frame.flushing;
        let messages = frame.flush_holders(now);
        let work = frame.flushing.since(&before);
        if work.flushes > 0 {
            out.push(Action::Tally(Tally::HoldersFlushed(work)));
        }
        if !messages.is_empty() {
            self.send(messages, out);
        }
    }

    /// Wall-clock milliseconds at `now`.
    fn unix_ms(&self, now: Time) -> i64 {
        self.config.unix_origin_ms + (now.0 / 1_000_000) as i64
    }

    /// The registered workers by key.
    pub fn workers(&self) -> impl Iterator<Item = (u32, &Registered)> {
        self.workers.iter().map(|(&k, w)| (k, w))
    }

    /// The frame running now.
    pub fn running(&self) -> Option<&RunningFrame> {
        self.running.as_ref()
    }

    /// The latest workers dropped, oldest first.
    pub fn lost_workers(&self) -> impl Iterator<Item = &LostWorker> {
        self.lost.iter()
    }

    /// Job `id`'s record, if the machine holds it: every unfinished job and the latest
    /// finished ones ([`KEPT_FINISHED_JOBS`]); the others are the store's.
    pub fn job(&self, id: &str) -> Option<&JobRecord> {
        self.jobs.get(id).map(|j| &j.record)
    }

    /// Every job's record the machine holds, in no particular order.
    pub fn jobs(&self) -> impl Iterator<Item = &JobRecord> {
        self.jobs.values().map(|j| &j.record)
    }

    /// How many jobs are in each state, the forgotten finished ones included.
    pub fn job_counts(&self) -> JobCounts {
        let mut counts = JobCounts {
            succeeded: self.ended[0],
            failed: self.ended[1],
            cancelled: self.ended[2],
            ..JobCounts::default()
        };
        for job in self.jobs.values() {
            match job.record.state() {
                JobState::Queued | JobState::Unspecified => counts.queued += 1,
                JobState::Running => counts.running += 1,
                // Counted in `ended` when they finished.
                JobState::Succeeded | JobState::Failed | JobState::Cancelled => {}
            }
        }
        counts
    }

    /// At most `size` of the jobs the machine holds, newest first, from sequence number
    /// `from_seq` down; and the sequence number the next page starts at, if any.
    pub fn page(&self, size: usize, from_seq: u64) -> (Vec<&JobRecord>, Option<u64>) {
        let mut ids = self.by_seq.range(..=from_seq).rev();
        let jobs = ids
            .by_ref()
            .take(size)
            .filter_map(|(_, id)| self.job(id))
            .collect();
        (jobs, ids.next().map(|(&seq, _)| seq))
    }

    /// The earliest time a [`Input::Tick`] has work to do besides the periodic reaping: a
    /// finished frame's report deadline, or the running frame's next holders flush.
    pub fn next_deadline(&self) -> Option<Time> {
        self.finishing
            .values()
            .filter(|f| f.stats.is_some())
            .map(|f| f.deadline)
            .chain(self.running.as_ref().and_then(RunningFrame::holders_due))
            .min()
    }
}

#[cfg(test)]
mod tests;
