//! The workers' side of the world: a worker's machine fed its events (control messages, peer
//! bundles, finished passes) and its actions carried out (messages, bundles with their
//! acknowledgements, passes on the real kernel, cache changes, reports), and a worker killed.

use std::sync::Arc;

use bytes::Bytes;
use rayfarm_core::bundler::Tier;
use rayfarm_core::wire::{self, BatchLimits};
use rayfarm_machine::worker::{self as machine, Action, Payload};
use rayfarm_proto::{self as proto, coordinator_message::Body, worker_message::Body as FromWorker};

use crate::calibrate::thread_cpu_ns;
use crate::net::{COORDINATOR, NodeId};

use super::{Ev, KEPT_BUNDLES, MeasuredBundle, Msg, RECONNECT, World};

impl World<'_> {
    pub(super) fn kill(&mut self, node: NodeId) {
        let Some(w) = self.worker_mut(node) else {
            return;
        };
        w.alive = false;
        let pass = w.pass_until;
        let in_flight = w.links.values().any(|l| !l.owed.is_empty());
        let conn = w.conn;
        // Its pass stops computing.
        if let Some(cores) = self.cores.as_mut() {
            cores.forget(self.now, node);
            self.check_cores_again();
        }
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

    pub(super) fn at_worker(&mut self, from: NodeId, to: NodeId, msg: Msg) {
        let now = self.now;
        if let Msg::Bundle { batches, seq, .. } = &msg {
            return self.receive_bundle(from, to, *seq, batches.iter().map(Bytes::len).sum(), msg);
        }
        let Some(w) = self.worker_mut(to) else { return };
        match msg {
            // What was sent on an older stream than the worker's is for nobody.
            Msg::Control(_, conn) | Msg::Closed(conn) if conn != w.conn => {}
            Msg::Control(m, _) if !matches!(m.body, Some(Body::StartFrame(_))) => {
                self.feed(to, machine::Event::SharedControl(m));
            }
            Msg::Control(m, _) => {
                if let Some(Body::StartFrame(start)) = Arc::unwrap_or_clone(m).body {
                    let opened = w.open(&start);
                    self.feed(to, machine::Event::FrameOpened { start, opened });
                }
            }
            Msg::Closed(_) => {
                w.disconnected = true;
                self.feed(to, machine::Event::Disconnected);
                // The shell reconnects; a worker sidelined for this frame sits it out.
                self.heap.push(now + RECONNECT, Ev::Reregister { node: to });
            }
            Msg::Ack { from: peer, seq } => {
                if let Some(link) = w.links.get_mut(&peer) {
                    while link.owed.front().is_some_and(|&(s, _)| s <= seq) {
                        link.owed.pop_front();
                    }
                }
            }
            Msg::Register(..)
            | Msg::ToCoordinator(..)
            | Msg::StreamEnded(_)
            | Msg::Bundle { .. } => {}
        }
    }

    /// A peer bundle from `from` has reached `to`. As the worker's peer service
    /// (`worker/src/peers.rs`, `exchange_bundles`) does, the task of the sender's stream
    /// decodes it after the bundles before it on that stream, for its receiving price, and
    /// acknowledges it once decoded; the engine takes it into the machine after what it is
    /// handling. So the acknowledgement waits for the stream's own bundles, never for the
    /// engine's backlog nor for the bundles other peers sent (a shell that did everything in
    /// one line missed deadlines the real worker keeps, and healthy peers were reported
    /// unresponsive). The machine's own queueing of the rays is part of the receiving price
    /// as calibrated, so the engine adds none.
    fn receive_bundle(&mut self, from: NodeId, to: NodeId, seq: u64, bytes: usize, msg: Msg) {
        let now = self.now;
        let cost = self.config.cost.bundle_receive(bytes);
        let Some(w) = self.worker(to) else { return };
        let ready = now.max(w.inbound.get(&from).copied().unwrap_or_default());
        let decoded = if cost.is_zero() {
            ready
        } else {
            self.steal(ready, cost)
        };
        let Some(w) = self.worker_mut(to) else { return };
        w.inbound.insert(from, decoded);
        // A worker stuck on its peer port takes in and acknowledges nothing from then on.
        if w.is_stuck(decoded) {
            return;
        }
        let me = w.address.clone();
        // Acknowledged once decoded; the engine takes it in after what it handles, after
        // the wake-ups that carry it there, and never before the sender's earlier bundles.
        let wake = self.wait(self.config.cost.bundle_take);
        let Some(w) = self.worker_mut(to) else { return };
        let earlier = w.taken_from.get(&from).copied().unwrap_or_default();
        let taken = (decoded.max(w.msg_free_at) + wake).max(earlier);
        w.taken_from.insert(from, taken);
        self.send_at(decoded, to, from, Msg::Ack { from: me, seq });
        if taken > now {
            self.heap.push(taken, Ev::Received { to, msg });
        } else {
            self.take_bundle(to, msg);
        }
    }

    /// A peer bundle the engine of `to` takes in: decoded and handed to the machine (with
    /// `measure`, the decoding's and the machine's CPU time recorded). It was acknowledged
    /// when its stream's task decoded it.
    pub(super) fn take_bundle(&mut self, to: NodeId, msg: Msg) {
        let Msg::Bundle {
            sender,
            job_id,
            tier,
            batches,
            ..
        } = msg
        else {
            return;
        };
        if self.worker(to).is_none() {
            return;
        }
        let measure = self.config.measure;
        let started = measure.then(thread_cpu_ns);
        let decoded = decode(tier, &batches);
        let decode_ns = started.map(|s| thread_cpu_ns().saturating_sub(s));
        match decoded {
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
        if let (Some(decode_ns), Some(handled_ns)) = (decode_ns, self.handled_ns.take()) {
            let kept = self.outcome.measured_bundles.len() < KEPT_BUNDLES;
            self.outcome.measured_bundles.push(MeasuredBundle {
                tier,
                bytes: batches.iter().map(Bytes::len).sum(),
                cpu_ns: decode_ns + handled_ns,
                batches: kept.then_some(batches),
            });
        }
    }

    /// Hands `event` to the machine of `node` and carries out its actions.
    pub(super) fn feed(&mut self, node: NodeId, event: machine::Event<machine::MemorySpill>) {
        let now = self.now;
        // Only the machine's own handling is timed: the actions it asks for (a pass among
        // them) are carried out below.
        let timed = self.config.measure
            && matches!(
                event,
                machine::Event::PeerBundle { .. } | machine::Event::PassFinished { .. }
            );
        let Some(w) = self.worker_mut(node) else {
            return;
        };
        let started = timed.then(thread_cpu_ns);
        // The machine's own logs name the simulated worker and the virtual time.
        let span = tracing::debug_span!("sim worker", node, virtual_us = now.0 / 1000);
        let actions = span.in_scope(|| w.machine.handle(now, event));
        let handled = started.map(|s| thread_cpu_ns().saturating_sub(s));
        let (queued, cap) = w.queued_bytes();
        let (early, early_cap) = (w.machine.early_bytes(), w.early_cap);
        self.handled_ns = handled;
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
                let bytes: usize = batches.iter().map(Bytes::len).sum();
                let send_cost = cost.bundle_send(bytes);
                let seq = w.next_bundle;
                w.next_bundle += 1;
                let sender = w.address.clone();
                // The engine hands it to the peer's link at once; the link times it from
                // there (`peers::run_link`) and sends it after the bundles it took before,
                // for its sending price, beside whatever the engine does next.
                let link = w.links.entry(peer.clone()).or_default();
                link.owed.push_back((seq, now));
                let ready = now.max(link.sending_until);
                self.heap.push(
                    now + ack_deadline,
                    Ev::AckDue {
                        node,
                        peer: peer.clone(),
                        seq,
                    },
                );
                let depart = if send_cost.is_zero() {
                    ready
                } else {
                    self.steal(ready, send_cost)
                };
                if let Some(link) = self.worker_mut(node).and_then(|w| w.links.get_mut(&peer)) {
                    link.sending_until = depart;
                }
                if let Some(to) = self.node_of(&peer) {
                    self.send_at(
                        depart,
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
                // A tracing thread takes it up, then its loads go on the node's line, then
                // its computing on a core.
                let wait = self.wait(cost.pass_start);
                let Some(w) = self.workers.get_mut(node).and_then(Option::as_mut) else {
                    return;
                };
                let start = now + wait;
                let run = w.run_pass(start, &job_id, work, &cost, &mut self.storage, measure);
                let loaded_at = start + run.load_time;
                let work = run.took.saturating_sub(run.load_time);
                self.outcome.time.thread_wait += wait;
                self.outcome.time.loading += run.load_time;
                self.outcome.time.computing += work;
                if let Some(w) = self.worker_mut(node) {
                    w.pass_until = Some((loaded_at + work, loaded_at));
                }
                self.outcome.loads += run.loads;
                self.compute(node, loaded_at, work, Ev::PassDone { node, job_id, run });
            }
            Action::Prefetch {
                job_id,
                domain,
                keep,
            } => {
                let keep = keep.into_iter().collect();
                let Some(w) = self.workers.get_mut(node).and_then(Option::as_mut) else {
                    return;
                };
                // Its bytes come over the node's line to the storage, after its other loads.
                let (pending, took) = w.begin_prefetch(now, domain, &keep, &mut self.storage);
                self.outcome.loads += u64::from(pending.is_some());
                self.heap.push(
                    now + took,
                    super::Ev::PrefetchDone {
                        node,
                        job_id,
                        domain,
                        keep,
                        pending,
                    },
                );
            }
            Action::Evict(domains) => w.evict(&domains),
            Action::Pin(domains) => w.pin(domains),
            Action::FrameEnded { job_id, mut stats } => {
                stats.cache = w.cache_counters();
                stats.threads = cost.threads as usize;
                let (migrated, passes) = (stats.rays_sent, stats.passes);
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
                self.outcome.passes += passes;
                self.outcome.time.add_frame(&stats);
            }
        }
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
