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

/// One triangle as a record: its three vertices exactly as the mesh gives them (so neighbours
/// share edge bits and the watertight test leaves no cracks), its scene-wide id and material.
/// The input of the BVH build, and what a hit's lane of a [`TriangleBlock`] reads back as for
/// shading ([`crate::bvh::Bvh::triangle`]); domain files store triangles only in blocks. Every
/// domain that references a triangle stores the same bits, so every domain computes the same
/// hit distance for the same ray.
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
    /// The origin in the ray's axes: `origin[axes[i]]` for i = 0, 1, 2, permuted once here
    /// rather than per triangle or per traversal (the subtractions from a vertex are the
    /// same per coordinate either way).
    origin: [f32; 3],
    /// The axes that become x, y and z: a permutation of 0, 1, 2 (made only by
    /// [`ShearedRay::new`], so the tests may index with them unchecked).
    axes: [usize; 3],
    shear: Vec3,
}

impl ShearedRay {
    /// Prepares `origin + t * dir`; `dir` must not be zero.
    #[inline]
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        let a = dir.abs();
        let d = dir.to_array();
        let (kz, mut kx, mut ky) = if a.x >= a.y && a.x >= a.z {
            (0, 1, 2)
        } else if a.y >= a.z {
            (1, 2, 0)
        } else {
            (2, 0, 1)
        };
        // Keep the winding: a negative dominant component mirrors the projection.
        if d[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
        let o = origin.to_array();
        ShearedRay {
            origin: [o[kx], o[ky], o[kz]],
            axes: [kx, ky, kz],
            shear: Vec3::new(d[kx] / d[kz], d[ky] / d[kz], 1.0 / d[kz]),
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
        let o = r.origin;
        // Vertices relative to the origin in the ray's axes, then sheared into its space.
        let rel = |v: [f32; 3]| [v[kx] - o[0], v[ky] - o[1], v[kz] - o[2]];
        let (a, b, c) = (rel(self.v0), rel(self.v1), rel(self.v2));
        let (ax, ay) = (a[0] - s.x * a[2], a[1] - s.y * a[2]);
        let (bx, by) = (b[0] - s.x * b[2], b[1] - s.y * b[2]);
        let (cx, cy) = (c[0] - s.x * c[2], c[1] - s.y * c[2]);
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
        let t_scaled = u * (s.z * a[2]) + v * (s.z * b[2]) + w * (s.z * c[2]);
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

/// Whether a triangle test's distance is a hit within `[t0, t1]`: a miss is infinity, which
/// must not count against an unbounded `t1`.
#[inline(always)]
pub fn within_interval(t: f32, t0: f32, t1: f32) -> bool {
    t >= t0 && t <= t1 && t != f32::INFINITY
}

/// Where a ray leaving a surface at `p` along the normal `n` (on the side it leaves to)
/// starts: a scene-relative margin `epsilon` plus a few ulps of the hit's magnitude, so the
/// child does not hit the surface it starts on. The render kernel's children and the Embree
/// comparison's rays both start here.
#[inline(always)]
pub fn leave_surface(p: Vec3, n: Vec3, epsilon: f32) -> Vec3 {
    p + n * (epsilon + p.abs().max_element() * 1e-6)
}

/// Shading normals at the corners of a [`TriangleBlock`]'s four triangles, `n[vertex][axis]
/// [lane]` as the block's vertices: a domain file of a smooth surface (an isosurface's
/// gradient normals) stores one per block, in block order. A lane of all zeros has none (the
/// facet normal shades it).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct NormalBlock {
    /// Unit normals (or zeros): `n[vertex][axis][lane]`.
    pub n: [[[f32; BLOCK]; 3]; 3],
}

const _: () = assert!(std::mem::size_of::<NormalBlock>() == 144);

impl NormalBlock {
    /// A lane's three corner normals, or `None` if any is zero or not finite.
    #[inline]
    pub fn lane(&self, lane: usize) -> Option<[Vec3; 3]> {
        let n = [0, 1, 2]
            .map(|i| Vec3::new(self.n[i][0][lane], self.n[i][1][lane], self.n[i][2][lane]));
        n.iter()
            .all(|v| v.is_finite() && *v != Vec3::ZERO)
            .then_some(n)
    }
}

/// Triangles tested together: one SSE register's worth.
pub const BLOCK: usize = 4;

/// Four triangles as structure-of-arrays, so one watertight test covers all four: `v[vertex]
/// [axis][lane]`, then per lane the scene-wide id (for the tie-break) and the material (for
/// shading). The only stored copy of a domain's triangles: a hit names its block and lane. A
/// leaf whose triangle count is not a multiple of four repeats its last triangle: a duplicate
/// has the same distance and id, so it never changes a nearest hit or an any-hit answer, and
/// no lane needs masking; [`TriangleBlock::is_repeat`] tells such a lane.
#[repr(C, align(64))]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct TriangleBlock {
    /// Vertex coordinates: `v[vertex][axis][lane]`.
    pub v: [[[f32; BLOCK]; 3]; 3],
    /// Low halves of the scene-wide ids.
    pub id_lo: [u32; BLOCK],
    /// High halves of the scene-wide ids.
    pub id_hi: [u32; BLOCK],
    /// Each lane's index into the scene's material table.
    pub material: [u32; BLOCK],
}

const _: () = assert!(std::mem::size_of::<TriangleBlock>() == 192);

impl TriangleBlock {
    /// The block of `tris[first .. first + count]` (one to four), padded with the last.
    pub fn new(tris: &[PackedTriangle], first: usize, count: usize) -> Self {
        assert!((1..=BLOCK).contains(&count));
        let mut b = TriangleBlock::zeroed();
        for lane in 0..BLOCK {
            let s = first + lane.min(count - 1);
            let t = &tris[s];
            for (i, p) in t.vertices().iter().enumerate() {
                for (axis, &c) in b.v[i].iter_mut().zip(p.as_ref()) {
                    axis[lane] = c;
                }
            }
            b.id_lo[lane] = t.id_lo;
            b.id_hi[lane] = t.id_hi;
            b.material[lane] = t.material;
        }
        b
    }

    /// Whether `lane` repeats the lane before it (the padding of a block of fewer than four
    /// triangles) rather than holding a triangle of its own. Ids are unique within a scene,
    /// so an equal id is a repeat.
    #[inline]
    pub fn is_repeat(&self, lane: usize) -> bool {
        lane > 0 && self.id(lane) == self.id(lane - 1)
    }

    /// Scene-wide id of a lane's triangle.
    #[inline(always)]
    pub fn id(&self, lane: usize) -> u64 {
        ((self.id_hi[lane] as u64) << 32) | self.id_lo[lane] as u64
    }

    /// One lane's triangle, bit for bit as it was built from.
    #[inline(always)]
    pub fn lane(&self, lane: usize) -> PackedTriangle {
        let p = |i: usize| [0, 1, 2].map(|a| self.v[i][a][lane]);
        PackedTriangle {
            v0: p(0),
            id_lo: self.id_lo[lane],
            v1: p(1),
            material: self.material[lane],
            v2: p(2),
            id_hi: self.id_hi[lane],
        }
    }

    /// The watertight test of every lane, one at a time: the reference the SIMD test equals.
    /// Returns the distances (infinity for a miss) and a bit per lane whose hit lies in
    /// `[t0, t1]`.
    #[inline(always)]
    pub fn intersect_scalar(&self, r: &ShearedRay, t0: f32, t1: f32) -> ([f32; BLOCK], u32) {
        let ts: [f32; BLOCK] = std::array::from_fn(|lane| self.lane(lane).intersect_t(r));
        let mut lanes = 0;
        for (lane, &t) in ts.iter().enumerate() {
            lanes |= (within_interval(t, t0, t1) as u32) << lane;
        }
        (ts, lanes)
    }

    /// The watertight test of all four lanes with SSE: the same operations in the same order as
    /// [`PackedTriangle::intersect_t`] (no fused multiply-add), so every lane's distance has
    /// the same bits as the scalar test (a lane whose edge functions are not all numbers is
    /// a miss either way, its distance infinity or NaN). Lanes with an exactly zero edge function, which the
    /// scalar test decides in double precision, are handed to it. The mask is as
    /// [`TriangleBlock::intersect_scalar`]'s.
    ///
    /// # Safety
    /// The CPU must support SSE2 (every x86-64 CPU does).
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub unsafe fn intersect_sse(&self, r: &ShearedSse, t0: f32, t1: f32) -> ([f32; BLOCK], u32) {
        use std::arch::x86_64::*;
        let [kx, ky, kz] = r.axis_bytes;
        // SAFETY: SSE2 is part of x86-64; the loads read this block's aligned arrays, at the
        // byte offsets of axes 0..3 (`ShearedSse::new`).
        unsafe {
            let rel = |i: usize| {
                let p = self.v[i].as_ptr().cast::<u8>();
                let axis = |at: usize| _mm_load_ps(p.add(at).cast::<f32>());
                (
                    _mm_sub_ps(axis(kx), r.origin[0]),
                    _mm_sub_ps(axis(ky), r.origin[1]),
                    _mm_sub_ps(axis(kz), r.origin[2]),
                )
            };
            let (a, b, c) = (rel(0), rel(1), rel(2));
            let shear = |p: (__m128, __m128, __m128)| {
                (
                    _mm_sub_ps(p.0, _mm_mul_ps(r.sx, p.2)),
                    _mm_sub_ps(p.1, _mm_mul_ps(r.sy, p.2)),
                )
            };
            let ((ax, ay), (bx, by), (cx, cy)) = (shear(a), shear(b), shear(c));
            let u = _mm_sub_ps(_mm_mul_ps(cx, by), _mm_mul_ps(cy, bx));
            let v = _mm_sub_ps(_mm_mul_ps(ax, cy), _mm_mul_ps(ay, cx));
            let w = _mm_sub_ps(_mm_mul_ps(bx, ay), _mm_mul_ps(by, ax));
            let zero = _mm_setzero_ps();
            let edge_zero = _mm_or_ps(
                _mm_or_ps(_mm_cmpeq_ps(u, zero), _mm_cmpeq_ps(v, zero)),
                _mm_cmpeq_ps(w, zero),
            );
            // Some edge function negative is the least of them negative, some positive the
            // greatest positive: two compares where six were, the same lanes whenever u, v and
            // w are numbers. (A NaN, from products overflowing to infinities of both signs,
            // may decide `outside` either way here; such a lane's distance is NaN or infinity
            // and never within the interval, so the lanes hit do not change.)
            let neg = _mm_cmplt_ps(_mm_min_ps(_mm_min_ps(u, v), w), zero);
            let pos = _mm_cmpgt_ps(_mm_max_ps(_mm_max_ps(u, v), w), zero);
            let outside = _mm_and_ps(neg, pos);
            let mut redo = _mm_movemask_ps(edge_zero) as u32;
            // Most blocks a ray reaches miss on every lane: stop before the distance.
            if _mm_movemask_ps(outside) == 0xf && redo == 0 {
                return ([f32::INFINITY; BLOCK], 0);
            }
            let det = _mm_add_ps(_mm_add_ps(u, v), w);
            let t_scaled = _mm_add_ps(
                _mm_add_ps(
                    _mm_mul_ps(u, _mm_mul_ps(r.sz, a.2)),
                    _mm_mul_ps(v, _mm_mul_ps(r.sz, b.2)),
                ),
                _mm_mul_ps(w, _mm_mul_ps(r.sz, c.2)),
            );
            let wrong_side = _mm_or_ps(
                _mm_and_ps(_mm_cmpgt_ps(det, zero), _mm_cmple_ps(t_scaled, zero)),
                _mm_and_ps(_mm_cmplt_ps(det, zero), _mm_cmpge_ps(t_scaled, zero)),
            );
            let miss = _mm_or_ps(_mm_or_ps(outside, _mm_cmpeq_ps(det, zero)), wrong_side);
            let t = _mm_div_ps(t_scaled, det);
            let t = _mm_or_ps(_mm_and_ps(miss, r.inf), _mm_andnot_ps(miss, t));
            let mut out = [0.0f32; BLOCK];
            _mm_storeu_ps(out.as_mut_ptr(), t);
            // The lanes within the interval, in the same register (a miss is infinity, which
            // must not count against an unbounded t1).
            let within = _mm_and_ps(
                _mm_and_ps(
                    _mm_cmpge_ps(t, _mm_set1_ps(t0)),
                    _mm_cmple_ps(t, _mm_set1_ps(t1)),
                ),
                _mm_cmpneq_ps(t, r.inf),
            );
            let mut lanes = _mm_movemask_ps(within) as u32;
            while redo != 0 {
                let lane = redo.trailing_zeros() as usize;
                redo &= redo - 1;
                let t = self.lane(lane).intersect_t(&r.ray);
                out[lane] = t;
                lanes = (lanes & !(1 << lane)) | (within_interval(t, t0, t1) as u32) << lane;
            }
            (out, lanes)
        }
    }
}

/// A [`ShearedRay`] with its values broadcast to SSE registers, made once per traversal.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
pub struct ShearedSse {
    ray: ShearedRay,
    /// Byte offsets of the ray's axes' rows in a block's `v[vertex]` (`axes[i] * 16`), so a
    /// block test adds them to its address unscaled.
    axis_bytes: [usize; 3],
    origin: [std::arch::x86_64::__m128; 3],
    sx: std::arch::x86_64::__m128,
    sy: std::arch::x86_64::__m128,
    sz: std::arch::x86_64::__m128,
    inf: std::arch::x86_64::__m128,
}

#[cfg(target_arch = "x86_64")]
impl ShearedSse {
    /// Broadcasts `ray`; the origin is permuted into the ray's axes.
    #[inline(always)]
    pub fn new(ray: &ShearedRay) -> Self {
        use std::arch::x86_64::_mm_set1_ps;
        let o = ray.origin;
        // SAFETY: SSE2 is part of x86-64.
        unsafe {
            ShearedSse {
                ray: *ray,
                axis_bytes: ray.axes.map(|k| k * std::mem::size_of::<[f32; BLOCK]>()),
                origin: [_mm_set1_ps(o[0]), _mm_set1_ps(o[1]), _mm_set1_ps(o[2])],
                sx: _mm_set1_ps(ray.shear.x),
                sy: _mm_set1_ps(ray.shear.y),
                sz: _mm_set1_ps(ray.shear.z),
                inf: _mm_set1_ps(f32::INFINITY),
            }
        }
    }
}
