//! What `rayfarm sim` prints and writes: a row per run (stdout and CSV) and the summary of a
//! schedule's fault seeds.

use std::io::Write;
use std::time::Duration;

use rayfarm_node::job::schedule_name;
use rayfarm_node::proto::Schedule;
use rayfarm_sim::Outcome;

use crate::units;

pub(super) fn print_row(schedule: Schedule, workers: usize, o: &Outcome, wall: f64) {
    let t = o.frame_time.map_or(f64::NAN, |t| t.as_secs_f64());
    eprintln!(
        "{} at {workers} workers: {wall:.1} s of wall time, {:.1} passes a worker",
        schedule_name(schedule),
        o.passes as f64 / workers.max(1) as f64
    );
    print_time(&o.time);
    if o.prefetches > 0 {
        eprintln!(
            "  of its {} loads, {} prefetched: {} used, {} wasted",
            o.loads, o.prefetches, o.prefetches_used, o.prefetches_wasted
        );
    }
    if o.peers_reported > 0 {
        eprintln!(
            "  {} peers reported unresponsive (bundles unacknowledged past the deadline)",
            o.peers_reported
        );
    }
    if let Some(r) = &o.coordinator_replayed {
        let secs = |d: Duration| d.as_secs_f64();
        eprintln!(
            "  coordinator machine replayed alone: {:.3} s of CPU for {} calls ({:.2}% of the frame; \
             priced busy {:.3} s): reports {:.3} s, tile results {:.3} s, heartbeats {:.3} s, \
             ticks {:.3} s, other {:.3} s (the clock's own {} ns a call taken out); {} rounds, \
             {} members planned, {} reports naming {} queues taken in; {}",
            secs(r.total()),
            r.calls,
            secs(r.total()) / t * 100.0,
            secs(o.coordinator_busy),
            secs(r.reports),
            secs(r.tile_results),
            secs(r.heartbeats),
            secs(r.ticks),
            secs(r.other),
            r.clock.as_nanos(),
            r.planning.rounds,
            r.planning.planned + r.planning.whole_members,
            r.planning.reports,
            r.planning.queues,
            if r.repeated {
                "its rounds planned what the run's did"
            } else {
                "ITS ROUNDS PLANNED OTHERWISE than the run's (the measure is not of this frame)"
            }
        );
    }
    println!(
        "{:<12} {:>7} {:>12.3} {:>7} {:>12} {:>10} {:>10} {:>12} {:>9} {:>7} {:>8.2}  {}",
        schedule_name(schedule),
        workers,
        t * 1e3,
        o.loads,
        units::human(o.storage_bytes),
        o.segments,
        o.rays_migrated,
        o.peer_bytes,
        o.messages,
        o.rounds,
        o.coordinator_busy.as_secs_f64() / t * 100.0,
        o.image_hash.as_deref().unwrap_or("-")
    );
}

/// Where a simulated worker's frame went, as `rayfarm bench` tabulates the real one's: the
/// mean over the workers' frames of each part, and its share of the frame.
fn print_time(t: &rayfarm_sim::FrameTime) {
    if t.frames == 0 {
        return;
    }
    let mean = |d: Duration| d.as_secs_f64() / t.frames as f64;
    let frame = mean(t.frame);
    let parts = t.parts();
    let accounted: f64 = parts.iter().map(|&(_, d)| mean(d)).sum();
    let share = |s: f64| s / frame.max(1e-12) * 100.0;
    let mut line = format!("  a worker's frame (mean): {frame:.3} s;");
    for (name, d) in parts {
        let s = mean(d);
        line.push_str(&format!(" {name} {s:.3} s ({:.0}%);", share(s)));
    }
    let other = frame - accounted;
    line.push_str(&format!(
        " other {other:.3} s ({:.0}%); the shell's computing, overlapping them, {:.3} s",
        share(other),
        mean(t.handling)
    ));
    eprintln!("{line}");
}

pub(super) fn write_csv(
    f: &mut std::fs::File,
    workers: usize,
    schedule: Schedule,
    seed: &str,
    faults: &str,
    o: &Outcome,
    wall: f64,
) -> anyhow::Result<()> {
    let violations: Vec<String> = o.violations.iter().map(|v| v.to_string()).collect();
    let quote = |s: &str| format!("\"{}\"", s.replace('"', "\"\""));
    write!(
        f,
        "{},{},{},{},{:.6},{},{},{},{},{},{},{},{:.6},{:.3},{},{}",
        workers,
        schedule_name(schedule),
        seed,
        quote(faults),
        o.frame_time.map_or(f64::NAN, |t| t.as_secs_f64() * 1e3),
        o.loads,
        o.storage_bytes,
        o.segments,
        o.rays_migrated,
        o.peer_bytes,
        o.messages,
        o.rounds,
        o.coordinator_busy.as_secs_f64() * 1e3,
        wall,
        o.image_hash.as_deref().unwrap_or(""),
        quote(&violations.join("; "))
    )?;
    let t = &o.time;
    let secs = |d: Duration| format!("{:.6}", d.as_secs_f64());
    let parts: Vec<String> = std::iter::once(t.frame)
        .chain(t.parts().map(|(_, d)| d))
        .chain([t.handling])
        .map(secs)
        .collect();
    writeln!(f, ",{},{},{}", o.passes, t.frames, parts.join(","))?;
    Ok(())
}

/// The CSV's columns of where the workers' frames went (`FrameTime`), seconds summed over
/// every worker's frame, after the frames counted: the frame, its parts in
/// `FrameTime::parts`'s order, and the shells' handling.
pub(super) const TIME_COLUMNS: &str = "frames,frame_seconds,loading_seconds,computing_seconds,\
    core_wait_seconds,thread_wait_seconds,shell_wait_seconds,idle_queued_seconds,\
    idle_verdicts_seconds,idle_empty_seconds,handling_seconds";

/// What the fault runs of one schedule came to.
#[derive(Default)]
pub(super) struct Summary {
    runs: u64,
    failed: u64,
    kills: u64,
    mid_pass: u64,
    mid_load: u64,
    in_flight: u64,
    /// Coordinator crashes, and frames started again after them or after losing every
    /// worker.
    crashes: u64,
    restarted_frames: u64,
    events: u64,
    /// Slowest faulty frame over the clean one.
    worst: f64,
}

impl Summary {
    pub(super) fn add(&mut self, o: &Outcome, clean: Duration) {
        self.runs += 1;
        self.failed += u64::from(!o.violations.is_empty());
        self.kills += o.kills.total;
        self.mid_pass += o.kills.mid_pass;
        self.mid_load += o.kills.mid_load;
        self.in_flight += o.kills.bundles_in_flight;
        self.crashes += o.coordinator_crashes;
        self.restarted_frames += o.frames.saturating_sub(o.jobs);
        self.events += o.events;
        if let Some(t) = o.frame_time {
            self.worst = self
                .worst
                .max(t.as_secs_f64() / clean.as_secs_f64().max(1e-12));
        }
    }

    pub(super) fn print(&self, schedule: Schedule, seeds: &std::ops::Range<u64>) {
        println!(
            "{}: seeds {}..{}: {} runs, {} failed; {} kills ({} mid-pass, {} mid-load, {} with \
             bundles in flight); {} coordinator crashes, {} frames started again; {} events; \
             slowest frame {:.2}x the clean one",
            schedule_name(schedule),
            seeds.start,
            seeds.end,
            self.runs,
            self.failed,
            self.kills,
            self.mid_pass,
            self.mid_load,
            self.in_flight,
            self.crashes,
            self.restarted_frames,
            self.events,
            self.worst
        );
    }
}

/// What the timing seeds of one schedule came to: each figure's median and range.
#[derive(Default)]
pub(super) struct Spread {
    millis: Vec<f64>,
    loads: Vec<f64>,
    migrated: Vec<f64>,
}

impl Spread {
    pub(super) fn add(&mut self, o: &Outcome) {
        if let Some(t) = o.frame_time {
            self.millis.push(t.as_secs_f64() * 1e3);
        }
        self.loads.push(o.loads as f64);
        self.migrated.push(o.rays_migrated as f64);
    }

    pub(super) fn print(&self, schedule: Schedule, workers: usize, seeds: &std::ops::Range<u64>) {
        println!(
            "{} at {workers} workers, timing seeds {}..{}: virtual ms {}, loads {}, rays migrated \
             {} (median [min-max])",
            schedule_name(schedule),
            seeds.start,
            seeds.end,
            median_range(&self.millis, 3),
            median_range(&self.loads, 0),
            median_range(&self.migrated, 0),
        );
    }
}

/// "median [min-max]" of `values` with `decimals` places (the median of an even count is the
/// mean of the middle two), or "-" for none.
fn median_range(values: &[f64], decimals: usize) -> String {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let (Some(min), Some(max)) = (v.first(), v.last()) else {
        return "-".into();
    };
    let mid = v.len() / 2;
    let median = if v.len().is_multiple_of(2) {
        (v[mid - 1] + v[mid]) / 2.0
    } else {
        v[mid]
    };
    format!("{median:.decimals$} [{min:.decimals$}-{max:.decimals$}]")
}

#[cfg(test)]
mod tests {
    use super::median_range;

    #[test]
    fn a_median_and_its_range() {
        assert_eq!(median_range(&[3.0, 1.0, 2.0], 0), "2 [1-3]");
        assert_eq!(median_range(&[4.0, 1.0, 2.0, 3.0], 1), "2.5 [1.0-4.0]");
        assert_eq!(median_range(&[], 0), "-");
    }
}
