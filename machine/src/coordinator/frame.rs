//! The frame the cluster is rendering: who takes part, their last queue reports, the rounds
//! of the dynamic schedule (planned in `planning`), and the tile ledger that says when the
//! frame is complete. Each event (the frame starts, a worker joins, reports, sends results
//! or is lost) is a method that returns the messages to send instead of sending them, and the
//! tiles it commits instead of writing them, so the coordinator's locking and I/O stay in its
//! shell.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use super::accusations::Accusations;
use super::cluster::ReportHold;
use super::grants::Grants;
use super::holders::SentHolders;
use super::tasks::{Direction, TASK_RAYS, TaskDirections};
use crate::Time;
use crate::queue_report;

use rayfarm_core::cluster::tile_sums;
use rayfarm_core::progressive::Samples;
use rayfarm_core::render::local::FrameSpec;
use rayfarm_core::schedule::dynamic::Options;
use rayfarm_core::schedule::keep_first_of_each;
use rayfarm_core::schedule::round_index::{Changes, Queue, RoundIndex};
use rayfarm_core::schedule::rounds;
use rayfarm_core::schedule::static_plans::{image_plane_share, owned_domains_fit};
use rayfarm_core::schedule::tiles::{HandOuts, strided_share};
use rayfarm_core::tile::credit::TILE_CREDIT;
use rayfarm_core::tile::ledger::{Accept, TileLedger};
use rayfarm_core::tile::{TILE_SIZE, TileGrid};
use rayfarm_proto::{self as proto, Schedule, coordinator_message::Body};
use tracing::{debug, info};

/// A message for one worker, by the coordinator's worker key. Shared (`Arc`): a holders
/// flush tells every member of a view class the same lines, and cloning that message for each
/// member (and dropping the copies) was nearly all of a flush, 103 ms at 4,096 workers x 32,768
/// domains every 100 ms of frame time (the `rounds` bench's profile). A flush makes one message
/// per class and state and hands each member a reference; the shells copy and encode it where
/// it is sent (the coordinator's in each worker's stream task, out of the state's lock).
pub type Outgoing = (u32, Arc<proto::CoordinatorMessage>);

/// How the dynamic schedule's rounds advance.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
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

/// What a frame's planning rounds did, counted since it started: what their cost follows, so
/// the simulator can price them (`rayfarm_sim::cost`) and the metrics count them. An
/// asynchronous round with someone busy plans only the members that ran dry from the figures
/// `RoundIndex` keeps, the holders map too (its cost follows those members and what their plans
/// changed); a barrier round, or an asynchronous one with nobody busy, plans every member
/// from the whole cluster (its cost follows the cluster's members and domains).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PlanningWork {
    /// Rounds planned, of every kind (the static schedules' one plan, the owner map, counts
    /// as a round that drafted no member: its cost follows the domains).
    pub rounds: u64,
    /// Of them, the rounds planned from the whole cluster.
    pub whole_rounds: u64,
    /// Members of the cluster summed over the whole-cluster rounds.
    pub whole_members: u64,
    /// Members whose plans the incremental rounds changed (each ran dry, was drafted and
    /// given a new plan: adopted, holders moved, a message), summed. A dry member a round
    /// leaves as it was costs it nothing: the round drafts only the members it gives
    /// something or whose plans change (`RoundIndex::dry_plans`).
    pub planned: u64,
    /// Members of the cluster summed over the incremental rounds.
    pub members: u64,
    /// Queues named by the reports taken in (a domain with rays queued, one entry of a
    /// report's map), summed: taking a report in and moving its rays cost its size, and a
    /// predictive report names about a hundred domains where a dynamic one names one (replays
    /// of 256-worker frames, README "A price for a report's size").
    pub queues: u64,
    /// Queue reports taken in, whether or not a round followed: each costs the coordinator
    /// its message and its member's figures (`RoundIndex::take_changes`) even when it names
    /// one queue, and a predictive frame at 4,096 workers takes 256,659 of them in 1,316
    /// rounds (README "Simulator": priced by the rounds alone, its coordinator was busy 1.05%
    /// of the frame where the machine replayed alone took 3.7%).
    pub reports: u64,
}

impl PlanningWork {
    /// What was planned since `before` (an earlier count of the same frame).
    pub fn since(&self, before: &PlanningWork) -> PlanningWork {
        PlanningWork {
            rounds: self.rounds.saturating_sub(before.rounds),
            whole_rounds: self.whole_rounds.saturating_sub(before.whole_rounds),
            whole_members: self.whole_members.saturating_sub(before.whole_members),
            planned: self.planned.saturating_sub(before.planned),
            members: self.members.saturating_sub(before.members),
            queues: self.queues.saturating_sub(before.queues),
            reports: self.reports.saturating_sub(before.reports),
        }
    }

    /// Adds `more` (another frame's, or another process's, count) to this count.
    pub fn add(&mut self, more: &PlanningWork) {
        self.rounds += more.rounds;
        self.whole_rounds += more.whole_rounds;
        self.whole_members += more.whole_members;
        self.planned += more.planned;
        self.members += more.members;
        self.queues += more.queues;
        self.reports += more.reports;
    }

    /// One round of `members` members planned from the whole cluster.
    fn whole(&mut self, members: usize) {
        self.rounds += 1;
        self.whole_rounds += 1;
        self.whole_members += members as u64;
    }

    /// The static schedules' one plan: every domain to its owner by a hash, drafting no
    /// member (its cost follows the domains only).
    fn owner_map(&mut self) {
        self.rounds += 1;
    }

    /// One incremental round of `members` members that gave `planned` of them new plans.
    fn incremental(&mut self, planned: usize, members: usize) {
        self.rounds += 1;
        self.planned += planned as u64;
        self.members += members as u64;
    }
}

/// What a frame's holders flushes did, counted since it started, so the simulator can price
/// them (`rayfarm_sim::cost`) as it prices rounds. A flush walks every member (each is owed
/// its class's pending lines, the whole map, or nothing) and makes the lines of each view
/// class and state once; each member owed them gets a reference to that one message, so its
/// cost follows the members and the lines made, not members x lines
/// (`RunningFrame::flush_holders`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FlushWork {
    /// Flushes made (due, and the frame had view classes to tell).
    pub flushes: u64,
    /// Members of the frame summed over the flushes.
    pub members: u64,
    /// Members sent a `Holders`, summed over the flushes.
    pub told: u64,
    /// Holder lines made, summed over the flushes: each message's lines once, however many
    /// members it went to.
    pub lines: u64,
}

impl FlushWork {
    /// What was flushed since `before` (an earlier count of the same frame).
    pub fn since(&self, before: &FlushWork) -> FlushWork {
        FlushWork {
            flushes: self.flushes.saturating_sub(before.flushes),
            members: self.members.saturating_sub(before.members),
            told: self.told.saturating_sub(before.told),
            lines: self.lines.saturating_sub(before.lines),
        }
    }

    /// Adds `more` (another frame's, or another process's, count) to this count.
    pub fn add(&mut self, more: &FlushWork) {
        self.flushes += more.flushes;
        self.members += more.members;
        self.told += more.told;
        self.lines += more.lines;
    }
}

/// What the frame needs to know about a worker.
#[derive(Clone, Debug)]
pub struct Member {
    pub peer_address: String,
    /// What the rounds know of it: its cache, latest report and current plan.
    rounds: rounds::Member,
    /// Segments it has traced for this frame (latest figure it sent).
    segments: u64,
    /// Whether it has sent a queue report in this (sub)frame (a loss clears the reports the
    /// rounds read, not this).
    reported: bool,
}

impl Member {
    pub fn new(peer_address: String, cache_bytes: u64) -> Self {
        Member {
            peer_address,
            rounds: rounds::Member::new(cache_bytes),
            segments: 0,
            reported: false,
        }
    }
}

impl AsRef<rounds::Member> for Member {
    fn as_ref(&self) -> &rounds::Member {
        &self.rounds
    }
}

impl AsMut<rounds::Member> for Member {
    fn as_mut(&mut self) -> &mut rounds::Member {
        &mut self.rounds
    }
}

/// A worker's whole report as the rounds read it.
fn queues(r: proto::QueueReport) -> rounds::Queues {
    rounds::Queues {
        round: r.round,
        resident: resident_once(r.resident_domains),
        queued: r.queued_rays,
        oldest_generation: r.oldest_generation,
        oldest_waiting: r.oldest_waiting,
    }
}

/// A report's resident domains in its order (least recently used first), each once.
fn resident_once(mut resident: Vec<u32>) -> Vec<u32> {
    // Checked on a sorted copy (a cache's worth of ids, every report): a set for each report
    // cost the 4,096-worker frame's coordinator a tenth more.
    let mut sorted = resident.clone();
    sorted.sort_unstable();
    if sorted.windows(2).any(|pair| pair[0] == pair[1]) {
        keep_first_of_each(&mut resident);
    }
    resident
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
    pub ledger: TileLedger,
    pub round: u64,
    /// What its planning rounds did, over all its subframes (`PlanningWork`).
    pub planning: PlanningWork,
    /// What its holders flushes did, over all its subframes (`FlushWork`).
    pub flushing: FlushWork,
    members: BTreeMap<u32, Member>,
    /// Keys of the members lost (a key is never given again): a holders line leaves them out.
    /// Asked for each key of every line a flush makes, this is nearly always empty, where
    /// looking each key up among the members was a tenth of predictive's coordinator at 4,096
    /// workers.
    lost: BTreeSet<u32>,
    /// The members' figures for asynchronous rounds, updated whenever a member's report, plan
    /// or presence changes (`touch`), so a dry member is planned without re-reading them all.
    index: RoundIndex,
    /// When it started, for its wall time and rate.
    pub started: Time,
    /// Domain loads the plans asked for.
    pub planned_loads: u64,
    options: Options,
    rounds: Rounds,
    /// Tiles not yet handed out (hybrid: demand-driven work for workers that run dry).
    hand_outs: HandOuts,
    /// Hybrid: which busy worker is asked to hand work to which idle one, once every tile is
    /// out (`tasks`).
    tasks: TaskDirections,
    /// Hybrid whose owned domains do not fit the caches: asynchronous rounds give each
    /// worker what its cache holds instead of one owner map (decided at the start).
    pub hybrid_rounds: bool,
    /// Ids of workers dropped because a peer could not reach them: they sit out the rest of
    /// this frame when they register again (they join the next one), or a worker that its
    /// peers cannot reach would be dropped, rejoin, get work and be dropped again, each time
    /// restarting every unfinished tile, for as long as its links are cut.
    pub sidelined: std::collections::BTreeSet<String>,
    /// Why each worker that declined this frame could not take part (they are left out of it).
    pub declined: Vec<String>,
    /// Members' reports of members they cannot reach, waiting to be judged.
    pub accusations: Accusations,
    /// Which member may send results of which tile.
    grants: Grants,
    /// The holders the members were last told, so a round sends only what changed.
    sent_holders: SentHolders,
    /// View classes of the holders' deltas (`holders::view`), fixed at the first asynchronous
    /// round from the members then.
    view_classes: Option<u32>,
    /// Busy members are told the holders at most once per this interval
    /// (`RunningFrame::flush_holders`); zero tells them after every round.
    holders_interval: std::time::Duration,
    /// What an asynchronous round's plans tell their workers to wait for the rays they move
    /// there before reporting again (`RoundPlan.report_hold_ms`).
    report_hold: ReportHold,
    /// Tile results refused as impossible (each dropped its sender).
    pub refused_results: u64,
    /// The job's samples as subframes (one for a one-pass job), and the one being rendered:
    /// each is a frame of its own on the workers (`frame_id`), its tiles committed into the
    /// same film (see [`RunningFrame::next_subframe`]).
    subframes: Vec<Samples>,
    pub subframe: usize,
    /// Whether a report taken since the last round asks for one (`plan_asked`).
    round_asked: bool,
    /// Queues named by the reports taken since the last round: counted in `planning` as the
    /// next round is asked for, so its tally carries them (`PlanningWork::queues`).
    queues_taken: u64,
    /// Reports taken since the last round, counted as `queues_taken` is
    /// (`PlanningWork::reports`).
    reports_taken: u64,
    /// Segments the members reported in this subframe, summed (kept as results come, so the
    /// progress published after every round does not walk the members).
    segments_now: u64,
    /// Rounds planned, and segments members reported, in the subframes committed before.
    rounds_before: u64,
    segments_before: u64,
}

fn msg(body: Body) -> Arc<proto::CoordinatorMessage> {
    Arc::new(proto::CoordinatorMessage { body: Some(body) })
}

impl RunningFrame {
    /// A frame of `spec` over a scene with domains of `domain_bytes` each, starting `now`.
    pub fn new(
        now: Time,
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
                copy_rays: 1,
            },
            _ => options,
        };
        let subframes = subframes::plan(&spec, frame.spp);
        let tiles = grid.count();
        let index = RoundIndex::new(&domain_bytes, schedule == Schedule::Predictive)
            .copying_from(options.copy_rays);
        Ok(RunningFrame {
            job_id,
            schedule,
            spec,
            frame,
            domain_bytes,
            ledger: TileLedger::new(grid, TILE_CREDIT).with_samples(subframes[0].count),
            round: 0,
            planning: PlanningWork::default(),
            flushing: FlushWork::default(),
            members: BTreeMap::new(),
            lost: BTreeSet::new(),
            index,
            started: now,
            planned_loads: 0,
            options,
            rounds,
            hand_outs: HandOuts::default(),
            tasks: TaskDirections::default(),
            hybrid_rounds: false,
            sidelined: Default::default(),
            declined: Vec::new(),
            accusations: Accusations::default(),
            grants: Grants::new(tiles),
            sent_holders: SentHolders::default(),
            view_classes: None,
            holders_interval: std::time::Duration::ZERO,
            report_hold: ReportHold::NONE,
            refused_results: 0,
            subframes,
            subframe: 0,
            round_asked: false,
            queues_taken: 0,
            reports_taken: 0,
            segments_now: 0,
            rounds_before: 0,
            segments_before: 0,
        })
    }

    /// Tells busy members the holders at most once per `interval` (zero: after every round):
    /// see [`RunningFrame::flush_holders`].
    pub fn with_holders_interval(mut self, interval: std::time::Duration) -> Self {
        self.holders_interval = interval;
        self
    }

    /// Tells the workers an asynchronous round plans to wait for the rays their plan moves to
    /// them before they report again.
    pub fn with_report_hold(mut self, hold: ReportHold) -> Self {
        self.report_hold = hold;
        self
    }

    /// The frame's roster, every member's peer address by key: one message that every member
    /// shares (a copy in each member's `StartFrame` made a 4,096-worker frame's start cost its
    /// coordinator 16.7 million address copies).
    fn roster_message(&self) -> Arc<proto::CoordinatorMessage> {
        msg(Body::Roster(proto::Roster {
            job_id: self.frame_id(),
            members: self
                .members
                .iter()
                .map(|(&k, m)| (k, m.peer_address.clone()))
                .collect(),
        }))
    }

    /// Member `key`'s `StartFrame`; the frame's roster follows it (`roster_message`).
    fn start_message(&self, key: u32, tiles: Vec<u32>) -> Arc<proto::CoordinatorMessage> {
        let mut spec = self.spec.clone();
        // Caches are dropped before the job, not before each of its subframes.
        spec.cold_cache &= self.subframe == 0;
        let samples = self.samples();
        msg(Body::StartFrame(proto::StartFrame {
            worker_key: key,
            job_id: self.frame_id(),
            spec: Some(spec),
            first_sample: samples.first,
            sample_count: samples.count,
            hybrid_rounds: self.hybrid_rounds,
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
                self.hand_outs = HandOuts::new(count, n as usize);
                (0..n).map(|_| self.hand_outs.next_batch()).collect()
            }
            _ => {
                let all: Vec<u32> = (0..count).collect();
                (0..n as usize)
                    .map(|i| strided_share(&all, i, n as usize))
                    .collect()
            }
        };
        let keys: Vec<u32> = workers.iter().map(|&(k, _)| k).collect();
        if self.schedule == Schedule::Hybrid {
            let caches: Vec<u64> = workers.iter().map(|(_, m)| m.rounds.cache_bytes).collect();
            self.hybrid_rounds = !owned_domains_fit(&self.domain_bytes, &caches);
            if self.hybrid_rounds {
                info!(
                    "hybrid: the owned domains do not fit the caches; rounds give each worker what its cache holds"
                );
            }
        }
        self.members.extend(workers);
        for &k in &keys {
            self.touch(k);
            self.tasks.joined(k);
        }
        // Each member's StartFrame is first on its stream, the roster right behind it (a
        // member's pair goes out before the next member's, so none waits behind every other
        // member's start for its peers).
        let roster = self.roster_message();
        let mut out: Vec<Outgoing> = Vec::with_capacity(2 * keys.len());
        for (key, tiles) in keys.into_iter().zip(tiles) {
            self.grants.deal(key, &tiles);
            out.push((key, self.start_message(key, tiles)));
            out.push((key, Arc::clone(&roster)));
        }
        if self.owners_once() {
            out.extend(self.owner_plans());
        }
        out
    }

    /// Lets a worker that registered mid-frame take part from the next round; the others
    /// learn its key and address.
    pub fn join(&mut self, key: u32, member: Member) -> Vec<Outgoing> {
        self.members.insert(key, member);
        self.sent_holders.forget(key);
        // It holds no map: the next flush tells it the whole one, whether or not a round
        // changes anything first (rays it holds for domains others hold wait for that; a
        // joiner whose rays were all for held domains, with every member dry and no plan to
        // change, waited for ever: `rayfarm sim` predictive seed 2364 of stop 47).
        self.sent_holders.mark_dirty();
        self.touch(key);
        self.tasks.joined(key);
        // One roster for every member, the newcomer's behind its StartFrame, shared as a
        // flush's holders are (`Outgoing`).
        let mut out = vec![(key, self.start_message(key, Vec::new()))];
        let roster = self.roster_message();
        out.extend(self.members.keys().map(|&k| (k, Arc::clone(&roster))));
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
        self.lost.insert(key);
        self.segments_now -= lost.segments;
        self.sent_holders.forget(key);
        self.touch(key);
        // Requests to it or for it are void, and it is never asked again, whatever becomes
        // of the frame.
        self.tasks.lose(key);
        if self.members.is_empty() {
            return Some(Vec::new());
        }
        let unfinished: Vec<u32> = self.ledger.unfinished().collect();
        let bumped = self.ledger.bump(&unfinished);
        self.grants.withdraw(bumped.iter().map(|&(t, _)| t));
        info!(tiles = bumped.len(), "epochs bumped after losing a worker");
        // One message every member shares, as the roster is.
        let bump = msg(Body::EpochBump(proto::EpochBump {
            job_id: self.frame_id(),
            epochs: bumped.iter().copied().collect(),
            lost_peers: vec![lost.peer_address],
        }));
        let keys: Vec<u32> = self.members.keys().copied().collect();
        let mut out: Vec<Outgoing> = keys.iter().map(|&k| (k, Arc::clone(&bump))).collect();
        // What members reported before the bump counted rays they have now dropped.
        for m in self.members.values_mut() {
            m.rounds.report = None;
        }
        let keys: Vec<u32> = self.members.keys().copied().collect();
        for &k in &keys {
            self.touch(k);
        }
        // The new owners go out before the re-dealt tiles: a worker traces a hand-out as soon
        // as it arrives, and under the old plan the rays leaving its tiles would be routed to
        // the lost worker, whose link holds them until it gives up (the frame never ended).
        if self.owners_once() {
            out.extend(self.owner_plans());
        }
        let tiles: Vec<u32> = bumped.into_iter().map(|(t, _)| t).collect();
        if self.schedule == Schedule::Hybrid {
            // Whoever runs dry first takes them, as before.
            self.hand_outs.refill(tiles);
            for &k in &keys {
                let tiles = self.hand_outs.next_batch();
                out.push((k, self.hand_out(k, tiles)));
            }
        } else {
            for (i, &k) in keys.iter().enumerate() {
                let share = strided_share(&tiles, i, keys.len());
                out.push((k, self.hand_out(k, share)));
            }
        }
        Some(out)
    }

    /// Deals `tiles`' camera rays to `key`: the message that says so.
    fn hand_out(&mut self, key: u32, tiles: Vec<u32>) -> Arc<proto::CoordinatorMessage> {
        self.grants.deal(key, &tiles);
        msg(Body::HandOutTiles(proto::HandOutTiles {
            job_id: self.frame_id(),
            tiles,
        }))
    }

    /// Records a queue report and plans the round it asks for at once: [`Self::take_report`]
    /// then [`Self::plan_asked`], for a caller that hands the frame one report at a time.
    pub fn report(
        &mut self,
        key: u32,
        report: proto::QueueReport,
    ) -> Result<Vec<Outgoing>, String> {
        let read = queue_report::read(&report)?;
        let mut out = self.take_report(key, report, read)?;
        out.extend(self.plan_asked());
        Ok(out)
    }

    /// Records a queue report; what it asks of the rounds waits for [`Self::plan_asked`], so
    /// the reports a busy coordinator received meanwhile are planned in one round (under
    /// asynchronous rounds, every member that ran dry among them is drafted together, as
    /// `RoundIndex::dry_plans` plans any number of dry members). Returns what does not wait:
    /// the hybrid schedule's demand-driven tiles and task requests. The static schedules
    /// decide once and never plan again. A report naming only what changed
    /// (`QueueReport.delta`, its queues as `read` once by the caller) is put into the
    /// member's last; an error if it cannot be right (the worker must be dropped).
    pub fn take_report(
        &mut self,
        key: u32,
        report: proto::QueueReport,
        read: queue_report::Read,
    ) -> Result<Vec<Outgoing>, String> {
        let Some(member) = self.members.get_mut(&key) else {
            return Ok(Vec::new());
        };
        self.queues_taken += (report.queued_rays.len() + report.cleared_domains.len()) as u64;
        self.reports_taken += 1;
        match read {
            queue_report::Read::Changes(queues) => {
                if !self.take_changes(key, report, queues) {
                    return Ok(Vec::new());
                }
            }
            queue_report::Read::Whole => {
                member.rounds.report = Some(queues(report));
                self.index.reported_whole(key);
                self.touch(key);
            }
        }
        let Some(member) = self.members.get_mut(&key) else {
            return Ok(Vec::new());
        };
        member.reported = true;
        // Just taken in, the report is the worker's own (the rounds have moved nothing yet).
        let queued: u64 = match (self.schedule, member.rounds.report.as_ref()) {
            (Schedule::Hybrid, Some(r)) => r.queued.values().sum(),
            _ => 0,
        };
        Ok(match self.schedule {
            Schedule::Dynamic | Schedule::Predictive | Schedule::Unspecified => {
                self.round_asked = true;
                Vec::new()
            }
            Schedule::Hybrid => {
                self.round_asked |= self.hybrid_rounds;
                self.demand_driven(key, queued)
            }
            _ => Vec::new(),
        })
    }

    /// Puts `report`, which names only the queues that changed since member `key`'s last,
    /// into that one (`RoundIndex::take_changes`). False if there is no report to put it
    /// into: the frame forgot every member's at a worker's loss (`lose`), and a report sent
    /// before the worker heard of it is dropped (its next, after it did, is whole).
    fn take_changes(
        &mut self,
        key: u32,
        report: proto::QueueReport,
        queues: Vec<(u32, Queue)>,
    ) -> bool {
        let changes = Changes {
            queues,
            round: report.round,
            resident: resident_once(report.resident_domains),
            oldest_waiting: report.oldest_waiting,
        };
        self.index.take_changes(key, &mut self.members, changes)
    }

    /// Plans the round the reports taken since the last one ask for, if any: under barrier
    /// rounds the next round when every member has finished the current one and some ray is
    /// queued somewhere, under asynchronous rounds every member that ran dry.
    pub fn plan_asked(&mut self) -> Vec<Outgoing> {
        self.planning.queues += std::mem::take(&mut self.queues_taken);
        self.planning.reports += std::mem::take(&mut self.reports_taken);
        if !std::mem::take(&mut self.round_asked) {
            return Vec::new();
        }
        match self.rounds {
            Rounds::Barrier if self.schedule != Schedule::Hybrid => self.plan_if_round_over(),
            _ => self.plan_dry_members(),
        }
    }

    /// Hybrid: a worker that reports has run out of work it may trace. While tiles are left
    /// it gets more; then, with nothing queued at all, a busy worker is asked to hand it part
    /// of its queue (`tasks`).
    fn demand_driven(&mut self, key: u32, queued: u64) -> Vec<Outgoing> {
        if !self.hand_outs.is_empty() {
            let tiles = self.hand_outs.next_batch();
            return vec![(key, self.hand_out(key, tiles))];
        }
        if queued > 0 {
            self.tasks.busy(key, queued);
            return Vec::new();
        }
        let direction = self.tasks.ran_dry(key);
        direction.into_iter().map(|d| self.share(d)).collect()
    }

    /// Hybrid: a busy worker's answer to a `ShareTasks`: the next requests, if any.
    pub fn tasks_shared(&mut self, key: u32, answer: &proto::TasksShared) -> Vec<Outgoing> {
        if self.schedule != Schedule::Hybrid || !self.members.contains_key(&key) {
            return Vec::new();
        }
        let directions = self.tasks.answered(key, answer.rays, answer.queued);
        directions.into_iter().map(|d| self.share(d)).collect()
    }

    /// Task requests made and rays the donors said they moved.
    pub fn task_counts(&self) -> (u64, u64) {
        (self.tasks.requests, self.tasks.rays_moved)
    }

    /// The `ShareTasks` for `d`, to its donor. The receiver may now be sent rays of any tile,
    /// so it is named a holder (`Grants`).
    fn share(&mut self, d: Direction) -> Outgoing {
        self.grants.name_holder(d.receiver);
        let receiver = &self.members[&d.receiver];
        let receiver_domains = receiver
            .rounds
            .report
            .as_ref()
            .map(|r| r.resident.clone())
            .unwrap_or_default();
        debug!(
            donor = d.donor,
            receiver = d.receiver,
            "asking a busy worker to share tasks"
        );
        let body = Body::ShareTasks(proto::ShareTasks {
            job_id: self.frame_id(),
            to: receiver.peer_address.clone(),
            receiver_domains,
            max_rays: TASK_RAYS,
        });
        (d.donor, msg(body))
    }

    /// Accepts a worker's tile results. Returns the tiles they committed with their sums,
    /// taken out of the ledger for the film, and why the rest was refused if a result
    /// cannot be right (the worker must be dropped; nothing after it was counted): more
    /// credit than the tile has outstanding or its pixels can hold, or a tile of which it
    /// was never given a ray (`Grants`).
    pub fn results(
        &mut self,
        key: u32,
        results: proto::TileResults,
    ) -> (Vec<CommittedTile>, Option<String>) {
        let (committed, refused) = self.accept_results(key, results);
        if refused.is_some() {
            self.refused_results += 1;
        }
        (committed, refused)
    }

    fn accept_results(
        &mut self,
        key: u32,
        results: proto::TileResults,
    ) -> (Vec<CommittedTile>, Option<String>) {
        if let Some(m) = self.members.get_mut(&key) {
            let now = m.segments.max(results.segments_traced);
            self.segments_now += now - m.segments;
            m.segments = now;
        }
        let mut committed = Vec::new();
        for r in results.results {
            let pixels = self.ledger.grid().tile_pixel_count(r.tile);
            let sums = match tile_sums::decode(&r.sums, pixels) {
                Ok(sums) => sums,
                Err(e) => return (committed, Some(format!("tile {}: {e}", r.tile))),
            };
            // An older epoch is ignored by the ledger whoever sends it, a newer one refused.
            if self.ledger.epoch(r.tile) == Some(r.epoch) && !self.grants.may_send(key, r.tile) {
                let why = format!(
                    "result for tile {} at epoch {}, of which this worker was given no ray \
                     (its camera rays went to another worker, and it holds no domain)",
                    r.tile, r.epoch
                );
                return (committed, Some(why));
            }
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

    /// Progress for watchers `now`: (tiles done in the current subframe, tiles, segments
    /// per second, ETA seconds or -1). The ETA counts samples: a subframe's tiles weigh its
    /// samples.
    pub fn progress(&self, now: Time) -> (u32, u32, f64, f64) {
        let done = self.ledger.tiles_done();
        let total = self.ledger.grid().count();
        let elapsed = now.since(self.started).as_secs_f64();
        let segments = self.segments_before + self.segments_now;
        let samples = self.samples();
        let spp = f64::from(self.frame.spp.max(1));
        let fraction = (f64::from(samples.first)
            + f64::from(samples.count) * f64::from(done) / f64::from(total.max(1)))
            / spp;
        let eta = if fraction <= 0.0 {
            -1.0
        } else {
            elapsed * (1.0 - fraction) / fraction
        };
        (done, total, segments as f64 / elapsed.max(1e-9), eta)
    }
}

#[path = "lifecycle.rs"]
pub mod lifecycle;

#[path = "planning.rs"]
mod planning;

#[path = "subframes.rs"]
pub mod subframes;

#[cfg(test)]
#[path = "frame_tests.rs"]
mod tests;
