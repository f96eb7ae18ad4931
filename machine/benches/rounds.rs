//! What one asynchronous round costs the real coordinator machine at the papers' scale: the
//! whole `Coordinator` handling a member's report of running dry (taking the report in,
//! planning the dry member from `RoundIndex`, the holders' deltas by view class, the plan and
//! holders messages, the tallies and progress), in the steady state of `coordinator::synthetic`
//! (every member planned already, busy members told the holders at most every 100 ms), for
//! 1,024 workers over 8,192 domains and 4,096 over 32,768. `rayfarm sim calibrate` prices the
//! simulator's rounds by timing the same rounds.
//!
//! `cargo bench -p rayfarm-machine --bench rounds`

use std::hint::black_box;
use std::time::Duration;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use rayfarm_machine::coordinator::synthetic::SteadyFrame;

fn rounds(c: &mut Criterion) {
    let mut group = c.benchmark_group("coordinator");
    group.sample_size(20);
    for (workers, domains) in [(1024u32, 8192u32), (4096, 32768)] {
        let mut frame = SteadyFrame::new(workers, domains, Duration::from_millis(100));
        let id = format!("{workers}w_{domains}d");
        profile(&mut frame, &id);
        group.bench_function(BenchmarkId::new("report_one_dry", &id), |b| {
            b.iter(|| {
                let input = frame.next_report();
                black_box(frame.handle(input))
            })
        });
    }
    group.finish();
}

/// Times 2,000 reports one by one and prints where the time went: the rounds (median and
/// mean), the holders flushes (every 100 ms of the frame's time, a report every 0.4 ms), the
/// messages and holder lines the rounds sent.
fn profile(frame: &mut SteadyFrame, id: &str) {
    use rayfarm_machine::coordinator::synthetic::{holder_lines, messages, planned};
    let mut times = Vec::new();
    let (mut flush_ns, mut flushes, mut planned_members) = (0u128, 0, 0);
    let (mut round_messages, mut round_lines) = (0usize, 0usize);
    for _ in 0..2000 {
        let input = frame.next_report();
        let t = std::time::Instant::now();
        let actions = frame.handle(input);
        let ns = t.elapsed().as_nanos();
        let m = messages(&actions);
        planned_members += planned(&actions).planned;
        if m.get("holders").copied().unwrap_or(0) > 64 {
            flush_ns += ns;
            flushes += 1;
        } else {
            times.push(ns);
            round_messages += m.values().sum::<usize>();
            round_lines += holder_lines(&actions);
        }
        black_box(actions);
    }
    times.sort_unstable();
    let total: u128 = times.iter().sum::<u128>() + flush_ns;
    eprintln!(
        "{id}: {} rounds median {} us mean {} us; {flushes} flushes {} us each, {:.0}% of all; {planned_members} planned",
        times.len(),
        times[times.len() / 2] / 1000,
        times.iter().sum::<u128>() / times.len() as u128 / 1000,
        flush_ns / flushes.max(1) / 1000,
        100.0 * flush_ns as f64 / total as f64
    );
    eprintln!("{id}: {round_messages} messages in rounds, {round_lines} holder lines");
}

criterion_group!(benches, rounds);
criterion_main!(benches);
