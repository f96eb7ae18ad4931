use super::*;

const PREDICTIVE: Options = Options {
    replicate_onto_idle: false,
    fill_free_slots: false,
    copy_rays: 1,
};

/// A report of `round`: `resident` domains, and (domain, rays, oldest generation) queues.
fn report(round: u64, resident: &[u32], queued: &[(u32, u64, u32)]) -> Queues {
    Queues {
        round,
        resident: resident.to_vec(),
        queued: queued.iter().map(|&(d, n, _)| (d, n)).collect(),
        oldest_generation: queued.iter().map(|&(d, _, g)| (d, g)).collect(),
        oldest_waiting: None,
    }
}

/// Two members with room for two of four equal domains each.
fn two_members() -> BTreeMap<u32, Member> {
    (0..2).map(|k| (k, Member::new(200))).collect()
}

/// Member `key` given `plan` at round 1, with `report` (of round 1 or later: it ran dry since;
/// earlier: it is busy on the plan).
fn planned_member(m: &mut BTreeMap<u32, Member>, key: u32, plan: &[u32], report: Queues) {
    let member = m.get_mut(&key).expect("member");
    member.plan = plan.iter().copied().collect();
    member.planned_round = 1;
    member.report = Some(report);
}

fn cluster(members: &BTreeMap<u32, Member>, oldest_first: bool) -> Cluster<'_> {
    Cluster {
        members,
        domain_bytes: &[100; 4],
        oldest_first,
        options: PREDICTIVE,
    }
}

fn planned(plans: &[WorkerPlan]) -> Vec<u32> {
    plans.iter().flat_map(|p| p.work().map(|d| d.0)).collect()
}

#[test]
fn a_dry_member_is_planned_at_once_without_waiting_for_the_others() {
    let mut m = two_members();
    m.get_mut(&0).expect("member").report = Some(report(0, &[], &[(1, 50, 0)]));
    let plans = cluster(&m, false).dry_plans();
    assert_eq!(planned(&plans), [1]);
    assert_eq!(plans[0].worker, WorkerId(0));
    // Barrier rounds wait for member 1's report.
    assert!(cluster(&m, false).barrier_round(0).is_none());
    m.get_mut(&1).expect("member").report = Some(report(0, &[], &[]));
    let (plan, wanted) = cluster(&m, false).barrier_round(0).expect("a round");
    assert_eq!((plan.load_count(), wanted), (1, 1));
}

#[test]
fn the_oldest_generation_is_planned_first() {
    let mut m = two_members();
    m.get_mut(&1).expect("member").report = Some(report(0, &[], &[]));
    // Domain 2 has more rays, but domain 3 holds the older generation.
    m.get_mut(&0).expect("member").report = Some(report(0, &[], &[(2, 900, 2), (3, 5, 1)]));
    assert_eq!(planned(&cluster(&m, true).dry_plans()), [3]);
    // Without the rule, both are planned.
    let mut all = planned(&cluster(&m, false).dry_plans());
    all.sort();
    assert_eq!(all, [2, 3]);
}

#[test]
fn with_every_member_dry_a_stuck_generation_does_not_stall_the_frame() {
    let mut m = two_members();
    // Member 0 holds domain 0, whose older rays it has planned already; member 1 is free.
    // Only domain 0 counts under the oldest-first rule, and its plan is unchanged: the
    // younger rays of domain 1 must be planned all the same.
    planned_member(&mut m, 0, &[0], report(1, &[0], &[(0, 5, 1), (1, 7, 2)]));
    assert!(
        planned(&cluster(&m, true).dry_plans()).is_empty() || m[&1].report.is_none(),
        "member 1 has not reported, so it has no place in a plan"
    );
    m.get_mut(&1).expect("member").report = Some(report(0, &[], &[]));
    assert!(planned(&cluster(&m, true).dry_plans()).contains(&1));
}

#[test]
fn while_someone_is_busy_younger_generations_wait() {
    let mut m = two_members();
    // Member 0 is busy on domain 0 (its report predates its plan) with generation 1 rays.
    planned_member(&mut m, 0, &[0], report(0, &[0], &[(0, 5, 1)]));
    m.get_mut(&1).expect("member").report = Some(report(0, &[], &[(2, 7, 2)]));
    assert!(cluster(&m, true).dry_plans().is_empty());
}

#[test]
fn queued_counts_move_to_the_new_holder_at_once() {
    let mut m = two_members();
    // Member 0 is busy and holds 40 rays of domain 3 (generation 4); member 1 is dry.
    planned_member(&mut m, 0, &[0], report(0, &[0], &[(0, 5, 1), (3, 40, 4)]));
    m.get_mut(&1).expect("member").report = Some(report(0, &[], &[(3, 2, 6)]));
    let plans = cluster(&m, false).dry_plans();
    assert_eq!(planned(&plans), [3]);
    let (loads, _) = adopt_plans(&mut m, &plans, 2);
    assert_eq!(loads, 1);
    // Member 1 is busy on domain 3 now: member 0's rays for it are counted there at once,
    // with the oldest generation among both.
    let one = m[&1].report.as_ref().expect("report");
    assert_eq!(
        (one.queued.get(&3), one.oldest_generation.get(&3)),
        (Some(&42), Some(&4))
    );
    assert!(
        !m[&0]
            .report
            .as_ref()
            .expect("report")
            .queued
            .contains_key(&3)
    );
    assert_eq!(m[&1].planned_round, 2);
    assert_eq!(
        current_holders(&m),
        BTreeMap::from([(0, vec![0]), (3, vec![1])])
    );
    // Once member 1 is busy and member 0 reports a newer count, it moves to member 1.
    m.get_mut(&1).expect("member").report = Some(report(1, &[3], &[]));
    m.get_mut(&1).expect("member").planned_round = 3;
    m.get_mut(&0).expect("member").report = Some(report(0, &[0], &[(3, 9, 4)]));
    move_queued_to_holders(&mut m);
    let one = m[&1].report.as_ref().expect("report");
    assert_eq!(
        (one.queued.get(&3), one.oldest_generation.get(&3)),
        (Some(&9), Some(&4))
    );
}

#[test]
fn a_dry_member_whose_plan_would_not_change_is_left_waiting() {
    let mut m = two_members();
    planned_member(&mut m, 0, &[1], report(1, &[1], &[(1, 5, 0)]));
    m.get_mut(&1).expect("member").report = Some(report(0, &[], &[]));
    assert!(cluster(&m, false).dry_plans().is_empty());
}

#[test]
fn a_dry_member_keeps_naming_a_resident_domain_whose_rays_ran_out() {
    let mut m = two_members();
    // Domain 1 has no rays left anywhere: a plan that would only drop it is not sent, so
    // member 0 stays its holder and rays that enter it later are sent to it directly.
    planned_member(&mut m, 0, &[1], report(1, &[0, 1], &[]));
    m.get_mut(&1).expect("member").report = Some(report(0, &[], &[]));
    assert!(cluster(&m, false).dry_plans().is_empty());

    // Rays for its other resident domain, which its plan does not name: planned to keep it,
    // and its plan names every domain it holds.
    m.get_mut(&1).expect("member").report = Some(report(0, &[], &[(0, 4, 0)]));
    let plans = cluster(&m, false).dry_plans();
    assert_eq!(plans.len(), 1, "{plans:?}");
    assert_eq!(plans[0].worker, WorkerId(0));
    assert_eq!(planned(&plans), [0, 1]);

    // A plan naming a domain it does not hold is replaced (member 1 keeps its own rays: its
    // plan stands).
    planned_member(&mut m, 1, &[3], report(1, &[3], &[(3, 6, 0)]));
    m.get_mut(&0).expect("member").plan = [1, 2].into();
    let plans = cluster(&m, false).dry_plans();
    assert_eq!(plans.len(), 1, "{plans:?}");
    assert_eq!(plans[0].worker, WorkerId(0));
    assert_eq!(planned(&plans), [0, 1]);
}
