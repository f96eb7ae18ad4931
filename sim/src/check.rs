//! The invariants a run must keep, checked as it goes and at its end: no tile committed
//! twice in one frame; ray queues and held bundles within their caps; the frame complete within the
//! virtual-time bound (liveness); its image the clean run's; no worker error.

use std::collections::BTreeMap;

use rayfarm_machine::Time;

/// A broken invariant: which, and what was seen.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Violation {
    pub invariant: &'static str,
    pub detail: String,
}

impl std::fmt::Display for Violation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.invariant, self.detail)
    }
}

/// What the checks have seen of a run.
#[derive(Default)]
pub struct Checks {
    /// By (frame, tile): when it was committed.
    committed: BTreeMap<(u64, u32), Time>,
    /// Commits of the coordinator already checked.
    pub commits_seen: usize,
    violations: Vec<Violation>,
    caps_broken: bool,
}

impl Checks {
    /// Records a broken invariant.
    pub fn violation(&mut self, invariant: &'static str, detail: String) {
        self.violations.push(Violation { invariant, detail });
    }

    /// Tile `tile` of the `frame`-th frame started was committed at `at` (a frame started
    /// again, after a coordinator crash or the loss of every worker, commits every tile
    /// again, to a film of its own).
    pub fn commit(&mut self, frame: u64, tile: u32, at: Time) {
        if let Some(first) = self.committed.insert((frame, tile), at) {
            self.violation(
                "commit once",
                format!(
                    "tile {tile} of frame {frame} committed at {:.3} ms and again at {:.3} ms",
                    first.0 as f64 / 1e6,
                    at.0 as f64 / 1e6
                ),
            );
        }
    }

    /// A worker holds `queued` bytes of rays (at most `cap`) and `early` bytes of bundles for
    /// frames not started (at most `early_cap`). Reported once per run.
    pub fn caps(&mut self, queued: u64, cap: u64, early: usize, early_cap: usize) {
        if self.caps_broken {
            return;
        }
        if queued > cap || early > early_cap {
            self.caps_broken = true;
            self.violation(
                "caps",
                format!("{queued} bytes queued (cap {cap}), {early} held early (cap {early_cap})"),
            );
        }
    }

    pub fn into_violations(self) -> Vec<Violation> {
        self.violations
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tile_committed_twice_and_a_cap_exceeded_are_violations() {
        let mut c = Checks::default();
        c.commit(1, 3, Time(1));
        c.commit(1, 4, Time(2));
        c.commit(2, 3, Time(3));
        assert!(c.violations.is_empty());
        c.commit(1, 3, Time(5));
        c.caps(10, 20, 0, 1);
        c.caps(30, 20, 0, 1);
        c.caps(40, 20, 0, 1);
        let v = c.into_violations();
        assert_eq!(v.len(), 2, "{v:?}");
        assert_eq!(v[0].invariant, "commit once");
        assert_eq!(v[1].invariant, "caps");
    }
}
