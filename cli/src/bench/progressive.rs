//! `rayfarm bench --progressive`: each schedule's progressive runs against its one-pass runs,
//! side by side. What a progressive frame costs is the time and the domain loads beyond one
//! pass; what it buys is a first preview long before the end, and, when the caches hold what
//! a subframe needs, subframes after the first that load little or nothing. Pure: the runs
//! in, one row per schedule out.

use comfy_table::{ContentArrangement, Table, presets::UTF8_FULL_CONDENSED};
use rayfarm_core::cluster::stats::ClusterStats;

use super::report::{count, times};
use super::{RunOutcome, median, ratio};

/// The suffix `rayfarm bench` gives a schedule's progressive row.
pub const SUFFIX: &str = "+progressive";

/// One schedule's progressive runs against its one-pass runs (medians over successful runs).
#[derive(Clone, Debug, PartialEq)]
pub struct Comparison {
    /// The schedule (without the suffix).
    pub schedule: String,
    /// Wall time, seconds: one pass, progressive.
    pub wall: (f64, f64),
    /// Domain loads: one pass, progressive.
    pub loads: (f64, f64),
    /// Seconds from the progressive frame's start to its first subframe's last tile: when
    /// the first whole preview exists (a one-pass frame has its first at its end).
    pub first_preview: f64,
    /// Per subframe of the progressive runs, in order: (samples, median loads). Only the
    /// runs with the most common subframe count are counted, so the columns line up.
    pub per_subframe: Vec<(u32, f64)>,
}

/// One comparison per schedule that has both rows with a successful run each, in the order
/// of `schedules` (the bench's row names).
pub fn compare(schedules: &[String], runs: &[RunOutcome]) -> Vec<Comparison> {
    let ok = |name: &str| -> Vec<&ClusterStats> {
        runs.iter()
            .filter(|r| r.schedule == name)
            .filter_map(RunOutcome::stats)
            .collect()
    };
    let med = |v: &[&ClusterStats], f: &dyn Fn(&ClusterStats) -> f64| {
        median(&v.iter().map(|s| f(s)).collect::<Vec<_>>())
    };
    schedules
        .iter()
        .filter(|n| !n.ends_with(SUFFIX))
        .filter_map(|name| {
            let one = ok(name);
            let prog = ok(&format!("{name}{SUFFIX}"));
            let wall = |s: &ClusterStats| s.wall_seconds;
            let loads = |s: &ClusterStats| s.cache.loads as f64;
            let first = |s: &ClusterStats| {
                s.subframe_costs
                    .first()
                    .map_or(s.wall_seconds, |c| c.done_seconds)
            };
            Some(Comparison {
                schedule: name.clone(),
                wall: (med(&one, &wall)?, med(&prog, &wall)?),
                loads: (med(&one, &loads)?, med(&prog, &loads)?),
                first_preview: med(&prog, &first)?,
                per_subframe: per_subframe(&prog),
            })
        })
        .collect()
}

/// Median loads per subframe over the runs with the most common number of subframes.
fn per_subframe(runs: &[&ClusterStats]) -> Vec<(u32, f64)> {
    let lengths: Vec<usize> = runs.iter().map(|s| s.subframe_costs.len()).collect();
    let Some(&n) = lengths
        .iter()
        .max_by_key(|&&n| (lengths.iter().filter(|&&m| m == n).count(), n))
    else {
        return Vec::new();
    };
    let same: Vec<&&ClusterStats> = runs
        .iter()
        .filter(|s| s.subframe_costs.len() == n)
        .collect();
    (0..n)
        .filter_map(|i| {
            let samples = same[0].subframe_costs[i].samples;
            let loads: Vec<f64> = same
                .iter()
                .map(|s| s.subframe_costs[i].loads as f64)
                .collect();
            Some((samples, median(&loads)?))
        })
        .collect()
}

/// The table printed under the bench's: one row per schedule.
pub fn progressive_table(comparisons: &[Comparison]) -> Table {
    let mut t = Table::new();
    t.load_preset(UTF8_FULL_CONDENSED)
        .set_content_arrangement(ContentArrangement::Dynamic)
        .set_header(vec![
            "schedule",
            "wall: one pass",
            "progressive",
            "time ratio",
            "loads: one pass",
            "progressive",
            "loads ratio",
            "first preview after",
            "loads per subframe (its spp)",
        ]);
    for c in comparisons {
        t.add_row(vec![
            c.schedule.clone(),
            format!("{:.2} s", c.wall.0),
            format!("{:.2} s", c.wall.1),
            times(ratio(c.wall.1, c.wall.0)),
            count(c.loads.0),
            count(c.loads.1),
            times(ratio(c.loads.1, c.loads.0)),
            format!("{:.2} s", c.first_preview),
            c.per_subframe
                .iter()
                .map(|(spp, loads)| format!("{} ({spp})", count(*loads)))
                .collect::<Vec<_>>()
                .join(", "),
        ]);
    }
    t
}

#[cfg(test)]
mod tests {
    use rayfarm_core::cluster::stats::SubframeCost;

    use super::super::tests::{outcome, stats};
    use super::*;

    fn progressive(wall: f64, loads: &[u64], hash: &str) -> ClusterStats {
        let mut s = stats(wall, loads.iter().sum(), 1.0, 0.1, hash);
        let mut first = 0;
        s.subframe_costs = loads
            .iter()
            .enumerate()
            .map(|(i, &l)| {
                let samples = if i == 0 { 1 } else { 1 << (i - 1) };
                let c = SubframeCost {
                    first_sample: first,
                    samples,
                    done_seconds: wall * (i + 1) as f64 / loads.len() as f64,
                    loads: l,
                };
                first += samples;
                c
            })
            .collect();
        s
    }

    #[test]
    fn each_schedule_is_set_against_its_progressive_runs() {
        let names: Vec<String> = [
            "dynamic",
            "dynamic+progressive",
            "domain",
            "domain+progressive",
        ]
        .map(String::from)
        .to_vec();
        let runs = vec![
            outcome(1, "dynamic", Ok(stats(2.0, 48, 1.0, 0.1, "h"))),
            outcome(
                2,
                "dynamic+progressive",
                Ok(progressive(3.0, &[48, 0, 2], "h")),
            ),
            outcome(3, "dynamic", Ok(stats(4.0, 50, 1.0, 0.1, "h"))),
            outcome(
                4,
                "dynamic+progressive",
                Ok(progressive(5.0, &[46, 4, 0], "h")),
            ),
            // A run with another subframe count is left out of the per-subframe medians.
            outcome(
                5,
                "dynamic+progressive",
                Ok(progressive(4.0, &[40, 9], "h")),
            ),
            outcome(6, "domain", Ok(stats(1.0, 10, 1.0, 0.1, "h"))),
            outcome(7, "domain+progressive", Err("no worker".into())),
        ];
        let c = compare(&names, &runs);
        assert_eq!(c.len(), 1, "domain has no successful progressive run");
        let d = &c[0];
        assert_eq!(d.schedule, "dynamic");
        assert_eq!(d.wall, (3.0, 4.0));
        assert_eq!(d.loads, (49.0, 50.0));
        // First subframes ended at 1.0, 5/3 and 2.0 s.
        assert_eq!(d.first_preview, 5.0 / 3.0);
        assert_eq!(d.per_subframe, vec![(1, 47.0), (1, 2.0), (2, 1.0)]);
        let table = progressive_table(&c).to_string();
        assert!(table.contains("1.33x"), "{table}");
        assert!(table.contains("47 (1), 2 (1), 1 (2)"), "{table}");
    }

    #[test]
    fn one_pass_statistics_without_subframe_costs_count_their_end_as_the_first_preview() {
        let names: Vec<String> = ["hybrid", "hybrid+progressive"].map(String::from).to_vec();
        let runs = vec![
            outcome(1, "hybrid", Ok(stats(2.0, 8, 1.0, 0.1, "h"))),
            outcome(2, "hybrid+progressive", Ok(stats(3.0, 8, 1.0, 0.1, "h"))),
        ];
        let c = compare(&names, &runs);
        assert_eq!(c[0].first_preview, 3.0);
        assert!(c[0].per_subframe.is_empty());
    }
}
