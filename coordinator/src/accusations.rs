//! Workers' reports that a peer is unreachable, and which worker to drop for them.
//!
//! A report says a link is broken, not which end is at fault: a worker cut off from its peers
//! reports every one of them, and each of them reports it. Acting on the first report would
//! drop a healthy worker on the word of the cut-off one. So reports wait a short grace period
//! for the other side's, then the worker reported by the most distinct members goes (on a
//! tie, the one reported first): the cut-off worker, whose accusations go with it.

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, Instant};

/// One report: `accuser` found `accused` unreachable at `at`, for `reason`.
#[derive(Clone, Debug)]
struct Accusation {
    accuser: u32,
    accused: u32,
    at: Instant,
    reason: String,
}

/// The reports of the running frame not yet judged, by worker key.
#[derive(Debug, Default)]
pub struct Accusations {
    pending: Vec<Accusation>,
}

/// The worker to drop, with the first reason given against it and who gave it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Verdict {
    pub accused: u32,
    pub accuser: u32,
    pub reason: String,
    /// Distinct members that reported it.
    pub accusers: usize,
}

impl Accusations {
    /// Records that `accuser` cannot reach `accused`.
    pub fn add(&mut self, accuser: u32, accused: u32, at: Instant, reason: &str) {
        if accuser != accused {
            self.pending.push(Accusation {
                accuser,
                accused,
                at,
                reason: reason.to_string(),
            });
        }
    }

    /// Forgets every report by or about `key` (it left the frame).
    pub fn forget(&mut self, key: u32) {
        self.pending
            .retain(|a| a.accuser != key && a.accused != key);
    }

    /// Once the oldest report is `grace` old, picks the worker to drop among `members` and
    /// forgets its reports both ways; `None` while reports may still be coming.
    pub fn judge(
        &mut self,
        now: Instant,
        grace: Duration,
        members: &BTreeSet<u32>,
    ) -> Option<Verdict> {
        self.pending
            .retain(|a| members.contains(&a.accuser) && members.contains(&a.accused));
        let oldest = self.pending.first()?;
        if now.saturating_duration_since(oldest.at) < grace {
            return None;
        }
        // Distinct accusers of each accused, and its first report (reports are in order).
        let mut accusers: BTreeMap<u32, BTreeSet<u32>> = BTreeMap::new();
        for a in &self.pending {
            accusers.entry(a.accused).or_default().insert(a.accuser);
        }
        let most = accusers.values().map(BTreeSet::len).max()?;
        let first = self
            .pending
            .iter()
            .find(|a| accusers[&a.accused].len() == most)?
            .clone();
        self.forget(first.accused);
        Some(Verdict {
            accused: first.accused,
            accuser: first.accuser,
            reason: first.reason,
            accusers: most,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const GRACE: Duration = Duration::from_millis(500);

    fn members(keys: &[u32]) -> BTreeSet<u32> {
        keys.iter().copied().collect()
    }

    #[test]
    fn reports_wait_for_the_grace_period() {
        let t0 = Instant::now();
        let mut a = Accusations::default();
        a.add(1, 2, t0, "silent");
        assert_eq!(a.judge(t0 + GRACE / 2, GRACE, &members(&[1, 2])), None);
        let v = a
            .judge(t0 + GRACE, GRACE, &members(&[1, 2]))
            .expect("verdict");
        assert_eq!((v.accused, v.accuser, v.accusers), (2, 1, 1));
        assert_eq!(a.judge(t0 + GRACE * 2, GRACE, &members(&[1])), None);
    }

    #[test]
    fn the_worker_cut_off_from_everyone_goes_though_it_reported_first() {
        let t0 = Instant::now();
        let ms = |n| t0 + Duration::from_millis(n);
        let mut a = Accusations::default();
        // Worker 1 is cut off from 0 and 2: it reports both, then both report it.
        a.add(1, 0, ms(0), "no connection");
        a.add(1, 2, ms(10), "no connection");
        a.add(2, 1, ms(40), "64 bundles unacknowledged");
        a.add(0, 1, ms(90), "no connection");
        let all = members(&[0, 1, 2]);
        let v = a.judge(ms(600), GRACE, &all).expect("verdict");
        assert_eq!((v.accused, v.accusers), (1, 2));
        assert_eq!(v.accuser, 2);
        // Its own reports went with it.
        assert_eq!(a.judge(ms(2000), GRACE, &members(&[0, 2])), None);
    }

    #[test]
    fn a_tie_drops_the_first_reported_and_a_gone_worker_s_reports_are_void() {
        let t0 = Instant::now();
        let mut a = Accusations::default();
        a.add(0, 1, t0, "a");
        a.add(1, 0, t0 + Duration::from_millis(5), "b");
        let v = a
            .judge(t0 + GRACE, GRACE, &members(&[0, 1, 2]))
            .expect("verdict");
        assert_eq!((v.accused, v.accuser), (1, 0));
        a.add(2, 0, t0, "c");
        // Worker 2 left before the judgement: its report counts for nothing.
        assert_eq!(a.judge(t0 + GRACE, GRACE, &members(&[0, 1])), None);
        a.add(3, 3, t0, "itself");
        assert_eq!(a.judge(t0 + GRACE, GRACE, &members(&[3])), None);
    }
}
