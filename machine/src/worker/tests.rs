//! The worker machine driven as a plain value: events in, actions checked; no process, socket,
//! file or clock. Passes are not run: a test answers a StartPass with the PassFinished it
//! wants the machine to react to.

use std::collections::{BTreeMap, HashMap};
use std::time::Duration;

use rayfarm_core::bundler::Tier;
use rayfarm_core::ray::RayRecord;
use rayfarm_core::tile::TileGrid;
use rayfarm_core::wire::{self, BatchLimits, VerdictRecord};
use rayfarm_proto::{self as proto, Schedule, coordinator_message::Body as FromCoordinator};

use super::*;
use crate::Time;

const JOB: &str = "job-1";
const DOMAINS: usize = 3;

fn worker() -> Worker<MemorySpill> {
    Worker::new(WorkerConfig::new("w1".into(), "me:1".into(), 1 << 30)).unwrap()
}

/// A StartFrame of an 8x8 frame in 4x4 tiles (tiles 0..4).
fn start(job: &str, schedule: Schedule, tiles: &[u32]) -> proto::StartFrame {
    proto::StartFrame {
        job_id: job.into(),
        spec: Some(proto::JobSpec {
            schedule: schedule as i32,
            ..Default::default()
        }),
        tile_size: 4,
        primary_tiles: tiles.to_vec(),
        ..Default::default()
    }
}

/// The frame's roster, [`NAMES`], as the coordinator sends it behind each StartFrame.
fn roster(job: &str) -> Event<MemorySpill> {
    control(FromCoordinator::Roster(proto::Roster {
        job_id: job.into(),
        members: NAMES
            .iter()
            .enumerate()
            .map(|(k, n)| (k as u32, n.to_string()))
            .collect(),
    }))
}

/// `w` opens a frame of `schedule` with no tiles of its own, holding `resident` mapped from
/// earlier frames, and takes its roster.
fn open_holding(w: &mut Worker<MemorySpill>, schedule: Schedule, resident: Vec<u32>) {
    w.handle(
        Time(0),
        Event::FrameOpened {
            start: start(JOB, schedule, &[]),
            opened: Ok(OpenedScene {
                resident,
                ..scene()
            }),
        },
    );
    w.handle(Time(0), roster(JOB));
}

/// `w` opens a frame and takes its roster, at `now`: the actions of both.
fn open(
    w: &mut Worker<MemorySpill>,
    now: Time,
    job: &str,
    schedule: Schedule,
    tiles: &[u32],
) -> Vec<Action> {
    let mut actions = w.handle(now, opened(job, schedule, tiles));
    actions.extend(w.handle(now, roster(job)));
    actions
}

fn scene() -> OpenedScene<MemorySpill> {
    let limits = BatchLimits {
        domains: DOMAINS as u32,
        pixels: 64,
        max_depth: 8,
        materials: 1,
        max_records: 1 << 20,
    };
    OpenedScene {
        grid: TileGrid::new(8, 8, 4).unwrap(),
        spp: 1,
        limits,
        domain_bytes: vec![1000; DOMAINS].into(),
        resident: Vec::new(),
        queues: DomainQueues::new(DOMAINS, 1 << 20, 1 << 20, MemorySpill::default()),
    }
}

fn opened(job: &str, schedule: Schedule, tiles: &[u32]) -> Event<MemorySpill> {
    Event::FrameOpened {
        start: start(job, schedule, tiles),
        opened: Ok(scene()),
    }
}

fn control(body: FromCoordinator) -> Event<MemorySpill> {
    Event::Control(proto::CoordinatorMessage { body: Some(body) })
}

fn plan(round: u64, work_on: &[u32], holders: &[(u32, &str)]) -> Event<MemorySpill> {
    control(FromCoordinator::RoundPlan(proto::RoundPlan {
        job_id: JOB.into(),
        round,
        work_on: work_on.to_vec(),
        holders: holders_of(holders),
        ..Default::default()
    }))
}

/// The frame's workers by key (its roster): this one (`me:1`) is key 0.
const NAMES: [&str; 6] = ["me:1", "a:1", "b:1", "c:1", "d:1", "gone:1"];

/// A worker's key in [`NAMES`].
fn key_of(address: &str) -> u32 {
    NAMES
        .iter()
        .position(|n| *n == address)
        .expect("in the roster") as u32
}

/// Holders by address, as the coordinator names them: by key.
fn holders_of(holders: &[(u32, &str)]) -> Vec<proto::DomainHolders> {
    holders
        .iter()
        .map(|&(domain, w)| proto::DomainHolders {
            domain,
            workers: vec![key_of(w)],
            lost: Vec::new(),
        })
        .collect()
}

/// A ray a batch may carry, of `tile` and `epoch`, queued for `domain`.
pub(super) fn ray(tile: u32, epoch: u32, domain: u32, pixel: u32) -> RayRecord {
    RayRecord {
        tile,
        epoch,
        domain,
        pixel,
        dir: [0.0, 0.0, 1.0],
        t_max: 1.0,
        ..bytemuck::Zeroable::zeroed()
    }
}

fn bundle(job: &str, rays: &[RayRecord]) -> Event<MemorySpill> {
    Event::PeerBundle {
        sender: "peer:1".into(),
        job_id: job.into(),
        payload: Payload::Rays(vec![rays.to_vec()]),
    }
}

/// An empty pass's end, the cache then holding `resident` (least recently used first).
fn finished_holding(resident: Vec<u32>) -> Event<MemorySpill> {
    Event::PassFinished {
        job_id: JOB.into(),
        result: Ok(PassOutput::default()),
        resident,
    }
}

fn finished(out: PassOutput) -> Event<MemorySpill> {
    Event::PassFinished {
        job_id: JOB.into(),
        result: Ok(out),
        resident: Vec::new(),
    }
}

/// `w` with a dynamic frame open (time 0), planned on domain 0 (1) and a pass tracing one ray
/// of it (2).
fn tracing_a_ray(w: &mut Worker<MemorySpill>) {
    open(w, Time(0), JOB, Schedule::Dynamic, &[]);
    w.handle(Time(1), plan(1, &[0], &[]));
    assert!(pass_started(&w.handle(Time(2), bundle(JOB, &[ray(0, 0, 0, 1)]))).is_some());
}

/// Rays sent to each peer by `actions` in the migrated-ray tier.
fn rays_sent(actions: &[Action]) -> BTreeMap<String, Vec<RayRecord>> {
    sent_in(actions, Tier::Migrated)
}

/// Rays sent to each peer by `actions` in `tier`.
fn sent_in(actions: &[Action], tier: Tier) -> BTreeMap<String, Vec<RayRecord>> {
    let mut out: BTreeMap<String, Vec<RayRecord>> = BTreeMap::new();
    for a in actions {
        if let Action::ToPeer {
            peer,
            tier: t,
            batches,
            ..
        } = a
            && *t == tier
        {
            for b in batches {
                let rays = wire::decode_batch(b, &BatchLimits::any_frame(1 << 20)).unwrap();
                out.entry(peer.clone()).or_default().extend(rays);
            }
        }
    }
    out
}

fn queue_reports(actions: &[Action]) -> Vec<&proto::QueueReport> {
    actions
        .iter()
        .filter_map(|a| match a {
            Action::ToCoordinator(proto::worker_message::Body::QueueReport(r)) => Some(r),
            _ => None,
        })
        .collect()
}

fn pass_started(actions: &[Action]) -> Option<&PassWork> {
    actions.iter().find_map(|a| match a {
        Action::StartPass { work, .. } => Some(work),
        _ => None,
    })
}

#[test]
fn a_batch_goes_to_the_holder_the_latest_plan_names() {
    let mut w = worker();
    open(&mut w, Time(0), JOB, Schedule::Dynamic, &[]);
    w.handle(Time(1), plan(1, &[0], &[(1, "b:1"), (2, "c:1")]));
    let rays = [ray(0, 0, 1, 5), ray(0, 0, 2, 6)];
    let sent = rays_sent(&w.handle(Time(2), bundle(JOB, &rays)));
    assert_eq!(sent["b:1"], [rays[0]]);
    assert_eq!(sent["c:1"], [rays[1]]);
    // Another worker's plan changed: domain 1 is d's now.
    w.handle(
        Time(3),
        control(FromCoordinator::Holders(proto::Holders {
            job_id: JOB.into(),
            holders: holders_of(&[(1, "d:1")]),
            delta: false,
        })),
    );
    let sent = rays_sent(&w.handle(Time(4), bundle(JOB, &rays)));
    assert_eq!(sent.keys().collect::<Vec<_>>(), ["d:1"]);
    assert_eq!(
        w.frame().unwrap().queue_sizes(),
        BTreeMap::from([(2, 1)]),
        "a domain no one holds waits here"
    );
    assert_eq!(w.frame().unwrap().counters.rays_received, 4);
    // A delta names what changed: domain 1 gains c and loses d; domain 2 gains b.
    let actions = w.handle(
        Time(5),
        control(FromCoordinator::Holders(proto::Holders {
            job_id: JOB.into(),
            holders: vec![
                proto::DomainHolders {
                    domain: 1,
                    workers: vec![key_of("c:1")],
                    lost: vec![key_of("d:1")],
                },
                proto::DomainHolders {
                    domain: 2,
                    workers: vec![key_of("b:1")],
                    lost: Vec::new(),
                },
            ],
            delta: true,
        })),
    );
    assert_eq!(
        rays_sent(&actions)["b:1"],
        [rays[1]],
        "the ray waiting for domain 2 leaves"
    );
    let sent = rays_sent(&w.handle(Time(6), bundle(JOB, &rays)));
    assert_eq!(sent["c:1"], [rays[0]]);
    assert_eq!(sent["b:1"], [rays[1]]);
}

#[test]
fn domain_schedule_rays_queued_before_the_plan_go_to_their_owner_though_mapped_here() {
    // A real frame hung this way: the first pass ended before the owners' plan came, its rays
    // waited here for every domain, and those of domains the worker had mapped from earlier
    // frames but does not own stayed, traced by no one.
    let mut w = worker();
    open_holding(&mut w, Schedule::Domain, vec![0, 1, 2]);
    let rays = [ray(0, 0, 0, 1), ray(0, 0, 1, 2), ray(0, 0, 2, 3)];
    let early = w.handle(Time(1), bundle(JOB, &rays));
    assert!(rays_sent(&early).is_empty(), "no owner known yet");
    // The domain schedule's plan, as the coordinator sends it: owners packed.
    let owners = ["me:1", "b:1", "b:1"].map(|w| key_of(w) + 1).to_vec();
    let mut out = w.handle(
        Time(2),
        control(FromCoordinator::RoundPlan(proto::RoundPlan {
            job_id: JOB.into(),
            round: 1,
            work_on: vec![0],
            sole_holders: owners,
            ..Default::default()
        })),
    );
    let work = pass_started(&out).expect("its own domain traced");
    assert_eq!(
        work.trace.as_ref().map(|(d, r)| (*d, r.len())),
        Some((0, 1))
    );
    // The others are on their way to their owner (bundled: they go out within a second).
    out.extend(w.handle(Time::from_duration(Duration::from_secs(1)), Event::Tick));
    assert_eq!(rays_sent(&out)["b:1"], [rays[1], rays[2]]);
}

#[test]
fn rays_for_a_peer_wait_here_until_the_roster_behind_the_start_names_it() {
    let mut w = worker();
    w.handle(Time(0), opened(JOB, Schedule::Dynamic, &[]));
    // The frame knows no address yet, so a holder's key names nobody: its rays stay here.
    w.handle(Time(1), plan(1, &[0], &[(1, "b:1")]));
    let rays = [ray(0, 0, 1, 5)];
    assert!(rays_sent(&w.handle(Time(2), bundle(JOB, &rays))).is_empty());
    assert_eq!(w.frame().unwrap().queue_sizes(), BTreeMap::from([(1, 1)]));
    let mut out = w.handle(Time(3), roster(JOB));
    out.extend(w.handle(Time::from_duration(Duration::from_secs(1)), Event::Tick));
    assert_eq!(rays_sent(&out)["b:1"], rays, "{out:?}");
}

#[test]
fn rays_kept_for_a_mapped_domain_leave_when_a_pass_pushes_it_out_of_the_cache() {
    let mut w = worker();
    open_holding(&mut w, Schedule::Dynamic, vec![1]);
    // Domain 1 is b's this round, but mapped here: its rays are traced here meanwhile.
    w.handle(Time(1), plan(1, &[0], &[(1, "b:1")]));
    let started = w.handle(Time(2), bundle(JOB, &[ray(0, 0, 0, 4)]));
    assert!(pass_started(&started).is_some(), "domain 0's pass runs");
    let rays = [ray(0, 0, 1, 5)];
    assert!(rays_sent(&w.handle(Time(3), bundle(JOB, &rays))).is_empty());
    // The pass loaded domain 0 and the cache let domain 1 go: its ray is b's now, at once
    // (the coordinator heard it queued here and plans nothing more for it).
    let mut out = w.handle(Time(4), finished_holding(vec![0]));
    out.extend(w.handle(Time::from_duration(Duration::from_secs(1)), Event::Tick));
    assert_eq!(rays_sent(&out)["b:1"], rays, "{out:?}");
}

#[test]
fn a_whole_maps_packed_holders_route_as_lines_do_and_a_delta_has_none() {
    let mut w = worker();
    open(&mut w, Time(0), JOB, Schedule::Dynamic, &[]);
    // Domain 1 is b's alone (packed), domain 2 c's and d's (a line), domain 3 nobody's.
    let packed = |round, delta, sole: &[&str]| {
        control(FromCoordinator::RoundPlan(proto::RoundPlan {
            job_id: JOB.into(),
            round,
            work_on: vec![0],
            holders: if delta {
                Vec::new()
            } else {
                vec![proto::DomainHolders {
                    domain: 2,
                    workers: vec![key_of("c:1"), key_of("d:1")],
                    lost: Vec::new(),
                }]
            },
            holders_delta: delta,
            sole_holders: sole
                .iter()
                .map(|w| if w.is_empty() { 0 } else { key_of(w) + 1 })
                .collect(),
            ..Default::default()
        }))
    };
    w.handle(Time(1), packed(1, false, &["me:1", "b:1", ""]));
    let rays = [ray(0, 0, 1, 0), ray(0, 0, 2, 0), ray(0, 0, 2, 1)];
    let sent = rays_sent(&w.handle(Time(2), bundle(JOB, &rays)));
    assert_eq!(sent["b:1"], [rays[0]]);
    assert_eq!(
        (&sent["c:1"], &sent["d:1"]),
        (&vec![rays[1]], &vec![rays[2]])
    );
    // A delta with packed holders (which a delta never has) changes nobody's domains.
    w.handle(Time(3), packed(2, true, &["", "a:1", "a:1"]));
    let sent = rays_sent(&w.handle(Time(4), bundle(JOB, &rays)));
    assert_eq!(sent["b:1"], [rays[0]]);
    assert_eq!(
        (&sent["c:1"], &sent["d:1"]),
        (&vec![rays[1]], &vec![rays[2]])
    );
}

#[test]
fn a_stale_epochs_rays_are_dropped() {
    let mut w = worker();
    open(&mut w, Time(0), JOB, Schedule::Dynamic, &[]);
    w.handle(Time(1), plan(1, &[0], &[]));
    let bump = control(FromCoordinator::EpochBump(proto::EpochBump {
        job_id: JOB.into(),
        epochs: HashMap::from([(1, 2)]),
        lost_peers: vec!["gone:1".into()],
    }));
    let actions = w.handle(Time(2), bump);
    assert!(
        actions
            .iter()
            .any(|a| matches!(a, Action::DropPeers(p) if p == &["gone:1".to_string()])),
        "{actions:?}"
    );
    let stale = ray(1, 1, 0, 20);
    let current = ray(1, 2, 0, 21);
    assert!(pass_started(&w.handle(Time(3), bundle(JOB, &[stale]))).is_none());
    let actions = w.handle(Time(4), bundle(JOB, &[stale, current]));
    let work = pass_started(&actions).expect("the current ray is traced");
    assert_eq!(work.trace, Some((0, vec![current])));
}

fn bump(tile: u32, epoch: u32, lost: &str) -> Event<MemorySpill> {
    control(FromCoordinator::EpochBump(proto::EpochBump {
        job_id: JOB.into(),
        epochs: HashMap::from([(tile, epoch)]),
        lost_peers: vec![lost.into()],
    }))
}

#[test]
fn a_peers_rays_of_an_epoch_not_yet_heard_of_here_wait_for_the_bump() {
    // A worker was lost; the coordinator's bump reached a peer first, and that peer sends
    // rays of its re-dealt tiles at the new epoch before the bump arrives here.
    let mut w = worker();
    open(&mut w, Time(0), JOB, Schedule::Dynamic, &[]);
    w.handle(Time(1), plan(1, &[0], &[]));
    let early = ray(1, 1, 0, 21);
    let actions = w.handle(Time(2), bundle(JOB, &[early]));
    assert!(
        pass_started(&actions).is_none(),
        "traced before the coordinator announced its epoch: {actions:?}"
    );
    let actions = w.handle(Time(3), bump(1, 1, "gone:1"));
    let work = pass_started(&actions).expect("the bump lets the held ray through");
    assert_eq!(work.trace, Some((0, vec![early])));
    w.handle(Time(4), finished(PassOutput::default()));
    // The tile's old epoch is stale here now, as everywhere else.
    let stale = ray(1, 0, 0, 20);
    assert!(pass_started(&w.handle(Time(5), bundle(JOB, &[stale]))).is_none());
}

#[test]
fn a_forged_ray_of_a_future_epoch_drops_no_real_rays() {
    // A node with the cluster credentials sends one ray of a far epoch for tile 1: the
    // tile's real rays here stay current and are traced; the forged one waits for a bump
    // the coordinator never sends, and goes with the frame.
    let mut w = worker();
    open(&mut w, Time(0), JOB, Schedule::Dynamic, &[]);
    w.handle(Time(1), plan(1, &[0], &[]));
    let real = ray(1, 0, 0, 20);
    let forged = ray(1, 9, 0, 22);
    let actions = w.handle(Time(2), bundle(JOB, &[forged, real]));
    let work = pass_started(&actions).expect("the real ray is traced");
    assert_eq!(work.trace, Some((0, vec![real])));
    // A bump to an epoch below the forged one moves the tile on; the forged ray still waits.
    w.handle(Time(3), finished(PassOutput::default()));
    let actions = w.handle(Time(4), bump(1, 1, "gone:1"));
    assert!(pass_started(&actions).is_none(), "{actions:?}");
}

#[test]
fn more_rays_of_unannounced_epochs_than_the_cap_leave_the_frame() {
    let mut w = Worker::new(WorkerConfig {
        ahead_bytes: 2 * std::mem::size_of::<RayRecord>() as u64,
        ..WorkerConfig::new("w1".into(), "me:1".into(), 1 << 30)
    })
    .unwrap();
    open(&mut w, Time(0), JOB, Schedule::Dynamic, &[]);
    w.handle(Time(1), plan(1, &[0], &[]));
    let ahead: Vec<RayRecord> = (0..3).map(|p| ray(1, 4, 0, p)).collect();
    assert!(frame_reports(&w.handle(Time(2), bundle(JOB, &ahead[..2]))).is_empty());
    let actions = w.handle(Time(3), bundle(JOB, &ahead[2..]));
    let reports = frame_reports(&actions);
    let report = reports.first().expect("a frame report");
    assert!(report.declined, "{report:?}");
    assert!(report.error.contains("not announced"), "{}", report.error);
    assert!(w.frame().is_none());
}

#[test]
fn a_pass_that_empties_the_planned_queues_is_reported_once() {
    let mut w = worker();
    open(&mut w, Time(0), JOB, Schedule::Dynamic, &[]);
    let actions = w.handle(Time(1), plan(1, &[0], &[]));
    assert_eq!(
        queue_reports(&actions).len(),
        1,
        "nothing queued: the round ends"
    );
    let actions = w.handle(Time(2), bundle(JOB, &[ray(0, 0, 0, 1)]));
    assert!(pass_started(&actions).is_some());
    assert!(queue_reports(&actions).is_empty(), "busy: no report");
    let actions = w.handle(Time(3), finished(PassOutput::default()));
    let reports = queue_reports(&actions);
    assert_eq!(reports.len(), 1, "{actions:?}");
    assert_eq!((reports[0].round, reports[0].queued_rays.len()), (1, 0));
    assert!(queue_reports(&w.handle(Time(4), Event::Tick)).is_empty());
    assert!(queue_reports(&w.handle(Time(5), Event::Tick)).is_empty());
}

#[test]
fn the_report_lists_mapped_domains_in_the_caches_order_of_use() {
    let mut w = worker();
    tracing_a_ray(&mut w);
    // The cache's order, least recently used first: the coordinator evicts in it, so domain
    // 0, traced last, is not the first to go though its id is the lowest.
    let actions = w.handle(Time(3), finished_holding(vec![3, 2, 0]));
    let reports = queue_reports(&actions);
    assert_eq!(reports.len(), 1, "{actions:?}");
    assert_eq!(reports[0].resident_domains, [3, 2, 0]);
}

/// The domains `actions` ask the shell to evict.
fn evicted(actions: &[Action]) -> Vec<u32> {
    actions
        .iter()
        .filter_map(|a| match a {
            Action::Evict(domains) => Some(domains.clone()),
            _ => None,
        })
        .flatten()
        .collect()
}

#[test]
fn a_plan_evicts_the_domain_a_pass_is_tracing_when_the_pass_ends() {
    let mut w = worker();
    tracing_a_ray(&mut w);
    let evicting = |round: u64, work_on: Vec<u32>, evict: Vec<u32>| {
        control(FromCoordinator::RoundPlan(proto::RoundPlan {
            job_id: JOB.into(),
            round,
            work_on,
            evict,
            ..Default::default()
        }))
    };
    // The pass on domain 0 runs; the next plan moves this worker to domain 1 and evicts 0
    // and 2. Domain 2 goes now; domain 0 when its pass ends (now, the pass would load it
    // again), and the report after it does not list it.
    assert_eq!(
        evicted(&w.handle(Time(3), evicting(2, vec![1], vec![0, 2]))),
        [2]
    );
    let done = w.handle(Time(4), finished_holding(vec![0]));
    assert_eq!(evicted(&done), [0], "{done:?}");
    let reports = queue_reports(&done);
    assert_eq!(reports.len(), 1, "{done:?}");
    assert!(reports[0].resident_domains.is_empty(), "{done:?}");
    // A plan that works on the domain again before the pass ends keeps it.
    let mut w = worker();
    tracing_a_ray(&mut w);
    assert!(evicted(&w.handle(Time(3), evicting(2, vec![1], vec![0]))).is_empty());
    assert!(evicted(&w.handle(Time(4), evicting(3, vec![0], vec![]))).is_empty());
    let done = w.handle(Time(5), finished_holding(vec![0]));
    assert!(evicted(&done).is_empty(), "{done:?}");
}

#[test]
fn a_plan_that_sends_work_here_holds_the_report_until_the_work_runs_or_the_hold_ends() {
    let ms = |n: u64| Time(n * 1_000_000);
    let held_plan = |round: u64, hold_ms: u32| {
        control(FromCoordinator::RoundPlan(proto::RoundPlan {
            job_id: JOB.into(),
            round,
            work_on: vec![0],
            report_hold_ms: hold_ms,
            ..Default::default()
        }))
    };
    // Nothing here yet: the report waits for the plan's rays, and the tick at the hold's end
    // sends it.
    let mut w = worker();
    open(&mut w, ms(0), JOB, Schedule::Dynamic, &[]);
    let actions = w.handle(ms(1), held_plan(1, 50));
    assert!(queue_reports(&actions).is_empty(), "held: {actions:?}");
    assert_eq!(w.next_timeout(), Some(ms(51)));
    assert!(queue_reports(&w.handle(ms(30), Event::Tick)).is_empty());
    let reports = queue_reports(&w.handle(ms(51), Event::Tick)).len();
    assert_eq!(reports, 1, "the hold is over");
    assert_eq!(w.next_timeout(), None);
    // The rays come within the hold: traced, then reported at once.
    let actions = w.handle(ms(60), held_plan(2, 50));
    assert!(queue_reports(&actions).is_empty());
    let actions = w.handle(ms(70), bundle(JOB, &[ray(0, 0, 0, 1)]));
    assert!(pass_started(&actions).is_some());
    assert_eq!(w.next_timeout(), None, "a pass runs");
    let actions = w.handle(ms(75), finished(PassOutput::default()));
    assert_eq!(
        queue_reports(&actions).len(),
        1,
        "ran dry after the work came"
    );
    // No hold (barrier rounds, or an older coordinator): reported at once.
    let actions = w.handle(ms(80), held_plan(3, 0));
    assert_eq!(queue_reports(&actions).len(), 1);
    // Whatever the coordinator asks, a hold is bounded.
    w.handle(ms(90), held_plan(4, u32::MAX));
    assert_eq!(w.next_timeout(), Some(ms(90 + 10_000)));
}

#[test]
fn a_roster_change_addresses_the_verdicts_held_for_a_newcomer() {
    let mut w = worker();
    let actions = open(&mut w, Time(0), JOB, Schedule::Predictive, &[0]);
    assert!(pass_started(&actions).is_some(), "camera rays of tile 0");
    let verdict = VerdictRecord {
        tile: 0,
        pixel: 3,
        ..bytemuck::Zeroable::zeroed()
    };
    let out = PassOutput {
        verdicts: vec![(7, verdict)],
        ..PassOutput::default()
    };
    let actions = w.handle(Time(1), finished(out));
    assert!(
        !actions.iter().any(|a| matches!(a, Action::ToPeer { .. })),
        "worker 7 is not known yet: {actions:?}"
    );
    let roster = control(FromCoordinator::Roster(proto::Roster {
        job_id: JOB.into(),
        members: HashMap::from([(0, "me:1".into()), (7, "new:1".into())]),
    }));
    let actions = w.handle(Time(2), roster);
    let sent: Vec<VerdictRecord> = actions
        .iter()
        .filter_map(|a| match a {
            Action::ToPeer {
                peer,
                tier: Tier::Results,
                batches,
                ..
            } if peer == "new:1" => Some(batches),
            _ => None,
        })
        .flatten()
        .flat_map(|b| wire::decode_verdicts(b, &BatchLimits::any_frame(16)).unwrap())
        .collect();
    assert_eq!(sent, [verdict]);
}

#[test]
fn early_bundles_are_held_within_their_cap_and_timeout_then_replayed() {
    let config = WorkerConfig {
        early_bytes: 600,
        early_timeout: Duration::from_secs(30),
        ..WorkerConfig::new("w1".into(), "me:1".into(), 1 << 30)
    };
    let mut w: Worker<MemorySpill> = Worker::new(config).unwrap();
    let first = ray(0, 0, 0, 1);
    w.handle(Time(0), bundle(JOB, &[first]));
    let held = w.early_bytes();
    assert!(held > 0);
    // Ten rays' batch passes the cap: dropped, the first kept.
    let many: Vec<RayRecord> = (0..10).map(|p| ray(0, 0, 0, p)).collect();
    w.handle(Time(1), bundle(JOB, &many));
    assert_eq!(w.early_bytes(), held);
    // Another job's bundle, past the first job's timeout: the first job's are dropped.
    let late = Time(0) + Duration::from_secs(31);
    w.handle(late, bundle("job-2", &[first]));
    assert_eq!(
        w.early_bytes(),
        held,
        "job-1's expired, job-2's one is held"
    );
    // job-2 starts: its bundle is replayed into the frame and traced.
    let mut frame = start("job-2", Schedule::ImagePlane, &[]);
    frame.job_id = "job-2".into();
    let actions = w.handle(
        late,
        Event::FrameOpened {
            start: frame,
            opened: Ok(scene()),
        },
    );
    assert_eq!(
        pass_started(&actions).unwrap().trace,
        Some((0, vec![first]))
    );
    assert_eq!(w.early_bytes(), 0);
}

#[test]
fn bundles_of_an_ended_frame_are_dropped_not_held() {
    let mut w = worker();
    open(&mut w, Time(0), JOB, Schedule::Dynamic, &[]);
    let end = control(FromCoordinator::EndFrame(proto::EndFrame {
        job_id: JOB.into(),
    }));
    let actions = w.handle(Time(1), end);
    assert!(
        actions
            .iter()
            .any(|a| matches!(a, Action::FrameEnded { job_id, .. } if job_id == JOB))
    );
    w.handle(Time(2), bundle(JOB, &[ray(0, 0, 0, 1)]));
    assert_eq!(w.early_bytes(), 0);
    assert!(w.frame().is_none());
}

#[test]
fn rays_leaving_for_a_new_holder_make_a_report_due_and_an_empty_move_does_not() {
    let mut w = worker();
    open(&mut w, Time(0), JOB, Schedule::Dynamic, &[]);
    w.handle(Time(1), plan(1, &[0], &[]));
    // Domain 2 has no holder: its rays wait here, and the coordinator hears of them.
    let actions = w.handle(Time(2), bundle(JOB, &[ray(0, 0, 2, 1)]));
    assert_eq!(
        queue_reports(&actions)[0].queued_rays,
        BTreeMap::from([(2, 1)])
    );
    let holders = |w: &str| {
        control(FromCoordinator::Holders(proto::Holders {
            job_id: JOB.into(),
            holders: holders_of(&[(2, w)]),
            delta: false,
        }))
    };
    let actions = w.handle(Time(3), holders("b:1"));
    assert_eq!(rays_sent(&actions)["b:1"].len(), 1);
    let reports = queue_reports(&actions);
    assert_eq!(reports.len(), 1, "the coordinator counted that ray here");
    assert!(reports[0].queued_rays.is_empty());
    let actions = w.handle(Time(4), holders("c:1"));
    assert!(
        queue_reports(&actions).is_empty(),
        "nothing moved: {actions:?}"
    );
}

#[test]
fn a_domain_it_cannot_load_is_a_decline_a_replaced_scene_fails_the_frame() {
    for (failure, declined) in [
        (
            PassFailed::Load("domain-00001.rfd: bad domain file".into()),
            true,
        ),
        (
            PassFailed::SceneReplaced("scene s was replaced".into()),
            false,
        ),
    ] {
        let mut w = worker();
        open(&mut w, Time(0), JOB, Schedule::Dynamic, &[0]);
        let failed = Event::PassFinished {
            job_id: JOB.into(),
            result: Err(failure.clone()),
            resident: Vec::new(),
        };
        let actions = w.handle(Time(1), failed);
        let reports = frame_reports(&actions);
        let report = reports.first().expect("a frame report");
        assert_eq!(report.declined, declined, "{failure:?}");
        assert!(report.error.starts_with("worker "), "{}", report.error);
        assert!(w.frame().is_none(), "the frame is left");
        // Its peers' late rays are dropped, not held for a frame that may start.
        w.handle(Time(2), bundle(JOB, &[ray(0, 0, 0, 1)]));
        assert_eq!(w.early_bytes(), 0);
    }
}

#[test]
fn a_batch_outside_the_frame_is_dropped_and_the_rest_of_its_bundle_routed() {
    let mut w = worker();
    open(&mut w, Time(0), JOB, Schedule::ImagePlane, &[]);
    let good = ray(0, 0, 1, 3);
    let outside = ray(0, 0, DOMAINS as u32, 3);
    let event = Event::PeerBundle {
        sender: "peer:1".into(),
        job_id: JOB.into(),
        payload: Payload::Rays(vec![vec![good, outside], vec![good]]),
    };
    let work = w.handle(Time(1), event);
    assert_eq!(pass_started(&work).unwrap().trace, Some((1, vec![good])));
    assert_eq!(w.frame().unwrap().counters.rays_received, 1);
}

fn frame_reports(actions: &[Action]) -> Vec<&proto::FrameReport> {
    actions
        .iter()
        .filter_map(|a| match a {
            Action::ToCoordinator(proto::worker_message::Body::FrameReport(r)) => Some(r),
            _ => None,
        })
        .collect()
}

#[test]
fn a_frame_the_shell_could_not_open_is_declined_with_the_reason() {
    let mut w = worker();
    let actions = w.handle(
        Time(0),
        Event::FrameOpened {
            start: start(JOB, Schedule::Dynamic, &[0]),
            opened: Err("scene \"x\" not found".into()),
        },
    );
    let reports = frame_reports(&actions);
    assert_eq!(reports.len(), 1);
    assert!(reports[0].declined);
    assert_eq!(reports[0].error, "worker w1: scene \"x\" not found");
    assert!(w.frame().is_none() && pass_started(&actions).is_none());
    // Primary tiles outside the frame are the machine's own reason to decline.
    let actions = open(&mut w, Time(1), JOB, Schedule::Dynamic, &[4]);
    let reports = frame_reports(&actions);
    assert!(reports[0].declined && reports[0].error.contains("outside the frame's 4 tiles"));
}

#[test]
fn queues_past_both_caps_fail_the_frame_once_with_the_budgets() {
    let mut w = worker();
    let mut scene = scene();
    scene.queues = DomainQueues::new(DOMAINS, 2 * queues::RAY_BYTES, 0, MemorySpill::default());
    w.handle(
        Time(0),
        Event::FrameOpened {
            start: start(JOB, Schedule::Dynamic, &[]),
            opened: Ok(scene),
        },
    );
    // Domain 2 is traced by no one: its three rays wait here, one more than fit.
    let rays: Vec<RayRecord> = (0..3).map(|p| ray(0, 0, 2, p)).collect();
    let actions = w.handle(Time(1), bundle(JOB, &rays));
    let reports = frame_reports(&actions);
    assert_eq!(reports.len(), 1, "{actions:?}");
    assert!(!reports[0].declined && reports[0].error.contains("--queue-bytes"));
    assert!(w.frame().is_none());
    assert!(frame_reports(&w.handle(Time(2), bundle(JOB, &rays))).is_empty());
}

#[test]
fn a_silent_peer_is_dropped_and_reported_and_a_stale_pass_is_ignored() {
    let mut w = worker();
    open(&mut w, Time(0), JOB, Schedule::ImagePlane, &[0]);
    let lost = Event::PeerUnresponsive {
        peer: "b:1".into(),
        reason: "3 bundles unacknowledged".into(),
    };
    let actions = w.handle(Time(1), lost);
    assert!(matches!(&actions[0], Action::DropPeers(p) if p == &["b:1".to_string()]));
    assert!(actions.iter().any(|a| matches!(
        a,
        Action::ToCoordinator(proto::worker_message::Body::PeerUnresponsive(p))
            if p.peer_address == "b:1"
    )));
    // The frame's camera-ray pass is running; the frame ends and another starts before it
    // finishes: its result belongs to no frame now.
    let end = control(FromCoordinator::EndFrame(proto::EndFrame {
        job_id: JOB.into(),
    }));
    w.handle(Time(2), end);
    open(&mut w, Time(3), "job-2", Schedule::ImagePlane, &[]);
    let out = PassOutput {
        rays: vec![ray(0, 0, 0, 1)],
        ..PassOutput::default()
    };
    let actions = w.handle(Time(4), finished(out));
    assert!(pass_started(&actions).is_none(), "{actions:?}");
    assert_eq!(w.frame().unwrap().queued_total(), 0);
}

#[test]
fn hybrid_pins_its_own_domains_only_while_demand_loads_fit_the_cache() {
    for (cache_bytes, pinned) in [(2000, vec![0]), (1999, vec![])] {
        let config = WorkerConfig::new("w1".into(), "me:1".into(), cache_bytes);
        let mut w: Worker<MemorySpill> = Worker::new(config).unwrap();
        open(&mut w, Time(0), JOB, Schedule::Hybrid, &[]);
        let actions = w.handle(Time(1), plan(1, &[0], &[(1, "b:1")]));
        let pins: Vec<&Vec<u32>> = actions
            .iter()
            .filter_map(|a| match a {
                Action::Pin(d) => Some(d),
                _ => None,
            })
            .collect();
        assert_eq!(pins, [&pinned], "cache of {cache_bytes} bytes");
        // Camera rays stay here with demand loads on, else migrate to the owner.
        let camera = ray(0, 0, 1, 2);
        let sent = rays_sent(&w.handle(Time(2), bundle(JOB, &[camera])));
        assert_eq!(sent.contains_key("b:1"), pinned.is_empty());
    }
}

fn prefetch_asked(actions: &[Action]) -> Option<(u32, Vec<u32>)> {
    actions.iter().find_map(|a| match a {
        Action::Prefetch { domain, keep, .. } => Some((*domain, keep.clone())),
        _ => None,
    })
}

#[test]
fn a_prefetching_worker_loads_its_next_domain_while_it_traces_the_mapped_one() {
    let mut w = worker();
    let mut start = start(JOB, Schedule::Dynamic, &[]);
    start.spec.as_mut().unwrap().prefetch = true;
    let mut scene = scene();
    scene.resident = vec![0];
    w.handle(
        Time(0),
        Event::FrameOpened {
            start,
            opened: Ok(scene),
        },
    );
    let mut next = plan(1, &[0, 1], &[]);
    if let Event::Control(proto::CoordinatorMessage {
        body: Some(FromCoordinator::RoundPlan(p)),
    }) = &mut next
    {
        p.next = vec![2];
    }
    // The planned domain not mapped yet loads at once, keeping the plan's domains.
    let actions = w.handle(Time(1), next);
    assert_eq!(
        prefetch_asked(&actions),
        Some((1, vec![0, 1])),
        "{actions:?}"
    );
    // Domain 1 has more rays, but it is loading: 0, mapped, is traced meanwhile.
    let mut rays = vec![ray(0, 0, 0, 1)];
    rays.extend((0..5).map(|p| ray(0, 0, 1, p)));
    let actions = w.handle(Time(2), bundle(JOB, &rays));
    let traced = pass_started(&actions).and_then(|p| p.trace.as_ref().map(|t| t.0));
    assert_eq!(traced, Some(0), "{actions:?}");
    assert_eq!(prefetch_asked(&actions), None, "one prefetch at a time");
    // The pass ends first: domain 1 is loading, so nothing is traced and no report goes.
    let actions = w.handle(Time(3), finished(PassOutput::default()));
    assert!(pass_started(&actions).is_none(), "{actions:?}");
    assert!(queue_reports(&actions).is_empty(), "{actions:?}");
    // Loaded: domain 1 is traced, and the coordinator's guess, 2, loads meanwhile.
    let done = Event::PrefetchDone {
        job_id: JOB.into(),
        domain: 1,
        result: Ok(true),
        resident: vec![0, 1],
    };
    let actions = w.handle(Time(4), done);
    let traced = pass_started(&actions).and_then(|p| p.trace.as_ref().map(|t| t.0));
    assert_eq!(traced, Some(1), "{actions:?}");
    assert_eq!(
        prefetch_asked(&actions),
        Some((2, vec![0, 1])),
        "{actions:?}"
    );
    // No room for it: it is not asked for again under this plan.
    let refused = Event::PrefetchDone {
        job_id: JOB.into(),
        domain: 2,
        result: Ok(false),
        resident: vec![0, 1],
    };
    assert_eq!(prefetch_asked(&w.handle(Time(5), refused)), None);
}

#[test]
fn a_frame_without_prefetch_asks_for_none() {
    let mut w = worker();
    open(&mut w, Time(0), JOB, Schedule::Dynamic, &[]);
    w.handle(Time(1), plan(1, &[0, 1], &[]));
    let actions = w.handle(Time(2), bundle(JOB, &[ray(0, 0, 1, 1)]));
    assert!(pass_started(&actions).is_some());
    assert_eq!(prefetch_asked(&actions), None, "{actions:?}");
}

#[test]
fn idle_time_is_counted_by_why_the_worker_has_no_pass() {
    let mut w = worker();
    open(&mut w, Time(0), JOB, Schedule::Dynamic, &[]);
    w.handle(Time(0), plan(1, &[0], &[(1, "b:1")]));
    // Nothing queued from 0 to 1000 ns; then a ray for domain 2, which no one holds and the
    // plan does not give this worker: it waits here, queued, until the frame ends at 3000.
    w.handle(Time(1000), bundle(JOB, &[ray(0, 0, 2, 6)]));
    assert_eq!(w.frame().unwrap().queue_sizes(), BTreeMap::from([(2, 1)]));
    let end = control(FromCoordinator::EndFrame(proto::EndFrame {
        job_id: JOB.into(),
    }));
    let actions = w.handle(Time(3000), end);
    let stats = actions
        .iter()
        .find_map(|a| match a {
            Action::FrameEnded { stats, .. } => Some(stats),
            _ => None,
        })
        .expect("the frame's statistics");
    assert_eq!(stats.idle_empty_seconds, 1e-6);
    assert_eq!(stats.idle_queued_seconds, 2e-6);
    assert_eq!(stats.idle_verdicts_seconds, 0.0);
    assert_eq!(stats.busy_seconds, 0.0);
}

#[test]
fn the_frame_statistics_count_the_passes_of_the_frame_that_finished() {
    let mut w = worker();
    tracing_a_ray(&mut w);
    w.handle(Time(3), finished(PassOutput::default()));
    assert!(pass_started(&w.handle(Time(4), bundle(JOB, &[ray(0, 0, 0, 2)]))).is_some());
    w.handle(Time(5), finished(PassOutput::default()));
    // A pass of another job is not this frame's.
    w.handle(
        Time(6),
        Event::PassFinished {
            job_id: "other".into(),
            result: Ok(PassOutput::default()),
            resident: Vec::new(),
        },
    );
    let end = control(FromCoordinator::EndFrame(proto::EndFrame {
        job_id: JOB.into(),
    }));
    let stats = w
        .handle(Time(7), end)
        .into_iter()
        .find_map(|a| match a {
            Action::FrameEnded { stats, .. } => Some(stats),
            _ => None,
        })
        .expect("the frame's statistics");
    assert_eq!(stats.passes, 2);
}

/// Rays sent in the tasks tier, by peer.
fn tasks_sent(actions: &[Action]) -> BTreeMap<String, Vec<RayRecord>> {
    sent_in(actions, Tier::Tasks)
}

fn share(to: &str, theirs: &[u32], max_rays: u32) -> Event<MemorySpill> {
    control(FromCoordinator::ShareTasks(proto::ShareTasks {
        job_id: JOB.into(),
        to: to.into(),
        receiver_domains: theirs.to_vec(),
        max_rays,
    }))
}

fn shared_answer(actions: &[Action]) -> Option<&proto::TasksShared> {
    actions.iter().find_map(|a| match a {
        Action::ToCoordinator(proto::worker_message::Body::TasksShared(t)) => Some(t),
        _ => None,
    })
}

#[test]
fn a_busy_hybrid_worker_hands_an_idle_peer_what_costs_it_least_and_keeps_half() {
    let mut w = worker();
    open_holding(&mut w, Schedule::Hybrid, vec![2]);
    // Owns domain 0; the cache holds it and more, so camera rays load on demand here.
    w.handle(Time(1), plan(1, &[0], &[(1, "b:1"), (2, "c:1")]));
    let own: Vec<RayRecord> = (0..10).map(|p| ray(0, 0, 0, p)).collect();
    let camera: Vec<RayRecord> = (10..12).map(|p| ray(0, 0, 1, p)).collect();
    let bounce: Vec<RayRecord> = (12..20)
        .map(|p| RayRecord {
            depth: 1,
            ..ray(0, 0, 2, p)
        })
        .collect();
    let rays: Vec<RayRecord> = own.iter().chain(&camera).chain(&bounce).copied().collect();
    let actions = w.handle(Time(2), bundle(JOB, &rays));
    // The pass traces its own domain 0; 2 camera rays (domain 1, not mapped here) and 8
    // bounces (domain 2, mapped here) wait.
    assert_eq!(
        pass_started(&actions)
            .and_then(|p| p.trace.as_ref())
            .map(|(d, _)| *d),
        Some(0)
    );
    assert_eq!(w.frame().unwrap().queued_total(), 10);
    // A peer with nothing mapped gets the camera rays this worker would load domain 1 for.
    let pixels = |actions: &[Action]| -> Vec<u32> {
        let mut p: Vec<u32> = tasks_sent(actions)
            .remove("idle:1")
            .unwrap_or_default()
            .iter()
            .map(|r| r.pixel)
            .collect();
        p.sort();
        p
    };
    let actions = w.handle(Time(3), share("idle:1", &[], 100));
    assert_eq!(pixels(&actions), [10, 11], "{actions:?}");
    let answer = shared_answer(&actions).expect("answered");
    assert_eq!(
        (answer.rays, answer.queued, answer.to.as_str()),
        (2, 8, "idle:1")
    );
    assert!(
        rays_sent(&actions).is_empty(),
        "tasks travel in the tasks tier only"
    );
    // A peer with domain 2 mapped gets its rays, half of what is queued here.
    let actions = w.handle(Time(4), share("idle:1", &[2], 100));
    let given = pixels(&actions);
    assert_eq!(given.len(), 4);
    assert!(given.iter().all(|p| (12..20).contains(p)), "{given:?}");
    // Domain 2 is mapped here too, so it is not handed to a peer that would load it; nor is
    // anything to this worker itself.
    let actions = w.handle(Time(5), share("idle:1", &[], 100));
    assert!(tasks_sent(&actions).is_empty());
    let actions = w.handle(Time(6), share("me:1", &[2], 100));
    assert_eq!(shared_answer(&actions).map(|a| a.rays), Some(0));
    assert_eq!(w.frame().unwrap().counters.rays_shared, 6);
}

#[test]
fn a_domain_the_idle_peer_would_load_goes_whole_or_not_at_all() {
    let mut w = worker();
    open(&mut w, Time(0), JOB, Schedule::Hybrid, &[]);
    w.handle(Time(1), plan(1, &[0], &[(1, "b:1"), (2, "c:1")]));
    let own: Vec<RayRecord> = (0..10).map(|p| ray(0, 0, 0, p)).collect();
    let camera: Vec<RayRecord> = (10..16).map(|p| ray(0, 0, 1, p)).collect();
    let camera2: Vec<RayRecord> = (16..20).map(|p| ray(0, 0, 2, p)).collect();
    let rays: Vec<RayRecord> = own.iter().chain(&camera).chain(&camera2).copied().collect();
    w.handle(Time(2), bundle(JOB, &rays));
    // 10 queued, so at most 3 asked for: neither domain's 6 or 4 camera rays fit.
    let actions = w.handle(Time(3), share("idle:1", &[], 3));
    assert_eq!(shared_answer(&actions).map(|a| a.rays), Some(0));
    // At most 5: domain 2's 4 go whole, domain 1's 6 stay.
    let actions = w.handle(Time(4), share("idle:1", &[], 100));
    let sent = tasks_sent(&actions);
    assert_eq!(sent["idle:1"].len(), 4);
    assert!(sent["idle:1"].iter().all(|r| r.domain == 2));
    assert_eq!(w.frame().unwrap().queue_sizes(), BTreeMap::from([(1, 6)]));
}

#[test]
fn only_the_hybrid_schedule_shares_tasks() {
    let mut w = worker();
    open(&mut w, Time(0), JOB, Schedule::Dynamic, &[]);
    w.handle(Time(1), plan(1, &[], &[]));
    let rays: Vec<RayRecord> = (0..8).map(|p| ray(0, 0, 1, p)).collect();
    w.handle(Time(2), bundle(JOB, &rays));
    let actions = w.handle(Time(3), share("idle:1", &[1], 100));
    assert!(tasks_sent(&actions).is_empty());
    assert_eq!(shared_answer(&actions).map(|a| a.rays), Some(0));
}

#[test]
fn a_worker_asked_to_share_tasks_of_a_frame_it_does_not_run_says_it_holds_none() {
    let mut w = worker();
    // No frame at all, then another job's frame: each time an answer of nothing, for the job
    // asked about, so the coordinator turns to another donor.
    for opened_job in [None, Some("other")] {
        if let Some(job) = opened_job {
            open(&mut w, Time(0), job, Schedule::Hybrid, &[]);
        }
        let actions = w.handle(Time(1), share("idle:1", &[], 100));
        let answer = shared_answer(&actions).expect("answered");
        assert_eq!(
            (
                answer.job_id.as_str(),
                answer.to.as_str(),
                answer.rays,
                answer.queued
            ),
            (JOB, "idle:1", 0, 0)
        );
        assert!(tasks_sent(&actions).is_empty());
    }
}

/// A predictive frame copying rays `speculation` ahead, issuing tile 0's camera rays.
fn speculating(speculation: &str) -> Event<MemorySpill> {
    let mut start = start(JOB, Schedule::Predictive, &[0]);
    if let Some(spec) = start.spec.as_mut() {
        spec.speculation = speculation.into();
    }
    Event::FrameOpened {
        start,
        opened: Ok(scene()),
    }
}

/// A pass that gave birth to camera rays of `pixels`, each along `path`.
fn born_along(pixels: std::ops::Range<u32>, path: &[u32]) -> Event<MemorySpill> {
    let rays: Vec<RayRecord> = pixels.map(|p| ray(0, 0, path[0], p)).collect();
    finished(PassOutput {
        paths: vec![path.to_vec(); rays.len()],
        rays,
        ..PassOutput::default()
    })
}

/// `a:1`'s verdicts on copies it was sent.
fn verdicts_from_a(verdicts: Vec<VerdictRecord>) -> Event<MemorySpill> {
    Event::PeerBundle {
        sender: "a:1".into(),
        job_id: JOB.into(),
        payload: Payload::Verdicts(vec![verdicts]),
    }
}

/// The copies `actions` sent to `a:1`.
fn copies_to_a(actions: &[Action]) -> Vec<RayRecord> {
    rays_sent(actions).remove("a:1").unwrap_or_default()
}

/// The domains of `copies`, per pixel.
fn domains_by_pixel(copies: &[RayRecord]) -> BTreeMap<u32, Vec<u32>> {
    let mut out: BTreeMap<u32, Vec<u32>> = BTreeMap::new();
    for c in copies {
        out.entry(c.pixel).or_default().push(c.domain);
    }
    out
}

/// Issue 20: a window is not cut in front of a domain that the later windows sent into it
/// reached after it had been traced for their generation (each such straggler would load it
/// again), and is cut as predicted where they came on time.
#[test]
fn a_window_runs_through_a_domain_later_windows_reached_late() {
    use rayfarm_core::render::speculation::{SurfaceHit, Verdict};
    let hit_at_0 = Verdict::Hit(SurfaceHit {
        t: 1.0,
        normal: [0.0, 1.0, 0.0],
        material: 0,
    });
    let mut w = worker();
    w.handle(Time(0), speculating("predicted:0.9"));
    w.handle(Time(0), roster(JOB));
    w.handle(Time(1), plan(1, &[], &[(0, "a:1"), (1, "a:1"), (2, "a:1")]));
    // Twenty camera rays along domains 0, 1, 2: nothing is known of them, so each is copied
    // into all three. Domain 1 answers clear (it has now been traced for generation 0), then
    // domain 0 hits: each ray ends in domain 0, which the windows learn.
    let first = copies_to_a(&w.handle(Time(2), born_along(0..20, &[0, 1, 2])));
    let by_pixel = domains_by_pixel(&first);
    assert_eq!(by_pixel.len(), 20);
    assert!(by_pixel.values().all(|d| d == &[0, 1, 2]), "{by_pixel:?}");
    let clear_at_1 = first
        .iter()
        .filter(|c| c.domain == 1)
        .map(|c| VerdictRecord::new(c, Verdict::Clear));
    let hits = first
        .iter()
        .filter(|c| c.domain == 0)
        .map(|c| VerdictRecord::new(c, hit_at_0));
    w.handle(Time(3), verdicts_from_a(clear_at_1.chain(hits).collect()));
    // Rays end in domain 0 often enough now that a window stops after it.
    let copies = copies_to_a(&w.handle(Time(4), born_along(30..31, &[0, 1, 2])));
    assert_eq!(domains_by_pixel(&copies)[&30], [0]);
    // This one goes on: its later window reaches domain 1 late (traced for its generation
    // already) and domain 2 on time (no verdict of it yet).
    let clear = vec![VerdictRecord::new(&copies[0], Verdict::Clear)];
    let later = copies_to_a(&w.handle(Time(5), verdicts_from_a(clear)));
    assert_eq!(domains_by_pixel(&later)[&30], [1, 2]);
    // So a window no longer ends in front of domain 1, but still in front of domain 2.
    let copies = copies_to_a(&w.handle(Time(6), born_along(31..32, &[0, 1, 2])));
    assert_eq!(domains_by_pixel(&copies)[&31], [0, 1]);
    let copies = copies_to_a(&w.handle(Time(7), born_along(32..33, &[0, 2])));
    assert_eq!(domains_by_pixel(&copies)[&32], [0]);
}

/// A peer that learned late that this worker gave domain 1 up sends its rays here anyway: they
/// wait (and are reported) until this worker hears who holds it now, then go on there, as do
/// later ones; nothing is lost or sent back to the stale sender.
#[test]
fn rays_sent_to_a_former_holder_wait_for_the_new_holder_then_go_on() {
    let mut w = worker();
    open(&mut w, Time(0), JOB, Schedule::Dynamic, &[]);
    w.handle(Time(1), plan(1, &[1], &[]));
    // Its next plan gives domain 1 up; the coordinator has not told it the new holder yet.
    w.handle(Time(2), plan(2, &[0], &[]));
    let rays = [ray(0, 0, 1, 3), ray(0, 0, 1, 4)];
    let actions = w.handle(Time(3), bundle(JOB, &rays));
    assert!(rays_sent(&actions).is_empty(), "{actions:?}");
    assert_eq!(
        queue_reports(&actions)[0].queued_rays,
        BTreeMap::from([(1, 2)]),
        "the coordinator hears of them"
    );
    // The flush names c the holder of domain 1: the waiting rays leave for it.
    let actions = w.handle(
        Time(4),
        control(FromCoordinator::Holders(proto::Holders {
            job_id: JOB.into(),
            holders: vec![proto::DomainHolders {
                domain: 1,
                workers: vec![key_of("c:1")],
                lost: Vec::new(),
            }],
            delta: true,
        })),
    );
    assert_eq!(rays_sent(&actions)["c:1"], rays);
    let sent = rays_sent(&w.handle(Time(5), bundle(JOB, &rays)));
    assert_eq!(sent.keys().collect::<Vec<_>>(), ["c:1"]);
    assert!(w.frame().unwrap().queue_sizes().is_empty());
}
