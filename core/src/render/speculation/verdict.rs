//! What one speculative copy found, and its form on the wire ([`VerdictRecord`]).

use super::super::dvr::Segment;
use crate::ray::RayRecord;
use crate::wire::VerdictRecord;

/// What a radiance ray's copy found in its domain: enough to shade the hit later, without
/// the domain's data. Which domain is the copy's: its verdict names it
/// ([`VerdictRecord::HIT`]), and the hit of the nearest domain along the ray with one wins,
/// as domains cut a ray into ordered intervals.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceHit {
    /// Distance of the hit along the ray.
    pub t: f32,
    /// The normal to shade the hit with, on the side the ray came from
    /// (`SceneView::surface_at`: the facet normal, or a smooth surface's shading normal).
    pub normal: [f32; 3],
    /// Material of the triangle hit.
    pub material: u32,
}

/// What one copy found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Verdict {
    /// Nothing in this domain's stretch of the ray.
    Clear,
    /// A shadow ray's occluder in this domain.
    Blocked,
    /// A radiance ray's nearest hit in this domain.
    Hit(SurfaceHit),
    /// One segment a volume ray's copy composited in its brick (not the copy's last verdict).
    Segment(Segment),
    /// The light one segment reflects of one light, to be sent on in a shadow ray.
    Light(SegmentLight),
    /// A radiance ray's nearest hit on the surfaces in a brick (not the copy's last verdict:
    /// the brick's segments in front of it come with it).
    VolumeHit(SurfaceHit),
    /// A volume ray's copy is done: it sent this many [`Verdict::Segment`]s,
    /// [`Verdict::Light`]s and [`Verdict::VolumeHit`]s before.
    VolumeEnd(u32),
}

/// What a shadowed segment reflects of one light (`render::volume_light`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SegmentLight {
    /// The segment's first sample: which segment this belongs to.
    pub first: u32,
    /// The light's index.
    pub light: u32,
    /// The segment's depth along the ray, where the shadow ray leaves.
    pub depth: f32,
    /// Premultiplied colour reflected of this light.
    pub rgb: [f32; 3],
}

/// Most segments one ray may collect from all its copies: a bound on what a peer can make a
/// group hold. The verdict format holds it, since a batch's check needs it.
pub use crate::wire::MAX_SEGMENTS;

impl VerdictRecord {
    /// Kind of a verdict that found nothing: `order` names the copy's domain, so its group
    /// knows which stretch of the ray is clear (it may conclude before farther copies answer).
    /// Every verdict on a stretch of the ray (clear, an occluder, a hit) names it so.
    pub const CLEAR: u8 = 0;
    /// Kind of a verdict that found an occluder: `order` names the copy's domain.
    pub const BLOCKED: u8 = 1;
    /// Kind of a verdict that found a hit: `order` names the copy's domain, `t`, `normal`
    /// and `material` the hit.
    pub const HIT: u8 = 2;
    /// Kind of a volume segment: `order` its first sample, `normal` its premultiplied colour,
    /// `t` its opacity.
    pub const SEGMENT: u8 = 3;
    /// Kind of a volume copy's closing verdict: `material` counts its segments and lights.
    pub const VOLUME_END: u8 = 4;
    /// Kind of a segment's light: `order` the segment's first sample, `material` the light,
    /// `t` the segment's depth, `normal` the premultiplied colour reflected.
    pub const LIGHT: u8 = 5;
    /// Kind of a hit on the surfaces in a brick: the fields of [`VerdictRecord::HIT`].
    pub const VOLUME_HIT: u8 = 6;

    /// `verdict` on `copy`, to go back to the copy's group.
    pub fn new(copy: &RayRecord, verdict: Verdict) -> Self {
        let mut r = VerdictRecord {
            group: copy.group,
            tile: copy.tile,
            epoch: copy.epoch,
            pixel: copy.pixel,
            sample: copy.sample,
            kind: Self::CLEAR,
            _pad: [0; 3],
            order: 0,
            t: 0.0,
            normal: [0.0; 3],
            material: 0,
        };
        match verdict {
            Verdict::Clear => r.order = copy.domain,
            Verdict::Blocked => {
                r.kind = Self::BLOCKED;
                r.order = copy.domain;
            }
            Verdict::Hit(hit) | Verdict::VolumeHit(hit) => {
                r.kind = if matches!(verdict, Verdict::Hit(_)) {
                    Self::HIT
                } else {
                    Self::VOLUME_HIT
                };
                r.order = copy.domain;
                r.t = hit.t;
                r.normal = hit.normal;
                r.material = hit.material;
            }
            Verdict::Segment(seg) => {
                r.kind = Self::SEGMENT;
                r.order = seg.first;
                r.t = seg.alpha;
                r.normal = seg.rgb;
            }
            Verdict::Light(light) => {
                r.kind = Self::LIGHT;
                r.order = light.first;
                r.material = light.light;
                r.t = light.depth;
                r.normal = light.rgb;
            }
            Verdict::VolumeEnd(segments) => {
                r.kind = Self::VOLUME_END;
                r.material = segments;
            }
        }
        r
    }

    /// The verdict carried (an unknown kind, refused by the wire checks, reads as clear).
    pub fn verdict(&self) -> Verdict {
        match self.kind {
            Self::BLOCKED => Verdict::Blocked,
            Self::HIT => Verdict::Hit(SurfaceHit {
                t: self.t,
                normal: self.normal,
                material: self.material,
            }),
            Self::VOLUME_HIT => Verdict::VolumeHit(SurfaceHit {
                t: self.t,
                normal: self.normal,
                material: self.material,
            }),
            Self::SEGMENT => Verdict::Segment(Segment::plain(self.order, self.normal, self.t)),
            Self::LIGHT => Verdict::Light(SegmentLight {
                first: self.order,
                light: self.material,
                depth: self.t,
                rgb: self.normal,
            }),
            Self::VOLUME_END => Verdict::VolumeEnd(self.material),
            _ => Verdict::Clear,
        }
    }
}
