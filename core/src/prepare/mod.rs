//! `rayfarm prepare`: turn a mesh, a volume or the built-in generator into a scene directory.
//! A scene is staged in a sibling directory and renamed into place only when complete, so a
//! failed or interrupted prepare never leaves a half-written scene behind.

pub mod brick_scene;
pub mod generate;
pub mod mesh_scene;
pub mod scalar_colour;
pub mod volume_scene;

use std::path::{Path, PathBuf};

use tracing::{info, info_span};

use crate::geometry::Aabb;
use crate::scene::domain_file::SourceTriangle;
use crate::scene::manifest::FORMAT_VERSION;
use crate::scene::{
    Camera, DomainEntry, DomainTree, Light, MANIFEST_FILE, Manifest, Material, SceneError, Sky,
    write_domain,
};

pub use mesh_scene::prepare_mesh;

/// Why preparing a scene failed.
#[derive(Debug, thiserror::Error)]
pub enum PrepareError {
    /// The input mesh could not be read.
    #[error(transparent)]
    Mesh(#[from] crate::mesh::MeshError),
    /// Writing the scene failed.
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// The output exists and `--force` was not given.
    #[error("{0}: already exists (pass --force to replace it)")]
    Exists(PathBuf),
    /// The input or the options cannot make a scene.
    #[error("{0}")]
    Invalid(String),
}

/// Everything about a scene except its triangles.
pub struct SceneSpec {
    /// A name for people.
    pub name: String,
    /// The domain tree (its root box is the scene's bounds).
    pub tree: DomainTree,
    /// Default view.
    pub camera: Camera,
    /// Sky.
    pub sky: Sky,
    /// Materials.
    pub materials: Vec<Material>,
    /// Lights.
    pub lights: Vec<Light>,
}

/// The triangles of one domain, and how many of them it owns (holds their centroid), so
/// that triangles referenced by several domains are counted once.
pub struct DomainTriangles {
    /// Every triangle that may be hit inside the domain.
    pub triangles: Vec<SourceTriangle>,
    /// How many of them have their centroid in this domain.
    pub owned: u64,
}

impl DomainTriangles {
    /// Counts the owned triangles of `triangles` for domain `domain` of `tree`.
    pub fn new(tree: &DomainTree, domain: u32, triangles: Vec<SourceTriangle>) -> Self {
        let owned = triangles
            .iter()
            .filter(|t| tree.domain_at(Aabb::of_triangle(&t.vertices).center()) == domain)
            .count() as u64;
        DomainTriangles { triangles, owned }
    }
}

/// Margin by which a triangle's box is grown before testing which domains it overlaps:
/// larger than any rounding in the hit point, far smaller than any domain.
pub fn reference_margin(bounds: &Aabb) -> f32 {
    bounds.diagonal() * 1e-5
}

/// Writes the scene to `out`: each domain's triangles come from `domain_triangles(id, box)`,
/// one domain at a time, so memory stays near one domain's size.
pub fn write_scene(
    out: &Path,
    spec: SceneSpec,
    force: bool,
    mut domain_triangles: impl FnMut(u32, &Aabb) -> Result<DomainTriangles, PrepareError>,
) -> Result<Manifest, PrepareError> {
    if out.exists() && !force {
        return Err(PrepareError::Exists(out.into()));
    }
    publish_staged(out, "scene", |staging| {
        let count = spec.tree.nodes().len().div_ceil(2);
        let boxes = spec.tree.domain_boxes(count);
        let mut domains = Vec::with_capacity(count);
        let mut triangles = 0;
        for (id, b) in boxes.iter().enumerate() {
            let _span = info_span!("write_domain", domain = id).entered();
            let tris = domain_triangles(id as u32, b)?;
            triangles += tris.owned;
            let file = format!("domain-{id:05}.rfd");
            let summary = write_domain(&staging.join(&file), id as u32, *b, &tris.triangles)?;
            info!(
                triangles = summary.triangles,
                bytes = summary.bytes,
                "domain written"
            );
            domains.push(DomainEntry {
                file,
                bounds: *b,
                bytes: summary.bytes,
                triangles: summary.triangles,
                checksum: format!("{:016x}", summary.checksum),
                values: None,
                surfaces: None,
            });
        }
        let bounds = spec.tree.bounds();
        let manifest = Manifest {
            format: FORMAT_VERSION,
            name: spec.name,
            bounds,
            triangles,
            ray_epsilon: bounds.diagonal() * 1e-5,
            camera: spec.camera,
            sky: spec.sky,
            materials: spec.materials,
            lights: spec.lights,
            kd_nodes: spec.tree.nodes().to_vec(),
            domains,
            volume: None,
        };
        manifest.save(staging)?;
        // Re-read what was written: a scene that does not load is not a scene.
        Manifest::load(staging)?;
        Ok(manifest)
    })
}

/// Writes a scene into a staging directory beside `out` with `write`, then puts it in place of
/// `out` whole; on an error the staging directory goes and `out` is untouched, so a scene is
/// never seen half written, whatever its kind (`kind` names it in the log).
pub(crate) fn publish_staged(
    out: &Path,
    kind: &str,
    write: impl FnOnce(&Path) -> Result<Manifest, PrepareError>,
) -> Result<Manifest, PrepareError> {
    remove_abandoned_staging(out);
    let staging = staging_dir(out);
    if staging.exists() {
        std::fs::remove_dir_all(&staging).map_err(|e| SceneError::io(&staging, e))?;
    }
    std::fs::create_dir_all(&staging).map_err(|e| SceneError::io(&staging, e))?;
    match write(&staging) {
        Ok(manifest) => {
            if out.exists() {
                std::fs::remove_dir_all(out).map_err(|e| SceneError::io(out, e))?;
            }
            std::fs::rename(&staging, out).map_err(|e| SceneError::io(out, e))?;
            info!(dir = %out.display(), manifest = MANIFEST_FILE, kind, "scene ready");
            Ok(manifest)
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(&staging);
            Err(e)
        }
    }
}

/// Removes the staging directories of earlier prepares of `out` whose process is gone (one
/// killed mid-write leaves `.NAME.staging-PID` behind; nothing else would ever remove it).
/// Only real directories named exactly so are touched, never through a symlink, and never one
/// whose process still runs (a concurrent prepare of the same scene); where the running
/// processes cannot be told (no `/proc`), nothing is removed. A failure is logged, not fatal:
/// the new scene does not depend on it.
fn remove_abandoned_staging(out: &Path) {
    let (Some(parent), Some(name)) = (out.parent(), out.file_name()) else {
        return;
    };
    let parent = if parent.as_os_str().is_empty() {
        Path::new(".")
    } else {
        parent
    };
    if !Path::new("/proc/self").is_dir() {
        return;
    }
    let mut prefix = std::ffi::OsString::from(".");
    prefix.push(name);
    prefix.push(".staging-");
    let Some(prefix) = prefix.to_str() else {
        return;
    };
    let Ok(entries) = std::fs::read_dir(parent) else {
        return;
    };
    for entry in entries.flatten() {
        let file_name = entry.file_name();
        let Some(pid) = file_name
            .to_str()
            .and_then(|n| n.strip_prefix(prefix))
            .filter(|pid| !pid.is_empty() && pid.bytes().all(|b| b.is_ascii_digit()))
        else {
            continue;
        };
        let is_dir = entry.file_type().is_ok_and(|t| t.is_dir());
        if !is_dir || Path::new("/proc").join(pid).exists() {
            continue;
        }
        let path = entry.path();
        match std::fs::remove_dir_all(&path) {
            Ok(()) => {
                info!(dir = %path.display(), "removed an interrupted prepare's staging directory")
            }
            Err(e) => {
                tracing::warn!(dir = %path.display(), error = %e, "could not remove an interrupted prepare's staging directory")
            }
        }
    }
}

pub(crate) fn staging_dir(out: &Path) -> PathBuf {
    let mut name = std::ffi::OsString::from(".");
    name.push(out.file_name().unwrap_or_default());
    name.push(format!(".staging-{}", std::process::id()));
    out.with_file_name(name)
}

/// A view, a sky and lights that show a scene with these bounds: the camera looks at the
/// center from the front and above, a sun and a soft area light above.
pub fn default_lighting(bounds: &Aabb) -> (Camera, Sky, Vec<Light>) {
    let c = glam::Vec3::from(bounds.center());
    let r = (bounds.diagonal() * 0.5).max(1e-3);
    let eye = c + glam::Vec3::new(0.35, 0.45, 1.0).normalize() * r * 2.6;
    let camera = Camera {
        eye: eye.into(),
        look_at: c.into(),
        up: [0.0, 1.0, 0.0],
        fov_y_degrees: 40.0,
    };
    let sky = Sky {
        horizon: [0.55, 0.6, 0.7],
        zenith: [0.15, 0.25, 0.5],
    };
    let s = r * 0.8;
    let top = c + glam::Vec3::new(-0.3 * r, 1.6 * r, 0.3 * r);
    let lights = vec![
        Light::Directional {
            direction: [0.4, 0.8, 0.45],
            radiance: [1.1, 1.0, 0.85],
        },
        Light::Quad {
            corner: (top - glam::Vec3::new(s, 0.0, s) * 0.5).into(),
            edge_u: [s, 0.0, 0.0],
            edge_v: [0.0, 0.0, s],
            emission: [4.0, 3.8, 3.5],
        },
    ];
    (camera, sky, lights)
}
