//! Admission: what a job's frame will need, checked at submit against `--max-frame-bytes` and
//! the free disk of the data directory, so a job that cannot fit is refused with
//! `RESOURCE_EXHAUSTED` (naming the figure and the limit) instead of breaking the farm later.

use std::path::Path;

use rayfarm_core::ray::RayRecord;
use rayfarm_core::render::Film;
use rayfarm_core::render::local::FrameSpec;
use rayfarm_core::tile::{TILE_SIZE, TileGrid};
use rayfarm_core::units::format_bytes;

/// What one frame needs, in bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Needs {
    /// The film file on the coordinator's disk while the frame runs and is encoded.
    pub film: u64,
    /// The images at their largest (PNG stored uncompressed, EXR scan lines that RLE
    /// could not shrink), kept after the frame.
    pub images: u64,
    /// Camera rays of one tile, which a worker issues in one pass.
    pub worker_tile: u64,
}

impl Needs {
    /// The needs of `frame`; `None` if it does not fit the tile grid.
    pub fn of(frame: &FrameSpec) -> Option<Needs> {
        let grid = TileGrid::new(frame.width, frame.height, TILE_SIZE)?;
        let (w, h) = (u64::from(frame.width), u64::from(frame.height));
        // PNG: a filter byte and three bytes a pixel per row, deflate's stored-block headers
        // (5 bytes per 64 KiB) and the chunks around them.
        let png_raw = h * (1 + 3 * w);
        let png = png_raw + png_raw / 8192 + 4096;
        // EXR: per scan line 12 bytes a pixel (RLE grows incompressible data by at most
        // 1/127), an 8-byte line header and an 8-byte offset; and the header.
        let exr = h * (12 * w + 12 * w / 127 + 16) + 4096;
        let rays = u64::from(TILE_SIZE) * u64::from(TILE_SIZE) * u64::from(frame.spp);
        Some(Needs {
            film: Film::file_bytes(&grid),
            images: png + exr,
            worker_tile: rays * std::mem::size_of::<RayRecord>() as u64,
        })
    }

    /// Refuses needs beyond `max_frame_bytes` (each figure on its own) or beyond the
    /// `free_disk` bytes of `data_dir`; the reason names the figure and the limit.
    pub fn check(
        &self,
        max_frame_bytes: u64,
        data_dir: &Path,
        free_disk: u64,
    ) -> Result<(), String> {
        let figures = [
            ("its film file", self.film),
            ("its images", self.images),
            ("the camera rays of one tile in a worker", self.worker_tile),
        ];
        for (what, bytes) in figures {
            if bytes > max_frame_bytes {
                return Err(format!(
                    "the frame needs {} for {what}, above the coordinator's --max-frame-bytes \
                     of {}",
                    format_bytes(bytes),
                    format_bytes(max_frame_bytes)
                ));
            }
        }
        let disk = self.film + self.images;
        if disk > free_disk {
            return Err(format!(
                "the frame needs {} of disk for its film and images, and {} has {} free",
                format_bytes(disk),
                data_dir.display(),
                format_bytes(free_disk)
            ));
        }
        Ok(())
    }
}

/// Bytes an unprivileged process may still write under `dir`.
pub fn free_disk(dir: &Path) -> std::io::Result<u64> {
    let st = rustix::fs::statvfs(dir)?;
    Ok(st.f_bavail.saturating_mul(st.f_frsize))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(width: u32, height: u32, spp: u32) -> FrameSpec {
        FrameSpec {
            width,
            height,
            spp,
            max_depth: 0,
            camera: None,
        }
    }

    #[test]
    fn the_largest_frame_needs_six_gib_of_film_and_fits_the_default_limit() {
        let n = Needs::of(&frame(16384, 16384, 1)).unwrap();
        assert_eq!(n.film, 6 << 30);
        assert!(
            n.images > (3 << 30) + (768 << 20) && n.images < 4 << 30,
            "{n:?}"
        );
        assert_eq!(n.worker_tile, 1024 * 104);
        n.check(16 << 30, Path::new("/d"), 11 << 30).unwrap();
    }

    #[test]
    fn needs_past_a_limit_are_refused_naming_the_figure_and_the_limit() {
        let n = Needs::of(&frame(4096, 4096, 65536)).unwrap();
        let e = n.check(1 << 30, Path::new("/d"), u64::MAX).unwrap_err();
        assert!(e.contains("384.0 MiB") || e.contains("6.5 GiB"), "{e}");
        assert!(e.contains("--max-frame-bytes of 1.0 GiB"), "{e}");
        let n = Needs::of(&frame(4096, 4096, 1)).unwrap();
        let e = n.check(16 << 30, Path::new("/d"), 100 << 20).unwrap_err();
        assert!(e.contains("/d has 100.0 MiB free"), "{e}");
    }
}
