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
use std::io::{BufWriter, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicI64, AtomicU32, AtomicUsize, Ordering};

use exr::block::writer::ChunksWriter;
use exr::block::{BlockIndex, UncompressedBlock};
use exr::meta::BlockDescription;
use exr::meta::attribute::{ChannelDescription, ChannelList, Compression, LineOrder, SampleType};
use exr::meta::header::Header;
use xxhash_rust::xxh3::Xxh3Default;

use crate::frame::TileGrid;

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

    /// Writes `.png` (8-bit sRGB) or `.exr` (linear float) by the path's extension; returns
    /// the image hash.
    pub fn save(&self, path: &Path) -> Result<u64, ImageError> {
        self.save_all(&[path])
    }

    /// Writes every image in `paths` (each `.png` or `.exr`, by its extension) in one pass
    /// over the film; returns the image hash ([`hash`](Self::hash)).
    pub fn save_all(&self, paths: &[&Path]) -> Result<u64, ImageError> {
        let mut pngs = Vec::new();
        let mut exrs = Vec::new();
        for path in paths {
            match image_kind(path) {
                Some(Kind::Png) => pngs.push(PngRows::create(path, self.width(), self.height())?),
                Some(Kind::Exr) => exrs.push(*path),
                None => return Err(ImageError::UnknownFormat(path.display().to_string())),
            }
        }
        let mut hasher = Xxh3Default::new();
        let mut each_row = |row: &[[i64; 3]], linear: &[f32]| {
            hasher.update(bytemuck::cast_slice(row));
            for png in &mut pngs {
                png.write_row(linear)?;
            }
            Ok(())
        };
        match exrs.as_slice() {
            [] => {
                let mut linear = Vec::new();
                self.for_each_row(|row| {
                    self.linear(row, &mut linear);
                    each_row(row, &linear)
                })?
            }
            // More than one EXR is never asked for; one pass writes one, the rest re-read.
            [first, rest @ ..] => {
                write_exr(self, first, &mut each_row)?;
                for path in rest {
                    write_exr(self, path, &mut |_, _| Ok(()))?;
                }
            }
        }
        for png in pngs {
            png.finish()?;
        }
        Ok(hasher.digest())
    }

    /// An 8-bit sRGB PNG, in memory, of the tiles written so far, each averaged over the
    /// samples the film holds of it (a progressive frame's tiles may hold different counts
    /// mid-subframe): a running frame's preview. Tiles not written show a dark checkerboard.
    /// An image longer than `max_side` pixels on a side is shrunk by the smallest whole
    /// factor that fits, each preview pixel the mean of the linear values it covers. Not
    /// shrunk and with every tile holding all samples, the bytes are those
    /// [`save`](Self::save) writes to a `.png`. Safe beside a writer: each row of tiles is
    /// read again until no tile of it changed during the read.
    pub fn preview_png(&self, max_side: u32) -> Result<Preview, ImageError> {
        let (w, h) = (self.width(), self.height());
        let factor = w.max(h).div_ceil(max_side.max(1)).max(1);
        let (pw, ph) = (w.div_ceil(factor), h.div_ceil(factor));
        let bytes = MemoryPng::default();
        let shown = Path::new("(preview)");
        let mut png = PngRows::to_writer(bytes.clone(), shown, pw, ph)?;
        let ts = self.grid.tile_size();
        let mut sums = vec![0f64; pw as usize * 3];
        let mut counts = vec![0u32; pw as usize];
        let mut out = Vec::new();
        let (mut buf, mut rows) = (Vec::new(), Vec::new());
        let mut y = 0u32;
        for band in 0..self.grid.tiles_y() {
            let held = self.read_band_steady(band, &mut buf, &mut rows)?;
            let scales: Vec<f64> = held
                .iter()
                .map(|&n| 1.0 / (FIXED_ONE * n.max(1) as f64))
                .collect();
            for row in rows.chunks_exact(w as usize) {
                for x in 0..w {
                    let px = (x / factor) as usize;
                    let tile_x = (x / ts) as usize;
                    let sum = &mut sums[px * 3..px * 3 + 3];
                    if held[tile_x] > 0 {
                        // The same value `linear` gives a tile of all the frame's samples.
                        for (s, &c) in sum.iter_mut().zip(&row[x as usize]) {
                            *s += f64::from((c as f64 * scales[tile_x]) as f32);
                        }
                    } else {
                        let light = ((x / factor / 8) + (y / factor / 8)) % 2 == 1;
                        let v = if light { CHECKER_LIGHT } else { CHECKER_DARK };
                        sum.iter_mut().for_each(|s| *s += v);
                    }
                    counts[px] += 1;
                }
                y += 1;
                if y.is_multiple_of(factor) || y == h {
                    out.clear();
                    for (sum, &n) in sums.chunks_exact(3).zip(&counts) {
                        // Divided by 1 when not shrunk: the film's own values, to the bit.
                        out.extend(sum.iter().map(|&s| (s / f64::from(n)) as f32));
                    }
                    png.write_row(&out)?;
                    sums.fill(0.0);
                    counts.fill(0);
                }
            }
        }
        png.finish()?;
        Ok(Preview {
            png: bytes.0.take(),
            width: pw,
            height: ph,
            factor,
        })
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

/// A preview image made by [`Film::preview_png`].
#[derive(Clone, Debug)]
pub struct Preview {
    /// The PNG file's bytes.
    pub png: Vec<u8>,
    /// Its width and height in pixels.
    pub width: u32,
    pub height: u32,
    /// How many film pixels a side of one preview pixel covers (1: full size).
    pub factor: u32,
}

/// Linear values of the checkerboard that stands for tiles not committed yet: dark enough
/// that rendered tiles stand out against it.
const CHECKER_DARK: f64 = 0.004;
const CHECKER_LIGHT: f64 = 0.012;

/// A PNG's bytes in memory, shared with the encoder writing them (which owns its writer).
#[derive(Clone, Default)]
struct MemoryPng(std::rc::Rc<std::cell::RefCell<Vec<u8>>>);

impl Write for MemoryPng {
    fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
        self.0.borrow_mut().extend_from_slice(bytes);
        Ok(bytes.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Drop for Film {
    fn drop(&mut self) {
        if let Some(path) = &self.remove {
            let _ = std::fs::remove_file(path);
        }
    }
}

enum Kind {
    Png,
    Exr,
}

fn image_kind(path: &Path) -> Option<Kind> {
    let ext = path.extension()?.to_str()?.to_ascii_lowercase();
    match ext.as_str() {
        "png" => Some(Kind::Png),
        "exr" => Some(Kind::Exr),
        _ => None,
    }
}

fn write_error(path: &Path, reason: impl ToString) -> ImageError {
    ImageError::Write {
        path: path.display().to_string(),
        reason: reason.to_string(),
    }
}

/// A PNG written row by row, to a file or (a preview) to memory.
struct PngRows<W: Write + 'static> {
    path: PathBuf,
    stream: png::StreamWriter<'static, W>,
    bytes: Vec<u8>,
}

impl PngRows<BufWriter<File>> {
    fn create(path: &Path, width: u32, height: u32) -> Result<Self, ImageError> {
        let file = File::create(path).map_err(|e| write_error(path, e))?;
        Self::to_writer(BufWriter::new(file), path, width, height)
    }
}

impl<W: Write + 'static> PngRows<W> {
    /// The one encoder setup of every PNG, so a preview of a whole film is the same bytes
    /// as the saved image.
    fn to_writer(out: W, path: &Path, width: u32, height: u32) -> Result<Self, ImageError> {
        let mut encoder = png::Encoder::new(out, width, height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        // fdeflate: an order of magnitude faster than zlib's levels on large frames.
        encoder.set_compression(png::Compression::Fast);
        let stream = encoder
            .write_header()
            .and_then(|w| w.into_stream_writer())
            .map_err(|e| write_error(path, e))?;
        Ok(PngRows {
            path: path.to_path_buf(),
            stream,
            bytes: Vec::new(),
        })
    }

    fn write_row(&mut self, linear: &[f32]) -> Result<(), ImageError> {
        self.bytes.clear();
        self.bytes.extend(linear.iter().map(|&v| srgb_byte(v)));
        self.stream
            .write_all(&self.bytes)
            .map_err(|e| write_error(&self.path, e))
    }

    fn finish(self) -> Result<(), ImageError> {
        let path = self.path;
        self.stream.finish().map_err(|e| write_error(&path, e))
    }
}

/// Called with each image row's sums and linear values, top to bottom.
type RowSink<'a> = dyn FnMut(&[[i64; 3]], &[f32]) -> Result<(), ImageError> + 'a;

/// Writes the film as an RLE-compressed scan-line EXR (R, G, B as 32-bit floats), calling
/// `each_row` with every row's sums and linear values as they go by.
fn write_exr(film: &Film, path: &Path, each_row: &mut RowSink<'_>) -> Result<(), ImageError> {
    let (width, height) = (film.width() as usize, film.height() as usize);
    let channels = ChannelList::new(
        ["B", "G", "R"]
            .into_iter()
            .map(|n| ChannelDescription::named(n, SampleType::F32))
            .collect(),
    );
    let header = Header::new("rayfarm".into(), (width, height), channels.list).with_encoding(
        Compression::RLE,
        BlockDescription::ScanLines,
        LineOrder::Increasing,
    );
    let file = File::create(path).map_err(|e| write_error(path, e))?;
    // The film's and the callback's errors travel through exr's closure as I/O errors and
    // come out here.
    let mut failure: Option<ImageError> = None;
    let result = exr::block::write(
        BufWriter::new(file),
        smallvec_of(header),
        true,
        |meta, chunks| {
            let mut linear = Vec::with_capacity(width * 3);
            let mut y = 0;
            let rows = film.for_each_row(|row| {
                film.linear(row, &mut linear);
                each_row(row, &linear)?;
                // One block per scan line (RLE); per channel, in the header's order B, G, R.
                let mut data = Vec::with_capacity(width * 12);
                for channel in [2, 1, 0] {
                    for px in linear.chunks_exact(3) {
                        data.extend_from_slice(&px[channel].to_ne_bytes());
                    }
                }
                let block = UncompressedBlock {
                    index: BlockIndex {
                        layer: 0,
                        pixel_position: exr::math::Vec2(0, y),
                        pixel_size: exr::math::Vec2(width, 1),
                        level: exr::math::Vec2(0, 0),
                    },
                    data,
                };
                block
                    .compress_to_chunk(&meta.headers)
                    .and_then(|chunk| chunks.write_chunk(y, chunk))
                    .map_err(|e| write_error(path, e))?;
                y += 1;
                Ok(())
            });
            match rows {
                Ok(()) => Ok(()),
                Err(e) => {
                    failure = Some(e);
                    Err(exr::error::Error::Io(std::io::Error::other("stopped")))
                }
            }
        },
    );
    match (failure, result) {
        (Some(e), _) => Err(e),
        (None, Err(e)) => Err(write_error(path, e)),
        (None, Ok(())) => Ok(()),
    }
}

fn smallvec_of(header: Header) -> exr::meta::Headers {
    let mut headers = exr::meta::Headers::new();
    headers.push(header);
    headers
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
mod tests {

    /// The deposit's fast conversion is the reference formula (fused multiply-add, then
    /// floor) to the bit, for every kind of value, rounding ties and the clamp included.
    #[test]
    fn to_fixed_equals_the_fused_multiply_add_and_floor() {
        let reference = |v: f32| {
            if v.is_finite() && v > 0.0 {
                (v as f64)
                    .min(MAX_CONTRIBUTION)
                    .mul_add(FIXED_ONE, 0.5)
                    .floor() as i64
            } else {
                0
            }
        };
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        let mut values = vec![
            0.0,
            -0.0,
            1.0,
            0.5,
            1e6,
            1e6 + 64.0,
            f32::MAX,
            f32::MIN_POSITIVE,
        ];
        values.extend([
            f32::INFINITY,
            f32::NAN,
            -1.0,
            1.0 / 16_777_216.0,
            1.5 / 16_777_216.0,
        ]);
        for _ in 0..1_000_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            values.push(f32::from_bits(x as u32));
            // Small values, where ties at half a fixed-point unit happen.
            values.push((x >> 40) as f32 / 16_777_216.0 / 2.0);
        }
        for v in values {
            assert_eq!(to_fixed(v), reference(v), "{v:e} ({:#x})", v.to_bits());
        }
    }

    use super::*;

    fn grid(w: u32, h: u32) -> TileGrid {
        TileGrid::new(w, h, 4).unwrap()
    }

    /// The sums of every pixel, row-major, as the hash covers them.
    fn film_with(dir: &Path, g: TileGrid, sums: impl Fn(u32) -> [i64; 3]) -> Film {
        let film = Film::temporary_in(dir, g, 1).unwrap();
        for tile in 0..g.count() {
            let s: Vec<[i64; 3]> = g.pixels(tile).map(&sums).collect();
            film.write_tile(tile, &s).unwrap();
        }
        film
    }

    #[test]
    fn a_full_size_preview_of_a_whole_film_is_the_saved_png() {
        let dir = tempfile::tempdir().unwrap();
        let g = grid(10, 7);
        let film = film_with(dir.path(), g, |p| [p as i64 * 40_000, 1 << 22, 0]);
        let saved = dir.path().join("image.png");
        film.save(&saved).unwrap();
        let preview = film.preview_png(1024).unwrap();
        assert_eq!((preview.width, preview.height, preview.factor), (10, 7, 1));
        assert_eq!(preview.png, std::fs::read(&saved).unwrap());
        // A tile not written is drawn as the checkerboard, not its sums.
        let part = Film::temporary_in(dir.path(), g, 1).unwrap();
        for tile in 1..g.count() {
            let s: Vec<[i64; 3]> = g
                .pixels(tile)
                .map(|p| [p as i64 * 40_000, 1 << 22, 0])
                .collect();
            part.write_tile(tile, &s).unwrap();
        }
        assert_ne!(part.preview_png(1024).unwrap().png, preview.png);
    }

    #[test]
    fn a_preview_longer_than_its_bound_is_shrunk_by_a_whole_factor() {
        let dir = tempfile::tempdir().unwrap();
        let g = grid(10, 7);
        let film = film_with(dir.path(), g, |_| [1 << 23, 1 << 23, 1 << 23]);
        let preview = film.preview_png(4).unwrap();
        // ceil(10 / 4) = 3; 10 / 3 and 7 / 3 rounded up.
        assert_eq!((preview.width, preview.height, preview.factor), (4, 3, 3));
        let mut decoder = png::Decoder::new(std::io::Cursor::new(preview.png))
            .read_info()
            .unwrap();
        let mut pixels = vec![0; decoder.output_buffer_size().unwrap()];
        decoder.next_frame(&mut pixels).unwrap();
        // Every film pixel is 0.5: so is every mean of them.
        assert!(pixels.iter().all(|&b| b == srgb_byte(0.5)));
    }

    #[test]
    fn subframes_added_tile_by_tile_make_the_one_pass_film_and_previews_average_each_tile() {
        let dir = tempfile::tempdir().unwrap();
        let g = grid(10, 7);
        // Three subframes of 1, 1 and 2 samples; the one pass has all 4.
        let part = |p: u32, k: i64| [p as i64 * 1000 + k, (1 << 24) * k, -k];
        let one = Film::temporary_in(dir.path(), g, 4).unwrap();
        let progressive = Film::temporary_in(dir.path(), g, 4).unwrap();
        for tile in 0..g.count() {
            let sub = |k: i64| -> Vec<[i64; 3]> { g.pixels(tile).map(|p| part(p, k)).collect() };
            let total: Vec<[i64; 3]> = (0..sub(1).len())
                .map(|i| [0, 1, 2].map(|c| sub(1)[i][c] + sub(1)[i][c] + sub(2)[i][c]))
                .collect();
            one.write_tile(tile, &total).unwrap();
            for (k, n) in [(1, 1), (1, 1), (2, 2)] {
                progressive.add_tile(tile, &sub(k), n).unwrap();
            }
            assert_eq!(progressive.tile_samples(tile), 4);
        }
        assert_eq!(progressive.hash().unwrap(), one.hash().unwrap());
        assert_eq!(
            progressive.preview_png(1024).unwrap().png,
            one.preview_png(1024).unwrap().png
        );
        // One subframe of one sample of light 1.0 everywhere previews as 1.0, not 1/4.
        let first = Film::temporary_in(dir.path(), g, 4).unwrap();
        for tile in 0..g.count() {
            let n = g.tile_pixel_count(tile);
            first.add_tile(tile, &vec![[1 << 24; 3]; n], 1).unwrap();
        }
        let preview = first.preview_png(1024).unwrap();
        let mut decoder = png::Decoder::new(std::io::Cursor::new(preview.png))
            .read_info()
            .unwrap();
        let mut pixels = vec![0; decoder.output_buffer_size().unwrap()];
        decoder.next_frame(&mut pixels).unwrap();
        assert!(pixels.iter().all(|&b| b == srgb_byte(1.0)));
    }

    #[test]
    fn the_hash_is_the_xxh3_of_the_sums_in_pixel_order() {
        let dir = tempfile::tempdir().unwrap();
        // Edge tiles smaller than the slot on both sides.
        let g = grid(10, 7);
        let value = |p: u32| [p as i64, -(p as i64) * 3, i64::MAX - p as i64];
        let film = film_with(dir.path(), g, value);
        let flat: Vec<i64> = (0..70).flat_map(value).collect();
        let expected = xxhash_rust::xxh3::xxh3_64(bytemuck::cast_slice(&flat));
        assert_eq!(film.hash().unwrap(), expected);
        let png = dir.path().join("a.png");
        let exr = dir.path().join("a.exr");
        assert_eq!(film.save_all(&[&png, &exr]).unwrap(), expected);
    }

    #[test]
    fn images_decode_to_the_film_row_by_row() {
        let dir = tempfile::tempdir().unwrap();
        let g = grid(9, 6);
        let value = |p: u32| {
            let v = (p as f64 / 54.0 * FIXED_ONE) as i64;
            [v, v / 2, FIXED_ONE as i64 - v]
        };
        let film = film_with(dir.path(), g, value);
        let (png, exr) = (dir.path().join("a.png"), dir.path().join("a.exr"));
        film.save_all(&[&png, &exr]).unwrap();
        let decoded = image::open(&png).unwrap().to_rgb8();
        assert_eq!(decoded.dimensions(), (9, 6));
        let exr_img = image::open(&exr).unwrap().to_rgb32f();
        assert_eq!(exr_img.dimensions(), (9, 6));
        for p in 0..54u32 {
            let (x, y) = (p % 9, p / 9);
            let linear = value(p).map(|c| (c as f64 / FIXED_ONE) as f32);
            assert_eq!(exr_img.get_pixel(x, y).0, linear, "pixel {p}");
            assert_eq!(
                decoded.get_pixel(x, y).0,
                linear.map(srgb_byte),
                "pixel {p}"
            );
        }
    }

    #[test]
    fn unwritten_tiles_are_black_and_bad_tiles_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let g = grid(8, 8);
        let path = dir.path().join("film.bin");
        let film = Film::create(&path, g, 1).unwrap();
        assert_eq!(
            std::fs::metadata(&path).unwrap().len(),
            Film::file_bytes(&g)
        );
        film.write_tile(3, &[[1, 2, 3]]).unwrap();
        let mut flat = vec![0i64; 64 * 3];
        // Tile 3 is the bottom-right one; its first pixel is (4, 4).
        flat[(4 * 8 + 4) * 3..(4 * 8 + 4) * 3 + 3].copy_from_slice(&[1, 2, 3]);
        assert_eq!(
            film.hash().unwrap(),
            xxhash_rust::xxh3::xxh3_64(bytemuck::cast_slice(&flat))
        );
        assert!(film.write_tile(4, &[]).is_err());
        assert!(film.write_tile(0, &[[0; 3]; 17]).is_err());
        drop(film);
        assert!(!path.exists(), "a named film is removed with it");
    }

    #[test]
    fn open_tiles_commit_to_the_film_and_free_their_memory() {
        let dir = tempfile::tempdir().unwrap();
        let g = grid(8, 4);
        let film = Film::temporary_in(dir.path(), g, 1).unwrap();
        let mut open = OpenTiles::new(g);
        let vals = [[0.1, 0.2, 0.3], [1e-7, 5.0, 0.0], [0.333, 0.333, 0.334]];
        for v in vals {
            open.deposit(0, 1, v);
        }
        open.deposit(1, 4, [1.0; 3]);
        open.deposit(1, 0, [1.0; 3]); // pixel 0 is not in tile 1: ignored
        assert_eq!(open.in_memory(), 2);
        open.commit(0, &film).unwrap();
        open.commit(1, &film).unwrap();
        open.deposit(1, 4, [1.0; 3]); // committed: ignored
        assert_eq!(open.in_memory(), 0);
        let mut flat = vec![0i64; 32 * 3];
        for v in vals {
            for (c, x) in flat[3..6].iter_mut().zip(v) {
                *c += to_fixed(x);
            }
        }
        flat[12..15].copy_from_slice(&[1 << 24; 3]);
        assert_eq!(
            film.hash().unwrap(),
            xxhash_rust::xxh3::xxh3_64(bytemuck::cast_slice(&flat))
        );
    }

    #[test]
    fn bad_values_are_ignored_not_propagated() {
        assert_eq!(to_fixed(f32::NAN), 0);
        assert_eq!(to_fixed(-1.0), 0);
        assert_eq!(to_fixed(1.0), 1 << 24);
    }
}
