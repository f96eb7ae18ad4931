//! Speculative copies: one copy of a ray traced against one domain alone, its verdicts
//! sent back, and the ray concluded once all its copies are in.

use std::ops::ControlFlow;

use glam::Vec3;

use super::volume::{SurfaceIn, surface_in};
use super::{CopyScratch, KernelCounters, RaySink, SceneView};
use crate::bvh::TraceRay;
use crate::ray::{RayKind, RayRecord};
use crate::render::dvr::{SampleCounts, Segment};
use crate::render::speculation::{Outcome, SegmentLight, SurfaceHit, Verdict};
use crate::render::volume_light::MAX_LIGHTS;
use crate::scene::DomainData;

impl SceneView {
    /// Traces one speculative copy of a ray against its domain `data` alone and pushes what
    /// it found to `out`: one verdict for a surface domain; for a brick, its composited
    /// segments and a closing verdict counting them. Nothing moves on: the verdicts go back
    /// to where the ray was born.
    pub fn trace_copy(
        &self,
        data: &DomainData,
        ray: &RayRecord,
        scratch: &mut CopyScratch,
        counters: &mut KernelCounters,
        out: &mut Vec<Verdict>,
    ) {
        let domain = data.domain();
        // A copy queued for a domain off its path finds nothing there.
        let Some((t0, t1)) = self.interval(ray, domain) else {
            out.push(Verdict::Clear);
            return;
        };
        if let Some(brick) = data.brick() {
            let Some(volume) = &self.volume else {
                out.push(Verdict::Clear);
                return;
            };
            match ray.kind() {
                RayKind::Radiance => counters.radiance_segments += 1,
                RayKind::Shadow => counters.shadow_segments += 1,
            }
            if scratch.skip.as_ref().is_none_or(|(d, _)| *d != domain) {
                scratch.skip = Some((domain, volume.transparent_blocks(&brick)));
            }
            let skip = scratch.skip.as_ref().map_or(&[][..], |(_, s)| s.as_slice());
            let line = (Vec3::from(ray.origin), Vec3::from(ray.dir));
            // Surfaces in the brick, as the chained trace meets them (`trace_brick`).
            let surfaces = data.surfaces().map(DomainData::bvh);
            let mut end = t1;
            let mut hit = None;
            match surfaces.map(|bvh| (bvh, surface_in(&mut scratch.traverser, bvh, ray, t0, t1))) {
                Some((_, SurfaceIn::Blocks)) => {
                    out.push(Verdict::Blocked);
                    return;
                }
                Some((bvh, SurfaceIn::Hit(h))) => {
                    let (normal, material) = self.surface_at(bvh, &h, ray);
                    end = h.t;
                    hit = Some(SurfaceHit {
                        t: h.t,
                        normal: normal.into(),
                        material,
                    });
                }
                _ => {}
            }
            let mut counts = SampleCounts::default();
            let before = out.len();
            let lit = volume.lights_for(ray);
            volume.march(&brick, skip, line, &lit, t0, end, &mut counts, |segment| {
                out.push(Verdict::Segment(segment));
                for light in segment.lit_by() {
                    out.push(Verdict::Light(SegmentLight {
                        first: segment.first,
                        light: light as u32,
                        depth: segment.depth,
                        rgb: segment.direct[light],
                    }));
                }
                ControlFlow::Continue(())
            });
            if let Some(hit) = hit {
                out.push(Verdict::VolumeHit(hit));
            }
            let segments = (out.len() - before) as u32;
            out.push(Verdict::VolumeEnd(segments));
            counters.volume_samples += counts.taken;
            counters.volume_skipped += counts.skipped;
            return;
        }
        let traverser = &mut scratch.traverser;
        let tr = TraceRay::new(Vec3::from(ray.origin), Vec3::from(ray.dir));
        let bvh = data.bvh();
        let verdict = match ray.kind() {
            RayKind::Shadow => {
                counters.shadow_segments += 1;
                if traverser.any_hit(bvh, &tr, t0, t1) {
                    Verdict::Blocked
                } else {
                    Verdict::Clear
                }
            }
            RayKind::Radiance => {
                counters.radiance_segments += 1;
                match traverser.nearest_hit(bvh, &tr, t0, t1) {
                    Some(hit) => {
                        let (normal, material) = self.surface_at(bvh, &hit, ray);
                        Verdict::Hit(SurfaceHit {
                            t: hit.t,
                            normal: normal.into(),
                            material,
                        })
                    }
                    None => Verdict::Clear,
                }
            }
        };
        out.push(verdict);
    }

    /// Finishes a speculative ray once all its copies are in: exactly what tracing it one
    /// domain at a time would have done, since a shadow ray is blocked if any domain blocks it
    /// and a radiance ray stops in the nearest domain along it that it hits.
    pub fn conclude(
        &self,
        ray: &RayRecord,
        outcome: &Outcome,
        sink: &mut impl RaySink,
        counters: &mut KernelCounters,
    ) {
        if let Some(volume) = &self.volume {
            if outcome.blocked {
                // A surface in the volume blocks this shadow ray.
                sink.retire(ray, [0.0; 3]);
                return;
            }
            // The segments of every brick, in order along the ray, each with the light it
            // reflects of each light: the chained trace's fold. With a surface hit, only
            // those in front of it: the hit's brick composited up to it, the bricks behind
            // it hold samples at or beyond it (the chained trace never reaches them).
            let mut ray = *ray;
            let lit = volume.lights_for(&ray);
            let mut lights = outcome.lights.iter().peekable();
            let in_front = |s: &&Segment| {
                outcome
                    .nearest
                    .is_none_or(|h| volume.sample_t(s.first) < h.t)
            };
            for segment in outcome.segments.iter().filter(in_front) {
                let mut segment = *segment;
                while let Some(l) = lights.next_if(|l| l.first <= segment.first) {
                    if l.first == segment.first && (l.light as usize) < MAX_LIGHTS {
                        segment.direct[l.light as usize] = l.rgb;
                        segment.depth = l.depth;
                    }
                }
                if self.fold_segment(volume, &lit, &mut ray, &segment, sink, counters) {
                    self.retire_opaque(&ray, sink);
                    return;
                }
            }
            match outcome.nearest {
                Some(h) => {
                    let surface = (Vec3::from(h.normal), h.material);
                    self.shade_behind_volume(&ray, h.t, surface, sink, counters);
                }
                None => self.escape(&ray, sink),
            }
            return;
        }
        match (ray.kind(), outcome.nearest) {
            (RayKind::Shadow, _) if outcome.blocked => sink.retire(ray, [0.0; 3]),
            (RayKind::Radiance, Some(hit)) => {
                let (origin, dir) = (Vec3::from(ray.origin), Vec3::from(ray.dir));
                let mut children = Vec::with_capacity(self.lights.len() + 1);
                let surface = (Vec3::from(hit.normal), hit.material);
                self.shade(ray, origin + dir * hit.t, surface, &mut children, counters);
                self.hand_on_credit(ray, None, &mut children, sink);
            }
            _ => self.escape(ray, sink),
        }
    }
}
