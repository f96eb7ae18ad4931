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
//!   in (`update`) and the dry member planned (`dry_plans`), equal plans.
//!
//! Each with Fig. 5 as written and with the coordinator's default, free cache slots filled with
//! copies of the hottest domains.
//!
//! `cargo bench -p rayfarm-core --bench planning`

use std::hint::black_box;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use rayfarm_core::schedule::dynamic::Options;
use rayfarm_core::schedule::round_index::RoundIndex;
use rayfarm_core::schedule::rounds::Cluster;
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
            let mut index = RoundIndex::new(domains, false);
            for (&k, m) in &one_dry {
                index.update(k, Some(m));
            }
            assert_eq!(
                index.dry_plans(&one_dry, &sizes, options),
                cluster(&one_dry).dry_plans()
            );
            group.bench_function(BenchmarkId::new("incremental_one_dry", &id), |b| {
                b.iter(|| {
                    index.update(0, Some(&one_dry[&0]));
                    black_box(index.dry_plans(&one_dry, &sizes, options))
                })
            });
        }
    }
    group.finish();
}

criterion_group!(benches, planning);
criterion_main!(benches);
