//! The frame the cluster is rendering: who takes part, their last queue reports, the rounds
//! of the dynamic schedule, and the tile ledger that says when the frame is complete. It
//! returns the messages to send instead of sending them, so the coordinator's locking and
//! I/O stay outside.

use crate::accusations::Accusations;
use std::collections::{BTreeMap, BTreeSet};
use std::time::Instant;

use rayfarm_core::cluster::tile_sums;
use rayfarm_core::frame::TILE_SIZE;
use rayfarm_core::frame::{Accept, FrameLedger, TILE_CREDIT, TileGrid};
use rayfarm_core::render::Film;
use rayfarm_core::render::local::FrameSpec;
use rayfarm_core::schedule::dynamic::{Options, WorkerPlan, next_round_with};
use rayfarm_core::schedule::static_plans::{domain_owner, image_plane_share};
use rayfarm_core::schedule::{ClusterState, DomainId, WorkerId, WorkerState};
use rayfarm_node::proto::{self, Schedule, coordinator_message::Body};
use tracing::{debug, info};

/// A message for one worker, by the coordinator's worker key.
pub type Outgoing = (u32, proto::CoordinatorMessage);

/// How the dynamic schedule's rounds advance.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Rounds {
    /// Fig. 5 as written: a round is planned when every worker has reported, so each round
    /// waits for its slowest worker.
    Barrier,
    /// A worker that runs dry is planned at once from the latest reports of all (the busy
    /// ones' are older); the others learn the new holders and go on. No worker waits for
    /// another, at the price of planning on older figures.
    #[default]
    Async,
}

/// What the frame needs to know about a worker.
#[derive(Clone, Debug)]
pub struct Member {
    pub peer_address: String,
    pub cache_bytes: u64,
    /// Its latest queue report for this frame.
    report: Option<proto::QueueReport>,
    /// Segments it has traced for this frame (latest figure it sent).
    segments: u64,
    /// Domains of its current plan (asynchronous rounds).
    plan: BTreeSet<u32>,
    /// Round of its current plan: a report of that round or later means it has run dry.
    planned_round: u64,
}

impl Member {
    pub fn new(peer_address: String, cache_bytes: u64) -> Self {
        Member {
            peer_address,
            cache_bytes,
            report: None,
            segments: 0,
            plan: BTreeSet::new(),
            planned_round: 0,
        }
    }

    /// Whether it has run out of work since its last plan.
    fn is_dry(&self) -> bool {
        self.report
            .as_ref()
            .is_some_and(|r| r.round >= self.planned_round)
    }
}

/// A tile the ledger committed, with its fixed-point sums for the film.
pub type CommittedTile = (u32, Vec<[i64; 3]>);

/// See the module documentation.
pub struct RunningFrame {
    pub job_id: String,
    pub schedule: Schedule,
    pub spec: proto::JobSpec,
    pub frame: FrameSpec,
    domain_bytes: Vec<u64>,
    pub ledger: FrameLedger,
    pub round: u64,
    members: BTreeMap<u32, Member>,
    pub started: Instant,
    /// Domain loads the plans asked for.
    pub planned_loads: u64,
    options: Options,
    rounds: Rounds,
    /// Tiles not yet handed out (hybrid: demand-driven work for workers that run dry).
    pending_tiles: std::collections::VecDeque<u32>,
    /// Tiles per hand-out.
    batch: usize,
    /// Ids of workers dropped because a peer could not reach them: they sit out the rest of
    /// this frame when they register again (they join the next one), or a worker that its
    /// peers cannot reach would be dropped, rejoin, get work and be dropped again, each time
    /// restarting every unfinished tile, for as long as its links are cut.
    pub sidelined: std::collections::BTreeSet<String>,
    /// Why each worker that declined this frame could not take part (they are left out of it).
    pub declined: Vec<String>,
    /// Members' reports of members they cannot reach, waiting to be judged.
    pub accusations: Accusations,
    /// Where committed tiles go: the coordinator's state writes them (this module does no
    /// I/O); `None` in unit tests.
    pub film: Option<Film>,
}

fn msg(body: Body) -> proto::CoordinatorMessage {
    proto::CoordinatorMessage { body: Some(body) }
}

impl RunningFrame {
    /// A frame of `spec` over a scene with domains of `domain_bytes` each.
    pub fn new(
        job_id: String,
        spec: proto::JobSpec,
        frame: FrameSpec,
        domain_bytes: Vec<u64>,
        options: Options,
        rounds: Rounds,
    ) -> Result<Self, String> {
        let grid = TileGrid::new(frame.width, frame.height, TILE_SIZE)
            .ok_or_else(|| "the image does not fit the tile grid".to_string())?;
        let schedule = match Schedule::try_from(spec.schedule) {
            Ok(Schedule::Unspecified) => Schedule::Dynamic,
            Ok(s) => s,
            Err(_) => return Err(format!("unknown schedule {}", spec.schedule)),
        };
        // A copy of a domain costs a load, which is what the predictive schedule saves; with
        // copies it loaded 269 domains against 222 without, and was no faster (README).
        let options = match schedule {
            Schedule::Predictive => Options {
                replicate_onto_idle: false,
                fill_free_slots: false,
            },
            _ => options,
        };
        let spp = frame.spp;
        Ok(RunningFrame {
            job_id,
            schedule,
            spec,
            frame,
            domain_bytes,
            ledger: FrameLedger::new(grid, TILE_CREDIT).with_samples(spp),
            round: 0,
            members: BTreeMap::new(),
            started: Instant::now(),
            planned_loads: 0,
            options,
            rounds,
            pending_tiles: Default::default(),
            batch: 1,
            sidelined: Default::default(),
            declined: Vec::new(),
            accusations: Accusations::default(),
            film: None,
        })
    }

    /// Every member's peer address by key.
    fn roster(&self) -> std::collections::HashMap<u32, String> {
        self.members
            .iter()
            .map(|(&k, m)| (k, m.peer_address.clone()))
            .collect()
    }

    fn start_message(&self, key: u32, tiles: Vec<u32>) -> proto::CoordinatorMessage {
        msg(Body::StartFrame(proto::StartFrame {
            worker_key: key,
            roster: self.roster(),
            job_id: self.job_id.clone(),
            spec: Some(self.spec.clone()),
            tile_size: TILE_SIZE,
            primary_tiles: tiles,
            round: self.round,
            epochs: (0..self.ledger.grid().count())
                .filter_map(|t| Some((t, self.ledger.epoch(t)?)))
                .filter(|&(_, e)| e > 0)
                .collect(),
        }))
    }

    /// Starts the frame on `workers` (at least one). Image-plane gives each worker a
    /// contiguous share of the tiles (Fig. 3); the other schedules deal tiles round robin,
    /// since neighbouring tiles cost about the same. The domain schedule's one plan, every
    /// domain with its round-robin owner (Fig. 4), follows at once.
    pub fn start(&mut self, workers: Vec<(u32, Member)>) -> Vec<Outgoing> {
        let n = workers.len().max(1) as u32;
        let count = self.ledger.grid().count();
        let tiles: Vec<Vec<u32>> = match self.schedule {
            Schedule::ImagePlane => (0..n)
                .map(|i| image_plane_share(i, n, count).collect())
                .collect(),
            Schedule::Hybrid => {
                // A first batch each; the rest goes to whoever runs dry first.
                self.batch = (count as usize / (n as usize * 4)).max(1);
                self.pending_tiles = (0..count).collect();
                (0..n).map(|_| self.hand_out()).collect()
            }
            _ => (0..n)
                .map(|i| (i..count).step_by(n as usize).collect())
                .collect(),
        };
        let keys: Vec<u32> = workers.iter().map(|&(k, _)| k).collect();
        self.members.extend(workers);
        let mut out: Vec<Outgoing> = keys
            .into_iter()
            .zip(tiles)
            .map(|(key, tiles)| (key, self.start_message(key, tiles)))
            .collect();
        if matches!(self.schedule, Schedule::Domain | Schedule::Hybrid) {
            out.extend(self.owner_plans());
        }
        out
    }

    fn hand_out(&mut self) -> Vec<u32> {
        let n = self.batch.min(self.pending_tiles.len());
        self.pending_tiles.drain(..n).collect()
    }

    /// The static domain schedule: domain `d` belongs to the `d mod n`-th worker.
    fn owner_plans(&mut self) -> Vec<Outgoing> {
        let keys: Vec<u32> = self.members.keys().copied().collect();
        let n = keys.len() as u32;
        let owner = |d: u32| keys[domain_owner(DomainId(d), n) as usize];
        let domains = self.domain_bytes.len() as u32;
        let holders: Vec<proto::DomainHolders> = (0..domains)
            .map(|d| proto::DomainHolders {
                domain: d,
                workers: vec![self.members[&owner(d)].peer_address.clone()],
            })
            .collect();
        self.round = 1;
        keys.iter()
            .map(|&key| {
                let body = Body::RoundPlan(proto::RoundPlan {
                    job_id: self.job_id.clone(),
                    round: 1,
                    work_on: (0..domains).filter(|&d| owner(d) == key).collect(),
                    evict: Vec::new(),
                    holders: holders.clone(),
                });
                (key, msg(body))
            })
            .collect()
    }

    /// Lets a worker that registered mid-frame take part from the next round; the others
    /// learn its key and address.
    pub fn join(&mut self, key: u32, member: Member) -> Vec<Outgoing> {
        self.members.insert(key, member);
        let roster = Body::Roster(proto::Roster {
            job_id: self.job_id.clone(),
            members: self.roster(),
        });
        let mut out = vec![(key, self.start_message(key, Vec::new()))];
        out.extend(
            self.members
                .keys()
                .filter(|&&k| k != key)
                .map(|&k| (k, msg(roster.clone()))),
        );
        out
    }

    /// Domains in the scene.
    pub fn domain_count(&self) -> usize {
        self.domain_bytes.len()
    }

    /// Workers taking part.
    pub fn members(&self) -> impl Iterator<Item = u32> + '_ {
        self.members.keys().copied()
    }

    /// A member is gone, and every unfinished tile may have had rays on it: bumps their
    /// epochs (dropping their partial sums), tells the others to drop those tiles' old rays
    /// and to send nothing more to the lost worker, and deals the tiles' camera rays again;
    /// the domain and hybrid schedules get new owners. Returns `None` if the worker took no
    /// part, and no messages if no member is left (the caller decides the job's fate).
    pub fn lose(&mut self, key: u32) -> Option<Vec<Outgoing>> {
        let lost = self.members.remove(&key)?;
        if self.members.is_empty() {
            return Some(Vec::new());
        }
        let unfinished: Vec<u32> = self.ledger.unfinished().collect();
        let bumped = self.ledger.bump(&unfinished);
        info!(tiles = bumped.len(), "epochs bumped after losing a worker");
        let bump = proto::EpochBump {
            job_id: self.job_id.clone(),
            epochs: bumped.iter().copied().collect(),
            lost_peers: vec![lost.peer_address],
        };
        let keys: Vec<u32> = self.members.keys().copied().collect();
        let mut out: Vec<Outgoing> = keys
            .iter()
            .map(|&k| (k, msg(Body::EpochBump(bump.clone()))))
            .collect();
        // What members reported before the bump counted rays they have now dropped.
        for m in self.members.values_mut() {
            m.report = None;
        }
        // The new owners go out before the re-dealt tiles: a worker traces a hand-out as soon
        // as it arrives, and under the old plan the rays leaving its tiles would be routed to
        // the lost worker, whose link holds them until it gives up (the frame never ended).
        if matches!(self.schedule, Schedule::Domain | Schedule::Hybrid) {
            out.extend(self.owner_plans());
        }
        let tiles: Vec<u32> = bumped.into_iter().map(|(t, _)| t).collect();
        if self.schedule == Schedule::Hybrid {
            // Whoever runs dry first takes them, as before.
            self.pending_tiles = tiles.into();
            for &k in &keys {
                let tiles = self.hand_out();
                out.push((k, self.hand_out_message(tiles)));
            }
        } else {
            let n = keys.len();
            for (i, &k) in keys.iter().enumerate() {
                let share = tiles.iter().copied().skip(i).step_by(n).collect();
                out.push((k, self.hand_out_message(share)));
            }
        }
        Some(out)
    }

    fn hand_out_message(&self, tiles: Vec<u32>) -> proto::CoordinatorMessage {
        msg(Body::HandOutTiles(proto::HandOutTiles {
            job_id: self.job_id.clone(),
            tiles,
        }))
    }

    /// Records a queue report; under the dynamic schedule, returns the next round's plans
    /// when every worker has finished the current round and some ray is queued somewhere.
    /// The static schedules decide once and never plan again.
    pub fn report(&mut self, key: u32, report: proto::QueueReport) -> Vec<Outgoing> {
        let Some(member) = self.members.get_mut(&key) else {
            return Vec::new();
        };
        member.report = Some(report);
        match self.schedule {
            Schedule::Dynamic | Schedule::Predictive | Schedule::Unspecified => match self.rounds {
                Rounds::Barrier => self.plan_if_round_over(),
                Rounds::Async => self.plan_dry_members(),
            },
            // A worker reports when it has run dry: hand it more demand-driven work.
            Schedule::Hybrid if !self.pending_tiles.is_empty() => {
                let tiles = self.hand_out();
                vec![(key, self.hand_out_message(tiles))]
            }
            _ => Vec::new(),
        }
    }

    fn plan_if_round_over(&mut self) -> Vec<Outgoing> {
        let round = self.round;
        let all_in = self
            .members
            .values()
            .all(|m| m.report.as_ref().is_some_and(|r| r.round >= round));
        if !all_in {
            return Vec::new();
        }
        let Some(mut state) = self.cluster_state(&BTreeSet::new(), true) else {
            return Vec::new();
        };
        if !state.has_rays() {
            // As in asynchronous rounds: everyone has reported, so plan the younger rays.
            match self.cluster_state(&BTreeSet::new(), false) {
                Some(all) => state = all,
                None => return Vec::new(),
            }
        }
        if !state.has_rays() {
            // Rays or results are still on the wire: a worker reports again when they land.
            return Vec::new();
        }
        let plan = next_round_with(&state, self.options);
        self.round += 1;
        self.planned_loads += plan.load_count() as u64;
        let holders: Vec<proto::DomainHolders> = plan
            .routes()
            .into_iter()
            .map(|(d, ws)| proto::DomainHolders {
                domain: d.0,
                workers: ws
                    .iter()
                    .filter_map(|w| self.members.get(&w.0))
                    .map(|m| m.peer_address.clone())
                    .collect(),
            })
            .collect();
        info!(
            round = self.round,
            loads = plan.load_count(),
            wanted = state.wanted().count(),
            "round planned"
        );
        plan.workers()
            .iter()
            .map(|p| self.plan_message(p, &holders))
            .collect()
    }

    /// `p` as this round's message to its worker.
    fn plan_message(&self, p: &WorkerPlan, holders: &[proto::DomainHolders]) -> Outgoing {
        debug!(worker = p.worker.0, keep = ?p.keep, load = ?p.load, evict = ?p.evict, "plan");
        let body = Body::RoundPlan(proto::RoundPlan {
            job_id: self.job_id.clone(),
            round: self.round,
            work_on: p.work().map(|d| d.0).collect(),
            evict: p.evict.iter().map(|d| d.0).collect(),
            holders: holders.to_vec(),
        });
        (p.worker.0, msg(body))
    }

    /// Asynchronous rounds: plans every member that has run dry, from the latest reports of
    /// all. Busy members keep their plans: the schedule sees them holding exactly what they
    /// work on, with no free slot. A dry member whose plan would not change is left waiting
    /// (its rays are elsewhere or on the wire); the next report plans it again. Members whose
    /// plan did not change learn the new holders.
    fn plan_dry_members(&mut self) -> Vec<Outgoing> {
        let dry: BTreeSet<u32> = self
            .members
            .iter()
            .filter(|(_, m)| m.is_dry())
            .map(|(&k, _)| k)
            .collect();
        if dry.is_empty() {
            return Vec::new();
        }
        let busy: BTreeSet<u32> = self
            .members
            .keys()
            .copied()
            .filter(|k| !dry.contains(k))
            .collect();
        // Predictive plans the oldest generation first. With no one busy, a generation that
        // cannot move on (its last copies on the wire or lost with a worker) must not stall
        // the frame: then everything queued is planned.
        let filters: &[bool] = match busy.is_empty() {
            true => &[true, false],
            false => &[true],
        };
        let mut changed = Vec::new();
        for &oldest_first in filters {
            let Some(state) = self.cluster_state(&busy, oldest_first) else {
                return Vec::new();
            };
            if !state.has_rays() {
                continue;
            }
            let plan = next_round_with(&state, self.options);
            changed = plan
                .workers()
                .iter()
                .filter(|p| dry.contains(&p.worker.0))
                .filter(|p| {
                    let work: BTreeSet<u32> = p.work().map(|d| d.0).collect();
                    !p.evict.is_empty() || work != self.members[&p.worker.0].plan
                })
                .cloned()
                .collect();
            if !changed.is_empty() {
                break;
            }
        }
        if changed.is_empty() {
            return Vec::new();
        }
        self.round += 1;
        for p in &changed {
            self.planned_loads += p.load.len() as u64;
            if let Some(m) = self.members.get_mut(&p.worker.0) {
                m.plan = p.work().map(|d| d.0).collect();
                m.planned_round = self.round;
            }
        }
        self.move_queued_to_holders();
        let holders = self.current_holders();
        debug!(
            round = self.round,
            planned = changed.len(),
            "dry workers planned"
        );
        let mut out: Vec<Outgoing> = changed
            .iter()
            .map(|p| self.plan_message(p, &holders))
            .collect();
        let planned: BTreeSet<u32> = changed.iter().map(|p| p.worker.0).collect();
        for &key in self.members.keys().filter(|k| !planned.contains(k)) {
            let body = Body::Holders(proto::Holders {
                job_id: self.job_id.clone(),
                holders: holders.clone(),
            });
            out.push((key, msg(body)));
        }
        out
    }

    /// Once told the new holders, a busy member sends its waiting rays for their domains to
    /// them, but its next report may be far off: account for the move now, so that its older
    /// figures do not keep a dry holder waiting on rays it has already traced.
    fn move_queued_to_holders(&mut self) {
        // A dry holder reports again when the rays reach it; counted there now, they would
        // stay after it traced them and mislead every later plan.
        let holder_of: BTreeMap<u32, u32> = self
            .members
            .iter()
            .filter(|(_, m)| !m.is_dry())
            .flat_map(|(&k, m)| m.plan.iter().map(move |&d| (d, k)))
            .collect();
        // Per new holder: domain -> (rays, oldest generation among them).
        let mut moved: BTreeMap<u32, BTreeMap<u32, (u64, Option<u32>)>> = BTreeMap::new();
        for m in self.members.values_mut() {
            let Some(report) = m.report.as_mut() else {
                continue;
            };
            let keeps = |d: &u32| m.plan.contains(d) || report.resident_domains.contains(d);
            let leaving: Vec<u32> = report
                .queued_rays
                .keys()
                .copied()
                .filter(|d| holder_of.contains_key(d) && !keeps(d))
                .collect();
            for d in leaving {
                let generation = report.oldest_generation.remove(&d);
                if let Some(n) = report.queued_rays.remove(&d) {
                    let entry = moved
                        .entry(holder_of[&d])
                        .or_default()
                        .entry(d)
                        .or_default();
                    entry.0 += n;
                    entry.1 = entry.1.into_iter().chain(generation).min();
                }
            }
        }
        for (key, queues) in moved {
            if let Some(report) = self.members.get_mut(&key).and_then(|m| m.report.as_mut()) {
                for (d, (n, generation)) in queues {
                    *report.queued_rays.entry(d).or_default() += n;
                    if let Some(g) = generation {
                        let oldest = report.oldest_generation.entry(d).or_insert(g);
                        *oldest = (*oldest).min(g);
                    }
                }
            }
        }
    }

    /// Every domain someone's current plan includes, with the peer addresses of its holders.
    fn current_holders(&self) -> Vec<proto::DomainHolders> {
        let mut by_domain: BTreeMap<u32, Vec<String>> = BTreeMap::new();
        for m in self.members.values() {
            for &d in &m.plan {
                by_domain.entry(d).or_default().push(m.peer_address.clone());
            }
        }
        by_domain
            .into_iter()
            .map(|(domain, workers)| proto::DomainHolders { domain, workers })
            .collect()
    }

    /// The cluster as the schedule sees it, from the latest reports. Members in `busy` are
    /// planned already and not re-planned now (asynchronous rounds): they hold their plan and
    /// what they reported resident, with no slot to spare. Members that have not reported
    /// yet take no part (barrier rounds wait until all have). Under the predictive schedule
    /// only queues holding the oldest generation still being traced count: a generation
    /// needs each domain once, so younger rays wait for it rather than cost a load of their
    /// own. While that generation's last copies are on the wire, nothing is planned
    /// (`oldest_first`; without it every queue counts).
    fn cluster_state(&self, busy: &BTreeSet<u32>, oldest_first: bool) -> Option<ClusterState> {
        let domains = self.domain_bytes.len() as u32;
        let oldest = (oldest_first && self.schedule == Schedule::Predictive)
            .then(|| {
                self.members
                    .values()
                    .filter_map(|m| m.report.as_ref())
                    .flat_map(|r| {
                        r.oldest_generation
                            .values()
                            .copied()
                            .chain(r.oldest_waiting)
                    })
                    .min()
            })
            .flatten();
        // Younger rays of a domain in memory somewhere cost no load: they count, so that the
        // domain is kept for them rather than evicted and loaded again a generation later.
        let in_memory: BTreeSet<u32> = self
            .members
            .values()
            .flat_map(|m| {
                let resident = m.report.iter().flat_map(|r| r.resident_domains.iter());
                resident.chain(m.plan.iter()).copied()
            })
            .collect();
        let counts = |r: &proto::QueueReport, d: &u32| {
            oldest.is_none_or(|g| r.oldest_generation.get(d) == Some(&g) || in_memory.contains(d))
        };
        let largest = self.domain_bytes.iter().copied().max().unwrap_or(1).max(1);
        let mut queued: BTreeMap<DomainId, u64> = BTreeMap::new();
        let mut workers = Vec::new();
        for (&key, m) in &self.members {
            let Some(report) = m.report.as_ref() else {
                continue;
            };
            let mut resident: BTreeSet<DomainId> = report
                .resident_domains
                .iter()
                .filter(|&&d| d < domains)
                .map(|&d| DomainId(d))
                .collect();
            if !busy.contains(&key) {
                // Domains differ in size: count the slots by the largest, but never fewer
                // than what the worker holds now.
                let capacity = ((m.cache_bytes / largest) as usize)
                    .max(1)
                    .max(resident.len());
                workers.push(WorkerState::new(WorkerId(key), resident, capacity));
            } else {
                resident.extend(m.plan.iter().map(|&d| DomainId(d)));
                // A busy member holding nothing has no place in the plan; its rays count.
                if !resident.is_empty() {
                    let capacity = resident.len();
                    workers.push(WorkerState::new(WorkerId(key), resident, capacity));
                }
            }
            for (&d, &n) in &report.queued_rays {
                if d < domains && counts(report, &d) {
                    *queued.entry(DomainId(d)).or_default() += n;
                }
            }
        }
        ClusterState::new(workers, queued).ok()
    }

    /// Accepts a worker's tile results. Returns the tiles they committed with their sums,
    /// taken out of the ledger for the film, and why the rest was refused if a result
    /// cannot be right (the worker must be dropped; nothing after it was counted).
    pub fn results(
        &mut self,
        key: u32,
        results: proto::TileResults,
    ) -> (Vec<CommittedTile>, Option<String>) {
        if let Some(m) = self.members.get_mut(&key) {
            m.segments = m.segments.max(results.segments_traced);
        }
        let mut committed = Vec::new();
        for r in results.results {
            let pixels = self.ledger.grid().tile_pixel_count(r.tile);
            let sums = match tile_sums::decode(&r.sums, pixels) {
                Ok(sums) => sums,
                Err(e) => return (committed, Some(format!("tile {}: {e}", r.tile))),
            };
            match self.ledger.accept(r.tile, r.epoch, r.credit, &sums) {
                Ok(Accept::Completed) => {
                    debug!(tile = r.tile, "tile complete");
                    committed.push((r.tile, self.ledger.take_sums(r.tile)));
                }
                Ok(Accept::Pending | Accept::Stale) => {}
                Err(reject) => return (committed, Some(reject.to_string())),
            }
        }
        (committed, None)
    }

    /// Progress for watchers: (tiles done, tiles, segments per second, ETA seconds or -1).
    pub fn progress(&self) -> (u32, u32, f64, f64) {
        let done = self.ledger.tiles_done();
        let total = self.ledger.grid().count();
        let elapsed = self.started.elapsed().as_secs_f64();
        let segments: u64 = self.members.values().map(|m| m.segments).sum();
        let eta = if done == 0 {
            -1.0
        } else {
            elapsed * f64::from(total - done) / f64::from(done)
        };
        (done, total, segments as f64 / elapsed.max(1e-9), eta)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn predictive_frame() -> RunningFrame {
        let spec = proto::JobSpec {
            width: 64,
            height: 64,
            spp: 1,
            max_depth: 3,
            schedule: Schedule::Predictive as i32,
            ..Default::default()
        };
        let frame = FrameSpec {
            width: 64,
            height: 64,
            spp: 1,
            max_depth: 3,
            camera: None,
        };
        let options = Options {
            replicate_onto_idle: false,
            fill_free_slots: true,
        };
        RunningFrame::new(
            "j".into(),
            spec,
            frame,
            vec![100; 4],
            options,
            Rounds::Async,
        )
        .expect("frame")
    }

    fn report(round: u64, resident: &[u32], queued: &[(u32, u64, u32)]) -> proto::QueueReport {
        proto::QueueReport {
            job_id: "j".into(),
            round,
            resident_domains: resident.to_vec(),
            queued_rays: queued.iter().map(|&(d, n, _)| (d, n)).collect(),
            oldest_generation: queued.iter().map(|&(d, _, g)| (d, g)).collect(),
            oldest_waiting: None,
        }
    }

    fn planned_domains(out: &[Outgoing], key: u32) -> Vec<u32> {
        out.iter()
            .filter(|(k, _)| *k == key)
            .filter_map(|(_, m)| match &m.body {
                Some(Body::RoundPlan(p)) => Some(p.work_on.clone()),
                _ => None,
            })
            .flatten()
            .collect()
    }

    #[test]
    fn predictive_never_copies_domains_into_free_slots() {
        assert!(!predictive_frame().options.fill_free_slots);
    }

    #[test]
    fn the_oldest_generation_is_planned_first() {
        let mut f = predictive_frame();
        let member = || Member::new("w".into(), 200);
        f.start(vec![(0, member()), (1, member())]);
        f.report(1, report(0, &[], &[]));
        // Domain 2 has more rays, but domain 3 holds the older generation.
        let out = f.report(0, report(0, &[], &[(2, 900, 2), (3, 5, 1)]));
        let planned = [planned_domains(&out, 0), planned_domains(&out, 1)].concat();
        assert_eq!(planned, [3], "{out:?}");
    }

    #[test]
    fn with_every_worker_dry_a_stuck_generation_does_not_stall_the_frame() {
        let mut f = predictive_frame();
        let member = || Member::new("w".into(), 200);
        f.start(vec![(0, member()), (1, member())]);
        // Worker 0 holds domain 0, whose older rays it has planned already; worker 1 is
        // free. Only domain 0 counts under the oldest-first rule, and its plan is unchanged:
        // the younger rays of domain 1 must be planned all the same.
        f.members.get_mut(&0).expect("member").plan = [0].into();
        f.members.get_mut(&0).expect("member").planned_round = 1;
        f.round = 1;
        let busy = f.report(0, report(1, &[0], &[(0, 5, 1), (1, 7, 2)]));
        assert!(busy.is_empty(), "worker 1 has not reported: wait for it");
        let out = f.report(1, report(0, &[], &[]));
        let planned = [planned_domains(&out, 0), planned_domains(&out, 1)].concat();
        assert!(planned.contains(&1), "{out:?}");
    }
}
