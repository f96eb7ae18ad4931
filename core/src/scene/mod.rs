//! A scene on shared storage: a TOML manifest and one memory-mappable file per domain.

pub mod domain_file;
pub mod manifest;
pub mod partition;

use std::path::PathBuf;

pub use domain_file::{DomainData, DomainSummary, write_domain};
pub use manifest::{Camera, DomainEntry, Light, Manifest, Material, Sky};
pub use partition::{DomainTree, KdNode};

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

/// Writes `bytes` to `path` through a temporary name in the same directory, so a reader never
/// sees a half-written file.
pub fn write_atomically(path: &std::path::Path, bytes: &[u8]) -> Result<(), SceneError> {
    let tmp = temporary_name(path);
    std::fs::write(&tmp, bytes).map_err(|e| SceneError::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| SceneError::io(path, e))
}

/// The name a file is written under before it is renamed into place.
pub fn temporary_name(path: &std::path::Path) -> PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(format!(".tmp{}", std::process::id()));
    path.with_file_name(name)
}
