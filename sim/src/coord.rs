//! The simulated coordinator process: the real coordinator machine
//! (`rayfarm_machine::coordinator::Coordinator`, the one the `rayfarm-coordinator` shell
//! drives) with what a shell keeps around it: which node each worker key is, the films of
//! its frames, and the job store, a disk whose writes complete in order after a latency. The
//! process can crash (the machine, its films and the writes not yet on disk are gone, every
//! worker's stream ends) and restart from the records on disk, as the real one does. It
//! records what the invariants need: every tile committed, by frame, and when.
//!
//! The jobs of a run are submitted one after another, each once the one before has its
//! results written, as a user's script does: the workers render them with the caches and
//! machines the frames before left them.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::sync::Arc;
use std::time::Duration;

use rayfarm_core::render::Film;
use rayfarm_core::render::local::FrameSpec;
use rayfarm_core::schedule::dynamic::Options;
use rayfarm_core::tile::{TILE_SIZE, TileGrid};
use rayfarm_machine::Time;
use rayfarm_machine::coordinator::Coordinator;
use rayfarm_machine::coordinator::Rounds;
use rayfarm_machine::coordinator::cluster::{
    Action, Config, FlushWork, Input, JobRecord, OpenedFrame, PlanningWork, Tally,
};
use rayfarm_machine::coordinator::synthetic::planned;
use rayfarm_node::cpu::{thread_clock_overhead_ns, thread_cpu_ns};
use rayfarm_proto::{self as proto, JobState, worker_message::Body as FromWorker};
use tracing::info;

use crate::cost::CostModel;
use crate::net::NodeId;

/// What the coordinator does to a worker's node.
pub enum ToNode {
    /// A message on its control stream `conn`: shared with the other members told the same
    /// (a holders flush makes one message per view class); each member's copy still costs
    /// the coordinator's NIC its bytes (`World::transmit`).
    Send(NodeId, u64, Arc<proto::CoordinatorMessage>),
    /// Its control stream `conn` is closed (it was dropped, refused, or the coordinator died).
    Close(NodeId, u64),
}

/// How the simulated coordinator is set up.
pub struct CoordConfig {
    /// The jobs submitted, in order (never empty).
    pub specs: Vec<proto::JobSpec>,
    pub frame: FrameSpec,
    pub domain_bytes: Vec<u64>,
    /// The first job is submitted once this many workers registered.
    pub workers: usize,
    pub heartbeat: Duration,
    pub worker_timeout: Duration,
    /// Busy workers are told new holders at most once per this interval.
    pub holders_interval: Duration,
    /// How long a planned worker with nothing to trace waits for its plan's rays before it
    /// reports again (the coordinator's `--report-hold-ms` and `--report-hold-per-worker-us`).
    pub report_hold: crate::ReportHold,
    /// The coordinator's `--copy-rays` (`Options::copy_rays`).
    pub copy_rays: u64,
    /// How long one record takes to reach the disk.
    pub disk_latency: Duration,
    /// What its planning rounds and holders flushes cost.
    pub cost: CostModel,
    /// Keep every call the coordinator machine is handed, so that [`SimCoordinator::replay`]
    /// can hand them to a new machine alone after the run.
    pub replay: bool,
}

/// How long a finished frame waits for its workers' statistics (the coordinator's).
const REPORT_TIMEOUT: Duration = Duration::from_secs(5);

/// The job store: records on disk, and writes on their way there (lost in a crash).
#[derive(Default)]
struct Disk {
    stored: BTreeMap<String, JobRecord>,
    /// (when it is on disk, the record, the start it answers).
    pending: VecDeque<(Time, JobRecord, Option<u64>)>,
}

/// A process of the coordinator, from its start to its crash.
struct Process {
    machine: Coordinator,
    /// Worker keys of this process: the node, and the stream it registered on.
    nodes: BTreeMap<u32, (NodeId, u64)>,
    /// `nodes` the other way round: every message a worker sends looks its key up, and a
    /// walk of `nodes` for it was a fifth of a 1,024-worker run's time.
    keys: HashMap<(NodeId, u64), u32>,
    films: BTreeMap<String, Film>,
}

/// See the module documentation.
pub struct SimCoordinator {
    config: CoordConfig,
    process: Option<Process>,
    /// Starts of the process so far: a worker's stream belongs to one.
    pub incarnation: u64,
    disk: Disk,
    film_dir: tempfile::TempDir,
    /// Registrations tried so far (refused ones and ones that found the coordinator dead
    /// included): the first job is submitted at the `workers`-th, or when the coordinator is
    /// back.
    registrations: usize,
    /// The jobs submitted so far, in order.
    pub job_ids: Vec<String>,
    /// Frames started so far (a restarted or re-queued job starts another).
    pub frames: u64,
    /// Every tile committed, in order: (frame, tile, when). A tile twice in one frame is a
    /// violation.
    pub commits: Vec<(u64, u32, Time)>,
    /// When the latest frame was complete.
    pub completed_at: Option<Time>,
    /// By job: the image of its frame whose results were written last (a job restored after
    /// a crash may write them again).
    pub images: BTreeMap<String, Result<String, String>>,
    /// Why the job failed, if it did.
    pub failed: Option<String>,
    /// What went wrong that no healthy run does (a worker's error, impossible results).
    pub problems: Vec<String>,
    /// Rounds planned over every frame.
    pub rounds: u64,
    /// Virtual time spent planning rounds and flushing holders, over every process.
    pub busy: Duration,
    /// What the rounds and the holders flushes of `busy` were, summed over every process.
    pub planning: PlanningWork,
    pub flushing: FlushWork,
    /// When the process is done planning what it was given so far: what it sends leaves
    /// then.
    pub free_at: Time,
    /// Thread CPU the coordinator machine took on this machine for the inputs it was given,
    /// by kind (`InputKind`), measured while the busy log is on (`log_busy`): what the real
    /// code cost here beside what the cost model charged.
    machine_ns: Option<[u64; InputKind::COUNT]>,
    /// The clock's own cost in each timed call (`thread_clock_overhead_ns`), taken out of
    /// `machine_ns` as the replay takes it out of its figures; 0 while `machine_ns` is off.
    clock_ns: u64,
    /// Every call the machine was handed, with its time, while `CoordConfig::replay` is set
    /// and the process has not crashed (a replay of a crashed run would need its restarts).
    calls: Option<Vec<(Time, Call)>>,
}

/// One call the simulated shell made to the coordinator machine.
#[derive(Clone)]
enum Call {
    Handle(Input),
    Register(proto::Register),
    Submit(proto::JobSpec, u64),
}

/// A run's coordinator machine handed every one of its calls again, in order and at the same
/// virtual times, as a new machine alone in this process (`SimCoordinator::replay`): the
/// thread CPU of each call by kind is what a process that only coordinates spends on the
/// frame, without the simulated workers sharing the caches, as the in-run measure does
/// (`log_busy`). Handling only: a real shell also encodes and sends what the machine returns.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Replayed {
    /// Calls handed again.
    pub calls: u64,
    /// Thread CPU of the queue reports (taking each in, the rounds they plan and the holders
    /// flushes due with them).
    pub reports: Duration,
    pub tile_results: Duration,
    pub heartbeats: Duration,
    pub ticks: Duration,
    /// Registrations, the submission and every other input.
    pub other: Duration,
    /// The clock's own cost in each call's time (`thread_clock_overhead_ns`), taken out of
    /// every figure above: `calls` times this is what timing the replay cost besides.
    pub clock: Duration,
    /// What the replayed rounds planned.
    pub planning: PlanningWork,
    /// Whether that is what the run's rounds planned (the machine repeated itself).
    pub repeated: bool,
}

impl Replayed {
    /// Thread CPU of every call.
    pub fn total(&self) -> Duration {
        self.reports + self.tile_results + self.heartbeats + self.ticks + self.other
    }
}

/// What the coordinator machine was handed, as its CPU is told apart (`log_busy`): a queue
/// report takes the report in and plans the round it asks for (and a holders flush, if due).
#[derive(Clone, Copy)]
enum InputKind {
    Report,
    TileResults,
    Heartbeat,
    Tick,
    Other,
}

impl InputKind {
    const COUNT: usize = 5;

    fn of(input: &Input) -> InputKind {
        match input {
            Input::WorkerMessage { body, .. } => match body {
                FromWorker::QueueReport(_) => InputKind::Report,
                FromWorker::TileResults(_) => InputKind::TileResults,
                FromWorker::Heartbeat(_) => InputKind::Heartbeat,
                _ => InputKind::Other,
            },
            Input::Tick => InputKind::Tick,
            _ => InputKind::Other,
        }
    }
}

impl SimCoordinator {
    pub fn new(config: CoordConfig) -> Result<Self, String> {
        let film_dir = tempfile::tempdir().map_err(|e| format!("temporary film directory: {e}"))?;
        // The machine's CPU is measured while the busy log is on (`log_busy`).
        let timed = tracing::enabled!(tracing::Level::INFO);
        let mut c = SimCoordinator {
            config,
            process: None,
            incarnation: 0,
            disk: Disk::default(),
            film_dir,
            registrations: 0,
            job_ids: Vec::new(),
            frames: 0,
            commits: Vec::new(),
            completed_at: None,
            images: BTreeMap::new(),
            failed: None,
            problems: Vec::new(),
            rounds: 0,
            busy: Duration::ZERO,
            planning: PlanningWork::default(),
            flushing: FlushWork::default(),
            free_at: Time(0),
            machine_ns: timed.then_some([0; InputKind::COUNT]),
            clock_ns: timed.then(thread_clock_overhead_ns).unwrap_or(0),
            calls: None,
        };
        c.calls = c.config.replay.then(Vec::new);
        c.start(Time(0));
        Ok(c)
    }

    fn machine_config(&self) -> Config {
        Config {
            heartbeat: self.config.heartbeat,
            worker_timeout: self.config.worker_timeout,
            report_timeout: REPORT_TIMEOUT,
            // The coordinator's defaults (`--replicate free-slots --rounds async`).
            schedule_options: Options {
                replicate_onto_idle: false,
                fill_free_slots: true,
                copy_rays: self.config.copy_rays,
            },
            rounds: Rounds::Async,
            holders_interval: self.config.holders_interval,
            report_hold: self.config.report_hold,
            max_attempts: 3,
            max_jobs_per_user: 16,
            max_pixel_samples_per_user: u64::MAX,
            unix_origin_ms: 0,
        }
    }

    /// A process starts (first or again) with the records on disk.
    fn start(&mut self, now: Time) -> Vec<ToNode> {
        self.incarnation += 1;
        let seq = self.disk.stored.values().map(|r| r.seq).max().unwrap_or(0);
        let mut process = Process {
            machine: Coordinator::new(self.machine_config(), seq),
            nodes: BTreeMap::new(),
            keys: HashMap::new(),
            films: BTreeMap::new(),
        };
        let mut actions = Vec::new();
        for record in self.disk.stored.values() {
            actions.extend(process.machine.restore(now, record.clone(), None));
        }
        self.process = Some(process);
        let mut out = self.carry_out(now, actions);
        out.extend(self.submit_when_due(now));
        out
    }

    /// The process dies: its machine, films and unwritten records go with it; the streams
    /// of its workers end.
    pub fn crash(&mut self) -> Vec<(NodeId, u64)> {
        self.disk.pending.clear();
        self.calls = None;
        // Its planning dies with it.
        self.free_at = Time(0);
        self.process
            .take()
            .map(|p| p.nodes.into_values().collect())
            .unwrap_or_default()
    }

    /// A new process starts from the records on disk.
    pub fn restart(&mut self, now: Time) -> Vec<ToNode> {
        self.start(now)
    }

    pub fn is_up(&self) -> bool {
        self.process.is_some()
    }

    /// Whether the run is over: every job's results written, or one failed.
    pub fn is_done(&self) -> bool {
        self.failed.is_some() || self.all_written()
    }

    /// Whether every job was submitted and has its results written.
    pub fn all_written(&self) -> bool {
        self.job_ids.len() == self.config.specs.len()
            && self.job_ids.iter().all(|id| self.images.contains_key(id))
    }

    /// When the next record reaches the disk.
    pub fn next_write(&self) -> Option<Time> {
        self.disk.pending.front().map(|(t, _, _)| *t)
    }

    /// Records due by `now` reach the disk; the machine hears of the starts among them.
    pub fn disk_done(&mut self, now: Time) -> Vec<ToNode> {
        let mut out = Vec::new();
        while self.disk.pending.front().is_some_and(|(t, _, _)| *t <= now) {
            let Some((_, record, start)) = self.disk.pending.pop_front() else {
                break;
            };
            self.disk.stored.insert(record.id().to_string(), record);
            if let Some(start) = start {
                out.extend(self.feed(now, Input::Stored { barrier: start }));
            }
        }
        out
    }

    fn feed(&mut self, now: Time, input: Input) -> Vec<ToNode> {
        let Some(p) = self.process.as_mut() else {
            return Vec::new();
        };
        if let Some(calls) = self.calls.as_mut() {
            calls.push((now, Call::Handle(input.clone())));
        }
        let start = self
            .machine_ns
            .map(|_| (InputKind::of(&input), thread_cpu_ns()));
        let actions = p.machine.handle(now, input);
        if let (Some(by_kind), Some((kind, start))) = (self.machine_ns.as_mut(), start) {
            by_kind[kind as usize] += thread_cpu_ns().saturating_sub(start + self.clock_ns);
        }
        self.carry_out(now, actions)
    }

    /// A worker on `node` registers on its stream `conn`.
    pub fn register(
        &mut self,
        now: Time,
        node: NodeId,
        conn: u64,
        r: proto::Register,
    ) -> Vec<ToNode> {
        self.registrations += 1;
        let Some(p) = self.process.as_mut() else {
            // Nobody listens: the connection fails.
            return vec![ToNode::Close(node, conn)];
        };
        if let Some(calls) = self.calls.as_mut() {
            calls.push((now, Call::Register(r.clone())));
        }
        let (key, actions) = match p.machine.register(now, &r) {
            Ok(registered) => registered,
            // The shell ends a refused stream at once; the worker tries again later.
            Err(_) => return vec![ToNode::Close(node, conn)],
        };
        if let Some(old) = p.nodes.insert(key, (node, conn)) {
            p.keys.remove(&old);
        }
        p.keys.insert((node, conn), key);
        let mut out = self.carry_out(now, actions);
        out.extend(self.submit_when_due(now));
        out
    }

    /// The first job is submitted once the first workers tried to register (some may have
    /// died since, or found the coordinator dead), as a user submits to a running cluster,
    /// and each next one once the one before has its results written; or once the
    /// coordinator is back if it was down then (the client tries again). A job is on disk
    /// before the reply, as the shell waits for it.
    fn submit_when_due(&mut self, now: Time) -> Vec<ToNode> {
        let next = self.job_ids.len();
        if self.registrations < self.config.workers
            || next == self.config.specs.len()
            || self.job_ids.iter().any(|id| !self.images.contains_key(id))
        {
            return Vec::new();
        }
        let Some(p) = self.process.as_mut() else {
            return Vec::new();
        };
        let cost = u64::from(self.config.frame.width) * u64::from(self.config.frame.height);
        let spec = self.config.specs[next].clone();
        if let Some(calls) = self.calls.as_mut() {
            calls.push((now, Call::Submit(spec.clone(), cost)));
        }
        let Ok(record) = p.machine.submit(now, spec, cost, "") else {
            self.problems.push("the job was refused".into());
            return Vec::new();
        };
        let id = record.id().to_string();
        self.disk.stored.insert(id.clone(), record);
        self.job_ids.push(id.clone());
        self.feed(
            now,
            Input::Recorded {
                job_id: id,
                result: Ok(()),
            },
        )
    }

    /// The key of stream `conn` of `node`, if this process registered it (a stream of a dead
    /// process, or one it closed, is none of its workers).
    fn key_of(&self, node: NodeId, conn: u64) -> Option<u32> {
        let p = self.process.as_ref()?;
        p.keys.get(&(node, conn)).copied()
    }

    /// A message of the worker on `node`, on its stream `conn`.
    pub fn message(&mut self, now: Time, node: NodeId, conn: u64, body: FromWorker) -> Vec<ToNode> {
        let Some(key) = self.key_of(node, conn) else {
            return Vec::new();
        };
        if let FromWorker::FrameReport(r) = &body
            && !r.error.is_empty()
        {
            self.problems.push(r.error.clone());
        }
        self.feed(now, Input::WorkerMessage { key, body })
    }

    /// Stream `conn` of the worker on `node` ended.
    pub fn gone(&mut self, now: Time, node: NodeId, conn: u64) -> Vec<ToNode> {
        match self.key_of(node, conn) {
            Some(key) => self.feed(
                now,
                Input::WorkerGone {
                    key,
                    why: "stream closed".into(),
                },
            ),
            None => Vec::new(),
        }
    }

    /// The coordinator's periodic work.
    pub fn tick(&mut self, now: Time) -> Vec<ToNode> {
        self.feed(now, Input::Tick)
    }

    /// The process works for `took` from `now` (or from when it is done with what it has):
    /// busy that long, and what it sends after leaves when it is done.
    fn occupy(&mut self, now: Time, took: Duration) {
        self.busy += took;
        self.free_at = self.free_at.max(now) + took;
    }

    /// Carries out the machine's actions as the shell does, answering the ones the shell
    /// answers at once (a scene read and results written take no virtual time here).
    fn carry_out(&mut self, now: Time, actions: Vec<Action>) -> Vec<ToNode> {
        let mut todo: VecDeque<Action> = actions.into();
        let mut out = Vec::new();
        let mut written = false;
        while let Some(action) = todo.pop_front() {
            let Some(p) = self.process.as_mut() else {
                break;
            };
            let answer = match action {
                Action::Send((key, m)) => {
                    if let Some(&(node, conn)) = p.nodes.get(&key) {
                        out.push(ToNode::Send(node, conn, m));
                    }
                    None
                }
                Action::Close { key, closing } => {
                    if let Some((node, conn)) = p.nodes.remove(&key) {
                        p.keys.remove(&(node, conn));
                        out.push(ToNode::Close(node, conn));
                    }
                    if let rayfarm_machine::coordinator::cluster::Closing::Refused(why) = closing {
                        self.problems
                            .push(format!("impossible tile results from key {key}: {why}"));
                    }
                    None
                }
                Action::Persist {
                    record,
                    barrier: start,
                } => {
                    if record.state() == JobState::Failed {
                        self.failed = Some(record.summary.error.clone());
                    }
                    let last = self.disk.pending.back().map_or(now, |(t, _, _)| *t);
                    let done = last.max(now) + self.config.disk_latency;
                    self.disk.pending.push_back((done, record, start));
                    None
                }
                Action::Progress { .. } => None,
                Action::PrepareFrame { job_id, .. } => {
                    let opened = self.open(&job_id);
                    let p = self.process.as_mut().expect("up");
                    let opened = opened.map(|film| {
                        p.films.insert(job_id.clone(), film);
                        OpenedFrame {
                            frame: self.config.frame.clone(),
                            domain_bytes: self.config.domain_bytes.clone(),
                        }
                    });
                    Some(Input::FrameOpened { job_id, opened })
                }
                Action::FrameStarted { .. } => {
                    self.frames += 1;
                    None
                }
                Action::WriteTiles {
                    job_id,
                    tiles,
                    samples,
                    ..
                } => {
                    let film = p.films.get(&job_id);
                    let mut failed = None;
                    for (tile, sums) in &tiles {
                        self.commits.push((self.frames, *tile, now));
                        if let Some(Err(e)) = film.map(|f| f.add_tile(*tile, sums, samples)) {
                            failed = Some(e.to_string());
                        }
                    }
                    failed.map(|error| {
                        self.problems.push(format!("film: {error}"));
                        Input::Fail { job_id, error }
                    })
                }
                Action::Discard { job_id } => {
                    p.films.remove(&job_id);
                    None
                }
                Action::WriteResults { job_id, .. } => {
                    let hash = p
                        .films
                        .remove(&job_id)
                        .ok_or_else(|| "the frame's film is gone".to_string())
                        .and_then(|f| f.hash().map_err(|e| e.to_string()))
                        .map(|h| format!("{h:016x}"));
                    let result = hash.clone().map(|h| ("{}".to_string(), h));
                    self.images.insert(job_id.clone(), hash);
                    written = true;
                    Some(Input::ResultsWritten { job_id, result })
                }
                Action::Tally(Tally::FrameCommitted) => {
                    self.completed_at = Some(now);
                    None
                }
                Action::Tally(Tally::Rounds(work)) => {
                    self.rounds += work.rounds;
                    self.planning.add(&work);
                    let took = self
                        .config
                        .cost
                        .planning(&work, self.config.domain_bytes.len());
                    self.occupy(now, took);
                    None
                }
                Action::Tally(Tally::HoldersFlushed(work)) => {
                    self.flushing.add(&work);
                    // The coordinator's time as a round's.
                    let took = self.config.cost.flushing(&work);
                    self.occupy(now, took);
                    None
                }
                Action::Tally(_) => None,
            };
            if let Some(input) = answer
                && let Some(p) = self.process.as_mut()
            {
                if let Some(calls) = self.calls.as_mut() {
                    calls.push((now, Call::Handle(input.clone())));
                }
                todo.extend(p.machine.handle(now, input));
            }
        }
        if written {
            out.extend(self.submit_when_due(now));
        }
        out
    }

    /// A film for job `id`'s next frame.
    fn open(&self, id: &str) -> Result<Film, String> {
        let frame = &self.config.frame;
        let grid = TileGrid::new(frame.width, frame.height, TILE_SIZE)
            .ok_or_else(|| "the image does not fit the tile grid".to_string())?;
        Film::temporary_in(self.film_dir.path(), grid, frame.spp)
            .map_err(|e| format!("job {id}'s film: {e}"))
    }

    /// Hands every call of the run again, in order and at its time, to a new coordinator
    /// machine alone (see [`Replayed`]); `None` unless `CoordConfig::replay` was set, or if
    /// the process crashed.
    pub fn replay(&self) -> Option<Replayed> {
        let calls = self.calls.as_ref()?;
        let mut machine = Coordinator::new(self.machine_config(), 0);
        let mut cpu = [0u64; InputKind::COUNT];
        let mut planning = PlanningWork::default();
        let clock = thread_clock_overhead_ns();
        for (now, call) in calls {
            // The copy handed over is made before the clock starts, as the run's own input was.
            let call = call.clone();
            let kind = match &call {
                Call::Handle(input) => InputKind::of(input),
                _ => InputKind::Other,
            };
            let start = thread_cpu_ns();
            let actions = match call {
                Call::Handle(input) => machine.handle(*now, input),
                Call::Register(r) => machine
                    .register(*now, &r)
                    .map(|(_, a)| a)
                    .unwrap_or_default(),
                Call::Submit(spec, cost) => {
                    // The record goes to the job store, as the shell's: nothing to hand back.
                    let _ = machine.submit(*now, spec, cost, "");
                    Vec::new()
                }
            };
            cpu[kind as usize] += thread_cpu_ns().saturating_sub(start + clock);
            planning.add(&planned(&actions));
        }
        let took = |kind: InputKind| Duration::from_nanos(cpu[kind as usize]);
        Some(Replayed {
            calls: calls.len() as u64,
            reports: took(InputKind::Report),
            tile_results: took(InputKind::TileResults),
            heartbeats: took(InputKind::Heartbeat),
            ticks: took(InputKind::Tick),
            other: took(InputKind::Other),
            clock: Duration::from_nanos(clock),
            repeated: planning == self.planning,
            planning,
        })
    }

    /// Logs where the coordinator's busy time went, priced term by term (`info`): which part
    /// of a round's price (`CostModel::planning`) or the flushes' a large cluster spends it on;
    /// and the thread CPU the real machine took here for all its inputs (reports, heartbeats,
    /// ticks and the rest besides rounds and flushes), to set the prices against.
    pub fn log_busy(&self) {
        let p = &self.planning;
        let cost = &self.config.cost;
        let domains = self.config.domain_bytes.len();
        let priced = |w: PlanningWork| cost.planning(&w, domains).as_secs_f64();
        let rounds = priced(PlanningWork {
            rounds: p.rounds,
            whole_rounds: p.whole_rounds,
            ..Default::default()
        });
        let planned = priced(PlanningWork {
            planned: p.planned,
            ..Default::default()
        });
        let members = priced(PlanningWork {
            members: p.members,
            whole_members: p.whole_members,
            ..Default::default()
        });
        let reports = priced(PlanningWork {
            reports: p.reports,
            queues: p.queues,
            ..Default::default()
        });
        let f = &self.flushing;
        info!(
            busy_s = format!("{:.3}", self.busy.as_secs_f64()),
            reports = p.reports,
            queues = p.queues,
            reports_s = format!("{reports:.3}"),
            rounds = p.rounds,
            whole_rounds = p.whole_rounds,
            planned = p.planned,
            rounds_s = format!("{rounds:.3}"),
            planned_s = format!("{planned:.3}"),
            members_s = format!("{members:.3}"),
            flushes = f.flushes,
            flush_lines = f.lines,
            flushes_s = format!("{:.3}", cost.flushing(f).as_secs_f64()),
            "coordinator busy"
        );
        let cpu = self.machine_ns.unwrap_or_default();
        let s = |kind: InputKind| format!("{:.3}", cpu[kind as usize] as f64 / 1e9);
        info!(
            total_s = format!("{:.3}", cpu.iter().sum::<u64>() as f64 / 1e9),
            reports_s = s(InputKind::Report),
            tile_results_s = s(InputKind::TileResults),
            heartbeats_s = s(InputKind::Heartbeat),
            ticks_s = s(InputKind::Tick),
            other_s = s(InputKind::Other),
            clock_ns_a_call_taken_out = self.clock_ns,
            "coordinator machine's thread CPU here"
        );
    }
}
