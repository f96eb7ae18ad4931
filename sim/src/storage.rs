//! The shared storage every worker loads its domains from: one resource of finite aggregate
//! bandwidth that every reader shares, as a parallel file system gives, and optionally a cap
//! per node (its link to the storage). A read of a pass's domains starts when the storage is
//! free (reads are served one after another, first come first served, so the storage never
//! delivers more than its aggregate bandwidth), holds it for its bytes over the aggregate
//! bandwidth, and ends no sooner than its bytes over the node's cap; every domain opened adds
//! the storage's latency. A domain may be charged at a stated virtual size instead of its
//! bytes on this machine, so a small scene stands for a large one.

use std::time::Duration;

use rayfarm_machine::Time;

/// What the storage is like.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StorageModel {
    /// Fixed cost of opening one domain (a metadata round trip).
    pub latency: Duration,
    /// Bytes per second the storage delivers to all readers together.
    pub aggregate_bytes_per_second: u64,
    /// Most bytes per second one node reads at, if capped.
    pub node_bytes_per_second: Option<u64>,
    /// Every domain load is charged this many bytes instead of the domain's own.
    pub charge_domain_bytes: Option<u64>,
}

impl Default for StorageModel {
    /// A commodity parallel file system: 10 GB/s for the whole cluster (a few storage
    /// servers), each node on a 10 Gb/s link (1.25 GB/s), 1 ms to open a file.
    fn default() -> Self {
        StorageModel {
            latency: Duration::from_millis(1),
            aggregate_bytes_per_second: 10_000_000_000,
            node_bytes_per_second: Some(1_250_000_000),
            charge_domain_bytes: None,
        }
    }
}

/// `bytes` at `rate` bytes per second.
fn transfer(bytes: u64, rate: u64) -> Duration {
    Duration::from_nanos((u128::from(bytes) * 1_000_000_000 / u128::from(rate.max(1))) as u64)
}

/// The storage's state: when it is free for the next read. See the module documentation.
#[derive(Debug)]
pub struct SharedStorage {
    model: StorageModel,
    free_at: Time,
    /// Bytes charged so far, for the statistics.
    pub bytes: u64,
}

impl SharedStorage {
    pub fn new(model: StorageModel) -> Self {
        SharedStorage {
            model,
            free_at: Time(0),
            bytes: 0,
        }
    }

    /// A node asks at `now` for `loads` domains of `bytes` bytes on this machine: how long
    /// until they are all read.
    pub fn read(&mut self, now: Time, loads: u64, bytes: u64) -> Duration {
        if loads == 0 {
            return Duration::ZERO;
        }
        let m = &self.model;
        let bytes = m.charge_domain_bytes.map_or(bytes, |b| b * loads);
        self.bytes += bytes;
        let start = now.max(self.free_at);
        self.free_at = start + transfer(bytes, m.aggregate_bytes_per_second);
        let own = m
            .node_bytes_per_second
            .map_or(Duration::ZERO, |r| transfer(bytes, r));
        let done = self.free_at.max(now + own) + m.latency * loads as u32;
        done.since(now)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn storage(node: Option<u64>, charge: Option<u64>) -> SharedStorage {
        SharedStorage::new(StorageModel {
            latency: Duration::from_millis(1),
            aggregate_bytes_per_second: 1_000_000_000,
            node_bytes_per_second: node,
            charge_domain_bytes: charge,
        })
    }

    #[test]
    fn readers_share_the_aggregate_bandwidth() {
        let mut s = storage(None, None);
        // 100 MB at 1 GB/s is 100 ms, plus 1 ms to open the domain.
        assert_eq!(s.read(Time(0), 1, 100_000_000), Duration::from_millis(101));
        // A second reader at the same instant waits for the first.
        assert_eq!(s.read(Time(0), 1, 100_000_000), Duration::from_millis(201));
        // Nothing to read costs nothing and holds nobody up.
        assert_eq!(s.read(Time(0), 0, 0), Duration::ZERO);
    }

    #[test]
    fn a_node_reads_no_faster_than_its_cap() {
        let mut s = storage(Some(100_000_000), None);
        // 100 MB at the node's 100 MB/s: 1 s, though the storage is free after 100 ms.
        assert_eq!(s.read(Time(0), 1, 100_000_000), Duration::from_millis(1001));
        // Another node reads alongside from 100 ms on.
        assert_eq!(s.read(Time(0), 1, 100_000_000), Duration::from_millis(1001));
    }

    #[test]
    fn a_domain_is_charged_its_stated_size() {
        let mut s = storage(None, Some(500_000_000));
        // Two domains charged 500 MB each, whatever their bytes here: 1 s plus 2 ms.
        assert_eq!(s.read(Time(0), 2, 10), Duration::from_millis(1002));
        assert_eq!(s.bytes, 1_000_000_000);
    }
}
