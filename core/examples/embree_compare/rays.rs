//! The ray sets both tracers trace: coherent camera rays, incoherent diffuse bounces and
//! shadow rays, each limited to the interval the render kernel gives it in the domain.

use super::*;

/// One ray as both tracers read it (the C++ program's `Ray`).
#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
pub(crate) struct BenchRay {
    pub(crate) origin: [f32; 3],
    pub(crate) t_min: f32,
    pub(crate) dir: [f32; 3],
    pub(crate) t_max: f32,
}

/// The ray limited to the interval the render kernel traces it over in the (only) domain, as
/// the domain tree's walk gives it; `None` if the ray misses the domain and would never be
/// traced. Both tracers get the same finite interval.
pub(crate) fn in_domain(tree: &DomainTree, origin: Vec3, dir: Vec3) -> Option<BenchRay> {
    let mut interval = None;
    tree.walk(origin, dir, 0.0, f32::INFINITY, |_, t0, t1| {
        interval = Some((t0, t1));
        ControlFlow::Break(())
    });
    let (t_min, t_max) = interval?;
    Some(BenchRay {
        origin: origin.into(),
        t_min,
        dir: dir.into(),
        t_max,
    })
}

/// One camera ray per pixel of a `size` x `size` image; also returns each ray's pixel.
pub(crate) fn camera_rays(
    manifest: &Manifest,
    tree: &DomainTree,
    size: u32,
) -> (Vec<BenchRay>, Vec<u32>) {
    let camera = PinholeCamera::new(&manifest.camera, size, size);
    (0..size * size)
        .filter_map(|pixel| {
            let r = camera.primary(pixel, 0);
            in_domain(tree, r.origin.into(), r.dir.into()).map(|ray| (ray, pixel))
        })
        .unzip()
}

/// One diffuse bounce from every camera ray that hit, drawn with the same hashed random
/// numbers a render uses for the first bounce, so the set is deterministic.
pub(crate) fn diffuse_rays(
    camera: &[BenchRay],
    pixels: &[u32],
    hits: &[Option<Hit>],
    bvh: Bvh,
    tree: &DomainTree,
    epsilon: f32,
) -> Vec<BenchRay> {
    let mut rays = Vec::with_capacity(camera.len());
    for ((ray, &pixel), hit) in camera.iter().zip(pixels).zip(hits) {
        let Some(hit) = hit else { continue };
        let (origin, n) = leaving(ray, hit, bvh, epsilon);
        let u = uniform(pixel, 0, 0, Purpose::BounceU, 0);
        let v = uniform(pixel, 0, 0, Purpose::BounceV, 0);
        rays.extend(in_domain(tree, origin, cosine_about(n, u, v)));
    }
    rays
}

/// Where rays leaving camera ray `ray`'s hit start, and the geometric normal on the side the
/// ray arrived from: the surface left as the render kernel leaves it, so these are the rays a
/// render would trace.
fn leaving(ray: &BenchRay, hit: &Hit, bvh: Bvh, epsilon: f32) -> (Vec3, Vec3) {
    let dir = Vec3::from(ray.dir);
    let p = Vec3::from(ray.origin) + dir * hit.t;
    let normal = bvh.triangle(hit).normal();
    let n = if normal.dot(dir) > 0.0 {
        -normal
    } else {
        normal
    };
    (leave_surface(p, n, epsilon), n)
}

/// Shadow rays from every camera ray that hit towards each of `lights` (a quad light's centre,
/// up to just before it; a directional light without end), leaving the surface as
/// [`diffuse_rays`] do; a light behind the surface gets none, as in a render.
pub(crate) fn shadow_rays(
    camera: &[BenchRay],
    hits: &[Option<Hit>],
    bvh: Bvh,
    tree: &DomainTree,
    (epsilon, lights): (f32, &[Light]),
) -> Vec<BenchRay> {
    let mut rays = Vec::with_capacity(camera.len() * lights.len());
    for (ray, hit) in camera.iter().zip(hits) {
        let Some(hit) = hit else { continue };
        let (origin, n) = leaving(ray, hit, bvh, epsilon);
        for light in lights {
            let (l, end) = match *light {
                Light::Directional { direction, .. } => {
                    (Vec3::from(direction).normalize_or(Vec3::Y), f32::INFINITY)
                }
                Light::Quad {
                    corner,
                    edge_u,
                    edge_v,
                    ..
                } => {
                    let q = Vec3::from(corner) + 0.5 * (Vec3::from(edge_u) + Vec3::from(edge_v));
                    let to = q - origin;
                    let dist = to.length();
                    (to / dist, dist * (1.0 - 1e-4))
                }
            };
            let cos = n.dot(l);
            if cos <= 0.0 || cos.is_nan() {
                continue;
            }
            let mut interval = None;
            tree.walk(origin, l, 0.0, end, |_, t0, t1| {
                interval = Some((t0, t1));
                ControlFlow::Break(())
            });
            if let Some((t_min, t_max)) = interval {
                rays.push(BenchRay {
                    origin: origin.into(),
                    t_min,
                    dir: l.into(),
                    t_max,
                });
            }
        }
    }
    rays
}

/// A cosine-distributed unit direction about the unit vector `n`: a uniform point on the unit
/// disk, lifted onto the hemisphere (Malley's method).
pub(crate) fn cosine_about(n: Vec3, u: f32, v: f32) -> Vec3 {
    let (tangent, bitangent) = n.any_orthonormal_pair();
    let r = u.sqrt();
    let (sin, cos) = (std::f32::consts::TAU * v).sin_cos();
    let lift = (1.0 - u).max(0.0).sqrt();
    (tangent * (r * cos) + bitangent * (r * sin) + n * lift).normalize()
}
