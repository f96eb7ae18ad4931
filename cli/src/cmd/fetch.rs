//! `rayfarm fetch ID`: a finished job's image (and statistics) onto local disk. The same
//! code saves the result of `submit --wait` and `demo`.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::Args;
use rayfarm_node::proto;

use crate::client::{Coordinator, CoordinatorArgs, runtime};

/// Options of `rayfarm fetch`.
#[derive(Args, Clone, Debug)]
pub struct FetchArgs {
    #[command(flatten)]
    pub coordinator: CoordinatorArgs,
    /// The finished job.
    pub job_id: String,
    /// Output image: .png (8-bit sRGB) or .exr (linear float) [default: <job id>.png].
    #[arg(long, short, env = "RAYFARM_OUTPUT")]
    pub output: Option<PathBuf>,
    /// Also write the frame's statistics as JSON here.
    #[arg(long, env = "RAYFARM_STATS_JSON")]
    pub stats_json: Option<PathBuf>,
}

pub fn run(a: FetchArgs) -> anyhow::Result<()> {
    let output = a.output.unwrap_or_else(|| default_output(&a.job_id));
    let format = image_format(&output)?;
    check_writable(&output)?;
    if let Some(p) = &a.stats_json {
        check_writable(p)?;
    }
    runtime()?.block_on(async {
        let mut coord = a.coordinator.connect().await?;
        let result = save_result(
            &mut coord,
            &a.job_id,
            &output,
            format,
            a.stats_json.as_deref(),
        )
        .await?;
        println!("image hash: {}", result.image_hash);
        Ok(())
    })
}

/// Where an image goes when the user names no file.
pub fn default_output(job_id: &str) -> PathBuf {
    PathBuf::from(format!("{job_id}.png"))
}

/// The image format an output path asks for, by extension.
pub fn image_format(path: &Path) -> anyhow::Result<proto::ImageFormat> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match ext.as_deref() {
        Some("png") => Ok(proto::ImageFormat::Png),
        Some("exr") => Ok(proto::ImageFormat::Exr),
        _ => bail!(
            "{}: the output image must end in .png (8-bit sRGB) or .exr (linear float)",
            path.display()
        ),
    }
}

/// Refuses an output path that cannot be written (a missing or read-only directory), so a
/// frame is not rendered, or fetched, only to fail at the very end. The file itself is not
/// created: a test file next to it is made and removed.
pub fn check_writable(path: &Path) -> anyhow::Result<()> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    if !dir.is_dir() {
        bail!(
            "{}: the directory {} does not exist (create it first)",
            path.display(),
            dir.display()
        );
    }
    if path.is_dir() {
        bail!("{}: is a directory; give a file name", path.display());
    }
    tempfile::Builder::new()
        .prefix(".rayfarm-write-check-")
        .tempfile_in(dir)
        .map(drop)
        .map_err(|e| anyhow::anyhow!("{}: cannot write in {}: {e}", path.display(), dir.display()))
}

/// Fetches job `job_id`'s result as `format`, writes the image to `output` and, if asked, the
/// statistics to `stats_json` (pretty-printed). Returns what the coordinator sent.
pub async fn save_result(
    coord: &mut Coordinator,
    job_id: &str,
    output: &Path,
    format: proto::ImageFormat,
    stats_json: Option<&Path>,
) -> anyhow::Result<proto::FetchResultResponse> {
    let result = coord
        .fetch(job_id, format)
        .await
        .with_context(|| format!("fetching the result of job {job_id}"))?;
    if result.image.is_empty() {
        bail!("the coordinator sent an empty image for job {job_id}");
    }
    std::fs::write(output, &result.image)
        .with_context(|| format!("writing {}", output.display()))?;
    if let Some(path) = stats_json {
        write_stats_json(path, &result.stats_json)?;
    }
    Ok(result)
}

/// Writes the coordinator's statistics JSON, re-indented for people, keeping every field.
fn write_stats_json(path: &Path, json: &str) -> anyhow::Result<()> {
    let value: serde_json::Value =
        serde_json::from_str(json).context("the coordinator sent statistics that are not JSON")?;
    let text = serde_json::to_string_pretty(&value)?;
    std::fs::write(path, text + "\n").with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_extension_picks_the_format() {
        assert_eq!(
            image_format(Path::new("a/b.png")).unwrap(),
            proto::ImageFormat::Png
        );
        assert_eq!(
            image_format(Path::new("B.EXR")).unwrap(),
            proto::ImageFormat::Exr
        );
        let e = image_format(Path::new("out.jpg")).unwrap_err();
        assert!(e.to_string().contains(".png"), "{e}");
        assert!(image_format(Path::new("noext")).is_err());
        assert_eq!(default_output("j3"), PathBuf::from("j3.png"));
    }

    #[test]
    fn outputs_in_missing_directories_are_refused_up_front() {
        let tmp = tempfile::tempdir().unwrap();
        check_writable(&tmp.path().join("x.png")).unwrap();
        let e = check_writable(&tmp.path().join("nodir/x.png")).unwrap_err();
        assert!(e.to_string().contains("does not exist"), "{e}");
        let e = check_writable(tmp.path()).unwrap_err();
        assert!(e.to_string().contains("is a directory"), "{e}");
        // Nothing is left behind by the check.
        assert_eq!(std::fs::read_dir(tmp.path()).unwrap().count(), 0);
    }
}
