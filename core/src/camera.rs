//! The pinhole camera: from a pixel and a sample to a primary ray.

use glam::Vec3;

use crate::ray::{RayKind, RayRecord};
use crate::sampling::{Purpose, uniform};
use crate::scene::Camera;

/// A camera set up for one image size.
#[derive(Clone, Copy, Debug)]
pub struct PinholeCamera {
    eye: Vec3,
    forward: Vec3,
    right: Vec3,
    up: Vec3,
    width: u32,
    height: u32,
}

impl PinholeCamera {
    /// Sets up `camera` for a `width` x `height` image.
    pub fn new(camera: &Camera, width: u32, height: u32) -> Self {
        let eye = Vec3::from(camera.eye);
        let forward = (Vec3::from(camera.look_at) - eye).normalize_or(Vec3::NEG_Z);
        let right = forward
            .cross(Vec3::from(camera.up))
            .normalize_or(forward.any_orthonormal_vector());
        let up = right.cross(forward);
        let half_h = (camera.fov_y_degrees.to_radians() * 0.5).tan();
        let half_w = half_h * width as f32 / height as f32;
        PinholeCamera {
            eye,
            forward,
            right: right * half_w,
            up: up * half_h,
            width,
            height,
        }
    }

    /// The primary ray of `sample` in `pixel`, jittered within the pixel.
    pub fn primary(&self, pixel: u32, sample: u32) -> RayRecord {
        let x = (pixel % self.width) as f32 + uniform(pixel, sample, 0, Purpose::PixelX, 0);
        let y = (pixel / self.width) as f32 + uniform(pixel, sample, 0, Purpose::PixelY, 0);
        let sx = 2.0 * x / self.width as f32 - 1.0;
        let sy = 1.0 - 2.0 * y / self.height as f32;
        let dir = (self.forward + self.right * sx + self.up * sy).normalize();
        RayRecord {
            origin: self.eye.into(),
            t_min: 0.0,
            dir: dir.into(),
            t_max: f32::INFINITY,
            throughput: [1.0; 3],
            pixel,
            sample,
            depth: 0,
            kind: RayKind::Radiance as u8,
            ..bytemuck::Zeroable::zeroed()
        }
    }
}
