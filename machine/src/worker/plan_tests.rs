//! Unit tests of [`super::Plan`]: routing, holders deltas, epochs, hybrid's rules.

use super::*;
use crate::worker::tests::ray;

/// Workers by address: `me:1` is key 0, `a:1` 1, `b:1` 2, `c:1` 3, `d:1` 4.
const NAMES: [&str; 5] = ["me:1", "a:1", "b:1", "c:1", "d:1"];

fn key(address: &str) -> u32 {
    NAMES
        .iter()
        .position(|n| *n == address)
        .expect("a known worker") as u32
}

fn holders(list: &[(u32, &[&str])]) -> Vec<HolderLine<'static>> {
    list.iter()
        .map(|(d, ws)| HolderLine {
            domain: *d,
            workers: ws.iter().map(|w| key(w)).collect(),
            lost: Default::default(),
        })
        .collect()
}

/// A delta: each domain's gained and lost workers.
fn delta(list: &[(u32, &[&str], &[&str])]) -> Vec<HolderLine<'static>> {
    list.iter()
        .map(|(d, gained, lost)| HolderLine {
            domain: *d,
            workers: gained.iter().map(|w| key(w)).collect(),
            lost: lost.iter().map(|w| key(w)).collect(),
        })
        .collect()
}

/// A plan of worker `me:1` (key 0) in a frame of the workers of [`NAMES`].
fn new_plan(mode: Mode, tiles: usize, domains: u32) -> Plan {
    let roster = NAMES
        .iter()
        .enumerate()
        .map(|(k, n)| (k as u32, n.to_string()))
        .collect();
    Plan::new(mode, tiles, domains, 0, Arc::new(roster))
}

#[test]
fn a_batch_goes_to_the_holder_the_latest_plan_names() {
    let mut plan = new_plan(Mode::Dynamic, 4, 3);
    plan.set_round(
        1,
        [0],
        holders(&[(0, &["me:1"]), (1, &["a:1"]), (2, &["b:1"])]),
        false,
    );
    let rays = vec![ray(0, 0, 0, 0), ray(0, 0, 1, 1), ray(1, 0, 2, 2)];
    let first = plan.sort(rays.clone());
    assert_eq!(first.local[&0].len(), 1);
    assert_eq!(first.peers["a:1"].len(), 1);
    assert_eq!(first.peers["b:1"].len(), 1);
    // The next plan moves domain 1 to c and gives domain 2 to no one else.
    plan.set_holders(holders(&[(1, &["c:1"])]), false);
    let second = plan.sort(rays);
    assert_eq!(second.peers.keys().collect::<Vec<_>>(), ["c:1"]);
    assert_eq!(second.local[&2].len(), 1, "unheld domains wait here");
    assert_eq!(second.dropped, 0);
}

#[test]
fn rays_for_one_destination_keep_their_order_and_stale_ones_are_dropped() {
    let mut plan = new_plan(Mode::Dynamic, 2, 3);
    plan.set_round(1, [0], holders(&[(1, &["a:1", "b:1"])]), false);
    let here: Vec<RayRecord> = (0..4).map(|p| ray(0, 0, 0, p)).collect();
    assert_eq!(plan.sort(here.clone()).local[&0], here);
    // Pixels 0 and 2 go to a, 1 and 3 to b; a ray of an older epoch goes nowhere.
    plan.bump_epochs(&BTreeMap::from([(1, 1)]));
    let mut mixed: Vec<RayRecord> = (0..4).map(|p| ray(0, 0, 1, p)).collect();
    mixed.push(ray(1, 0, 1, 9));
    let sorted = plan.sort(mixed.clone());
    assert_eq!(sorted.peers["a:1"], [mixed[0], mixed[2]]);
    assert_eq!(sorted.peers["b:1"], [mixed[1], mixed[3]]);
    assert!(sorted.local.is_empty());
    assert_eq!(sorted.dropped, 1);
}

#[test]
fn a_delta_changes_only_the_domains_it_lists() {
    let mut plan = new_plan(Mode::Dynamic, 1, 4);
    plan.set_round(
        1,
        [],
        holders(&[(0, &["a:1"]), (1, &["b:1"]), (2, &["c:1"])]),
        false,
    );
    // Domain 0 moves to d, domain 1 has no holder now but this worker, domain 2 is not
    // listed and stays c's; domain 3 is new.
    plan.set_holders(
        delta(&[
            (0, &["d:1"], &["a:1"]),
            (1, &["me:1"], &["b:1"]),
            (3, &["a:1", "me:1"], &[]),
        ]),
        true,
    );
    let to = |d| plan.destination(&ray(0, 0, d, 0));
    assert_eq!(to(0), Destination::Peer("d:1".into()));
    assert_eq!(to(1), Destination::Local);
    assert_eq!(to(2), Destination::Peer("c:1".into()));
    assert_eq!(to(3), Destination::Peer("a:1".into()));
    plan.set_holders(delta(&[(2, &[], &["c:1"])]), true);
    assert_eq!(plan.held_elsewhere().collect::<Vec<_>>(), [0, 3]);
    // A long list changes by its gains and losses, each gain at its place in key order,
    // so a ray's holder is the one the whole list would give.
    plan.set_holders(delta(&[(3, &["d:1", "b:1"], &[])]), true);
    plan.set_holders(delta(&[(3, &["c:1"], &["d:1"])]), true);
    let whole = {
        let mut p = new_plan(Mode::Dynamic, 1, 4);
        p.set_holders(holders(&[(3, &["a:1", "b:1", "c:1"])]), false);
        p
    };
    for pixel in 0..6 {
        let r = ray(0, 0, 3, pixel);
        assert_eq!(plan.destination(&r), whole.destination(&r));
    }
    assert_eq!(plan.holders_of(3), ["a:1", "b:1", "c:1", "d:1"]);
    // A whole map replaces everything.
    plan.set_holders(holders(&[(1, &["b:1"])]), false);
    assert_eq!(plan.held_elsewhere().collect::<Vec<_>>(), [1]);
}

#[test]
fn a_stale_epochs_rays_are_dropped() {
    let mut plan = new_plan(Mode::ImagePlane, 2, 2);
    plan.bump_epochs(&BTreeMap::from([(1, 3)]));
    plan.bump_epochs(&BTreeMap::from([(1, 2)]));
    assert_eq!(plan.epochs, [0, 3], "epochs never go back");
    let sorted = plan.sort(vec![ray(1, 2, 0, 0), ray(1, 3, 0, 0), ray(0, 0, 9, 0)]);
    assert_eq!(
        sorted.dropped, 2,
        "an old epoch and a domain past the scene's"
    );
    assert_eq!(sorted.local[&0], [ray(1, 3, 0, 0)]);
}

#[test]
fn a_load_may_ask_current_then_former_holders_but_never_lost_ones() {
    let mut plan = new_plan(Mode::Dynamic, 4, 4);
    plan.set_round(1, [], holders(&[(0, &["a:1"]), (1, &["b:1"])]), false);
    assert_eq!(plan.holders_of(0), ["a:1"]);
    // Domain 0 moves to c, domain 1 to this worker: their holders before are asked after.
    plan.set_holders(
        delta(&[(0, &["c:1"], &["a:1"]), (1, &["me:1"], &["b:1"])]),
        true,
    );
    assert_eq!(plan.holders_of(0), ["c:1", "a:1"]);
    assert_eq!(plan.holders_of(1), ["b:1"]);
    // A whole map without domain 0: c held it last.
    plan.set_holders(holders(&[(1, &["d:1"])]), false);
    assert_eq!(plan.holders_of(0), ["c:1", "a:1"]);
    assert_eq!(plan.holders_of(1), ["d:1", "b:1"]);
    assert!(plan.holders_of(2).is_empty());
    plan.forget_peers(&["a:1".into(), "d:1".into()]);
    assert_eq!(plan.holders_of(0), ["c:1"]);
    assert_eq!(plan.holders_of(1), ["b:1"]);
    // Routing still follows current holders only.
    assert!(!plan.is_held_elsewhere(0));
}

#[test]
fn holders_spread_by_pixel_and_lost_peers_are_forgotten() {
    let mut plan = new_plan(Mode::Domain, 1, 1);
    plan.set_round(2, [], holders(&[(0, &["a:1", "b:1"])]), false);
    let to = |p| plan.destination(&ray(0, 0, 0, p));
    assert_eq!(to(0), Destination::Peer("a:1".into()));
    assert_eq!(to(1), Destination::Peer("b:1".into()));
    plan.forget_peers(&["a:1".into()]);
    assert_eq!(
        plan.destination(&ray(0, 0, 0, 0)),
        Destination::Peer("b:1".into())
    );
    plan.forget_peers(&["b:1".into()]);
    assert_eq!(plan.destination(&ray(0, 0, 0, 0)), Destination::Local);
    assert!(!plan.traces(0), "held here until a plan names this worker");
}

#[test]
fn hybrid_keeps_camera_rays_only_while_demand_loads_are_on() {
    let mut plan = new_plan(
        Mode::Hybrid {
            demand_loads: true,
            rounds: false,
        },
        1,
        2,
    );
    plan.set_round(1, [0], holders(&[(1, &["a:1"])]), false);
    let camera = ray(0, 0, 1, 0);
    let bounce = RayRecord { depth: 1, ..camera };
    assert_eq!(plan.destination(&camera), Destination::Local);
    assert_eq!(plan.destination(&bounce), Destination::Peer("a:1".into()));
    plan.mode = Mode::Hybrid {
        demand_loads: false,
        rounds: false,
    };
    assert_eq!(plan.destination(&camera), Destination::Peer("a:1".into()));
    assert!(
        plan.traces(1),
        "with owners, whatever was kept here is traced here"
    );
}

#[test]
fn hybrid_by_rounds_traces_only_what_it_is_planned_or_has_mapped() {
    let mode = Mode::Hybrid {
        demand_loads: false,
        rounds: true,
    };
    let mut plan = new_plan(mode, 1, 3);
    plan.set_round(1, [0], holders(&[(1, &["a:1"])]), false);
    plan.set_resident([2]);
    assert!(plan.traces(0) && plan.traces(2));
    plan.set_resident([]);
    assert!(!plan.traces(2), "a domain nobody holds waits for a plan");
    assert_eq!(plan.destination(&ray(0, 0, 2, 0)), Destination::Local);
    assert_eq!(
        plan.destination(&ray(0, 0, 1, 0)),
        Destination::Peer("a:1".into())
    );
}

#[test]
fn a_batch_is_sorted_as_each_ray_destination_says() {
    use rayfarm_core::sampling::mix64;
    let modes = [
        Mode::ImagePlane,
        Mode::Domain,
        Mode::Dynamic,
        Mode::Predictive,
        Mode::Hybrid {
            demand_loads: true,
            rounds: false,
        },
        Mode::Hybrid {
            demand_loads: true,
            rounds: true,
        },
        Mode::Hybrid {
            demand_loads: false,
            rounds: true,
        },
    ];
    const DOMAINS: u32 = 12;
    for seed in 0..300u64 {
        let r = |i: u64| mix64(seed << 32 | i);
        let mode = modes[(r(0) % modes.len() as u64) as usize];
        let mut plan = new_plan(mode, 4, DOMAINS);
        plan.bump_epochs([(&1, &1), (&2, &2)]);
        // Holders among keys 0..=5: key 0 is this worker, key 5 a worker the roster lacks.
        let lines: Vec<HolderLine> = (0..DOMAINS)
            .map(|d| HolderLine {
                domain: d,
                workers: (0..6u32)
                    .filter(|k| r(100 + u64::from(d) * 8 + u64::from(*k)) % 3 == 0)
                    .collect(),
                lost: Default::default(),
            })
            .collect();
        let work_on: Vec<u32> = (0..DOMAINS)
            .filter(|d| r(300 + u64::from(*d)) % 4 == 0)
            .collect();
        plan.set_round(1, work_on, lines, false);
        plan.set_resident((0..DOMAINS).filter(|d| r(400 + u64::from(*d)) % 5 == 0));
        let rays: Vec<RayRecord> = (0..200u64)
            .map(|i| {
                let x = r(1000 + i);
                let mut ray = ray(
                    (x % 4) as u32,
                    ((x >> 8) % 3) as u32,
                    ((x >> 16) % u64::from(DOMAINS + 1)) as u32,
                    ((x >> 24) % 64) as u32,
                );
                ray.depth = ((x >> 40) % 3) as u16;
                ray
            })
            .collect();
        let mut want = Sorted::default();
        for ray in &rays {
            if !plan.is_current(ray.tile, ray.epoch) || ray.domain >= DOMAINS {
                want.dropped += 1;
                continue;
            }
            match plan.destination(ray) {
                Destination::Local => want.local.entry(ray.domain).or_default().push(*ray),
                Destination::Peer(p) => want.peers.entry(p).or_default().push(*ray),
            }
        }
        let got = plan.sort(rays);
        assert_eq!(got.local, want.local, "seed {seed}, {mode:?}");
        assert_eq!(got.peers, want.peers, "seed {seed}, {mode:?}");
        assert_eq!(got.dropped, want.dropped, "seed {seed}");
    }
}
