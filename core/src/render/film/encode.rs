//! The film as images: PNG and EXR files written one row of tiles at a time, and the
//! in-memory PNG previews of a running frame.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use exr::block::writer::ChunksWriter;
use exr::block::{BlockIndex, UncompressedBlock};
use exr::meta::BlockDescription;
use exr::meta::attribute::{ChannelDescription, ChannelList, Compression, LineOrder, SampleType};
use exr::meta::header::Header;
use xxhash_rust::xxh3::Xxh3Default;

use super::{FIXED_ONE, Film, ImageError};

impl Film {
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
pub(super) fn srgb_byte(v: f32) -> u8 {
    let v = v.clamp(0.0, 1.0);
    let s = if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0 + 0.5) as u8
}
