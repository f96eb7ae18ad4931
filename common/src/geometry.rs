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

    /// Extends the box to hold `other`.
    pub fn union(&mut self, other: &Aabb) {
        self.grow(other.min);
        self.grow(other.max);
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

/// A triangle stored ready for intersection: one vertex and two edges, its scene-wide id and
/// material. Every domain that references a triangle stores the same bits, so every domain
/// computes the same hit distance for the same ray.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct PackedTriangle {
    /// First vertex.
    pub v0: [f32; 3],
    /// Low half of the scene-wide triangle id, which breaks ties between equal distances.
    pub id_lo: u32,
    /// `v1 - v0`.
    pub e1: [f32; 3],
    /// Index into the scene's material table.
    pub material: u32,
    /// `v2 - v0`.
    pub e2: [f32; 3],
    /// High half of the scene-wide triangle id.
    pub id_hi: u32,
}

impl PackedTriangle {
    /// Packs a triangle given by its three vertices.
    pub fn new(v: &[[f32; 3]; 3], id: u64, material: u32) -> Self {
        let v0 = Vec3::from(v[0]);
        PackedTriangle {
            v0: v[0],
            id_lo: id as u32,
            e1: (Vec3::from(v[1]) - v0).into(),
            material,
            e2: (Vec3::from(v[2]) - v0).into(),
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
        let v0 = Vec3::from(self.v0);
        [
            self.v0,
            (v0 + Vec3::from(self.e1)).into(),
            (v0 + Vec3::from(self.e2)).into(),
        ]
    }

    /// Unit geometric normal (right-hand rule over v0, v1, v2).
    pub fn normal(&self) -> Vec3 {
        Vec3::from(self.e1)
            .cross(Vec3::from(self.e2))
            .normalize_or(Vec3::Z)
    }

    /// Möller-Trumbore: the distance along `dir` at which the ray meets the triangle, if it does
    /// at a positive distance. A pure function of the ray and this record.
    #[inline(always)]
    pub fn intersect(&self, origin: Vec3, dir: Vec3) -> Option<f32> {
        let t = self.intersect_t(origin, dir);
        (t != f32::INFINITY).then_some(t)
    }

    /// [`Self::intersect`] without branches on the way: infinity when there is no hit, so
    /// traversal pays one comparison per triangle instead of three mispredicted ones.
    #[inline(always)]
    pub fn intersect_t(&self, origin: Vec3, dir: Vec3) -> f32 {
        // Scalar on purpose: the fourth lane of each 16-byte row holds integer bits that read as
        // denormal floats, and SIMD arithmetic on them stalls (masking it is optimised away).
        let (v0, e1, e2) = (
            Vec3::from(self.v0),
            Vec3::from(self.e1),
            Vec3::from(self.e2),
        );
        let p = dir.cross(e2);
        let det = e1.dot(p);
        let inv = 1.0 / det;
        let s = origin - v0;
        let u = s.dot(p) * inv;
        let q = s.cross(e1);
        let v = dir.dot(q) * inv;
        let t = e2.dot(q) * inv;
        let inside = u >= 0.0 && v >= 0.0 && u + v <= 1.0;
        if inside & (det.abs() >= 1e-30) & (t > 0.0) {
            t
        } else {
            f32::INFINITY
        }
    }
}

/// Whether hit `(t, id)` is nearer than `(best_t, best_id)`: distance first, then the lower
/// scene-wide triangle id, so that the winner does not depend on traversal order.
#[inline(always)]
pub fn nearer(t: f32, id: u64, best_t: f32, best_id: u64) -> bool {
    t < best_t || (t == best_t && id < best_id)
}
