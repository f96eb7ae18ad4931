//! The coordinator's planning at the papers' scale: one round of the dynamic schedule
//! (`schedule::rounds`) for 1024 and 4096 workers over 8192 and 32768 domains.
//!
//! Four cases, each from the same synthetic reports (`schedule::synthetic`: every worker holds
//! two domains and has rays queued for sixteen, drawn from a fixed hash, the cluster
//! `rayfarm sim calibrate` times too):
//! - `barrier`: every member has reported, the whole cluster is planned at once;
//! - `async_one_dry`: asynchronous rounds, one member ran dry while the rest are busy (the
//!   common event: the coordinator handles one of these per report);
//! - `async_all_dry`: asynchronous rounds with every member dry (a frame's first round);
//! - `incremental_one_dry`: `async_one_dry` as the coordinator plans it, from a
//!   `round_index::RoundIndex` kept up to date report by report: the dry member's report taken
//!   in (`update`) and the dry member planned (`dry_plans`), equal plans;
//! - `round_one_dry`: the whole asynchronous round as the coordinator makes it with one member
//!   dry (`RunningFrame::plan_dry_members`, as `rayfarm sim calibrate` times it): the report
//!   taken in, the plan drafted and adopted (queued rays moved to their holders), and the holders
//!   map brought up to date against the last one sent, two ways side by side: `rebuilt` makes
//!   the map again from every member's plan and compares it whole with the last one (the
//!   coordinator before `RoundIndex` kept the map), `kept` takes the domains whose holders
//!   changed from the index (`RoundIndex::take_holder_changes`) and compares only those.
//!
//! Each with Fig. 5 as written and with the coordinator's default, free cache slots filled with
//! copies of the hottest domains.
//!
//! `cargo bench -p rayfarm-core --bench planning`

use std::hint::black_box;

use std::collections::BTreeMap;

use criterion::{BatchSize, BenchmarkId, Criterion, criterion_group, criterion_main};
use rayfarm_core::schedule::dynamic::Options;
use rayfarm_core::schedule::round_index::RoundIndex;
use rayfarm_core::schedule::rounds::{Cluster, Member, current_holders};
use rayfarm_core::schedule::synthetic::{DOMAIN_BYTES, members};

fn planning(c: &mut Criterion) {
    let mut group = c.benchmark_group("planning");
    group.sample_size(10);
    // Fig. 5 as written, and the coordinator's default (`--replicate free-slots`).
    let variants = [
        ("fig5", Options::default()),
        (
            "free_slots",
            Options {
                fill_free_slots: true,
                ..Options::default()
            },
        ),
    ];
    for (workers, domains) in [(1024u32, 8192u32), (4096, 32768)] {
        let sizes = vec![DOMAIN_BYTES; domains as usize];
        let all_dry = members(workers, domains, workers);
        let one_dry = members(workers, domains, 1);
        for (name, options) in variants {
            let id = format!("{name}/{workers}w_{domains}d");
            let cluster = |members| Cluster {
                members,
                domain_bytes: &sizes,
                oldest_first: false,
                options,
            };
            group.bench_function(BenchmarkId::new("barrier", &id), |b| {
                b.iter(|| black_box(cluster(&all_dry).barrier_round(1)))
            });
            group.bench_function(BenchmarkId::new("async_all_dry", &id), |b| {
                b.iter(|| black_box(cluster(&all_dry).dry_plans()))
            });
            group.bench_function(BenchmarkId::new("async_one_dry", &id), |b| {
                b.iter(|| black_box(cluster(&one_dry).dry_plans()))
            });
            let mut index = RoundIndex::new(&sizes, false);
            for (&k, m) in &one_dry {
                index.update(k, Some(m));
            }
            assert_eq!(
                index.dry_plans(&one_dry, options),
                cluster(&one_dry).dry_plans()
            );
            group.bench_function(BenchmarkId::new("incremental_one_dry", &id), |b| {
                b.iter(|| {
                    index.update(0, Some(&one_dry[&0]));
                    black_box(index.dry_plans(&one_dry, options))
                })
            });
        }
    }
    group.finish();
}

/// Holders by domain, as member keys.
type HolderMap = BTreeMap<u32, Vec<u32>>;

/// The domains whose holders differ between `sent` and `map` (a domain gone listed with none),
/// and `map` becomes `sent`: the whole-map comparison the coordinator made each round.
fn diff_whole(sent: &mut HolderMap, map: HolderMap) -> Vec<(u32, Vec<u32>)> {
    let mut delta: Vec<(u32, Vec<u32>)> = map
        .iter()
        .filter(|(d, keys)| sent.get(d) != Some(keys))
        .map(|(&d, keys)| (d, keys.clone()))
        .collect();
    delta.extend(
        sent.keys()
            .filter(|d| !map.contains_key(d))
            .map(|&d| (d, Vec::new())),
    );
    *sent = map;
    delta
}

/// `changes` (domains with their holders now) applied to `sent`: the ones that differ.
fn apply_changes(sent: &mut HolderMap, changes: Vec<(u32, Vec<u32>)>) -> Vec<(u32, Vec<u32>)> {
    let mut delta = Vec::new();
    for (d, keys) in changes {
        if sent.get(&d).map_or(keys.is_empty(), |k| *k == keys) {
            continue;
        }
        if keys.is_empty() {
            sent.remove(&d);
        } else {
            sent.insert(d, keys.clone());
        }
        delta.push((d, keys));
    }
    delta
}

/// A cluster one round in, as `rayfarm sim calibrate` sets it up: every member taken into the
/// index, one round planned and adopted, its holders map sent; then member 0 runs dry.
fn one_round_in(
    workers: u32,
    domains: u32,
    options: Options,
) -> (BTreeMap<u32, Member>, RoundIndex, HolderMap) {
    let sizes = vec![DOMAIN_BYTES; domains as usize];
    let mut members = members(workers, domains, 1);
    let mut index = RoundIndex::new(&sizes, false);
    for (&k, m) in &members {
        index.update(k, Some(m));
    }
    let plans = index.dry_plans(&members, options);
    index.adopt(&mut members, &plans, 2);
    index.take_holder_changes();
    let sent = current_holders(&members);
    if let Some(r) = members.get_mut(&0).and_then(|m| m.report.as_mut()) {
        r.round = 2;
    }
    (members, index, sent)
}

fn rounds(c: &mut Criterion) {
    let mut group = c.benchmark_group("planning");
    group.sample_size(10);
    let options = Options {
        fill_free_slots: true,
        ..Options::default()
    };
    for (workers, domains) in [
        (1024u32, 8192u32),
        (4096, 8192),
        (1024, 32768),
        (4096, 32768),
    ] {
        let start = one_round_in(workers, domains, options);
        let id = format!("{workers}w_{domains}d");
        let round =
            |(mut members, mut index, sent): (BTreeMap<u32, Member>, RoundIndex, HolderMap)| {
                index.update(0, members.get(&0));
                let plans = index.dry_plans(&members, options);
                index.adopt(&mut members, &plans, 3);
                (members, index, sent)
            };
        group.bench_function(BenchmarkId::new("round_one_dry/rebuilt", &id), |b| {
            b.iter_batched(
                || start.clone(),
                |state| {
                    let (members, index, mut sent) = round(state);
                    let delta = diff_whole(&mut sent, current_holders(&members));
                    black_box(delta);
                    (members, index, sent)
                },
                BatchSize::LargeInput,
            )
        });
        group.bench_function(BenchmarkId::new("round_one_dry/kept", &id), |b| {
            b.iter_batched(
                || start.clone(),
                |state| {
                    let (members, mut index, mut sent) = round(state);
                    let delta = apply_changes(&mut sent, index.take_holder_changes());
                    black_box(delta);
                    (members, index, sent)
                },
                BatchSize::LargeInput,
            )
        });
        // Both ways send the same delta.
        let (members, mut index, mut sent) = round(start.clone());
        let mut other = sent.clone();
        let mut want = diff_whole(&mut sent, current_holders(&members));
        want.sort_unstable();
        assert_eq!(apply_changes(&mut other, index.take_holder_changes()), want);
        assert_eq!(other, sent);
    }
    group.finish();
}

criterion_group!(benches, planning, rounds);
criterion_main!(benches);
