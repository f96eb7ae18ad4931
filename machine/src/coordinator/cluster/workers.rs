//! Workers: registration and its refusals, their messages (heartbeats, queue reports, tile
//! results, frame reports, accusations), their loss, and the periodic tick that drops the
//! silent and judges accusations.

use std::sync::Arc;
use tracing::{error, info, warn};

use super::*;
use crate::coordinator::frame::Member;
use crate::coordinator::frame::lifecycle::accusation_grace;
use crate::coordinator::frame::subframes::job_of_frame;
use rayfarm_proto::{PROTOCOL_VERSION, coordinator_message::Body};

/// Why a registration is refused.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Refusal {
    /// It speaks another protocol version (the worker's).
    Protocol(u32),
    /// Its id or peer address is empty.
    Incomplete,
    ShuttingDown,
    /// A worker of this id is attached.
    DuplicateId(String),
    /// A worker at this peer address is attached: it would take that worker's rays.
    DuplicateAddress(String),
}

impl std::fmt::Display for Refusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Refusal::Protocol(v) => write!(
                f,
                "worker speaks protocol {v}, the coordinator {PROTOCOL_VERSION}"
            ),
            Refusal::Incomplete => write!(f, "worker id and peer address are required"),
            Refusal::ShuttingDown => write!(f, "the coordinator is shutting down"),
            Refusal::DuplicateId(id) => write!(f, "a worker called {id} is already attached"),
            Refusal::DuplicateAddress(a) => {
                write!(f, "a worker at peer address {a} is already attached")
            }
        }
    }
}

impl Coordinator {
    /// Registers a worker at `now`: its key, and what follows (its Registered message, and
    /// its place in the running frame or the start of a queued job).
    pub fn register(
        &mut self,
        now: Time,
        r: &proto::Register,
    ) -> Result<(u32, Vec<Action>), Refusal> {
        if r.protocol_version != PROTOCOL_VERSION {
            return Err(Refusal::Protocol(r.protocol_version));
        }
        if r.worker_id.is_empty() || r.peer_address.is_empty() {
            return Err(Refusal::Incomplete);
        }
        if self.stopping {
            return Err(Refusal::ShuttingDown);
        }
        if self.workers.values().any(|w| w.id == r.worker_id) {
            return Err(Refusal::DuplicateId(r.worker_id.clone()));
        }
        // A worker that restarted on the same address gets in once its old entry is reaped.
        if self
            .workers
            .values()
            .any(|w| w.peer_address == r.peer_address)
        {
            return Err(Refusal::DuplicateAddress(r.peer_address.clone()));
        }
        let key = self.next_key;
        self.next_key += 1;
        let registered = Body::Registered(proto::Registered {
            heartbeat_ms: self.config.heartbeat.as_millis() as u32,
        });
        // Straight out, never held: it is the stream's first message.
        let mut out = vec![Action::Send((
            key,
            Arc::new(proto::CoordinatorMessage {
                body: Some(registered),
            }),
        ))];
        self.workers.insert(
            key,
            Registered {
                id: r.worker_id.clone(),
                peer_address: r.peer_address.clone(),
                cache_bytes: r.cache_bytes,
                last_seen: now,
                last_report: ReportedQueues::default(),
                heartbeat: proto::Heartbeat::default(),
                left_out: String::new(),
            },
        );
        info!(worker = %r.worker_id, key, peer = %r.peer_address, cache_bytes = r.cache_bytes, threads = r.threads, "worker attached");
        let member = Member::new(r.peer_address.clone(), r.cache_bytes);
        if let Some(frame) = self.running.as_mut() {
            let Some(join) = frame.admit(key, &r.worker_id, member) else {
                info!(job = %frame.job_id, worker = %r.worker_id, "worker sits out the running frame: a peer could not reach it");
                return Ok((key, out));
            };
            info!(job = %frame.job_id, round = frame.round, "worker joins the running frame");
            self.send(join, &mut out);
        } else {
            self.try_start(now, &mut out);
        }
        Ok((key, out))
    }

    pub(super) fn worker_message(
        &mut self,
        now: Time,
        key: u32,
        body: FromWorker,
        out: &mut Vec<Action>,
    ) {
        let Some(worker) = self.workers.get_mut(&key) else {
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
        worker.last_seen = now;
        match body {
            FromWorker::Register(_) => warn!(key, "worker registered twice; ignored"),
            FromWorker::Heartbeat(h) => worker.heartbeat = h,
            FromWorker::QueueReport(r) => {
                let read = match queue_report::read(&r) {
                    Ok(read) => read,
                    Err(e) => return self.refuse(now, key, "queue report", &e, out),
                };
                worker.last_report.take(&r, &read);
                if let Some(f) = self.running.as_mut().filter(|f| f.frame_id() == r.job_id) {
                    // The round it asks for is planned once the inputs at hand are taken
                    // (`Coordinator::plan`), with every other report among them.
                    match f.take_report(key, r, read) {
                        Ok(messages) => self.send(messages, out),
                        Err(e) => return self.refuse(now, key, "queue report", &e, out),
                    }
                    self.reports_taken = true;
                }
            }
            FromWorker::TasksShared(t) => {
                if let Some(f) = self.running.as_mut().filter(|f| f.frame_id() == t.job_id) {
                    let requests = f.tasks_shared(key, &t);
                    self.send(requests, out);
                }
            }
            FromWorker::TileResults(r) => self.tile_results(now, key, r, out),
            FromWorker::FrameReport(r) => self.frame_report(now, key, r, out),
            FromWorker::PeerUnresponsive(p) => {
                let reporter = worker.id.clone();
                let silent = self
                    .workers
                    .iter()
                    .find(|(_, w)| w.peer_address == p.peer_address)
                    .map(|(&k, _)| k);
                // Judged after a grace period, with the other side's reports (`accusations`).
                match (silent, self.running.as_mut()) {
                    (Some(k), Some(frame))
                        if frame.members().any(|m| m == k) && frame.members().any(|m| m == key) =>
                    {
                        warn!(worker = %reporter, peer = %p.peer_address, reason = %p.reason, "a worker reports a peer unreachable");
                        frame.accusations.add(key, k, now, &p.reason);
                    }
                    _ => {
                        info!(worker = %reporter, "unresponsive peer is no member of a running frame: ignored")
                    }
                }
            }
        }
    }

    /// Commits a worker's tile results. If they cannot be right (a forged or broken worker)
    /// nothing of them is counted, the worker is dropped and sits out the frame, and the
    /// frame goes on without it, so its image is still the one `render --local` makes.
    fn tile_results(&mut self, now: Time, key: u32, r: proto::TileResults, out: &mut Vec<Action>) {
        let Some(frame) = self.running.as_mut().filter(|f| f.frame_id() == r.job_id) else {
            return;
        };
        let (committed, refused) = frame.results(key, r);
        if !committed.is_empty() {
            out.push(Action::Tally(Tally::TilesCommitted(committed.len() as u64)));
            out.push(Action::WriteTiles {
                job_id: frame.job_id.clone(),
                tiles: committed,
                samples: frame.samples().count,
                subframes_done: frame.subframes().0,
            });
        }
        if let Some(e) = refused {
            return self.refuse(now, key, "tile results", &e, out);
        }
        if frame.ledger.is_complete() && frame.has_next_subframe() {
            self.next_subframe(now, out);
        } else if frame.ledger.is_complete() {
            self.complete(now, out);
        } else {
            self.publish_progress(now, out);
        }
    }

    /// Drops worker `key`, which sent `what` that cannot be right (`why`): it is sidelined
    /// from the running frame and its tiles are dealt again.
    fn refuse(&mut self, now: Time, key: u32, what: &str, why: &str, out: &mut Vec<Action>) {
        let worker = self
            .workers
            .get(&key)
            .map(|w| w.id.clone())
            .unwrap_or_default();
        error!(worker = %worker, error = %why, "worker sent impossible {what}: dropped, its tiles re-dealt");
        if let Some(frame) = self.running.as_mut() {
            frame.refuse(worker);
        }
        let why = format!("impossible {what}: {why}");
        self.lose(now, key, &why.clone(), Closing::Refused(why), out);
    }

    fn frame_report(&mut self, now: Time, key: u32, r: proto::FrameReport, out: &mut Vec<Action>) {
        if !r.error.is_empty() {
            if self
                .running
                .as_ref()
                .is_none_or(|f| f.frame_id() != r.job_id)
            {
                return;
            }
            if r.declined {
                return self.declined(now, key, job_of_frame(&r.job_id), &r.error, out);
            }
            return self.fail_running(now, &r.error, out);
        }
        if let Some(w) = self.workers.get_mut(&key) {
            w.left_out.clear();
        }
        let Some(fin) = self.finishing.get_mut(&r.job_id) else {
            return;
        };
        match serde_json::from_str::<WorkerFrameStats>(&r.stats_json) {
            Ok(stats) => fin.reports.push(stats),
            Err(e) => warn!(key, error = %e, "unreadable worker statistics"),
        }
        fin.waiting.remove(&key);
        self.finish_ready(now, out);
    }

    /// A worker cannot take part in the running frame (`reason` names it and why): it is left
    /// out of this frame as if lost, but stays registered for the next jobs. The job fails
    /// only when no member is left, with every member's reason.
    fn declined(&mut self, now: Time, key: u32, job_id: &str, reason: &str, out: &mut Vec<Action>) {
        warn!(job = %job_id, reason, "worker left out of the frame");
        if let Some(w) = self.workers.get_mut(&key) {
            w.left_out = format!("job {job_id}: {reason}");
        }
        let Some(frame) = self.running.as_mut() else {
            return;
        };
        frame.declined.push(reason.to_string());
        let before = frame.planning;
        let lost = frame.lose(key);
        tally_rounds(frame, &before, out);
        let Some(rest) = lost else {
            return;
        };
        if rest.is_empty() {
            let msg = format!(
                "no worker can take part in the frame: {}",
                frame.declined.join("; ")
            );
            return self.fail_running(now, &msg, out);
        }
        self.send_bumped(rest, out);
    }

    /// Forgets worker `key` (its stream is closed with `closing`): the running frame deals
    /// its tiles again, or the job is re-queued if it was the last member, or fails if this
    /// worker was lost `max_attempts` times during it.
    pub(super) fn lose(
        &mut self,
        now: Time,
        key: u32,
        why: &str,
        closing: Closing,
        out: &mut Vec<Action>,
    ) {
        let Some(worker) = self.workers.remove(&key) else {
            return;
        };
        warn!(worker = %worker.id, why, "worker lost");
        out.push(Action::Close { key, closing });
        out.push(Action::Tally(Tally::WorkerLost));
        self.lost.push_back(LostWorker {
            worker_id: worker.id.clone(),
            peer_address: worker.peer_address.clone(),
            lost_unix_ms: self.unix_ms(now),
            reason: why.to_string(),
        });
        if self.lost.len() > KEPT_LOST_WORKERS {
            self.lost.pop_front();
        }
        for fin in self.finishing.values_mut() {
            fin.waiting.remove(&key);
        }
        self.finish_ready(now, out);
        let Some(frame) = self.running.as_mut() else {
            return;
        };
        let before = frame.planning;
        let lost = frame.lose(key);
        tally_rounds(frame, &before, out);
        let Some(rest) = lost else {
            return;
        };
        let max = self.config.max_attempts;
        let job_id = frame.job_id.clone();
        let losses = self.jobs.get_mut(&job_id).map_or(0, |j| {
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
            return self.fail_running(now, &reason, out);
        }
        if rest.is_empty() {
            return self.requeue_running(now, out);
        }
        info!(worker = %worker.id, "re-issuing the unfinished tiles on the remaining workers");
        self.send_bumped(rest, out);
    }

    /// Drops workers silent longer than the timeout, judges reports of unreachable peers,
    /// and writes finished frames whose reports are overdue.
    pub(super) fn tick(&mut self, now: Time, out: &mut Vec<Action>) {
        let timeout = self.config.worker_timeout;
        let silent: Vec<u32> = self
            .workers
            .iter()
            .filter(|(_, w)| now.since(w.last_seen) > timeout)
            .map(|(&k, _)| k)
            .collect();
        for key in silent {
            self.lose(now, key, "no heartbeat", Closing::NoHeartbeat, out);
        }
        while let Some((key, why)) = self.judge_accusations(now) {
            // Dropping it closes its control stream: if it is only slow or cut off, it comes
            // back through a fresh registration and sits out the rest of this frame.
            self.lose(now, key, &why, Closing::Dropped, out);
        }
        self.finish_ready(now, out);
    }

    /// The member to drop for its peers' reports, if their grace period is over (see
    /// [`crate::coordinator::accusations`]); it sits out the rest of the frame.
    fn judge_accusations(&mut self, now: Time) -> Option<(u32, String)> {
        let grace = accusation_grace(self.config.heartbeat);
        let frame = self.running.as_mut()?;
        // Nothing to judge (nearly every tick): the sets below cost a walk of every member,
        // which at 1,024 workers and four ticks a heartbeat was a few percent of a simulation.
        if frame.accusations.is_empty() {
            return None;
        }
        // Members the coordinator hears from itself: one peer's word alone does not drop them.
        let heard: BTreeSet<u32> = frame
            .members()
            .filter(|k| {
                self.workers
                    .get(k)
                    .is_some_and(|w| now.since(w.last_seen) < grace)
            })
            .collect();
        let workers = &self.workers;
        let id_of = |k| workers.get(&k).map(|w| w.id.clone()).unwrap_or_default();
        let v = frame.judge(now, grace, &heard, id_of)?;
        let (accused, accuser) = (id_of(v.accused), id_of(v.accuser));
        let why = format!(
            "broken links to {} peers; first report: {accused} unresponsive to worker \
             {accuser}: {}",
            v.links, v.reason
        );
        Some((v.drop, why))
    }
}

/// Tallies the rounds `frame` planned since its planning was counted at `before`.
pub(super) fn tally_rounds(frame: &RunningFrame, before: &PlanningWork, out: &mut Vec<Action>) {
    let work = frame.planning.since(before);
    if work.rounds > 0 || work.queues > 0 || work.reports > 0 {
        out.push(Action::Tally(Tally::Rounds(work)));
    }
}
