//! The SSE and AVX2 box tests; the triangle test is SSE in both
//! ([`TriangleBlock::intersect_sse`]).

use std::arch::x86_64::*;

use super::packet::{PacketStack, nearest_packet};
use super::{Bvh, BvhNode, Hit, Isa, Stack, TraceRay, WIDTH, any, nearest};
use crate::geometry::{BLOCK, ShearedSse, TriangleBlock};

/// The first float of the `bounds` row at byte offset `offset` (one of [`TraceRay`]'s `rows`).
///
/// # Safety
/// `offset` must be a row's offset within `bounds` (below 6 rows).
#[inline(always)]
unsafe fn row_ptr(node: &BvhNode, offset: u32) -> *const f32 {
    // SAFETY: as the caller promises.
    unsafe {
        node.bounds
            .as_ptr()
            .cast::<u8>()
            .add(offset as usize)
            .cast::<f32>()
    }
}

/// Four lanes at a time: a node's two halves in turn.
pub struct Sse;

#[derive(Clone, Copy)]
pub struct SseRay {
    tri: ShearedSse,
    inv: [__m128; 3],
    origin_inv: [__m128; 3],
    /// [`TraceRay`]'s row offsets.
    rows: [u32; 6],
}

impl Isa for Sse {
    type Ray = SseRay;

    #[inline(always)]
    fn prepare(ray: &TraceRay) -> SseRay {
        // SAFETY: SSE2 is part of x86-64.
        unsafe {
            SseRay {
                tri: ShearedSse::new(&ray.sheared),
                inv: ray.inv.map(|v| _mm_set1_ps(v)),
                origin_inv: ray.origin_inv.map(|v| _mm_set1_ps(v)),
                rows: ray.rows,
            }
        }
    }

    #[inline(always)]
    fn slab(node: &BvhNode, r: &SseRay, t0: f32, t1: f32) -> ([f32; WIDTH], u32) {
        let mut out = [0.0f32; WIDTH];
        let mut mask = 0;
        // SAFETY: SSE2 is part of x86-64; loads read the node's 64-byte aligned rows.
        unsafe {
            for half in 0..2 {
                let at = half * 4;
                let plane = |k: usize, a: usize| {
                    // SAFETY: `rows` are row offsets within `bounds` (`TraceRay::new`), `at`
                    // is 0 or 4.
                    let b = _mm_load_ps(row_ptr(node, r.rows[k]).add(at));
                    _mm_sub_ps(_mm_mul_ps(b, r.inv[a]), r.origin_inv[a])
                };
                let near = _mm_max_ps(
                    _mm_max_ps(plane(0, 0), plane(1, 1)),
                    _mm_max_ps(plane(2, 2), _mm_set1_ps(t0)),
                );
                let far = _mm_min_ps(
                    _mm_min_ps(plane(3, 0), plane(4, 1)),
                    _mm_min_ps(plane(5, 2), _mm_set1_ps(t1)),
                );
                _mm_storeu_ps(out[at..].as_mut_ptr(), near);
                mask |= (_mm_movemask_ps(_mm_cmple_ps(near, far)) as u32) << at;
            }
        }
        (out, mask)
    }

    #[inline(always)]
    fn rank_keys(near: &[f32; WIDTH]) -> [i32; WIDTH] {
        let mut keys = [0i32; WIDTH];
        // SAFETY: SSE2 is part of x86-64; the loads and stores cover `near`'s and `keys`' eight
        // lanes.
        unsafe {
            for at in [0, 4] {
                let v = _mm_castps_si128(_mm_loadu_ps(near.as_ptr().add(at)));
                let slots = _mm_setr_epi32(at as i32, at as i32 + 1, at as i32 + 2, at as i32 + 3);
                let k = _mm_or_si128(_mm_and_si128(v, _mm_set1_epi32(!7)), slots);
                _mm_storeu_si128(keys.as_mut_ptr().add(at).cast(), k);
            }
        }
        keys
    }

    #[inline(always)]
    fn above(keys: &[i32; WIDTH], slot: usize) -> u32 {
        // SAFETY: SSE2 is part of x86-64; the loads read `keys`' eight lanes.
        unsafe {
            let d = _mm_set1_epi32(keys[slot]);
            let half = |at: usize| {
                let v = _mm_loadu_si128(keys.as_ptr().add(at).cast());
                (_mm_movemask_ps(_mm_castsi128_ps(_mm_cmpgt_epi32(v, d))) as u32) << at
            };
            half(0) | half(4)
        }
    }

    #[inline(always)]
    fn block(block: &TriangleBlock, r: &SseRay, t0: f32, t1: f32) -> ([f32; BLOCK], u32) {
        // SAFETY: SSE2 is part of x86-64.
        unsafe { block.intersect_sse(&r.tri, t0, t1) }
    }
}

/// All eight lanes at once, box planes with one fused multiply-subtract each.
struct Avx2;

#[derive(Clone, Copy)]
struct Avx2Ray {
    tri: ShearedSse,
    inv: [__m256; 3],
    origin_inv: [__m256; 3],
    /// [`TraceRay`]'s row offsets.
    rows: [u32; 6],
}

impl Isa for Avx2 {
    type Ray = Avx2Ray;

    #[inline(always)]
    fn prepare(ray: &TraceRay) -> Avx2Ray {
        // SAFETY: only reached from the `avx2,fma,popcnt` functions below.
        unsafe {
            Avx2Ray {
                tri: ShearedSse::new(&ray.sheared),
                inv: ray.inv.map(|v| _mm256_set1_ps(v)),
                origin_inv: ray.origin_inv.map(|v| _mm256_set1_ps(v)),
                rows: ray.rows,
            }
        }
    }

    #[inline(always)]
    fn fresh(ray: &Avx2Ray) -> Avx2Ray {
        // Volatile reads, so that they are neither merged with the ray's other reads nor
        // hoisted out of the loop: the values are live only from here through the node visits.
        let read = |v: &__m256| {
            // SAFETY: a read of a live, aligned value.
            unsafe { std::ptr::read_volatile(v) }
        };
        Avx2Ray {
            inv: ray.inv.each_ref().map(read),
            origin_inv: ray.origin_inv.each_ref().map(read),
            ..*ray
        }
    }

    #[inline(always)]
    fn slab(node: &BvhNode, r: &Avx2Ray, t0: f32, t1: f32) -> ([f32; WIDTH], u32) {
        let mut out = [0.0f32; WIDTH];
        // SAFETY: only reached from the `avx2,fma,popcnt` functions below; loads read the node's
        // 64-byte aligned rows.
        let mask = unsafe {
            let plane = |k: usize, a: usize| {
                // SAFETY: `rows` are row offsets within `bounds` (`TraceRay::new`).
                let b = _mm256_load_ps(row_ptr(node, r.rows[k]));
                _mm256_fmsub_ps(b, r.inv[a], r.origin_inv[a])
            };
            let near = _mm256_max_ps(
                _mm256_max_ps(plane(0, 0), plane(1, 1)),
                _mm256_max_ps(plane(2, 2), _mm256_set1_ps(t0)),
            );
            let far = _mm256_min_ps(
                _mm256_min_ps(plane(3, 0), plane(4, 1)),
                _mm256_min_ps(plane(5, 2), _mm256_set1_ps(t1)),
            );
            _mm256_storeu_ps(out.as_mut_ptr(), near);
            _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(near, far)) as u32
        };
        (out, mask)
    }

    #[inline(always)]
    fn slab_nearest(
        node: &BvhNode,
        r: &Avx2Ray,
        t0: f32,
        t1: f32,
        nearest: &mut [f32; WIDTH],
    ) -> u32 {
        // SAFETY: only reached from the `avx2,fma,popcnt` functions below; loads read the node's
        // 64-byte aligned rows and `nearest`'s eight floats.
        unsafe {
            let plane = |k: usize, a: usize| {
                // SAFETY: `rows` are row offsets within `bounds` (`TraceRay::new`).
                let b = _mm256_load_ps(row_ptr(node, r.rows[k]));
                _mm256_fmsub_ps(b, r.inv[a], r.origin_inv[a])
            };
            let near = _mm256_max_ps(
                _mm256_max_ps(plane(0, 0), plane(1, 1)),
                _mm256_max_ps(plane(2, 2), _mm256_set1_ps(t0)),
            );
            let far = _mm256_min_ps(
                _mm256_min_ps(plane(3, 0), plane(4, 1)),
                _mm256_min_ps(plane(5, 2), _mm256_set1_ps(t1)),
            );
            let entered = _mm256_cmp_ps::<_CMP_LE_OQ>(near, far);
            let held = _mm256_loadu_ps(nearest.as_ptr());
            let lower = _mm256_min_ps(held, near);
            _mm256_storeu_ps(nearest.as_mut_ptr(), _mm256_blendv_ps(held, lower, entered));
            _mm256_movemask_ps(entered) as u32
        }
    }

    #[inline(always)]
    fn rank_keys(near: &[f32; WIDTH]) -> [i32; WIDTH] {
        let mut keys = [0i32; WIDTH];
        // SAFETY: only reached from the `avx2,fma,popcnt` functions below; the load and store
        // cover `near`'s and `keys`' eight lanes.
        unsafe {
            let v = _mm256_castps_si256(_mm256_loadu_ps(near.as_ptr()));
            let slots = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
            let k = _mm256_or_si256(_mm256_and_si256(v, _mm256_set1_epi32(!7)), slots);
            _mm256_storeu_si256(keys.as_mut_ptr().cast(), k);
        }
        keys
    }

    #[inline(always)]
    fn above(keys: &[i32; WIDTH], slot: usize) -> u32 {
        // SAFETY: only reached from the `avx2,fma,popcnt` functions below; the load reads
        // `keys`' eight lanes.
        unsafe {
            let v = _mm256_loadu_si256(keys.as_ptr().cast());
            let d = _mm256_set1_epi32(keys[slot]);
            _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpgt_epi32(v, d))) as u32
        }
    }

    #[inline(always)]
    fn block(block: &TriangleBlock, r: &Avx2Ray, t0: f32, t1: f32) -> ([f32; BLOCK], u32) {
        // SAFETY: SSE2 is part of x86-64.
        unsafe { block.intersect_sse(&r.tri, t0, t1) }
    }
}

/// # Safety
/// The CPU must support AVX2, FMA and POPCNT.
#[target_feature(enable = "avx2,fma,popcnt")]
pub unsafe fn nearest_avx2(
    stack: &mut Stack,
    bvh: &Bvh,
    ray: &TraceRay,
    t0: f32,
    t1: f32,
) -> Option<Hit> {
    nearest::<Avx2>(stack, *bvh, ray, t0, t1)
}

/// # Safety
/// The CPU must support AVX2, FMA and POPCNT.
#[target_feature(enable = "avx2,fma,popcnt")]
pub unsafe fn nearest_packet_avx2(
    stack: &mut PacketStack,
    single: &mut Stack,
    bvh: Bvh,
    rays: &[TraceRay],
    t0: &[f32],
    t1: &[f32],
    out: &mut [Option<Hit>],
) {
    nearest_packet::<Avx2>(stack, single, bvh, rays, t0, t1, out)
}

/// # Safety
/// The CPU must support AVX2, FMA and POPCNT.
#[target_feature(enable = "avx2,fma,popcnt")]
pub unsafe fn any_avx2(stack: &mut Stack, bvh: &Bvh, ray: &TraceRay, t0: f32, t1: f32) -> bool {
    any::<Avx2>(stack, *bvh, ray, t0, t1)
}
