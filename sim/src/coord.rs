//! The simulated coordinator: the real frame machine (`RunningFrame` and its lifecycle)
//! with what the coordinator shell keeps around it for one job: registered workers and when
//! each was last heard, the film its committed tiles go to, and the workers' frame reports.
//! It records what the invariants need (every tile committed, and when).

use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

use rayfarm_core::cluster::stats::WorkerFrameStats;
use rayfarm_core::render::Film;
use rayfarm_core::render::local::FrameSpec;
use rayfarm_core::schedule::dynamic::Options;
use rayfarm_machine::Time;
use rayfarm_machine::coordinator::{Member, Outgoing, Rounds, RunningFrame, accusation_grace};
use rayfarm_proto::{self as proto, coordinator_message::Body, worker_message::Body as FromWorker};

use crate::net::NodeId;

/// What the coordinator does to a worker's node.
pub enum ToNode {
    /// A message on its control stream.
    Send(NodeId, Box<proto::CoordinatorMessage>),
    /// Its control stream is closed (it was dropped).
    Close(NodeId),
}

struct Entry {
    id: String,
    node: NodeId,
    address: String,
    cache_bytes: u64,
    last_seen: Time,
}

/// How the simulated coordinator is set up.
pub struct CoordConfig {
    pub job_id: String,
    pub spec: proto::JobSpec,
    pub frame: FrameSpec,
    pub domain_bytes: Vec<u64>,
    /// The frame starts once this many workers registered.
    pub workers: usize,
    pub heartbeat: Duration,
    pub worker_timeout: Duration,
}

/// See the module documentation.
pub struct SimCoordinator {
    config: CoordConfig,
    workers: BTreeMap<u32, Entry>,
    next_key: u32,
    pub frame: Option<RunningFrame>,
    /// Registrations so far: the job is submitted once the first `workers` registered.
    registrations: usize,
    started: bool,
    film: Film,
    _film_dir: tempfile::TempDir,
    /// Every tile committed, in order, with when (a tile twice is a violation).
    pub commits: Vec<(u32, Time)>,
    /// When the ledger was complete.
    pub completed_at: Option<Time>,
    /// Members whose frame report is awaited after the end.
    waiting: BTreeSet<u32>,
    pub reports: Vec<WorkerFrameStats>,
    /// What went wrong that no healthy run does (a worker's error, impossible results, every
    /// worker lost).
    pub problems: Vec<String>,
    /// Rounds planned and the domain loads the plans asked for, at the end.
    pub rounds: u64,
}

impl SimCoordinator {
    pub fn new(config: CoordConfig) -> Result<Self, String> {
        let dir = tempfile::tempdir().map_err(|e| format!("temporary film directory: {e}"))?;
        let frame = RunningFrame::new(
            Time(0),
            config.job_id.clone(),
            config.spec.clone(),
            config.frame.clone(),
            config.domain_bytes.clone(),
            // The coordinator's defaults (`--replicate free-slots --rounds async`).
            Options {
                replicate_onto_idle: false,
                fill_free_slots: true,
            },
            Rounds::Async,
        )?;
        let film = Film::temporary_in(dir.path(), *frame.ledger.grid(), config.frame.spp)
            .map_err(|e| e.to_string())?;
        Ok(SimCoordinator {
            config,
            workers: BTreeMap::new(),
            next_key: 0,
            frame: Some(frame),
            registrations: 0,
            started: false,
            film,
            _film_dir: dir,
            commits: Vec::new(),
            completed_at: None,
            waiting: BTreeSet::new(),
            reports: Vec::new(),
            problems: Vec::new(),
            rounds: 0,
        })
    }

    /// Whether the frame is complete and every member's report is in.
    pub fn is_done(&self) -> bool {
        self.completed_at.is_some() && self.waiting.is_empty()
    }

    /// The image hash, once complete.
    pub fn image_hash(&self) -> Result<String, String> {
        self.film
            .hash()
            .map(|h| format!("{h:016x}"))
            .map_err(|e| e.to_string())
    }

    fn key_of(&self, node: NodeId) -> Option<u32> {
        self.workers
            .iter()
            .find(|(_, e)| e.node == node)
            .map(|(&k, _)| k)
    }

    fn out(&self, out: Vec<Outgoing>) -> Vec<ToNode> {
        out.into_iter()
            .filter_map(|(k, m)| Some(ToNode::Send(self.workers.get(&k)?.node, Box::new(m))))
            .collect()
    }

    /// A worker registers.
    pub fn register(&mut self, now: Time, node: NodeId, r: proto::Register) -> Vec<ToNode> {
        let key = self.next_key;
        self.next_key += 1;
        self.registrations += 1;
        let registered = Body::Registered(proto::Registered {
            heartbeat_ms: self.config.heartbeat.as_millis() as u32,
        });
        let mut out = vec![ToNode::Send(
            node,
            Box::new(proto::CoordinatorMessage {
                body: Some(registered),
            }),
        )];
        let member = Member::new(r.peer_address.clone(), r.cache_bytes);
        self.workers.insert(
            key,
            Entry {
                id: r.worker_id.clone(),
                node,
                address: r.peer_address,
                cache_bytes: r.cache_bytes,
                last_seen: now,
            },
        );
        let Some(frame) = self.frame.as_mut() else {
            return out;
        };
        if self.started {
            if let Some(join) = frame.admit(key, &r.worker_id, member) {
                out.extend(self.out(join));
            }
        } else if self.registrations >= self.config.workers {
            // Submitted once the first workers registered, it starts on those attached now
            // (some may have died meanwhile), as the coordinator starts a queued job.
            let members = self
                .workers
                .iter()
                .map(|(&k, e)| (k, Member::new(e.address.clone(), e.cache_bytes)))
                .collect();
            let start = frame.start(members);
            self.started = true;
            out.extend(self.out(start));
        }
        out
    }

    /// A message of the worker on `node`.
    pub fn message(&mut self, now: Time, node: NodeId, body: FromWorker) -> Vec<ToNode> {
        let Some(key) = self.key_of(node) else {
            return Vec::new();
        };
        if let Some(e) = self.workers.get_mut(&key) {
            e.last_seen = now;
        }
        let Some(frame) = self.frame.as_mut() else {
            // After the end only frame reports matter.
            if let FromWorker::FrameReport(r) = body {
                self.frame_report(key, r);
            }
            return Vec::new();
        };
        match body {
            FromWorker::Register(_) | FromWorker::Heartbeat(_) => Vec::new(),
            FromWorker::QueueReport(r) if r.job_id == frame.job_id => {
                let out = frame.report(key, r);
                self.out(out)
            }
            FromWorker::QueueReport(_) => Vec::new(),
            FromWorker::TileResults(r) if r.job_id == frame.job_id => {
                let (committed, refused) = frame.results(key, r);
                for (tile, sums) in &committed {
                    self.commits.push((*tile, now));
                    if let Err(e) = self.film.write_tile(*tile, sums) {
                        self.problems.push(format!("film: {e}"));
                    }
                }
                if let Some(why) = refused {
                    self.problems
                        .push(format!("impossible tile results from key {key}: {why}"));
                    let id = self.workers[&key].id.clone();
                    frame.refuse(id);
                    let mut out = vec![ToNode::Close(node)];
                    out.extend(self.lose(key));
                    return out;
                }
                if frame.ledger.is_complete() {
                    return self.complete(now);
                }
                Vec::new()
            }
            FromWorker::TileResults(_) => Vec::new(),
            FromWorker::FrameReport(r) => {
                if !r.error.is_empty() && r.job_id == frame.job_id {
                    self.problems.push(r.error.clone());
                    if r.declined {
                        frame.declined.push(r.error);
                        return self.lose(key);
                    }
                    // The job fails: the run ends with the problem recorded.
                    let end = frame.end_messages();
                    self.frame = None;
                    return self.out(end);
                }
                Vec::new()
            }
            FromWorker::PeerUnresponsive(p) => {
                let silent = self
                    .workers
                    .iter()
                    .find(|(_, e)| e.address == p.peer_address)
                    .map(|(&k, _)| k);
                if let Some(k) = silent
                    && frame.members().any(|m| m == k)
                    && frame.members().any(|m| m == key)
                {
                    frame.accusations.add(key, k, now, &p.reason);
                }
                Vec::new()
            }
        }
    }

    fn complete(&mut self, now: Time) -> Vec<ToNode> {
        let Some(frame) = self.frame.take() else {
            return Vec::new();
        };
        self.completed_at = Some(now);
        self.rounds = frame.round;
        self.waiting = frame.members().collect();
        let end = frame.end_messages();
        self.out(end)
    }

    fn frame_report(&mut self, key: u32, r: proto::FrameReport) {
        if !r.error.is_empty() {
            self.problems.push(r.error);
        } else if let Ok(stats) = serde_json::from_str::<WorkerFrameStats>(&r.stats_json) {
            self.reports.push(stats);
        }
        self.waiting.remove(&key);
    }

    /// The worker on `node` is gone (its stream ended).
    pub fn gone(&mut self, node: NodeId) -> Vec<ToNode> {
        match self.key_of(node) {
            Some(key) => self.lose(key),
            None => Vec::new(),
        }
    }

    fn lose(&mut self, key: u32) -> Vec<ToNode> {
        self.waiting.remove(&key);
        let Some(frame) = self.frame.as_mut() else {
            self.workers.remove(&key);
            return Vec::new();
        };
        let lost = frame.lose(key);
        let out = match lost {
            Some(out) if out.is_empty() => {
                self.problems
                    .push("every worker of the frame was lost".into());
                self.frame = None;
                Vec::new()
            }
            Some(out) => self.out(out),
            None => Vec::new(),
        };
        self.workers.remove(&key);
        out
    }

    /// The coordinator's periodic work: workers silent too long are dropped, and reports of
    /// unreachable peers judged.
    pub fn tick(&mut self, now: Time) -> Vec<ToNode> {
        let mut out = Vec::new();
        let silent: Vec<u32> = self
            .workers
            .iter()
            .filter(|(_, e)| now.since(e.last_seen) > self.config.worker_timeout)
            .map(|(&k, _)| k)
            .collect();
        for key in silent {
            out.push(ToNode::Close(self.workers[&key].node));
            out.extend(self.lose(key));
        }
        let grace = accusation_grace(self.config.heartbeat);
        loop {
            let heard: BTreeSet<u32> = self
                .workers
                .iter()
                .filter(|(_, e)| now.since(e.last_seen) < grace)
                .map(|(&k, _)| k)
                .collect();
            let ids: BTreeMap<u32, String> = self
                .workers
                .iter()
                .map(|(&k, e)| (k, e.id.clone()))
                .collect();
            let Some(frame) = self.frame.as_mut() else {
                break;
            };
            let id_of = |k| ids.get(&k).cloned().unwrap_or_default();
            let Some(v) = frame.judge(now, grace, &heard, id_of) else {
                break;
            };
            if let Some(e) = self.workers.get(&v.drop) {
                out.push(ToNode::Close(e.node));
            }
            out.extend(self.lose(v.drop));
        }
        out
    }
}
