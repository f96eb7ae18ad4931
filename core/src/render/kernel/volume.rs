//! Rays through a volume brick: marching and compositing, the shadow rays of lit samples,
//! and surfaces inside a brick (hit or blocking, then shaded behind the volume).

use std::ops::ControlFlow;

use glam::Vec3;

use super::{KernelCounters, RaySink, SceneView};
use crate::bvh::{Bvh, Hit, TraceRay, Traverser};
use crate::ray::{RayKind, RayRecord};
use crate::render::dvr::{self, March, SampleCounts, Segment, VolumeView};
use crate::render::volume_light::{MAX_LIGHTS, RayLights};
use crate::tile::credit::split_path_credit;

impl SceneView {
    /// Marches `rays` through `brick`: each is composited over its interval there, then
    /// retired if it became opaque, else sent on to the next brick that can show anything
    /// (or retired over the sky). With `surfaces` in the brick, a shadow ray they block
    /// brings nothing, and a radiance ray is composited up to the nearest surface it meets
    /// there, exactly, then shaded there behind the volume (`shade_behind_volume`).
    pub(super) fn trace_brick(
        &self,
        volume: &VolumeView,
        (brick, surfaces): (&crate::scene::brick::Brick, Option<Bvh>),
        rays: &[RayRecord],
        sink: &mut impl RaySink,
        counters: &mut KernelCounters,
    ) {
        let skip = volume.transparent_blocks(brick);
        let mut counts = SampleCounts::default();
        let mut traverser = Traverser::new();
        for ray in rays {
            let (interval, next) = self.segment(ray, brick.header.domain);
            let Some((t0, t1)) = interval else {
                self.route_new(*ray, sink);
                continue;
            };
            match ray.kind() {
                RayKind::Radiance => counters.radiance_segments += 1,
                RayKind::Shadow => counters.shadow_segments += 1,
            }
            let mut ray = *ray;
            let line = (Vec3::from(ray.origin), Vec3::from(ray.dir));
            let (hit, end) =
                match surfaces.map(|bvh| (bvh, surface_in(&mut traverser, bvh, &ray, t0, t1))) {
                    Some((_, SurfaceIn::Blocks)) => {
                        sink.retire(&ray, [0.0; 3]);
                        continue;
                    }
                    Some((bvh, SurfaceIn::Hit(h))) => (Some((bvh, h)), h.t),
                    _ => (None, t1),
                };
            let lit = volume.lights_for(&ray);
            let march = volume.march(brick, &skip, line, &lit, t0, end, &mut counts, |segment| {
                if self.fold_segment(volume, &lit, &mut ray, &segment, sink, counters) {
                    ControlFlow::Break(())
                } else {
                    ControlFlow::Continue(())
                }
            });
            match (march, hit) {
                (March::Opaque, _) => self.retire_opaque(&ray, sink),
                (March::Through, Some((bvh, h))) => {
                    let surface = self.surface_at(bvh, &h, &ray);
                    self.shade_behind_volume(&ray, h.t, surface, sink, counters);
                }
                (March::Through, None) => {
                    if next.is_some() {
                        counters.forwarded += 1;
                    }
                    self.send(ray, next, sink);
                }
            }
        }
        counters.volume_samples += counts.taken;
        counters.volume_skipped += counts.skipped;
    }

    /// Folds `segment` into the volume ray `ray` (`dvr::composite`); returns whether the ray
    /// is now opaque. With shadows, first sends a shadow ray from the segment's depth towards
    /// each light it reflects, carrying that light times the ray's transparency in front of
    /// the segment (the one place they are made, chained or speculative: the same bits).
    /// Each takes the least credit; if the ray's credit cannot be split, it sends none.
    pub(super) fn fold_segment(
        &self,
        volume: &VolumeView,
        lit: &RayLights,
        ray: &mut RayRecord,
        segment: &Segment,
        sink: &mut impl RaySink,
        counters: &mut KernelCounters,
    ) -> bool {
        if ray.kind() == RayKind::Radiance && segment.lit_by().next().is_some() {
            let w = 1.0 - ray.volume_alpha;
            let origin = Vec3::from(ray.origin) + Vec3::from(ray.dir) * segment.depth;
            let mut children = [*ray; MAX_LIGHTS];
            let mut made = 0;
            for i in segment.lit_by() {
                let carried = Vec3::from(segment.direct[i]) * w * Vec3::from(ray.throughput);
                let Some((dir, t_max)) = lit.shadow_ray(i, origin) else {
                    continue;
                };
                let shows = carried.max_element() > 0.0;
                if !shows || !origin.is_finite() {
                    continue;
                }
                children[made] = RayRecord {
                    origin: origin.into(),
                    t_min: volume.shadow_bias().min(t_max),
                    dir: dir.into(),
                    t_max,
                    throughput: carried.into(),
                    kind: RayKind::Shadow as u8,
                    volume_rgb: [0.0; 3],
                    volume_alpha: 0.0,
                    ..*ray
                };
                made += 1;
            }
            if made > 0
                && let Ok(split) = split_path_credit(ray.credit, made)
            {
                ray.credit = split.continuation;
                for child in &mut children[..made] {
                    child.credit = split.leaf;
                    counters.shadow_rays += 1;
                    self.route_new(*child, sink);
                }
            }
        }
        dvr::composite(ray, segment)
    }

    /// A volume ray that became opaque: a radiance ray shows its colour, a shadow ray brings
    /// no light.
    pub(super) fn retire_opaque(&self, ray: &RayRecord, sink: &mut impl RaySink) {
        match ray.kind() {
            RayKind::Radiance => {
                let rgb = Vec3::from(ray.volume_rgb) * Vec3::from(ray.throughput);
                sink.retire(ray, rgb.into());
            }
            RayKind::Shadow => sink.retire(ray, [0.0; 3]),
        }
    }

    /// A radiance ray composited up to a surface at `t` in the volume, and not opaque there:
    /// the surface is shaded as if the ray had met it bare, its children carrying the ray's
    /// weight times the volume's transparency in front of it (and starting their own
    /// compositing from nothing), and the ray retires the volume's colour (weighted by its
    /// own throughput) as one more leaf: pixel = volume colour + transparency * surface.
    pub(super) fn shade_behind_volume(
        &self,
        ray: &RayRecord,
        t: f32,
        surface: (Vec3, u32),
        sink: &mut impl RaySink,
        counters: &mut KernelCounters,
    ) {
        let weight = Vec3::from(ray.throughput);
        let behind = RayRecord {
            throughput: (weight * (1.0 - ray.volume_alpha)).into(),
            volume_rgb: [0.0; 3],
            volume_alpha: 0.0,
            ..*ray
        };
        let p = Vec3::from(ray.origin) + Vec3::from(ray.dir) * t;
        let mut children = Vec::with_capacity(self.lights.len() + 1);
        self.shade(&behind, p, surface, &mut children, counters);
        let own = Vec3::from(ray.volume_rgb) * weight;
        if own == Vec3::ZERO {
            self.hand_on_credit(&behind, None, &mut children, sink);
            return;
        }
        // The ray's own report is a leaf: with a bounce, it takes a leaf's share; without,
        // the continuation's (so credit still sums exactly).
        let leaves = children
            .iter()
            .filter(|c| c.kind() == RayKind::Shadow)
            .count();
        let bounce = leaves < children.len();
        match split_path_credit(ray.credit, leaves + usize::from(bounce)) {
            Ok(s) => {
                let own_credit = if bounce { s.leaf } else { s.continuation };
                sink.retire(
                    &RayRecord {
                        credit: own_credit,
                        ..*ray
                    },
                    own.into(),
                );
                for child in &mut children {
                    child.credit = if child.kind() == RayKind::Shadow {
                        s.leaf
                    } else {
                        s.continuation
                    };
                    self.route_new(*child, sink);
                }
            }
            Err(_) => sink.retire(ray, own.into()),
        }
    }
}

/// What the surfaces in a brick do to a ray over its interval `[t0, t1)` there.
pub(super) enum SurfaceIn {
    /// Nothing: the ray goes on through the voxels.
    Clear,
    /// A shadow ray is blocked.
    Blocks,
    /// A radiance ray's nearest hit (ties by triangle id, as in any mesh domain).
    Hit(Hit),
}

/// [`SurfaceIn`] of `ray` over `[t0, t1]` against a brick's surfaces `bvh`.
pub(super) fn surface_in(
    traverser: &mut Traverser,
    bvh: Bvh,
    ray: &RayRecord,
    t0: f32,
    t1: f32,
) -> SurfaceIn {
    let tr = TraceRay::new(Vec3::from(ray.origin), Vec3::from(ray.dir));
    match ray.kind() {
        RayKind::Shadow if traverser.any_hit(bvh, &tr, t0, t1) => SurfaceIn::Blocks,
        RayKind::Shadow => SurfaceIn::Clear,
        RayKind::Radiance => match traverser.nearest_hit(bvh, &tr, t0, t1) {
            Some(h) => SurfaceIn::Hit(h),
            None => SurfaceIn::Clear,
        },
    }
}
