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
//! any brick computes the same bits; the colour and opacity accumulated so far travel in the
//! ray record, composited in the order of `k`. A skipped sample is one whose cell lies in a
//! sub-block whose whole range the transfer function makes transparent: compositing it would
//! have added exactly nothing.

use glam::Vec3;

use crate::brick::Brick;
use crate::ray::RayRecord;
use crate::scene::VolumeSpec;
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
    shading: bool,
    table: TransferTable,
    /// Whether to skip transparent sub-blocks (off only to measure what skipping saves).
    pub skipping: bool,
}

/// How far one brick's march got.
pub enum March {
    /// The ray passed through the brick's interval.
    Through,
    /// The ray became opaque in it: nothing behind can show.
    Opaque,
}

impl VolumeView {
    /// The view of a manifest's checked volume section.
    pub fn new(v: &VolumeSpec) -> Self {
        let spacing = Vec3::from(v.spacing);
        VolumeView {
            origin: Vec3::from(v.origin),
            inv_spacing: Vec3::ONE / spacing,
            spacing,
            last_cell: v.dims.map(|d| d - 2),
            step: v.step,
            shading: v.shading,
            table: TransferTable::new(&v.transfer, v.step / v.voxel_length()),
            skipping: true,
        }
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

    /// Composites the samples of `ray` with `t` in `[t0, t1)` (its interval in `brick`) into its
    /// colour and opacity. `skip` is [`VolumeView::transparent_blocks`] of the brick.
    pub fn march(
        &self,
        brick: &Brick,
        skip: &[bool],
        ray: &mut RayRecord,
        t0: f32,
        t1: f32,
        counts: &mut SampleCounts,
    ) -> March {
        let (origin, dir) = (Vec3::from(ray.origin), Vec3::from(ray.dir));
        let dt = self.step;
        let t_of = |k: u32| k as f32 * dt;
        // The first k with t_k >= t0: start near it, then settle exactly by the same formula.
        let mut k = (t0.max(0.0) / dt) as u32;
        while k > 0 && t_of(k - 1) >= t0 {
            k -= 1;
        }
        while t_of(k) < t0 {
            k += 1;
        }
        let mut rgb = Vec3::from(ray.volume_rgb);
        let mut alpha = ray.volume_alpha;
        let mut outcome = March::Through;
        loop {
            let t = t_of(k);
            if t >= t1 || k == u32::MAX {
                break;
            }
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
            let mut c = Vec3::new(r, gr, b);
            if self.shading {
                c *= self.headlight(brick, g, dir);
            }
            let w = 1.0 - alpha;
            rgb += c * w;
            alpha += a * w;
            if alpha >= OPAQUE {
                outcome = March::Opaque;
                break;
            }
        }
        ray.volume_rgb = rgb.into();
        ray.volume_alpha = alpha;
        outcome
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

    /// Diffuse shading by a light at the eye: the gradient's central difference one voxel
    /// either side (ghost voxels hold it) against the ray's direction.
    fn headlight(&self, brick: &Brick, g: Vec3, dir: Vec3) -> f32 {
        let at = |d: Vec3| {
            let (cell, frac) = self.locate(g + d);
            trilinear(brick, cell, frac)
        };
        let grad = Vec3::new(
            at(Vec3::X) - at(-Vec3::X),
            at(Vec3::Y) - at(-Vec3::Y),
            at(Vec3::Z) - at(-Vec3::Z),
        ) * self.inv_spacing;
        let len = grad.length();
        if len > 0.0 && len.is_finite() {
            0.25 + 0.75 * (grad.dot(dir) / len).abs()
        } else {
            1.0
        }
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
