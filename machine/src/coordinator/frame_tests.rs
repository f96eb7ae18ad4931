//! The running frame driven by plain events: no process, socket or clock.

use super::*;
use crate::coordinator::holders::{HolderChange, ViewChange, view_classes};
use rayfarm_core::cluster::tile_sums;

/// A 64x64 frame of four 32-pixel tiles over four domains of 100 bytes.
fn frame_of(schedule: Schedule, rounds: Rounds) -> RunningFrame {
    let spec = proto::JobSpec {
        width: 64,
        height: 64,
        spp: 1,
        max_depth: 3,
        schedule: schedule as i32,
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
        copy_rays: 1,
    };
    RunningFrame::new(
        Time(0),
        "j".into(),
        spec,
        frame,
        vec![100; 4],
        options,
        rounds,
    )
    .expect("frame")
}

/// A frame started on `n` members with room for two domains each, keys 0..n, addresses w0..
fn started(schedule: Schedule, rounds: Rounds, n: u32) -> (RunningFrame, Vec<Outgoing>) {
    let mut f = frame_of(schedule, rounds);
    let out = f.start(
        (0..n)
            .map(|k| (k, Member::new(format!("w{k}"), 200)))
            .collect(),
    );
    (f, out)
}

fn report(round: u64, resident: &[u32], queued: &[(u32, u64, u32)]) -> proto::QueueReport {
    proto::QueueReport {
        job_id: "j".into(),
        round,
        resident_domains: resident.to_vec(),
        queued_rays: queued.iter().map(|&(d, n, _)| (d, n)).collect(),
        oldest_generation: queued.iter().map(|&(d, _, g)| (d, g)).collect(),
        ..Default::default()
    }
}

/// The messages to `key`.
fn to(out: &[Outgoing], key: u32) -> Vec<&Body> {
    out.iter()
        .filter(|(k, _)| *k == key)
        .filter_map(|(_, m)| m.body.as_ref())
        .collect()
}

fn planned_domains(out: &[Outgoing], key: u32) -> Vec<u32> {
    to(out, key)
        .into_iter()
        .filter_map(|b| match b {
            Body::RoundPlan(p) => Some(p.work_on.clone()),
            _ => None,
        })
        .flatten()
        .collect()
}

/// A result for all of `tile`'s pixels at `epoch`, returning `credit`.
fn whole_tile(f: &RunningFrame, tile: u32, epoch: u32, credit: u64) -> proto::TileResult {
    let pixels: Vec<(u32, [i64; 3])> = f
        .ledger
        .grid()
        .pixels(tile)
        .map(|p| (p, [1, 2, 3]))
        .collect();
    let sums = tile_sums::encode(&pixels);
    proto::TileResult {
        tile,
        epoch,
        credit,
        sums,
    }
}

fn results(results: Vec<proto::TileResult>) -> proto::TileResults {
    proto::TileResults {
        job_id: "j".into(),
        results,
        segments_traced: 10,
    }
}

#[test]
fn predictive_never_copies_domains_into_free_slots() {
    assert!(
        !frame_of(Schedule::Predictive, Rounds::Async)
            .options
            .fill_free_slots
    );
}

#[test]
fn a_dry_worker_is_planned_at_once_under_asynchronous_rounds() {
    let (mut f, start) = started(Schedule::Dynamic, Rounds::Async, 2);
    // Each gets a strided share of the four tiles, then its peers' addresses.
    for (key, tiles) in [(0, [0, 2]), (1, [1, 3])] {
        match to(&start, key)[..] {
            [Body::StartFrame(s), Body::Roster(r)] => {
                assert_eq!(s.primary_tiles, tiles);
                assert_eq!(r.members.len(), 2);
            }
            ref other => panic!("{other:?}"),
        }
    }
    // Worker 0 runs dry with rays for domain 1; worker 1 has not reported and is not waited for.
    let out = f.report(0, report(0, &[], &[(1, 50, 0)])).unwrap();
    assert!(planned_domains(&out, 0).contains(&1), "{out:?}");
    assert_eq!(f.round, 1);
    // Worker 1 keeps working and learns who holds domain 1 at the holders flush (here after
    // every round: the frame's interval is zero).
    assert!(to(&out, 1).is_empty(), "{out:?}");
    let out = f.flush_holders(Time(0));
    match to(&out, 1)[..] {
        [Body::Holders(h)] => {
            let one = h.holders.iter().find(|h| h.domain == 1).expect("domain 1");
            assert_eq!(one.workers, [0], "worker 0, by its key");
        }
        ref other => panic!("{other:?}"),
    }
    // A report of the round before its plan is no news: worker 0 is busy now.
    assert!(
        f.report(0, report(0, &[1], &[(1, 50, 0)]))
            .unwrap()
            .is_empty()
    );
}

#[test]
fn a_dry_member_with_nothing_new_is_left_out_of_the_rounds_and_their_tally() {
    let (mut f, _) = started(Schedule::Dynamic, Rounds::Async, 3);
    // Worker 0 runs dry with one ray for domain 1: planned (worker 2 has not reported, so
    // the round is incremental).
    f.report(0, report(0, &[], &[(1, 1, 0)])).unwrap();
    assert_eq!((f.round, f.planning.rounds, f.planning.planned), (1, 1, 1));
    // Worker 1 runs dry with nothing, and nothing is left to give it (domain 1 is held and
    // one ray is too few to copy): no plan changes, no round, nothing counted.
    let out = f.report(1, report(0, &[], &[])).unwrap();
    assert!(out.is_empty(), "{out:?}");
    assert_eq!((f.round, f.planning.rounds, f.planning.planned), (1, 1, 1));
    // Worker 0 runs dry again with a ray for domain 2: only it is planned; worker 1 stays
    // dry with nothing.
    let out = f.report(0, report(1, &[1], &[(2, 1, 0)])).unwrap();
    assert!(out.iter().all(|(to, _)| *to == 0), "{out:?}");
    assert_eq!((f.round, f.planning.rounds, f.planning.planned), (2, 2, 2));
}

#[test]
fn barrier_rounds_wait_for_every_report() {
    let (mut f, _) = started(Schedule::Dynamic, Rounds::Barrier, 2);
    assert!(
        f.report(0, report(0, &[], &[(1, 50, 0)]))
            .unwrap()
            .is_empty()
    );
    assert_eq!(f.round, 0);
    let out = f.report(1, report(0, &[], &[(2, 70, 0)])).unwrap();
    assert_eq!(f.round, 1);
    let mut planned = [planned_domains(&out, 0), planned_domains(&out, 1)].concat();
    planned.sort();
    planned.dedup();
    assert_eq!(planned, [1, 2], "{out:?}");
    // Every member gets round 1's plan, with the same holders.
    for key in [0, 1] {
        match to(&out, key)[..] {
            [Body::RoundPlan(p)] => assert_eq!((p.round, p.holders.len()), (1, 2)),
            ref other => panic!("{other:?}"),
        }
    }
    // Both domains, and a copy of each in the other worker's free slots.
    assert_eq!(f.planned_loads, 4);
}

#[test]
fn asynchronous_plans_tell_the_report_hold_and_barrier_plans_none() {
    let holds_with = |rounds, hold| {
        let (f, _) = started(Schedule::Dynamic, rounds, 2);
        let mut f = f.with_report_hold(hold);
        let mut out = f.report(0, report(0, &[], &[(1, 50, 0)])).unwrap();
        out.extend(f.report(1, report(0, &[], &[(2, 70, 0)])).unwrap());
        let holds: Vec<u32> = out
            .iter()
            .filter_map(|(_, m)| match &m.body {
                Some(Body::RoundPlan(p)) => Some(p.report_hold_ms),
                _ => None,
            })
            .collect();
        assert!(!holds.is_empty(), "{out:?}");
        holds
    };
    let ms = std::time::Duration::from_millis;
    let fixed = ReportHold {
        least: ms(50),
        per_member: ms(0),
    };
    let holds = |rounds| holds_with(rounds, fixed);
    assert!(holds(Rounds::Async).iter().all(|&h| h == 50));
    let per_member = ReportHold {
        least: ms(50),
        per_member: ms(40),
    };
    assert!(
        holds_with(Rounds::Async, per_member)
            .iter()
            .all(|&h| h == 80),
        "two members of 40 ms each hold longer than the least"
    );
    assert!(
        holds(Rounds::Barrier).iter().all(|&h| h == 0),
        "a barrier round waits for every report"
    );
}

#[test]
fn only_the_predictive_schedule_plans_the_oldest_generation_first() {
    let planned = |schedule| {
        let (mut f, _) = started(schedule, Rounds::Async, 2);
        f.report(1, report(0, &[], &[])).unwrap();
        // Domain 2 has more rays, but domain 3 holds the older generation.
        let out = f
            .report(0, report(0, &[], &[(2, 900, 2), (3, 5, 1)]))
            .unwrap();
        let mut planned = [planned_domains(&out, 0), planned_domains(&out, 1)].concat();
        // Dynamic may copy a domain into a free slot too.
        planned.sort();
        planned.dedup();
        planned
    };
    assert_eq!(planned(Schedule::Predictive), [3]);
    assert_eq!(planned(Schedule::Dynamic), [2, 3]);
}

#[test]
fn a_lost_worker_s_unfinished_tiles_get_new_epochs_and_go_to_the_survivors() {
    let (mut f, _) = started(Schedule::Dynamic, Rounds::Async, 3);
    // Tile 1 is done before the loss; the other three are not.
    let done = whole_tile(&f, 1, 0, TILE_CREDIT);
    let (committed, refused) = f.results(1, results(vec![done]));
    assert_eq!((committed.len(), refused), (1, None));
    f.report(0, report(0, &[], &[(1, 50, 0)])).unwrap();
    let out = f.lose(2).expect("a member");
    assert_eq!(f.members().collect::<Vec<_>>(), [0, 1]);
    let mut dealt = Vec::new();
    for key in [0, 1] {
        let bodies = to(&out, key);
        match bodies[0] {
            Body::EpochBump(b) => {
                let bumped: BTreeMap<u32, u32> = b.epochs.clone().into_iter().collect();
                assert_eq!(bumped, BTreeMap::from([(0, 1), (2, 1), (3, 1)]));
                assert_eq!(b.lost_peers, ["w2"]);
            }
            ref other => panic!("{other:?}"),
        }
        match bodies[1..] {
            [Body::HandOutTiles(h)] => dealt.extend(h.tiles.iter().copied()),
            ref other => panic!("{other:?}"),
        }
    }
    dealt.sort();
    assert_eq!(dealt, [0, 2, 3]);
    // Results of the old epoch count for nothing; the lost worker's are not taken either.
    let (committed, refused) = f.results(0, results(vec![whole_tile(&f, 0, 0, TILE_CREDIT)]));
    assert_eq!((committed.len(), refused), (0, None));
    assert!(!f.ledger.is_complete());
    // The reports from before the bump counted rays the workers dropped: they plan nothing.
    assert!(f.report(1, report(1, &[], &[])).unwrap().is_empty());
    // A worker that took no part is no loss.
    assert!(f.lose(7).is_none());
}

#[test]
fn a_result_with_more_credit_than_outstanding_is_refused() {
    let (mut f, _) = started(Schedule::Dynamic, Rounds::Async, 1);
    let three_quarters = TILE_CREDIT / 4 * 3;
    let (committed, refused) = f.results(0, results(vec![whole_tile(&f, 0, 0, three_quarters)]));
    assert_eq!((committed.len(), refused), (0, None));
    // The second three quarters would be more than the quarter still out: refused, with the
    // tile left as it was, and nothing after it in the batch counted.
    let batch = vec![
        whole_tile(&f, 0, 0, three_quarters),
        whole_tile(&f, 2, 0, TILE_CREDIT),
    ];
    let (committed, refused) = f.results(0, results(batch));
    assert!(committed.is_empty());
    assert!(refused.expect("refused").contains("tile 0"));
    assert_eq!(f.ledger.tiles_done(), 0);
    // The quarter still out completes it.
    let rest = whole_tile(&f, 0, 0, TILE_CREDIT - three_quarters);
    let (committed, refused) = f.results(0, results(vec![rest]));
    assert_eq!(committed.len(), 1);
    assert_eq!(refused, None);
    assert_eq!(committed[0].1.len(), 32 * 32);
}

#[test]
fn progress_counts_time_from_the_start_event() {
    let (mut f, _) = started(Schedule::Dynamic, Rounds::Async, 1);
    f.results(0, results(vec![whole_tile(&f, 0, 0, TILE_CREDIT)]));
    let (done, total, rate, eta) = f.progress(Time(2_000_000_000));
    assert_eq!((done, total), (1, 4));
    assert_eq!(rate, 5.0);
    assert_eq!(eta, 6.0);
}

/// The tiles `key` was dealt at the start.
fn primary(out: &[Outgoing], key: u32) -> Vec<u32> {
    match to(out, key)[..] {
        [Body::StartFrame(s), ..] => s.primary_tiles.clone(),
        ref other => panic!("{other:?}"),
    }
}

#[test]
fn results_of_a_tile_whose_rays_the_sender_was_never_given_are_refused() {
    // Image-plane routes no rays: only the worker dealt a tile may send its results.
    let (mut f, start) = started(Schedule::ImagePlane, Rounds::Async, 2);
    let (mine, theirs) = (primary(&start, 0), primary(&start, 1));
    assert!(!mine.is_empty() && !theirs.is_empty());
    // A plausible half of worker 1's tile from worker 0: refused, nothing counted.
    let forged = whole_tile(&f, theirs[0], 0, TILE_CREDIT / 2);
    let (committed, refused) = f.results(0, results(vec![forged]));
    assert!(committed.is_empty());
    assert!(refused.expect("refused").contains("given no ray"));
    assert_eq!(f.refused_results, 1);
    // The ledger is as it was: worker 1's whole credit still completes its tile, and worker
    // 0's own tile is taken.
    let honest = vec![whole_tile(&f, theirs[0], 0, TILE_CREDIT)];
    assert_eq!(f.results(1, results(honest)).0.len(), 1);
    let own = vec![whole_tile(&f, mine[0], 0, TILE_CREDIT)];
    assert_eq!(f.results(0, results(own)).0.len(), 1);
    // Worker 1 is lost: its unfinished tiles are re-dealt to worker 0 at epoch 1, whose
    // results of them are now taken.
    f.lose(1).expect("a member");
    let redealt = theirs[1];
    assert_eq!(f.ledger.epoch(redealt), Some(1));
    let (committed, refused) = f.results(0, results(vec![whole_tile(&f, redealt, 1, TILE_CREDIT)]));
    assert_eq!((committed.len(), refused), (1, None));
    assert_eq!(f.refused_results, 1);
}

#[test]
fn a_subframe_after_the_first_is_planned_once_every_member_has_reported() {
    // Two subframes of one sample each, on two members.
    let mut f = frame_of(Schedule::Predictive, Rounds::Async);
    f.spec.spp = 2;
    f.spec.progressive = Some(proto::Progressive { subframe_spp: 1 });
    f.frame.spp = 2;
    f.subframes = subframes::plan(&f.spec, 2);
    f.start(
        (0..2)
            .map(|k| (k, Member::new(format!("w{k}"), 200)))
            .collect(),
    );
    f.next_subframe();
    assert_eq!(f.subframe, 1);
    // Worker 0 holds domain 1 from the subframe before and has rays for domain 2, which worker
    // 1 holds: planned alone it would be given domain 2 to load; it waits for worker 1.
    assert!(
        f.report(0, report(0, &[1], &[(2, 50, 0)]))
            .unwrap()
            .is_empty()
    );
    assert_eq!(f.round, 0);
    let out = f.report(1, report(0, &[2], &[(1, 50, 0)])).unwrap();
    assert_eq!(f.round, 1);
    assert!(planned_domains(&out, 0).contains(&1), "{out:?}");
    assert!(planned_domains(&out, 1).contains(&2), "{out:?}");
}

#[test]
fn a_worker_named_a_holder_may_send_results_of_any_tile() {
    let half = TILE_CREDIT / 2;
    // Dynamic: before any plan, a worker holds nothing and only its own tiles are its.
    let (mut f, start) = started(Schedule::Dynamic, Rounds::Async, 2);
    let theirs = primary(&start, 1)[0];
    let (_, refused) = f.results(0, results(vec![whole_tile(&f, theirs, 0, half)]));
    assert!(refused.is_some());
    // Worker 0 runs dry and is planned domain 1: peers may now send it rays of any tile.
    assert!(planned_domains(&f.report(0, report(0, &[], &[(1, 50, 0)])).unwrap(), 0).contains(&1));
    let (_, refused) = f.results(0, results(vec![whole_tile(&f, theirs, 0, half)]));
    assert_eq!(refused, None);
    // The domain schedule names every owner a holder from the start.
    let (mut f, start) = started(Schedule::Domain, Rounds::Async, 2);
    let theirs = primary(&start, 1)[0];
    let (_, refused) = f.results(0, results(vec![whole_tile(&f, theirs, 0, half)]));
    assert_eq!(refused, None);
}

/// A frame of `schedule` started on `n` members with caches of `cache` bytes each.
fn started_with_caches(schedule: Schedule, n: u32, cache: u64) -> (RunningFrame, Vec<Outgoing>) {
    let mut f = frame_of(schedule, Rounds::Async);
    let out = f.start(
        (0..n)
            .map(|k| (k, Member::new(format!("w{k}"), cache)))
            .collect(),
    );
    (f, out)
}

fn share_requests(out: &[Outgoing], key: u32) -> Vec<&proto::ShareTasks> {
    to(out, key)
        .into_iter()
        .filter_map(|b| match b {
            Body::ShareTasks(s) => Some(s),
            _ => None,
        })
        .collect()
}

fn answer(rays: u64, queued: u64) -> proto::TasksShared {
    proto::TasksShared {
        job_id: "j".into(),
        to: String::new(),
        rays,
        queued,
    }
}

#[test]
fn hybrid_asks_a_busy_worker_to_feed_one_that_ran_dry_once_every_tile_is_out() {
    // Caches hold the owned domains and one more: one owner map, no rounds.
    let (mut f, start) = started_with_caches(Schedule::Hybrid, 2, 1000);
    assert!(!f.hybrid_rounds);
    assert!(matches!(to(&start, 0)[0], Body::StartFrame(s) if !s.hybrid_rounds));
    assert_eq!((primary(&start, 0), primary(&start, 1)), (vec![0], vec![1]));
    // While tiles are left, a dry worker gets tiles, not tasks.
    let out = f.report(0, report(0, &[0, 2], &[])).unwrap();
    assert!(share_requests(&out, 1).is_empty());
    assert!(matches!(to(&out, 0)[..], [Body::HandOutTiles(h)] if h.tiles == [2]));
    f.report(1, report(0, &[1], &[])).unwrap();
    // Every tile is out: worker 0 runs dry, worker 1 is asked to feed it, with what 0 has mapped.
    let out = f.report(0, report(0, &[0, 2], &[])).unwrap();
    let asked = share_requests(&out, 1);
    assert_eq!(asked.len(), 1, "{out:?}");
    assert_eq!(
        (asked[0].to.as_str(), asked[0].receiver_domains.as_slice()),
        ("w0", &[0, 2][..])
    );
    assert!(asked[0].max_rays > 0 && asked[0].max_rays <= TASK_RAYS);
    // A second dry report while the request is out asks nobody again.
    assert!(f.report(0, report(0, &[0, 2], &[])).unwrap().is_empty());
    // Worker 1 sent some: nothing more until worker 0 runs dry again.
    assert!(f.tasks_shared(1, &answer(500, 40_000)).is_empty());
    let out = f.report(0, report(0, &[0, 2], &[])).unwrap();
    assert_eq!(share_requests(&out, 1).len(), 1);
    // Worker 1 had nothing worth sending: with no other busy worker, worker 0 waits.
    assert!(f.tasks_shared(1, &answer(0, 100)).is_empty());
    assert!(f.report(0, report(0, &[0, 2], &[])).unwrap().is_empty());
    assert_eq!(f.task_counts(), (2, 500));
}

#[test]
fn hybrid_whose_owned_domains_do_not_fit_the_caches_plans_rounds_instead_of_owners() {
    // Two workers own two domains of 100 bytes each; caches of 200 leave no room for a
    // demand load, so the owners would thrash: rounds give each what its cache holds.
    let (mut f, start) = started_with_caches(Schedule::Hybrid, 2, 200);
    assert!(f.hybrid_rounds);
    assert!(
        to(&start, 0)
            .iter()
            .all(|b| !matches!(b, Body::RoundPlan(_))),
        "no owner map: {start:?}"
    );
    assert!(matches!(to(&start, 0)[0], Body::StartFrame(s) if s.hybrid_rounds));
    // A dry worker with rays queued for domain 3 gets tiles and a plan that holds them.
    let out = f.report(0, report(0, &[], &[(3, 500, 0)])).unwrap();
    assert!(
        to(&out, 0)
            .iter()
            .any(|b| matches!(b, Body::HandOutTiles(_)))
    );
    let planned = planned_domains(&out, 0);
    assert!(planned.contains(&3) && planned.len() <= 2, "{planned:?}");
    // Losing a member sends no owner map either.
    let out = f.lose(1).expect("a member");
    assert!(
        out.iter()
            .all(|(_, m)| !matches!(m.body, Some(Body::RoundPlan(_))))
    );
}

#[test]
fn a_hot_domains_change_is_news_to_the_view_classes_of_the_keys_it_gained_and_lost() {
    let (mut f, _) = started(Schedule::Dynamic, Rounds::Async, 256);
    let classes = view_classes(f.members.len());
    assert_eq!(classes, 4);
    // Domain 1 is held by 200 members (every class) and gains 203 and loses 4; domain 2,
    // held by member 5 alone, gains member 6: a short list, news to every class.
    let hot: Vec<u32> = (0..200).collect();
    let mut now: Vec<u32> = hot.iter().copied().filter(|&k| k != 4).collect();
    now.push(203);
    let changes = [
        HolderChange::between(1, Some(&hot), &now).unwrap(),
        HolderChange::between(2, Some(&vec![5]), &[5, 6]).unwrap(),
    ];
    let deltas = f.holder_changes(&changes, classes);
    let line = |domain: u32, gained: &[u32], lost: &[u32]| {
        (
            domain,
            ViewChange {
                gained: gained.to_vec(),
                lost: lost.to_vec(),
            },
        )
    };
    let told = |class: u32| -> Vec<(u32, ViewChange)> {
        deltas
            .iter()
            .filter_map(|c| c.of(class).map(|l| (c.domain, l.clone())))
            .collect()
    };
    // Class 0 loses its 4 and sees every holder of domain 2 (it has none of its own).
    assert_eq!(told(0), [line(1, &[], &[4]), line(2, &[6], &[])]);
    assert!(
        told(1).is_empty(),
        "class 1 sees its own 5 before and after"
    );
    // Class 2 saw every holder of domain 2 and now sees its own 6 only.
    assert_eq!(told(2), [line(2, &[6], &[5])]);
    assert_eq!(told(3), [line(1, &[203], &[]), line(2, &[6], &[])]);
    // Domain 1's change is kept once for the classes of its holders, all four; domain 2's
    // for those of 5 and 6 apart, once for the rest.
    assert_eq!(deltas[0].own.len(), 4);
    assert_eq!(deltas[1].own.keys().copied().collect::<Vec<_>>(), [1, 2]);
}

/// The holders a worker's plan routes by after `messages` (its plans and holders messages).
fn apply_holders(plan: &mut crate::worker::Plan, messages: &[&Body]) {
    use crate::worker::HolderLine;
    let lines = |ls: &[proto::DomainHolders]| -> Vec<HolderLine> {
        ls.iter()
            .map(|l| HolderLine {
                domain: l.domain,
                workers: l.workers.clone().into(),
                lost: l.lost.clone().into(),
            })
            .collect()
    };
    for m in messages {
        match m {
            Body::RoundPlan(p) => plan.set_round(
                p.round,
                p.work_on.clone(),
                lines(&p.holders),
                p.holders_delta,
            ),
            Body::Holders(h) => plan.set_holders(lines(&h.holders), h.delta),
            _ => {}
        }
    }
}

#[test]
fn busy_members_hear_of_new_holders_at_most_once_an_interval_and_then_route_by_the_latest() {
    use crate::worker::{Mode, Plan};
    let ms = |n: u64| Time(n * 1_000_000);
    let (f, _) = started(Schedule::Dynamic, Rounds::Async, 3);
    let mut f = f.with_holders_interval(std::time::Duration::from_millis(10));
    let roster: std::sync::Arc<std::collections::HashMap<u32, String>> =
        std::sync::Arc::new((0..3).map(|k| (k, format!("w{k}"))).collect());
    let mut plans: Vec<Plan> = (0..3)
        .map(|k| Plan::new(Mode::Dynamic, 4, 4, k, roster.clone()))
        .collect();
    let hear = |out: &[Outgoing], plans: &mut [Plan]| {
        for (k, plan) in plans.iter_mut().enumerate() {
            apply_holders(plan, &to(out, k as u32));
        }
    };
    // The first round (member 0 dry with rays for domain 1) goes out at once, whole.
    let out = f.report(0, report(0, &[], &[(1, 50, 0)])).unwrap();
    hear(&out, &mut plans);
    assert_eq!(f.holders_due(), Some(Time(0)));
    let flush = f.flush_holders(Time(0));
    assert_eq!(flush.len(), 2, "both busy members: {flush:?}");
    hear(&flush, &mut plans);
    assert_eq!(f.holders_due(), None, "nothing changed since");
    // Member 1 runs dry 1 ms later with rays for domain 2: its plan carries what changed, the
    // busy member 2 hears nothing yet, not even at a flush before the interval is over.
    let out = f.report(1, report(0, &[], &[(2, 40, 0)])).unwrap();
    assert!(planned_domains(&out, 1).contains(&2), "{out:?}");
    assert!(to(&out, 2).is_empty() && to(&out, 0).is_empty(), "{out:?}");
    hear(&out, &mut plans);
    assert_eq!(f.holders_due(), Some(ms(10)));
    assert!(f.flush_holders(ms(1)).is_empty());
    assert!(f.flush_holders(ms(9)).is_empty());
    // Member 0 runs dry again at 5 ms, with rays for domain 3.
    let out = f.report(0, report(1, &[1], &[(3, 30, 0)])).unwrap();
    assert!(planned_domains(&out, 0).contains(&3), "{out:?}");
    hear(&out, &mut plans);
    // Until the flush, member 2 routes domain 2 and 3's rays nowhere: it keeps them.
    let ray = |domain: u32| rayfarm_core::ray::RayRecord {
        domain,
        pixel: 7,
        ..bytemuck::Zeroable::zeroed()
    };
    let stale = plans[2].destination(&ray(3));
    assert_eq!(stale, crate::worker::Destination::Local, "not heard of yet");
    // At 10 ms every member that was not told the latest changes gets them, once: member 2
    // both rounds' folded, member 1 (planned before the second round) the second's, and
    // member 0 too: its plan carried only the lines of the domains whose rays the round moved
    // from it, the rest waits for the flush as for any busy member.
    let flush = f.flush_holders(ms(10));
    let told: Vec<u32> = flush.iter().map(|(k, _)| *k).collect();
    assert_eq!(told, [0, 1, 2], "{flush:?}");
    for (_, m) in &flush {
        assert!(matches!(&m.body, Some(Body::Holders(h)) if h.delta));
    }
    // One class, every member synced: one message, made once and shared by the three, so a
    // flush makes its lines once, not once a member.
    assert!(
        flush
            .windows(2)
            .all(|w| std::sync::Arc::ptr_eq(&w[0].1, &w[1].1))
    );
    let Some(Body::Holders(h)) = &flush[0].1.body else {
        unreachable!()
    };
    let first = f.flushing.lines - h.holders.len() as u64;
    assert_eq!(
        f.flushing,
        crate::coordinator::FlushWork {
            flushes: 2,
            members: 6,
            told: 5,
            lines: first + h.holders.len() as u64,
        },
        "two flushes (not the ones not due), of 3 members, telling 2 then 3"
    );
    hear(&flush, &mut plans);
    assert!(f.flush_holders(ms(30)).is_empty(), "nothing new");
    // Every member now holds the coordinator's map (less itself) and routes by it.
    let map = f.sent_holders.sent().clone();
    for (k, plan) in plans.iter().enumerate() {
        for d in 0..4u32 {
            let mut want: Vec<u32> = map.get(&d).cloned().unwrap_or_default();
            want.retain(|&w| w != k as u32);
            assert_eq!(plan.holder_keys(d), want, "member {k}, domain {d}");
        }
    }
    let holder = map[&3][0];
    assert_eq!(
        plans[2].destination(&ray(3)),
        crate::worker::Destination::Peer(format!("w{holder}"))
    );
}

#[test]
fn a_busy_member_whose_reported_rays_a_round_counts_at_a_new_holder_is_told_at_once() {
    let ms = |n: u64| Time(n * 1_000_000);
    // Caches of one domain each.
    let (f, _) = started_with_caches(Schedule::Dynamic, 3, 100);
    let mut f = f.with_holders_interval(std::time::Duration::from_millis(10));
    // Member 0 runs dry with rays for domains 1 and 3 and is given 1; everyone hears of it.
    let out = f
        .report(0, report(0, &[], &[(1, 50, 0), (3, 30, 0)]))
        .unwrap();
    assert_eq!(planned_domains(&out, 0), [1]);
    assert_eq!(f.flush_holders(ms(0)).len(), 2);
    // Member 1 runs dry with rays for domain 3 and is given it: the index now counts member
    // 0's 30 rays there, so member 0 (busy) hears at once, not at the flush; member 2, with
    // no rays reported, waits for the flush.
    let out = f.report(1, report(0, &[], &[(3, 10, 0)])).unwrap();
    assert_eq!(planned_domains(&out, 1), [3]);
    match to(&out, 0)[..] {
        [Body::Holders(h)] => {
            assert!(h.delta);
            let three = h.holders.iter().find(|l| l.domain == 3).expect("domain 3");
            assert_eq!(three.workers, [1]);
        }
        ref other => panic!("{other:?}"),
    }
    assert!(to(&out, 2).is_empty(), "{out:?}");
    assert!(f.flush_holders(ms(5)).is_empty(), "not due yet");
    // Member 0 was told already (domain 3, whose rays moved from it, is all that changed);
    // member 1's plan carried the lines of the domains whose rays moved from it, none, so it
    // hears at the flush like member 2.
    let flush = f.flush_holders(ms(10));
    assert_eq!(
        flush.iter().map(|(k, _)| *k).collect::<Vec<_>>(),
        [1, 2],
        "member 0 was told already"
    );
}

#[test]
fn a_report_naming_what_changed_is_put_into_the_last_and_one_without_a_last_is_dropped() {
    let (mut f, _) = started(Schedule::Dynamic, Rounds::Async, 3);
    // A delta before any whole report (the worker sent it before it heard of a loss that
    // made the frame forget its report): nothing to put it into, nothing planned.
    let early = proto::QueueReport {
        delta: true,
        ..report(0, &[], &[(1, 50, 0)])
    };
    assert!(f.report(0, early).unwrap().is_empty());
    assert_eq!(f.round, 0);
    // Worker 0 runs dry with rays for domains 1 and 2, both planned to it.
    let out = f
        .report(0, report(0, &[], &[(1, 50, 0), (2, 5, 0)]))
        .unwrap();
    assert_eq!(planned_domains(&out, 0), [1, 2]);
    // Worker 1 runs dry with rays for domain 3; then names only its queue for 3 emptied
    // and one for domain 0: the rounds see domain 0 wanted and domain 3 not.
    f.report(1, report(0, &[], &[(3, 7, 0)])).unwrap();
    let changed = proto::QueueReport {
        delta: true,
        cleared_domains: vec![3],
        ..report(0, &[], &[(0, 9, 0)])
    };
    let read = queue_report::read(&changed).unwrap();
    f.take_report(1, changed, read).unwrap();
    let queues = &f.members[&1].rounds.report.as_ref().expect("report").queued;
    assert_eq!(queues, &BTreeMap::from([(0, 9)]));
    // A report that clears a domain it gives a queue is refused: the worker must go.
    let impossible = proto::QueueReport {
        delta: true,
        cleared_domains: vec![0],
        ..report(0, &[], &[(0, 1, 0)])
    };
    assert!(f.report(1, impossible).is_err());
}

#[test]
fn a_member_that_joins_hears_the_whole_holders_map_at_the_next_flush_with_no_round_after_it() {
    let ms = |n: u64| Time(n * 1_000_000);
    let (f, _) = started(Schedule::Dynamic, Rounds::Async, 2);
    let mut f = f.with_holders_interval(std::time::Duration::from_millis(10));
    // Member 0 runs dry with rays for domain 1 and is given it; everyone is told at once.
    let out = f.report(0, report(0, &[], &[(1, 50, 0)])).unwrap();
    assert!(planned_domains(&out, 0).contains(&1), "{out:?}");
    f.flush_holders(Time(0));
    assert_eq!(f.holders_due(), None);
    // A worker joins. Its rays for domain 1 must go to member 0, but no round may follow to
    // tell it (every member dry, no plan to change): the flush must, by itself.
    f.join(2, Member::new("w2".to_string(), 200));
    assert_eq!(f.holders_due(), Some(ms(10)));
    let flush = f.flush_holders(ms(10));
    let told: Vec<&proto::Holders> = to(&flush, 2)
        .into_iter()
        .filter_map(|b| match b {
            Body::Holders(h) => Some(h),
            _ => None,
        })
        .collect();
    assert!(
        matches!(told[..], [h] if !h.delta && h.holders.iter().any(|l| l.domain == 1 && l.workers == [0])),
        "{flush:?}"
    );
}
