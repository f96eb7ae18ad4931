//! Direct volume rendering of one brick's part of a ray: samples on a grid fixed along the ray
//! (`t = k * step` from the ray's own origin, whichever brick takes them), trilinear
//! interpolation, the transfer function tabulated for the step, front-to-back compositing of
//! premultiplied colour into the ray record, early termination, and empty-space skipping by
//! the sub-blocks' value ranges.
//!
//! Why bricking changes no bit: a sample belongs to the brick whose interval `[a, b)` along
//! the ray holds its `t` (the domain walk's intervals share end points exactly, so each `k`
//! falls in exactly one); its value is computed from the global voxel index of its cell,
//! clamped to the volume, and every brick stores the voxels of its cells plus ghost voxels, so
//! any brick computes the same bits. Samples are composited in segments, the stretches of the
//! ray between block faces (planes every 8 cells, where bricks are cut), each from nothing;
//! segments are folded into the colour and opacity the ray record carries, in order along the
//! ray. A brick boundary is a block face, so it never splits a segment, and a speculative copy
//! can composite its brick's segments without knowing what lies in front (the ray's group
//! folds them in the same order, `render::speculation`). A skipped sample is one whose cell lies in a
//! sub-block whose whole range the transfer function makes transparent: compositing it would
//! have added exactly nothing.

use std::ops::ControlFlow;

use glam::Vec3;

use super::volume_light::{Lighting, MAX_LIGHTS, RayLights, SHADOW_BIAS_VOXELS};
use crate::ray::{RayKind, RayRecord};
use crate::scene::brick::{BLOCK, Brick};
use crate::scene::{Light, VolumeSpec};
use crate::transfer::TransferTable;

/// Accumulated opacity at which a ray stops: what lies behind adds under 1/256 of the pixel.
pub const OPAQUE: f32 = 1.0 - 1.0 / 256.0;

/// Counts of the volume kernel.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SampleCounts {
    /// Samples interpolated and composited.
    pub taken: u64,
    /// Samples skipped as lying in a transparent sub-block.
    pub skipped: u64,
}

/// The volume's grid and transfer function as the kernel samples them.
#[derive(Clone, Debug)]
pub struct VolumeView {
    origin: Vec3,
    inv_spacing: Vec3,
    spacing: Vec3,
    last_cell: [u32; 3],
    step: f32,
    lighting: Lighting,
    lights: Vec<Light>,
    voxel: f32,
    table: TransferTable,
    /// Whether to skip transparent sub-blocks (off only to measure what skipping saves).
    pub skipping: bool,
}

/// The composite of one segment of a ray: its samples between two block faces, composited
/// front to back from nothing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    /// Index `k` of its first sample that showed anything: its place along the ray.
    pub first: u32,
    /// Premultiplied colour.
    pub rgb: [f32; 3],
    /// Opacity.
    pub alpha: f32,
    /// With shadows: where along the ray its shadow rays leave (the opacity-weighted mean of
    /// its samples' distances).
    pub depth: f32,
    /// With shadows: per light, the premultiplied colour it reflects of that light (sent on
    /// in a shadow ray, not composited into the ray).
    pub direct: [[f32; 3]; MAX_LIGHTS],
}

impl Segment {
    /// A segment of colour `rgb` and opacity `alpha` from sample `first`, without shadow rays.
    pub fn plain(first: u32, rgb: [f32; 3], alpha: f32) -> Segment {
        Segment {
            first,
            rgb,
            alpha,
            depth: 0.0,
            direct: [[0.0; 3]; MAX_LIGHTS],
        }
    }

    /// The lights this segment sends shadow rays to: those it reflects any light of.
    pub fn lit_by(&self) -> impl Iterator<Item = usize> + '_ {
        (0..MAX_LIGHTS).filter(|&i| self.direct[i].iter().any(|&c| c > 0.0))
    }
}

/// Composites `segment` behind what `ray` has gathered so far; returns whether the ray is now
/// opaque (nothing behind can show). The one fold both the chained and the speculative trace
/// make, segment by segment in order along the ray.
pub fn composite(ray: &mut RayRecord, segment: &Segment) -> bool {
    let w = 1.0 - ray.volume_alpha;
    ray.volume_rgb = (Vec3::from(ray.volume_rgb) + Vec3::from(segment.rgb) * w).into();
    ray.volume_alpha += segment.alpha * w;
    ray.volume_alpha >= OPAQUE
}

/// The crossings of a ray with the block faces in one brick's box, nearest first: per axis
/// the planes every [`BLOCK`] cells, at `t = (plane - o) / d` (the k-d walk's formula for the
/// same planes, so a brick boundary is a crossing to the bit).
struct BlockFaces {
    o: Vec3,
    d: Vec3,
    origin: Vec3,
    spacing: Vec3,
    /// Per axis: the next plane's index (in blocks), the index past the last, and the step.
    next: [i64; 3],
    end: [i64; 3],
    step: [i64; 3],
}

impl BlockFaces {
    fn new(view: &VolumeView, brick: &Brick, o: Vec3, d: Vec3) -> Self {
        let h = brick.header;
        let mut f = BlockFaces {
            o,
            d,
            origin: view.origin,
            spacing: view.spacing,
            next: [0; 3],
            end: [0; 3],
            step: [0; 3],
        };
        for a in 0..3 {
            let first = i64::from(h.cells_lo[a].div_ceil(BLOCK));
            let last = i64::from(h.cells_hi[a] / BLOCK);
            if d[a] > 0.0 {
                (f.next[a], f.end[a], f.step[a]) = (first, last + 1, 1);
            } else if d[a] < 0.0 {
                (f.next[a], f.end[a], f.step[a]) = (last, first - 1, -1);
            } else {
                // Parallel to these planes: never crosses one.
                (f.next[a], f.end[a], f.step[a]) = (0, 0, 1);
            }
        }
        f
    }

    /// Where the ray crosses plane `j` (in blocks) of axis `a`.
    fn crossing(&self, a: usize, j: i64) -> f32 {
        // `Grid::point`'s formula for voxel plane `j * BLOCK`, as the brick cut used.
        let plane = self.origin[a] + self.spacing[a] * (j as u32 * BLOCK) as f32;
        (plane - self.o[a]) / self.d[a]
    }

    /// The nearest crossing beyond `t`, if any in the brick.
    fn next_after(&mut self, t: f32) -> Option<f32> {
        let mut best: Option<f32> = None;
        for a in 0..3 {
            while self.next[a] != self.end[a] {
                let c = self.crossing(a, self.next[a]);
                if c > t {
                    best = Some(best.map_or(c, |b| b.min(c)));
                    break;
                }
                self.next[a] += self.step[a];
            }
        }
        best
    }
}

/// How far one brick's march got.
pub enum March {
    /// The ray passed through the brick's interval.
    Through,
    /// The ray became opaque in it: nothing behind can show.
    Opaque,
}

impl VolumeView {
    /// The view of a manifest's checked volume section, lit by `lights` (the scene's).
    pub fn new(v: &VolumeSpec, lights: &[Light]) -> Self {
        let spacing = Vec3::from(v.spacing);
        let lighting = match (v.shading, v.shadows, lights.is_empty()) {
            (false, _, _) => Lighting::Unlit,
            (true, _, true) => Lighting::Headlight,
            (true, false, false) => Lighting::Lights,
            (true, true, false) => Lighting::Shadowed,
        };
        VolumeView {
            origin: Vec3::from(v.origin),
            inv_spacing: Vec3::ONE / spacing,
            spacing,
            last_cell: v.dims.map(|d| d - 2),
            step: v.step,
            lighting,
            lights: lights.to_vec(),
            voxel: v.voxel_length(),
            table: TransferTable::new(&v.transfer, v.step / v.voxel_length()),
            skipping: true,
        }
    }

    /// How `ray`'s samples are lit: a shadow ray's not at all (only their opacity counts).
    pub fn lights_for(&self, ray: &RayRecord) -> RayLights {
        match ray.kind() {
            RayKind::Shadow => RayLights::UNLIT,
            RayKind::Radiance => RayLights::for_ray(self.lighting, &self.lights, ray),
        }
    }

    /// Where a shadow ray leaving a segment starts along its way to the light: past the
    /// material around the segment's depth.
    pub fn shadow_bias(&self) -> f32 {
        SHADOW_BIAS_VOXELS * self.voxel
    }

    /// Whether a brick whose voxels range over `values` shows nothing (it is then walked past
    /// without being loaded).
    pub fn transparent(&self, values: [f32; 2]) -> bool {
        self.table.transparent(values[0], values[1])
    }

    /// Which of `brick`'s sub-blocks are transparent, for [`VolumeView::march`].
    pub fn transparent_blocks(&self, brick: &Brick) -> Vec<bool> {
        brick
            .ranges()
            .iter()
            .map(|r| self.skipping && self.table.transparent(r[0], r[1]))
            .collect()
    }

    /// Where along a ray its sample `k` lies: `t_k = k * step`, the one formula of the grid.
    pub fn sample_t(&self, k: u32) -> f32 {
        k as f32 * self.step
    }

    /// The first sample index `k` with `t_k >= t` (on the grid `t_k = k * step`).
    fn first_sample_at(&self, t: f32) -> u32 {
        let dt = self.step;
        let t_of = |k: u32| k as f32 * dt;
        // Start near it, then settle exactly by the same formula the march uses.
        let mut k = (t.max(0.0) / dt) as u32;
        while k > 0 && t_of(k - 1) >= t {
            k -= 1;
        }
        while k < u32::MAX && t_of(k) < t {
            k += 1;
        }
        k
    }

    /// Composites the samples of the ray `(origin, dir)` with `t` in `[t0, t1)` (its interval
    /// in `brick`) segment by segment, each from nothing, and hands every segment that shows
    /// anything to `emit`, in order along the ray; `emit` breaks to stop the march (the ray
    /// became opaque). `skip` is [`VolumeView::transparent_blocks`] of the brick.
    ///
    /// Segments are the stretches of the ray between its crossings of the volume's block
    /// faces (planes every [`BLOCK`] cells, where bricks are cut): the same stretches whatever
    /// the bricking, and never split by a brick boundary, so compositing segment by segment
    /// into the ray (`composite`) gives the same bits traced one brick after another, in any
    /// bricking, or speculatively (each brick's segments sent back and folded in order).
    #[allow(clippy::too_many_arguments)]
    pub fn march(
        &self,
        brick: &Brick,
        skip: &[bool],
        (origin, dir): (Vec3, Vec3),
        lit: &RayLights,
        t0: f32,
        t1: f32,
        counts: &mut SampleCounts,
        mut emit: impl FnMut(Segment) -> ControlFlow<()>,
    ) -> March {
        let dt = self.step;
        let t_of = |k: u32| k as f32 * dt;
        let mut faces = BlockFaces::new(self, brick, origin, dir);
        let mut k = self.first_sample_at(t0);
        let mut lo = t0;
        while lo < t1 {
            let hi = faces.next_after(lo).map_or(t1, |t| t.min(t1));
            let mut rgb = Vec3::ZERO;
            let mut alpha = 0.0f32;
            let mut first = None;
            let mut direct = [Vec3::ZERO; MAX_LIGHTS];
            // Opacity-weighted sums of the samples' distances (the shadow rays' depth).
            let (mut weighted_t, mut weight) = (0.0f32, 0.0f32);
            loop {
                let t = t_of(k);
                if t >= hi || k == u32::MAX {
                    break;
                }
                if alpha >= OPAQUE {
                    // Nothing behind shows through this segment: on to its end.
                    k = self.first_sample_at(hi).max(k);
                    break;
                }
                let here = k;
                k += 1;
                let g = (origin + dir * t - self.origin) * self.inv_spacing;
                let (cell, frac) = self.locate(g);
                if let Some(b) = brick.block_of(cell)
                    && skip[b]
                {
                    counts.skipped += 1;
                    continue;
                }
                counts.taken += 1;
                let value = trilinear(brick, cell, frac);
                let [r, gr, b, a] = self.table.lookup(value);
                if a <= 0.0 {
                    continue;
                }
                let c = Vec3::new(r, gr, b);
                let w = 1.0 - alpha;
                match lit.lighting {
                    Lighting::Unlit => rgb += c * w,
                    Lighting::Headlight | Lighting::Lights => {
                        let p = origin + dir * t;
                        let (own, lights) = lit.shade(c, p, self.gradient(brick, g), dir);
                        rgb += (own + lights.iter().sum::<Vec3>()) * w;
                    }
                    Lighting::Shadowed => {
                        let p = origin + dir * t;
                        let (own, lights) = lit.shade(c, p, self.gradient(brick, g), dir);
                        rgb += own * w;
                        for (d, l) in direct.iter_mut().zip(lights) {
                            *d += l * w;
                        }
                        weighted_t += t * a * w;
                        weight += a * w;
                    }
                }
                alpha += a * w;
                first.get_or_insert(here);
            }
            if let Some(first) = first
                && (alpha > 0.0 || rgb != Vec3::ZERO)
            {
                let segment = Segment {
                    first,
                    rgb: rgb.into(),
                    alpha,
                    depth: if weight > 0.0 {
                        weighted_t / weight
                    } else {
                        0.0
                    },
                    direct: direct.map(Into::into),
                };
                if emit(segment).is_break() {
                    return March::Opaque;
                }
            }
            lo = hi;
        }
        March::Through
    }

    /// The cell holding grid position `g` (clamped to the volume) and the position in it.
    #[inline]
    fn locate(&self, g: Vec3) -> ([u32; 3], [f32; 3]) {
        let mut cell = [0u32; 3];
        let mut frac = [0f32; 3];
        for a in 0..3 {
            // `as` saturates: negatives and NaN go to cell 0.
            let c = (g[a].floor() as u32).min(self.last_cell[a]);
            cell[a] = c;
            frac[a] = (g[a] - c as f32).clamp(0.0, 1.0);
        }
        (cell, frac)
    }

    /// The volume's gradient at grid position `g`, in value per world unit: central
    /// differences one voxel either side (ghost voxels hold them, so every brick computes the
    /// same bits).
    fn gradient(&self, brick: &Brick, g: Vec3) -> Vec3 {
        let at = |d: Vec3| {
            let (cell, frac) = self.locate(g + d);
            trilinear(brick, cell, frac)
        };
        Vec3::new(
            at(Vec3::X) - at(-Vec3::X),
            at(Vec3::Y) - at(-Vec3::Y),
            at(Vec3::Z) - at(-Vec3::Z),
        ) * self.inv_spacing
            * 0.5
    }

    /// Voxel spacing, for tools.
    pub fn spacing(&self) -> Vec3 {
        self.spacing
    }
}

/// The trilinear value in `cell` at `frac`, from global voxel indices.
#[inline]
fn trilinear(brick: &Brick, c: [u32; 3], f: [f32; 3]) -> f32 {
    let v = |i: u32, j: u32, k: u32| brick.voxel([c[0] + i, c[1] + j, c[2] + k]);
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = lerp(v(0, 0, 0), v(1, 0, 0), f[0]);
    let x10 = lerp(v(0, 1, 0), v(1, 1, 0), f[0]);
    let x01 = lerp(v(0, 0, 1), v(1, 0, 1), f[0]);
    let x11 = lerp(v(0, 1, 1), v(1, 1, 1), f[0]);
    lerp(lerp(x00, x10, f[1]), lerp(x01, x11, f[1]), f[2])
}
