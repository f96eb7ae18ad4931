//! The simulation loop: the coordinator and the workers as nodes on the simulated network,
//! one heap of timed events, faults of a seed applied at their times. A run ends when the
//! frame is complete and every member's report is in, when the job fails, or at the
//! liveness bound.
//!
//! The parts: [`run`] is what a run is given and what it produced; this module holds the
//! loop and the faults; [`workers`] is the workers' side (their machines' events and actions,
//! peer bundles and acknowledgements, kills), [`coordinator`] the coordinator's, [`network`]
//! messages on the wire and [`compute`] time on the workers' cores.

use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use rayfarm_core::bundler::Tier;
use rayfarm_core::render::local::FrameSpec;
use rayfarm_core::scene::Manifest;
use rayfarm_machine::Time;
use rayfarm_machine::worker::{self as machine, WorkerConfig};
use rayfarm_proto::{self as proto, worker_message::Body as FromWorker};

use crate::check::Checks;
use crate::coord::{CoordConfig, SimCoordinator};
use crate::cores::SharedCores;
use crate::cost::FinishedWork;
use crate::events::EventHeap;
use crate::faults::{Fault, FaultPlan, Rng};
use crate::net::{COORDINATOR, Network, NodeId};
use crate::node::{PassRun, Scene, SimWorker};
use crate::storage::SharedStorage;

mod compute;
mod coordinator;
mod network;
mod run;
mod traffic;
mod workers;

pub use run::{
    FrameTime, KEPT_BUNDLES, Kills, MeasuredBundle, MeasuredFinished, MeasuredPass, Outcome,
    SimConfig,
};

/// How long a worker whose control stream ended waits before it registers again (the
/// worker shell backs off from 100 ms to 5 s; one second stands for it here).
pub const RECONNECT: Duration = Duration::from_secs(1);

/// Most events a run of `workers` workers may take unless told (`SimConfig::max_events`): a
/// machine that asks for a timer in the past forever would otherwise spin at one virtual
/// instant. A frame's events grow with its workers (each runs its own passes, loads, reports
/// and heartbeats), so a fixed cap stopped image-plane at 64 and 256 workers mid-frame
/// (README "Simulator"): a million a worker, at least twenty million.
pub fn default_max_events(workers: usize) -> u64 {
    (workers as u64).saturating_mul(1_000_000).max(20_000_000)
}

/// What travels between nodes. Control-stream messages name their stream (`conn`): each
/// registration opens a new one, and what was sent on a stream that has ended (the worker was
/// dropped, or the coordinator died) is for nobody.
enum Msg {
    Register(proto::Register, u64),
    ToCoordinator(FromWorker, u64),
    /// A coordinator's message, shared with the other workers told the same (each worker's
    /// machine reads it in place, `Event::SharedControl`; a StartFrame is taken out).
    Control(Arc<proto::CoordinatorMessage>, u64),
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
    /// A bundle the receiver's engine takes in now (its stream's task decoded it, and the
    /// engine was done with what it handled before).
    Received {
        to: NodeId,
        msg: Msg,
    },
    /// A worker's message that its sender is done with now (a bundle its link encoded, an
    /// acknowledgement its peer service made) goes to the sender's NIC: the NIC sends
    /// messages in the order they are ready, so one ready later never holds up one ready
    /// sooner.
    Depart {
        from: NodeId,
        to: NodeId,
        msg: Msg,
    },
    PassDone {
        node: NodeId,
        job_id: String,
        run: PassRun,
    },
    /// A prefetch's bytes have arrived from the storage: the domain is mapped now.
    PrefetchDone {
        node: NodeId,
        job_id: String,
        domain: u32,
        keep: std::collections::BTreeSet<u32>,
        pending: Option<rayfarm_core::render::cache::PendingLoad>,
    },
    /// A computation of `node` is ready for the shared cores (`--cores`): `done` follows
    /// when they have computed `work` for it.
    Compute {
        node: NodeId,
        work: Duration,
        done: Box<Ev>,
    },
    /// The shared cores' check of `epoch`: computations may be done, or shares change.
    CoresCheck {
        epoch: u64,
    },
    /// A finished pass's output, taken in by the worker's shell (after its price).
    PassTaken {
        node: NodeId,
        job_id: String,
        result: Result<machine::PassOutput, machine::PassFailed>,
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
    /// Workers' nodes by peer address (every bundle sent looks its receiver up).
    by_address: std::collections::HashMap<String, NodeId>,
    checks: Checks,
    outcome: Outcome,
    /// When an `Ev::Disk` is due.
    disk_at: Option<Time>,
    /// Control streams opened so far.
    conns: u64,
    /// The cores every worker shares (`CostModel::cores`), sliced between them; `None` when
    /// every worker has its own.
    cores: Option<SharedCores<Ev>>,
    /// CPU time of the machine's handling of the last bundle fed, when measured.
    handled_ns: Option<u64>,
    /// Messages by kind and the like, for the progress log (`traffic`).
    traffic: traffic::Traffic,
    /// The coordinator's message sized last, and its encoded size: a holders message goes to
    /// a whole view class in a row, and sizing it for each member was 6% of a 4,096-worker
    /// run (perf). Weak, so it neither keeps the message (a StartFrame is taken out of its
    /// `Arc` at delivery) nor lets its address be reused while remembered.
    control_size: Option<(std::sync::Weak<proto::CoordinatorMessage>, usize)>,
    /// Draws of the waits a timing seed makes random (`SimConfig::timing_seed`): a pass's for
    /// its tracing thread, a peer bundle's for the engine; `None`: every wait is its mean.
    waits: Option<Rng>,
}

/// Opens the scene a simulation reads (once for many runs).
pub fn open_scene(dir: &std::path::Path) -> Result<Arc<Scene>, String> {
    let manifest = Manifest::load(dir).map_err(|e| e.to_string())?;
    Ok(Arc::new(Scene::new(dir.to_path_buf(), manifest)))
}

/// Runs one simulation of `config` over `scene` with the faults of `plan`, ending at `bound`
/// at the latest. `expected_hash`: the clean run's image, which every job's must equal.
pub fn simulate(
    config: &SimConfig,
    scene: Arc<Scene>,
    plan: &FaultPlan,
    bound: Duration,
    expected_hash: Option<&str>,
) -> Result<Outcome, String> {
    // The warm-up jobs, then the measured one: the same frame, each with its schedule.
    let specs = config
        .warm_up
        .iter()
        .chain([&config.schedule])
        .map(|&schedule| proto::JobSpec {
            scene: config.scene.display().to_string(),
            width: config.width,
            height: config.height,
            spp: config.spp,
            max_depth: config.depth,
            schedule: schedule as i32,
            speculation: config.speculation.clone(),
            prefetch: config.prefetch,
            ..Default::default()
        })
        .collect();
    let frame = FrameSpec {
        width: config.width,
        height: config.height,
        spp: config.spp,
        max_depth: config.depth,
        camera: None,
    };
    frame.check()?;
    let coord = SimCoordinator::new(CoordConfig {
        specs,
        frame,
        domain_bytes: scene.domain_bytes.to_vec(),
        workers: config.workers,
        heartbeat: config.heartbeat,
        worker_timeout: config.worker_timeout,
        holders_interval: config.holders_interval,
        report_hold: config.report_hold,
        copy_rays: config.copy_rays,
        disk_latency: config.disk_latency,
        cost: config.cost,
        replay: config.replay_coordinator,
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
        by_address: Default::default(),
        checks: Checks::default(),
        outcome: Outcome::default(),
        disk_at: None,
        conns: 0,
        cores: config.cost.cores.map(SharedCores::new),
        handled_ns: None,
        traffic: Default::default(),
        control_size: None,
        waits: config.timing_seed.map(Rng::new),
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
        if t > bound || world.heap.scheduled() > config.max_events {
            break;
        }
        world.now = t;
        world.traffic.popped(t, &ev, &world.net, world.coord.rounds);
        world.event(ev);
        world.schedule_disk();
        if world.coord.is_done() {
            ended = true;
            break;
        }
    }
    world
        .traffic
        .log("run over", world.now, &world.net, world.coord.rounds);
    world.coord.log_busy();
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
        self.by_address.insert(w.address.clone(), node);
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
        self.by_address.get(address).copied()
    }

    fn event(&mut self, ev: Ev) {
        match ev {
            Ev::Deliver { from, to, msg } if to == COORDINATOR => self.at_coordinator(from, msg),
            Ev::Deliver { from, to, msg } => self.at_worker(from, to, msg),
            Ev::Received { to, msg } => self.take_bundle(to, msg),
            Ev::Depart { from, to, msg } => {
                // A process that died sends nothing more.
                if self.worker(from).is_some() {
                    self.transmit(self.now, from, to, msg);
                }
            }
            Ev::PassDone { node, job_id, run } => {
                let Some(w) = self.worker_mut(node) else {
                    return;
                };
                let computed = w.pass_until.take().map(|(end, _)| end);
                let free = w.msg_free_at;
                // What the shared cores stretched the pass's computing by.
                if let Some(end) = computed {
                    self.outcome.time.core_wait += self.now.since(end);
                }
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
                // The shell takes the output in after what it is handling, for its price.
                let price = match &result {
                    Ok(out) => self.config.cost.finished_pass(&FinishedWork::of(out)),
                    Err(_) => Duration::ZERO,
                };
                let ready = self.now.max(free);
                let done = if price.is_zero() {
                    ready
                } else {
                    self.steal(ready, price)
                };
                if done == self.now {
                    return self.take_pass(node, job_id, result);
                }
                self.outcome.time.shell_wait += done.since(self.now);
                if let Some(w) = self.worker_mut(node) {
                    w.msg_free_at = done;
                }
                self.heap.push(
                    done,
                    Ev::PassTaken {
                        node,
                        job_id,
                        result,
                    },
                );
            }
            Ev::PassTaken {
                node,
                job_id,
                result,
            } => self.take_pass(node, job_id, result),
            Ev::PrefetchDone {
                node,
                job_id,
                domain,
                keep,
                pending,
            } => {
                let Some(w) = self.worker_mut(node) else {
                    return;
                };
                let result = w.finish_prefetch(pending, &keep);
                let resident = w.resident();
                self.feed(
                    node,
                    machine::Event::PrefetchDone {
                        job_id,
                        domain,
                        result,
                        resident,
                    },
                );
            }
            Ev::Compute { node, work, done } => {
                if self.worker(node).is_none() {
                    return;
                }
                if let Some(cores) = self.cores.as_mut() {
                    cores.compute(self.now, node, work, *done);
                }
                self.check_cores_again();
            }
            Ev::CoresCheck { epoch } => {
                let now = self.now;
                let Some(done) = self.cores.as_mut().and_then(|c| c.check(now, epoch)) else {
                    return;
                };
                for ev in done {
                    self.heap.push(now, ev);
                }
                self.check_cores_again();
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
                self.outcome.peers_reported += 1;
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

    fn finish(mut self, ended: bool, bound: Time, expected_hash: Option<&str>) -> Outcome {
        let mut o = std::mem::take(&mut self.outcome);
        o.events = self.heap.scheduled();
        o.messages = self.net.messages;
        o.rounds = self.coord.rounds;
        o.frame_time = self.coord.completed_at.map(|t| t.since(Time(0)));
        o.frames = self.coord.frames;
        o.coordinator_busy = self.coord.busy;
        o.coordinator_replayed = self.coord.replay();
        o.storage_bytes = self.storage.bytes;
        for w in self.workers.iter().flatten() {
            let c = w.cache_counters();
            o.prefetches += c.prefetches;
            o.prefetches_used += c.prefetches_used;
            o.prefetches_wasted += c.prefetches_wasted;
        }
        for p in &self.coord.problems {
            self.checks.violation("worker error", p.clone());
        }
        if let Some(e) = &self.coord.failed {
            self.checks.violation("job failed", e.clone());
        }
        o.jobs = self.coord.job_ids.len() as u64;
        if o.frame_time.is_none() || !self.coord.all_written() {
            let why = if ended {
                "the job ended without its image".to_string()
            } else if o.events > self.config.max_events {
                format!(
                    "more than {} events without completing (--max-events)",
                    self.config.max_events
                )
            } else {
                format!(
                    "not complete at the bound of {:.3} s virtual",
                    bound.0 as f64 / 1e9
                )
            };
            self.checks.violation("liveness", why);
        } else {
            // Every job renders the same frame: each image must be the clean run's, or, in
            // the clean run, the first job's.
            let mut want = expected_hash.map(str::to_string);
            for (i, id) in self.coord.job_ids.iter().enumerate() {
                match &self.coord.images[id] {
                    Ok(h) => {
                        match &want {
                            Some(w) if w != h => self.checks.violation(
                                "image",
                                format!(
                                    "job {} of {}: image hash {h}, expected {w}",
                                    i + 1,
                                    o.jobs
                                ),
                            ),
                            Some(_) => {}
                            None => want = Some(h.clone()),
                        }
                        o.image_hash = Some(h.clone());
                    }
                    Err(e) => self.checks.violation("image", e.clone()),
                }
            }
        }
        o.violations = self.checks.into_violations();
        o
    }
}

#[cfg(test)]
mod tests;
