//! Finished frames on disk: `<data dir>/jobs/<job id>/` holds `image.png`, `image.exr` and
//! `stats.json`, so results outlive the connection that asked for them.

use std::path::{Path, PathBuf};

use anyhow::Context;
use rayfarm_core::cluster::stats::ClusterStats;
use rayfarm_core::render::Film;
use rayfarm_node::proto::ImageFormat;

/// The directory of one job's results.
pub fn job_dir(data_dir: &Path, job_id: &str) -> PathBuf {
    data_dir.join("jobs").join(job_id)
}

/// The file holding a job's image in `format`.
pub fn image_path(data_dir: &Path, job_id: &str, format: ImageFormat) -> PathBuf {
    let name = match format {
        ImageFormat::Exr => "image.exr",
        ImageFormat::Png | ImageFormat::Unspecified => "image.png",
    };
    job_dir(data_dir, job_id).join(name)
}

/// Writes the image in both formats and the statistics; returns the statistics as JSON.
pub fn write(
    data_dir: &Path,
    job_id: &str,
    film: &Film,
    stats: &ClusterStats,
) -> anyhow::Result<String> {
    let dir = job_dir(data_dir, job_id);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    for format in [ImageFormat::Png, ImageFormat::Exr] {
        film.save(&image_path(data_dir, job_id, format))?;
    }
    let json = serde_json::to_string_pretty(stats)?;
    std::fs::write(dir.join("stats.json"), &json)
        .with_context(|| format!("writing {}", dir.join("stats.json").display()))?;
    Ok(json)
}
