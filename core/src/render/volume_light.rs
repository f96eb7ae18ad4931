//! How direct volume rendering lights its samples: by the scene's lights, with the volume's
//! gradient as the normal (a sample in a uniform region, whose gradient is zero, takes the
//! light whole), plus a fixed ambient share; optionally with shadow rays.
//!
//! Shadows: a shadow ray per sample and light would be far too many. Instead each composited
//! segment of a ray (the samples between two block faces, `render::dvr`) keeps the light it
//! got from each light apart from its ambient part, and its depth along the ray (the
//! opacity-weighted mean of its samples' distances). When the segment is folded into the ray,
//! one shadow ray per light leaves from that depth towards the light, carrying the segment's
//! direct light times the ray's transparency in front of it; marching the volume on its way,
//! it delivers that light times its own transparency. Everything a shadow ray needs is fixed by
//! the segment, which no bricking splits, and by the ray (a quad light's point is a hash of
//! the ray's pixel, sample and depth, as for surfaces), so the image stays the same bits at any
//! bricking, chained or speculative.

use glam::Vec3;

use crate::ray::RayRecord;
use crate::sampling::{Purpose, uniform};
use crate::scene::Light;

/// Most lights that light a volume; the manifest's first ones (a shadowed segment carries one
/// colour per light, so the verdict format bounds them: `wire::MAX_SEGMENT_LIGHTS`).
pub const MAX_LIGHTS: usize = crate::wire::MAX_SEGMENT_LIGHTS;

/// Share of a sample's colour it shows unlit (the sky's light, without shadows or occlusion).
pub const AMBIENT: f32 = 0.2;

/// Shadow rays leave a segment's depth this many voxel lengths out, so a surface-like
/// material does not shadow itself where the ray met it.
pub const SHADOW_BIAS_VOXELS: f32 = 2.0;

/// How a ray's samples are lit.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Lighting {
    /// Each sample its transfer function's colour (and shadow rays, which only count opacity).
    #[default]
    Unlit,
    /// Diffuse by the gradient against the ray (a light at the eye): no lights in the scene.
    Headlight,
    /// By the scene's lights, all light composited into the ray.
    Lights,
    /// By the scene's lights, each light's share sent on in shadow rays.
    Shadowed,
}

/// One light as one ray's samples see it.
#[derive(Clone, Copy, Debug)]
enum LightAt {
    /// From infinitely far away: towards the light `l`, bringing `radiance`.
    Far { l: Vec3, radiance: Vec3 },
    /// A quad light's point `q` chosen for this ray, its normal times area, and emission.
    Point {
        q: Vec3,
        area_n: Vec3,
        emission: Vec3,
    },
}

impl LightAt {
    /// Direction towards the light from `p`, the light arriving there (before the normal's
    /// cosine), and how far the light is (infinite for a far light); `None` if `p` is
    /// behind a quad light.
    fn at(&self, p: Vec3) -> Option<(Vec3, Vec3, f32)> {
        match *self {
            LightAt::Far { l, radiance } => Some((l, radiance, f32::INFINITY)),
            LightAt::Point {
                q,
                area_n,
                emission,
            } => {
                let to = q - p;
                let dist2 = to.length_squared();
                if dist2 <= 0.0 || !dist2.is_finite() {
                    return None;
                }
                let dist = dist2.sqrt();
                let l = to / dist;
                let cos_l = -area_n.dot(l);
                (cos_l > 0.0).then(|| (l, emission * (cos_l / dist2), dist))
            }
        }
    }
}

/// The lights as one ray's samples see them.
#[derive(Clone, Copy, Debug)]
pub struct RayLights {
    /// How samples are lit.
    pub lighting: Lighting,
    lights: [Option<LightAt>; MAX_LIGHTS],
}

impl RayLights {
    /// No lighting: each sample its transfer function's colour.
    pub const UNLIT: RayLights = RayLights {
        lighting: Lighting::Unlit,
        lights: [None; MAX_LIGHTS],
    };

    /// The first [`MAX_LIGHTS`] of `lights` for `ray`, lit as `lighting` says.
    pub fn for_ray(lighting: Lighting, lights: &[Light], ray: &RayRecord) -> RayLights {
        let mut out = RayLights {
            lighting,
            lights: [None; MAX_LIGHTS],
        };
        if !matches!(lighting, Lighting::Lights | Lighting::Shadowed) {
            return out;
        }
        for (i, light) in lights.iter().take(MAX_LIGHTS).enumerate() {
            out.lights[i] = Some(match *light {
                Light::Directional {
                    direction,
                    radiance,
                } => LightAt::Far {
                    l: Vec3::from(direction).normalize_or(Vec3::Y),
                    radiance: Vec3::from(radiance),
                },
                Light::Quad {
                    corner,
                    edge_u,
                    edge_v,
                    emission,
                } => {
                    // The surface kernel's point on the light for this ray: the same hashes.
                    let u = |p| uniform(ray.pixel, ray.sample, ray.depth as u32, p, i as u32);
                    let (eu, ev) = (Vec3::from(edge_u), Vec3::from(edge_v));
                    LightAt::Point {
                        q: Vec3::from(corner) + eu * u(Purpose::LightU) + ev * u(Purpose::LightV),
                        area_n: eu.cross(ev),
                        emission: Vec3::from(emission),
                    }
                }
            });
        }
        out
    }

    /// The light a sample of premultiplied colour `c` at `p` reflects, given the volume's
    /// gradient there (world units) and the ray's direction: its ambient part, and each
    /// light's part (zero for a light it does not see).
    #[inline]
    pub fn shade(&self, c: Vec3, p: Vec3, gradient: Vec3, dir: Vec3) -> (Vec3, [Vec3; MAX_LIGHTS]) {
        let mut direct = [Vec3::ZERO; MAX_LIGHTS];
        let len = gradient.length();
        // The outward normal of denser material; none where the volume is uniform.
        let normal = (len > 0.0 && len.is_finite()).then(|| -gradient / len);
        match self.lighting {
            Lighting::Unlit => (c, direct),
            Lighting::Headlight => {
                let lit = normal.map_or(1.0, |n| 0.25 + 0.75 * n.dot(dir).abs());
                (c * lit, direct)
            }
            Lighting::Lights | Lighting::Shadowed => {
                for (slot, light) in direct.iter_mut().zip(&self.lights) {
                    if let Some((l, incoming, _)) = light.and_then(|x| x.at(p)) {
                        let cos = normal.map_or(1.0, |n| n.dot(l).max(0.0));
                        *slot = c * incoming * cos;
                    }
                }
                (c * AMBIENT, direct)
            }
        }
    }

    /// Where a shadow ray for light `i` from `p` goes: its direction and length.
    pub fn shadow_ray(&self, i: usize, p: Vec3) -> Option<(Vec3, f32)> {
        let (l, _, dist) = self.lights.get(i).copied().flatten()?.at(p)?;
        Some((
            l,
            if dist.is_finite() {
                dist * (1.0 - 1e-4)
            } else {
                dist
            },
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_surface_facing_the_light_gets_it_and_one_facing_away_does_not() {
        let lights = [Light::Directional {
            direction: [0.0, 1.0, 0.0],
            radiance: [2.0, 2.0, 2.0],
        }];
        let ray = <RayRecord as bytemuck::Zeroable>::zeroed();
        let lit = RayLights::for_ray(Lighting::Shadowed, &lights, &ray);
        let c = Vec3::splat(0.5);
        // Density grows downwards: the outward normal points up, at the light.
        let (ambient, direct) = lit.shade(c, Vec3::ZERO, -Vec3::Y, Vec3::Z);
        assert_eq!(ambient, c * AMBIENT);
        assert_eq!(direct[0], Vec3::ONE);
        let (_, direct) = lit.shade(c, Vec3::ZERO, Vec3::Y, Vec3::Z);
        assert_eq!(direct[0], Vec3::ZERO);
        // A uniform region takes the light whole.
        let (_, direct) = lit.shade(c, Vec3::ZERO, Vec3::ZERO, Vec3::Z);
        assert_eq!(direct[0], Vec3::ONE);
        assert_eq!(
            lit.shadow_ray(0, Vec3::ZERO),
            Some((Vec3::Y, f32::INFINITY))
        );
        assert_eq!(lit.shadow_ray(1, Vec3::ZERO), None);
        let unlit = RayLights::for_ray(Lighting::Unlit, &lights, &ray);
        assert_eq!(
            unlit.shade(c, Vec3::ZERO, -Vec3::Y, Vec3::Z),
            (c, [Vec3::ZERO; 4])
        );
    }

    #[test]
    fn a_quad_light_lights_only_its_front() {
        let lights = [Light::Quad {
            corner: [-1.0, 2.0, -1.0],
            edge_u: [2.0, 0.0, 0.0],
            edge_v: [0.0, 0.0, 2.0],
            emission: [4.0, 4.0, 4.0],
        }];
        let ray = <RayRecord as bytemuck::Zeroable>::zeroed();
        let lit = RayLights::for_ray(Lighting::Lights, &lights, &ray);
        // edge_u x edge_v points down (-y): it lights what lies below it.
        let (l, len) = lit.shadow_ray(0, Vec3::ZERO).unwrap();
        assert!(l.y > 0.0 && len > 1.99 && len < 2.9, "{l} {len}");
        assert!(lit.shadow_ray(0, Vec3::new(0.0, 3.0, 0.0)).is_none());
    }
}
