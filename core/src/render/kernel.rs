//! The render kernel: given a loaded domain and rays queued for it, each ray is forwarded to
//! the next domain along it, retired (adding its light to its pixel), or hits and is shaded
//! (spawning shadow rays towards the lights and a bounce). Rays carry their own contribution,
//! so nothing ever travels back to where a ray was born.
//!
//! This file traces a surface domain's queue (camera rays as packets, the others one at a
//! time); routing between domains is in `route`, shading in `shade`, volume bricks in
//! `volume`, speculative copies in `copy`.

use glam::Vec3;

use super::dvr::VolumeView;
use crate::bvh::{Bvh, Hit, PACKET, TraceRay, Traverser};
use crate::geometry::Aabb;
use crate::ray::{RayKind, RayRecord};
use crate::scene::{DomainData, DomainTree, Light, Manifest, Material, Sky};

mod copy;
mod route;
mod shade;
mod volume;

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
}
