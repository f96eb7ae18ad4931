//! The bench's report: the table of medians against the bound, the image check, the failures,
//! the CSV of every run and the chart.

use anyhow::bail;

use crate::bench::csv_out::{Setup, write_runs_file};
use crate::bench::progressive::{compare, progressive_table};
use crate::bench::report::{bench_table, bound_footnote, hash_verdict, split_table};
use crate::bench::{BoundInputs, HashCheck, RunOutcome, bound, check_hashes, summarize};
use crate::units::human;

use super::*;

/// Prints the table, the bound, the image check and the failures; writes the CSV and the
/// chart. An error if every run failed or the images differ.
pub(super) fn report(
    a: &BenchArgs,
    plan: &Plan,
    runs: &[RunOutcome],
    setup: &Setup,
) -> anyhow::Result<()> {
    let summaries = summarize(&plan.names(), runs);
    let bandwidth = a
        .storage_bandwidth
        .as_ref()
        .map(|r| r.bytes_per_second as f64);
    let inputs = BoundInputs {
        domain_bytes: plan.domain_bytes.clone(),
        workers: setup.workers.unwrap_or(0),
        cache_bytes: setup.cache_bytes_per_worker,
        bandwidth,
        max_depth: setup.depth,
        // The cores this machine gives the bench (affinity and cgroup quotas counted): those
        // of a cluster the bench started itself; another cluster's are not known.
        cores: setup
            .workers
            .map(|_| std::thread::available_parallelism().map_or(1, |n| n.get())),
    };
    let bound = bound(runs, &inputs);
    let ok = runs.iter().filter(|r| r.result.is_ok()).count();
    println!("{}", describe(plan, setup, runs));
    println!("{}", bench_table(&summaries, bound.as_ref()));
    println!(
        "{}",
        bound_footnote(
            bound.as_ref(),
            ok,
            &inputs,
            a.storage_bandwidth.as_ref().map(|r| r.text.as_str())
        )
    );
    println!(
        "where a worker's frame went (mean per worker over the runs; tracing CPU is the \
         tracing threads' CPU time, the rest of the passes' ray work waited for a core):"
    );
    println!("{}", split_table(&summaries));
    for s in summaries
        .iter()
        .filter(|s| s.ok > 0 && !s.errors.is_empty())
    {
        println!(
            "note: {} of {} {} runs failed: {}",
            s.runs - s.ok,
            s.runs,
            s.schedule,
            s.errors.join("; ")
        );
    }
    if a.progressive.is_some() {
        println!(
            "progressive against one pass (medians; first preview: when the first subframe's \
             last tile came back, from the frame's start; loads per subframe: summed over \
             workers, with the subframe's samples per pixel):"
        );
        println!("{}", progressive_table(&compare(&plan.names(), runs)));
    }
    let check = check_hashes(runs);
    println!("{}", hash_verdict(&check));
    if let Some(csv) = &plan.csv {
        write_runs_file(csv, runs, setup)?;
        println!("wrote {}", csv.display());
    }
    if let Some(chart) = &plan.chart {
        if ok == 0 {
            eprintln!("no chart: no run succeeded");
        } else {
            crate::bench::chart::write_chart(chart, &chart_title(plan, setup, runs), &summaries)?;
            println!("wrote {}", chart.display());
        }
    }
    if ok == 0 {
        bail!("every run failed");
    }
    if matches!(check, HashCheck::Differ(_)) {
        bail!("the schedules rendered different images (listed above)");
    }
    Ok(())
}

/// Workers of the bench: those started, or those that took part in the first successful run
/// on an existing cluster.
fn workers_of(setup: &Setup, runs: &[RunOutcome]) -> Option<usize> {
    setup
        .workers
        .or_else(|| runs.iter().find_map(|r| r.stats().map(|s| s.workers)))
}

/// The line above the table: what was measured.
fn describe(plan: &Plan, setup: &Setup, runs: &[RunOutcome]) -> String {
    let workers = workers_of(setup, runs).map_or("?".to_string(), |w| w.to_string());
    let mut text = format!(
        "scene {} ({} domains, {}), {}x{}, {} spp, depth {}, {} workers",
        plan.scene_name,
        plan.domains,
        human(plan.scene_bytes),
        setup.width,
        setup.height,
        setup.spp,
        setup.depth,
        workers
    );
    if let (Some(t), Some(c)) = (setup.threads_per_worker, setup.cache_bytes_per_worker) {
        text.push_str(&format!(
            " x {t} thread{}, {} cache each",
            if t == 1 { "" } else { "s" },
            human(c)
        ));
    }
    if !setup.replicate.is_empty() {
        text.push_str(&format!(", replicate {}", setup.replicate));
    }
    if !setup.storage_bandwidth.is_empty() {
        text.push_str(&format!(", storage {}", setup.storage_bandwidth));
    }
    if !setup.storage_latency.is_empty() {
        text.push_str(&format!(" + {} per load", setup.storage_latency));
    }
    text.push_str(&format!(
        ", {} repeat{}, cold caches",
        plan.repeats,
        if plan.repeats == 1 { "" } else { "s" }
    ));
    text
}

/// The chart's title: scene, workers, cache.
fn chart_title(plan: &Plan, setup: &Setup, runs: &[RunOutcome]) -> String {
    let workers = workers_of(setup, runs).map_or("?".to_string(), |w| w.to_string());
    let cache = setup
        .cache_bytes_per_worker
        .map_or(String::new(), |c| format!(", {} cache each", human(c)));
    format!(
        "{} ({} domains, {}), {} workers{cache}, {}x{}, {} spp",
        plan.scene_name,
        plan.domains,
        human(plan.scene_bytes),
        workers,
        setup.width,
        setup.height,
        setup.spp
    )
}
