//! A volume scene for direct volume rendering: a scalar volume cut into bricks (`crate::scene::brick`),
//! one domain each, written one brick at a time so the volume is never all in memory (a raw
//! file is mapped and only the brick being written is read).
//!
//! Voxel `(i, j, k)` sits at `origin + (i, j, k) * spacing` (the formula of
//! `isosurface::Grid::point`); the bricks are the leaves of a k-d tree whose planes lie on
//! voxel planes, each brick owning the cells between its planes.

use std::path::Path;

use glam::Vec3;
use tracing::{info, info_span};

use super::{DomainTriangles, PrepareError, default_lighting, publish_staged, reference_margin};
use crate::geometry::Aabb;
use crate::isosurface::{Grid, Lattice, march_smooth};
use crate::scene::brick::{BLOCK, write_brick};
use crate::scene::domain_file::SourceTriangle;
use crate::scene::manifest::FORMAT_VERSION;
use crate::scene::{
    DomainEntry, DomainTree, KdNode, Manifest, Material, SceneError, SurfaceFile, VolumeSpec,
    write_domain,
};
use crate::transfer::TransferFunction;

/// Most bricks a volume is cut into.
pub const MAX_BRICKS: u32 = 65_536;

/// How to cut and render a volume.
#[derive(Clone, Debug)]
pub struct BrickOptions {
    /// Scene name.
    pub name: String,
    /// What the volume's values are read from, for errors ("skull.raw", "the generator").
    pub source: String,
    /// Voxels along x, y, z.
    pub dims: [u32; 3],
    /// Position of voxel (0, 0, 0).
    pub origin: [f32; 3],
    /// Distance between voxel centres along x, y, z.
    pub spacing: [f32; 3],
    /// Bricks to cut the volume into.
    pub bricks: u32,
    /// Distance between samples along a ray (default: half the smallest spacing).
    pub step: Option<f32>,
    /// How the volume is rendered.
    pub look: VolumeLook,
    /// Replace an existing scene.
    pub force: bool,
}

/// How a volume scene is rendered: its transfer function and lighting (`render::dvr`,
/// `render::volume_light`).
#[derive(Clone, Debug)]
pub struct VolumeLook {
    /// Colour map and opacity curve.
    pub transfer: TransferFunction,
    /// Shade samples by the volume's gradient and the scene's lights.
    pub shading: bool,
    /// With shading: shadow rays towards the lights.
    pub shadows: bool,
    /// Surfaces in the volume: its isosurface at this value (by marching cubes, in the
    /// volume's own coordinates), traced with its voxels; compositing stops where a ray meets
    /// it and the surface is shaded behind the volume in front of it.
    pub iso_surface: Option<f32>,
}

impl VolumeLook {
    /// `transfer`, unlit.
    pub fn unlit(transfer: TransferFunction) -> Self {
        VolumeLook {
            transfer,
            shading: false,
            shadows: false,
            iso_surface: None,
        }
    }
}

/// A box of voxel cells: `[start, end)` per axis.
type VoxelBox = [[u32; 2]; 3];

/// The cell boxes of the bricks, by domain id, and the k-d tree over them (planes in world
/// coordinates on voxel planes). Splits the longest axis (in sub-blocks, then cells) of each
/// box into shares of the brick count, so 8 bricks of a cube are its octants.
///
/// Every plane lies on a multiple of [`BLOCK`] cells: bricks are unions of the volume's global
/// 8-cell blocks, whose faces cut a ray into the segments it is composited by
/// (`render::dvr`), so a brick boundary never splits a segment and the brick count changes
/// no bit of the image, traced one brick after another or speculatively.
fn cut(o: &BrickOptions, grid: &Grid) -> Result<(Vec<VoxelBox>, Vec<KdNode>), String> {
    fn split(
        grid: &Grid,
        cells: VoxelBox,
        leaves: u32,
        nodes: &mut Vec<KdNode>,
        boxes: &mut Vec<VoxelBox>,
    ) -> Result<u32, String> {
        let me = nodes.len() as u32;
        if leaves == 1 {
            nodes.push(KdNode::Leaf {
                domain: boxes.len() as u32,
            });
            boxes.push(cells);
            return Ok(me);
        }
        let len = |a: usize| cells[a][1] - cells[a][0];
        // A box starts on a block plane (the volume's start, or a cut).
        let blocks = |a: usize| len(a).div_ceil(BLOCK);
        let axis = (0..3)
            .max_by_key(|&a| (blocks(a), len(a), 2 - a))
            .unwrap_or(0);
        let below_leaves = leaves / 2;
        if blocks(axis) < 2 {
            return Err("more bricks than blocks".into());
        }
        let share = u64::from(blocks(axis)) * u64::from(below_leaves) / u64::from(leaves);
        let cut = cells[axis][0] + (share as u32).clamp(1, blocks(axis) - 1) * BLOCK;
        let position = grid.point(cut, cut, cut)[axis];
        nodes.push(KdNode::Leaf { domain: u32::MAX });
        let (mut lo, mut hi) = (cells, cells);
        lo[axis][1] = cut;
        hi[axis][0] = cut;
        let below = split(grid, lo, below_leaves, nodes, boxes)?;
        let above = split(grid, hi, leaves - below_leaves, nodes, boxes)?;
        nodes[me as usize] = KdNode::Split {
            axis: axis as u8,
            position,
            below,
            above,
        };
        Ok(me)
    }
    let all = o.dims.map(|d| [0, d - 1]);
    let mut nodes = Vec::new();
    let mut boxes = Vec::new();
    split(grid, all, o.bricks, &mut nodes, &mut boxes).map_err(|_| {
        format!(
            "{}: {} bricks do not fit {:?} voxels (bricks are cut on {BLOCK}-cell blocks)",
            o.source, o.bricks, o.dims
        )
    })?;
    Ok((boxes, nodes))
}

/// Checks the options and returns the volume's grid and rendering spec.
fn spec_of(o: &BrickOptions) -> Result<(Grid, VolumeSpec), PrepareError> {
    let invalid = PrepareError::Invalid;
    if !(1..=MAX_BRICKS).contains(&o.bricks) {
        return Err(invalid(format!(
            "--bricks {} is outside 1..={MAX_BRICKS}",
            o.bricks
        )));
    }
    let smallest = o.spacing.iter().copied().fold(f32::INFINITY, f32::min);
    let spec = VolumeSpec {
        dims: o.dims,
        origin: o.origin,
        spacing: o.spacing,
        step: o.step.unwrap_or(smallest * 0.5),
        shading: o.look.shading,
        shadows: o.look.shadows,
        transfer: o.look.transfer.clone(),
    };
    spec.check()
        .map_err(|e| invalid(format!("{}: {e}", o.source)))?;
    let grid = Grid {
        origin: Vec3::from(o.origin),
        spacing: Vec3::from(o.spacing),
        dims: o.dims,
    };
    Ok((grid, spec))
}

/// The triangles of `volume`'s isosurface at `iso`, with smooth normals from the volume's
/// gradient (`isosurface::march_smooth`), that brick `domain` (box `b`) of `tree` references: those of the cells around it whose box, grown by the reference margin,
/// overlaps it, as a mesh scene's domain references the triangles crossing into it. Marching
/// cubes gives a triangle the same bits and id whichever cells are marched, so a triangle
/// two bricks share is the same triangle in both.
fn surfaces_in(
    grid: &Grid,
    volume: &impl Lattice,
    iso: f32,
    tree: &DomainTree,
    domain: u32,
    b: &Aabb,
) -> DomainTriangles {
    let grown = b.expanded(reference_margin(&tree.bounds()));
    let mut tris = Vec::new();
    march_smooth(grid, volume, iso, grid.cells_touching(&grown), |t| {
        if Aabb::of_triangle(&t.vertices).overlaps(&grown) {
            tris.push(SourceTriangle {
                vertices: t.vertices,
                id: t.id,
                material: 0,
                normals: t.normals,
            });
        }
    });
    DomainTriangles::new(tree, domain, tris)
}

/// Cuts `volume` into bricks and writes the scene to `out`, one brick at a time.
pub fn prepare_bricks(
    out: &Path,
    volume: &impl Lattice,
    o: &BrickOptions,
) -> Result<Manifest, PrepareError> {
    if out.exists() && !o.force {
        return Err(PrepareError::Exists(out.into()));
    }
    let (grid, spec) = spec_of(o)?;
    let (cells, kd_nodes) = cut(o, &grid).map_err(PrepareError::Invalid)?;
    let bounds = Aabb {
        min: grid.point(0, 0, 0).into(),
        max: grid
            .point(o.dims[0] - 1, o.dims[1] - 1, o.dims[2] - 1)
            .into(),
    };
    let tree = DomainTree::new(bounds, kd_nodes.clone());
    publish_staged(out, "volume", |staging| {
        let mut domains = Vec::with_capacity(cells.len());
        let mut triangles = 0;
        for (id, c) in cells.iter().enumerate() {
            let _span = info_span!("write_brick", domain = id).entered();
            let file = format!("brick-{id:05}.rfb");
            let lo = c.map(|a| a[0]);
            let hi = c.map(|a| a[1]);
            let summary = write_brick(&staging.join(&file), id as u32, volume, o.dims, lo, hi)
                .map_err(|e| match e {
                    // The brick writer names the voxel; the user's file is the one to name.
                    SceneError::Domain { reason, .. } => {
                        PrepareError::Invalid(format!("{}: {reason}", o.source))
                    }
                    e => e.into(),
                })?;
            info!(bytes = summary.bytes, "brick written");
            let brick_box = Aabb {
                min: grid.point(lo[0], lo[1], lo[2]).into(),
                max: grid.point(hi[0], hi[1], hi[2]).into(),
            };
            let mut entry = DomainEntry {
                file,
                bounds: brick_box,
                bytes: summary.bytes,
                triangles: 0,
                checksum: format!("{:016x}", summary.checksum),
                values: Some(summary.values),
                surfaces: None,
            };
            if let Some(iso) = o.look.iso_surface {
                let tris = surfaces_in(&grid, volume, iso, &tree, id as u32, &brick_box);
                if !tris.triangles.is_empty() {
                    let file = format!("surface-{id:05}.rfd");
                    let s =
                        write_domain(&staging.join(&file), id as u32, brick_box, &tris.triangles)?;
                    info!(
                        triangles = s.triangles,
                        bytes = s.bytes,
                        "brick's surfaces written"
                    );
                    triangles += tris.owned;
                    entry.bytes += s.bytes;
                    entry.triangles = s.triangles;
                    entry.surfaces = Some(SurfaceFile {
                        file,
                        checksum: format!("{:016x}", s.checksum),
                    });
                }
            }
            domains.push(entry);
        }
        if o.look.iso_surface.is_some() && triangles == 0 {
            return Err(PrepareError::Invalid(format!(
                "{}: no surface at iso {} (every voxel is on one side)",
                o.source,
                o.look.iso_surface.unwrap_or_default()
            )));
        }
        // A black sky: the volume's colour is what the image shows.
        let (camera, _, lights) = default_lighting(&bounds);
        let manifest = Manifest {
            format: FORMAT_VERSION,
            name: o.name.clone(),
            bounds,
            triangles,
            ray_epsilon: bounds.diagonal() * 1e-5,
            camera,
            sky: crate::scene::Sky {
                horizon: [0.0; 3],
                zenith: [0.0; 3],
            },
            materials: vec![Material::Diffuse { albedo: [0.7; 3] }],
            lights,
            kd_nodes,
            domains,
            volume: Some(spec),
        };
        DomainTree::check(&manifest.kd_nodes, manifest.domains.len())
            .map_err(PrepareError::Invalid)?;
        manifest.save(staging)?;
        // Re-read what was written: a scene that does not load is not a scene.
        Manifest::load(staging)?.check_domains(staging, true)?;
        Ok(manifest)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Ramp;
    impl Lattice for Ramp {
        fn value(&self, i: u32, j: u32, k: u32) -> f32 {
            (i + j + k) as f32 * 0.1
        }
    }

    fn options(bricks: u32) -> BrickOptions {
        BrickOptions {
            name: "ramp".into(),
            source: "ramp".into(),
            dims: [41, 33, 48],
            origin: [0.0; 3],
            spacing: [1.0, 1.0, 2.0],
            bricks,
            step: None,
            look: VolumeLook::unlit(TransferFunction::preset("density").unwrap()),
            force: false,
        }
    }

    #[test]
    fn bricks_tile_the_cells_on_voxel_planes() {
        for bricks in [1, 3, 8, 64] {
            let o = options(bricks);
            let (grid, _) = spec_of(&o).unwrap();
            let (cells, nodes) = cut(&o, &grid).unwrap();
            assert_eq!(cells.len(), bricks as usize);
            DomainTree::check(&nodes, cells.len()).unwrap();
            let owned: u64 = cells
                .iter()
                .map(|c| c.iter().map(|a| u64::from(a[1] - a[0])).product::<u64>())
                .sum();
            assert_eq!(owned, 40 * 32 * 47);
            assert!(
                cells.iter().all(|c| c.iter().all(|a| a[0] % BLOCK == 0)),
                "cut on block planes"
            );
        }
        assert!(cut(&options(2000), &spec_of(&options(2000)).unwrap().0).is_err());
    }

    #[test]
    fn writes_a_scene_that_loads() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("v");
        let m = prepare_bricks(&out, &Ramp, &options(8)).unwrap();
        assert_eq!(m.domains.len(), 8);
        assert_eq!(m.bounds.max, [40.0, 32.0, 94.0]);
        let back = Manifest::load(&out).unwrap();
        back.check_domains(&out, true).unwrap();
        assert_eq!(back.volume.unwrap().step, 0.5);
    }
}
