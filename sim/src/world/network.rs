//! Messages on the simulated network: sized as encoded, sent when their sender is done with
//! them (a worker's NIC is not held before), acknowledgements as single packets beside bulk.

use std::sync::Arc;

use bytes::Bytes;
use prost::Message;
use rayfarm_machine::Time;
use rayfarm_proto as proto;

use crate::net::{COORDINATOR, NodeId};

use super::{Ev, Msg, World};

impl World<'_> {
    pub(super) fn send(&mut self, from: NodeId, to: NodeId, msg: Msg) {
        self.send_at(self.now, from, to, msg);
    }

    /// Sends `msg` when its sender is done with it at `depart` (not before now).
    pub(super) fn send_at(&mut self, depart: Time, from: NodeId, to: NodeId, msg: Msg) {
        if from != COORDINATOR && depart > self.now {
            // A worker's NIC is not held for it until it is ready (`Ev::Depart`).
            self.heap.push(depart, Ev::Depart { from, to, msg });
            return;
        }
        self.transmit(depart, from, to, msg);
    }

    /// The encoded size of the coordinator's message `m`.
    fn control_size(&mut self, m: &Arc<proto::CoordinatorMessage>) -> usize {
        if let Some((last, size)) = &self.control_size
            && std::ptr::eq(last.as_ptr(), Arc::as_ptr(m))
        {
            return *size;
        }
        let size = m.encoded_len();
        self.control_size = Some((Arc::downgrade(m), size));
        size
    }

    /// Puts `msg` on the network.
    pub(super) fn transmit(&mut self, depart: Time, from: NodeId, to: NodeId, msg: Msg) {
        let bytes = match &msg {
            Msg::Register(r, _) => r.encoded_len(),
            // A WorkerMessage is its body alone: the oneof's size, key included.
            Msg::ToCoordinator(b, _) => b.encoded_len(),
            Msg::Control(m, _) => self.control_size(m),
            Msg::Bundle { batches, .. } => batches.iter().map(Bytes::len).sum::<usize>() + 64,
            Msg::Closed(_) | Msg::StreamEnded(_) | Msg::Ack { .. } => 16,
        };
        if let Msg::Bundle { .. } = msg {
            self.outcome.peer_bytes += bytes as u64;
        }
        self.traffic.sent(&msg);
        if let Msg::Ack { .. } = msg {
            let at = self.net.send_packet(depart.max(self.now), from, to, bytes);
            self.heap.push(at, Ev::Deliver { from, to, msg });
            return;
        }
        let (_, at) = self.net.send(depart.max(self.now), from, to, bytes);
        self.heap.push(at, Ev::Deliver { from, to, msg });
    }
}
