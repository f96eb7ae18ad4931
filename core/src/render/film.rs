//! The film: per-pixel sums in fixed point, so the image does not depend on the order in
//! which contributions arrive, kept in a file so no process ever holds a whole image.
//!
//! A [`Film`] is a file of finished tiles: each tile of the [`TileGrid`] has a slot of
//! `tile_size²` pixels, three little-endian `i64` sums per pixel in the tile's row-by-row
//! order, written once when the tile is complete. The file is sparse until then, and an
//! unwritten slot reads as black. Whoever renders keeps only the tiles in flight in memory
//! ([`OpenTiles`] in this process, the tile ledger on the coordinator). Encoding, and the
//! image hash, read the file one row of tiles at a time: PNG rows and EXR scan lines are
//! written as they are read, so memory is bounded by one row of tiles whatever the
//! resolution.

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicI64, AtomicU32, AtomicUsize, Ordering};

use xxhash_rust::xxh3::Xxh3Default;

use crate::tile::TileGrid;

pub mod encode;

/// One unit of radiance in fixed point.
pub const FIXED_ONE: f64 = (1u64 << 24) as f64;
/// Contributions are clamped here so a pathological path cannot overflow a pixel's sum.
const MAX_CONTRIBUTION: f64 = 1.0e6;
/// Bytes of one pixel in the film file: three `i64` sums.
pub const PIXEL_BYTES: u64 = 24;

/// Converts one channel of one contribution to fixed point.
#[inline]
pub fn to_fixed(v: f32) -> i64 {
    if v.is_finite() && v > 0.0 {
        // An f32 times 2^24 is exact in f64, so the plain product and sum round once, as a
        // fused multiply-add would; the sum is positive and bounded, so truncation is the
        // floor. No libm calls (they were a fifth of every deposit).
        ((v as f64).min(MAX_CONTRIBUTION) * FIXED_ONE + 0.5) as i64
    } else {
        0
    }
}

/// What can go wrong with a film or writing an image. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// The extension is neither .png nor .exr.
    #[error("{0}: unknown image format (use .png or .exr)")]
    UnknownFormat(String),
    /// The film file could not be created, written or read.
    #[error("film {path}: {source}")]
    Film {
        /// The film file (or the directory of an unnamed one).
        path: String,
        /// The cause.
        source: std::io::Error,
    },
    /// Encoding or writing an image failed.
    #[error("{path}: {reason}")]
    Write {
        /// The image file.
        path: String,
        /// The cause.
        reason: String,
    },
}

/// A film file: the fixed-point sums of finished tiles (see the module documentation).
pub struct Film {
    file: File,
    /// What errors name: the file, or for an unnamed temporary file its directory.
    shown: String,
    /// A named file removed when the film is dropped.
    remove: Option<PathBuf>,
    grid: TileGrid,
    spp: u32,
    /// Per tile, the samples its slot holds (see [`TileSamples`]).
    samples: Vec<TileSamples>,
}

/// How many samples of a tile the film holds, readable while the tile is written: a
/// sequence lock (odd `version` while the slot is being changed), so a preview read beside
/// a progressive subframe's additions sees each tile's sums with their own sample count.
#[derive(Default)]
struct TileSamples {
    version: AtomicU32,
    samples: AtomicU32,
}

fn tile_samples(grid: &TileGrid) -> Vec<TileSamples> {
    (0..grid.count()).map(|_| TileSamples::default()).collect()
}

impl Film {
    /// Bytes the film file of `grid` takes on disk once every tile is written.
    pub fn file_bytes(grid: &TileGrid) -> u64 {
        u64::from(grid.count()) * Self::slot_pixels(grid) * PIXEL_BYTES
    }

    fn slot_pixels(grid: &TileGrid) -> u64 {
        u64::from(grid.tile_size()) * u64::from(grid.tile_size())
    }

    /// A black film in a new file at `path` (replacing one left there), removed when the
    /// film is dropped.
    pub fn create(path: &Path, grid: TileGrid, spp: u32) -> Result<Film, ImageError> {
        let shown = path.display().to_string();
        let err = |source| ImageError::Film {
            path: shown.clone(),
            source,
        };
        let file = File::options()
            .read(true)
            .write(true)
            .create(true)
            .truncate(true)
            .open(path)
            .map_err(err)?;
        let film = Film {
            file,
            shown: shown.clone(),
            remove: Some(path.to_path_buf()),
            samples: tile_samples(&grid),
            grid,
            spp,
        };
        film.file.set_len(Self::file_bytes(&grid)).map_err(err)?;
        Ok(film)
    }

    /// A black film in an unnamed temporary file in `dir`, gone when the film is dropped.
    pub fn temporary_in(dir: &Path, grid: TileGrid, spp: u32) -> Result<Film, ImageError> {
        let shown = format!("(temporary) in {}", dir.display());
        let err = |source| ImageError::Film {
            path: shown.clone(),
            source,
        };
        let file = tempfile::tempfile_in(dir).map_err(err)?;
        file.set_len(Self::file_bytes(&grid)).map_err(err)?;
        Ok(Film {
            file,
            shown,
            remove: None,
            samples: tile_samples(&grid),
            grid,
            spp,
        })
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.grid.width()
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.grid.height()
    }

    /// The tiles the film is cut into.
    pub fn grid(&self) -> &TileGrid {
        &self.grid
    }

    fn io_error(&self, source: std::io::Error) -> ImageError {
        ImageError::Film {
            path: self.shown.clone(),
            source,
        }
    }

    /// Writes a finished tile's sums, in [`TileGrid::pixels`] order, as all the frame's
    /// samples of it. Fewer sums than the tile has pixels leave the rest black; an unknown
    /// tile or too many sums is refused.
    pub fn write_tile(&self, tile: u32, sums: &[[i64; 3]]) -> Result<(), ImageError> {
        self.check_tile(tile, sums)?;
        self.change_tile(tile, self.spp, |_| sums.to_vec())
    }

    /// Adds a tile's sums of `samples` more samples (a progressive subframe's) to what the
    /// film holds of it: integers, so the film after every subframe holds exactly the sums
    /// of a one-pass render.
    pub fn add_tile(&self, tile: u32, sums: &[[i64; 3]], samples: u32) -> Result<(), ImageError> {
        self.check_tile(tile, sums)?;
        let held = self.tile_samples(tile);
        self.change_tile(tile, held.saturating_add(samples), |old| {
            let mut new = old;
            new.resize(sums.len().max(new.len()), [0; 3]);
            for (n, s) in new.iter_mut().zip(sums) {
                for (a, b) in n.iter_mut().zip(s) {
                    *a = a.wrapping_add(*b);
                }
            }
            new
        })
    }

    /// Samples of `tile` the film holds (0: none written yet).
    pub fn tile_samples(&self, tile: u32) -> u32 {
        self.samples
            .get(tile as usize)
            .map_or(0, |t| t.samples.load(Ordering::Acquire))
    }

    fn check_tile(&self, tile: u32, sums: &[[i64; 3]]) -> Result<(), ImageError> {
        let pixels = self.grid.tile_pixel_count(tile);
        if tile >= self.grid.count() || sums.len() > pixels {
            return Err(self.io_error(std::io::Error::other(format!(
                "tile {tile} with {} pixel sums does not fit the film",
                sums.len()
            ))));
        }
        Ok(())
    }

    /// Replaces `tile`'s sums by `change` of them (read from the file), now holding
    /// `samples` samples. One writer at a time (the renderer's commits), readers any time.
    fn change_tile(
        &self,
        tile: u32,
        samples: u32,
        change: impl FnOnce(Vec<[i64; 3]>) -> Vec<[i64; 3]>,
    ) -> Result<(), ImageError> {
        let slot = &self.samples[tile as usize];
        let offset = u64::from(tile) * Self::slot_pixels(&self.grid) * PIXEL_BYTES;
        let pixels = self.grid.tile_pixel_count(tile);
        let old = if slot.samples.load(Ordering::Acquire) == 0 {
            Vec::new()
        } else {
            let mut bytes = vec![0u8; pixels * PIXEL_BYTES as usize];
            self.file
                .read_exact_at(&mut bytes, offset)
                .map_err(|e| self.io_error(e))?;
            decode_sums(&bytes)
        };
        let new = change(old);
        let mut bytes = Vec::with_capacity(new.len() * PIXEL_BYTES as usize);
        for rgb in &new {
            for c in rgb {
                bytes.extend_from_slice(&c.to_le_bytes());
            }
        }
        slot.version.fetch_add(1, Ordering::AcqRel);
        let written = self.file.write_all_at(&bytes, offset);
        slot.samples.store(samples, Ordering::Release);
        slot.version.fetch_add(1, Ordering::AcqRel);
        written.map_err(|e| self.io_error(e))
    }

    /// The versions of a row of tiles, or `None` while one of them is being written.
    fn band_versions(&self, band: u32) -> Option<Vec<u32>> {
        let tiles_x = self.grid.tiles_x();
        let first = (band * tiles_x) as usize;
        let versions: Vec<u32> = self.samples[first..first + tiles_x as usize]
            .iter()
            .map(|t| t.version.load(Ordering::Acquire))
            .collect();
        versions.iter().all(|v| v % 2 == 0).then_some(versions)
    }

    /// Reads one row of tiles as image rows: `rows` rows of `width` pixels, row-major.
    fn read_band(
        &self,
        band: u32,
        buf: &mut Vec<u8>,
        rows: &mut Vec<[i64; 3]>,
    ) -> Result<(), ImageError> {
        let g = &self.grid;
        let slot = (Self::slot_pixels(g) * PIXEL_BYTES) as usize;
        let tiles_x = g.tiles_x() as usize;
        buf.resize(tiles_x * slot, 0);
        let first = u64::from(band) * u64::from(g.tiles_x());
        self.file
            .read_exact_at(buf, first * slot as u64)
            .map_err(|e| self.io_error(e))?;
        let ts = g.tile_size();
        let y0 = band * ts;
        let band_rows = ts.min(g.height() - y0) as usize;
        let width = g.width() as usize;
        rows.clear();
        rows.resize(band_rows * width, [0; 3]);
        for tx in 0..tiles_x {
            let x0 = tx * ts as usize;
            let tw = (ts as usize).min(width - x0);
            let tile = &buf[tx * slot..(tx + 1) * slot];
            for r in 0..band_rows {
                let src = &tile[r * tw * PIXEL_BYTES as usize..(r + 1) * tw * PIXEL_BYTES as usize];
                let dst = &mut rows[r * width + x0..r * width + x0 + tw];
                for (px, bytes) in dst.iter_mut().zip(src.chunks_exact(PIXEL_BYTES as usize)) {
                    for (c, b) in px.iter_mut().zip(bytes.chunks_exact(8)) {
                        *c = i64::from_le_bytes(b.try_into().expect("8 bytes"));
                    }
                }
            }
        }
        Ok(())
    }

    /// Calls `each` with every image row, top to bottom, reading one row of tiles at a time.
    fn for_each_row(
        &self,
        mut each: impl FnMut(&[[i64; 3]]) -> Result<(), ImageError>,
    ) -> Result<(), ImageError> {
        let (mut buf, mut rows) = (Vec::new(), Vec::new());
        let width = self.width() as usize;
        for band in 0..self.grid.tiles_y() {
            self.read_band(band, &mut buf, &mut rows)?;
            for row in rows.chunks_exact(width) {
                each(row)?;
            }
        }
        Ok(())
    }

    /// xxh3-64 of the fixed-point sums in pixel order (three `i64` per pixel, row-major):
    /// two renders agree to the bit iff their hashes agree.
    pub fn hash(&self) -> Result<u64, ImageError> {
        let mut hasher = Xxh3Default::new();
        self.for_each_row(|row| {
            hasher.update(bytemuck::cast_slice(row));
            Ok(())
        })?;
        Ok(hasher.digest())
    }

    /// Reads a row of tiles as [`read_band`](Self::read_band) does, while no tile of it is
    /// being written, and returns the samples each of its tiles holds. A writer changes a
    /// tile in well under a millisecond, so a few tries do; past them the last read is used
    /// (a preview, never a result, is made of it).
    fn read_band_steady(
        &self,
        band: u32,
        buf: &mut Vec<u8>,
        rows: &mut Vec<[i64; 3]>,
    ) -> Result<Vec<u32>, ImageError> {
        let tiles_x = self.grid.tiles_x();
        let held = || -> Vec<u32> {
            (band * tiles_x..(band + 1) * tiles_x)
                .map(|t| self.tile_samples(t))
                .collect()
        };
        for _ in 0..1000 {
            let Some(before) = self.band_versions(band) else {
                std::thread::yield_now();
                continue;
            };
            self.read_band(band, buf, rows)?;
            let counts = held();
            if self.band_versions(band).as_ref() == Some(&before) {
                return Ok(counts);
            }
        }
        self.read_band(band, buf, rows)?;
        Ok(held())
    }

    /// Linear radiance of a row of sums, averaged over samples, RGB per pixel.
    fn linear(&self, row: &[[i64; 3]], out: &mut Vec<f32>) {
        let scale = 1.0 / (FIXED_ONE * self.spp.max(1) as f64);
        out.clear();
        out.extend(row.iter().flatten().map(|&c| (c as f64 * scale) as f32));
    }
}

/// Little-endian `i64` triples as pixel sums.
fn decode_sums(bytes: &[u8]) -> Vec<[i64; 3]> {
    bytes
        .chunks_exact(PIXEL_BYTES as usize)
        .map(|px| {
            let mut rgb = [0i64; 3];
            for (c, b) in rgb.iter_mut().zip(px.chunks_exact(8)) {
                *c = i64::from_le_bytes(b.try_into().expect("8 bytes"));
            }
            rgb
        })
        .collect()
}

impl Drop for Film {
    fn drop(&mut self) {
        if let Some(path) = &self.remove {
            let _ = std::fs::remove_file(path);
        }
    }
}

/// The sums of the tiles still being rendered in this process, safe to add to from any
/// thread. A tile's sums are allocated at its first contribution and leave memory for the
/// film file when the tile is committed, so memory holds only the tiles in flight.
pub struct OpenTiles {
    grid: TileGrid,
    slots: Vec<OnceLock<Box<[AtomicI64]>>>,
    committed: Vec<bool>,
    allocated: AtomicUsize,
}

impl OpenTiles {
    /// No tile open yet.
    pub fn new(grid: TileGrid) -> Self {
        OpenTiles {
            grid,
            slots: (0..grid.count()).map(|_| OnceLock::new()).collect(),
            committed: vec![false; grid.count() as usize],
            allocated: AtomicUsize::new(0),
        }
    }

    /// Adds light to `pixel` of `tile`; contributions to pixels outside the tile, or to a
    /// committed tile, are ignored.
    pub fn deposit(&self, tile: u32, pixel: u32, rgb: [f32; 3]) {
        let fixed = rgb.map(to_fixed);
        if fixed == [0; 3] {
            return;
        }
        let Some(local) = self.grid.local_index(tile, pixel) else {
            return;
        };
        if self.committed[tile as usize] {
            return;
        }
        let cells = self.slots[tile as usize].get_or_init(|| {
            self.allocated.fetch_add(1, Ordering::Relaxed);
            let n = self.grid.tile_pixel_count(tile) * 3;
            (0..n).map(|_| AtomicI64::new(0)).collect()
        });
        for (cell, v) in cells[local * 3..local * 3 + 3].iter().zip(fixed) {
            if v != 0 {
                cell.fetch_add(v, Ordering::Relaxed);
            }
        }
    }

    /// Tiles holding sums in memory.
    pub fn in_memory(&self) -> usize {
        self.allocated.load(Ordering::Relaxed)
    }

    /// Writes `tile`'s sums to `film` and frees them; later deposits to it are ignored.
    pub fn commit(&mut self, tile: u32, film: &Film) -> Result<(), ImageError> {
        let Some(done) = self.committed.get_mut(tile as usize) else {
            return Ok(());
        };
        if std::mem::replace(done, true) {
            return Ok(());
        }
        if let Some(cells) = self.slots[tile as usize].take() {
            self.allocated.fetch_sub(1, Ordering::Relaxed);
            let sums: Vec<[i64; 3]> = cells
                .chunks_exact(3)
                .map(|c| [0, 1, 2].map(|i| c[i].load(Ordering::Relaxed)))
                .collect();
            film.write_tile(tile, &sums)?;
        }
        Ok(())
    }

    /// Whether `tile` has been committed.
    pub fn is_committed(&self, tile: u32) -> bool {
        self.committed.get(tile as usize).copied().unwrap_or(false)
    }
}

#[cfg(test)]
mod tests;
