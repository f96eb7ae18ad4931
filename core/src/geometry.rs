//! Axis-aligned boxes and the one ray-triangle test every part of rayfarm agrees on.

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use serde::{Deserialize, Serialize};

/// An axis-aligned box, closed on every side.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable, Serialize, Deserialize)]
pub struct Aabb {
    /// Smallest corner.
    pub min: [f32; 3],
    /// Largest corner.
    pub max: [f32; 3],
}

impl Aabb {
    /// The empty box: growing it by any point gives that point.
    pub const EMPTY: Aabb = Aabb {
        min: [f32::INFINITY; 3],
        max: [f32::NEG_INFINITY; 3],
    };

    /// The smallest box holding the three points.
    pub fn of_triangle(v: &[[f32; 3]; 3]) -> Aabb {
        let mut b = Aabb::EMPTY;
        for p in v {
            b.grow(*p);
        }
        b
    }

    /// Extends the box to hold `p`.
    pub fn grow(&mut self, p: [f32; 3]) {
        self.min = (Vec3::from(self.min).min(Vec3::from(p))).into();
        self.max = (Vec3::from(self.max).max(Vec3::from(p))).into();
    }

    /// Whether the box holds nothing.
    pub fn is_empty(&self) -> bool {
        (0..3).any(|a| self.min[a] > self.max[a])
    }

    /// Whether the two closed boxes share at least one point.
    pub fn overlaps(&self, other: &Aabb) -> bool {
        (0..3).all(|a| self.min[a] <= other.max[a] && other.min[a] <= self.max[a])
    }

    /// The box grown by `margin` on every side.
    pub fn expanded(&self, margin: f32) -> Aabb {
        Aabb {
            min: self.min.map(|v| v - margin),
            max: self.max.map(|v| v + margin),
        }
    }

    /// Length of the diagonal.
    pub fn diagonal(&self) -> f32 {
        (Vec3::from(self.max) - Vec3::from(self.min)).length()
    }

    /// The axis along which the box is longest.
    pub fn longest_axis(&self) -> usize {
        let e = Vec3::from(self.max) - Vec3::from(self.min);
        if e.x >= e.y && e.x >= e.z {
            0
        } else if e.y >= e.z {
            1
        } else {
            2
        }
    }

    /// Center point.
    pub fn center(&self) -> [f32; 3] {
        ((Vec3::from(self.min) + Vec3::from(self.max)) * 0.5).into()
    }
}

/// A triangle stored ready for intersection: its three vertices exactly as the mesh gives
/// them (so neighbours share edge bits and the watertight test leaves no cracks), its
/// scene-wide id and material. Every domain that references a triangle stores the same bits,
/// so every domain computes the same hit distance for the same ray.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct PackedTriangle {
    /// First vertex.
    pub v0: [f32; 3],
    /// Low half of the scene-wide triangle id, which breaks ties between equal distances.
    pub id_lo: u32,
    /// Second vertex.
    pub v1: [f32; 3],
    /// Index into the scene's material table.
    pub material: u32,
    /// Third vertex.
    pub v2: [f32; 3],
    /// High half of the scene-wide triangle id.
    pub id_hi: u32,
}

/// A ray transformed for the watertight test (Woop, Benthin and Wald, JCGT 2013): the
/// dominant direction axis becomes z and the ray is sheared onto it, so each triangle edge is
/// tested with the same arithmetic from both of its triangles.
#[derive(Clone, Copy, Debug)]
pub struct ShearedRay {
    origin: Vec3,
    axes: [usize; 3],
    shear: Vec3,
}

impl ShearedRay {
    /// Prepares `origin + t * dir`; `dir` must not be zero.
    #[inline]
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        let a = dir.abs();
        let kz = if a.x >= a.y && a.x >= a.z {
            0
        } else if a.y >= a.z {
            1
        } else {
            2
        };
        let (mut kx, mut ky) = ((kz + 1) % 3, (kz + 2) % 3);
        // Keep the winding: a negative dominant component mirrors the projection.
        if dir[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
        ShearedRay {
            origin,
            axes: [kx, ky, kz],
            shear: Vec3::new(dir[kx] / dir[kz], dir[ky] / dir[kz], 1.0 / dir[kz]),
        }
    }
}

impl PackedTriangle {
    /// Packs a triangle given by its three vertices.
    pub fn new(v: &[[f32; 3]; 3], id: u64, material: u32) -> Self {
        PackedTriangle {
            v0: v[0],
            id_lo: id as u32,
            v1: v[1],
            material,
            v2: v[2],
            id_hi: (id >> 32) as u32,
        }
    }

    /// Scene-wide triangle id.
    #[inline(always)]
    pub fn id(&self) -> u64 {
        ((self.id_hi as u64) << 32) | self.id_lo as u64
    }

    /// The three vertices.
    pub fn vertices(&self) -> [[f32; 3]; 3] {
        [self.v0, self.v1, self.v2]
    }

    /// Unit geometric normal (right-hand rule over v0, v1, v2).
    pub fn normal(&self) -> Vec3 {
        let v0 = Vec3::from(self.v0);
        (Vec3::from(self.v1) - v0)
            .cross(Vec3::from(self.v2) - v0)
            .normalize_or(Vec3::Z)
    }

    /// The distance along `dir` at which the ray meets the triangle, if it does at a positive
    /// distance. A pure function of the ray and this record.
    #[inline(always)]
    pub fn intersect(&self, origin: Vec3, dir: Vec3) -> Option<f32> {
        let t = self.intersect_t(&ShearedRay::new(origin, dir));
        (t != f32::INFINITY).then_some(t)
    }

    /// The watertight test: infinity when there is no hit. A ray through a shared edge or
    /// vertex hits at least one of the triangles that share it.
    #[inline(always)]
    pub fn intersect_t(&self, r: &ShearedRay) -> f32 {
        let [kx, ky, kz] = r.axes;
        let s = r.shear;
        // Vertices relative to the origin, sheared into the ray's space.
        let a = Vec3::from(self.v0) - r.origin;
        let b = Vec3::from(self.v1) - r.origin;
        let c = Vec3::from(self.v2) - r.origin;
        let (ax, ay) = (a[kx] - s.x * a[kz], a[ky] - s.y * a[kz]);
        let (bx, by) = (b[kx] - s.x * b[kz], b[ky] - s.y * b[kz]);
        let (cx, cy) = (c[kx] - s.x * c[kz], c[ky] - s.y * c[kz]);
        let mut u = cx * by - cy * bx;
        let mut v = ax * cy - ay * cx;
        let mut w = bx * ay - by * ax;
        // An exact zero may be rounding: decide the edge in double precision.
        if u == 0.0 || v == 0.0 || w == 0.0 {
            let d =
                |p: f32, q: f32, m: f32, n: f32| (p as f64 * q as f64 - m as f64 * n as f64) as f32;
            u = d(cx, by, cy, bx);
            v = d(ax, cy, ay, cx);
            w = d(bx, ay, by, ax);
        }
        if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
            return f32::INFINITY;
        }
        let det = u + v + w;
        if det == 0.0 {
            return f32::INFINITY;
        }
        let t_scaled = u * (s.z * a[kz]) + v * (s.z * b[kz]) + w * (s.z * c[kz]);
        // Same sign as det means a positive distance.
        if (det > 0.0 && t_scaled <= 0.0) || (det < 0.0 && t_scaled >= 0.0) {
            return f32::INFINITY;
        }
        t_scaled / det
    }
}

/// Whether hit `(t, id)` is nearer than `(best_t, best_id)`: distance first, then the lower
/// scene-wide triangle id, so that the winner does not depend on traversal order.
#[inline(always)]
pub fn nearer(t: f32, id: u64, best_t: f32, best_id: u64) -> bool {
    t < best_t || (t == best_t && id < best_id)
}
