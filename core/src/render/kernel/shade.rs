//! Shading a surface hit: the children of a radiance ray (shadow rays towards the lights,
//! at most one bounce) and the split of its credit among them.

use glam::Vec3;

use super::{KernelCounters, RaySink, SceneView};
use crate::bvh::{Bvh, Hit};
use crate::geometry::leave_surface;
use crate::ray::{RayKind, RayRecord};
use crate::sampling::{Purpose, uniform};
use crate::scene::{Light, Material};
use crate::tile::credit::{split_credit, split_path_credit};

impl SceneView {
    /// Splits the parent's credit among its children (shadow rays get the minimum, the bounce
    /// the rest, so credit lasts for any depth) and sends them on. A parent without children, or
    /// whose credit cannot be split, ends its path and returns its credit; credit depends only
    /// on the ray tree, so that cut is the same in every run. `here` is the domain of the hit
    /// ([`SceneView::route_child`]).
    pub(super) fn hand_on_credit(
        &self,
        parent: &RayRecord,
        here: Option<u32>,
        children: &mut [RayRecord],
        sink: &mut impl RaySink,
    ) {
        let leaves = children
            .iter()
            .filter(|c| c.kind() == RayKind::Shadow)
            .count();
        if children.is_empty() {
            sink.retire(parent, [0.0; 3]);
            return;
        }
        // The shares are computed in place (no vector of them per ray): even shares when every
        // child is a leaf, else the minimum per leaf and the rest to the bounce.
        if leaves == children.len() {
            match split_credit(parent.credit, leaves) {
                Ok(shares) => {
                    for (child, credit) in children.iter_mut().zip(shares) {
                        child.credit = credit;
                        self.route_child(*child, here, sink);
                    }
                }
                Err(_) => sink.retire(parent, [0.0; 3]),
            }
            return;
        }
        match split_path_credit(parent.credit, leaves) {
            Ok(s) => {
                for child in children.iter_mut() {
                    child.credit = if child.kind() == RayKind::Shadow {
                        s.leaf
                    } else {
                        s.continuation
                    };
                    self.route_child(*child, here, sink);
                }
            }
            Err(_) => sink.retire(parent, [0.0; 3]),
        }
    }

    /// The surface the radiance ray `ray` meets at `hit` (of `bvh`), as [`SceneView::shade`]
    /// takes it: the normal to shade with, on the side the ray came from, and the material.
    ///
    /// The triangle's geometric normal decides the side: it is turned towards the ray. A
    /// triangle with corner shading normals (a smooth isosurface) is shaded with them,
    /// interpolated at the hit by its barycentric coordinates and turned the same way; where
    /// that leans within [`MIN_SHADING_COS`] of the triangle's plane it is bent back towards
    /// the geometric normal, so leaving the surface along it (`shade`) always leaves on the
    /// ray's side. A pure function of the triangle, the ray and the distance: a chained trace
    /// and a speculative copy (which sends it home in its verdict) get the same bits.
    pub(super) fn surface_at(&self, bvh: Bvh, hit: &Hit, ray: &RayRecord) -> (Vec3, u32) {
        let tri = bvh.triangle(hit);
        let dir = Vec3::from(ray.dir);
        let mut n = tri.normal();
        let facing = if n.dot(dir) > 0.0 { -1.0 } else { 1.0 };
        n *= facing;
        let Some(corners) = bvh.vertex_normals(hit) else {
            return (n, tri.material);
        };
        let p = Vec3::from(ray.origin) + dir * hit.t;
        let corners_at = [tri.v0, tri.v1, tri.v2].map(Vec3::from);
        let smooth = barycentrics(corners_at, p)
            .map(|b| (corners[0] * b[0] + corners[1] * b[1] + corners[2] * b[2]) * facing);
        (smooth.map_or(n, |s| bend_to_side(s, n)), tri.material)
    }

    /// The children of a radiance ray that hit a surface (shading normal on the ray's side, as
    /// [`SceneView::surface_at`] gives it, and material) at `p`: shadow rays towards the lights
    /// and at most one bounce, pushed to `out` without credit.
    pub(super) fn shade(
        &self,
        ray: &RayRecord,
        p: Vec3,
        surface: (Vec3, u32),
        out: &mut Vec<RayRecord>,
        counters: &mut KernelCounters,
    ) {
        let dir = Vec3::from(ray.dir);
        let (n, material) = surface;
        let origin = leave_surface(p, n, self.epsilon);
        let throughput = Vec3::from(ray.throughput);
        let u = |purpose| uniform(ray.pixel, ray.sample, ray.depth as u32, purpose, 0);
        let can_bounce = ray.depth < self.max_depth;
        let child = |d: Vec3, weight: Vec3| RayRecord {
            origin: origin.into(),
            t_min: 0.0,
            dir: d.into(),
            t_max: f32::INFINITY,
            throughput: weight.into(),
            depth: ray.depth + 1,
            kind: RayKind::Radiance as u8,
            ..*ray
        };
        // Materials are checked against the manifest when a domain is loaded; a colour-mapped
        // one is diffuse with the map's colour at this height.
        let material = match self.materials[material as usize] {
            Material::Mapped { map, axis, range } => {
                // The manifest checked the axis and that the range is finite and increasing.
                let height = (p[usize::from(axis)] - range[0]) / (range[1] - range[0]);
                Material::Diffuse {
                    albedo: map.at(height),
                }
            }
            m => m,
        };
        match material {
            Material::Diffuse { albedo } => {
                let albedo = Vec3::from(albedo);
                self.direct_light(ray, origin, n, throughput * albedo, out, counters);
                if can_bounce {
                    let d = cosine_direction(n, u(Purpose::BounceU), u(Purpose::BounceV));
                    counters.bounce_rays += 1;
                    out.push(child(d, throughput * albedo));
                }
            }
            // Made diffuse above.
            Material::Mapped { .. } => {}
            Material::Mirror { tint } => {
                if can_bounce {
                    counters.reflection_rays += 1;
                    let d = reflect(dir, n);
                    out.push(child(d, throughput * Vec3::from(tint)));
                }
            }
            Material::Glossy {
                albedo,
                specular,
                roughness,
            } => {
                let specular = specular.clamp(0.0, 1.0);
                let base = throughput * Vec3::from(albedo) * (1.0 - specular);
                self.direct_light(ray, origin, n, base, out, counters);
                if !can_bounce {
                    return;
                }
                // One bounce: the coat with probability `specular`, else the base. Both
                // weights are divided by their probability, so the estimate stays unbiased.
                if u(Purpose::Lobe) < specular {
                    let fuzz = sphere_point(u(Purpose::GlossU), u(Purpose::GlossV)) * roughness;
                    let d = (reflect(dir, n) + fuzz).normalize_or(n);
                    if d.dot(n) > 0.0 {
                        counters.bounce_rays += 1;
                        out.push(child(d, throughput));
                    }
                } else if specular < 1.0 {
                    let d = cosine_direction(n, u(Purpose::BounceU), u(Purpose::BounceV));
                    counters.bounce_rays += 1;
                    out.push(child(d, throughput * Vec3::from(albedo)));
                }
            }
        }
    }

    /// Shadow rays towards every light, each carrying the light it will add if unoccluded.
    /// `weight` is the path throughput times the diffuse reflectance.
    fn direct_light(
        &self,
        ray: &RayRecord,
        origin: Vec3,
        n: Vec3,
        weight: Vec3,
        out: &mut Vec<RayRecord>,
        counters: &mut KernelCounters,
    ) {
        let brdf = weight * std::f32::consts::FRAC_1_PI;
        for (i, light) in self.lights.iter().enumerate() {
            let (dir, t_max, light_in) = match *light {
                Light::Directional {
                    direction,
                    radiance,
                } => {
                    let l = Vec3::from(direction).normalize_or(Vec3::Y);
                    let cos = n.dot(l);
                    if cos <= 0.0 {
                        continue;
                    }
                    (
                        l,
                        f32::INFINITY,
                        Vec3::from(radiance) * cos * std::f32::consts::PI,
                    )
                }
                Light::Quad {
                    corner,
                    edge_u,
                    edge_v,
                    emission,
                } => {
                    let (eu, ev) = (Vec3::from(edge_u), Vec3::from(edge_v));
                    let su = uniform(
                        ray.pixel,
                        ray.sample,
                        ray.depth as u32,
                        Purpose::LightU,
                        i as u32,
                    );
                    let sv = uniform(
                        ray.pixel,
                        ray.sample,
                        ray.depth as u32,
                        Purpose::LightV,
                        i as u32,
                    );
                    let q = Vec3::from(corner) + eu * su + ev * sv;
                    let to = q - origin;
                    let dist2 = to.length_squared();
                    if dist2 <= 0.0 {
                        continue;
                    }
                    let dist = dist2.sqrt();
                    let l = to / dist;
                    let area_n = eu.cross(ev);
                    let cos_s = n.dot(l);
                    let cos_l = -area_n.dot(l); // area_n carries the quad's area
                    if cos_s <= 0.0 || cos_l <= 0.0 {
                        continue;
                    }
                    let geometry = cos_s * cos_l / dist2;
                    (l, dist * (1.0 - 1e-4), Vec3::from(emission) * geometry)
                }
            };
            let carried = brdf * light_in;
            if carried.max_element() <= 0.0 {
                continue;
            }
            counters.shadow_rays += 1;
            out.push(RayRecord {
                origin: origin.into(),
                t_min: 0.0,
                dir: dir.into(),
                t_max,
                throughput: carried.into(),
                kind: RayKind::Shadow as u8,
                ..*ray
            });
        }
    }
}

/// Least cosine between a shading normal and the geometric normal on the ray's side: below
/// it, the shading normal is bent towards the geometric one (`bend_to_side`).
pub const MIN_SHADING_COS: f32 = 0.25;

/// The barycentric coordinates of `p` (a point on the triangle `v`, up to rounding) clamped
/// into the triangle; `None` for a degenerate triangle.
fn barycentrics(v: [Vec3; 3], p: Vec3) -> Option<[f32; 3]> {
    let (e1, e2, w) = (v[1] - v[0], v[2] - v[0], p - v[0]);
    let (d11, d12, d22) = (e1.dot(e1), e1.dot(e2), e2.dot(e2));
    let (dw1, dw2) = (w.dot(e1), w.dot(e2));
    let det = d11 * d22 - d12 * d12;
    if !(det.is_finite() && det > 0.0) {
        return None;
    }
    let b1 = ((d22 * dw1 - d12 * dw2) / det).clamp(0.0, 1.0);
    let b2 = ((d11 * dw2 - d12 * dw1) / det).clamp(0.0, 1.0);
    let sum = b1 + b2;
    let (b1, b2) = if sum > 1.0 {
        (b1 / sum, b2 / sum)
    } else {
        (b1, b2)
    };
    Some([1.0 - b1 - b2, b1, b2])
}

/// The shading normal `s` made unit length and kept at least [`MIN_SHADING_COS`] (about)
/// above the plane of the geometric normal `g` (unit, on the ray's side): `s + k g` with the
/// least `k >= 0` that gives the cosine the bound before normalising. `g` if `s` vanishes.
fn bend_to_side(s: Vec3, g: Vec3) -> Vec3 {
    let Some(s) = s.try_normalize() else {
        return g;
    };
    let cos = s.dot(g);
    if cos >= MIN_SHADING_COS {
        return s;
    }
    (s + g * (MIN_SHADING_COS - cos)).normalize_or(g)
}

fn reflect(d: Vec3, n: Vec3) -> Vec3 {
    d - n * (2.0 * d.dot(n))
}

/// Cosine-weighted direction about `n` (pdf cos/pi, which cancels the Lambert BRDF's cos/pi).
fn cosine_direction(n: Vec3, u: f32, v: f32) -> Vec3 {
    let (t, b) = n.any_orthonormal_pair();
    let r = u.sqrt();
    let phi = 2.0 * std::f32::consts::PI * v;
    (t * (r * phi.cos()) + b * (r * phi.sin()) + n * (1.0 - u).max(0.0).sqrt()).normalize_or(n)
}

/// A point on the unit sphere.
fn sphere_point(u: f32, v: f32) -> Vec3 {
    let z = 1.0 - 2.0 * u;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * std::f32::consts::PI * v;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn barycentrics_recover_the_corners_and_weights() {
        let v = [Vec3::ZERO, Vec3::X, Vec3::Y];
        assert_eq!(barycentrics(v, Vec3::ZERO), Some([1.0, 0.0, 0.0]));
        assert_eq!(barycentrics(v, Vec3::X), Some([0.0, 1.0, 0.0]));
        let b = barycentrics(v, Vec3::new(0.25, 0.5, 0.0)).unwrap();
        assert!((b[0] - 0.25).abs() < 1e-6 && (b[1] - 0.25).abs() < 1e-6);
        // Outside (rounding): clamped into the triangle, still summing to one.
        let b = barycentrics(v, Vec3::new(0.7, 0.7, 0.0)).unwrap();
        assert!(b.iter().all(|&x| x >= 0.0) && (b.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        assert_eq!(
            barycentrics([Vec3::ZERO, Vec3::X, Vec3::X * 2.0], Vec3::X),
            None
        );
    }

    #[test]
    fn shading_normals_stay_on_the_geometric_side() {
        let g = Vec3::Z;
        assert_eq!(
            bend_to_side(Vec3::new(0.0, 0.6, 0.8), g),
            Vec3::new(0.0, 0.6, 0.8)
        );
        for s in [
            Vec3::X,
            -Vec3::Z,
            Vec3::new(1.0, 0.0, -0.2),
            Vec3::new(0.3, 0.2, 0.01),
        ] {
            let b = bend_to_side(s, g);
            assert!((b.length() - 1.0).abs() < 1e-5);
            assert!(b.dot(g) >= MIN_SHADING_COS * 0.9, "{s} bent to {b}");
        }
        assert_eq!(bend_to_side(Vec3::ZERO, g), g);
    }
}
