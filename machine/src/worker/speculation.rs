//! The predictive schedule on a worker: the rays born here wait in groups for their
//! speculative copies' verdicts, which come back from whichever workers traced the copies
//! (see `rayfarm_core::render::speculation`). Verdicts travel in the bundler's results
//! tier to the worker named in the copy, looked up in the frame's roster.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::Arc;

use rayfarm_core::ray::RayRecord;
use rayfarm_core::render::speculation::{GroupError, Groups, Outcome};
use rayfarm_core::schedule::speculation_depth::Depth;
use rayfarm_core::wire::VerdictRecord;
use tracing::{debug, warn};

/// See the module documentation.
pub struct Speculation {
    /// This worker's key: the resolver named in the copies of rays born here.
    pub me: u32,
    /// Peer address of every worker of the frame, by key (shared with the frame's plan).
    roster: Arc<HashMap<u32, String>>,
    groups: Groups,
    /// Rays whose verdicts are all in, for the next pass to conclude.
    pub to_conclude: Vec<(RayRecord, Outcome)>,
    /// Copies of the next windows of rays whose last window did not end them, to route.
    pub next_windows: Vec<RayRecord>,
    /// Verdicts for workers not in the roster yet (one that joined the frame and whose
    /// copies arrived before the coordinator's word of it).
    unaddressed: BTreeMap<u32, Vec<VerdictRecord>>,
    /// Workers lost from the frame: verdicts for them are dropped.
    gone: BTreeSet<u32>,
    /// Verdicts refused: stale (their ray's tile restarted) or not for a waiting ray.
    pub refused: u64,
}

impl Speculation {
    /// Groups for rays born at worker `me`, copied `depth` domains ahead, their verdicts
    /// sent to the workers of `roster`.
    pub fn new(me: u32, roster: Arc<HashMap<u32, String>>, depth: Depth) -> Self {
        Speculation {
            me,
            roster,
            groups: Groups::new(depth),
            to_conclude: Vec::new(),
            next_windows: Vec::new(),
            unaddressed: BTreeMap::new(),
            gone: BTreeSet::new(),
            refused: 0,
        }
    }

    /// Adopts a new roster; returns the held verdicts that now have an address.
    pub fn set_roster(
        &mut self,
        roster: Arc<HashMap<u32, String>>,
    ) -> Vec<(String, Vec<VerdictRecord>)> {
        self.roster = roster;
        let known: Vec<u32> = self
            .unaddressed
            .keys()
            .copied()
            .filter(|k| self.roster.contains_key(k))
            .collect();
        known
            .into_iter()
            .filter_map(|k| Some((self.roster[&k].clone(), self.unaddressed.remove(&k)?)))
            .collect()
    }

    /// Makes each ray born here wait for its copies in the domains of its path (`paths`, in
    /// the same order) and returns the copies of their first windows.
    pub fn spread(&mut self, born: &[RayRecord], paths: Vec<Vec<u32>>) -> Vec<RayRecord> {
        // At most one copy per domain of each path: sized once rather than grown copy by copy
        // (growing it was a twentieth of a predictive worker's event loop: perf, README).
        let mut copies = Vec::with_capacity(paths.iter().map(Vec::len).sum());
        for (ray, path) in born.iter().zip(paths) {
            self.groups.spread(*ray, path, self.me, &mut copies);
        }
        copies
    }

    /// Whether `copy` may be dropped untraced: it is a copy of a ray born here that a nearer
    /// domain already ended (`Groups::skip`; copies of other workers' rays are traced).
    pub fn skip(&mut self, copy: &RayRecord) -> bool {
        copy.resolver == self.me && self.groups.skip(copy)
    }

    /// Copies dropped untraced, and rays concluded before all their copies answered.
    pub fn skipped_and_early(&self) -> (u64, u64) {
        (self.groups.skipped, self.groups.early)
    }

    /// Copies sent in all windows, and windows sent after a ray's first.
    pub fn copies_and_extensions(&self) -> (u64, u64) {
        (self.groups.copies, self.groups.extensions)
    }

    /// Takes verdicts for rays born here; the rays they conclude join `to_conclude`.
    pub fn settle(&mut self, verdicts: &[VerdictRecord]) {
        for v in verdicts {
            match self.groups.settle(v, &mut self.next_windows) {
                Ok(Some(done)) => self.to_conclude.push(done),
                Ok(None) => {}
                Err(e @ (GroupError::Unknown(_) | GroupError::Mismatch(_))) => {
                    // After a fault, verdicts on the wire for restarted tiles land here.
                    debug!(error = %e, tile = v.tile, epoch = v.epoch, "verdict refused");
                    self.refused += 1;
                }
                Err(e @ GroupError::TooManySegments(_)) => {
                    // Only a peer that breaks the protocol sends these: its ray is dropped.
                    warn!(error = %e, tile = v.tile, epoch = v.epoch, "verdict refused");
                    self.refused += 1;
                }
            }
        }
    }

    /// Sends each verdict where its copy says: settled here if this worker is the
    /// resolver, else grouped by peer address (held back for resolvers not yet known).
    pub fn address(
        &mut self,
        verdicts: Vec<(u32, VerdictRecord)>,
    ) -> BTreeMap<String, Vec<VerdictRecord>> {
        // By resolver key first: a peer's address is copied once, not once per verdict. Each
        // key's list is sized from a count first (a few keys, thousands of verdicts: grown one
        // push at a time, the lists were regrown and copied).
        let mut counts: BTreeMap<u32, usize> = BTreeMap::new();
        for (resolver, _) in &verdicts {
            *counts.entry(*resolver).or_default() += 1;
        }
        let mut by_key: BTreeMap<u32, Vec<VerdictRecord>> = BTreeMap::new();
        let mut mine = Vec::with_capacity(counts.get(&self.me).copied().unwrap_or(0));
        for (resolver, v) in verdicts {
            if resolver == self.me {
                mine.push(v);
            } else if self.roster.contains_key(&resolver) {
                by_key
                    .entry(resolver)
                    .or_insert_with(|| {
                        Vec::with_capacity(counts.get(&resolver).copied().unwrap_or(0))
                    })
                    .push(v);
            } else if self.gone.contains(&resolver) {
                self.refused += 1;
            } else {
                self.unaddressed.entry(resolver).or_default().push(v);
            }
        }
        self.settle(&mine);
        let mut out: BTreeMap<String, Vec<VerdictRecord>> = BTreeMap::new();
        for (resolver, mut verdicts) in by_key {
            // (Every key here is in the roster, looked up just above.)
            if let Some(peer) = self.roster.get(&resolver) {
                // Two keys of one address (a worker that re-registered) share its list.
                out.entry(peer.clone()).or_default().append(&mut verdicts);
            }
        }
        out
    }

    /// Rays waiting for verdicts.
    pub fn waiting(&self) -> usize {
        self.groups.waiting()
    }

    /// The oldest generation among them, if any.
    pub fn oldest_waiting(&self) -> Option<u16> {
        self.groups.oldest_waiting()
    }

    /// Drops everything of tiles whose epoch moved on (a fault restarted them), and the
    /// verdicts held for lost workers.
    pub fn retain_current(&mut self, epochs: &[u32], lost: &[String]) {
        let current = |tile: u32, epoch: u32| epochs.get(tile as usize) == Some(&epoch);
        self.groups.retain(|r| current(r.tile, r.epoch));
        self.to_conclude.retain(|(r, _)| current(r.tile, r.epoch));
        self.next_windows.retain(|r| current(r.tile, r.epoch));
        for held in self.unaddressed.values_mut() {
            held.retain(|v| current(v.tile, v.epoch));
        }
        let gone: Vec<u32> = self
            .roster
            .iter()
            .filter(|(_, a)| lost.contains(a))
            .map(|(&k, _)| k)
            .collect();
        for k in gone {
            Arc::make_mut(&mut self.roster).remove(&k);
            self.gone.insert(k);
            if let Some(held) = self.unaddressed.remove(&k) {
                warn!(
                    worker = k,
                    verdicts = held.len(),
                    "dropping verdicts for a lost worker"
                );
            }
        }
    }
}
