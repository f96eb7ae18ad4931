//! What a run is made of, counted as it goes: events by kind and messages by kind, logged
//! (`info`, target `rayfarm_sim`) every [`EVERY`] events and at the end. A long run shows
//! where it is in virtual time and which events fill it, so "slow" can be told apart from
//! "the modelled frame really has that many events" (README "Simulator"). Counting only: no
//! figure of a run depends on it.

use rayfarm_machine::Time;
use rayfarm_proto::{coordinator_message::Body, worker_message::Body as FromWorker};
use tracing::info;

use super::{Ev, Msg};
use crate::net::Network;

/// Events between two progress lines.
const EVERY: u64 = 1 << 20;

/// Counts by kind (see the module documentation).
#[derive(Default)]
pub(super) struct Traffic {
    /// Events popped, in all and by kind.
    events: u64,
    deliveries: u64,
    passes: u64,
    heartbeats: u64,
    ticks: u64,
    other_events: u64,
    /// Coordinator messages by body.
    plans: u64,
    holders: u64,
    /// Domain lines in those `Holders` (a worker applies each one).
    holder_lines: u64,
    other_control: u64,
    /// Worker messages to the coordinator by body.
    reports: u64,
    worker_heartbeats: u64,
    other_to_coordinator: u64,
    bundles: u64,
    acks: u64,
}

impl Traffic {
    /// Counts `ev`, popped at `now`; every [`EVERY`] events, logs where the run is.
    pub(super) fn popped(&mut self, now: Time, ev: &Ev, net: &Network, rounds: u64) {
        self.events += 1;
        match ev {
            Ev::Deliver { .. } | Ev::Received { .. } => self.deliveries += 1,
            Ev::PassDone { .. } | Ev::PassTaken { .. } => self.passes += 1,
            Ev::Heartbeat { .. } => self.heartbeats += 1,
            Ev::Tick { .. } | Ev::CoordTick => self.ticks += 1,
            _ => self.other_events += 1,
        }
        if self.events.is_multiple_of(EVERY) {
            self.log("progress", now, net, rounds);
        }
    }

    /// Counts a message put on the network.
    pub(super) fn sent(&mut self, msg: &Msg) {
        match msg {
            Msg::Control(m, _) => match &m.body {
                Some(Body::RoundPlan(p)) => {
                    self.plans += 1;
                    self.holder_lines += p.holders.len() as u64;
                }
                Some(Body::Holders(h)) => {
                    self.holders += 1;
                    self.holder_lines += h.holders.len() as u64;
                }
                _ => self.other_control += 1,
            },
            Msg::ToCoordinator(body, _) => match body {
                FromWorker::QueueReport(_) | FromWorker::FrameReport(_) => self.reports += 1,
                FromWorker::Heartbeat(_) => self.worker_heartbeats += 1,
                _ => self.other_to_coordinator += 1,
            },
            Msg::Bundle { .. } => self.bundles += 1,
            Msg::Ack { .. } => self.acks += 1,
            Msg::Register(..) | Msg::Closed(_) | Msg::StreamEnded(_) => {
                self.other_to_coordinator += 1
            }
        }
    }

    /// Logs the counts so far, `what` naming the moment.
    pub(super) fn log(&self, what: &str, now: Time, net: &Network, rounds: u64) {
        let virtual_s = now.0 as f64 / 1e9;
        info!(
            virtual_s = format!("{virtual_s:.3}"),
            events = self.events,
            deliveries = self.deliveries,
            passes = self.passes,
            heartbeats = self.heartbeats,
            ticks = self.ticks,
            other_events = self.other_events,
            messages = net.messages,
            rounds,
            plans = self.plans,
            holders = self.holders,
            holder_lines = self.holder_lines,
            other_control = self.other_control,
            reports = self.reports,
            worker_heartbeats = self.worker_heartbeats,
            other_to_coordinator = self.other_to_coordinator,
            bundles = self.bundles,
            acks = self.acks,
            "{what}"
        );
    }
}
