//! The simulation loop: the coordinator and the workers as nodes on the simulated network,
//! one heap of timed events, faults of a seed applied at their times. A run ends when the
//! frame is complete and every member's report is in, when the job fails, or at the
//! liveness bound.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use prost::Message;
use rayfarm_core::bundler::Tier;
use rayfarm_core::render::local::FrameSpec;
use rayfarm_core::scene::Manifest;
use rayfarm_core::wire::{self, BatchLimits};
use rayfarm_machine::Time;
use rayfarm_machine::worker::{self as machine, Action, Payload, WorkerConfig};
use rayfarm_proto::{
    self as proto, Schedule, coordinator_message::Body, worker_message::Body as FromWorker,
};

use crate::check::{Checks, Violation};
use crate::coord::{CoordConfig, SimCoordinator, ToNode};
use crate::cost::CostModel;
use crate::events::EventHeap;
use crate::faults::{Fault, FaultPlan, Rng};
use crate::net::{COORDINATOR, LinkModel, Network, NodeId};
use crate::node::{PassRun, QueueCaps, Scene, SimWorker};
use crate::storage::{SharedStorage, StorageModel};

/// How long a worker whose control stream ended waits before it registers again (the
/// worker shell backs off from 100 ms to 5 s; one second stands for it here).
pub const RECONNECT: Duration = Duration::from_secs(1);

/// Most events one run may take (a machine that asks for a timer in the past forever would
/// otherwise spin at one virtual instant).
const MAX_EVENTS: u64 = 20_000_000;

/// What to simulate.
#[derive(Clone, Debug)]
pub struct SimConfig {
    pub scene: PathBuf,
    pub workers: usize,
    pub schedule: Schedule,
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub depth: u32,
    pub cache_bytes: u64,
    /// Camera rays are issued while fewer than this many rays are queued on a worker.
    pub wave_rays: usize,
    /// Most rays a worker traces in one pass.
    pub pass_rays: usize,
    pub links: LinkModel,
    pub cost: CostModel,
    pub storage: StorageModel,
    /// Measure each pass's CPU time on this machine (`calibrate`; the virtual times do not
    /// depend on it).
    pub measure: bool,
    pub caps: QueueCaps,
    /// A peer that acknowledges nothing for this long is reported unresponsive.
    pub ack_deadline: Duration,
    /// How long one job record takes to reach the coordinator's disk.
    pub disk_latency: Duration,
    pub heartbeat: Duration,
    pub worker_timeout: Duration,
    /// The predictive schedule's speculation setting (`JobSpec.speculation`; empty: full).
    pub speculation: String,
}

/// Kills by what the killed worker was doing.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Kills {
    pub total: u64,
    pub mid_pass: u64,
    pub mid_load: u64,
    /// With bundles it sent still unacknowledged.
    pub bundles_in_flight: u64,
}

/// What a run produced.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Outcome {
    /// Virtual time from the start to the last tile committed.
    pub frame_time: Option<Duration>,
    pub image_hash: Option<String>,
    /// Domain loads of every worker.
    pub loads: u64,
    /// Ray segments traced, in every pass that finished.
    pub segments: u64,
    /// Bytes of peer bundles sent.
    pub peer_bytes: u64,
    /// Rays sent to another worker, as the workers' frame reports count them.
    pub rays_migrated: u64,
    /// Messages of every kind.
    pub messages: u64,
    pub rounds: u64,
    pub events: u64,
    pub kills: Kills,
    pub coordinator_crashes: u64,
    /// Frames started (more than one after a coordinator crash or a loss of every worker).
    pub frames: u64,
    pub violations: Vec<Violation>,
    /// Virtual time the coordinator spent planning.
    pub coordinator_busy: Duration,
    /// Bytes the storage was charged for.
    pub storage_bytes: u64,
    /// Every pass that loaded nothing, with the CPU time it took here, when measured.
    pub measured: Vec<MeasuredPass>,
}

/// A pass's work and what it cost on this machine (`calibrate` fits the prices to these).
#[derive(Clone, Debug, PartialEq)]
pub struct MeasuredPass {
    pub counters: rayfarm_core::render::KernelCounters,
    pub cpu_ns: u64,
}

/// What travels between nodes. Control-stream messages name their stream (`conn`): each
/// registration opens a new one, and what was sent on a stream that has ended (the worker was
/// dropped, or the coordinator died) is for nobody.
enum Msg {
    Register(proto::Register, u64),
    ToCoordinator(FromWorker, u64),
    Control(proto::CoordinatorMessage, u64),
    /// The coordinator closed the worker's control stream (or died, or refused it).
    Closed(u64),
    /// The worker's process died: its stream ends.
    StreamEnded(u64),
    Bundle {
        sender: String,
        job_id: String,
        tier: Tier,
        batches: Vec<Bytes>,
        seq: u64,
    },
    Ack {
        from: String,
        seq: u64,
    },
}

enum Ev {
    Deliver {
        from: NodeId,
        to: NodeId,
        msg: Msg,
    },
    PassDone {
        node: NodeId,
        job_id: String,
        run: PassRun,
    },
    Tick {
        node: NodeId,
    },
    AckDue {
        node: NodeId,
        peer: String,
        seq: u64,
    },
    Heartbeat {
        node: NodeId,
    },
    CoordTick,
    Kill {
        node: NodeId,
    },
    Join,
    Reregister {
        node: NodeId,
    },
    /// The coordinator's next job record is on disk.
    Disk,
    /// The coordinator's process dies, and a new one starts `down` later.
    Crash {
        down: Duration,
    },
    Restart,
}

struct World<'a> {
    config: &'a SimConfig,
    scene: Arc<Scene>,
    now: Time,
    heap: EventHeap<Ev>,
    net: Network,
    storage: SharedStorage,
    coord: SimCoordinator,
    /// Index 0 is the coordinator's place; workers from 1.
    workers: Vec<Option<SimWorker>>,
    checks: Checks,
    outcome: Outcome,
    /// When an `Ev::Disk` is due.
    disk_at: Option<Time>,
    /// Control streams opened so far.
    conns: u64,
}

/// Opens the scene a simulation reads (once for many runs).
pub fn open_scene(dir: &std::path::Path) -> Result<Arc<Scene>, String> {
    let manifest = Manifest::load(dir).map_err(|e| e.to_string())?;
    Ok(Arc::new(Scene {
        dir: dir.to_path_buf(),
        manifest,
    }))
}

/// Runs one simulation of `config` over `scene` with the faults of `plan`, ending at `bound`
/// at the latest. `expected_hash`: the clean run's image, which the run's must equal.
pub fn simulate(
    config: &SimConfig,
    scene: Arc<Scene>,
    plan: &FaultPlan,
    bound: Duration,
    expected_hash: Option<&str>,
) -> Result<Outcome, String> {
    let spec = proto::JobSpec {
        scene: config.scene.display().to_string(),
        width: config.width,
        height: config.height,
        spp: config.spp,
        max_depth: config.depth,
        schedule: config.schedule as i32,
        speculation: config.speculation.clone(),
        ..Default::default()
    };
    let frame = FrameSpec {
        width: config.width,
        height: config.height,
        spp: config.spp,
        max_depth: config.depth,
        camera: None,
    };
    frame.check()?;
    let coord = SimCoordinator::new(CoordConfig {
        spec,
        frame,
        domain_bytes: scene.manifest.domains.iter().map(|d| d.bytes).collect(),
        workers: config.workers,
        heartbeat: config.heartbeat,
        worker_timeout: config.worker_timeout,
        disk_latency: config.disk_latency,
        cost: config.cost,
    })?;
    let mut world = World {
        config,
        scene,
        now: Time(0),
        heap: EventHeap::default(),
        net: Network::new(config.links, plan.jitter, Rng::new(plan.seed ^ 0x5eed)),
        storage: SharedStorage::new(config.storage),
        coord,
        workers: vec![None],
        checks: Checks::default(),
        outcome: Outcome::default(),
        disk_at: None,
        conns: 0,
    };
    for _ in 0..config.workers {
        world.spawn()?;
    }
    world.apply(plan)?;
    world
        .heap
        .push(Time(0) + config.heartbeat / 4, Ev::CoordTick);
    let bound = Time(0) + bound;
    let mut ended = false;
    while let Some((t, ev)) = world.heap.pop() {
        if t > bound || world.heap.scheduled() > MAX_EVENTS {
            break;
        }
        world.now = t;
        world.event(ev);
        world.schedule_disk();
        if world.coord.is_done() {
            ended = true;
            break;
        }
    }
    Ok(world.finish(ended, bound, expected_hash))
}

impl World<'_> {
    /// A new worker node; it registers at once.
    fn spawn(&mut self) -> Result<NodeId, String> {
        let node = self.workers.len();
        let id = format!("sim-w{}", node - 1);
        let address = format!("{id}:7000");
        let config = WorkerConfig {
            wave_rays: self.config.wave_rays,
            pass_rays: self.config.pass_rays,
            ..WorkerConfig::new(id, address, self.config.cache_bytes)
        };
        let w = SimWorker::new(node, config, self.scene.clone(), self.config.caps)?;
        self.workers.push(Some(w));
        self.register(node);
        self.heap
            .push(self.now + self.config.heartbeat, Ev::Heartbeat { node });
        Ok(node)
    }

    fn register(&mut self, node: NodeId) {
        self.conns += 1;
        let conn = self.conns;
        let Some(w) = self.worker_mut(node) else {
            return;
        };
        w.conn = conn;
        let r = proto::Register {
            protocol_version: proto::PROTOCOL_VERSION,
            worker_id: w.id.clone(),
            peer_address: w.address.clone(),
            cache_bytes: w.cache_bytes,
            threads: self.config.cost.threads,
        };
        self.send(node, COORDINATOR, Msg::Register(r, conn));
    }

    /// An `Ev::Disk` at the coordinator's next disk write, if it is sooner than the one due.
    fn schedule_disk(&mut self) {
        if let Some(t) = self.coord.next_write()
            && self.disk_at.is_none_or(|d| t < d)
        {
            self.disk_at = Some(t);
            self.heap.push(t, Ev::Disk);
        }
    }

    /// Schedules the plan's faults.
    fn apply(&mut self, plan: &FaultPlan) -> Result<(), String> {
        for f in &plan.faults {
            match *f {
                Fault::Kill { worker, at } => self.heap.push(at, Ev::Kill { node: worker + 1 }),
                Fault::Join { at } => self.heap.push(at, Ev::Join),
                Fault::Delay {
                    worker,
                    window,
                    extra,
                } => self.net.delay(worker + 1, window, extra),
                Fault::Partition { a, b, window } => self.net.partition(a + 1, b + 1, window),
                Fault::StopAcking { worker, at } => {
                    if let Some(w) = self.worker_mut(worker + 1) {
                        w.stuck_from = Some(at);
                    }
                }
                Fault::CrashCoordinator { at, down } => self.heap.push(at, Ev::Crash { down }),
            }
        }
        Ok(())
    }

    fn worker(&self, node: NodeId) -> Option<&SimWorker> {
        self.workers.get(node)?.as_ref().filter(|w| w.alive)
    }

    fn worker_mut(&mut self, node: NodeId) -> Option<&mut SimWorker> {
        self.workers.get_mut(node)?.as_mut().filter(|w| w.alive)
    }

    fn node_of(&self, address: &str) -> Option<NodeId> {
        self.workers
            .iter()
            .position(|w| w.as_ref().is_some_and(|w| w.address == address))
    }

    fn send(&mut self, from: NodeId, to: NodeId, msg: Msg) {
        self.send_at(self.now, from, to, msg);
    }

    /// Sends `msg` when its sender is done with it at `depart` (not before now).
    fn send_at(&mut self, depart: Time, from: NodeId, to: NodeId, msg: Msg) {
        let bytes = match &msg {
            Msg::Register(r, _) => r.encoded_len(),
            Msg::ToCoordinator(b, _) => proto::WorkerMessage {
                body: Some(b.clone()),
            }
            .encoded_len(),
            Msg::Control(m, _) => m.encoded_len(),
            Msg::Bundle { batches, .. } => batches.iter().map(Bytes::len).sum::<usize>() + 64,
            Msg::Closed(_) | Msg::StreamEnded(_) | Msg::Ack { .. } => 16,
        };
        if let Msg::Bundle { .. } = msg {
            self.outcome.peer_bytes += bytes as u64;
        }
        let at = self.net.arrival(depart.max(self.now), from, to, bytes);
        self.heap.push(at, Ev::Deliver { from, to, msg });
    }

    fn event(&mut self, ev: Ev) {
        match ev {
            Ev::Deliver { from, to, msg } if to == COORDINATOR => self.at_coordinator(from, msg),
            Ev::Deliver { from, to, msg } => self.at_worker(from, to, msg),
            Ev::PassDone { node, job_id, run } => {
                let Some(w) = self.worker_mut(node) else {
                    return;
                };
                w.pass_until = None;
                let resident = w.resident();
                if let Ok(out) = &run.result {
                    self.outcome.segments += out.counters.segments();
                    if let Some(cpu_ns) = run.cpu_ns.filter(|_| run.loads == 0) {
                        self.outcome.measured.push(MeasuredPass {
                            counters: out.counters,
                            cpu_ns,
                        });
                    }
                }
                let result = run.result.map_err(machine::PassFailed::Load);
                self.feed(
                    node,
                    machine::Event::PassFinished {
                        job_id,
                        result,
                        resident,
                    },
                );
            }
            Ev::Tick { node } => {
                let now = self.now;
                let Some(w) = self.worker_mut(node) else {
                    return;
                };
                if w.tick_at != Some(now) {
                    return;
                }
                w.tick_at = None;
                self.feed(node, machine::Event::Tick);
            }
            Ev::AckDue { node, peer, seq } => {
                let Some(w) = self.worker_mut(node) else {
                    return;
                };
                let Some(link) = w.links.get_mut(&peer) else {
                    return;
                };
                if link.reported || link.owed.front().is_none_or(|&(s, _)| s > seq) {
                    return;
                }
                link.reported = true;
                let reason = format!("{} bundles unacknowledged", link.owed.len());
                self.feed(node, machine::Event::PeerUnresponsive { peer, reason });
            }
            Ev::Heartbeat { node } => {
                let Some(w) = self.worker(node) else { return };
                if !w.disconnected {
                    let hb = FromWorker::Heartbeat(proto::Heartbeat {
                        sent_ms: self.now.0 / 1_000_000,
                        ..Default::default()
                    });
                    let conn = w.conn;
                    self.send(node, COORDINATOR, Msg::ToCoordinator(hb, conn));
                }
                self.heap
                    .push(self.now + self.config.heartbeat, Ev::Heartbeat { node });
            }
            Ev::CoordTick => {
                let out = self.coord.tick(self.now);
                self.carry_out(out);
                self.heap
                    .push(self.now + self.config.heartbeat / 4, Ev::CoordTick);
            }
            Ev::Kill { node } => self.kill(node),
            Ev::Join => {
                // A failure to make a worker is a simulator bug; the run goes on without it.
                let _ = self.spawn();
            }
            Ev::Reregister { node } => {
                if let Some(w) = self.worker_mut(node) {
                    w.disconnected = false;
                    self.register(node);
                }
            }
            Ev::Disk => {
                self.disk_at = None;
                let out = self.coord.disk_done(self.now);
                self.carry_out(out);
            }
            Ev::Crash { down } => {
                self.outcome.coordinator_crashes += 1;
                // Its operating system closes its sockets: every worker's stream ends.
                for (node, conn) in self.coord.crash() {
                    self.send(COORDINATOR, node, Msg::Closed(conn));
                }
                self.heap.push(self.now + down, Ev::Restart);
            }
            Ev::Restart => {
                let out = self.coord.restart(self.now);
                self.carry_out(out);
            }
        }
    }

    fn kill(&mut self, node: NodeId) {
        let Some(w) = self.worker_mut(node) else {
            return;
        };
        w.alive = false;
        let pass = w.pass_until;
        let in_flight = w.links.values().any(|l| !l.owed.is_empty());
        let conn = w.conn;
        let k = &mut self.outcome.kills;
        k.total += 1;
        if let Some((_, loaded_at)) = pass {
            k.mid_pass += 1;
            k.mid_load += u64::from(self.now < loaded_at);
        }
        k.bundles_in_flight += u64::from(in_flight);
        // Its operating system closes its sockets: the coordinator sees the stream end.
        self.send(node, COORDINATOR, Msg::StreamEnded(conn));
    }

    fn at_coordinator(&mut self, from: NodeId, msg: Msg) {
        let now = self.now;
        let out = match msg {
            Msg::Register(r, conn) => self.coord.register(now, from, conn, r),
            Msg::ToCoordinator(body, conn) => self.coord.message(now, from, conn, body),
            Msg::StreamEnded(conn) => self.coord.gone(now, from, conn),
            _ => Vec::new(),
        };
        for &(frame, tile, at) in &self.coord.commits[self.checks.commits_seen..] {
            self.checks.commit(frame, tile, at);
        }
        self.checks.commits_seen = self.coord.commits.len();
        self.carry_out(out);
    }

    /// Sends what the coordinator answered, once it is done planning (it handles one thing
    /// at a time, so what it sends leaves when all it was given so far is done).
    fn carry_out(&mut self, out: Vec<ToNode>) {
        let depart = self.coord.free_at;
        for o in out {
            match o {
                ToNode::Send(node, conn, m) => {
                    self.send_at(depart, COORDINATOR, node, Msg::Control(*m, conn))
                }
                ToNode::Close(node, conn) => {
                    self.send_at(depart, COORDINATOR, node, Msg::Closed(conn))
                }
            }
        }
    }

    fn at_worker(&mut self, from: NodeId, to: NodeId, msg: Msg) {
        let now = self.now;
        let Some(w) = self.worker_mut(to) else { return };
        match msg {
            // What was sent on an older stream than the worker's is for nobody.
            Msg::Control(_, conn) | Msg::Closed(conn) if conn != w.conn => {}
            Msg::Control(m, _) => match m.body {
                Some(Body::StartFrame(start)) => {
                    let opened = w.open(&start);
                    self.feed(to, machine::Event::FrameOpened { start, opened });
                }
                body => self.feed(
                    to,
                    machine::Event::Control(proto::CoordinatorMessage { body }),
                ),
            },
            Msg::Closed(_) => {
                w.disconnected = true;
                self.feed(to, machine::Event::Disconnected);
                // The shell reconnects; a worker sidelined for this frame sits it out.
                self.heap.push(now + RECONNECT, Ev::Reregister { node: to });
            }
            Msg::Bundle {
                sender,
                job_id,
                tier,
                batches,
                seq,
            } => {
                if w.is_stuck(now) {
                    return;
                }
                let me = w.address.clone();
                match decode(tier, &batches) {
                    Ok(payload) => self.feed(
                        to,
                        machine::Event::PeerBundle {
                            sender,
                            job_id,
                            payload,
                        },
                    ),
                    Err(e) => self
                        .checks
                        .violation("bundle", format!("undecodable bundle: {e}")),
                }
                self.send(to, from, Msg::Ack { from: me, seq });
            }
            Msg::Ack { from: peer, seq } => {
                if let Some(link) = w.links.get_mut(&peer) {
                    while link.owed.front().is_some_and(|&(s, _)| s <= seq) {
                        link.owed.pop_front();
                    }
                }
            }
            Msg::Register(..) | Msg::ToCoordinator(..) | Msg::StreamEnded(_) => {}
        }
    }

    /// Hands `event` to the machine of `node` and carries out its actions.
    fn feed(&mut self, node: NodeId, event: machine::Event<machine::MemorySpill>) {
        let now = self.now;
        let Some(w) = self.worker_mut(node) else {
            return;
        };
        let actions = w.machine.handle(now, event);
        let (queued, cap) = w.queued_bytes();
        let (early, early_cap) = (w.machine.early_bytes(), w.early_cap);
        self.checks.caps(queued, cap, early, early_cap);
        for a in actions {
            self.action(node, a);
        }
        let Some(w) = self.worker_mut(node) else {
            return;
        };
        if let Some(t) = w.machine.next_timeout() {
            let t = t.max(now);
            if w.tick_at.is_none_or(|x| t < x) {
                w.tick_at = Some(t);
                self.heap.push(t, Ev::Tick { node });
            }
        }
    }

    fn action(&mut self, node: NodeId, action: Action) {
        let now = self.now;
        let cost = self.config.cost;
        let measure = self.config.measure;
        let ack_deadline = self.config.ack_deadline;
        let Some(w) = self.worker_mut(node) else {
            return;
        };
        match action {
            Action::ToCoordinator(body) => {
                if !w.disconnected {
                    let conn = w.conn;
                    self.send(node, COORDINATOR, Msg::ToCoordinator(body, conn));
                }
            }
            Action::ToPeer {
                peer,
                job_id,
                tier,
                batches,
            } => {
                let seq = w.next_bundle;
                w.next_bundle += 1;
                w.links
                    .entry(peer.clone())
                    .or_default()
                    .owed
                    .push_back((seq, now));
                let sender = w.address.clone();
                self.heap.push(
                    now + ack_deadline,
                    Ev::AckDue {
                        node,
                        peer: peer.clone(),
                        seq,
                    },
                );
                if let Some(to) = self.node_of(&peer) {
                    self.send(
                        node,
                        to,
                        Msg::Bundle {
                            sender,
                            job_id,
                            tier,
                            batches,
                            seq,
                        },
                    );
                }
            }
            Action::DropPeers(peers) => {
                for p in peers {
                    w.links.remove(&p);
                }
            }
            Action::StartPass { job_id, work } => {
                let Some(w) = self.workers.get_mut(node).and_then(Option::as_mut) else {
                    return;
                };
                let run = w.run_pass(now, &job_id, work, &cost, &mut self.storage, measure);
                let until = now + run.took;
                w.pass_until = Some((until, now + run.load_time));
                self.outcome.loads += run.loads;
                self.heap.push(until, Ev::PassDone { node, job_id, run });
            }
            Action::Evict(domains) => w.evict(&domains),
            Action::Pin(domains) => w.pin(domains),
            Action::FrameEnded { job_id, mut stats } => {
                stats.cache = w.cache_counters();
                stats.threads = cost.threads as usize;
                let migrated = stats.rays_sent;
                let report = proto::FrameReport {
                    job_id,
                    stats_json: serde_json::to_string(&stats).unwrap_or_default(),
                    error: String::new(),
                    declined: false,
                };
                if !w.disconnected {
                    let conn = w.conn;
                    self.send(
                        node,
                        COORDINATOR,
                        Msg::ToCoordinator(FromWorker::FrameReport(report), conn),
                    );
                }
                self.outcome.rays_migrated += migrated;
            }
        }
    }

    fn finish(mut self, ended: bool, bound: Time, expected_hash: Option<&str>) -> Outcome {
        let mut o = std::mem::take(&mut self.outcome);
        o.events = self.heap.scheduled();
        o.messages = self.net.messages;
        o.rounds = self.coord.rounds;
        o.frame_time = self.coord.completed_at.map(|t| t.since(Time(0)));
        o.frames = self.coord.frames;
        o.coordinator_busy = self.coord.busy;
        o.storage_bytes = self.storage.bytes;
        for p in &self.coord.problems {
            self.checks.violation("worker error", p.clone());
        }
        if let Some(e) = &self.coord.failed {
            self.checks.violation("job failed", e.clone());
        }
        let written = self.coord.image_hash.clone();
        if o.frame_time.is_none() || written.is_none() {
            let why = if ended {
                "the job ended without its image".to_string()
            } else if o.events > MAX_EVENTS {
                format!("more than {MAX_EVENTS} events without completing")
            } else {
                format!(
                    "not complete at the bound of {:.3} s virtual",
                    bound.0 as f64 / 1e9
                )
            };
            self.checks.violation("liveness", why);
        } else if let Some(written) = written {
            match written {
                Ok(h) => {
                    if let Some(want) = expected_hash
                        && want != h
                    {
                        self.checks
                            .violation("image", format!("image hash {h}, the clean run's {want}"));
                    }
                    o.image_hash = Some(h);
                }
                Err(e) => self.checks.violation("image", e),
            }
        }
        o.violations = self.checks.into_violations();
        o
    }
}

/// A bundle's batches decoded for any frame, as the worker shell's peer service does.
fn decode(tier: Tier, batches: &[Bytes]) -> Result<Payload, String> {
    let limits = BatchLimits::any_frame(1 << 20);
    Ok(match tier {
        Tier::Results => Payload::Verdicts(
            batches
                .iter()
                .map(|b| wire::decode_verdicts(b, &limits).map_err(|e| e.to_string()))
                .collect::<Result<_, _>>()?,
        ),
        _ => Payload::Rays(
            batches
                .iter()
                .map(|b| wire::decode_batch(b, &limits).map_err(|e| e.to_string()))
                .collect::<Result<_, _>>()?,
        ),
    })
}
