//! Scenes are named relative to a scene root that every node is configured with, so one job
//! works whatever the mount point on each node; an absolute path works where all nodes see
//! the same path.

use std::path::{Component, Path, PathBuf};

/// Why a scene name cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SceneRefError {
    /// The job named no scene and no default is configured.
    #[error("the job names no scene and the coordinator has no default scene (--default-scene)")]
    Missing,
    /// A relative name that climbs out of the scene root.
    #[error("scene name {0:?} must stay inside the scene root (no `..`)")]
    Escapes(String),
}

/// The directory of `scene` on a node whose scene root is `root`.
pub fn resolve(root: &Path, scene: &str) -> Result<PathBuf, SceneRefError> {
    if scene.is_empty() {
        return Err(SceneRefError::Missing);
    }
    let path = Path::new(scene);
    if path.is_absolute() {
        return Ok(path.to_path_buf());
    }
    if path
        .components()
        .any(|c| !matches!(c, Component::Normal(_) | Component::CurDir))
    {
        return Err(SceneRefError::Escapes(scene.to_string()));
    }
    Ok(root.join(path))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_resolve_under_the_root_and_absolute_paths_stay() {
        let root = Path::new("/mnt/scenes");
        assert_eq!(
            resolve(root, "city/v2").unwrap(),
            PathBuf::from("/mnt/scenes/city/v2")
        );
        assert_eq!(resolve(root, "/data/x").unwrap(), PathBuf::from("/data/x"));
        assert_eq!(resolve(root, ""), Err(SceneRefError::Missing));
        assert!(matches!(
            resolve(root, "../etc"),
            Err(SceneRefError::Escapes(_))
        ));
        assert!(matches!(
            resolve(root, "a/../../b"),
            Err(SceneRefError::Escapes(_))
        ));
    }
}
