//! What a worker counts of one frame (rays, bytes, passes, busy time, idle time by its cause),
//! kept by the frame and written into `FrameEnded`'s statistics.

use std::time::Duration;

use rayfarm_core::render::KernelCounters;

/// Counters of one frame on this worker.
#[derive(Default)]
pub struct FrameCounters {
    pub rays: KernelCounters,
    pub rays_sent: u64,
    pub bytes_sent: u64,
    pub rays_received: u64,
    /// Rays handed to idle peers as demand-driven tasks (hybrid).
    pub rays_shared: u64,
    /// Passes of the frame it took back finished (the shell and the simulator both read this).
    pub passes: u64,
    pub busy: Duration,
    /// Time with no pass to run, by why ([`IdleKind`] as index), closed intervals only.
    pub idle: [Duration; 3],
    /// The open idle interval: since when, and why.
    pub idle_since: Option<(crate::Time, IdleKind)>,
}

/// Why a worker has no pass to run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum IdleKind {
    /// Rays are queued here, but for no domain this round's plan lets it trace (or only for
    /// the one being prefetched): waiting for the coordinator's next plan or a load.
    Queued = 0,
    /// Nothing queued, but rays of its own wait for their copies' verdicts from peers.
    Verdicts = 1,
    /// Nothing queued, nothing waiting: waiting for peers' rays or the frame's end.
    Empty = 2,
}

impl FrameCounters {
    /// Closes the open idle interval at `now`, if any.
    pub fn close_idle(&mut self, now: crate::Time) {
        if let Some((since, kind)) = self.idle_since.take() {
            self.idle[kind as usize] += now.since(since);
        }
    }

    /// Closes the open idle interval and opens one of `kind` at `now`.
    pub fn open_idle(&mut self, now: crate::Time, kind: IdleKind) {
        self.close_idle(now);
        self.idle_since = Some((now, kind));
    }
}
