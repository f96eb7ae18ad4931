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
    fn farther_or_tied(near: &[f32; WIDTH], slot: usize) -> u32 {
        // SAFETY: SSE2 is part of x86-64; the loads read `near`'s eight floats.
        unsafe {
            let d = _mm_set1_ps(near[slot]);
            let half = |at: usize| {
                let v = _mm_loadu_ps(near.as_ptr().add(at));
                let farther = _mm_movemask_ps(_mm_cmpgt_ps(v, d)) as u32;
                let tied = _mm_movemask_ps(_mm_cmpeq_ps(v, d)) as u32;
                (farther << at, tied << at)
            };
            let ((f0, e0), (f1, e1)) = (half(0), half(4));
            (f0 | f1) | ((e0 | e1) & ((1 << slot) - 1))
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
    fn farther_or_tied(near: &[f32; WIDTH], slot: usize) -> u32 {
        // SAFETY: only reached from the `avx2,fma,popcnt` functions below; the loads read `near`'s
        // eight floats.
        unsafe {
            let v = _mm256_loadu_ps(near.as_ptr());
            let d = _mm256_set1_ps(near[slot]);
            let farther = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_GT_OQ>(v, d)) as u32;
            let tied = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_EQ_OQ>(v, d)) as u32;
            farther | (tied & ((1 << slot) - 1))
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
