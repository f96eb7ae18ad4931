//! Scenes are named relative to a scene root that every node is configured with, so one job
//! works whatever the mount point on each node. A name resolves under the root only: no `..`,
//! and the resolved directory and its manifest, symlinks followed, must stay inside it.
//! Absolute paths are refused unless the node allows them (`--allow-absolute-scenes`, for
//! clusters where every node sees the same paths).
//!
//! Whether a name is missing or leads outside the root gets the same answer, so a caller
//! learns nothing about paths outside it.

use std::path::{Component, Path, PathBuf};

use crate::scene::MANIFEST_FILE;

/// Why a scene name cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SceneRefError {
    /// The job named no scene and no default is configured.
    #[error("the job names no scene and the coordinator has no default scene (--default-scene)")]
    Missing,
    /// A relative name that climbs out of the scene root.
    #[error("scene name {0:?} must stay inside the scene root (no `..`)")]
    Escapes(String),
    /// An absolute path where only names under the scene root are allowed.
    #[error(
        "scene {0:?} is an absolute path: name a scene under the scene root (absolute paths \
         need --allow-absolute-scenes on every node)"
    )]
    Absolute(String),
    /// No scene directory of that name inside the scene root.
    #[error(
        "scene {0:?} not found: no directory of that name with a {MANIFEST_FILE} inside the \
         scene root"
    )]
    NotFound(String),
    /// The scene root itself cannot be used.
    #[error("the scene root {root} is unusable: {reason}", root = .0.display(), reason = .1)]
    Root(PathBuf, String),
}

/// The directory of `scene` on a node whose scene root is `root`, with symlinks resolved
/// (canonical). With `allow_absolute`, an absolute path is taken as it is.
pub fn resolve(root: &Path, scene: &str, allow_absolute: bool) -> Result<PathBuf, SceneRefError> {
    if scene.is_empty() {
        return Err(SceneRefError::Missing);
    }
    let path = Path::new(scene);
    let not_found = || SceneRefError::NotFound(scene.to_string());
    if path.is_absolute() {
        if !allow_absolute {
            return Err(SceneRefError::Absolute(scene.to_string()));
        }
        let dir = path.canonicalize().map_err(|_| not_found())?;
        return if dir.is_dir() {
            Ok(dir)
        } else {
            Err(not_found())
        };
    }
    if path
        .components()
        .any(|c| !matches!(c, Component::Normal(_) | Component::CurDir))
    {
        return Err(SceneRefError::Escapes(scene.to_string()));
    }
    let root = root
        .canonicalize()
        .map_err(|e| SceneRefError::Root(root.to_path_buf(), e.to_string()))?;
    let inside = |p: &Path| p.canonicalize().ok().filter(|c| c.starts_with(&root));
    let dir = inside(&root.join(path))
        .filter(|d| d.is_dir())
        .ok_or_else(not_found)?;
    // The manifest may be a symlink too; one leading outside is answered as missing. A
    // manifest that does not exist at all is left to the reader, which names the file.
    let manifest = dir.join(MANIFEST_FILE);
    if manifest.symlink_metadata().is_ok() && inside(&manifest).is_none() {
        return Err(not_found());
    }
    Ok(dir)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_resolve_under_the_root_only() {
        let root = tempfile::tempdir().unwrap();
        let outside = tempfile::tempdir().unwrap();
        let root_c = root.path().canonicalize().unwrap();
        std::fs::create_dir_all(root.path().join("city/v2")).unwrap();
        std::fs::write(outside.path().join(MANIFEST_FILE), "secret").unwrap();
        assert_eq!(
            resolve(root.path(), "city/v2", false).unwrap(),
            root_c.join("city/v2")
        );
        assert_eq!(resolve(root.path(), "", false), Err(SceneRefError::Missing));
        for name in ["../etc", "a/../../b"] {
            assert!(matches!(
                resolve(root.path(), name, false),
                Err(SceneRefError::Escapes(_))
            ));
        }
        let abs = outside.path().to_str().unwrap();
        assert!(matches!(
            resolve(root.path(), abs, false),
            Err(SceneRefError::Absolute(_))
        ));
        assert_eq!(
            resolve(root.path(), abs, true).unwrap(),
            outside.path().canonicalize().unwrap()
        );
        // A symlinked directory or manifest leading outside answers as a missing scene does.
        std::os::unix::fs::symlink(outside.path(), root.path().join("escape")).unwrap();
        std::fs::create_dir(root.path().join("linked")).unwrap();
        std::os::unix::fs::symlink(
            outside.path().join(MANIFEST_FILE),
            root.path().join("linked").join(MANIFEST_FILE),
        )
        .unwrap();
        for name in ["escape", "linked", "nothing-here"] {
            assert_eq!(
                resolve(root.path(), name, false),
                Err(SceneRefError::NotFound(name.into()))
            );
        }
        // A symlink that stays inside is fine.
        std::os::unix::fs::symlink(root.path().join("city"), root.path().join("town")).unwrap();
        assert_eq!(
            resolve(root.path(), "town/v2", false).unwrap(),
            root_c.join("city/v2")
        );
    }
}
