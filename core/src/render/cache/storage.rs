//! Emulated shared storage: what a load would cost on a cluster's network file system, and a
//! worker's one line to it, which serves its loads one after another.

use std::sync::Arc;
use std::time::{Duration, Instant};

/// An emulation of slower shared storage, charged on every load: `latency` plus the file's
/// bytes at `bandwidth`. For benchmarks only; it makes a load cost what it would on a
/// cluster's network file system.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StorageModel {
    /// Bytes per second; `None` is unlimited.
    pub bandwidth: Option<u64>,
    /// Fixed cost of each load.
    pub latency: Duration,
}

impl StorageModel {
    /// The emulated time to load `bytes`.
    pub fn delay(&self, bytes: u64) -> Duration {
        let transfer = self
            .bandwidth
            .filter(|&b| b > 0)
            .map_or(Duration::ZERO, |b| {
                Duration::from_secs_f64(bytes as f64 / b as f64)
            });
        self.latency + transfer
    }

    /// Whether any delay is added.
    pub fn is_active(&self) -> bool {
        self.bandwidth.is_some() || !self.latency.is_zero()
    }
}

/// One worker's line to the emulated storage: its loads are served one after another, so a
/// prefetch beside a pass's load does not double the bandwidth. Shared by the cache and its
/// pending prefetches (they wait off the cache's lock).
#[derive(Clone, Debug, Default)]
pub(super) struct StorageLine {
    pub(super) model: StorageModel,
    /// When the last load reserved on the line is delivered.
    pub(super) free_at: Arc<std::sync::Mutex<Option<Instant>>>,
}

impl StorageLine {
    /// The emulated transfer time of `bytes` when storage is emulated (the estimate of a
    /// load's cost until loads have been measured).
    pub(super) fn estimate(&self, bytes: u64) -> Option<Duration> {
        self.model.is_active().then(|| self.model.delay(bytes))
    }

    /// Waits until `bytes` are delivered after the loads reserved before them.
    pub(super) fn deliver(&self, bytes: u64) {
        if !self.model.is_active() {
            return;
        }
        let now = Instant::now();
        let done = {
            let mut free = self.free_at.lock().unwrap_or_else(|p| p.into_inner());
            let start = free.map_or(now, |f| f.max(now));
            let done = start + self.model.delay(bytes);
            *free = Some(done);
            done
        };
        std::thread::sleep(done.saturating_duration_since(now));
    }
}
