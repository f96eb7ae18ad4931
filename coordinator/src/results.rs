//! Finished frames on disk: `<data dir>/jobs/<job id>/` holds `image.png`, `image.exr` and
//! `stats.json`, so results outlive the connection that asked for them.

use std::path::{Path, PathBuf};

use anyhow::Context;
use rayfarm_core::cluster::stats::ClusterStats;
use rayfarm_core::render::Film;
use rayfarm_core::tile::TileGrid;
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

/// The film file of a job's running frame: the committed tiles' fixed-point sums.
pub fn film_path(data_dir: &Path, job_id: &str) -> PathBuf {
    job_dir(data_dir, job_id).join("film.bin")
}

/// A fresh film for a job's frame in its directory (removed when dropped).
pub fn create_film(
    data_dir: &Path,
    job_id: &str,
    grid: TileGrid,
    spp: u32,
) -> anyhow::Result<Film> {
    let dir = job_dir(data_dir, job_id);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    Ok(Film::create(&film_path(data_dir, job_id), grid, spp)?)
}

/// Encodes the image in both formats from the film in one pass and writes the statistics
/// with the image hash; returns the statistics as JSON and the hash.
pub fn write(
    data_dir: &Path,
    job_id: &str,
    film: &Film,
    stats: &mut ClusterStats,
) -> anyhow::Result<(String, String)> {
    let dir = job_dir(data_dir, job_id);
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let png = image_path(data_dir, job_id, ImageFormat::Png);
    let exr = image_path(data_dir, job_id, ImageFormat::Exr);
    stats.image_hash = format!("{:016x}", film.save_all(&[&png, &exr])?);
    let json = serde_json::to_string_pretty(stats)?;
    std::fs::write(dir.join("stats.json"), &json)
        .with_context(|| format!("writing {}", dir.join("stats.json").display()))?;
    Ok((json, stats.image_hash.clone()))
}
