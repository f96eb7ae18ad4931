//! The running frame's life around its rounds: a worker admitted to it or made to sit it
//! out, a restarted job's fresh epochs, the judgement of accusations with what the
//! coordinator hears itself, and the frame's end. The coordinator shell and the simulator
//! both call these, so the policy exists once.

use std::collections::BTreeSet;
use std::time::Duration;

use rayfarm_proto::{self as proto, coordinator_message::Body};

use super::{Member, Outgoing, RunningFrame, msg};
use crate::Time;
use crate::coordinator::Verdict;

/// Least time a worker's report of an unreachable peer waits for the other side's reports
/// (see [`crate::coordinator::accusations`]): both sides notice a broken link within about
/// this long of each other when their deadlines are alike.
pub const ACCUSATION_GRACE: Duration = Duration::from_secs(2);

/// How long reports of unreachable peers wait before they are judged, with heartbeats every
/// `heartbeat`.
pub fn accusation_grace(heartbeat: Duration) -> Duration {
    (heartbeat * 2).max(ACCUSATION_GRACE)
}

impl RunningFrame {
    /// A worker `worker_id` registered while the frame runs: it joins (the messages to send),
    /// or `None` if it sits the frame out (its peers could not reach it, or its results were
    /// refused, earlier in this frame).
    pub fn admit(&mut self, key: u32, worker_id: &str, member: Member) -> Option<Vec<Outgoing>> {
        if self.sidelined.contains(worker_id) {
            return None;
        }
        Some(self.join(key, member))
    }

    /// A job whose frames started `starts` times before starts every tile that many epochs
    /// on, so rays and results of the abandoned runs still in flight are dropped as stale.
    pub fn restart_epochs(&mut self, starts: u32) {
        let tiles: Vec<u32> = (0..self.ledger.grid().count()).collect();
        for _ in 0..starts {
            self.ledger.bump(&tiles);
        }
    }

    /// The epoch the next frame of this job must start at, at least, if this one is abandoned:
    /// one past the highest it used.
    pub fn epoch_floor(&self) -> u32 {
        let grid = self.ledger.grid().count();
        let used = (0..grid).filter_map(|t| self.ledger.epoch(t)).max();
        used.unwrap_or(0).saturating_add(1)
    }

    /// Judges the reports of unreachable peers once their grace period is over; `heard` are
    /// the members the coordinator itself heard from within it. The worker to drop (called
    /// `dropped_id` by the caller) sits out the rest of the frame.
    pub fn judge(
        &mut self,
        now: Time,
        grace: Duration,
        heard: &BTreeSet<u32>,
        id_of: impl Fn(u32) -> String,
    ) -> Option<Verdict> {
        let members: BTreeSet<u32> = self.members().collect();
        let v = self.accusations.judge_heard(now, grace, &members, heard)?;
        self.sidelined.insert(id_of(v.drop));
        Some(v)
    }

    /// A member's tile results were refused (see [`RunningFrame::results`]): worker
    /// `worker_id` sits out the rest of the frame.
    pub fn refuse(&mut self, worker_id: String) {
        self.sidelined.insert(worker_id);
    }

    /// The frame is over (complete or failed): EndFrame to every member.
    pub fn end_messages(&self) -> Vec<Outgoing> {
        self.members()
            .map(|k| {
                let body = Body::EndFrame(proto::EndFrame {
                    job_id: self.frame_id(),
                });
                (k, msg(body))
            })
            .collect()
    }
}
