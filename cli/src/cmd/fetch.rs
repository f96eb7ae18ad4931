//! `rayfarm fetch ID`: a finished job's image (and statistics) onto local disk. The same
//! code saves the result of `submit --wait` and `demo`.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, bail};
use clap::Args;
use rayfarm_node::proto;

use crate::client::{Coordinator, CoordinatorArgs, is_unavailable, runtime};

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
            Duration::ZERO,
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

/// Where the bytes of an image being fetched go until all are in and checked.
pub fn part_path(output: &Path) -> PathBuf {
    let mut name = output.as_os_str().to_owned();
    name.push(".part");
    PathBuf::from(name)
}

/// Fetches job `job_id`'s result as `format`, streamed chunk by chunk into `<output>.part`
/// (resuming after what an earlier, interrupted fetch left there), checks the whole file
/// against the coordinator's checksum and renames it to `output`; writes the statistics to
/// `stats_json` (pretty-printed) if asked. A stream lost midway is resumed at the byte it
/// stopped at, reconnecting until `ride_out` has passed. Returns what the coordinator said
/// of the result.
pub async fn save_result(
    coord: &mut Coordinator,
    job_id: &str,
    output: &Path,
    format: proto::ImageFormat,
    stats_json: Option<&Path>,
    ride_out: Duration,
) -> anyhow::Result<proto::FetchResultHeader> {
    let part = part_path(output);
    let mut file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&part)
        .with_context(|| format!("opening {}", part.display()))?;
    let deadline = tokio::time::Instant::now() + ride_out;
    let header = loop {
        match stream_into(coord, job_id, format, &mut file, &part).await {
            Ok(header) => break header,
            Err(e) if is_unavailable(&e) && tokio::time::Instant::now() < deadline => {
                tracing::warn!(error = %e, "fetch interrupted; resuming");
                coord.reconnect(deadline).await?;
            }
            Err(e) => {
                // Nothing received (an unknown job, a refusal): leave no empty file behind.
                if file.metadata().is_ok_and(|m| m.len() == 0) {
                    drop(file);
                    let _ = std::fs::remove_file(&part);
                    return Err(e.context(format!("fetching the result of job {job_id}")));
                }
                return Err(e.context(format!(
                    "fetching the result of job {job_id} (the bytes received are kept in {}: \
                     the same command resumes after them)",
                    part.display()
                )));
            }
        }
    };
    drop(file);
    let (len, sum) = rayfarm_node::result_file::checksum(&part)
        .with_context(|| format!("reading {}", part.display()))?;
    if len != header.total_bytes || sum != header.checksum {
        let _ = std::fs::remove_file(&part);
        bail!(
            "the fetched result of job {job_id} ({len} bytes, checksum {sum}) differs from the \
             coordinator's ({} bytes, checksum {}); removed it, fetch again",
            header.total_bytes,
            header.checksum
        );
    }
    std::fs::rename(&part, output)
        .with_context(|| format!("renaming {} to {}", part.display(), output.display()))?;
    if let Some(path) = stats_json {
        write_stats_json(path, &header.stats_json)?;
    }
    Ok(header)
}

/// Appends the rest of the result to `file` from where it ends; returns the header once the
/// stream has delivered every byte.
async fn stream_into(
    coord: &mut Coordinator,
    job_id: &str,
    format: proto::ImageFormat,
    file: &mut std::fs::File,
    part: &Path,
) -> anyhow::Result<proto::FetchResultHeader> {
    let mut have = file
        .metadata()
        .with_context(|| format!("reading {}", part.display()))?
        .len();
    let mut stream = coord.fetch_stream(job_id, format, have).await;
    if let Err(e) = &stream
        && have > 0
        && e.to_string().contains("OUT_OF_RANGE")
    {
        // Left by a fetch of another file: start over.
        file.set_len(0)?;
        have = 0;
        stream = coord.fetch_stream(job_id, format, 0).await;
    }
    let mut stream = stream?;
    let mut header = None;
    if have > 0 {
        tracing::info!(offset = have, "resuming a fetch");
    }
    loop {
        let chunk = match stream.message().await {
            Ok(Some(chunk)) => chunk,
            Ok(None) => break,
            Err(status) => return Err(coord.rpc_error(&status)),
        };
        if let Some(h) = chunk.header {
            header = Some(h);
        }
        if chunk.offset != have {
            bail!(
                "the coordinator sent bytes from {} where {have} were expected",
                chunk.offset
            );
        }
        file.write_all(&chunk.data)
            .with_context(|| format!("writing {}", part.display()))?;
        have += chunk.data.len() as u64;
    }
    let header = header.context("the coordinator's stream ended without a header")?;
    if have != header.total_bytes {
        bail!(
            "the coordinator's stream ended at byte {have} of {}",
            header.total_bytes
        );
    }
    Ok(header)
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
