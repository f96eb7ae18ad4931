//! What `rayfarm bench` prints: the table with one row per schedule, the footnote saying how
//! the bound is computed, and the verdict on the images. Text only; the numbers come from the
//! parent module.

use comfy_table::{ContentArrangement, Table, presets::UTF8_FULL_CONDENSED};
use rayfarm_core::bundler::Tier;
use rayfarm_core::cluster::stats::tier_name;

use super::{
    Bound, BoundInputs, HashCheck, REFERENCE_SCHEDULE, ScheduleSummary, best_median, efficiency,
    generations, ratio, reference_loads,
};
use crate::units::human;

/// The comparison table: one row per schedule, medians over its successful runs. A schedule
/// whose runs all failed shows its error instead of numbers.
pub fn bench_table(summaries: &[ScheduleSummary], bound: Option<&Bound>) -> Table {
    let best = best_median(summaries);
    let reference = reference_loads(summaries);
    let mut t = Table::new();
    t.load_preset(UTF8_FULL_CONDENSED)
        .set_content_arrangement(ContentArrangement::Dynamic)
        .set_header(vec![
            "schedule".to_string(),
            "runs ok".into(),
            "wall time: median (min-max)".into(),
            "vs best".into(),
            "domain loads".into(),
            format!("loads vs {REFERENCE_SCHEDULE}"),
            "bytes loaded".into(),
            "of them from peers (loads)".into(),
            "of the loads prefetched (used / wasted)".into(),
            "rays traced (segments)".into(),
            "rays migrated".into(),
            "bytes between workers".into(),
            "bundles per tier".into(),
            "rounds".into(),
            "idle".into(),
            "peak RSS".into(),
            "efficiency (bound / time)".into(),
        ]);
    for s in summaries {
        let ok = format!("{}/{}", s.ok, s.runs);
        let Some(m) = &s.measured else {
            let mut row = vec![
                s.schedule.clone(),
                ok,
                format!("failed: {}", s.errors.join("; ")),
            ];
            row.extend(std::iter::repeat_n("-".to_string(), 14));
            t.add_row(row);
            continue;
        };
        t.add_row(vec![
            s.schedule.clone(),
            ok,
            format!(
                "{:.2} s ({:.2}-{:.2})",
                m.wall.median, m.wall.min, m.wall.max
            ),
            times(best.and_then(|b| ratio(m.wall.median, b))),
            count(m.domain_loads),
            times(reference.and_then(|r| ratio(m.domain_loads, r))),
            human(m.bytes_loaded.round() as u64),
            from_peers(m),
            prefetched(m),
            count(m.segments),
            count(m.rays_migrated),
            human(m.bytes_migrated.round() as u64),
            bundles(&m.bundles),
            count(m.rounds),
            format!("{:.1} %", m.idle_fraction * 100.0),
            human(m.peak_rss_bytes),
            percent(bound.and_then(|b| efficiency(b.seconds(), m.wall.median))),
        ]);
    }
    t
}

/// Where the workers' frames went: one row per schedule, the mean per worker over its runs.
pub fn split_table(summaries: &[ScheduleSummary]) -> Table {
    let mut t = Table::new();
    t.load_preset(UTF8_FULL_CONDENSED)
        .set_content_arrangement(ContentArrangement::Dynamic)
        .set_header(vec![
            "schedule",
            "frame",
            "tracing (CPU)",
            "tracing, waiting for a core",
            "loading",
            "idle: rays queued, not planned",
            "idle: waiting for verdicts",
            "idle: nothing queued",
            "finished pass waiting for the event loop",
            "pass waiting for a tracing thread",
            "other",
            "worker CPU outside tracing (overlaps)",
            "passes",
        ]);
    for s in summaries {
        let Some(m) = &s.measured else { continue };
        let p = &m.split;
        let part = |v: f64| format!("{v:.2} s ({:.0} %)", 100.0 * v / p.frame.max(1e-9));
        t.add_row(vec![
            s.schedule.clone(),
            format!("{:.2} s", p.frame),
            part(p.trace_cpu),
            part(p.trace_wait),
            part(p.load),
            part(p.idle_queued),
            part(p.idle_verdicts),
            part(p.idle_empty),
            part(p.pass_wait),
            part(p.start_wait),
            part(p.other),
            format!("{:.2} s", p.other_cpu),
            format!("{:.0}", p.passes),
        ]);
    }
    t
}

/// A row's bytes loaded from peers: "-" when none, else "BYTES (N)".
fn from_peers(m: &super::Measured) -> String {
    if m.peer_loads == 0.0 {
        return "-".into();
    }
    format!(
        "{} ({})",
        human(m.bytes_from_peers.round() as u64),
        count(m.peer_loads)
    )
}

/// A row's prefetches: "-" when it made none, else "N (used / wasted)".
fn prefetched(m: &super::Measured) -> String {
    if m.prefetches == 0.0 {
        return "-".into();
    }
    format!(
        "{} ({} / {})",
        count(m.prefetches),
        count(m.prefetches_used),
        count(m.prefetches_wasted)
    )
}

/// The footnote under the table: what the bound is, with its numbers, and what the other
/// columns mean. `bandwidth`: the storage bandwidth as typed.
pub fn bound_footnote(
    bound: Option<&Bound>,
    successful_runs: usize,
    inputs: &BoundInputs,
    bandwidth: Option<&str>,
) -> String {
    let legend = "wall times are the coordinator's (frame start to last tile); other columns \
                  are medians over a schedule's successful runs, except idle (the mean over \
                  workers and runs) and peak RSS (the largest worker's high-water mark since \
                  it started: the same workers serve every run); bundles per tier: r results, \
                  m migrated, t tasks.";
    let Some(b) = bound else {
        return format!("no run succeeded, so there is no bound; {legend}");
    };
    let scene: u64 = inputs.domain_bytes.iter().sum();
    let caches = match inputs.cache_bytes {
        Some(c) => format!("caches of {} x {}", b.workers, human(c)),
        None => "caches unknown (taken as unbounded)".into(),
    };
    let capped = if b.load_bytes < b.model_bytes {
        format!(
            ", capped at the fewest bytes a run loaded ({})",
            human(b.load_bytes)
        )
    } else {
        String::new()
    };
    let load = match bandwidth {
        Some(rate) => format!(
            "unavoidable domain bytes {} (the scene, {}, once, and again in each of {} later \
             ray generations what {caches} cannot keep{capped}) / ({} workers x {rate}) = \
             {:.3} s",
            human(b.model_bytes),
            human(scene),
            generations(inputs.max_depth).saturating_sub(1),
            b.workers,
            b.load_seconds
        ),
        None => "0 (no --storage-bandwidth given)".into(),
    };
    let compute = if b.compute_is_cpu {
        let cores = inputs
            .cores
            .map_or("cores unknown".to_string(), |c| format!("{c} cores here"));
        format!(
            "the sum over workers of their tracing threads' CPU seconds / min(threads, \
             available cores: {cores})"
        )
    } else {
        "the sum over workers of (busy - load) wall seconds / total threads".into()
    };
    format!(
        "efficiency = bound / median wall time, where bound = max(compute, loads) = {:.3} s:\n  \
         compute = the least ray work of the {successful_runs} successful runs: {compute} = \
         {:.3} s\n  \
         loads = {load}\n\
         {legend}",
        b.seconds(),
        b.compute_seconds
    )
}

/// The verdict on the images: one line when they agree, every group when they do not.
pub fn hash_verdict(check: &HashCheck) -> String {
    match check {
        HashCheck::NoImages => "no run succeeded: no images to compare".into(),
        HashCheck::Identical { count, hash } => {
            format!("all {count} images identical (hash {hash})")
        }
        HashCheck::Differ(groups) => {
            let mut text = format!(
                "IMAGES DIFFER: {} different hashes among the successful runs",
                groups.len()
            );
            for (hash, runs) in groups {
                text.push_str(&format!("\n  {hash}: {}", runs.join(", ")));
            }
            text
        }
    }
}

/// A count for the table: exact below 10,000, then with k, M or G.
pub fn count(v: f64) -> String {
    let a = v.abs();
    if a < 1e4 {
        if v.fract() == 0.0 {
            format!("{v:.0}")
        } else {
            format!("{v:.1}")
        }
    } else if a < 1e6 {
        format!("{:.1} k", v / 1e3)
    } else if a < 1e9 {
        format!("{:.2} M", v / 1e6)
    } else {
        format!("{:.2} G", v / 1e9)
    }
}

/// A ratio as "1.00x" (two decimals below 10, one above); "-" when there is none.
pub fn times(r: Option<f64>) -> String {
    match r {
        Some(r) if r < 10.0 => format!("{r:.2}x"),
        Some(r) => format!("{r:.1}x"),
        None => "-".into(),
    }
}

/// A fraction as a percentage; "-" when there is none.
pub fn percent(f: Option<f64>) -> String {
    f.map_or_else(|| "-".into(), |f| format!("{:.0} %", f * 100.0))
}

/// Bundles per tier, most urgent first, compact: "r0 m1661 t0".
pub fn bundles(per_tier: &[f64; Tier::COUNT]) -> String {
    Tier::MOST_URGENT_FIRST
        .iter()
        .zip(per_tier)
        .map(|(&tier, n)| {
            let initial = &tier_name(tier)[..1];
            format!("{initial}{}", count(*n).replace(' ', ""))
        })
        .collect::<Vec<_>>()
        .join(" ")
}

#[cfg(test)]
mod tests {
    use super::super::tests::inputs;
    use super::super::tests::{outcome, stats};
    use super::super::{bound, summarize};
    use super::*;

    fn row<'a>(table: &'a str, key: &str) -> &'a str {
        table
            .lines()
            .find(|l| l.contains(key))
            .unwrap_or_else(|| panic!("no {key:?} row in\n{table}"))
    }

    #[test]
    fn formats() {
        assert_eq!(count(48.0), "48");
        assert_eq!(count(2.5), "2.5");
        assert_eq!(count(12_345.0), "12.3 k");
        assert_eq!(count(2_400_000.0), "2.40 M");
        assert_eq!(times(Some(1.0)), "1.00x");
        assert_eq!(times(Some(12.34)), "12.3x");
        assert_eq!(times(None), "-");
        assert_eq!(percent(Some(0.434)), "43 %");
        assert_eq!(bundles(&[0.0, 1661.0, 0.0]), "r0 m1661 t0");
        assert_eq!(bundles(&[4.0, 18672.0, 2.5]), "r4 m18.7k t2.5");
    }

    #[test]
    fn the_table_compares_each_schedule_with_the_best_and_with_dynamic() {
        let runs = vec![
            outcome(1, "dynamic", Ok(stats(2.0, 4, 1.0, 0.0, "h"))),
            outcome(2, "domain", Ok(stats(4.0, 40, 1.5, 0.5, "h"))),
            outcome(3, "image-plane", Err("UNIMPLEMENTED: not yet".into())),
        ];
        let names: Vec<String> = ["dynamic", "domain", "image-plane"]
            .map(String::from)
            .into();
        let summaries = summarize(&names, &runs);
        let b = bound(&runs, &inputs(vec![1 << 20], None));
        let text = bench_table(&summaries, b.as_ref()).to_string();
        let dynamic = row(&text, "│ dynamic ");
        for want in ["1/1", "2.00 s (2.00-2.00)", "1.00x", "r0 m6 t0", "50 %"] {
            assert!(dynamic.contains(want), "{want:?} missing in {dynamic}");
        }
        let domain = row(&text, "│ domain ");
        for want in ["4.00 s", "2.00x", "10.0x", "25 %"] {
            assert!(domain.contains(want), "{want:?} missing in {domain}");
        }
        let failed = row(&text, "image-plane");
        assert!(failed.contains("0/1") && failed.contains("failed: UNIMPLEMENTED"));

        let note = bound_footnote(b.as_ref(), 2, &inputs(vec![1 << 20], None), None);
        assert!(
            note.contains("bound = max(compute, loads) = 1.000 s"),
            "{note}"
        );
        assert!(note.contains("no --storage-bandwidth"), "{note}");
        let mut with_caches = inputs(vec![1 << 19; 2], Some(1024.0 * 1024.0));
        with_caches.cache_bytes = Some(1 << 19);
        let b = bound(&runs, &with_caches);
        let note = bound_footnote(b.as_ref(), 2, &with_caches, Some("1MiB/s"));
        // 1 MiB once; each of 4 later generations again nothing (2 x 512 KiB kept); the
        // runs loaded 4 and 40 KiB, so the fewest, 4 KiB, at 2 x 1 MiB/s.
        assert!(
            note.contains("bytes 1.0 MiB (the scene, 1.0 MiB, once, and again in each of 4"),
            "{note}"
        );
        assert!(
            note.contains("capped at the fewest bytes a run loaded (4.0 KiB)) / (2 workers x 1MiB/s) = 0.002 s"),
            "{note}"
        );
        assert!(note.contains("(busy - load) wall seconds"), "{note}");
    }

    #[test]
    fn the_verdict_names_the_hash_or_every_differing_run() {
        let same = HashCheck::Identical {
            count: 9,
            hash: "00ff".into(),
        };
        assert_eq!(hash_verdict(&same), "all 9 images identical (hash 00ff)");
        let differ = HashCheck::Differ(vec![
            ("aa".into(), vec!["run 1 (dynamic, repeat 1)".into()]),
            ("bb".into(), vec!["run 2 (domain, repeat 1)".into()]),
        ]);
        let text = hash_verdict(&differ);
        assert!(
            text.starts_with("IMAGES DIFFER: 2 different hashes"),
            "{text}"
        );
        assert!(text.contains("\n  bb: run 2 (domain, repeat 1)"), "{text}");
    }
}
