//! The film: per-pixel sums in fixed point, so the image does not depend on the order in
//! which contributions arrive.

use std::path::Path;
use std::sync::atomic::{AtomicI64, Ordering};

/// One unit of radiance in fixed point.
pub const FIXED_ONE: f64 = (1u64 << 24) as f64;
/// Contributions are clamped here so a pathological path cannot overflow a pixel's sum.
const MAX_CONTRIBUTION: f64 = 1.0e6;

/// Converts one channel of one contribution to fixed point.
#[inline]
pub fn to_fixed(v: f32) -> i64 {
    if v.is_finite() && v > 0.0 {
        (v as f64)
            .min(MAX_CONTRIBUTION)
            .mul_add(FIXED_ONE, 0.5)
            .floor() as i64
    } else {
        0
    }
}

/// What can go wrong writing an image.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// The extension is neither .png nor .exr.
    #[error("{0}: unknown image format (use .png or .exr)")]
    UnknownFormat(String),
    /// Encoding or writing failed.
    #[error("{path}: {source}")]
    Write {
        /// The file.
        path: String,
        /// The cause.
        source: image::ImageError,
    },
}

/// Accumulated light per pixel.
pub struct Film {
    width: u32,
    height: u32,
    spp: u32,
    sums: Vec<AtomicI64>,
}

impl Film {
    /// A black film for `spp` samples per pixel.
    pub fn new(width: u32, height: u32, spp: u32) -> Self {
        let n = width as usize * height as usize * 3;
        Film {
            width,
            height,
            spp,
            sums: (0..n).map(|_| AtomicI64::new(0)).collect(),
        }
    }

    /// A film holding already accumulated fixed-point sums, one `[r, g, b]` per pixel (as
    /// the coordinator assembles them from tile results).
    pub fn from_fixed(width: u32, height: u32, spp: u32, sums: &[[i64; 3]]) -> Self {
        let film = Film::new(width, height, spp);
        for (cells, rgb) in film.sums.chunks_exact(3).zip(sums) {
            for (cell, v) in cells.iter().zip(rgb) {
                cell.store(*v, Ordering::Relaxed);
            }
        }
        film
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Adds light to a pixel; safe from any thread. Out-of-range pixels are ignored.
    pub fn deposit(&self, pixel: u32, rgb: [f32; 3]) {
        let base = pixel as usize * 3;
        if let Some(cells) = self.sums.get(base..base + 3) {
            for (cell, v) in cells.iter().zip(rgb) {
                let f = to_fixed(v);
                if f != 0 {
                    cell.fetch_add(f, Ordering::Relaxed);
                }
            }
        }
    }

    /// The raw sums, three per pixel.
    pub fn fixed_sums(&self) -> Vec<i64> {
        self.sums
            .iter()
            .map(|c| c.load(Ordering::Relaxed))
            .collect()
    }

    /// xxh3-64 of the fixed-point sums: two renders agree to the bit iff their hashes agree.
    pub fn hash(&self) -> u64 {
        let sums = self.fixed_sums();
        xxhash_rust::xxh3::xxh3_64(bytemuck::cast_slice(&sums))
    }

    /// Linear radiance, RGB per pixel, averaged over samples.
    pub fn linear(&self) -> Vec<f32> {
        let scale = 1.0 / (FIXED_ONE * self.spp.max(1) as f64);
        self.sums
            .iter()
            .map(|c| (c.load(Ordering::Relaxed) as f64 * scale) as f32)
            .collect()
    }

    /// Writes `.png` (8-bit sRGB) or `.exr` (linear float) by the path's extension.
    pub fn save(&self, path: &Path) -> Result<(), ImageError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase());
        let err = |source| ImageError::Write {
            path: path.display().to_string(),
            source,
        };
        match ext.as_deref() {
            Some("png") => {
                let bytes: Vec<u8> = self.linear().into_iter().map(srgb_byte).collect();
                image::RgbImage::from_raw(self.width, self.height, bytes)
                    .expect("buffer has width*height*3 bytes")
                    .save(path)
                    .map_err(err)
            }
            Some("exr") => image::Rgb32FImage::from_raw(self.width, self.height, self.linear())
                .expect("buffer has width*height*3 floats")
                .save(path)
                .map_err(err),
            _ => Err(ImageError::UnknownFormat(path.display().to_string())),
        }
    }
}

/// Linear to 8-bit sRGB.
fn srgb_byte(v: f32) -> u8 {
    let v = v.clamp(0.0, 1.0);
    let s = if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0 + 0.5) as u8
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn order_of_deposits_does_not_change_the_hash() {
        let a = Film::new(2, 1, 1);
        let b = Film::new(2, 1, 1);
        let vals = [[0.1, 0.2, 0.3], [1e-7, 5.0, 0.0], [0.333, 0.333, 0.334]];
        for v in vals {
            a.deposit(1, v);
        }
        for v in vals.iter().rev() {
            b.deposit(1, *v);
        }
        assert_eq!(a.hash(), b.hash());
        b.deposit(0, [1e-3, 0.0, 0.0]);
        assert_ne!(a.hash(), b.hash());
    }

    #[test]
    fn bad_values_are_ignored_not_propagated() {
        assert_eq!(to_fixed(f32::NAN), 0);
        assert_eq!(to_fixed(-1.0), 0);
        assert_eq!(to_fixed(1.0), 1 << 24);
        let f = Film::new(1, 1, 1);
        f.deposit(5, [1.0; 3]);
        assert_eq!(f.fixed_sums(), vec![0; 3]);
    }
}
