//! A scene from a raw scalar volume: the isosurface at `iso`, by marching cubes, cut into
//! domains like any mesh, with the volume's voxel spacing and scaled so its longest side is 1;
//! or (`prepare_raw_bricks`) the volume itself cut into bricks for direct volume rendering.

use std::path::Path;

use glam::Vec3;

use super::PrepareError;
use super::mesh_scene::{SurfaceLook, prepare_triangles};
use crate::colour_map::ColourMap;
use crate::isosurface::{Grid, IsoTriangle, march, march_smooth};
use crate::scene::{Manifest, Material};

use super::brick_scene::{BrickOptions, VolumeLook, prepare_bricks};
use crate::volume::{RawVolume, VoxelType};

/// How an isosurface is shaded and coloured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IsoLook {
    /// Shade with the volume's gradient at the vertices (`isosurface::march_smooth`), not the
    /// facets' normals.
    pub smooth: bool,
    /// Colour by height with this map along `colour_axis` (over the surface's extent along
    /// it), instead of one plain colour.
    pub colour_map: Option<ColourMap>,
    /// The axis heights are measured along: 0, 1 or 2.
    pub colour_axis: u8,
}

impl Default for IsoLook {
    /// Smooth, plain colour, heights along z (a CT's slices).
    fn default() -> Self {
        IsoLook {
            smooth: true,
            colour_map: None,
            colour_axis: 2,
        }
    }
}

impl IsoLook {
    /// The material of a surface whose extent along the colour axis is `low..high`.
    pub fn material(&self, low: f32, high: f32) -> Material {
        match self.colour_map {
            Some(map) => Material::Mapped {
                map,
                axis: self.colour_axis.min(2),
                range: if low < high {
                    [low, high]
                } else {
                    [low, low + 1.0]
                },
            },
            None => Material::Diffuse {
                albedo: [0.75, 0.72, 0.68],
            },
        }
    }
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
    let axis = usize::from(look.colour_axis.min(2));
    let (low, high) = tris
        .iter()
        .flatten()
        .fold((f32::MAX, f32::MIN), |(lo, hi), v| {
            (lo.min(v[axis]), hi.max(v[axis]))
        });
    let surface = SurfaceLook {
        material: look.material(low, high),
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
