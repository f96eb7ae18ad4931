//! A scene from a raw scalar volume: the isosurface at `iso`, by marching cubes, cut into
//! domains like any mesh, with the volume's voxel spacing and scaled so its longest side is 1;
//! or (`prepare_raw_bricks`) the volume itself cut into bricks for direct volume rendering.

use std::path::Path;

use glam::Vec3;

use super::{PrepareError, prepare_mesh};
use crate::isosurface::{Grid, march};
use crate::mesh::TriangleMesh;
use crate::scene::Manifest;

use super::brick_scene::{BrickOptions, VolumeLook, prepare_bricks};
use crate::volume::{RawVolume, VoxelType};

/// Extracts the isosurface of the volume in `input` (voxels `spacing` apart) and writes it as
/// a scene to `out`.
#[allow(clippy::too_many_arguments)]
pub fn prepare_volume(
    input: &Path,
    dims: [u32; 3],
    dtype: VoxelType,
    spacing: [f32; 3],
    iso: f32,
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
    let mut mesh = TriangleMesh::default();
    march(&grid, &volume, iso, grid.all_cells(), |t| {
        let base = mesh.positions.len() as u32;
        mesh.positions.extend_from_slice(&t.vertices);
        mesh.triangles.push([base, base + 1, base + 2]);
    });
    if mesh.triangles.is_empty() {
        return Err(PrepareError::Invalid(format!(
            "{}: no surface at iso {iso} (every voxel is on one side)",
            input.display()
        )));
    }
    prepare_mesh(&mesh, name, out, domains, force)
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
