//! The statistics table printed after a render.

use comfy_table::{Table, presets::UTF8_FULL_CONDENSED};
use rayfarm_common::render::stats::RenderStats;

use crate::units::human;

/// Renders the statistics of a frame as a two-column table.
pub fn stats_table(s: &RenderStats) -> Table {
    let r = &s.rays;
    let rows: Vec<(&str, String)> = vec![
        (
            "image",
            format!(
                "{}x{}, {} spp, depth {}",
                s.width, s.height, s.spp, s.max_depth
            ),
        ),
        ("wall time", format!("{:.3} s", s.wall_seconds)),
        ("threads", s.threads.to_string()),
        ("camera rays", r.primary_rays.to_string()),
        ("shadow rays", r.shadow_rays.to_string()),
        ("bounce rays (diffuse, glossy)", r.bounce_rays.to_string()),
        ("reflection rays (mirror)", r.reflection_rays.to_string()),
        (
            "segments traced (radiance / shadow)",
            format!("{} / {}", r.radiance_segments, r.shadow_segments),
        ),
        ("rays forwarded between domains", r.forwarded.to_string()),
        ("rays/s (segments)", format!("{:.3} M", s.rays_per_s / 1e6)),
        (
            "rays/s per core",
            format!("{:.3} M", s.rays_per_s_per_core / 1e6),
        ),
        ("domains", s.domains.to_string()),
        ("domain loads", s.cache.loads.to_string()),
        ("bytes loaded", human(s.cache.bytes_loaded)),
        ("evictions", s.cache.evictions.to_string()),
        ("queue passes", s.queue_passes.to_string()),
        ("peak RSS", human(s.peak_rss_bytes)),
        ("image hash", s.image_hash.clone()),
    ];
    let mut t = Table::new();
    t.load_preset(UTF8_FULL_CONDENSED)
        .set_header(vec!["statistic", "value"]);
    for (k, v) in rows {
        t.add_row(vec![k.to_string(), v]);
    }
    t
}
