//! Workers as the shell sees them: registration (the fields' bounds and the certificate's
//! names checked here, the rest by the machine), their messages and the end of their
//! streams handed to the machine, the periodic tick, and what the cluster status shows.

use rayfarm_machine::coordinator::cluster::Refusal;
use rayfarm_node::bounds::{check_field, shown};
use rayfarm_node::identity::PeerIdentity;

use super::*;

impl Coordinator {
    /// Workers, their resident domains and queues.
    pub fn status(&self) -> proto::GetClusterStatusResponse {
        let st = self.lock();
        let at = now();
        let running = st.machine.running();
        proto::GetClusterStatusResponse {
            workers: st
                .machine
                .workers()
                .map(|(_, w)| proto::WorkerStatus {
                    worker_id: w.id.clone(),
                    peer_address: w.peer_address.clone(),
                    resident_domains: ascending(&w.last_report.resident_domains),
                    queued_rays: w.last_report.queued_rays.iter().copied().collect(),
                    last_seen_ms: at.since(w.last_seen).as_millis() as u64,
                    left_out: w.left_out.clone(),
                    domain_loads: w.heartbeat.domain_loads,
                    ray_segments: w.heartbeat.ray_segments,
                    queue_bytes: w.heartbeat.queue_bytes,
                    spill_bytes: w.heartbeat.spill_bytes,
                })
                .collect(),
            running_job_id: running.map(|f| f.job_id.clone()).unwrap_or_default(),
            round: running.map_or(0, |f| f.round),
        }
    }

    /// The latest workers dropped, oldest first.
    pub fn lost_workers(&self) -> Vec<LostWorker> {
        self.lock()
            .machine
            .lost_workers()
            .map(|l| LostWorker {
                worker_id: l.worker_id.clone(),
                peer_address: l.peer_address.clone(),
                lost_unix_ms: l.lost_unix_ms,
                reason: l.reason.clone(),
            })
            .collect()
    }

    /// Registers a worker whose messages go to `tx`; returns its key. `certified`, the names
    /// of its client certificate under mutual TLS, must name its id and its address's host.
    pub fn register(
        self: &Arc<Self>,
        r: &proto::Register,
        certified: Option<&PeerIdentity>,
        tx: WorkerTx,
    ) -> Result<u32, Status> {
        check_field("worker_id", &r.worker_id)?;
        check_field("peer_address", &r.peer_address)?;
        if let Some(id) = certified
            && let Err(refused) = id.check_registration(&r.worker_id, &r.peer_address)
        {
            warn!(
                worker = %shown(&r.worker_id),
                certificate = %id.name,
                "registration refused: {}",
                refused.message()
            );
            return Err(refused);
        }
        let began = Instant::now();
        let mut st = self.lock();
        let (key, actions) = st.machine.register(now(), r).map_err(|refusal| {
            let message = refusal.to_string();
            match refusal {
                Refusal::Protocol(_) => Status::failed_precondition(message),
                Refusal::Incomplete => Status::invalid_argument(message),
                Refusal::ShuttingDown => Status::unavailable(SHUTTING_DOWN),
                Refusal::DuplicateId(_) | Refusal::DuplicateAddress(_) => {
                    Status::already_exists(message)
                }
            }
        })?;
        st.senders.insert(key, tx);
        self.carry_out(&mut st, actions, began);
        Ok(key)
    }

    /// Handles one message of a registered worker.
    pub fn worker_message(self: &Arc<Self>, key: u32, mut body: FromWorker) {
        if let FromWorker::PeerUnresponsive(p) = &mut body {
            // Logged and kept by the machine: at most a field's bounds of either.
            p.peer_address = shown(&p.peer_address).to_string();
            p.reason = shown(&p.reason).to_string();
        }
        let mut st = self.lock();
        self.feed(&mut st, Input::WorkerMessage { key, body });
    }

    /// Forgets a worker whose stream ended.
    pub fn worker_gone(self: &Arc<Self>, key: u32, why: &str) {
        let mut st = self.lock();
        let why = why.to_string();
        self.feed(&mut st, Input::WorkerGone { key, why });
    }

    /// The periodic work: drops workers that have been silent longer than the timeout,
    /// judges reports of unreachable peers, and writes finished frames whose workers'
    /// statistics are overdue. Returns when the machine next has a deadline, if any.
    pub fn tick(self: &Arc<Self>) -> Option<Duration> {
        let mut st = self.lock();
        self.feed(&mut st, Input::Tick);
        st.machine.next_deadline().map(|t| t.since(now()))
    }
}

/// A report's resident domains (in the worker's order of use) as the status lists them.
fn ascending(by_use: &[u32]) -> Vec<u32> {
    let mut domains = by_use.to_vec();
    domains.sort_unstable();
    domains.dedup();
    domains
}
