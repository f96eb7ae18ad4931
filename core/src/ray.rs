//! The ray record: a fixed-size plain struct that carries everything needed to continue a
//! path anywhere in the cluster, including the light it will add to its pixel.

use bytemuck::{Pod, Zeroable};

/// What a ray is looking for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum RayKind {
    /// Looks for the nearest surface; adds sky light if it escapes.
    Radiance = 0,
    /// Looks for any occluder; adds its carried light if there is none.
    Shadow = 1,
}

/// One ray in flight. 104 bytes, no padding holes, so batches travel as raw bytes.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct RayRecord {
    /// Origin.
    pub origin: [f32; 3],
    /// Hits nearer than this are ignored.
    pub t_min: f32,
    /// Direction (unit length).
    pub dir: [f32; 3],
    /// Hits farther than this are ignored (a shadow ray stops short of its light).
    pub t_max: f32,
    /// Path weight (radiance rays) or the light to add if unoccluded (shadow rays).
    pub throughput: [f32; 3],
    /// Pixel index, `y * width + x`.
    pub pixel: u32,
    /// Sample index within the pixel.
    pub sample: u32,
    /// Bounces so far (0 for camera rays and their shadow rays).
    pub depth: u16,
    /// [`RayKind`] as a byte.
    pub kind: u8,
    /// Unused; zero.
    pub _pad: u8,
    /// Domain whose queue the ray is in.
    pub domain: u32,
    /// Image tile the ray contributes to (frame completion).
    pub tile: u32,
    /// Epoch of that tile when the ray was born (stale rays are dropped after a fault).
    pub epoch: u32,
    /// Under speculative placement, the ray's group at the place it was born, whose copies
    /// this is (see `render::speculation`); zero otherwise.
    pub group: u32,
    /// The ray's share of its tile's credit (frame completion).
    pub credit: u64,
    /// Under speculative placement, the worker holding the ray's group (the coordinator's
    /// key for it), where this copy's verdict goes; zero otherwise.
    pub resolver: u32,
    /// Unused; zero.
    pub _pad2: u32,
    /// Direct volume rendering: the premultiplied colour composited so far along the ray,
    /// carried from brick to brick (zero for surface rays).
    pub volume_rgb: [f32; 3],
    /// Direct volume rendering: the opacity accumulated so far (`1 - transmittance`; zero,
    /// the default, is a ray that has seen nothing).
    pub volume_alpha: f32,
}

const _: () = assert!(std::mem::size_of::<RayRecord>() == 104);

impl RayRecord {
    /// How many resolved hits lie between this ray and its camera ray: a radiance ray's depth,
    /// one more for a shadow ray (it leaves the hit that made it). Rays of one generation can
    /// only be made once the previous generation has been traced.
    pub fn generation(&self) -> u16 {
        self.depth + u16::from(self.kind == RayKind::Shadow as u8)
    }

    /// The ray's kind.
    pub fn kind(&self) -> RayKind {
        if self.kind == RayKind::Shadow as u8 {
            RayKind::Shadow
        } else {
            RayKind::Radiance
        }
    }
}
