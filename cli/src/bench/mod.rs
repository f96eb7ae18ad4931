//! The arithmetic of `rayfarm bench`, kept pure so it can be tested without a cluster: the
//! order of the runs, medians and ratios per schedule, the lower bound on a frame's time and
//! each schedule's efficiency against it, and the check that every image is the same.
//!
//! `cmd::bench` runs the frames and feeds the results here. This module holds a run and the
//! plain statistics (run order, medians, spreads, ratios); [`lower_bound`] the bound and the
//! ray work it is made of, [`summary`] the per-schedule measures, [`hashes`] the image check.
//! [`report`] turns the summaries into the table, [`csv_out`] into one CSV row per run and
//! [`chart`] into a PNG.

pub mod chart;
pub mod csv_out;
pub mod hashes;
pub mod lower_bound;
pub mod progressive;
pub mod report;
pub mod summary;

use rayfarm_core::cluster::stats::ClusterStats;

pub use hashes::{HashCheck, check_hashes};
pub use lower_bound::{Bound, BoundInputs, bound, efficiency, generations, ray_work_seconds};
pub use summary::{
    Measured, ScheduleSummary, best_median, reference_loads, summarize, tier_bundles,
};

/// The schedule the domain-load ratios are measured against (the paper's algorithm).
pub const REFERENCE_SCHEDULE: &str = "dynamic";

/// One frame of the bench: which schedule in which repeat, and what came of it.
#[derive(Clone, Debug)]
pub struct RunOutcome {
    /// 1-based position in the whole bench.
    pub run: usize,
    /// 1-based repeat.
    pub repeat: usize,
    /// Schedule name.
    pub schedule: String,
    /// The job, once submitted.
    pub job_id: Option<String>,
    /// Seconds from submission to the job's last event, as this client saw it.
    pub client_seconds: f64,
    /// The frame's statistics, or why the run failed.
    pub result: Result<ClusterStats, String>,
}

impl RunOutcome {
    /// The statistics of a successful run.
    pub fn stats(&self) -> Option<&ClusterStats> {
        self.result.as_ref().ok()
    }
}

/// The runs of a bench as (repeat, schedule index), 1-based repeats: every schedule once per
/// repeat, the order rotated by one each repeat (a,b,c; b,c,a; c,a,b; ...), so that slow drift
/// of the machine (heat, other load) falls on every schedule alike.
pub fn run_order(schedules: usize, repeats: usize) -> Vec<(usize, usize)> {
    (0..repeats)
        .flat_map(|r| (0..schedules).map(move |i| (r + 1, (i + r) % schedules)))
        .collect()
}

/// The median of `values` (the mean of the middle two for an even count); `None` when empty.
pub fn median(values: &[f64]) -> Option<f64> {
    let mut v: Vec<f64> = values.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    match n {
        0 => None,
        _ if n % 2 == 1 => Some(v[n / 2]),
        _ => Some((v[n / 2 - 1] + v[n / 2]) / 2.0),
    }
}

/// Median, least and largest of some measurements.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Spread {
    pub median: f64,
    pub min: f64,
    pub max: f64,
}

/// The spread of `values`; `None` when empty.
pub fn spread(values: &[f64]) -> Option<Spread> {
    Some(Spread {
        median: median(values)?,
        min: values.iter().copied().fold(f64::INFINITY, f64::min),
        max: values.iter().copied().fold(f64::NEG_INFINITY, f64::max),
    })
}

/// `value / reference`, or `None` when the reference is zero, negative or not finite (no
/// meaningful ratio).
pub fn ratio(value: f64, reference: f64) -> Option<f64> {
    (reference.is_finite() && reference > 0.0 && value.is_finite()).then(|| value / reference)
}

#[cfg(test)]
pub(crate) mod tests;
