//! A scene on shared storage: a TOML manifest and one memory-mappable file per domain.

pub mod brick;
pub mod domain_file;
pub mod manifest;
pub mod partition;
pub mod residence;

use std::fs::File;
use std::path::{Path, PathBuf};

pub use domain_file::{DomainData, DomainSummary, write_domain};
pub use manifest::{Camera, DomainEntry, Light, Manifest, Material, Sky, SurfaceFile, VolumeSpec};
pub use partition::{DomainTree, KdNode};
pub use residence::{Received, Residence};

/// Name of the manifest inside a scene directory.
pub const MANIFEST_FILE: &str = "scene.toml";

/// What can be wrong with a scene on disk. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// Reading or writing failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The manifest does not parse or contradicts itself.
    #[error("{path}: malformed manifest: {reason}")]
    Manifest {
        /// The manifest file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A scene file that is no regular file (a FIFO, a device, a directory): never read.
    #[error("{path}: not a regular file")]
    NotRegular {
        /// The file.
        path: PathBuf,
    },
    /// A file larger than it may be: refused before reading.
    #[error("{path}: {bytes} bytes, more than the {max} a {what} may have")]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// Its size.
        bytes: u64,
        /// The most accepted.
        max: u64,
        /// What the file is ("manifest").
        what: &'static str,
    },
    /// A domain file is truncated, corrupt or does not match the manifest.
    #[error("{path}: bad domain file: {reason}")]
    Domain {
        /// The domain file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
}

impl SceneError {
    pub(crate) fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        SceneError::Io {
            path: path.into(),
            source,
        }
    }
}

/// Opens `path` for reading if it is a regular file of at most `max_bytes` (`what` names the
/// kind of file in the error); returns it with its size. The open never blocks: a FIFO or a
/// device named as a scene file is refused by its type, before any byte is read.
pub(crate) fn open_regular(
    path: &Path,
    max_bytes: u64,
    what: &'static str,
) -> Result<(File, u64), SceneError> {
    use std::os::unix::fs::OpenOptionsExt;
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path)
        .map_err(|e| SceneError::io(path, e))?;
    let meta = file.metadata().map_err(|e| SceneError::io(path, e))?;
    if !meta.is_file() {
        return Err(SceneError::NotRegular {
            path: path.to_path_buf(),
        });
    }
    if meta.len() > max_bytes {
        return Err(SceneError::TooLarge {
            path: path.to_path_buf(),
            bytes: meta.len(),
            max: max_bytes,
            what,
        });
    }
    Ok((file, meta.len()))
}

/// Writes `bytes` to `path` through a temporary name in the same directory, so a reader never
/// sees a half-written file.
pub fn write_atomically(path: &std::path::Path, bytes: &[u8]) -> Result<(), SceneError> {
    let tmp = temporary_name(path);
    std::fs::write(&tmp, bytes).map_err(|e| SceneError::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| SceneError::io(path, e))
}

/// Writes a domain's file (mesh or brick) as `header` then `body`, synced, through a
/// temporary name in the same directory, so a reader never sees a half-written file.
pub(crate) fn write_domain_file(
    path: &std::path::Path,
    header: &[u8],
    body: &[u8],
) -> Result<(), SceneError> {
    use std::io::Write;
    let tmp = temporary_name(path);
    let write = || -> std::io::Result<()> {
        let mut f = std::io::BufWriter::new(File::create(&tmp)?);
        f.write_all(header)?;
        f.write_all(body)?;
        f.into_inner().map_err(|e| e.into_error())?.sync_all()
    };
    write().map_err(|e| SceneError::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| SceneError::io(path, e))
}

/// The checksum a domain's file (mesh or brick) records: xxh3 of its header (with the
/// checksum field zero) followed by its body.
pub(crate) fn domain_checksum(header: &[u8], body: &[u8]) -> u64 {
    let mut h = xxhash_rust::xxh3::Xxh3::new();
    h.update(header);
    h.update(body);
    h.digest()
}

/// Checks a domain's file (mesh or brick) against its checksums: the one its header
/// records (`recorded`) must be the manifest's (`expected`), and with `verify` its contents
/// (`unsealed_header`, the header with the checksum field zero, then `body`) must hash to it.
pub(crate) fn check_domain_checksum(
    recorded: u64,
    expected: u64,
    verify: bool,
    unsealed_header: &[u8],
    body: &[u8],
) -> Result<(), String> {
    if recorded != expected {
        return Err(format!(
            "header checksum {recorded:016x} differs from the manifest's {expected:016x}"
        ));
    }
    if verify {
        let actual = domain_checksum(unsealed_header, body);
        if actual != recorded {
            return Err(format!(
                "contents hash to {actual:016x}, header says {recorded:016x} (corrupt file)"
            ));
        }
    }
    Ok(())
}

/// The name a file is written under before it is renamed into place.
pub fn temporary_name(path: &std::path::Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(format!(".tmp{}", std::process::id()));
    path.with_file_name(name)
}
