//! The statistics tables printed after a frame: one for a local render, one for a frame the
//! cluster rendered (plus its per-worker breakdown). Rows that mean the same thing are built by
//! the same helpers so the two tables read alike.

use comfy_table::{Table, presets::UTF8_FULL_CONDENSED};
use rayfarm_core::cluster::stats::{ClusterStats, WorkerFrameStats};
use rayfarm_core::render::cache::CacheCounters;
use rayfarm_core::render::kernel::KernelCounters;
use rayfarm_core::render::stats::RenderStats;

use crate::units::human;

/// Renders the statistics of a frame as a two-column table.
pub fn stats_table(s: &RenderStats) -> Table {
    let mut rows: Vec<(&str, String)> = vec![
        (
            "image",
            format!(
                "{}x{}, {} spp, depth {}",
                s.width, s.height, s.spp, s.max_depth
            ),
        ),
        ("wall time", format!("{:.3} s", s.wall_seconds)),
        ("threads", s.threads.to_string()),
    ];
    rows.extend(ray_rows(&s.rays));
    rows.extend(rate_rows(s.rays_per_s, s.rays_per_s_per_core));
    rows.push(("domains", s.domains.to_string()));
    rows.extend(cache_rows(&s.cache));
    rows.extend([
        ("queue passes", s.queue_passes.to_string()),
        ("peak RSS", human(s.peak_rss_bytes)),
        ("image hash", s.image_hash.clone()),
    ]);
    two_columns(rows)
}

/// Renders the statistics of a frame rendered by the cluster as a two-column table: the same
/// rows as a local render's where they mean the same, then rounds and traffic between workers.
pub fn cluster_stats_table(s: &ClusterStats) -> Table {
    let tier_keys: Vec<String> = s
        .tiers
        .iter()
        .map(|t| format!("{} tier: bundles / messages / bytes", t.tier))
        .collect();
    let mut rows: Vec<(&str, String)> = vec![
        (
            "image",
            format!(
                "{}x{}, {} spp, depth {}",
                s.width, s.height, s.spp, s.max_depth
            ),
        ),
        ("scene", s.scene.clone()),
        ("schedule", s.schedule.clone()),
        ("workers", s.workers.to_string()),
        ("threads", s.threads.to_string()),
        ("wall time", format!("{:.3} s", s.wall_seconds)),
    ];
    rows.extend(ray_rows(&s.rays));
    rows.extend(rate_rows(s.rays_per_s, s.rays_per_s_per_core));
    rows.push(("rounds", s.rounds.to_string()));
    rows.push(("domains", s.domains.to_string()));
    rows.extend(cache_rows(&s.cache));
    rows.push(("rays migrated between workers", s.rays_migrated.to_string()));
    // Only the hybrid schedule hands work to idle workers; elsewhere the row would be noise.
    if s.rays_shared > 0 {
        rows.push(("of them, tasks for idle workers", s.rays_shared.to_string()));
    }
    rows.push(("bytes migrated between workers", human(s.bytes_migrated)));
    for (t, key) in s.tiers.iter().zip(&tier_keys) {
        rows.push((
            key,
            format!(
                "{} / {} / {}",
                t.sent.bundles,
                t.sent.messages,
                human(t.sent.bytes)
            ),
        ));
    }
    // The kernel's high-water mark, kept for a process's whole life: earlier, bigger frames
    // of the same worker count too.
    rows.push((
        "peak RSS (largest worker, since it started)",
        human(s.peak_rss_bytes),
    ));
    rows.push(("image hash", s.image_hash.clone()));
    two_columns(rows)
}

/// One row per worker: what each did for the frame.
pub fn worker_stats_table(workers: &[WorkerFrameStats]) -> Table {
    let mut t = Table::new();
    t.load_preset(UTF8_FULL_CONDENSED).set_header(vec![
        "worker",
        "threads",
        "segments",
        "domain loads",
        "rays sent",
        "rays received",
        "busy",
        "idle",
        "peak RSS since start",
    ]);
    for w in workers {
        t.add_row(vec![
            w.worker_id.clone(),
            w.threads.to_string(),
            w.rays.segments().to_string(),
            w.cache.loads.to_string(),
            w.rays_sent.to_string(),
            w.rays_received.to_string(),
            format!("{:.3} s", w.busy_seconds),
            format!("{:.1} %", w.idle_fraction * 100.0),
            human(w.peak_rss_bytes),
        ]);
    }
    t
}

/// Rays created and traced, by kind.
fn ray_rows(r: &KernelCounters) -> [(&'static str, String); 6] {
    [
        ("camera rays", r.primary_rays.to_string()),
        ("shadow rays", r.shadow_rays.to_string()),
        ("bounce rays (diffuse, glossy)", r.bounce_rays.to_string()),
        ("reflection rays (mirror)", r.reflection_rays.to_string()),
        (
            "segments traced (radiance / shadow)",
            format!("{} / {}", r.radiance_segments, r.shadow_segments),
        ),
        ("rays forwarded between domains", r.forwarded.to_string()),
    ]
}

/// Throughput in ray segments.
fn rate_rows(rays_per_s: f64, per_core: f64) -> [(&'static str, String); 2] {
    [
        ("rays/s (segments)", format!("{:.3} M", rays_per_s / 1e6)),
        ("rays/s per core", format!("{:.3} M", per_core / 1e6)),
    ]
}

/// Domain cache traffic.
fn cache_rows(c: &CacheCounters) -> [(&'static str, String); 3] {
    [
        ("domain loads", c.loads.to_string()),
        ("bytes loaded", human(c.bytes_loaded)),
        ("evictions", c.evictions.to_string()),
    ]
}

fn two_columns(rows: Vec<(&str, String)>) -> Table {
    let mut t = Table::new();
    t.load_preset(UTF8_FULL_CONDENSED)
        .set_header(vec!["statistic", "value"]);
    for (k, v) in rows {
        t.add_row(vec![k.to_string(), v]);
    }
    t
}

#[cfg(test)]
mod tests {
    use rayfarm_core::bundler::TierStats;
    use rayfarm_core::cluster::stats::TierTraffic;

    use super::*;

    fn worker(id: &str, segments: u64, rss: u64) -> WorkerFrameStats {
        WorkerFrameStats {
            worker_id: id.into(),
            threads: 2,
            rays: KernelCounters {
                radiance_segments: segments,
                ..Default::default()
            },
            cache: CacheCounters {
                loads: 3,
                bytes_loaded: 3 << 20,
                ..Default::default()
            },
            rays_sent: 10,
            bytes_sent: 800,
            rays_received: 7,
            tiers: vec![TierTraffic {
                tier: "migrated".into(),
                sent: TierStats {
                    bundles: 2,
                    messages: 5,
                    bytes: 2048,
                    rejected: 0,
                },
            }],
            busy_seconds: 1.5,
            load_seconds: 0.0,
            frame_seconds: 2.0,
            idle_fraction: 0.25,
            peak_rss_bytes: rss,
            // Fields added later default to zero.
            ..Default::default()
        }
    }

    fn sample() -> ClusterStats {
        let mut s = ClusterStats {
            job_id: "j1".into(),
            scene: "nbody".into(),
            schedule: "dynamic".into(),
            width: 96,
            height: 72,
            spp: 2,
            max_depth: 3,
            domains: 16,
            wall_seconds: 2.0,
            rounds: 11,
            image_hash: "0123456789abcdef".into(),
            ..Default::default()
        };
        s.absorb(vec![
            worker("w1", 1_000_000, 300 << 20),
            worker("w2", 3_000_000, 500 << 20),
        ]);
        s
    }

    fn row<'a>(table: &'a str, key: &str) -> &'a str {
        table
            .lines()
            .find(|l| l.contains(key))
            .unwrap_or_else(|| panic!("no {key:?} row in\n{table}"))
    }

    #[test]
    fn the_cluster_table_shows_totals_traffic_and_the_largest_worker() {
        let text = cluster_stats_table(&sample()).to_string();
        assert!(row(&text, "image").contains("96x72, 2 spp, depth 3"));
        assert!(row(&text, "workers").contains('2'));
        assert!(row(&text, "threads").contains('4'));
        assert!(row(&text, "segments traced").contains("4000000 / 0"));
        // 4 M segments in 2 s on 4 threads.
        assert!(row(&text, "rays/s (segments)").contains("2.000 M"));
        assert!(row(&text, "rays/s per core").contains("0.500 M"));
        assert!(row(&text, "rounds").contains("11"));
        assert!(row(&text, "domain loads").contains('6'));
        assert!(row(&text, "bytes loaded").contains("6.0 MiB"));
        assert!(row(&text, "rays migrated").contains("20"));
        assert!(row(&text, "bytes migrated").contains("1.6 KiB"));
        assert!(row(&text, "migrated tier").contains("4 / 10 / 4.0 KiB"));
        assert!(row(&text, "peak RSS").contains("500.0 MiB"));
        assert!(row(&text, "image hash").contains("0123456789abcdef"));
    }

    #[test]
    fn the_worker_table_has_a_row_per_worker() {
        let text = worker_stats_table(&sample().per_worker).to_string();
        let w2 = row(&text, "w2");
        for want in ["3000000", "1.500 s", "25.0 %", "500.0 MiB"] {
            assert!(w2.contains(want), "{want:?} missing in {w2}");
        }
        assert!(row(&text, "w1").contains("300.0 MiB"));
    }
}
