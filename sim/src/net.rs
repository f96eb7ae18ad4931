//! The simulated network: a message from one node to another arrives after the network's
//! latency plus its bytes over the sender's NIC bandwidth (a NIC sends one message at a time,
//! whatever its destination), in the order it was sent on that link (per-link FIFO, as over
//! one TCP stream). Faults add to
//! this: seeded jitter, extra delay on a node's links for a while, and partitions that hold a
//! link's messages until it heals.

use std::collections::BTreeMap;
use std::time::Duration;

use rayfarm_machine::Time;

use crate::faults::Rng;

/// A simulated node: 0 is the coordinator, workers count from 1.
pub type NodeId = usize;

/// The coordinator's node id.
pub const COORDINATOR: NodeId = 0;

/// What the network is like when nothing is wrong.
#[derive(Clone, Copy, Debug)]
pub struct LinkModel {
    /// One-way latency of a message.
    pub latency: Duration,
    /// Bytes per second each node's NIC sends.
    pub bytes_per_second: u64,
}

impl Default for LinkModel {
    /// A commodity 10 Gb/s Ethernet data-centre network: 100 us one way through its switches,
    /// 1.25 GB/s per NIC.
    fn default() -> Self {
        LinkModel {
            latency: Duration::from_micros(100),
            bytes_per_second: 1_250_000_000,
        }
    }
}

/// A span of virtual time, `[from, until)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Window {
    pub from: Time,
    pub until: Time,
}

impl Window {
    /// Whether `t` lies in it.
    pub fn contains(&self, t: Time) -> bool {
        self.from <= t && t < self.until
    }
}

/// The links between nodes and the faults on them.
pub struct Network {
    model: LinkModel,
    /// When each node's NIC is free to send its next message.
    free_at: BTreeMap<NodeId, Time>,
    /// When the last message on each directed link arrives (later ones never overtake it).
    last_arrival: BTreeMap<(NodeId, NodeId), Time>,
    /// The same for the packets sent beside the NIC's queue ([`Network::send_packet`]).
    last_packet: BTreeMap<(NodeId, NodeId), Time>,
    /// Links cut both ways for a while: what is sent meanwhile arrives after the heal.
    partitions: Vec<(NodeId, NodeId, Window)>,
    /// Extra delay on every message to or from a node sent in a window.
    delays: Vec<(NodeId, Window, Duration)>,
    /// Most extra delay of any message, drawn per message (none in a clean run).
    jitter: Duration,
    rng: Rng,
    /// Messages and bytes sent, for the statistics.
    pub messages: u64,
    pub bytes: u64,
}

impl Network {
    /// A network of `model` links; `jitter` and `rng` perturb each message's delay.
    pub fn new(model: LinkModel, jitter: Duration, rng: Rng) -> Self {
        Network {
            model,
            free_at: BTreeMap::new(),
            last_arrival: BTreeMap::new(),
            last_packet: BTreeMap::new(),
            partitions: Vec::new(),
            delays: Vec::new(),
            jitter,
            rng,
            messages: 0,
            bytes: 0,
        }
    }

    /// Cuts the link between `a` and `b` (both ways) during `window`.
    pub fn partition(&mut self, a: NodeId, b: NodeId, window: Window) {
        self.partitions.push((a, b, window));
    }

    /// Delays every message to or from `node` sent during `window` by `extra`.
    pub fn delay(&mut self, node: NodeId, window: Window, extra: Duration) {
        self.delays.push((node, window, extra));
    }

    /// Whether the link between `a` and `b` is cut at `t`.
    pub fn is_cut(&self, a: NodeId, b: NodeId, t: Time) -> bool {
        self.partitions
            .iter()
            .any(|&(x, y, w)| ((x, y) == (a, b) || (x, y) == (b, a)) && w.contains(t))
    }

    /// When a message of `bytes` sent from `from` to `to` at `now` arrives.
    pub fn arrival(&mut self, now: Time, from: NodeId, to: NodeId, bytes: usize) -> Time {
        self.send(now, from, to, bytes).1
    }

    fn transmit(&self, bytes: usize) -> Duration {
        Duration::from_nanos(
            (bytes as u128 * 1_000_000_000 / u128::from(self.model.bytes_per_second.max(1))) as u64,
        )
    }

    /// A message of `bytes` sent from `from` to `to` at `now`: when its NIC begins to send it,
    /// and when it arrives.
    pub fn send(&mut self, now: Time, from: NodeId, to: NodeId, bytes: usize) -> (Time, Time) {
        self.messages += 1;
        self.bytes += bytes as u64;
        let start = now.max(self.free_at.get(&from).copied().unwrap_or_default());
        let transmit = self.transmit(bytes);
        self.free_at.insert(from, start + transmit);
        let at = self.arrive(now, start + transmit, from, to);
        let link = (from, to);
        let at = at.max(self.last_arrival.get(&link).copied().unwrap_or_default());
        self.last_arrival.insert(link, at);
        (start, at)
    }

    /// A message of one packet (a peer's acknowledgement) sent from `from` to `to` at `now`
    /// on a connection of its own: it does not queue behind the bulk the NIC is sending for
    /// other connections (a NIC interleaves its connections' packets, so it waits one
    /// packet, whose time is left out), only behind the packets sent before it on its link.
    /// When it arrives.
    pub fn send_packet(&mut self, now: Time, from: NodeId, to: NodeId, bytes: usize) -> Time {
        self.messages += 1;
        self.bytes += bytes as u64;
        let transmit = self.transmit(bytes);
        // It takes its own bytes' time from the NIC's queue all the same.
        if let Some(free) = self.free_at.get_mut(&from).filter(|f| **f > now) {
            *free = *free + transmit;
        }
        let at = self.arrive(now, now + transmit, from, to);
        let link = (from, to);
        let at = at.max(self.last_packet.get(&link).copied().unwrap_or_default());
        self.last_packet.insert(link, at);
        at
    }

    /// When a message sent at `now` from `from` to `to`, off the NIC at `sent`, arrives: the
    /// latency, then the faults' jitter, delays and partitions.
    fn arrive(&mut self, now: Time, sent: Time, from: NodeId, to: NodeId) -> Time {
        let link = (from, to);
        let mut at = sent + self.model.latency;
        if !self.jitter.is_zero() {
            at = at + Duration::from_nanos(self.rng.below(self.jitter.as_nanos() as u64 + 1));
        }
        for &(node, window, extra) in &self.delays {
            if (node == from || node == to) && window.contains(now) {
                at = at + extra;
            }
        }
        for &(a, b, window) in &self.partitions {
            if ((a, b) == link || (b, a) == link) && window.contains(now) {
                at = at.max(window.until + self.model.latency);
            }
        }
        at
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn net() -> Network {
        Network::new(LinkModel::default(), Duration::ZERO, Rng::new(1))
    }

    #[test]
    fn a_message_takes_latency_plus_its_bytes_over_the_bandwidth() {
        let mut n = net();
        // 1.25 MB at 1.25 GB/s is 1 ms, plus 100 us.
        assert_eq!(n.arrival(Time(0), 1, 2, 1_250_000), Time(1_100_000));
    }

    #[test]
    fn a_node_sends_one_message_at_a_time_whatever_its_destination() {
        let mut n = net();
        // Two 1.25 MB messages to two nodes: the second leaves when the first is sent.
        assert_eq!(n.arrival(Time(0), 1, 2, 1_250_000), Time(1_100_000));
        assert_eq!(n.arrival(Time(0), 1, 3, 1_250_000), Time(2_100_000));
        // Another sender's NIC is free.
        assert_eq!(n.arrival(Time(0), 2, 3, 1_250_000), Time(1_100_000));
    }

    #[test]
    fn a_packet_slips_past_the_bulk_on_the_nic_and_keeps_its_order_among_packets() {
        let mut n = net();
        // 12.5 MB of bulk for node 2 keeps the NIC busy for 10 ms.
        assert_eq!(n.arrival(Time(0), 1, 2, 12_500_000), Time(10_100_000));
        // An acknowledgement to node 2 sent meanwhile arrives after the latency alone.
        let ack = n.send_packet(Time(1_000), 1, 2, 16);
        assert_eq!(ack, Time(101_012));
        // One sent later on the same link never overtakes it.
        n.delay(
            1,
            Window {
                from: Time(0),
                until: Time(2_000),
            },
            Duration::from_millis(5),
        );
        let delayed = n.send_packet(Time(1_500), 1, 2, 16);
        assert!(delayed > ack);
        assert!(n.send_packet(Time(3_000), 1, 2, 16) >= delayed);
        // The NIC still sends the packets' bytes: the next bulk leaves that much later.
        let (start, _) = n.send(Time(0), 1, 3, 0);
        assert_eq!(start, Time(10_000_000 + 3 * 12));
    }

    #[test]
    fn a_link_keeps_its_order_and_sends_one_message_at_a_time() {
        let mut n = net();
        n.delay(
            1,
            Window {
                from: Time(0),
                until: Time(10),
            },
            Duration::from_millis(5),
        );
        let first = n.arrival(Time(0), 1, 2, 0);
        let second = n.arrival(Time(20), 1, 2, 0);
        assert!(second >= first, "a later message overtook an earlier one");
        // Another link is not held up.
        assert_eq!(n.arrival(Time(20), 2, 1, 0), Time(100_020));
    }

    #[test]
    fn a_partition_holds_messages_until_it_heals() {
        let mut n = net();
        let w = Window {
            from: Time(0),
            until: Time(1_000_000),
        };
        n.partition(1, 2, w);
        assert!(n.is_cut(2, 1, Time(5)));
        assert_eq!(n.arrival(Time(5), 2, 1, 0), Time(1_100_000));
        assert!(!n.is_cut(1, 2, Time(1_000_000)));
    }
}
