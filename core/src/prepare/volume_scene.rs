//! A scene from a raw scalar volume: the isosurface at `iso`, by marching cubes, cut into
//! domains like any mesh, with the volume's voxel spacing and scaled so its longest side is 1;
//! or (`prepare_raw_bricks`) the volume itself cut into bricks for direct volume rendering.

use std::path::{Path, PathBuf};

use glam::Vec3;

use super::PrepareError;
use super::mesh_scene::{SurfaceLook, prepare_triangles};
use super::scalar_colour;
use crate::colour_map::ColourMap;
use crate::isosurface::{GradientMagnitude, Grid, IsoTriangle, march, march_smooth};
use crate::scene::{Manifest, Material};

use super::brick_scene::{BrickOptions, VolumeLook, prepare_bricks};
use crate::volume::{RawVolume, VoxelType};

/// How an isosurface is shaded and coloured.
#[derive(Clone, Debug, PartialEq)]
pub struct IsoLook {
    /// Shade with the volume's gradient at the vertices (`isosurface::march_smooth`), not the
    /// facets' normals.
    pub smooth: bool,
    /// Colour with this map by what `colour_by` says, instead of one plain colour.
    pub colour_map: Option<ColourMap>,
    /// What picks a point's colour from the map.
    pub colour_by: ColourBy,
}

/// What picks an isosurface's colour from its colour map.
#[derive(Clone, Debug, PartialEq)]
pub enum ColourBy {
    /// The height of the point shaded along `axis` (0, 1 or 2), over the surface's extent
    /// along it (`Material::Mapped`, read where a ray hits).
    Height {
        /// The axis heights run along.
        axis: u8,
    },
    /// The volume's gradient magnitude at the vertices (`isosurface::GradientMagnitude`): how
    /// sharp the boundary is there; a lookup table entry per triangle (`scalar_colour`).
    Gradient,
    /// The value at the vertices of a second raw volume in this file, of the same dimensions
    /// and voxel type (a temperature on a density's surface, say); a lookup table entry per
    /// triangle (`scalar_colour`).
    Volume(PathBuf),
}

impl Default for IsoLook {
    /// Smooth, plain colour, heights along z (a CT's slices).
    fn default() -> Self {
        IsoLook {
            smooth: true,
            colour_map: None,
            colour_by: ColourBy::Height { axis: 2 },
        }
    }
}

/// A plain surface's colour.
const PLAIN: Material = Material::Diffuse {
    albedo: [0.75, 0.72, 0.68],
};

/// The materials of the isosurface `tris` of `volume` (placed by `grid`) as `look` colours
/// it, and each triangle's material when they differ (a lookup table's entries).
fn materials(
    look: &IsoLook,
    tris: &[[[f32; 3]; 3]],
    volume: &RawVolume,
    grid: &Grid,
    dtype: VoxelType,
) -> Result<(Vec<Material>, Option<Vec<u32>>), PrepareError> {
    let Some(map) = look.colour_map else {
        return Ok((vec![PLAIN], None));
    };
    let (entries, range) = match &look.colour_by {
        ColourBy::Height { axis } => {
            let axis = (*axis).min(2);
            let (low, high) = tris
                .iter()
                .flatten()
                .fold((f32::MAX, f32::MIN), |(lo, hi), v| {
                    (lo.min(v[usize::from(axis)]), hi.max(v[usize::from(axis)]))
                });
            let range = if low < high {
                [low, high]
            } else {
                [low, low + 1.0]
            };
            return Ok((vec![Material::Mapped { map, axis, range }], None));
        }
        ColourBy::Gradient => {
            let gradient = GradientMagnitude {
                grid,
                lattice: volume,
            };
            scalar_colour::entries(tris, |v| grid.interpolate(&gradient, Vec3::from(v)))
        }
        ColourBy::Volume(path) => {
            let second = RawVolume::open(path, grid.dims, dtype)
                .map_err(|e| PrepareError::Invalid(e.to_string()))?;
            scalar_colour::entries(tris, |v| grid.interpolate(&second, Vec3::from(v)))
        }
    };
    tracing::info!(low = range[0], high = range[1], "colour map range");
    Ok((scalar_colour::lookup_table(map), Some(entries)))
}

/// Extracts the isosurface of the volume in `input` (voxels `spacing` apart) and writes it as
/// a scene to `out`, shaded and coloured as `look` says.
#[allow(clippy::too_many_arguments)]
pub fn prepare_volume(
    input: &Path,
    dims: [u32; 3],
    dtype: VoxelType,
    spacing: [f32; 3],
    iso: f32,
    look: IsoLook,
    name: &str,
    out: &Path,
    domains: u32,
    force: bool,
) -> Result<Manifest, PrepareError> {
    let volume =
        RawVolume::open(input, dims, dtype).map_err(|e| PrepareError::Invalid(e.to_string()))?;
    check_spacing(input, spacing)?;
    // Physical extent per axis; scaled so the longest is 1, keeping the proportions.
    let extent: [f32; 3] = std::array::from_fn(|a| spacing[a] * dims[a].saturating_sub(1) as f32);
    let longest = extent.iter().copied().fold(0.0f32, f32::max);
    let scale = if longest > 0.0 { 1.0 / longest } else { 1.0 };
    let grid = Grid {
        origin: Vec3::ZERO,
        spacing: Vec3::from(spacing) * scale,
        dims,
    };
    let mut tris = Vec::new();
    let mut normals = Vec::new();
    let emit = |t: IsoTriangle| {
        tris.push(t.vertices);
        if let Some(n) = t.normals {
            normals.push(n);
        }
    };
    if look.smooth {
        march_smooth(&grid, &volume, iso, grid.all_cells(), emit);
    } else {
        march(&grid, &volume, iso, grid.all_cells(), emit);
    }
    if tris.is_empty() {
        return Err(PrepareError::Invalid(format!(
            "{}: no surface at iso {iso} (every voxel is on one side)",
            input.display()
        )));
    }
    let (materials, material_of) = materials(&look, &tris, &volume, &grid, dtype)?;
    let surface = SurfaceLook {
        materials,
        material_of: material_of.as_deref(),
        normals: look.smooth.then_some(normals.as_slice()),
    };
    prepare_triangles(&tris, surface, name, out, domains, force)
}

fn check_spacing(input: &Path, spacing: [f32; 3]) -> Result<(), PrepareError> {
    if spacing.iter().all(|s| s.is_finite() && *s > 0.0) {
        Ok(())
    } else {
        Err(PrepareError::Invalid(format!(
            "{}: --spacing {spacing:?} must be finite and positive",
            input.display()
        )))
    }
}

/// Cuts the raw volume in `input` (voxels `spacing` apart, voxel 0 at the origin) into
/// `bricks` bricks for direct volume rendering looking as `look` says, writing the scene to `out`.
/// The file is mapped, so only the brick being written is read; a non-finite value is
/// refused naming the file and the voxel.
#[allow(clippy::too_many_arguments)]
pub fn prepare_raw_bricks(
    input: &Path,
    dims: [u32; 3],
    dtype: VoxelType,
    spacing: [f32; 3],
    look: VolumeLook,
    step: Option<f32>,
    name: &str,
    out: &Path,
    bricks: u32,
    force: bool,
) -> Result<Manifest, PrepareError> {
    let volume =
        RawVolume::open(input, dims, dtype).map_err(|e| PrepareError::Invalid(e.to_string()))?;
    check_spacing(input, spacing)?;
    if dims.iter().any(|&d| d < 2) {
        return Err(PrepareError::Invalid(format!(
            "{}: --dims {dims:?} needs at least 2 voxels per axis for a volume",
            input.display()
        )));
    }
    prepare_bricks(
        out,
        &volume,
        &BrickOptions {
            name: name.into(),
            source: input.display().to_string(),
            dims,
            origin: [0.0; 3],
            spacing,
            bricks,
            step,
            look,
            force,
        },
    )
}
