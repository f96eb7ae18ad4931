//! Workers: registration, their messages (queue reports, tile results, frame reports,
//! accusations), their loss, and what the cluster status shows of them.

use super::*;
use rayfarm_machine::coordinator::job_of_frame;
use rayfarm_node::identity::PeerIdentity;
use rayfarm_node::metrics;

impl Coordinator {
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
                    domain_loads: w.heartbeat.domain_loads,
                    ray_segments: w.heartbeat.ray_segments,
                    queue_bytes: w.heartbeat.queue_bytes,
                    spill_bytes: w.heartbeat.spill_bytes,
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

    /// The latest workers dropped, oldest first.
    pub fn lost_workers(&self) -> Vec<LostWorker> {
        self.lock().lost.iter().cloned().collect()
    }

    /// Registers a worker whose messages go to `tx`; returns its key. `certified`, the names
    /// of its client certificate under mutual TLS, must name its id and its address's host.
    pub fn register(
        self: &Arc<Self>,
        r: &proto::Register,
        certified: Option<&PeerIdentity>,
        tx: WorkerTx,
    ) -> Result<u32, Status> {
        rayfarm_node::bounds::check_field("worker_id", &r.worker_id)?;
        rayfarm_node::bounds::check_field("peer_address", &r.peer_address)?;
        if let Some(id) = certified
            && let Err(refused) = id.check_registration(&r.worker_id, &r.peer_address)
        {
            warn!(
                worker = %rayfarm_node::bounds::shown(&r.worker_id),
                certificate = %id.name,
                "registration refused: {}",
                refused.message()
            );
            return Err(refused);
        }
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
                heartbeat: proto::Heartbeat::default(),
                left_out: String::new(),
            },
        );
        info!(worker = %r.worker_id, key, peer = %r.peer_address, cache_bytes = r.cache_bytes, threads = r.threads, "worker attached");
        let member = Member::new(r.peer_address.clone(), r.cache_bytes);
        if let Some(frame) = st.running.as_mut() {
            let Some(out) = frame.admit(key, &r.worker_id, member) else {
                info!(job = %frame.job_id, worker = %r.worker_id, "worker sits out the running frame: a peer could not reach it");
                return Ok(key);
            };
            info!(job = %frame.job_id, round = frame.round, "worker joins the running frame");
            send(&mut st, out);
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
            FromWorker::Heartbeat(h) => worker.heartbeat = h,
            FromWorker::QueueReport(r) => {
                worker.last_report = Some(r.clone());
                let out = match st.running.as_mut() {
                    Some(f) if f.frame_id() == r.job_id => {
                        let (round, planning) = (f.round, Instant::now());
                        let out = f.report(key, r);
                        count_rounds(f, round, planning);
                        out
                    }
                    _ => Vec::new(),
                };
                send(&mut st, out);
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
                        frame.accusations.add(key, k, now(), &p.reason);
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
    pub(super) fn tile_results(
        self: &Arc<Self>,
        st: &mut State,
        key: u32,
        r: proto::TileResults,
    ) -> Option<String> {
        let frame = st.running.as_mut().filter(|f| f.frame_id() == r.job_id)?;
        let (committed, refused) = frame.results(key, r);
        metrics::coordinator()
            .tiles_committed
            .inc_by(committed.len() as u64);
        if let Err(e) = frame.write_tiles(&committed) {
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
                frame.refuse(worker);
            }
            return Some(format!("impossible tile results: {e}"));
        }
        if frame.ledger.is_complete() && frame.has_next_subframe() {
            self.next_subframe(st);
        } else if frame.ledger.is_complete() {
            self.complete(st);
        } else if let Some(f) = st.running.as_ref() {
            publish_progress(st, f);
        }
        None
    }

    pub(super) fn frame_report(self: &Arc<Self>, st: &mut State, key: u32, r: proto::FrameReport) {
        if !r.error.is_empty() {
            if st.running.as_ref().is_none_or(|f| f.frame_id() != r.job_id) {
                return;
            }
            if r.declined {
                return self.declined(st, key, job_of_frame(&r.job_id), &r.error);
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
    pub(super) fn declined(self: &Arc<Self>, st: &mut State, key: u32, job_id: &str, reason: &str) {
        warn!(job = %job_id, reason, "worker left out of the frame");
        if let Some(w) = st.workers.get_mut(&key) {
            w.left_out = format!("job {job_id}: {reason}");
        }
        let Some(frame) = st.running.as_mut() else {
            return;
        };
        frame.declined.push(reason.to_string());
        let (round, planning) = (frame.round, Instant::now());
        let lost = frame.lose(key);
        count_rounds(frame, round, planning);
        let Some(out) = lost else {
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
        metrics::coordinator().workers_lost.inc();
        st.lost.push_back(LostWorker {
            worker_id: worker.id.clone(),
            peer_address: worker.peer_address.clone(),
            lost_unix_ms: unix_ms(),
            reason: why.to_string(),
        });
        if st.lost.len() > KEPT_LOST_WORKERS {
            st.lost.pop_front();
        }
        for fin in st.finishing.values_mut() {
            fin.waiting.remove(&key);
            if fin.waiting.is_empty()
                && let Some(done) = fin.done.take()
            {
                let _ = done.send(());
            }
        }
        let lost = st.running.as_mut().and_then(|f| {
            let (round, planning) = (f.round, Instant::now());
            let lost = f.lose(key);
            count_rounds(f, round, planning);
            lost
        });
        let Some(out) = lost else {
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
                if let Some(job) = st.jobs.get_mut(&frame.job_id) {
                    job.epoch_floor = frame.epoch_floor();
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
        send(&mut st, out);
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
    /// [`rayfarm_machine::coordinator::accusations`]); it sits out the rest of the frame.
    pub(super) fn judge_accusations(&self) -> Option<(u32, String)> {
        let grace = accusation_grace(self.config.heartbeat);
        let mut st = self.lock();
        // Members the coordinator hears from itself: one peer's word alone does not drop them.
        let heard: BTreeSet<u32> = st
            .running
            .as_ref()?
            .members()
            .filter(|k| {
                st.workers
                    .get(k)
                    .is_some_and(|w| w.last_seen.elapsed() < grace)
            })
            .collect();
        let ids: BTreeMap<u32, String> =
            st.workers.iter().map(|(&k, w)| (k, w.id.clone())).collect();
        let id_of = |k| ids.get(&k).cloned().unwrap_or_default();
        let v = st.running.as_mut()?.judge(now(), grace, &heard, id_of)?;
        let (accused, accuser) = (id_of(v.accused), id_of(v.accuser));
        let why = format!(
            "broken links to {} peers; first report: {accused} unresponsive to worker \
             {accuser}: {}",
            v.links, v.reason
        );
        Some((v.drop, why))
    }
}

/// Counts the rounds `frame` planned since it was at `round`, and the time since `planning`
/// as the time planning took (when it planned).
fn count_rounds(frame: &RunningFrame, round: u64, planning: Instant) {
    if frame.round > round {
        let m = metrics::coordinator();
        m.rounds.inc_by(frame.round - round);
        m.planning_seconds.observe(planning.elapsed().as_secs_f64());
    }
}
