use super::*;
use crate::schedule::rounds::{Queues, adopt_plans, current_holders};
use proptest::prelude::*;

const DOMAINS: u32 = 10;

/// One change the coordinator makes to its members between plans.
#[derive(Clone, Debug)]
enum Change {
    /// Member `key` reports, of its plan's round (it ran dry) or of the one before (busy);
    /// naming only the queues that changed since its last report if `delta` (and it has one),
    /// and then with the resident domains of that one if `same_resident` (in the same order or
    /// another).
    Report {
        key: u32,
        dry: bool,
        delta: bool,
        same_resident: bool,
        resident: Vec<u32>,
        queued: Vec<(u32, u64, u32)>,
        waiting: Option<u32>,
    },
    /// The coordinator plans the dry members and adopts the plans.
    Plan,
    /// Member `key` joins (with a cache of `slots` domains) or leaves.
    Join {
        key: u32,
        slots: u64,
    },
    Leave {
        key: u32,
    },
    /// Every report dropped (an epoch bump).
    Forget,
}

fn change() -> impl Strategy<Value = Change> {
    let key = 0u32..6;
    let domain = 0..DOMAINS + 1; // one past the scene: reports may name what it lacks
    prop_oneof![
        4 => (
            (key.clone(), any::<bool>(), any::<bool>(), any::<bool>()),
            prop::collection::vec(domain.clone(), 0..4),
            prop::collection::vec((domain, 0u64..40, 0u32..3), 0..6),
            prop::option::of(0u32..3),
        )
            .prop_map(|((key, dry, delta, same_resident), resident, queued, waiting)| Change::Report {
                key,
                dry,
                delta,
                same_resident,
                resident,
                queued,
                waiting,
            }),
        3 => Just(Change::Plan),
        1 => (key.clone(), 1u64..4).prop_map(|(key, slots)| Change::Join { key, slots }),
        1 => key.prop_map(|key| Change::Leave { key }),
        1 => Just(Change::Forget),
    ]
}

const SIZE: u64 = 100;

/// What an index counts for its plans, comparable (a `Heat` equals another of the same
/// ratio, so the hot set is listed by its fields).
fn figures(index: &RoundIndex) -> String {
    let hot: Vec<(u32, u64, u64)> = index
        .hot
        .iter()
        .map(|h| (h.domain.0, h.rays, h.copies))
        .collect();
    format!(
        "parts {:?}\ndry {:?} {:?} {:?} {:?} {:?}\nqueued {:?}\nby generation {:?}\ngenerations {:?}\n\
         oldest {:?}\nheld {:?}\nin memory {:?}\nshown {:?}\nwanted {}\nunheld {:?} {:?}\n\
         hot {hot:?}\nplan holders {:?}\nqueuers {:?}\nholders {:?}",
        index.parts,
        index.dry,
        index.open,
        index.free,
        index.differs,
        index.dry_resident,
        index.queued,
        index.by_generation,
        index.generations,
        index.oldest,
        index.held,
        index.in_memory,
        index.shown,
        index.wanted,
        index.unheld,
        index.unheld_bits,
        index.plan_holders,
        index.queuers,
        index.holders,
    )
}

/// The figures `index` keeps equal those of an index given `members` afresh, whatever path
/// (a whole update, a queue moved) brought each member's part there.
fn check_figures(
    index: &RoundIndex,
    members: &BTreeMap<u32, Member>,
    oldest_first: bool,
) -> Result<(), TestCaseError> {
    let mut fresh =
        RoundIndex::new(&[SIZE; DOMAINS as usize], oldest_first).copying_from(index.copy_rays);
    for (&k, m) in members {
        fresh.update(k, Some(m));
    }
    prop_assert_eq!(figures(index), figures(&fresh));
    Ok(())
}

/// Applies `changes`, planning with the index and with `Cluster::dry_plans` at every `Plan`
/// and checking they agree; after every change, the index's holders map is the one rebuilt
/// from every member's plan, and so is a map kept only from its changes.
fn run(changes: &[Change], oldest_first: bool, options: Options) -> Result<(), TestCaseError> {
    let sizes = vec![SIZE; DOMAINS as usize];
    let mut members: BTreeMap<u32, Member> = (0..3).map(|k| (k, Member::new(2 * SIZE))).collect();
    let mut index = RoundIndex::new(&sizes, oldest_first).copying_from(options.copy_rays);
    for (&k, m) in &members {
        index.update(k, Some(m));
    }
    let mut round = 1;
    // What a coordinator told its members, kept from the index's changes alone.
    let mut told: BTreeMap<u32, Vec<u32>> = BTreeMap::new();
    // Each member's last report as it sent it (the rounds move rays in the coordinator's copy).
    let mut sent: BTreeMap<u32, Queues> = BTreeMap::new();
    for c in changes {
        match c {
            Change::Report {
                key,
                dry,
                delta,
                same_resident,
                resident,
                queued,
                waiting,
            } => {
                let Some(m) = members.get_mut(key) else {
                    continue;
                };
                let at = if *dry {
                    m.planned_round
                } else if m.planned_round > 0 {
                    m.planned_round - 1
                } else {
                    continue;
                };
                // In the worker's order of use, each once, as the coordinator takes it in.
                let mut seen = BTreeSet::new();
                let resident = match sent.get(key) {
                    // The same domains, in another order of use when the drawn list's
                    // length is odd (a pass used one).
                    Some(last) if *delta && *same_resident => {
                        let mut same = last.resident.clone();
                        if resident.len() % 2 == 1 && !same.is_empty() {
                            same.rotate_left(1);
                        }
                        same
                    }
                    _ => resident
                        .iter()
                        .copied()
                        .filter(|&d| seen.insert(d))
                        .collect(),
                };
                let report = Queues {
                    round: at,
                    resident,
                    queued: queued.iter().map(|&(d, n, _)| (d, n)).collect(),
                    oldest_generation: queued.iter().map(|&(d, _, g)| (d, g)).collect(),
                    oldest_waiting: *waiting,
                };
                match sent.get(key).filter(|_| *delta && m.report.is_some()) {
                    Some(last) => {
                        let mut domains: Vec<u32> = last
                            .queued
                            .keys()
                            .chain(report.queued.keys())
                            .copied()
                            .collect();
                        domains.sort_unstable();
                        domains.dedup();
                        let changes = Changes {
                            round: report.round,
                            resident: report.resident.clone(),
                            oldest_waiting: report.oldest_waiting,
                            queues: domains
                                .into_iter()
                                .filter(|&d| last.queue(d) != report.queue(d))
                                .map(|d| (d, report.queue(d)))
                                .collect(),
                        };
                        prop_assert!(index.take_changes(*key, &mut members, changes));
                        // Put back where the rounds moved rays, the report is as sent.
                        prop_assert_eq!(members[key].report.as_ref(), Some(&report));
                    }
                    None => {
                        m.report = Some(report.clone());
                        index.reported_whole(*key);
                        index.update(*key, Some(m));
                    }
                }
                sent.insert(*key, report);
            }
            Change::Plan => {
                let cluster = Cluster {
                    members: &members,
                    domain_bytes: &sizes,
                    oldest_first,
                    options,
                };
                let want = cluster.dry_plans();
                let got = index.dry_plans(&members, options);
                prop_assert_eq!(&got, &want);
                if !got.is_empty() {
                    round += 1;
                    let mut reference = members.clone();
                    let want = adopt_plans(&mut reference, &got, round);
                    let got = index.adopt(&mut members, &got, round);
                    prop_assert_eq!(got, want);
                    for (k, m) in &members {
                        let r = &reference[k];
                        prop_assert_eq!(&m.report, &r.report, "member {}", k);
                        prop_assert_eq!(&m.plan, &r.plan);
                        prop_assert_eq!(m.planned_round, r.planned_round);
                    }
                }
            }
            Change::Join { key, slots } => {
                members.insert(*key, Member::new(slots * SIZE));
                index.update(*key, members.get(key));
            }
            Change::Leave { key } => {
                members.remove(key);
                sent.remove(key);
                index.update(*key, None);
            }
            Change::Forget => {
                // The workers' next reports are whole (they hear of the bump).
                sent.clear();
                for (&k, m) in members.iter_mut() {
                    m.report = None;
                    index.update(k, Some(m));
                }
            }
        }
        check_figures(&index, &members, oldest_first)?;
        let rebuilt = current_holders(&members);
        let kept: BTreeMap<u32, Vec<u32>> = index
            .holders()
            .iter()
            .map(|(&d, keys)| (d, keys.iter().copied().collect()))
            .collect();
        prop_assert_eq!(&kept, &rebuilt);
        // Not every change is taken at once: a coordinator takes them when it plans.
        if matches!(c, Change::Plan | Change::Leave { .. }) {
            for (d, keys) in index.take_holder_changes() {
                if keys.is_empty() {
                    told.remove(&d);
                } else {
                    told.insert(d, keys);
                }
            }
            prop_assert_eq!(&told, &rebuilt);
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn incremental_plans_equal_whole_cluster_plans(
        changes in prop::collection::vec(change(), 1..40),
        oldest_first in any::<bool>(),
        replicate_onto_idle in any::<bool>(),
        fill_free_slots in any::<bool>(),
        copy_rays in 0u64..12,
    ) {
        let options = Options { replicate_onto_idle, fill_free_slots, copy_rays };
        run(&changes, oldest_first, options)?;
    }
}

/// A member with a cache of one domain, planned domain 3 in round 2 and busy with it (its
/// report, of round 1, holds `queued`).
fn busy_on_domain_3(queued: &[(u32, u64)]) -> Member {
    Member {
        plan: BTreeSet::from([3]),
        planned_round: 2,
        report: Some(Queues {
            round: 1,
            resident: vec![3],
            queued: queued.iter().copied().collect(),
            ..Queues::default()
        }),
        ..Member::new(SIZE)
    }
}

#[test]
fn a_dry_member_takes_the_fullest_unheld_domain_while_the_others_work() {
    let sizes = vec![SIZE; DOMAINS as usize];
    let mut members: BTreeMap<u32, Member> = (0..2).map(|k| (k, Member::new(SIZE))).collect();
    let mut index = RoundIndex::new(&sizes, false);
    members.insert(1, busy_on_domain_3(&[(3, 5), (4, 9), (5, 20)]));
    members.get_mut(&0).expect("member").report = Some(Queues::default());
    for (&k, m) in &members {
        index.update(k, Some(m));
    }
    let plans = index.dry_plans(&members, Options::default());
    assert_eq!(plans.len(), 1);
    assert_eq!(plans[0].worker.0, 0);
    assert_eq!(plans[0].load, BTreeSet::from([DomainId(5)]));
}

#[test]
fn a_round_drafts_whom_it_serves_not_every_idle_member() {
    let sizes = vec![SIZE; DOMAINS as usize];
    // Member 0 is busy with domain 3; members 1..=40 ran dry with nothing.
    let mut members: BTreeMap<u32, Member> = (0..=40).map(|k| (k, Member::new(SIZE))).collect();
    members.insert(0, busy_on_domain_3(&[(3, 1)]));
    for k in 1..=40 {
        members.get_mut(&k).expect("member").report = Some(Queues::default());
    }
    let mut index = RoundIndex::new(&sizes, false);
    for (&k, m) in &members {
        index.update(k, Some(m));
    }
    // Nothing to give anyone (domain 3 is held, one ray too few to copy): no draft at all.
    assert!(index.dry_plans(&members, Options::default()).is_empty());
    assert_eq!(index.drafts_made(), 0);
    // The busy member reports rays for an unheld domain: one idle member gets it, the lowest
    // key, and is the only one drafted.
    let busy = members.get_mut(&0).expect("member");
    busy.report.as_mut().expect("report").queued.insert(7, 5);
    index.update(0, members.get(&0));
    let plans = index.dry_plans(&members, Options::default());
    assert_eq!(plans.len(), 1);
    assert_eq!(plans[0].worker.0, 1);
    assert_eq!(plans[0].load, BTreeSet::from([DomainId(7)]));
    assert_eq!(index.drafts_made(), 1);
}

/// One step of a round's planning on the hot order: a copy of the `nth` domain nobody holds
/// that has no copy yet (`pair_with_free_slots`), or the hottest domain outside `barred`
/// (a bit a domain) taken.
#[derive(Clone, Debug)]
enum HotStep {
    Copy { nth: usize },
    Take { barred: u16 },
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    /// The overlay over the unheld domains' bits and the held ones' set gives the domains in
    /// the order one ordered set of every wanted domain that splits gives them (the order the
    /// index kept before the two were apart), is exhausted when that set is empty, and puts
    /// the figures back as they were.
    #[test]
    fn the_hot_order_apart_equals_one_ordered_set(
        counts in prop::collection::vec((0u64..6, 0u32..4), DOMAINS as usize),
        steps in prop::collection::vec(
            prop_oneof![
                (0usize..10).prop_map(|nth| HotStep::Copy { nth }),
                any::<u16>().prop_map(|barred| HotStep::Take { barred }),
            ],
            0..20,
        ),
    ) {
        let mut index = RoundIndex::new(&[SIZE; DOMAINS as usize], false);
        for (d, &(rays, holders)) in counts.iter().enumerate() {
            index.queued[d] = rays;
            index.held[d] = holders;
            index.refresh(d as u32);
        }
        let before = figures(&index);
        let mut one: BTreeSet<Heat> = counts
            .iter()
            .enumerate()
            .map(|(d, &(rays, holders))| Heat {
                domain: DomainId(d as u32),
                rays,
                copies: u64::from(holders),
            })
            .filter(|h| h.rays > 0 && h.splits(1))
            .collect();
        let mut overlay = HotOverlay {
            hot: &mut index.hot,
            unheld: &index.unheld_bits,
            unheld_left: index.unheld.len(),
            shown: &index.shown,
            changed: BTreeMap::new(),
            copy_rays: 1,
        };
        let again = |one: &mut BTreeSet<Heat>, mut h: Heat| {
            one.remove(&h);
            h.copies += 1;
            if h.splits(1) {
                one.insert(h);
            }
        };
        for step in &steps {
            match *step {
                HotStep::Copy { nth } => {
                    let uncopied: Vec<Heat> =
                        one.iter().filter(|h| h.copies == 0).copied().collect();
                    let Some(&h) = uncopied.get(nth % uncopied.len().max(1)) else {
                        continue;
                    };
                    overlay.add_copy(h.domain.0, h.rays, 0);
                    again(&mut one, h);
                }
                HotStep::Take { barred } => {
                    let eligible = |d: DomainId| barred & (1 << d.0) == 0;
                    let want = one.iter().rev().find(|h| eligible(h.domain)).copied();
                    if let Some(h) = want {
                        again(&mut one, h);
                    }
                    prop_assert_eq!(overlay.take_hottest(eligible), want.map(|h| h.domain));
                }
            }
            // The extensions stop asking once nothing is left, whoever asks.
            prop_assert_eq!(overlay.exhausted(), one.is_empty());
        }
        overlay.undo();
        prop_assert_eq!(figures(&index), before);
    }
}

#[test]
fn a_queue_whose_domain_its_member_evicted_moves_to_the_holder_after_a_delta_report() {
    // Member 0 holds domain 3 (resident) with 5 rays queued for it, busy on domain 4; member
    // 1 is busy on domain 3. While 0 holds 3 its rays stay; a report naming no queue, only
    // that 3 left its memory, lets them move to member 1, as a whole report would.
    let sizes = vec![SIZE; DOMAINS as usize];
    let mut members: BTreeMap<u32, Member> = BTreeMap::new();
    members.insert(1, busy_on_domain_3(&[]));
    members.insert(
        0,
        Member {
            plan: BTreeSet::from([4]),
            planned_round: 2,
            report: Some(Queues {
                round: 1,
                resident: vec![3, 4],
                queued: BTreeMap::from([(3, 5)]),
                ..Queues::default()
            }),
            ..Member::new(2 * SIZE)
        },
    );
    let mut index = RoundIndex::new(&sizes, false);
    for (&k, m) in &members {
        index.update(k, Some(m));
    }
    index.adopt(&mut members, &[], 2);
    assert_eq!(
        members[&0].report.as_ref().map(|r| r.queue(3)),
        Some((Some(5), None))
    );
    let mut whole = members.clone();
    whole
        .get_mut(&0)
        .and_then(|m| m.report.as_mut())
        .expect("report")
        .resident = vec![4];
    let changes = Changes {
        round: 1,
        resident: vec![4],
        ..Changes::default()
    };
    let reports = |m: &BTreeMap<u32, Member>| -> Vec<Option<Queues>> {
        m.values().map(|m| m.report.clone()).collect()
    };
    assert!(index.take_changes(0, &mut members, changes));
    assert_eq!(reports(&members), reports(&whole));
    let moved = index.adopt(&mut members, &[], 2);
    let want = adopt_plans(&mut whole, &[], 2);
    assert_eq!(moved, want);
    assert_eq!(reports(&members), reports(&whole));
    assert_eq!(
        members[&0].report.as_ref().map(|r| r.queue(3)),
        Some((None, None))
    );
    assert_eq!(
        members[&1].report.as_ref().map(|r| r.queue(3)),
        Some((Some(5), None))
    );
}
