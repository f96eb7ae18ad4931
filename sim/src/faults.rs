//! The faults of one seed: a seed names a plan (which workers die when, who joins, which
//! links are slow or cut, who stops acknowledging) drawn from a small generator, so the same
//! seed is the same run. Times are drawn within the clean run's frame time, so kills land
//! anywhere in a frame: mid-load, mid-pass, with bundles in flight.

use std::time::Duration;

use rayfarm_machine::Time;

use crate::net::Window;

/// SplitMix64: a tiny, well-mixed generator; all a fault plan needs.
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(seed)
    }

    pub fn draw(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// A number in `0..n` (0 when `n` is 0).
    pub fn below(&mut self, n: u64) -> u64 {
        if n == 0 { 0 } else { self.draw() % n }
    }

    /// A duration drawn from the exponential distribution of mean `mean`: the wait for an
    /// event that is as likely at any moment, all that is known of it being its mean.
    pub fn exponential(&mut self, mean: Duration) -> Duration {
        // A uniform draw in (0, 1]: 53 random bits, never zero.
        let u = ((self.draw() >> 11) + 1) as f64 / (1u64 << 53) as f64;
        Duration::from_nanos((-u.ln() * mean.as_nanos() as f64) as u64)
    }

    /// A time in `[0, span)`.
    pub fn time_within(&mut self, span: Duration) -> Time {
        Time(self.below(span.as_nanos().max(1) as u64))
    }
}

/// Mixed into a seed for the draws of a coordinator crash.
const CRASH_STREAM: u64 = 0xc0_0d1e;

/// One thing that goes wrong, by worker index (0-based among the first workers).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Fault {
    /// The worker's process dies at `at`: its passes and links go with it.
    Kill { worker: usize, at: Time },
    /// A new worker registers at `at` and joins the running frame.
    Join { at: Time },
    /// Every message to or from the worker sent in the window is late by `extra`.
    Delay {
        worker: usize,
        window: Window,
        extra: Duration,
    },
    /// The link between two workers is cut for the window, then heals.
    Partition { a: usize, b: usize, window: Window },
    /// From `at` the worker takes no more peer bundles and acknowledges none (it is stuck on
    /// its peer port but still talks to the coordinator).
    StopAcking { worker: usize, at: Time },
    /// The coordinator's process dies at `at` (its job records not yet on disk are lost,
    /// every worker's control stream ends) and a new one starts `down` later from the
    /// records on disk.
    CrashCoordinator { at: Time, down: Duration },
}

/// The faults of one seed, and the seeded jitter on every message.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FaultPlan {
    pub seed: u64,
    pub faults: Vec<Fault>,
    /// Most extra delay of any message.
    pub jitter: Duration,
}

impl FaultPlan {
    /// No faults: the clean run.
    pub fn clean() -> Self {
        FaultPlan {
            seed: 0,
            faults: Vec::new(),
            jitter: Duration::ZERO,
        }
    }

    /// The plan of `seed` for `workers` workers whose clean frame took `span`. At least one
    /// of the first workers always survives (a frame whose every worker is lost is re-queued
    /// by the coordinator's job logic, which is not simulated).
    pub fn from_seed(seed: u64, workers: usize, span: Duration) -> Self {
        let mut rng = Rng::new(seed);
        let span = span.max(Duration::from_millis(1));
        let mut faults = Vec::new();
        let worker = |rng: &mut Rng| rng.below(workers as u64) as usize;
        let other = |rng: &mut Rng, not: usize| {
            (not + 1 + rng.below(workers as u64 - 1) as usize) % workers
        };
        let window = |rng: &mut Rng| {
            let from = rng.time_within(span);
            let long = Duration::from_nanos(rng.below(3 * span.as_nanos() as u64 + 1));
            Window {
                from,
                until: from + long,
            }
        };
        let kind = if workers < 2 { 3 } else { rng.below(8) };
        match kind {
            0 => faults.push(Fault::Kill {
                worker: worker(&mut rng),
                at: rng.time_within(span),
            }),
            1 if workers >= 3 => {
                // Two at once.
                let a = worker(&mut rng);
                let b = other(&mut rng, a);
                let at = rng.time_within(span);
                faults.push(Fault::Kill { worker: a, at });
                faults.push(Fault::Kill { worker: b, at });
            }
            1 | 2 => {
                // A death and a replacement.
                let at = rng.time_within(span);
                faults.push(Fault::Kill {
                    worker: worker(&mut rng),
                    at,
                });
                faults.push(Fault::Join {
                    at: at + Duration::from_nanos(rng.below(span.as_nanos() as u64 + 1)),
                });
            }
            3 => faults.push(Fault::Join {
                at: rng.time_within(span),
            }),
            4 => {
                let w = worker(&mut rng);
                let window = window(&mut rng);
                let extra = Duration::from_nanos(rng.below(span.as_nanos() as u64 + 1));
                faults.push(Fault::Delay {
                    worker: w,
                    window,
                    extra,
                });
            }
            5 => {
                let a = worker(&mut rng);
                let b = other(&mut rng, a);
                faults.push(Fault::Partition {
                    a,
                    b,
                    window: window(&mut rng),
                });
            }
            6 => faults.push(Fault::StopAcking {
                worker: worker(&mut rng),
                at: rng.time_within(span),
            }),
            _ => {
                // A death while another worker's links are slow.
                let a = worker(&mut rng);
                faults.push(Fault::Kill {
                    worker: a,
                    at: rng.time_within(span),
                });
                let window = window(&mut rng);
                faults.push(Fault::Delay {
                    worker: other(&mut rng, a),
                    window,
                    extra: Duration::from_nanos(rng.below(span.as_nanos() as u64 + 1)),
                });
            }
        }
        let jitter = Duration::from_nanos(rng.below(span.as_nanos() as u64 / 20 + 1));
        // On top of a quarter of the plans, drawn apart so that the faults above are the
        // same for a seed as before coordinator crashes were simulated.
        let mut crash = Rng::new(seed ^ CRASH_STREAM);
        if crash.below(4) == 0 {
            faults.push(Fault::CrashCoordinator {
                at: crash.time_within(span),
                down: Duration::from_nanos(crash.below(span.as_nanos() as u64 + 1)),
            });
        }
        FaultPlan {
            seed,
            faults,
            jitter,
        }
    }

    /// A short description for tables and failure reports.
    pub fn describe(&self) -> String {
        if self.faults.is_empty() {
            return "none".into();
        }
        let ms = |t: Time| t.0 as f64 / 1e6;
        self.faults
            .iter()
            .map(|f| match f {
                Fault::Kill { worker, at } => format!("kill w{worker} at {:.3} ms", ms(*at)),
                Fault::Join { at } => format!("join at {:.3} ms", ms(*at)),
                Fault::Delay {
                    worker,
                    window,
                    extra,
                } => format!(
                    "delay w{worker} by {:.3} ms in {:.3}..{:.3} ms",
                    extra.as_secs_f64() * 1e3,
                    ms(window.from),
                    ms(window.until)
                ),
                Fault::Partition { a, b, window } => format!(
                    "cut w{a}-w{b} in {:.3}..{:.3} ms",
                    ms(window.from),
                    ms(window.until)
                ),
                Fault::StopAcking { worker, at } => {
                    format!("w{worker} stops acknowledging at {:.3} ms", ms(*at))
                }
                Fault::CrashCoordinator { at, down } => format!(
                    "coordinator crashes at {:.3} ms, restarts {:.3} ms later",
                    ms(*at),
                    down.as_secs_f64() * 1e3
                ),
            })
            .collect::<Vec<_>>()
            .join(", ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exponential_draws_have_their_mean_and_its_spread() {
        let mut rng = Rng::new(11);
        let mean = Duration::from_micros(1500);
        let draws: Vec<f64> = (0..20_000)
            .map(|_| rng.exponential(mean).as_secs_f64() * 1e6)
            .collect();
        let avg = draws.iter().sum::<f64>() / draws.len() as f64;
        assert!((avg - 1500.0).abs() < 45.0, "mean {avg} us");
        // An exponential's median is ln 2 of its mean.
        let below = draws.iter().filter(|&&d| d < 1500.0 * 2f64.ln()).count();
        assert!((9_600..10_400).contains(&below), "{below} below the median");
    }

    #[test]
    fn a_seed_is_always_the_same_plan_and_seeds_differ() {
        let span = Duration::from_millis(50);
        assert_eq!(
            FaultPlan::from_seed(7, 3, span),
            FaultPlan::from_seed(7, 3, span)
        );
        let plans: std::collections::BTreeSet<String> = (0..64)
            .map(|s| FaultPlan::from_seed(s, 3, span).describe())
            .collect();
        assert!(plans.len() > 32, "seeds give too few distinct plans");
    }

    #[test]
    fn some_first_worker_always_survives() {
        for seed in 0..2000 {
            for workers in 1..5 {
                let plan = FaultPlan::from_seed(seed, workers, Duration::from_millis(10));
                let killed: std::collections::BTreeSet<usize> = plan
                    .faults
                    .iter()
                    .filter_map(|f| match f {
                        Fault::Kill { worker, .. } => Some(*worker),
                        _ => None,
                    })
                    .collect();
                assert!(killed.len() < workers, "seed {seed}: every worker killed");
            }
        }
    }
}
