//! Statistics of one rendered frame.

use serde::{Deserialize, Serialize};

use super::cache::CacheCounters;
use super::kernel::KernelCounters;

/// What a frame cost and produced.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RenderStats {
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Samples per pixel.
    pub spp: u32,
    /// Maximum bounces.
    pub max_depth: u32,
    /// Threads used for tracing.
    pub threads: usize,
    /// Domains in the scene.
    pub domains: usize,
    /// Wall time of the frame in seconds.
    pub wall_seconds: f64,
    /// Ray counts.
    pub rays: KernelCounters,
    /// Domain loads.
    pub cache: CacheCounters,
    /// Ray segments traced per second of wall time.
    pub rays_per_s: f64,
    /// `rays_per_s` divided by the threads.
    pub rays_per_s_per_core: f64,
    /// Times the fullest queue was taken and traced.
    pub queue_passes: u64,
    /// Peak resident memory of the process, bytes (0 where unknown).
    pub peak_rss_bytes: u64,
    /// xxh3-64 of the fixed-point pixel sums, 16 hex digits.
    pub image_hash: String,
}

/// The process's peak resident set, from `/proc/self/status` (0 where unavailable).
pub fn peak_rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("VmHWM:"))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}
