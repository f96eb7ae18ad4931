//! The render kernel: given a loaded domain and rays queued for it, each ray is forwarded to
//! the next domain along it, retired (adding its light to its pixel), or hits and is shaded
//! (spawning shadow rays towards the lights and a bounce). Rays carry their own contribution,
//! so nothing ever travels back to where a ray was born.

use std::ops::ControlFlow;

use glam::Vec3;

use super::dvr::{self, March, SampleCounts, Segment, VolumeView};
use super::speculation::{Outcome, SegmentLight, SurfaceHit, Verdict};
use super::volume_light::{MAX_LIGHTS, RayLights};
use crate::bvh::{Bvh, Hit, PACKET, TraceRay, Traverser};
use crate::geometry::Aabb;
use crate::ray::{RayKind, RayRecord};
use crate::scene::{DomainData, DomainTree, Light, Manifest, Material, Sky};
use crate::tile::credit::split_path_credit;

mod shade;

/// Where the kernel puts its results.
pub trait RaySink {
    /// A ray that continues in domain `ray.domain`.
    fn push(&mut self, ray: RayRecord);
    /// A ray ends here: `rgb` (possibly black) goes to its pixel and `ray.credit` back to its tile.
    fn retire(&mut self, ray: &RayRecord, rgb: [f32; 3]);
}

/// Counts kept by the kernel; summed across threads and processes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct KernelCounters {
    /// Radiance-ray segments traced against a domain.
    pub radiance_segments: u64,
    /// Shadow-ray segments traced against a domain.
    pub shadow_segments: u64,
    /// Camera rays created.
    pub primary_rays: u64,
    /// Shadow rays created.
    pub shadow_rays: u64,
    /// Diffuse and glossy bounce rays created.
    pub bounce_rays: u64,
    /// Mirror reflection rays created.
    pub reflection_rays: u64,
    /// Rays moved on to another domain after finding nothing in theirs.
    pub forwarded: u64,
    /// Volume samples interpolated and composited.
    #[serde(default)]
    pub volume_samples: u64,
    /// Volume samples skipped in sub-blocks the transfer function makes transparent.
    #[serde(default)]
    pub volume_skipped: u64,
}

impl KernelCounters {
    /// Adds `other` into `self`.
    pub fn add(&mut self, other: &KernelCounters) {
        self.radiance_segments += other.radiance_segments;
        self.shadow_segments += other.shadow_segments;
        self.primary_rays += other.primary_rays;
        self.shadow_rays += other.shadow_rays;
        self.bounce_rays += other.bounce_rays;
        self.reflection_rays += other.reflection_rays;
        self.forwarded += other.forwarded;
        self.volume_samples += other.volume_samples;
        self.volume_skipped += other.volume_skipped;
    }

    /// Ray segments traced, of both kinds.
    pub fn segments(&self) -> u64 {
        self.radiance_segments + self.shadow_segments
    }
}

/// What tracing speculative copies keeps between copies on one thread: the BVH traverser's
/// stack and the last brick's transparent sub-blocks.
#[derive(Default)]
pub struct CopyScratch {
    traverser: Traverser,
    skip: Option<(u32, Vec<bool>)>,
}

impl CopyScratch {
    /// Nothing kept yet.
    pub fn new() -> Self {
        Self::default()
    }
}

/// Camera rays of one queue waiting to be traced together (at most [`PACKET`]): the rays, their
/// prepared forms, intervals in this domain and the next domain after it.
struct CameraPacket {
    len: usize,
    /// The domain being traced (where a hit's children start).
    domain: u32,
    rays: [RayRecord; PACKET],
    trace: [TraceRay; PACKET],
    t0: [f32; PACKET],
    t1: [f32; PACKET],
    next: [Option<u32>; PACKET],
}

impl Default for CameraPacket {
    fn default() -> Self {
        let tr = TraceRay::new(Vec3::ZERO, Vec3::Z);
        CameraPacket {
            len: 0,
            domain: 0,
            rays: [bytemuck::Zeroable::zeroed(); PACKET],
            trace: [tr; PACKET],
            t0: [0.0; PACKET],
            t1: [0.0; PACKET],
            next: [None; PACKET],
        }
    }
}

impl CameraPacket {
    fn add(&mut self, ray: &RayRecord, trace: TraceRay, (t0, t1): (f32, f32), next: Option<u32>) {
        let i = self.len;
        self.rays[i] = *ray;
        self.trace[i] = trace;
        self.t0[i] = t0;
        self.t1[i] = t1;
        self.next[i] = next;
        self.len += 1;
    }
}

/// The replicated part of a scene the kernel needs besides the domain being traced.
#[derive(Clone, Debug)]
pub struct SceneView {
    tree: DomainTree,
    /// Per domain: whether a ray can meet anything in it (triangles; for a brick, a value the
    /// transfer function does not make transparent). Rays walk past the others unloaded.
    has_triangles: Vec<bool>,
    /// Per domain, its box in the domain tree (the region its planes bound).
    boxes: Vec<Aabb>,
    volume: Option<VolumeView>,
    materials: Vec<Material>,
    lights: Vec<Light>,
    sky: Sky,
    epsilon: f32,
    max_depth: u16,
}

impl SceneView {
    /// The view of `manifest` for paths of at most `max_depth` bounces.
    pub fn new(manifest: &Manifest, max_depth: u16) -> Self {
        let volume = manifest
            .volume
            .as_ref()
            .map(|v| VolumeView::new(v, &manifest.lights));
        let has_triangles = manifest
            .domains
            .iter()
            .map(|d| match (&volume, d.values) {
                // A brick with surfaces in it is visited even where its voxels show nothing.
                (Some(v), Some(values)) => !v.transparent(values) || d.triangles > 0,
                _ => d.triangles > 0,
            })
            .collect();
        let tree = manifest.domain_tree();
        SceneView {
            boxes: tree.domain_boxes(manifest.domains.len()),
            tree,
            has_triangles,
            volume,
            materials: manifest.materials.clone(),
            lights: manifest.lights.clone(),
            sky: manifest.sky,
            epsilon: manifest.ray_epsilon,
            max_depth,
        }
    }

    /// Whether this is a volume scene (direct volume rendering, no surfaces).
    pub fn is_volume(&self) -> bool {
        self.volume.is_some()
    }

    /// Turns empty-space skipping inside bricks off or on (to measure what it saves; the
    /// image is the same either way).
    pub fn set_volume_skipping(&mut self, on: bool) {
        if let Some(v) = &mut self.volume {
            v.skipping = on;
        }
    }

    /// Each domain's place in the order rays from `point` meet domains (the camera's eye:
    /// camera rays), by domain id (`DomainTree::front_to_back`).
    pub fn front_to_back(&self, point: [f32; 3]) -> Vec<u32> {
        self.tree.front_to_back(point, self.domain_count())
    }

    /// Number of domains.
    pub fn domain_count(&self) -> usize {
        self.has_triangles.len()
    }

    /// Visits the domains `ray` crosses, nearest first, with its interval in each.
    fn walk(&self, ray: &RayRecord, visit: impl FnMut(u32, f32, f32) -> ControlFlow<()>) {
        let (origin, dir) = (ray.origin.into(), ray.dir.into());
        self.tree.walk(origin, dir, ray.t_min, ray.t_max, visit);
    }

    /// Sends a new ray to the first domain along it, or retires it at once if it meets none.
    pub fn route_new(&self, ray: RayRecord, sink: &mut impl RaySink) {
        let mut first = None;
        self.walk(&ray, |d, _, _| {
            if self.has_triangles[d as usize] {
                first = Some(d);
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        });
        self.send(ray, first, sink);
    }

    /// Sends on a child born at a hit in domain `here` (none: a concluded speculative ray).
    /// The walk of [`SceneView::route_new`] is skipped when its answer is known: a ray that
    /// starts at `t = 0` strictly inside `here`'s box (on no plane of the domain tree) meets
    /// `here` first, over an interval that starts at 0 and is not empty, whatever its
    /// direction; `here` has geometry (it was hit). The walk when the ray is traced gives its
    /// interval, as before. Half the walks of a frame were these.
    fn route_child(&self, ray: RayRecord, here: Option<u32>, sink: &mut impl RaySink) {
        if let Some(d) = here
            && ray.t_min == 0.0
            && ray.t_max > 0.0
            && self.has_triangles[d as usize]
            && strictly_inside(&self.boxes[d as usize], ray.origin)
        {
            self.send(ray, Some(d), sink);
        } else {
            self.route_new(ray, sink);
        }
    }

    fn send(&self, mut ray: RayRecord, domain: Option<u32>, sink: &mut impl RaySink) {
        match domain {
            Some(d) => {
                ray.domain = d;
                sink.push(ray);
            }
            None => self.escape(&ray, sink),
        }
    }

    /// A ray that meets no more geometry: a shadow ray delivers its light, a radiance ray
    /// sees the sky.
    fn escape(&self, ray: &RayRecord, sink: &mut impl RaySink) {
        let t = Vec3::from(ray.throughput);
        let light = match ray.kind() {
            // Through a volume, what its opacity lets pass.
            RayKind::Shadow if self.volume.is_some() => t * (1.0 - ray.volume_alpha),
            RayKind::Shadow => t,
            RayKind::Radiance => {
                let up = Vec3::from(ray.dir).y.clamp(0.0, 1.0);
                let sky = t * Vec3::from(self.sky.horizon).lerp(Vec3::from(self.sky.zenith), up);
                if self.volume.is_some() {
                    // The volume's colour over what shows through it (the path's weight
                    // applies to both: a bounce off a surface sees the volume too).
                    Vec3::from(ray.volume_rgb) * t + sky * (1.0 - ray.volume_alpha)
                } else {
                    sky
                }
            }
        };
        sink.retire(ray, light.into());
    }

    /// This ray's interval in `domain`, and the next domain with geometry after it.
    fn segment(&self, ray: &RayRecord, domain: u32) -> (Option<(f32, f32)>, Option<u32>) {
        let mut interval = None;
        let mut next = None;
        self.walk(ray, |d, a, b| {
            if interval.is_some() {
                if self.has_triangles[d as usize] {
                    next = Some(d);
                    return ControlFlow::Break(());
                }
            } else if d == domain {
                interval = Some((a, b));
            }
            ControlFlow::Continue(())
        });
        (interval, next)
    }

    /// Traces `rays` (all queued for `data`'s domain) and sends every outcome to `sink`.
    pub fn trace(
        &self,
        data: &DomainData,
        rays: &[RayRecord],
        sink: &mut impl RaySink,
        counters: &mut KernelCounters,
    ) {
        if let (Some(volume), Some(brick)) = (&self.volume, data.brick()) {
            let surfaces = data.surfaces().map(DomainData::bvh);
            self.trace_brick(volume, (&brick, surfaces), rays, sink, counters);
            return;
        }
        let bvh = data.bvh();
        let mut traverser = Traverser::new();
        let mut children = Vec::with_capacity(self.lights.len() + 1);
        let mut camera = CameraPacket {
            domain: data.domain(),
            ..CameraPacket::default()
        };
        let packets = traverser.packets();
        for ray in rays {
            let (interval, next) = self.segment(ray, data.domain());
            // Camera rays queue in pixel order: neighbours, traced together. Any other ray
            // finishes the packet first, so outcomes leave in queue order. (Shadow rays are
            // traced alone: as packets they took 11% more instructions per ray; README.)
            let joins_camera =
                packets && interval.is_some() && ray.kind() == RayKind::Radiance && ray.depth == 0;
            if !joins_camera {
                self.flush(
                    bvh,
                    &mut traverser,
                    &mut camera,
                    &mut children,
                    sink,
                    counters,
                );
            }
            let Some((t0, t1)) = interval else {
                // Not on this ray's path (a stale or foreign ray): start it over.
                self.route_new(*ray, sink);
                continue;
            };
            let origin = Vec3::from(ray.origin);
            let dir = Vec3::from(ray.dir);
            let tr = TraceRay::new(origin, dir);
            match ray.kind() {
                RayKind::Radiance if joins_camera => {
                    camera.add(ray, tr, (t0, t1), next);
                    if camera.len == PACKET {
                        self.flush(
                            bvh,
                            &mut traverser,
                            &mut camera,
                            &mut children,
                            sink,
                            counters,
                        );
                    }
                }
                RayKind::Shadow => {
                    let blocked = traverser.any_hit(bvh, &tr, t0, t1);
                    self.shadow_done(ray, blocked, next, sink, counters);
                }
                RayKind::Radiance => {
                    let hit = traverser.nearest_hit(bvh, &tr, t0, t1);
                    let here = data.domain();
                    self.radiance_done(bvh, here, ray, hit, next, &mut children, sink, counters);
                }
            }
        }
        self.flush(
            bvh,
            &mut traverser,
            &mut camera,
            &mut children,
            sink,
            counters,
        );
    }

    /// Traces the camera rays gathered in `packet`, if any (checked here, inlined: most rays
    /// are not camera rays and must not pay a call for an empty packet).
    #[inline(always)]
    fn flush(
        &self,
        bvh: Bvh,
        traverser: &mut Traverser,
        packet: &mut CameraPacket,
        children: &mut Vec<RayRecord>,
        sink: &mut impl RaySink,
        counters: &mut KernelCounters,
    ) {
        if packet.len != 0 {
            self.trace_packet(bvh, traverser, packet, children, sink, counters);
        }
    }

    /// Traces the camera rays gathered in `packet` together and finishes each, in queue order.
    #[inline(never)]
    fn trace_packet(
        &self,
        bvh: Bvh,
        traverser: &mut Traverser,
        packet: &mut CameraPacket,
        children: &mut Vec<RayRecord>,
        sink: &mut impl RaySink,
        counters: &mut KernelCounters,
    ) {
        let n = packet.len;
        packet.len = 0;
        let mut hits = [None; PACKET];
        traverser.nearest_hits(
            bvh,
            &packet.trace[..n],
            &packet.t0[..n],
            &packet.t1[..n],
            &mut hits[..n],
        );
        for (i, hit) in hits[..n].iter().enumerate() {
            let next = packet.next[i];
            let ray = &packet.rays[i];
            self.radiance_done(
                bvh,
                packet.domain,
                ray,
                *hit,
                next,
                children,
                sink,
                counters,
            );
        }
    }

    /// A shadow ray traced through this domain: retired dark if blocked (its credit still goes
    /// home), else sent on to `next` (or it delivers its light).
    #[inline(always)]
    fn shadow_done(
        &self,
        ray: &RayRecord,
        blocked: bool,
        next: Option<u32>,
        sink: &mut impl RaySink,
        counters: &mut KernelCounters,
    ) {
        counters.shadow_segments += 1;
        if blocked {
            sink.retire(ray, [0.0; 3]);
            return;
        }
        if next.is_some() {
            counters.forwarded += 1;
        }
        self.send(*ray, next, sink);
    }

    /// A radiance ray traced through domain `here`: shaded where it hit, else sent on to `next`
    /// (or the sky).
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn radiance_done(
        &self,
        bvh: Bvh,
        here: u32,
        ray: &RayRecord,
        hit: Option<Hit>,
        next: Option<u32>,
        children: &mut Vec<RayRecord>,
        sink: &mut impl RaySink,
        counters: &mut KernelCounters,
    ) {
        counters.radiance_segments += 1;
        match hit {
            Some(hit) => {
                children.clear();
                let surface = self.surface_at(bvh, &hit, ray);
                let p = Vec3::from(ray.origin) + Vec3::from(ray.dir) * hit.t;
                self.shade(ray, p, surface, children, counters);
                self.hand_on_credit(ray, Some(here), children, sink);
            }
            None => {
                if next.is_some() {
                    counters.forwarded += 1;
                }
                self.send(*ray, next, sink);
            }
        }
    }

    /// Marches `rays` through `brick`: each is composited over its interval there, then
    /// retired if it became opaque, else sent on to the next brick that can show anything
    /// (or retired over the sky). With `surfaces` in the brick, a shadow ray they block
    /// brings nothing, and a radiance ray is composited up to the nearest surface it meets
    /// there, exactly, then shaded there behind the volume (`shade_behind_volume`).
    fn trace_brick(
        &self,
        volume: &VolumeView,
        (brick, surfaces): (&crate::brick::Brick, Option<Bvh>),
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
    fn fold_segment(
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
    fn retire_opaque(&self, ray: &RayRecord, sink: &mut impl RaySink) {
        match ray.kind() {
            RayKind::Radiance => {
                let rgb = Vec3::from(ray.volume_rgb) * Vec3::from(ray.throughput);
                sink.retire(ray, rgb.into());
            }
            RayKind::Shadow => sink.retire(ray, [0.0; 3]),
        }
    }

    /// Every domain with geometry along `ray`, nearest first: where a speculative ray is
    /// queued at once.
    pub fn domains_along(&self, ray: &RayRecord) -> Vec<u32> {
        let mut out = Vec::new();
        self.walk(ray, |d, _, _| {
            if self.has_triangles[d as usize] {
                out.push(d);
            }
            ControlFlow::Continue(())
        });
        out
    }

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
        let mut order = 0u32;
        let mut interval = None;
        self.walk(ray, |d, a, b| {
            if d == data.domain() {
                interval = Some((a, b));
                return ControlFlow::Break(());
            }
            if self.has_triangles[d as usize] {
                order += 1;
            }
            ControlFlow::Continue(())
        });
        // A copy queued for a domain off its path finds nothing there.
        let Some((t0, t1)) = interval else {
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
            let domain = data.domain();
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
                    out.push(Verdict::Blocked(order));
                    return;
                }
                Some((bvh, SurfaceIn::Hit(h))) => {
                    let (normal, material) = self.surface_at(bvh, &h, ray);
                    end = h.t;
                    hit = Some(SurfaceHit {
                        order,
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
                    Verdict::Blocked(order)
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
                            order,
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

    /// A radiance ray composited up to a surface at `t` in the volume, and not opaque there:
    /// the surface is shaded as if the ray had met it bare, its children carrying the ray's
    /// weight times the volume's transparency in front of it (and starting their own
    /// compositing from nothing), and the ray retires the volume's colour (weighted by its
    /// own throughput) as one more leaf: pixel = volume colour + transparency * surface.
    fn shade_behind_volume(
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
enum SurfaceIn {
    /// Nothing: the ray goes on through the voxels.
    Clear,
    /// A shadow ray is blocked.
    Blocks,
    /// A radiance ray's nearest hit (ties by triangle id, as in any mesh domain).
    Hit(Hit),
}

fn surface_in(traverser: &mut Traverser, bvh: Bvh, ray: &RayRecord, t0: f32, t1: f32) -> SurfaceIn {
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

/// Whether `p` lies strictly inside `b` on every axis.
fn strictly_inside(b: &Aabb, p: [f32; 3]) -> bool {
    (0..3).all(|a| b.min[a] < p[a] && p[a] < b.max[a])
}
