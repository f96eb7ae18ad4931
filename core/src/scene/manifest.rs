//! The scene manifest: camera, lights, materials and the domain table, as TOML.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::partition::{DomainTree, KdNode};
use super::residence::Received;
use super::{DomainData, MANIFEST_FILE, Residence, SceneError, write_atomically};
use crate::geometry::Aabb;

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

/// Most domains a scene may have (`prepare --domains`' limit, checked when a manifest is read).
pub const MAX_DOMAINS: u32 = 1 << 16;

/// Longest file name a domain entry may give (prepare writes 16 to 18 bytes); names are
/// ASCII letters, digits, `.`, `-` and `_`, so TOML writes them unescaped and a domain's text
/// stays within [`MAX_DOMAIN_TEXT_BYTES`].
pub const MAX_FILE_NAME: usize = 32;

/// Longest checksum text: 16 hex digits, a 64-bit hash.
const MAX_CHECKSUM: usize = 16;

/// Longest text TOML writes for an `f32`: `{}` never uses an exponent, so the longest are
/// negative normals near the smallest, `-0.` then 37 zeros and up to 9 significant digits
/// (the 9 digits that round-trip any `f32`); subnormals need no digit past the 45th place
/// (their spacing is 1.4e-45), and numbers from 1 up print at most 39 integer digits and `.0`.
/// Checked by `manifest::tests::no_f32_is_longer_than_its_bound`.
pub const MAX_F32_TEXT: usize = 49;

/// Most text one domain adds to a manifest: its entry (with a volume brick's value range and
/// surfaces file) and its two k-d tree nodes (a leaf, and the split that a tree of n leaves
/// has n - 1 of), every number and name at its longest (`manifest::tests`).
pub const MAX_DOMAIN_TEXT_BYTES: u64 = 896;

/// Room for everything but the domains and the k-d tree: name, camera, sky, materials (prepare
/// writes up to 263), lights, a volume's transfer function (prepare reads up to
/// `transfer::MAX_POINTS` points; `manifest::tests`).
pub const MAX_MANIFEST_HEAD_BYTES: u64 = 2 << 20;

/// Largest manifest read: every manifest prepare can write fits, [`MAX_DOMAINS`] domains at
/// their longest after the longest head (`manifest::tests` checks the sum), and nothing larger
/// is read. 58 MiB; a 65,536-domain scene prepare writes is about 23.4 MB (README "Scenes").
pub const MAX_MANIFEST_BYTES: u64 =
    MAX_MANIFEST_HEAD_BYTES + MAX_DOMAINS as u64 * MAX_DOMAIN_TEXT_BYTES;

/// A TOML error as `line L, column C: what` without any of the text: toml's own message
/// quotes the offending line, and serde's quote values (`invalid type: string "…"`) and
/// unknown keys, which for a file that is no manifest would be its contents.
fn toml_error(text: &str, mut e: toml::de::Error) -> String {
    let at = e.span().map(|span| {
        let before = &text.as_bytes()[..span.start.min(text.len())];
        let line = before.iter().filter(|&&b| b == b'\n').count() + 1;
        let column = before.iter().rev().take_while(|&&b| b != b'\n').count() + 1;
        format!("line {line}, column {column}: ")
    });
    // Without the input, the message says which key it was in rather than quoting the line.
    e.set_input(None);
    let what = e.to_string().trim_end().replace('\n', " ");
    format!("{}{}", at.unwrap_or_default(), redact(&what))
}

/// `message` with every `"quoted"` literal and the name after `unknown field`/`unknown
/// variant` withheld.
fn redact(message: &str) -> String {
    let mut out = String::with_capacity(message.len());
    let mut rest = message;
    while let Some(i) = rest.find('"') {
        out.push_str(&rest[..i]);
        out.push_str("\"…\"");
        rest = match rest[i + 1..].find('"') {
            Some(j) => &rest[i + 1 + j + 1..],
            None => "",
        };
    }
    out.push_str(rest);
    for lead in ["unknown field `", "unknown variant `"] {
        if let Some(i) = out.find(lead) {
            let start = i + lead.len();
            if let Some(len) = out[start..].find('`') {
                out.replace_range(start..start + len, "…");
            }
        }
    }
    out
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

    /// Maps domain `domain` of the scene in `dir` and checks it against this manifest: its id,
    /// its size, its header checksum, its materials; with `verify_checksum` also hashes every
    /// byte. The one way every reader opens a domain.
    pub fn open_domain(
        &self,
        dir: &Path,
        domain: u32,
        verify_checksum: bool,
    ) -> Result<DomainData, SceneError> {
        self.open_domain_as(dir, domain, verify_checksum, None)
    }

    /// [`Manifest::open_domain`], its files held in memory as `residence` says (`None`: as the
    /// process chooses, [`Residence::selected`]).
    pub fn open_domain_as(
        &self,
        dir: &Path,
        domain: u32,
        verify_checksum: bool,
        residence: Option<Residence>,
    ) -> Result<DomainData, SceneError> {
        let entry = self
            .domains
            .get(domain as usize)
            .ok_or_else(|| SceneError::Manifest {
                path: dir.join(MANIFEST_FILE),
                reason: format!("no domain {domain} of {}", self.domains.len()),
            })?;
        let checksum = checksum_value(&entry.checksum);
        let path = dir.join(&entry.file);
        let materials = self.materials.len() as u32;
        let mut data = DomainData::open_as(&path, checksum, verify_checksum, materials, residence)?;
        if let Some(s) = &entry.surfaces {
            let checksum = checksum_value(&s.checksum);
            let file = dir.join(&s.file);
            let surfaces =
                DomainData::open_as(&file, checksum, verify_checksum, materials, residence)?;
            data.attach_surfaces(surfaces)?;
        }
        self.check_domain(entry, domain, path, data)
    }

    /// The domain `domain` from bytes that arrived from a peer (`origin` names it in errors):
    /// its file and, for a brick with surfaces, its surfaces' file, each checked against its
    /// own checksum in the manifest, then against the manifest's entry exactly as
    /// [`Manifest::open_domain`] checks a file from storage. Nothing here trusts the sender.
    pub fn received_domain(
        &self,
        origin: &Path,
        domain: u32,
        file: Received,
        surfaces: Option<Received>,
    ) -> Result<DomainData, SceneError> {
        let entry = self
            .domains
            .get(domain as usize)
            .ok_or_else(|| SceneError::Domain {
                path: origin.into(),
                reason: format!("no domain {domain} of {}", self.domains.len()),
            })?;
        let materials = self.materials.len() as u32;
        let checksum = checksum_value(&entry.checksum);
        let mut data = DomainData::from_received(file, origin, checksum, materials)?;
        match (&entry.surfaces, surfaces) {
            (Some(s), Some(received)) => {
                let checksum = checksum_value(&s.checksum);
                let surfaces = DomainData::from_received(received, origin, checksum, materials)?;
                data.attach_surfaces(surfaces)?;
            }
            (None, None) => {}
            (expected, _) => {
                return Err(SceneError::Domain {
                    path: origin.into(),
                    reason: format!(
                        "sent {} surfaces file where the manifest has {}",
                        if expected.is_some() { "no" } else { "a" },
                        if expected.is_some() { "one" } else { "none" }
                    ),
                });
            }
        }
        self.check_domain(entry, domain, origin.into(), data)
    }

    /// `data` if it is what the manifest's `entry` for `domain` describes.
    fn check_domain(
        &self,
        entry: &DomainEntry,
        domain: u32,
        path: PathBuf,
        data: DomainData,
    ) -> Result<DomainData, SceneError> {
        let mismatch = if data.domain() != domain {
            Some(format!(
                "holds domain {}, the manifest says {domain}",
                data.domain()
            ))
        } else if data.bytes() != entry.bytes {
            Some(format!(
                "is {} bytes, the manifest says {}",
                data.bytes(),
                entry.bytes
            ))
        } else if data.brick().is_some() != self.volume.is_some() {
            Some(match self.volume {
                Some(_) => "is a mesh domain in a volume scene".to_string(),
                None => "is a volume brick in a scene of triangles".to_string(),
            })
        } else if let (Some(b), Some(v)) = (data.brick(), &self.volume)
            && (b.header.volume_dims != v.dims
                || entry.values != Some([b.header.value_min, b.header.value_max]))
        {
            Some("brick's volume dims or value range differ from the manifest's".to_string())
        } else if data.triangle_count() != entry.triangles {
            Some(format!(
                "holds {} triangles, the manifest says {}",
                data.triangle_count(),
                entry.triangles
            ))
        } else {
            None
        };
        match mismatch {
            Some(reason) => Err(SceneError::Domain { path, reason }),
            None => Ok(data),
        }
    }

    /// Maps every domain file once to check it matches this build and the manifest; with
    /// `verify_checksums` also hashes every byte.
    pub fn check_domains(&self, dir: &Path, verify_checksums: bool) -> Result<(), SceneError> {
        for d in 0..self.domains.len() as u32 {
            // Mapped: the check keeps nothing, so a copy into huge pages would be wasted.
            self.open_domain_as(dir, d, verify_checksums, Some(Residence::Mapped))?;
        }
        Ok(())
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

/// A checksum of the domain table as a number (its hex was checked when the manifest was
/// read).
fn checksum_value(hex: &str) -> u64 {
    u64::from_str_radix(hex, 16).unwrap_or_default()
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
