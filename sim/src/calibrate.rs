//! `rayfarm sim calibrate`: the cost model's prices (`cost::ComputeCost`) measured on this
//! machine rather than guessed.
//!
//! Passes: a simulation of the scene runs on one thread with every pass's CPU time measured
//! (the thread's own clock, so other processes on the machine do not inflate it); passes
//! that loaded a domain are left out (their time is the storage's, priced apart). The passes
//! differ in their mix of radiance segments, shadow segments and camera samples (a pass of a
//! domain the camera sees starts paths; one of a domain behind holds bounces and shadows),
//! which lets a least-squares fit of `time = pass + radiance x R + shadow x S + camera x C +
//! volume x V` tell the prices apart. A price the fit makes negative is dropped to zero and
//! the rest fitted again (non-negative least squares by elimination).
//!
//! Planning: asynchronous rounds of the dynamic schedule (free cache slots filled, as the
//! coordinator plans by default) timed on the real coordinator machine in its steady state at
//! several sizes (`machine::coordinator::synthetic::SteadyFrame`, the machine's `rounds`
//! benchmark's coordinator): the dry members' reports taken, then one round planned, as the
//! coordinator shell and the simulator hand them over (thread clock, the median of several
//! rounds). Incremental rounds (1, 8 or 64 members dry, the rest busy) are fitted as
//! `round + planned x P + member x M + domain x D`: the incremental planner's cost follows the
//! members it plans, not the cluster's size. Rounds with every member dry are planned from the
//! whole cluster and fitted apart as `round + member x M + domain x D`.
//!
//! Holders flushes: timed on the same steady state apart from the round that found them due
//! (`SteadyFrame::handle_round`, then `SteadyFrame::flush`), at the same sizes and two holders intervals (so the lines
//! a flush makes vary apart from the members), fitted as `flush + member x M + line x L`
//! (`FlushWork`: the frame's members, and the lines made, once per view class and state).

use std::sync::Arc;
use std::time::Duration;

use bytes::Bytes;
use rayfarm_core::bundler::Tier;
use rayfarm_core::wire::{self, BatchLimits};

use rayfarm_machine::coordinator::FlushWork;
use rayfarm_machine::coordinator::synthetic::{SteadyFrame, flushed, planned};

use crate::cost::ComputeCost;
use crate::faults::FaultPlan;
use crate::node::Scene;
use crate::world::{MeasuredPass, SimConfig, simulate};

pub use rayfarm_node::cpu::thread_cpu_ns;

/// What a calibration measured, and how well the prices fit it.
#[derive(Clone, Debug)]
pub struct Calibration {
    pub cost: ComputeCost,
    /// Passes the pass prices were fitted to.
    pub passes: usize,
    /// Their CPU time in all, and the root-mean-square error of the fit over the mean pass.
    pub pass_cpu: Duration,
    pub pass_fit_error: f64,
    /// Reports taken in with no round after them, the report price's measure.
    pub reports: Vec<TimedReports>,
    /// The planning rounds the planning prices were fitted to.
    pub rounds: Vec<TimedRound>,
    /// The fit's root-mean-square error over the mean round: incremental rounds, and rounds
    /// planned from the whole cluster.
    pub round_fit_error: f64,
    pub whole_round_fit_error: f64,
    /// The holders flushes the flush prices were fitted to, and the fit's error.
    pub flushes: Vec<TimedFlush>,
    pub flush_fit_error: f64,
    /// Peer bundles received in the run, and the fit of their receiving (decoding and the
    /// worker machine's handling) as `bundle + byte x B`: coefficients and error.
    pub bundles_received: usize,
    pub receive: ([f64; 2], f64),
    /// The fit of encoding a bundle's batches (what the sending worker's bundler does), over
    /// the bundles that kept their batches.
    pub encode: ([f64; 2], f64),
    /// Those bundles, (tier as the protocol numbers it, batches), for timing their transport
    /// over gRPC (the CLI's `transport`).
    pub bundles: Vec<(i32, Vec<Bytes>)>,
    /// Finished passes whose output the machine took in the run, and the fit's error.
    pub finished: usize,
    pub finished_fit_error: f64,
}

/// Least squares with non-negative coefficients: `rows` of (features, value); a feature
/// whose coefficient comes out negative is dropped (its coefficient zero) and the rest fitted
/// again. Features that are zero in every row keep a zero coefficient. Returns the
/// coefficients and the fit's root-mean-square error over the mean value.
pub fn fit(rows: &[(Vec<f64>, f64)]) -> (Vec<f64>, f64) {
    let n = rows.first().map_or(0, |r| r.0.len());
    let mut active: Vec<bool> = (0..n)
        .map(|j| rows.iter().any(|(x, _)| x[j] != 0.0))
        .collect();
    loop {
        let cols: Vec<usize> = (0..n).filter(|&j| active[j]).collect();
        let beta = solve_normal(rows, &cols);
        let mut coef = vec![0.0; n];
        for (k, &j) in cols.iter().enumerate() {
            coef[j] = beta[k];
        }
        match cols.iter().enumerate().find(|(k, _)| beta[*k] < 0.0) {
            Some((_, &j)) => active[j] = false,
            None => {
                let mean = rows.iter().map(|r| r.1).sum::<f64>() / rows.len().max(1) as f64;
                let sq: f64 = rows
                    .iter()
                    .map(|(x, y)| {
                        let p: f64 = x.iter().zip(&coef).map(|(a, b)| a * b).sum();
                        (p - y).powi(2)
                    })
                    .sum();
                let rms = (sq / rows.len().max(1) as f64).sqrt();
                return (coef, if mean > 0.0 { rms / mean } else { 0.0 });
            }
        }
    }
}

/// Solves the normal equations of `rows` over the columns `cols` (Gaussian elimination with
/// partial pivoting; a singular column gets zero).
fn solve_normal(rows: &[(Vec<f64>, f64)], cols: &[usize]) -> Vec<f64> {
    let m = cols.len();
    // Columns scaled to unit size so counts in millions and a constant 1 mix well.
    let scale: Vec<f64> = cols
        .iter()
        .map(|&j| {
            let s = rows.iter().map(|r| r.0[j].abs()).fold(0.0, f64::max);
            if s > 0.0 { s } else { 1.0 }
        })
        .collect();
    let mut a = vec![vec![0.0; m + 1]; m];
    for (x, y) in rows {
        for p in 0..m {
            let xp = x[cols[p]] / scale[p];
            for q in 0..m {
                a[p][q] += xp * x[cols[q]] / scale[q];
            }
            a[p][m] += xp * y;
        }
    }
    for c in 0..m {
        let pivot = (c..m)
            .max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))
            .unwrap_or(c);
        a.swap(c, pivot);
        if a[c][c].abs() < 1e-12 {
            continue;
        }
        let pivot_row = a[c].clone();
        for (r, row) in a.iter_mut().enumerate() {
            if r != c {
                let f = row[c] / pivot_row[c];
                for (x, p) in row.iter_mut().zip(&pivot_row).skip(c) {
                    *x -= f * p;
                }
            }
        }
    }
    (0..m)
        .map(|c| {
            if a[c][c].abs() < 1e-12 {
                0.0
            } else {
                a[c][m] / a[c][c] / scale[c]
            }
        })
        .collect()
}

/// Measures the prices: passes of `config` over `scene` (run on one thread), and planning
/// rounds. `defaults` gives the prices the measurement cannot see (volume samples in a scene
/// without volumes).
pub fn calibrate(
    config: &SimConfig,
    scene: Arc<Scene>,
    defaults: ComputeCost,
) -> Result<Calibration, String> {
    let config = SimConfig {
        measure: true,
        ..config.clone()
    };
    // One thread: the pass's parallel loops run on the thread whose clock is read.
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .map_err(|e| e.to_string())?;
    let outcome = pool.install(|| {
        simulate(
            &config,
            scene,
            &FaultPlan::clean(),
            Duration::from_secs(3600),
            None,
        )
    })?;
    if let Some(v) = outcome.violations.first() {
        return Err(format!("the calibration run broke an invariant: {v}"));
    }
    let passes = &outcome.measured;
    if passes.len() < 8 {
        return Err(format!(
            "only {} passes without loads to measure: give a larger frame or smaller --pass-rays",
            passes.len()
        ));
    }
    let (pass_coef, pass_fit_error) = fit(&passes.iter().map(pass_row).collect::<Vec<_>>());
    let volumes = passes.iter().any(|p| p.counters.volume_samples > 0);
    let reports = time_reports();
    let report_ns = median(reports.iter().map(|r| r.ns).collect());
    let rounds = time_rounds();
    let (round_coef, round_fit_error, whole_coef, whole_round_fit_error) =
        fit_rounds(&rounds, report_ns);
    let flushes = time_flushes();
    let (flush_coef, flush_fit_error) = fit_flushes(&flushes);
    let received = &outcome.measured_bundles;
    let receive = fit_per_byte(
        &received
            .iter()
            .map(|b| (b.bytes, b.cpu_ns as f64))
            .collect::<Vec<_>>(),
    );
    let kept: Vec<(Tier, Vec<Bytes>)> = received
        .iter()
        .filter_map(|b| Some((b.tier, b.batches.clone()?)))
        .collect();
    let encode = fit_per_byte(
        &kept
            .iter()
            .filter_map(|(tier, batches)| {
                let bytes = batches.iter().map(Bytes::len).sum();
                Some((bytes, time_encode(*tier, batches)?))
            })
            .collect::<Vec<_>>(),
    );
    let finished = &outcome.measured_finished;
    let (finished_coef, finished_fit_error) = if finished.len() >= 4 {
        fit(&finished
            .iter()
            .map(|f| {
                (
                    vec![
                        1.0,
                        f.work.rays as f64,
                        f.work.path_domains as f64,
                        f.work.verdicts as f64,
                    ],
                    f.cpu_ns as f64,
                )
            })
            .collect::<Vec<_>>())
    } else {
        (vec![0.0; 4], 0.0)
    };
    Ok(Calibration {
        cost: ComputeCost {
            pass_ns: pass_coef[0],
            radiance_segment_ns: pass_coef[1],
            shadow_segment_ns: pass_coef[2],
            camera_sample_ns: pass_coef[3],
            volume_sample_ns: if volumes {
                pass_coef[4]
            } else {
                defaults.volume_sample_ns
            },
            round_ns: round_coef[0],
            round_planned_ns: round_coef[1],
            round_planned_domain_ns: round_coef[4],
            round_queue_ns: round_coef[5],
            report_ns,
            round_member_ns: round_coef[2],
            round_domain_ns: round_coef[3],
            whole_round_ns: whole_coef[0],
            whole_round_member_ns: whole_coef[1],
            whole_round_domain_ns: whole_coef[2],
            flush_ns: flush_coef[0],
            flush_member_ns: flush_coef[1],
            flush_line_ns: flush_coef[2],
            // What this run timed: encoding on the sender, decoding and the machine on the
            // receiver; the gRPC stream between them is the caller's to add (it needs a
            // runtime and sockets: the CLI's `transport`).
            bundle_send_ns: encode.0[0],
            bundle_send_byte_ns: encode.0[1],
            bundle_receive_ns: receive.0[0],
            bundle_receive_byte_ns: receive.0[1],
            finished_pass_ns: finished_coef[0],
            finished_ray_ns: finished_coef[1],
            finished_path_domain_ns: finished_coef[2],
            finished_verdict_ns: finished_coef[3],
        },
        passes: passes.len(),
        pass_cpu: Duration::from_nanos(passes.iter().map(|p| p.cpu_ns).sum()),
        pass_fit_error,
        reports,
        rounds,
        round_fit_error,
        whole_round_fit_error,
        flushes,
        flush_fit_error,
        bundles_received: received.len(),
        receive,
        encode,
        bundles: kept
            .into_iter()
            .map(|(tier, b)| (proto_tier(tier), b))
            .collect(),
        finished: finished.len(),
        finished_fit_error,
    })
}

/// Fits `ns = bundle + byte x bytes` to (bytes, ns) rows: the coefficients and the fit's
/// error; zeros with fewer than two rows (a run with no peer traffic).
fn fit_per_byte(rows: &[(usize, f64)]) -> ([f64; 2], f64) {
    if rows.len() < 2 {
        return ([0.0; 2], 0.0);
    }
    let (c, e) = fit(&rows
        .iter()
        .map(|&(bytes, ns)| (vec![1.0, bytes as f64], ns))
        .collect::<Vec<_>>());
    ([c[0], c[1]], e)
}

/// CPU time here of encoding `batches` again as the sending worker's bundler encodes them
/// (`wire::encode_batch`, `wire::encode_verdicts`), the fastest of three; `None` if they do
/// not decode.
fn time_encode(tier: Tier, batches: &[Bytes]) -> Option<f64> {
    let limits = BatchLimits::any_frame(1 << 20);
    let best = if tier == Tier::Results {
        let verdicts: Vec<_> = batches
            .iter()
            .map(|b| wire::decode_verdicts(b, &limits).ok())
            .collect::<Option<_>>()?;
        (0..3)
            .map(|_| {
                let start = thread_cpu_ns();
                for v in &verdicts {
                    std::hint::black_box(wire::encode_verdicts(v));
                }
                thread_cpu_ns().saturating_sub(start)
            })
            .min()
    } else {
        let rays: Vec<_> = batches
            .iter()
            .map(|b| wire::decode_batch(b, &limits).ok())
            .collect::<Option<_>>()?;
        (0..3)
            .map(|_| {
                let start = thread_cpu_ns();
                for r in &rays {
                    std::hint::black_box(wire::encode_batch(r));
                }
                thread_cpu_ns().saturating_sub(start)
            })
            .min()
    };
    best.map(|ns| ns as f64)
}

/// `tier` as the peer protocol numbers it.
fn proto_tier(tier: Tier) -> i32 {
    let t = match tier {
        Tier::Results => rayfarm_proto::Tier::Results,
        Tier::Migrated => rayfarm_proto::Tier::Migrated,
        Tier::Tasks => rayfarm_proto::Tier::Tasks,
    };
    t as i32
}

fn pass_row(p: &MeasuredPass) -> (Vec<f64>, f64) {
    let c = &p.counters;
    (
        vec![
            1.0,
            c.radiance_segments as f64,
            c.shadow_segments as f64,
            c.primary_rays as f64,
            c.volume_samples as f64,
        ],
        p.cpu_ns as f64,
    )
}

/// Cluster sizes planning is timed at: members and domains varied apart, so the fit tells
/// their prices apart.
const ROUND_SIZES: [(u32, u32); 6] = [
    (128, 1024),
    (512, 1024),
    (128, 4096),
    (512, 4096),
    (1024, 8192),
    (4096, 32768),
];

/// Members dry at once in the timed incremental rounds (a round plans those that ran dry
/// since the last one: one in the common case, more when reports arrive together).
const DRY_COUNTS: [u32; 3] = [1, 8, 64];

/// Domains a report names in the rounds timed again with large reports (one and eight members
/// dry at every size), so the fit tells a report's size from the members planned: a predictive
/// report names about a hundred (the synthetic reports otherwise name `schedule::synthetic::QUEUED`).
const LARGE_REPORT_QUEUES: usize = 256;

/// One timed planning round: the cluster's size, how many members it planned, and its
/// thread CPU time (the median of several, `time_round`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimedRound {
    pub members: usize,
    pub domains: usize,
    /// Members planned: the dry ones, or every member in a whole-cluster round.
    pub planned: usize,
    /// Whether every member was dry, so the round was planned from the whole cluster.
    pub whole: bool,
    /// Queues the reports taken in named (`PlanningWork::queues`), of the median round.
    pub queues: u64,
    pub ns: f64,
}

/// Reports timed alone at each size (the median is kept).
const REPORTS_TIMED: usize = 201;

/// What one report taken in costs the coordinator at a cluster's size when no round follows:
/// thread CPU, the median over [`REPORTS_TIMED`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimedReports {
    pub members: usize,
    pub domains: usize,
    pub ns: f64,
}

/// Reports of busy members at every size (`SteadyFrame::next_busy_report`: a delta naming
/// one queue, as a worker sends after its first), each handed to the machine with the round
/// it asks for, which plans nothing: the message, the status's copy, the member's figures in
/// the index (`RoundIndex::take_changes`), the tally. A round's reports are priced by this and
/// the rest of the round by [`fit_rounds`].
fn time_reports() -> Vec<TimedReports> {
    ROUND_SIZES
        .iter()
        .map(|&(workers, domains)| {
            let mut frame = SteadyFrame::new(workers, domains, Duration::from_millis(100));
            frame.flush();
            // Each member's first report while it works moves its round back; the timed ones
            // after it change a queue only, as a worker's reports between its plans do.
            for _ in 0..workers {
                let input = frame.next_busy_report();
                frame.handle_round(input);
                frame.flush();
            }
            let times: Vec<f64> = (0..REPORTS_TIMED)
                .filter_map(|_| {
                    let input = frame.next_busy_report();
                    let start = thread_cpu_ns();
                    let actions = std::hint::black_box(frame.handle_round(input));
                    let work = planned(&actions);
                    drop(actions);
                    let ns = thread_cpu_ns().saturating_sub(start);
                    frame.flush();
                    (work.rounds == 0).then_some(ns as f64)
                })
                .collect();
            TimedReports {
                members: workers as usize,
                domains: domains as usize,
                ns: median(times),
            }
        })
        .collect()
}

/// The middle of `values` (0 for none).
fn median(mut values: Vec<f64>) -> f64 {
    values.sort_unstable_by(f64::total_cmp);
    values.get(values.len() / 2).copied().unwrap_or(0.0)
}

/// Rounds at every size: incremental ones with each of [`DRY_COUNTS`] members dry, and one
/// whole-cluster round (every member dry).
fn time_rounds() -> Vec<TimedRound> {
    let mut out = Vec::new();
    for &(workers, domains) in &ROUND_SIZES {
        for dry in DRY_COUNTS.into_iter().filter(|&k| k < workers) {
            out.push(time_round(workers, domains, dry, None));
        }
        for dry in [1, 8] {
            out.push(time_round(workers, domains, dry, Some(LARGE_REPORT_QUEUES)));
        }
        out.push(time_round(workers, domains, workers, None));
    }
    out
}

/// A round of `workers` members over `domains` domains with `dry` of them dry, as the real
/// coordinator machine plans it (`machine::coordinator::synthetic::SteadyFrame`: the whole
/// `Coordinator` in its steady state, every member planned once already): the `dry` members'
/// reports taken (`Coordinator::take`), then one round planned (`Coordinator::plan`): the
/// plans drafted and adopted, the holders' deltas by view class, the plan and holders
/// messages made, tallies and progress. Thread CPU time, the median of several rounds (each
/// plans other members, so they differ); with every member dry, one round from the whole
/// cluster. Busy members are told the holders every 100 ms, as the long runs of README
/// "Simulator" do, and the flushes are not timed here (`time_flushes`): before the timed
/// rounds, half an interval of reports (125, one every 0.4 ms) leaves the lines pending for
/// each view class as a round meets them on average. (With an hour's interval, as before,
/// every line of the frame stayed pending and each round folded its changes into maps of
/// every domain: the price per member grew with the scene's domains for that reason.)
/// With `report_queues`, the timed rounds' reports name that many domains (the warm-up's name
/// the usual few).
fn time_round(workers: u32, domains: u32, dry: u32, report_queues: Option<usize>) -> TimedRound {
    let whole = dry >= workers;
    let mut frame = SteadyFrame::new(workers, domains, Duration::from_millis(100));
    frame.flush();
    for _ in 0..125 {
        let input = frame.next_report();
        frame.handle_round(input);
        frame.flush();
    }
    if let Some(queues) = report_queues {
        frame.set_report_queues(queues);
    }
    let repeats = match dry {
        _ if whole => 1,
        1 => 21,
        2..=8 => 9,
        _ => 5,
    };
    // (thread CPU, queues the round's reports named)
    let mut times: Vec<(u64, u64)> = (0..repeats)
        .map(|_| {
            let inputs: Vec<_> = (0..dry).map(|_| frame.next_report()).collect();
            let start = thread_cpu_ns();
            let actions = std::hint::black_box(frame.handle_all(inputs));
            let queues = planned(&actions).queues;
            drop(actions);
            let ns = thread_cpu_ns().saturating_sub(start);
            frame.flush();
            (ns, queues)
        })
        .collect();
    times.sort_unstable();
    let (ns, queues) = times[times.len() / 2];
    TimedRound {
        members: workers as usize,
        domains: domains as usize,
        planned: dry.min(workers) as usize,
        whole,
        queues,
        ns: ns as f64,
    }
}

/// Fits the incremental rounds as `round + planned x (P + domains x PD) + members x M + domains
/// x D + queues x Q`, each round's error relative to its time (they run from 0.02 ms to
/// milliseconds; fitted by absolute error, the large ones set a price per member of the
/// cluster that charged a 4,096-member round with one member dry five times its time), and
/// the whole-cluster rounds as `round + members x M + domains x D`: (the incremental prices,
/// their fit error, the whole-cluster prices, their fit error). Each round's reports (one a
/// member planned) are priced at `report_ns` apiece (`time_reports`), so what is fitted is
/// the rest of its time.
fn fit_rounds(rounds: &[TimedRound], report_ns: f64) -> ([f64; 6], f64, [f64; 3], f64) {
    let rest = |r: &TimedRound| (r.ns - report_ns * r.planned as f64).max(0.0);
    let incremental: Vec<(Vec<f64>, f64)> = rounds
        .iter()
        .filter(|r| !r.whole)
        .map(|r| {
            (
                vec![
                    1.0,
                    r.planned as f64,
                    r.members as f64,
                    r.domains as f64,
                    (r.planned * r.domains) as f64,
                    r.queues as f64,
                ],
                rest(r),
            )
        })
        .collect();
    let whole: Vec<(Vec<f64>, f64)> = rounds
        .iter()
        .filter(|r| r.whole)
        .map(|r| (vec![1.0, r.members as f64, r.domains as f64], rest(r)))
        .collect();
    let (i, ie) = fit_relative(&incremental);
    let (w, we) = fit(&whole);
    (
        [i[0], i[1], i[2], i[3], i[4], i[5]],
        ie,
        [w[0], w[1], w[2]],
        we,
    )
}

/// Holders intervals the flushes are timed at: a flush tells what the rounds of one interval
/// changed, so the longer one makes more lines over the same members.
const FLUSH_INTERVALS_MS: [u64; 2] = [20, 100];

/// Flushes timed at each size and interval (the median is kept), after the first (every
/// member's first plan, made as the frame was set up, is still in it).
const FLUSHES_TIMED: usize = 5;

/// One timed holders flush: the cluster's size, what the flush did (`FlushWork`), and its
/// thread CPU time (the median of [`FLUSHES_TIMED`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimedFlush {
    pub members: usize,
    pub domains: usize,
    pub interval: Duration,
    /// Members told (sent a `Holders`) and lines made, of the median flush.
    pub told: u64,
    pub lines: u64,
    pub ns: f64,
}

/// Flushes at every size of [`ROUND_SIZES`] and interval of [`FLUSH_INTERVALS_MS`].
fn time_flushes() -> Vec<TimedFlush> {
    let mut out = Vec::new();
    for &(workers, domains) in &ROUND_SIZES {
        for ms in FLUSH_INTERVALS_MS {
            out.push(time_flush(workers, domains, Duration::from_millis(ms)));
        }
    }
    out
}

/// Holders flushes of `workers` members over `domains` domains, every `interval`, as the
/// real coordinator machine makes them in its steady state
/// (`machine::coordinator::synthetic::SteadyFrame`, members running dry one after another
/// a report's gap apart): each report's round planned, then the flush, if due, timed alone
/// (`SteadyFrame::flush`; thread CPU time, the actions dropped included, as a
/// round's). The median flush of [`FLUSHES_TIMED`], with what it did.
fn time_flush(workers: u32, domains: u32, interval: Duration) -> TimedFlush {
    let mut frame = SteadyFrame::new(workers, domains, interval);
    let mut timed: Vec<(u64, FlushWork)> = Vec::new();
    let mut seen = 0;
    while timed.len() < FLUSHES_TIMED {
        let input = frame.next_report();
        drop(frame.handle_round(input));
        let start = thread_cpu_ns();
        let flush = std::hint::black_box(frame.flush());
        let work = flushed(&flush);
        drop(flush);
        let ns = thread_cpu_ns().saturating_sub(start);
        if work.flushes == 0 {
            continue;
        }
        seen += 1;
        if seen > 1 {
            timed.push((ns, work));
        }
    }
    timed.sort_unstable_by_key(|t| t.0);
    let (ns, work) = timed[timed.len() / 2];
    TimedFlush {
        members: work.members as usize,
        domains: domains as usize,
        interval,
        told: work.told,
        lines: work.lines,
        ns: ns as f64,
    }
}

/// Fits the flushes as `flush + members x M + lines x L`: the prices and the fit's error.
/// Each flush's error counts relative to its time: the timed flushes run from tens of
/// microseconds (128 members) to milliseconds (4,096), and a fit of absolute errors served the
/// large ones and charged a small flush twice its time (84-159 us for a flush of 74 us, and
/// about that for one of 8 members, which a simulated 8-worker cluster makes after every
/// round). The error is then the root mean square of the relative errors.
fn fit_flushes(flushes: &[TimedFlush]) -> ([f64; 3], f64) {
    let (c, e) = fit_relative(
        &flushes
            .iter()
            .map(|f| (vec![1.0, f.members as f64, f.lines as f64], f.ns))
            .collect::<Vec<_>>(),
    );
    ([c[0], c[1], c[2]], e)
}

/// [`fit`] with each row's error relative to its value (rows of value zero left out): the
/// root mean square of the relative errors is the fit's error.
fn fit_relative(rows: &[(Vec<f64>, f64)]) -> (Vec<f64>, f64) {
    fit(&rows
        .iter()
        .filter(|(_, y)| *y > 0.0)
        .map(|(x, y)| (x.iter().map(|v| v / y).collect(), 1.0))
        .collect::<Vec<_>>())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flushes_are_fitted_by_relative_error_so_a_small_one_is_not_overcharged() {
        // The twelve flushes one `rayfarm sim calibrate` timed on this project's machine
        // (stop 38): (members, lines made, ms).
        let timed = [
            (128, 400, 0.074),
            (128, 1_326, 0.267),
            (512, 1_176, 0.198),
            (512, 4_978, 0.813),
            (128, 400, 0.073),
            (128, 1_482, 0.287),
            (512, 1_600, 0.259),
            (512, 7_968, 1.058),
            (1_024, 3_200, 0.381),
            (1_024, 15_968, 1.666),
            (4_096, 12_800, 2.429),
            (4_096, 64_000, 5.898),
        ];
        let flushes: Vec<TimedFlush> = timed
            .iter()
            .map(|&(members, lines, ms)| TimedFlush {
                members,
                domains: 0,
                interval: Duration::ZERO,
                told: members as u64,
                lines,
                ns: ms * 1e6,
            })
            .collect();
        // The smallest flush as each fit prices it, over its time.
        let small = |c: &[f64]| (c[0] + 128.0 * c[1] + 400.0 * c[2]) / flushes[0].ns - 1.0;
        let (relative, _) = fit_flushes(&flushes);
        assert!(small(&relative).abs() < 0.25, "{relative:?}");
        // Fitted by absolute errors, the large flushes bought a fixed part the small ones
        // do not have.
        let (absolute, _) = fit(&flushes
            .iter()
            .map(|f| (vec![1.0, f.members as f64, f.lines as f64], f.ns))
            .collect::<Vec<_>>());
        assert!(small(&absolute) > 0.5, "{absolute:?}");
    }

    #[test]
    fn the_fit_recovers_known_prices_and_drops_a_negative_one() {
        // time = 100 + 5 a + 2 b, exactly; c is noise-free and unused.
        let rows: Vec<(Vec<f64>, f64)> = (0..20)
            .map(|i| {
                let (a, b) = ((i * 7 % 13) as f64, (i * 3 % 5) as f64 * 1000.0);
                (vec![1.0, a, b, 0.0], 100.0 + 5.0 * a + 2.0 * b)
            })
            .collect();
        let (coef, err) = fit(&rows);
        for (got, want) in coef.iter().zip([100.0, 5.0, 2.0, 0.0]) {
            assert!((got - want).abs() < 1e-6, "{coef:?}");
        }
        assert!(err < 1e-9);
        // A feature that only hurts gets zero, not a negative price.
        let rows: Vec<(Vec<f64>, f64)> = (0..20)
            .map(|i| {
                let a = i as f64;
                let noise = if i % 2 == 0 { 1.0 } else { 0.0 };
                (vec![a, noise], 3.0 * a - 0.5 * noise)
            })
            .collect();
        let (coef, _) = fit(&rows);
        assert_eq!(coef[1], 0.0);
        assert!(coef[0] > 2.9, "{coef:?}");
    }
}
