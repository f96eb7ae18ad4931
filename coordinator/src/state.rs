//! The coordinator's state and everything that changes it: jobs and their queue, registered
//! workers, the running frame and frames being finished. Handlers of both gRPC services call
//! in here; every method takes the lock briefly and sends on unbounded channels, never
//! awaiting while holding it.

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard};
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

use crate::admission::{Needs, free_disk};
use crate::frame::{CommittedTile, Member, Outgoing, Rounds, RunningFrame};
use crate::queue::JobQueue;
use crate::results;
use crate::store::{Store, StoreError, StoredJob};

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

/// Least time a worker's report of an unreachable peer waits for the other side's reports
/// (see [`crate::accusations`]): both sides notice a broken link within about this long of
/// each other when their deadlines are alike.
const ACCUSATION_GRACE: Duration = Duration::from_secs(2);

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
    /// Why it declined its last frame ("job ID: reason"); empty once it reports a frame.
    left_out: String,
}

struct Finishing {
    waiting: BTreeSet<u32>,
    reports: Vec<WorkerFrameStats>,
    done: Option<oneshot::Sender<()>>,
}

struct State {
    /// Where every job change is written through to.
    store: Store,
    jobs: BTreeMap<String, Job>,
    /// Every job's id by its sequence number, so a page of the list is a range, not a sort.
    by_seq: BTreeMap<u64, String>,
    queue: JobQueue,
    seq: u64,
    workers: BTreeMap<u32, WorkerEntry>,
    next_key: u32,
    running: Option<RunningFrame>,
    finishing: BTreeMap<String, Finishing>,
    /// Set by [`Coordinator::shut_down`]: no worker attaches and no frame starts any more.
    stopping: bool,
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
        let mut st = State {
            store,
            jobs: BTreeMap::new(),
            by_seq: BTreeMap::new(),
            queue: JobQueue::default(),
            seq: loaded.seq,
            workers: BTreeMap::new(),
            next_key: 0,
            running: None,
            finishing: BTreeMap::new(),
            stopping: false,
        };
        for stored in loaded.jobs {
            restore(&mut st, &config.data_dir, stored);
        }
        info!(
            store = %st.store.path().display(),
            jobs = st.jobs.len(),
            queued = st.jobs.values().filter(|j| j.summary.state() == JobState::Queued).count(),
            "job store opened"
        );
        Ok(Arc::new(Coordinator {
            config,
            state: Mutex::new(st),
        }))
    }

    pub fn config(&self) -> &Config {
        &self.config
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A handler that panicked mid-update is a bug; keep serving the other jobs.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    // ----- the user API -----

    /// Checks and queues a job; returns its id. Reads the scene's manifest on the calling
    /// thread: the job API reads it off the async runtime ([`Coordinator::spec_with_defaults`],
    /// [`Coordinator::open_scene`], [`Coordinator::enqueue`]).
    #[cfg(test)]
    pub fn submit(self: &Arc<Self>, spec: Option<proto::JobSpec>) -> Result<String, Status> {
        let spec = self.spec_with_defaults(spec)?;
        let (_, manifest) = self.open_scene(&spec.scene)?;
        self.enqueue(spec, &manifest, None)
    }

    /// The job's spec with the defaults filled in (schedule, scene), or why it has none.
    pub fn spec_with_defaults(
        &self,
        spec: Option<proto::JobSpec>,
    ) -> Result<proto::JobSpec, Status> {
        let mut spec =
            spec.ok_or_else(|| Status::invalid_argument("the request has no job spec"))?;
        let schedule = Schedule::try_from(spec.schedule)
            .map_err(|_| Status::invalid_argument(format!("unknown schedule {}", spec.schedule)))?;
        let schedule = match schedule {
            Schedule::Unspecified => Schedule::Dynamic,
            s => s,
        };
        spec.schedule = schedule as i32;
        if spec.scene.is_empty() {
            spec.scene = self.config.default_scene.clone().unwrap_or_default();
        }
        Ok(spec)
    }

    /// Checks `spec` against its scene's `manifest` and the quotas of `user` (the
    /// authenticated submitter, `None` without user tokens), and queues the job owned by the
    /// user; returns its id.
    pub fn enqueue(
        self: &Arc<Self>,
        spec: proto::JobSpec,
        manifest: &Manifest,
        user: Option<&User>,
    ) -> Result<String, Status> {
        let frame = frame_spec(&spec, &manifest.camera).map_err(Status::invalid_argument)?;
        self.admit(&frame)?;
        let cost = u64::from(frame.width) * u64::from(frame.height) * u64::from(frame.spp);
        let owner = user.map(|u| u.name.clone()).unwrap_or_default();
        let mut st = self.lock();
        self.check_quota(&st, &owner, cost)?;
        st.seq += 1;
        let seq = st.seq;
        let id = format!("job-{}-{seq}", unix_ms() / 1000);
        let summary = proto::JobSummary {
            job_id: id.clone(),
            spec: Some(spec.clone()),
            state: JobState::Queued as i32,
            submitted_unix_ms: unix_ms(),
            owner: owner.clone(),
            ..Default::default()
        };
        let job = Job {
            summary,
            cost,
            seq,
            attempts: 0,
            epoch_floor: 0,
            workers_lost: BTreeMap::new(),
            progress: progress_channel(&id, JobState::Queued, "", ""),
            image_hash: String::new(),
            stats_json: String::new(),
        };
        // A job the client was told about must survive a restart: on disk before the reply.
        st.store.put(&job.stored()).map_err(|e| {
            let e = e.with_causes();
            error!(job = %id, error = %e, "job not recorded");
            Status::internal(format!("the job could not be recorded: {e}"))
        })?;
        st.add_job(id.clone(), job);
        st.queue.push(id.clone(), spec.priority, seq);
        info!(job = %id, user = %owner, scene = %spec.scene, width = spec.width, height = spec.height, spp = spec.spp, priority = spec.priority, "job queued");
        self.try_start(&mut st);
        Ok(id)
    }

    /// Refuses a frame whose needs pass the limits (see `admission`).
    fn admit(&self, frame: &rayfarm_core::render::local::FrameSpec) -> Result<(), Status> {
        let needs = Needs::of(frame)
            .ok_or_else(|| Status::invalid_argument("the image does not fit the tile grid"))?;
        let dir = &self.config.data_dir;
        let free = free_disk(dir).map_err(|e| {
            Status::internal(format!("free disk of {} unknown: {e}", dir.display()))
        })?;
        needs
            .check(self.config.max_frame_bytes, dir, free)
            .map_err(|reason| {
                warn!(%reason, "job refused");
                Status::resource_exhausted(reason)
            })
    }

    /// The directory and manifest of `scene`, resolved under the scene root (see
    /// [`scene_ref`]). Errors name the scene and the position of a fault in its manifest,
    /// never the manifest's text nor anything about paths outside the root.
    pub fn open_scene(&self, scene: &str) -> Result<(PathBuf, Manifest), Status> {
        let dir = scene_ref::resolve(
            &self.config.scene_root,
            scene,
            self.config.allow_absolute_scenes,
        )
        .map_err(|e| match e {
            scene_ref::SceneRefError::Missing => Status::failed_precondition(e.to_string()),
            scene_ref::SceneRefError::Escapes(_) | scene_ref::SceneRefError::Absolute(_) => {
                Status::invalid_argument(e.to_string())
            }
            scene_ref::SceneRefError::NotFound(_) => Status::not_found(e.to_string()),
            scene_ref::SceneRefError::Root(..) => {
                error!(error = %e, "scene root unusable");
                Status::unavailable(format!(
                    "scene {scene:?}: the coordinator's scene root is unusable"
                ))
            }
        })?;
        let manifest = Manifest::load(&dir)
            .map_err(|e| Status::failed_precondition(format!("scene {scene:?}: {e}")))?;
        Ok((dir, manifest))
    }

    /// Refuses (`RESOURCE_EXHAUSTED`) a job of `cost` that would take `owner` past a quota.
    fn check_quota(&self, st: &State, owner: &str, cost: u64) -> Result<(), Status> {
        let (jobs, queued) = st
            .jobs
            .values()
            .filter(|j| j.summary.owner == owner && !is_terminal(j.summary.state()))
            .fold((0usize, 0u64), |(n, c), j| {
                (n + 1, c.saturating_add(j.cost))
            });
        let who = if owner.is_empty() { "anonymous" } else { owner };
        if jobs >= self.config.max_jobs_per_user {
            warn!(user = %who, jobs, "job refused: queued-jobs quota");
            return Err(Status::resource_exhausted(format!(
                "user {who} has {jobs} jobs queued or running, the most allowed \
                 (--max-jobs-per-user {})",
                self.config.max_jobs_per_user
            )));
        }
        let max = self.config.max_pixel_samples_per_user;
        if queued.saturating_add(cost) > max {
            warn!(user = %who, queued, cost, "job refused: pixel-samples quota");
            return Err(Status::resource_exhausted(format!(
                "user {who} has {queued} pixel-samples queued or running; this job's {cost} \
                 would pass the quota of {max} (--max-pixel-samples-per-user)"
            )));
        }
        Ok(())
    }

    /// Cancels a queued or running job for `user` (`None` without user tokens: anyone may);
    /// returns its state afterwards. Only the job's owner or an admin may cancel it.
    pub fn cancel(self: &Arc<Self>, id: &str, user: Option<&User>) -> Result<JobState, Status> {
        let mut st = self.lock();
        let job = st.jobs.get(id).ok_or_else(|| not_found(id))?;
        if let Some(user) = user
            && !user.admin
            && job.summary.owner != user.name
        {
            warn!(job = %id, user = %user.name, owner = %job.summary.owner, "cancel refused: not the owner");
            return Err(Status::permission_denied(format!(
                "job {id} belongs to another user: only its owner or an admin may cancel it"
            )));
        }
        let state = job.summary.state();
        if is_terminal(state) {
            return Ok(state);
        }
        if st.queue.remove(id) {
            set_state(&mut st, id, JobState::Cancelled, "");
        } else if st.running.as_ref().is_some_and(|f| f.job_id == id) {
            if let Some(frame) = st.running.take() {
                end_frame(&st, &frame);
            }
            set_state(&mut st, id, JobState::Cancelled, "");
            self.try_start(&mut st);
        }
        info!(job = %id, user = %user.map_or("", |u| u.name.as_str()), "job cancelled");
        Ok(st
            .jobs
            .get(id)
            .map_or(JobState::Cancelled, |j| j.summary.state()))
    }

    /// Jobs, newest first.
    pub fn list(&self, page: JobPage) -> (Vec<proto::JobSummary>, Option<u64>) {
        let st = self.lock();
        let mut ids = st.by_seq.range(..=page.from_seq).rev();
        let jobs = ids
            .by_ref()
            .take(page.size)
            .filter_map(|(_, id)| st.jobs.get(id))
            .map(|j| j.summary.clone())
            .collect();
        (jobs, ids.next().map(|(&seq, _)| seq))
    }

    /// A receiver of a job's progress events.
    pub fn watch(&self, id: &str) -> Result<watch::Receiver<proto::WatchJobResponse>, Status> {
        let st = self.lock();
        st.jobs
            .get(id)
            .map(|j| j.progress.subscribe())
            .ok_or_else(|| not_found(id))
    }

    /// Where a finished job's image is, with its statistics and hash.
    pub fn result(
        &self,
        id: &str,
        format: proto::ImageFormat,
    ) -> Result<(PathBuf, String, String), Status> {
        let st = self.lock();
        let job = st.jobs.get(id).ok_or_else(|| not_found(id))?;
        if job.summary.state() != JobState::Succeeded {
            return Err(Status::failed_precondition(format!(
                "job {id} is {} and has no result",
                state_name(job.summary.state())
            )));
        }
        Ok((
            results::image_path(&self.config.data_dir, id, format),
            job.stats_json.clone(),
            job.image_hash.clone(),
        ))
    }

    /// Workers, their resident domains and queues.
    pub fn status(&self) -> proto::GetClusterStatusResponse {
        let st = self.lock();
        proto::GetClusterStatusResponse {
            workers: st
                .workers
                .values()
                .map(|w| proto::WorkerStatus {
                    worker_id: w.id.clone(),
                    peer_address: w.peer_address.clone(),
                    resident_domains: w
                        .last_report
                        .as_ref()
                        .map(|r| r.resident_domains.clone())
                        .unwrap_or_default(),
                    queued_rays: w
                        .last_report
                        .as_ref()
                        .map(|r| r.queued_rays.clone())
                        .unwrap_or_default(),
                    last_seen_ms: w.last_seen.elapsed().as_millis() as u64,
                    left_out: w.left_out.clone(),
                })
                .collect(),
            running_job_id: st
                .running
                .as_ref()
                .map(|f| f.job_id.clone())
                .unwrap_or_default(),
            round: st.running.as_ref().map_or(0, |f| f.round),
        }
    }

    // ----- workers -----

    /// Registers a worker whose messages go to `tx`; returns its key.
    pub fn register(self: &Arc<Self>, r: &proto::Register, tx: WorkerTx) -> Result<u32, Status> {
        rayfarm_node::bounds::check_field("worker_id", &r.worker_id)?;
        rayfarm_node::bounds::check_field("peer_address", &r.peer_address)?;
        if r.protocol_version != PROTOCOL_VERSION {
            return Err(Status::failed_precondition(format!(
                "worker speaks protocol {}, the coordinator {PROTOCOL_VERSION}",
                r.protocol_version
            )));
        }
        if r.worker_id.is_empty() || r.peer_address.is_empty() {
            return Err(Status::invalid_argument(
                "worker id and peer address are required",
            ));
        }
        let mut st = self.lock();
        if st.stopping {
            return Err(Status::unavailable(SHUTTING_DOWN));
        }
        if st.workers.values().any(|w| w.id == r.worker_id) {
            return Err(Status::already_exists(format!(
                "a worker called {} is already attached",
                r.worker_id
            )));
        }
        // Another worker's address would take its rays: refused like a duplicate id (a worker
        // that restarted on the same address gets in once its old entry is reaped).
        if st
            .workers
            .values()
            .any(|w| w.peer_address == r.peer_address)
        {
            return Err(Status::already_exists(format!(
                "a worker at peer address {} is already attached",
                r.peer_address
            )));
        }
        let key = st.next_key;
        st.next_key += 1;
        let registered = Body::Registered(proto::Registered {
            heartbeat_ms: self.config.heartbeat.as_millis() as u32,
        });
        let _ = tx.send(Ok(proto::CoordinatorMessage {
            body: Some(registered),
        }));
        st.workers.insert(
            key,
            WorkerEntry {
                id: r.worker_id.clone(),
                peer_address: r.peer_address.clone(),
                cache_bytes: r.cache_bytes,
                tx,
                last_seen: Instant::now(),
                last_report: None,
                left_out: String::new(),
            },
        );
        info!(worker = %r.worker_id, key, peer = %r.peer_address, cache_bytes = r.cache_bytes, threads = r.threads, "worker attached");
        let member = Member::new(r.peer_address.clone(), r.cache_bytes);
        if let Some(frame) = st.running.as_mut() {
            if frame.sidelined.contains(&r.worker_id) {
                info!(job = %frame.job_id, worker = %r.worker_id, "worker sits out the running frame: a peer could not reach it");
                return Ok(key);
            }
            let out = frame.join(key, member);
            info!(job = %frame.job_id, round = frame.round, "worker joins the running frame");
            send(&st, out);
        } else {
            self.try_start(&mut st);
        }
        Ok(key)
    }

    /// Handles one message of a registered worker.
    pub fn worker_message(self: &Arc<Self>, key: u32, body: FromWorker) {
        let mut st = self.lock();
        let Some(worker) = st.workers.get_mut(&key) else {
            // Its stream outlived its membership (a healed partition delivers what it sent
            // meanwhile): whatever it says is stale.
            if !matches!(body, FromWorker::Heartbeat(_)) {
                info!(
                    key,
                    "message from a worker no longer attached: refused as stale"
                );
            }
            return;
        };
        worker.last_seen = Instant::now();
        match body {
            FromWorker::Register(_) => warn!(key, "worker registered twice; ignored"),
            FromWorker::Heartbeat(_) => {}
            FromWorker::QueueReport(r) => {
                worker.last_report = Some(r.clone());
                let out = match st.running.as_mut() {
                    Some(f) if f.job_id == r.job_id => f.report(key, r),
                    _ => Vec::new(),
                };
                send(&st, out);
                if let Some(f) = st.running.as_ref() {
                    publish_progress(&st, f);
                }
            }
            FromWorker::TileResults(r) => {
                if let Some(why) = self.tile_results(&mut st, key, r) {
                    // Its stream is closed and its tiles re-dealt to the others; it sits out
                    // the frame, so re-registering does not bring it back into this one.
                    if let Some(w) = st.workers.get(&key) {
                        let _ = w.tx.send(Err(Status::permission_denied(why.clone())));
                    }
                    drop(st);
                    self.worker_gone(key, &why);
                }
            }
            FromWorker::FrameReport(r) => self.frame_report(&mut st, key, r),
            FromWorker::PeerUnresponsive(p) => {
                let reporter = worker.id.clone();
                let silent = st
                    .workers
                    .iter()
                    .find(|(_, w)| w.peer_address == p.peer_address)
                    .map(|(&k, _)| k);
                // Judged after a grace period, with the other side's reports (`accusations`).
                match (silent, st.running.as_mut()) {
                    (Some(k), Some(frame))
                        if frame.members().any(|m| m == k) && frame.members().any(|m| m == key) =>
                    {
                        warn!(worker = %reporter, peer = %p.peer_address, reason = %rayfarm_node::bounds::shown(&p.reason), "a worker reports a peer unreachable");
                        frame.accusations.add(key, k, Instant::now(), &p.reason);
                    }
                    _ => {
                        info!(worker = %reporter, peer = %rayfarm_node::bounds::shown(&p.peer_address), "unresponsive peer is no member of a running frame: ignored")
                    }
                }
            }
        }
    }

    /// Commits a worker's tile results. Returns why the worker must be dropped if they
    /// cannot be right (a forged or broken worker): nothing of them is counted, and the
    /// frame goes on without it, so its image is still the one `render --local` makes.
    fn tile_results(
        self: &Arc<Self>,
        st: &mut State,
        key: u32,
        r: proto::TileResults,
    ) -> Option<String> {
        let frame = st.running.as_mut().filter(|f| f.job_id == r.job_id)?;
        let (committed, refused) = frame.results(key, r);
        if let Err(e) = write_tiles(frame, &committed) {
            let msg = format!("{e:#}");
            self.fail_running(st, &msg);
            return None;
        }
        if let Some(e) = refused {
            let worker = st
                .workers
                .get(&key)
                .map(|w| w.id.clone())
                .unwrap_or_default();
            error!(worker = %worker, error = %e, "worker sent impossible tile results: dropped, its tiles re-dealt");
            if let Some(frame) = st.running.as_mut() {
                frame.sidelined.insert(worker);
            }
            return Some(format!("impossible tile results: {e}"));
        }
        if frame.ledger.is_complete() {
            self.complete(st);
        } else if let Some(f) = st.running.as_ref() {
            publish_progress(st, f);
        }
        None
    }

    fn frame_report(self: &Arc<Self>, st: &mut State, key: u32, r: proto::FrameReport) {
        if !r.error.is_empty() {
            if st.running.as_ref().is_none_or(|f| f.job_id != r.job_id) {
                return;
            }
            if r.declined {
                return self.declined(st, key, &r.job_id, &r.error);
            }
            self.fail_running(st, &r.error);
            return;
        }
        if let Some(w) = st.workers.get_mut(&key) {
            w.left_out.clear();
        }
        let Some(fin) = st.finishing.get_mut(&r.job_id) else {
            return;
        };
        match serde_json::from_str::<WorkerFrameStats>(&r.stats_json) {
            Ok(stats) => fin.reports.push(stats),
            Err(e) => warn!(key, error = %e, "unreadable worker statistics"),
        }
        fin.waiting.remove(&key);
        if fin.waiting.is_empty()
            && let Some(done) = fin.done.take()
        {
            let _ = done.send(());
        }
    }

    /// A worker cannot take part in the running frame (`reason` names it and why): it is left
    /// out of this frame as if lost, but stays registered for the next jobs. The job fails
    /// only when no member is left, with every member's reason.
    fn declined(self: &Arc<Self>, st: &mut State, key: u32, job_id: &str, reason: &str) {
        warn!(job = %job_id, reason, "worker left out of the frame");
        if let Some(w) = st.workers.get_mut(&key) {
            w.left_out = format!("job {job_id}: {reason}");
        }
        let Some(frame) = st.running.as_mut() else {
            return;
        };
        frame.declined.push(reason.to_string());
        let Some(out) = frame.lose(key) else {
            return;
        };
        if out.is_empty() {
            let msg = format!(
                "no worker can take part in the frame: {}",
                frame.declined.join("; ")
            );
            self.fail_running(st, &msg);
            return;
        }
        send(st, out);
    }

    /// Forgets a worker whose stream ended or who stopped sending heartbeats.
    pub fn worker_gone(self: &Arc<Self>, key: u32, why: &str) {
        let mut st = self.lock();
        let Some(worker) = st.workers.remove(&key) else {
            return;
        };
        warn!(worker = %worker.id, why, "worker lost");
        for fin in st.finishing.values_mut() {
            fin.waiting.remove(&key);
            if fin.waiting.is_empty()
                && let Some(done) = fin.done.take()
            {
                let _ = done.send(());
            }
        }
        let Some(out) = st.running.as_mut().and_then(|f| f.lose(key)) else {
            return;
        };
        let max = self.config.max_attempts;
        let job_id = st
            .running
            .as_ref()
            .map(|f| f.job_id.clone())
            .unwrap_or_default();
        let losses = st.jobs.get_mut(&job_id).map_or(0, |j| {
            let n = j.workers_lost.entry(worker.id.clone()).or_insert(0);
            *n += 1;
            *n
        });
        if losses >= max {
            // The same worker lost again and again on one job: the job is the likelier
            // culprit. It fails; the workers stay.
            let reason = format!(
                "worker {} was lost {losses} times during this job's frames (last: {why}); \
                 --max-attempts is {max}",
                worker.id
            );
            self.fail_running(&mut st, &reason);
            return;
        }
        if out.is_empty() {
            // No worker left: the job goes back to the front of its priority class and
            // starts over when workers come back.
            if let Some(frame) = st.running.take() {
                warn!(job = %frame.job_id, "every worker of the frame is gone: job re-queued");
                let grid = frame.ledger.grid().count();
                let used = (0..grid).filter_map(|t| frame.ledger.epoch(t)).max();
                if let Some(job) = st.jobs.get_mut(&frame.job_id) {
                    job.epoch_floor = used.unwrap_or(0).saturating_add(1);
                }
                let seq = st.jobs.get(&frame.job_id).map_or(0, |j| j.seq);
                st.queue
                    .push(frame.job_id.clone(), frame.spec.priority, seq);
                set_state(&mut st, &frame.job_id, JobState::Queued, "");
            }
            // Workers sitting out the frame are still here: they start it over.
            self.try_start(&mut st);
            return;
        }
        info!(worker = %worker.id, "re-issuing the unfinished tiles on the remaining workers");
        send(&st, out);
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
        st.store.close();
    }

    /// Drops workers that have been silent longer than the timeout.
    pub fn reap_silent_workers(self: &Arc<Self>) {
        let silent: Vec<u32> = {
            let st = self.lock();
            st.workers
                .iter()
                .filter(|(_, w)| w.last_seen.elapsed() > self.config.worker_timeout)
                .map(|(&k, _)| k)
                .collect()
        };
        for key in silent {
            if let Some(tx) = self.lock().workers.get(&key).map(|w| w.tx.clone()) {
                let _ = tx.send(Err(Status::deadline_exceeded("no heartbeat")));
            }
            self.worker_gone(key, "no heartbeat");
        }
        while let Some((key, why)) = self.judge_accusations() {
            // Dropping it closes its control stream: if it is only slow or cut off, it comes
            // back through a fresh registration and joins the next frame.
            self.worker_gone(key, &why);
        }
    }

    /// The member to drop for its peers' reports, if their grace period is over (see
    /// [`crate::accusations`]); it sits out the rest of the frame.
    fn judge_accusations(&self) -> Option<(u32, String)> {
        let grace = (self.config.heartbeat * 2).max(ACCUSATION_GRACE);
        let mut st = self.lock();
        let members: BTreeSet<u32> = st.running.as_ref()?.members().collect();
        // Members the coordinator hears from itself: one peer's word alone does not drop them.
        let heard = members
            .iter()
            .copied()
            .filter(|k| {
                st.workers
                    .get(k)
                    .is_some_and(|w| w.last_seen.elapsed() < grace)
            })
            .collect();
        let frame = st.running.as_mut()?;
        let v = frame
            .accusations
            .judge_heard(Instant::now(), grace, &members, &heard)?;
        let id_of = |k| st.workers.get(&k).map(|w| w.id.clone()).unwrap_or_default();
        let (dropped, accused, accuser) = (id_of(v.drop), id_of(v.accused), id_of(v.accuser));
        if let Some(frame) = st.running.as_mut() {
            frame.sidelined.insert(dropped);
        }
        let why = format!(
            "broken links to {} peers; first report: {accused} unresponsive to worker \
             {accuser}: {}",
            v.links, v.reason
        );
        Some((v.drop, why))
    }

    // ----- frames -----

    /// Starts the next queued job if the cluster is free and has workers.
    fn try_start(self: &Arc<Self>, st: &mut State) {
        while !st.stopping && st.running.is_none() && !st.workers.is_empty() {
            let Some(id) = st.queue.pop() else {
                return;
            };
            let Some(spec) = st.jobs.get(&id).and_then(|j| j.summary.spec.clone()) else {
                continue;
            };
            let _span = info_span!("start_job", job = %id).entered();
            let attempts = st.jobs.get(&id).map_or(0, |j| j.attempts);
            if attempts >= self.config.max_attempts {
                // A job that kills the coordinator (or loses every worker) each time it runs
                // would otherwise be a crash loop; the queue moves on.
                let reason = format!(
                    "its frame started {attempts} times without finishing (the coordinator \
                     stopped or every worker was lost each time); --max-attempts is {}",
                    self.config.max_attempts
                );
                set_state(st, &id, JobState::Failed, &reason);
                continue;
            }
            match self.prepare_frame(&id, spec) {
                Ok(mut frame) => {
                    // A job started before (by a coordinator since restarted, or before its
                    // workers were all lost) starts every tile at a new epoch, so rays and
                    // results of the abandoned run still in flight are dropped as stale.
                    let tiles: Vec<u32> = (0..frame.ledger.grid().count()).collect();
                    let floor = st.jobs.get(&id).map_or(0, |j| j.epoch_floor);
                    for _ in 0..attempts.max(floor) {
                        frame.ledger.bump(&tiles);
                    }
                    let members: Vec<(u32, Member)> = st
                        .workers
                        .iter()
                        .map(|(&k, w)| (k, Member::new(w.peer_address.clone(), w.cache_bytes)))
                        .collect();
                    let out = frame.start(members);
                    info!(
                        workers = out.len(),
                        tiles = frame.ledger.grid().count(),
                        attempt = attempts + 1,
                        "frame started"
                    );
                    if let Some(job) = st.jobs.get_mut(&id) {
                        job.summary.started_unix_ms = unix_ms();
                        job.attempts = attempts.saturating_add(1);
                    }
                    // The start is on disk before any worker hears of it: a frame that kills
                    // the coordinator counts against the job's attempts all the same.
                    set_state(st, &id, JobState::Running, "");
                    send(st, out);
                    publish_progress(st, &frame);
                    st.running = Some(frame);
                }
                Err(status) => {
                    error!(error = %status.message(), "job cannot start");
                    set_state(st, &id, JobState::Failed, status.message());
                }
            }
        }
    }

    fn prepare_frame(&self, id: &str, spec: proto::JobSpec) -> Result<RunningFrame, Status> {
        // The scene was checked at submission; check again, it may have changed since.
        let (_, manifest) = self.open_scene(&spec.scene)?;
        let frame = frame_spec(&spec, &manifest.camera).map_err(Status::invalid_argument)?;
        let domain_bytes = manifest.domains.iter().map(|d| d.bytes).collect();
        let spp = frame.spp;
        let mut frame = RunningFrame::new(
            id.to_string(),
            spec,
            frame,
            domain_bytes,
            self.config.schedule_options,
            self.config.rounds,
        )
        .map_err(Status::invalid_argument)?;
        let grid = *frame.ledger.grid();
        let film = results::create_film(&self.config.data_dir, id, grid, spp)
            .map_err(|e| Status::internal(format!("{e:#}")))?;
        frame.film = Some(film);
        Ok(frame)
    }

    fn fail_running(self: &Arc<Self>, st: &mut State, error: &str) {
        if let Some(frame) = st.running.take() {
            end_frame(st, &frame);
            set_state(st, &frame.job_id, JobState::Failed, error);
        }
        self.try_start(st);
    }

    /// The running frame has all its credit back: end it on the workers, collect their
    /// statistics, write the results, and move on to the next job at once.
    fn complete(self: &Arc<Self>, st: &mut State) {
        let Some(frame) = st.running.take() else {
            return;
        };
        let wall = frame.started.elapsed().as_secs_f64();
        info!(job = %frame.job_id, wall, rounds = frame.round, "frame complete");
        end_frame(st, &frame);
        let (done_tx, done_rx) = oneshot::channel();
        st.finishing.insert(
            frame.job_id.clone(),
            Finishing {
                waiting: frame.members().collect(),
                reports: Vec::new(),
                done: Some(done_tx),
            },
        );
        let this = self.clone();
        tokio::spawn(async move {
            let _ = tokio::time::timeout(this.config.report_timeout, done_rx).await;
            this.finish(frame, wall).await;
        });
        self.try_start(st);
    }

    async fn finish(self: Arc<Self>, frame: RunningFrame, wall: f64) {
        let id = frame.job_id.clone();
        let reports = {
            let mut st = self.lock();
            st.finishing
                .remove(&id)
                .map(|f| f.reports)
                .unwrap_or_default()
        };
        let spec = &frame.frame;
        let mut stats = ClusterStats {
            job_id: id.clone(),
            scene: frame.spec.scene.clone(),
            schedule: schedule_name(frame.schedule).into(),
            width: spec.width,
            height: spec.height,
            spp: spec.spp,
            max_depth: spec.max_depth,
            domains: frame.domain_count(),
            wall_seconds: wall,
            rounds: frame.round,
            left_out: frame.declined.clone(),
            ..Default::default()
        };
        stats.absorb(reports);
        let data_dir = self.config.data_dir.clone();
        let job = id.clone();
        let film = frame.film;
        let written = tokio::task::spawn_blocking(move || {
            let film = film.ok_or_else(|| anyhow::anyhow!("the frame has no film"))?;
            // The film file goes with `film` once both images are written.
            results::write(&data_dir, &job, &film, &mut stats)
        })
        .await;
        let mut st = self.lock();
        match written {
            Ok(Ok((json, hash))) => {
                if let Some(job) = st.jobs.get_mut(&id) {
                    job.stats_json = json;
                    job.image_hash = hash.clone();
                }
                info!(job = %id, %hash, "results written");
                set_state(&mut st, &id, JobState::Succeeded, "");
            }
            Ok(Err(e)) => set_state(&mut st, &id, JobState::Failed, &format!("{e:#}")),
            Err(e) => set_state(&mut st, &id, JobState::Failed, &format!("{e}")),
        }
    }
}

/// Writes committed tiles to the running frame's film.
fn write_tiles(frame: &RunningFrame, committed: &[CommittedTile]) -> anyhow::Result<()> {
    let Some(film) = frame.film.as_ref() else {
        return Ok(());
    };
    for (tile, sums) in committed {
        film.write_tile(*tile, sums)?;
    }
    Ok(())
}

fn not_found(id: &str) -> Status {
    Status::not_found(format!("no job {id}"))
}

fn send(st: &State, out: Vec<Outgoing>) {
    for (key, msg) in out {
        if let Some(w) = st.workers.get(&key) {
            // A closed channel means the worker is going; worker_gone will handle it.
            let _ = w.tx.send(Ok(msg));
        }
    }
}

fn end_frame(st: &State, frame: &RunningFrame) {
    let out = frame
        .members()
        .map(|k| {
            let body = Body::EndFrame(proto::EndFrame {
                job_id: frame.job_id.clone(),
            });
            (k, proto::CoordinatorMessage { body: Some(body) })
        })
        .collect();
    send(st, out);
}

/// Pixels times samples per pixel of a spec as given (a field left 0 counts as 1).
fn spec_cost(spec: &proto::JobSpec) -> u64 {
    [spec.width, spec.height, spec.spp]
        .iter()
        .map(|&v| u64::from(v.max(1)))
        .product()
}

fn set_state(st: &mut State, id: &str, state: JobState, error: &str) {
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
    // Written through under the lock, so the store sees the changes in the order they
    // happened. Once per state change; a failed write is logged and the job goes on (the
    // change is lost only if the coordinator restarts before the next write of this job).
    if let Err(e) = st.store.put(&job.stored()) {
        error!(job = %id, error = %e.with_causes(), "job state not saved");
    }
    job.progress.send_modify(|p| {
        p.state = state as i32;
        p.error = error.to_string();
        p.stats_json = stats_json;
        if state == JobState::Succeeded {
            p.tiles_done = p.tiles_total;
            p.eta_seconds = 0.0;
        }
    });
}

fn publish_progress(st: &State, frame: &RunningFrame) {
    let Some(job) = st.jobs.get(&frame.job_id) else {
        return;
    };
    let (done, total, rate, eta) = frame.progress();
    job.progress.send_modify(|p| {
        p.tiles_done = done;
        p.tiles_total = total;
        p.round = frame.round;
        p.rays_per_second = rate;
        p.eta_seconds = eta;
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
        if let Err(e) = st.store.put(&job.stored()) {
            error!(job = %id, error = %e.with_causes(), "job state not saved");
        }
    }
    st.add_job(id, job);
}

#[cfg(test)]
mod tests {
    use rayfarm_core::prepare::generate::{NbodyOptions, prepare_nbody};

    use super::*;

    fn config(root: &std::path::Path) -> Config {
        Config {
            data_dir: root.join("data"),
            scene_root: root.join("scenes"),
            allow_absolute_scenes: false,
            max_jobs_per_user: 64,
            max_pixel_samples_per_user: 1 << 40,
            default_scene: None,
            heartbeat: Duration::from_secs(1),
            worker_timeout: Duration::from_secs(10),
            report_timeout: Duration::from_secs(1),
            schedule_options: Options::default(),
            rounds: Rounds::default(),
            max_frame_bytes: 16 << 30,
            max_attempts: 3,
        }
    }

    /// Attaches a worker (its control stream is the channel) and returns the epochs of every
    /// tile in the StartFrame it is sent, tile by tile.
    fn start_epochs(c: &Arc<Coordinator>) -> BTreeMap<u32, u32> {
        start_epochs_of(c, "w").1
    }

    /// Registers a worker called `id` whose control stream is a channel: its key and the
    /// channel's receiving end.
    fn attach(
        c: &Arc<Coordinator>,
        id: &str,
    ) -> (
        u32,
        mpsc::UnboundedReceiver<Result<proto::CoordinatorMessage, Status>>,
    ) {
        let (tx, rx) = mpsc::unbounded_channel();
        let register = proto::Register {
            protocol_version: PROTOCOL_VERSION,
            worker_id: id.into(),
            peer_address: format!("{id}:1"),
            cache_bytes: 1 << 30,
            threads: 1,
        };
        (c.register(&register, tx).expect("registered"), rx)
    }

    /// [`start_epochs`] of a worker called `id`; also returns its key.
    fn start_epochs_of(c: &Arc<Coordinator>, id: &str) -> (u32, BTreeMap<u32, u32>) {
        let (key, mut rx) = attach(c, id);
        while let Ok(msg) = rx.try_recv() {
            if let Some(Body::StartFrame(s)) = msg.expect("no error").body {
                // Its channel stays open while the test runs, as a live worker's would.
                std::mem::forget(rx);
                return (key, s.epochs.into_iter().collect());
            }
        }
        panic!("no StartFrame sent");
    }

    #[test]
    fn a_worker_lost_three_times_on_one_job_fails_the_job_and_stays() {
        let root = tempfile::tempdir().unwrap();
        let spec = small_job(root.path());
        let c = Coordinator::open(config(root.path())).unwrap();
        let _stays = attach(&c, "stays");
        let id = c.submit(Some(spec)).unwrap();
        for lost in 1..=3 {
            assert_eq!(
                c.list(JobPage::newest(100)).0[0].state(),
                JobState::Running,
                "loss {lost}"
            );
            let (key, _rx) = attach(&c, "flaky");
            c.worker_gone(key, "stream closed");
        }
        let job = c
            .list(JobPage::newest(100))
            .0
            .into_iter()
            .find(|j| j.job_id == id)
            .unwrap();
        assert_eq!(job.state(), JobState::Failed);
        assert!(
            job.error.contains("worker flaky was lost 3 times")
                && job.error.contains("--max-attempts is 3"),
            "{}",
            job.error
        );
        assert_eq!(c.status().workers.len(), 1, "the other worker stays");
    }

    /// A scene `nb` under `root` and a small job of it.
    fn small_job(root: &std::path::Path) -> proto::JobSpec {
        let options = NbodyOptions {
            name: "nb".into(),
            triangles: 2000,
            seed: 1,
            domains: 2,
            max_memory: None,
            force: false,
        };
        prepare_nbody(&root.join("scenes").join("nb"), &options).unwrap();
        std::fs::create_dir_all(root.join("data")).unwrap();
        proto::JobSpec {
            scene: "nb".into(),
            width: 64,
            height: 32,
            spp: 1,
            max_depth: 1,
            ..Default::default()
        }
    }

    #[test]
    fn a_job_whose_workers_were_all_lost_restarts_above_every_epoch_it_used() {
        let root = tempfile::tempdir().unwrap();
        let spec = small_job(root.path());
        let c = Coordinator::open(config(root.path())).unwrap();
        c.submit(Some(spec)).unwrap();
        let (a, first) = start_epochs_of(&c, "a");
        assert!(first.is_empty(), "a first frame starts at epoch 0");
        let (b, _) = start_epochs_of(&c, "b");
        // Losing a bumps every tile to epoch 1; losing b too re-queues the job.
        c.worker_gone(a, "test");
        c.worker_gone(b, "test");
        assert_eq!(c.list(JobPage::newest(100)).0[0].state(), JobState::Queued);
        // Worker b, dropped but still running, may send epoch-1 rays: the new frame is above.
        let (_, again) = start_epochs_of(&c, "c");
        assert!(
            !again.is_empty() && again.values().all(|&e| e >= 2),
            "{again:?}"
        );
    }

    #[test]
    fn a_job_restarted_after_a_coordinator_restart_starts_its_tiles_at_a_new_epoch() {
        let root = tempfile::tempdir().unwrap();
        let spec = small_job(root.path());
        let c = Coordinator::open(config(root.path())).unwrap();
        let id = c.submit(Some(spec.clone())).unwrap();
        assert!(
            start_epochs(&c).is_empty(),
            "a first frame starts at epoch 0"
        );
        assert_eq!(c.list(JobPage::newest(100)).0[0].state(), JobState::Running);
        drop(c);
        for epoch in 1..=2 {
            // As after a crash: the running job is queued again, and its next frame's tiles
            // are all at an epoch the dead run never used.
            let c = Coordinator::open(config(root.path())).unwrap();
            let jobs = c.list(JobPage::newest(100)).0;
            assert_eq!((jobs.len(), jobs[0].state()), (1, JobState::Queued));
            let epochs = start_epochs(&c);
            let tiles = epochs.len();
            assert!(tiles >= 2, "{epochs:?}");
            assert!(epochs.values().all(|&e| e == epoch), "{epochs:?}");
            assert_eq!(c.list(JobPage::newest(100)).0[0].job_id, id);
        }
        // Sequence numbers go on where they stopped.
        let c = Coordinator::open(config(root.path())).unwrap();
        let next = c.submit(Some(spec)).unwrap();
        assert!(next.ends_with("-2"), "{next}");
    }

    #[test]
    fn the_job_list_comes_in_pages_that_new_jobs_do_not_shift() {
        let root = tempfile::tempdir().unwrap();
        let spec = small_job(root.path());
        let c = Coordinator::open(config(root.path())).unwrap();
        let ids: Vec<String> = (0..5)
            .map(|_| c.submit(Some(spec.clone())).unwrap())
            .collect();
        let names = |jobs: &[proto::JobSummary]| -> Vec<String> {
            jobs.iter().map(|j| j.job_id.clone()).collect()
        };
        let (first, next) = c.list(JobPage::newest(2));
        assert_eq!(names(&first), [ids[4].clone(), ids[3].clone()]);
        // A job submitted between two pages is newer than both: the next page goes on.
        let newest = c.submit(Some(spec)).unwrap();
        let (second, next) = c.list(JobPage {
            size: 2,
            from_seq: next.expect("more pages"),
        });
        assert_eq!(names(&second), [ids[2].clone(), ids[1].clone()]);
        let (last, next) = c.list(JobPage {
            size: 2,
            from_seq: next.expect("more pages"),
        });
        assert_eq!((names(&last), next), (vec![ids[0].clone()], None));
        assert_eq!(c.list(JobPage::newest(1)).0[0].job_id, newest);
        // The order survives a restart.
        drop(c);
        let c = Coordinator::open(config(root.path())).unwrap();
        let all = c.list(JobPage::newest(10)).0;
        assert_eq!(all.len(), 6);
        assert_eq!(all[5].job_id, ids[0]);
    }
}
