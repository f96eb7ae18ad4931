//! Routing: which domains a ray crosses, where a new or forwarded ray goes next, and what
//! a ray that meets no more geometry brings.

use std::ops::ControlFlow;

use glam::Vec3;

use super::{RaySink, SceneView};
use crate::geometry::Aabb;
use crate::ray::{RayKind, RayRecord};

impl SceneView {
    /// Visits the domains `ray` crosses, nearest first, with its interval in each.
    pub(super) fn walk(
        &self,
        ray: &RayRecord,
        visit: impl FnMut(u32, f32, f32) -> ControlFlow<()>,
    ) {
        let (origin, dir) = (ray.origin.into(), ray.dir.into());
        self.tree.walk(origin, dir, ray.t_min, ray.t_max, visit);
    }

    /// `ray`'s interval in `domain`, as [`SceneView::walk`] would visit it (`None`: the ray
    /// does not cross it), without walking the domains before it.
    pub(super) fn interval(&self, ray: &RayRecord, domain: u32) -> Option<(f32, f32)> {
        let (origin, dir) = (ray.origin.into(), ray.dir.into());
        self.tree
            .interval(domain, origin, dir, ray.t_min, ray.t_max)
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
    pub(super) fn route_child(&self, ray: RayRecord, here: Option<u32>, sink: &mut impl RaySink) {
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

    pub(super) fn send(&self, mut ray: RayRecord, domain: Option<u32>, sink: &mut impl RaySink) {
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
    pub(super) fn escape(&self, ray: &RayRecord, sink: &mut impl RaySink) {
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
    pub(super) fn segment(
        &self,
        ray: &RayRecord,
        domain: u32,
    ) -> (Option<(f32, f32)>, Option<u32>) {
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

    /// Every domain with geometry along `ray`, nearest first: where a speculative ray is
    /// queued at once.
    pub fn domains_along(&self, ray: &RayRecord) -> Vec<u32> {
        // Sized for the handful of domains most rays cross: grown from empty, a path was
        // reallocated and copied once or twice a ray (2% of the simulator's instructions on
        // big48 at 4 workers).
        let mut out = Vec::with_capacity(self.domain_count().min(8));
        self.walk(ray, |d, _, _| {
            if self.has_triangles[d as usize] {
                out.push(d);
            }
            ControlFlow::Continue(())
        });
        out
    }
}

/// Whether `p` lies strictly inside `b` on every axis.
fn strictly_inside(b: &Aabb, p: [f32; 3]) -> bool {
    (0..3).all(|a| b.min[a] < p[a] && p[a] < b.max[a])
}
