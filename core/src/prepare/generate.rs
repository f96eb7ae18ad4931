//! The built-in scene: an isosurface of a clustered particle-density field (in the spirit of
//! the cosmology data of the dynamic-scheduling paper) over a ground plane, with a mirror
//! behind it so reflections matter. Any size: the field is the same at every triangle count,
//! only the lattice gets finer. Domains are written one at a time, each marching only its own
//! cells (and a one-cell halo), so peak memory stays near one domain's size.

use std::path::Path;

use glam::Vec3;
use tracing::info;

use super::{DomainTriangles, PrepareError, SceneSpec, reference_margin, write_scene};
use crate::colour_map::ColourMap;
use crate::geometry::Aabb;
use crate::isosurface::{Grid, IsoTriangle, march, march_smooth};
use crate::nbody::{NbodyField, SampledField, resolution_for_triangles};
use crate::scene::domain_file::SourceTriangle;
use crate::scene::{Camera, DomainTree, Light, Manifest, Material, Sky};

/// Options of the generator.
#[derive(Clone, Debug)]
pub struct NbodyOptions {
    /// Scene name.
    pub name: String,
    /// Approximate number of triangles.
    pub triangles: u64,
    /// Seed of the particle distribution.
    pub seed: u64,
    /// Domains to cut the scene into (more are used if `max_memory` needs them).
    pub domains: u32,
    /// Peak memory to stay under while generating.
    pub max_memory: Option<u64>,
    /// Replace an existing scene.
    pub force: bool,
}

/// Particles in the field: fixed, so the scene looks the same at every size.
const PARTICLES: usize = 20_000;
/// Peak bytes per triangle while one domain is built (source, packed and obvhs copies, the
/// BVH builder's work arrays), measured with `/usr/bin/time -v` (335 MiB peak for one 872k-triangle domain) and rounded up.
const BUILD_BYTES_PER_TRIANGLE: u64 = 400;
/// Memory the process needs besides the domain being built.
const BASE_BYTES: u64 = 32 << 20;
/// Lattice resolution of the coarse pass that estimates where the triangles are.
const COARSE: u32 = 48;

const GROUND: f32 = -0.02;
const MIRROR_Z: f32 = -0.2;
const MAT_GROUND: u32 = 0;
const MAT_MIRROR: u32 = 1;
const BLOB_MATERIALS: u32 = 4;
/// The blobs' material with a colour map: after the ground, the mirror and the four blob
/// colours.
const MAT_MAPPED: u32 = 2 + BLOB_MATERIALS;

/// How the generated blobs are shaded and coloured.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct NbodyLook {
    /// Smooth normals from the density field's gradient (`isosurface::march_smooth`) instead
    /// of the facets'.
    pub smooth: bool,
    /// Colour the blobs by height (along y, the scene's up, from the ground to the top of the
    /// field) with this map, instead of one of four colours per region of space.
    pub colour_map: Option<ColourMap>,
}

/// Generates the scene into `out`, with flat normals and colours by region of space.
pub fn prepare_nbody(out: &Path, o: &NbodyOptions) -> Result<Manifest, PrepareError> {
    prepare_nbody_with(out, o, NbodyLook::default())
}

/// Generates the scene into `out`, its blobs looking as `look` says.
pub fn prepare_nbody_with(
    out: &Path,
    o: &NbodyOptions,
    look: NbodyLook,
) -> Result<Manifest, PrepareError> {
    if o.triangles < 1_000 || o.triangles > 1 << 36 {
        return Err(PrepareError::Invalid(format!(
            "--triangles {} is outside 1000..={}",
            o.triangles,
            1u64 << 36
        )));
    }
    let field = NbodyField::new(o.seed, PARTICLES);
    let iso = field.suggested_iso();
    let n = resolution_for_triangles(&field, iso, o.triangles).max(8);
    let grid = Grid::unit_cube(n);
    let sampled = SampledField {
        field: &field,
        grid,
    };
    let (mut points, surface_cells) = coarse_surface(&field, iso);
    let domains = domains_for_memory(o, n, surface_cells)?;
    let bounds = scene_bounds();
    let tree = DomainTree::balanced(bounds, &mut points, domains);
    drop(points);
    info!(resolution = n, domains, "generating nbody scene");
    let margin = reference_margin(&bounds);
    let fixed = fixed_triangles();
    let spec = SceneSpec {
        name: o.name.clone(),
        tree: tree.clone(),
        camera: Camera {
            eye: [0.5, 0.7, 2.75],
            look_at: [0.5, 0.38, 0.35],
            up: [0.0, 1.0, 0.0],
            fov_y_degrees: 38.0,
        },
        sky: Sky {
            horizon: [0.6, 0.65, 0.75],
            zenith: [0.2, 0.3, 0.6],
        },
        materials: materials(look.colour_map),
        lights: lights(),
    };
    let tree_for_count = tree.clone();
    write_scene(out, spec, o.force, |d, b| {
        let grown = b.expanded(margin);
        let mut tris: Vec<SourceTriangle> = fixed
            .iter()
            .filter(|t| Aabb::of_triangle(&t.vertices).overlaps(&grown))
            .copied()
            .collect();
        let cells = grid.cells_touching(&grown);
        if cells.iter().all(|r| !r.is_empty()) {
            let emit = |t: IsoTriangle| {
                if Aabb::of_triangle(&t.vertices).overlaps(&grown) {
                    tris.push(SourceTriangle {
                        vertices: t.vertices,
                        id: fixed.len() as u64 + t.id,
                        material: match look.colour_map {
                            Some(_) => MAT_MAPPED,
                            None => blob_material(&t.vertices),
                        },
                        normals: t.normals,
                    });
                }
            };
            if look.smooth {
                march_smooth(&grid, &sampled, iso, cells, emit);
            } else {
                march(&grid, &sampled, iso, cells, emit);
            }
        }
        Ok(DomainTriangles::new(&tree_for_count, d, tris))
    })
}

/// The generator's density field as a volume of `n`^3 voxels over the unit cube (the paper's
/// n-body DVR), in units of the isosurface value the mesh scene uses (1 is its surface), cut
/// into `bricks` for direct volume rendering; voxels are computed brick by brick as written.
pub fn prepare_nbody_volume(
    out: &Path,
    o: &NbodyOptions,
    n: u32,
    look: super::brick_scene::VolumeLook,
) -> Result<Manifest, PrepareError> {
    if !(2..=4096).contains(&n) {
        return Err(PrepareError::Invalid(format!(
            "the generated volume's --dims {n} is outside 2..=4096 per axis"
        )));
    }
    use crate::isosurface::Lattice;
    struct Scaled<'a>(SampledField<'a>, f32);
    impl Lattice for Scaled<'_> {
        fn value(&self, i: u32, j: u32, k: u32) -> f32 {
            self.0.value(i, j, k) / self.1
        }
    }
    let field = NbodyField::new(o.seed, PARTICLES);
    let grid = Grid::unit_cube(n);
    let iso = field.suggested_iso();
    let volume = Scaled(
        SampledField {
            field: &field,
            grid,
        },
        iso,
    );
    super::brick_scene::prepare_bricks(
        out,
        &volume,
        &super::brick_scene::BrickOptions {
            name: o.name.clone(),
            source: "the generated volume".into(),
            dims: [n; 3],
            origin: grid.origin.into(),
            spacing: grid.spacing.into(),
            bricks: o.domains,
            step: None,
            look,
            force: o.force,
        },
    )
}

/// Samples the field coarsely: a weighted point at every coarse cell the surface crosses
/// (for balancing domains), and how many such cells there are (for memory planning).
fn coarse_surface(field: &NbodyField, iso: f32) -> (Vec<([f32; 3], f64)>, u64) {
    let grid = Grid::unit_cube(COARSE + 1);
    let sampled = SampledField { field, grid };
    let mut points = Vec::new();
    march(&grid, &sampled, iso, grid.all_cells(), |t| {
        points.push((Aabb::of_triangle(&t.vertices).center(), 1.0));
    });
    let crossing = points.len() as u64;
    (points, crossing)
}

/// The domain count: as asked, or more if one domain's build would not fit `max_memory`.
fn domains_for_memory(
    o: &NbodyOptions,
    n: u32,
    coarse_triangles: u64,
) -> Result<u32, PrepareError> {
    super::mesh_scene::check_domains(o.domains)?;
    let Some(limit) = o.max_memory else {
        return Ok(o.domains);
    };
    if limit <= BASE_BYTES + (16 << 20) {
        return Err(PrepareError::Invalid(format!(
            "--max-memory {limit} is too small: the generator needs about {} MiB besides the domain being built",
            (BASE_BYTES >> 20) + 16
        )));
    }
    // Triangles grow with the square of the lattice resolution.
    let scale = (n as f64 / COARSE as f64).powi(2);
    let estimate = (coarse_triangles as f64 * scale * 1.3) as u64 + 4;
    let per_domain = (limit - BASE_BYTES) / BUILD_BYTES_PER_TRIANGLE;
    // Balancing is approximate; leave room for a domain half again the average.
    let needed = (estimate * 3 / 2).div_ceil(per_domain.max(1));
    let domains = u32::try_from(needed).unwrap_or(u32::MAX).max(o.domains);
    if super::mesh_scene::check_domains(domains).is_err() {
        return Err(PrepareError::Invalid(format!(
            "--max-memory {limit} would need {domains} domains, more than the {} a scene may \
             have: give more memory",
            super::mesh_scene::MAX_DOMAINS
        )));
    }
    if domains > o.domains {
        info!(
            asked = o.domains,
            domains, "more domains to stay under --max-memory"
        );
    }
    Ok(domains)
}

fn scene_bounds() -> Aabb {
    let mut b = Aabb {
        min: [0.0; 3],
        max: [1.0; 3],
    };
    for t in fixed_triangles() {
        for v in t.vertices {
            b.grow(v);
        }
    }
    b.expanded(1e-3)
}

/// The ground plane and the mirror: two triangles each, ids 0 to 3.
fn fixed_triangles() -> Vec<SourceTriangle> {
    let quad = |c: [f32; 3], u: [f32; 3], v: [f32; 3], material, first: u64| {
        let (c, u, v) = (Vec3::from(c), Vec3::from(u), Vec3::from(v));
        let p = [c, c + u, c + u + v, c + v].map(<[f32; 3]>::from);
        [
            SourceTriangle {
                vertices: [p[0], p[1], p[2]],
                id: first,
                material,
                normals: None,
            },
            SourceTriangle {
                vertices: [p[0], p[2], p[3]],
                id: first + 1,
                material,
                normals: None,
            },
        ]
    };
    let mut v = Vec::new();
    v.extend(quad(
        [-0.6, GROUND, -0.6],
        [0.0, 0.0, 2.2],
        [2.2, 0.0, 0.0],
        MAT_GROUND,
        0,
    ));
    v.extend(quad(
        [-0.3, GROUND, MIRROR_Z],
        [1.6, 0.0, 0.0],
        [0.0, 1.05, 0.0],
        MAT_MIRROR,
        2,
    ));
    v
}

/// The scene's materials; with a colour map, one more after the others for the blobs
/// ([`MAT_MAPPED`]).
fn materials(colour_map: Option<ColourMap>) -> Vec<Material> {
    let mut m = vec![
        Material::Diffuse {
            albedo: [0.55, 0.55, 0.52],
        },
        Material::Mirror {
            tint: [0.9, 0.9, 0.95],
        },
        Material::Diffuse {
            albedo: [0.85, 0.5, 0.25],
        },
        Material::Diffuse {
            albedo: [0.3, 0.45, 0.85],
        },
        Material::Diffuse {
            albedo: [0.8, 0.8, 0.75],
        },
        Material::Glossy {
            albedo: [0.75, 0.55, 0.2],
            specular: 0.4,
            roughness: 0.12,
        },
    ];
    if let Some(map) = colour_map {
        m.push(Material::Mapped {
            map,
            axis: 1,
            range: [GROUND, 1.0],
        });
    }
    m
}

/// Colour by region of space, so a blob keeps its colour at every triangle count.
fn blob_material(v: &[[f32; 3]; 3]) -> u32 {
    let c = v[0].map(|x| (x * 5.0).floor() as i64 as u64);
    let h = c[0].wrapping_mul(0x9e37_79b9_7f4a_7c15)
        ^ c[1].wrapping_mul(0xc2b2_ae3d_27d4_eb4f)
        ^ c[2].wrapping_mul(0x1656_67b1_9e37_79f9);
    2 + ((h >> 33) % BLOB_MATERIALS as u64) as u32
}

fn lights() -> Vec<Light> {
    vec![
        Light::Directional {
            direction: [0.35, 0.85, 0.4],
            radiance: [1.0, 0.95, 0.85],
        },
        Light::Quad {
            corner: [0.1, 1.6, 0.2],
            edge_u: [0.6, 0.0, 0.0],
            edge_v: [0.0, 0.0, 0.6],
            emission: [3.0, 2.9, 2.7],
        },
    ]
}
