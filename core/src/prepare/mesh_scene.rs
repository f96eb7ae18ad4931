//! A scene from a triangle mesh: domains balanced on triangle centroids; a triangle that
//! crosses domain boundaries is referenced by every domain its (slightly grown) box overlaps.

use std::path::Path;

use super::{
    DomainTriangles, PrepareError, SceneSpec, default_lighting, reference_margin, write_scene,
};
use crate::geometry::Aabb;
use crate::mesh::TriangleMesh;
use crate::scene::domain_file::SourceTriangle;
use crate::scene::{DomainTree, Manifest, Material};

pub use crate::scene::manifest::MAX_DOMAINS;

/// Refuses a domain count outside 1..=[`MAX_DOMAINS`], the limit README states.
pub fn check_domains(domains: u32) -> Result<(), PrepareError> {
    if domains == 0 || domains > MAX_DOMAINS {
        return Err(PrepareError::Invalid(format!(
            "--domains {domains} is outside 1..={MAX_DOMAINS}"
        )));
    }
    Ok(())
}

/// Cuts `mesh` into `domains` domains and writes the scene to `out`.
pub fn prepare_mesh(
    mesh: &TriangleMesh,
    name: &str,
    out: &Path,
    domains: u32,
    force: bool,
) -> Result<Manifest, PrepareError> {
    check_domains(domains)?;
    let tris: Vec<[[f32; 3]; 3]> = mesh
        .triangles
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let v = t.map(|k| mesh.positions.get(k as usize).copied());
            match v {
                [Some(a), Some(b), Some(c)] => Ok([a, b, c]),
                _ => Err(PrepareError::Invalid(format!(
                    "triangle {i} names a missing vertex"
                ))),
            }
        })
        .collect::<Result<_, _>>()?;
    let look = SurfaceLook {
        materials: vec![Material::Diffuse {
            albedo: [0.75, 0.72, 0.68],
        }],
        material_of: None,
        normals: None,
    };
    prepare_triangles(&tris, look, name, out, domains, force)
}

/// How a mesh scene's triangles are shaded.
pub(crate) struct SurfaceLook<'a> {
    /// The scene's materials.
    pub materials: Vec<Material>,
    /// Each triangle's material, an index into `materials` (a colour from a lookup table);
    /// `None`: the first material for every triangle.
    pub material_of: Option<&'a [u32]>,
    /// Corner shading normals, one triple per triangle (a smooth surface), or facet normals.
    pub normals: Option<&'a [[[f32; 3]; 3]]>,
}

/// Cuts the triangles `tris` into `domains` domains and writes the scene to `out`.
pub(crate) fn prepare_triangles(
    tris: &[[[f32; 3]; 3]],
    look: SurfaceLook,
    name: &str,
    out: &Path,
    domains: u32,
    force: bool,
) -> Result<Manifest, PrepareError> {
    check_domains(domains)?;
    if tris.is_empty() {
        return Err(PrepareError::Invalid(
            "the mesh has no triangles (an empty file, or only points and lines)".into(),
        ));
    }
    if look.material_of.is_some_and(|m| m.len() != tris.len()) {
        return Err(PrepareError::Invalid(
            "a material for every triangle, or none".into(),
        ));
    }
    let mut bounds = Aabb::EMPTY;
    for t in tris {
        for v in t {
            if v.iter().any(|x| !x.is_finite()) {
                return Err(PrepareError::Invalid(
                    "the mesh has a non-finite vertex".into(),
                ));
            }
            bounds.grow(*v);
        }
    }
    // A flat mesh still needs a box with volume, or rays could not enter it.
    let bounds = bounds.expanded(reference_margin(&bounds).max(1e-6) * 4.0);
    let mut centroids: Vec<([f32; 3], f64)> = tris
        .iter()
        .map(|t| (Aabb::of_triangle(t).center(), 1.0))
        .collect();
    let tree = DomainTree::balanced(bounds, &mut centroids, domains);
    drop(centroids);
    let margin = reference_margin(&bounds);
    let mut per_domain: Vec<Vec<u32>> = vec![Vec::new(); domains as usize];
    for (i, t) in tris.iter().enumerate() {
        tree.overlapping(&Aabb::of_triangle(t).expanded(margin), |d| {
            per_domain[d as usize].push(i as u32)
        });
    }
    let (camera, sky, lights) = default_lighting(&bounds);
    let spec = SceneSpec {
        name: name.into(),
        tree: tree.clone(),
        camera,
        sky,
        materials: look.materials.clone(),
        lights,
    };
    write_scene(out, spec, force, |d, _| {
        let mine = per_domain[d as usize]
            .iter()
            .map(|&i| SourceTriangle {
                vertices: tris[i as usize],
                id: i as u64,
                material: look.material_of.map_or(0, |m| m[i as usize]),
                normals: look.normals.map(|n| n[i as usize]),
            })
            .collect();
        Ok(DomainTriangles::new(&tree, d, mine))
    })
}
