//! A scene from a raw scalar volume: the isosurface at `iso`, by marching cubes, cut into
//! domains like any mesh. The volume is scaled to fit the unit cube.

use std::path::Path;

use glam::Vec3;

use super::{PrepareError, prepare_mesh};
use crate::isosurface::{Grid, march};
use crate::mesh::TriangleMesh;
use crate::scene::Manifest;
use crate::volume::{RawVolume, VoxelType};

/// Extracts the isosurface of the volume in `input` and writes it as a scene to `out`.
#[allow(clippy::too_many_arguments)]
pub fn prepare_volume(
    input: &Path,
    dims: [u32; 3],
    dtype: VoxelType,
    iso: f32,
    name: &str,
    out: &Path,
    domains: u32,
    force: bool,
) -> Result<Manifest, PrepareError> {
    let volume =
        RawVolume::open(input, dims, dtype).map_err(|e| PrepareError::Invalid(e.to_string()))?;
    let longest = dims
        .iter()
        .copied()
        .max()
        .unwrap_or(1)
        .saturating_sub(1)
        .max(1);
    let grid = Grid {
        origin: Vec3::ZERO,
        spacing: Vec3::splat(1.0 / longest as f32),
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
