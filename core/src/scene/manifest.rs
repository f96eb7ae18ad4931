//! The scene manifest: camera, lights, materials and the domain table, as TOML.
//!
//! The types and their checks are here; a module each holds the limits on a manifest's size
//! (`limits`), TOML errors with the text withheld (`redacted`), and opening a domain's files
//! against the manifest's entry (`domains`).

mod domains;
mod limits;
mod redacted;

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::partition::{DomainTree, KdNode};
use super::{MANIFEST_FILE, SceneError, write_atomically};
use crate::geometry::Aabb;
use limits::MAX_CHECKSUM;
use redacted::toml_error;

pub use limits::{
    MAX_DOMAIN_TEXT_BYTES, MAX_DOMAINS, MAX_F32_TEXT, MAX_FILE_NAME, MAX_MANIFEST_BYTES,
    MAX_MANIFEST_HEAD_BYTES,
};

/// Version of the manifest and domain file layout this build reads and writes.
pub const FORMAT_VERSION: u32 = 1;

/// Everything about a scene except its triangles.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// Layout version, [`FORMAT_VERSION`].
    pub format: u32,
    /// A name for people.
    pub name: String,
    /// Box around all geometry; the root of the domain tree.
    pub bounds: Aabb,
    /// Total triangles in the scene (each counted once, however many domains reference it).
    pub triangles: u64,
    /// Offset applied along the surface normal when a ray leaves a surface.
    pub ray_epsilon: f32,
    /// The default view.
    pub camera: Camera,
    /// Light from rays that leave the scene.
    pub sky: Sky,
    /// Materials, indexed by each triangle's material number.
    pub materials: Vec<Material>,
    /// Light sources.
    pub lights: Vec<Light>,
    /// The k-d tree whose leaves are the domains; node 0 is the root.
    pub kd_nodes: Vec<KdNode>,
    /// One entry per domain, in domain-id order.
    pub domains: Vec<DomainEntry>,
    /// A volume scene: how its voxels lie in space and how they are rendered; its domains are
    /// bricks (`scene::brick`). Absent for a scene of triangles.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub volume: Option<VolumeSpec>,
}

/// A volume scene's voxel grid and its direct volume rendering.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VolumeSpec {
    /// Voxels along x, y, z (at least 2 each).
    pub dims: [u32; 3],
    /// Position of voxel (0, 0, 0).
    pub origin: [f32; 3],
    /// Distance between voxel centres along x, y, z.
    pub spacing: [f32; 3],
    /// Distance between samples along a ray.
    pub step: f32,
    /// Shade samples by the volume's gradient and the scene's lights (a headlight if it has
    /// none): `render::volume_light`.
    pub shading: bool,
    /// With shading: shadow rays from each composited segment towards the lights.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub shadows: bool,
    /// Colour map and opacity curve.
    pub transfer: crate::transfer::TransferFunction,
}

impl VolumeSpec {
    /// Checks the grid, step and transfer function.
    pub fn check(&self) -> Result<(), String> {
        if self.dims.iter().any(|&d| d < 2) {
            return Err(format!(
                "volume dims {:?}: at least 2 voxels per axis",
                self.dims
            ));
        }
        if !finite(&self.origin) || !self.spacing.iter().all(|s| s.is_finite() && *s > 0.0) {
            return Err("volume origin must be finite and spacing finite and positive".into());
        }
        let smallest = self.spacing.iter().copied().fold(f32::INFINITY, f32::min);
        if !(self.step.is_finite() && self.step >= smallest * 1e-3) {
            return Err(format!(
                "volume step {} must be finite and at least a thousandth of the spacing",
                self.step
            ));
        }
        if self.shadows && !self.shading {
            return Err("volume shadows need shading".into());
        }
        self.transfer
            .check()
            .map_err(|e| format!("volume transfer function: {e}"))
    }

    /// The smallest voxel spacing: the length the transfer function's opacities are for.
    pub fn voxel_length(&self) -> f32 {
        self.spacing.iter().copied().fold(f32::INFINITY, f32::min)
    }
}

/// A pinhole camera.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    /// Eye position.
    pub eye: [f32; 3],
    /// Point looked at.
    pub look_at: [f32; 3],
    /// Up direction.
    pub up: [f32; 3],
    /// Vertical field of view in degrees.
    pub fov_y_degrees: f32,
}

impl Camera {
    /// Rejects a camera that cannot make an image: non-finite vectors, an eye on the point it
    /// looks at, an up direction that is zero or along the view (the image's orientation
    /// would be arbitrary), or a field of view outside (0, 180) degrees. The one check of
    /// every entry point: scene files, `render`, and jobs on the coordinator.
    pub fn check(&self) -> Result<(), String> {
        if !(finite(&self.eye) && finite(&self.look_at)) {
            return Err("camera eye and look-at must be finite".into());
        }
        check_up(self.up)?;
        check_fov(self.fov_y_degrees)?;
        let view = glam::Vec3::from(self.look_at) - glam::Vec3::from(self.eye);
        if view.length_squared() == 0.0 {
            return Err("camera eye and look-at must be distinct".into());
        }
        let up = glam::Vec3::from(self.up);
        // Up within about half a degree of the view direction leaves no sideways direction.
        if view.normalize().cross(up.normalize()).length() < 1e-2 {
            return Err(format!(
                "camera up {:?} is along the view direction; give an up direction across it",
                self.up
            ));
        }
        Ok(())
    }
}

/// Rejects a vertical field of view outside (0, 180) degrees.
pub fn check_fov(degrees: f32) -> Result<(), String> {
    if degrees > 0.0 && degrees < 180.0 {
        Ok(())
    } else {
        Err(format!(
            "field of view {degrees} is outside (0, 180) degrees"
        ))
    }
}

/// Rejects an up direction that is not finite or is zero.
pub fn check_up(up: [f32; 3]) -> Result<(), String> {
    if !finite(&up) {
        return Err("camera up must be finite".into());
    }
    if up == [0.0; 3] {
        return Err("camera up 0,0,0 has no direction".into());
    }
    Ok(())
}

/// A vertical gradient for rays that escape.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sky {
    /// Radiance looking sideways.
    pub horizon: [f32; 3],
    /// Radiance looking straight up.
    pub zenith: [f32; 3],
}

/// How a surface scatters light.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Material {
    /// Lambertian.
    Diffuse {
        /// Reflectance per channel.
        albedo: [f32; 3],
    },
    /// Perfect mirror.
    Mirror {
        /// Reflectance per channel.
        tint: [f32; 3],
    },
    /// A diffuse base under a rough specular coat.
    Glossy {
        /// Reflectance of the base.
        albedo: [f32; 3],
        /// Probability of the coat reflecting (0..1).
        specular: f32,
        /// Spread of the coat's reflection (0 = mirror).
        roughness: f32,
    },
    /// Lambertian, its reflectance read from a colour map at the height of the point shaded:
    /// its coordinate along `axis`, `range[0]` reading the map's start and `range[1]` its end.
    Mapped {
        /// The colour map.
        map: crate::colour_map::ColourMap,
        /// The axis heights are measured along: 0, 1 or 2 (x, y, z).
        axis: u8,
        /// Heights of the map's two ends (the first below the second).
        range: [f32; 2],
    },
}

/// A light source.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Light {
    /// Light from infinitely far away (a sun).
    Directional {
        /// Direction towards the light.
        direction: [f32; 3],
        /// Irradiance on a surface facing the light.
        radiance: [f32; 3],
    },
    /// A one-sided parallelogram emitter (soft shadows); it emits on the side of `edge_u x edge_v`.
    Quad {
        /// One corner.
        corner: [f32; 3],
        /// First edge from the corner.
        edge_u: [f32; 3],
        /// Second edge from the corner.
        edge_v: [f32; 3],
        /// Emitted radiance.
        emission: [f32; 3],
    },
}

/// One domain as the manifest records it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DomainEntry {
    /// File name inside the scene directory.
    pub file: String,
    /// The domain's box (a leaf of the k-d tree).
    pub bounds: Aabb,
    /// Size of the domain's files in bytes (with its surfaces' file, if any).
    pub bytes: u64,
    /// Triangles referenced by the domain (a brick's: those of its surfaces).
    pub triangles: u64,
    /// xxh3-64 of the file with its checksum field zeroed, as 16 hex digits.
    pub checksum: String,
    /// A volume brick: the range of its voxels' values (with a cell around it), so that a
    /// brick the transfer function makes transparent is skipped without loading it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub values: Option<[f32; 2]>,
    /// A brick of a volume with surfaces in it: the mesh domain file of the triangles in its
    /// box, traced in the same pass as its voxels (`render::kernel`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub surfaces: Option<SurfaceFile>,
}

/// The mesh domain file of a brick's surfaces.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SurfaceFile {
    /// File name inside the scene directory.
    pub file: String,
    /// xxh3-64 of the file with its checksum field zeroed, as 16 hex digits.
    pub checksum: String,
}

impl Manifest {
    /// Reads and checks `DIR/scene.toml`: a regular file of at most [`MAX_MANIFEST_BYTES`],
    /// else refused before reading. Errors name the file and the position, never its text.
    pub fn load(dir: &Path) -> Result<Manifest, SceneError> {
        use std::io::Read;
        let path = dir.join(MANIFEST_FILE);
        let (file, bytes) = super::open_regular(&path, MAX_MANIFEST_BYTES, "manifest")?;
        let mut raw = Vec::with_capacity(bytes as usize);
        // `take`: a file that grows while being read stops at the cap all the same.
        file.take(MAX_MANIFEST_BYTES)
            .read_to_end(&mut raw)
            .map_err(|e| SceneError::io(&path, e))?;
        let text = String::from_utf8(raw).map_err(|e| SceneError::Manifest {
            path: path.clone(),
            reason: format!("not UTF-8 text (byte {})", e.utf8_error().valid_up_to()),
        })?;
        Manifest::parse(&text).map_err(|reason| SceneError::Manifest { path, reason })
    }

    /// Parses and checks manifest text. A syntax or type error gives its line and column and
    /// what was expected, without quoting the text (see [`toml_error`]).
    pub fn parse(text: &str) -> Result<Manifest, String> {
        let m: Manifest = toml::from_str(text).map_err(|e| toml_error(text, e))?;
        m.check()?;
        Ok(m)
    }

    /// Writes `DIR/scene.toml` atomically.
    pub fn save(&self, dir: &Path) -> Result<(), SceneError> {
        let text = toml::to_string_pretty(self).map_err(|e| SceneError::Manifest {
            path: dir.join(MANIFEST_FILE),
            reason: e.to_string(),
        })?;
        write_atomically(&dir.join(MANIFEST_FILE), text.as_bytes())
    }

    /// The domain tree, checked.
    pub fn domain_tree(&self) -> DomainTree {
        DomainTree::new(self.bounds, self.kd_nodes.clone())
    }

    fn check(&self) -> Result<(), String> {
        if self.format != FORMAT_VERSION {
            return Err(format!(
                "format {} is not the supported {FORMAT_VERSION}",
                self.format
            ));
        }
        if self.domains.is_empty() {
            return Err("no domains".into());
        }
        if self.domains.len() > MAX_DOMAINS as usize {
            return Err(format!(
                "{} domains, more than the {MAX_DOMAINS} a scene may have",
                self.domains.len()
            ));
        }
        // A tree of n leaves has n - 1 splits: a longer list holds nodes outside the tree.
        if self.kd_nodes.len() > 2 * self.domains.len() - 1 {
            return Err(format!(
                "{} k-d nodes for {} domains: a tree of n domains has 2n - 1",
                self.kd_nodes.len(),
                self.domains.len()
            ));
        }
        if self.materials.is_empty() {
            return Err("no materials".into());
        }
        if let Some(v) = &self.volume {
            v.check()?;
            if let Some(i) = self.domains.iter().position(|d| {
                !d.values
                    .is_some_and(|[a, b]| a.is_finite() && b.is_finite() && a <= b)
            }) {
                return Err(format!("domain {i}: a brick needs a finite value range"));
            }
        }
        if self.bounds.is_empty() || !finite(&self.bounds.min) || !finite(&self.bounds.max) {
            return Err("bounds are empty or not finite".into());
        }
        if !(self.ray_epsilon.is_finite() && self.ray_epsilon >= 0.0) {
            return Err("ray_epsilon must be a finite non-negative number".into());
        }
        self.camera.check()?;
        if !(finite(&self.sky.horizon) && finite(&self.sky.zenith)) {
            return Err("sky has a non-finite value".into());
        }
        for (i, m) in self.materials.iter().enumerate() {
            let ok = match *m {
                Material::Diffuse { albedo } => finite(&albedo),
                Material::Mirror { tint } => finite(&tint),
                Material::Glossy {
                    albedo,
                    specular,
                    roughness,
                } => finite(&albedo) && specular.is_finite() && roughness.is_finite(),
                Material::Mapped { axis, range, .. } => {
                    let ordered = range.iter().all(|x| x.is_finite()) && range[0] < range[1];
                    if axis > 2 || !ordered {
                        return Err(format!(
                            "material {i}: a colour map needs an axis of 0, 1 or 2 and a range \
                             [low, high] with low below high, not axis {axis} and {range:?}"
                        ));
                    }
                    true
                }
            };
            if !ok {
                return Err(format!("material {i} has a non-finite value"));
            }
        }
        for (i, d) in self.domains.iter().enumerate() {
            let files = std::iter::once((&d.file, &d.checksum))
                .chain(d.surfaces.as_ref().map(|s| (&s.file, &s.checksum)));
            for (file, checksum) in files {
                if !plain_name(file) {
                    return Err(format!(
                        "domain {i}: file name {file:?} must be a plain name of at most \
                         {MAX_FILE_NAME} ASCII letters, digits, '.', '-' or '_'"
                    ));
                }
                if checksum.len() > MAX_CHECKSUM || u64::from_str_radix(checksum, 16).is_err() {
                    return Err(format!(
                        "domain {i}: checksum {checksum:?} is not {MAX_CHECKSUM} hex digits"
                    ));
                }
            }
            if d.surfaces.is_some() && self.volume.is_none() {
                return Err(format!(
                    "domain {i}: only a volume's bricks have surfaces beside them"
                ));
            }
        }
        for (i, l) in self.lights.iter().enumerate() {
            let ok = match l {
                Light::Directional {
                    direction,
                    radiance,
                } => finite(direction) && finite(radiance),
                Light::Quad {
                    corner,
                    edge_u,
                    edge_v,
                    emission,
                } => finite(corner) && finite(edge_u) && finite(edge_v) && finite(emission),
            };
            if !ok {
                return Err(format!("light {i} has a non-finite value"));
            }
        }
        DomainTree::check(&self.kd_nodes, self.domains.len())
    }
}

/// A file name in the scene directory: short, no path, nothing TOML must escape.
fn plain_name(file: &str) -> bool {
    !file.is_empty()
        && file.len() <= MAX_FILE_NAME
        && !file.contains("..")
        && file
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'-' | b'_'))
}

fn finite(v: &[f32; 3]) -> bool {
    v.iter().all(|x| x.is_finite())
}

#[cfg(test)]
#[path = "manifest_tests.rs"]
mod tests;
