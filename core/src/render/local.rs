//! The single-process reference renderer (Pharr-style): one queue per domain, always trace
//! the fullest queue, a byte-budgeted domain cache. Every distributed render must equal its
//! image bit for bit.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use rayon::prelude::*;
use tracing::{info, info_span};

use self::queue::{Batch, Queues, SEGMENT, SegmentPool};

use super::cache::DomainCache;
use super::film::{Film, ImageError, OpenTiles};
use super::kernel::{CopyScratch, KernelCounters, RaySink, SceneView};
use super::primary::primary_ray;
use super::speculation::{Groups, Verdict};
use super::stats::{RenderStats, peak_rss_bytes};
use crate::camera::PinholeCamera;
use crate::progressive::Samples;
use crate::ray::RayRecord;
use crate::scene::{Camera, DomainData, Manifest, SceneError};
use crate::schedule::speculation_depth::Depth;
use crate::tile::TileGrid;
use crate::tile::credit::TILE_CREDIT;
use crate::wire::VerdictRecord;

mod queue;

/// Largest image side accepted.
pub const MAX_SIDE: u32 = 16384;
/// Largest samples per pixel accepted.
pub const MAX_SPP: u32 = 65536;
/// Largest path depth accepted.
pub const MAX_DEPTH: u32 = 64;

/// What to render.
#[derive(Clone, Debug)]
pub struct FrameSpec {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Samples per pixel.
    pub spp: u32,
    /// Maximum bounces.
    pub max_depth: u32,
    /// View; the manifest's camera when `None`.
    pub camera: Option<Camera>,
}

impl FrameSpec {
    /// Rejects sizes the renderer will not attempt, with the reason.
    pub fn check(&self) -> Result<(), String> {
        if self.width == 0 || self.height == 0 || self.width > MAX_SIDE || self.height > MAX_SIDE {
            return Err(format!(
                "resolution {}x{} is outside 1..={MAX_SIDE} per side",
                self.width, self.height
            ));
        }
        if self.spp == 0 || self.spp > MAX_SPP {
            return Err(format!("spp {} is outside 1..={MAX_SPP}", self.spp));
        }
        if self.max_depth > MAX_DEPTH {
            return Err(format!("depth {} is above {MAX_DEPTH}", self.max_depth));
        }
        if let Some(c) = &self.camera {
            c.check()?;
        }
        Ok(())
    }
}

/// How to run the local renderer.
#[derive(Clone, Debug)]
pub struct LocalOptions {
    /// Tracing threads.
    pub threads: usize,
    /// Domain cache budget in bytes.
    pub cache_bytes: u64,
    /// Camera rays issued whenever fewer than this many rays are queued.
    pub wave_rays: usize,
    /// Queue every new ray in all domains along it at once (`speculation`), oldest
    /// generation first: fewer domain loads, more ray segments traced.
    pub speculate: bool,
    /// Speculating, how many domains ahead a ray is copied (`schedule::speculation_depth`).
    pub depth: Depth,
    /// Where the film file goes (an unnamed temporary file; the system's temporary
    /// directory when `None`). It takes [`Film::file_bytes`] on disk.
    pub film_dir: Option<PathBuf>,
}

/// Why a local render failed.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// The frame asks for something unreasonable.
    #[error("invalid frame: {0}")]
    Frame(String),
    /// The scene could not be read.
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// The film file failed.
    #[error(transparent)]
    Film(#[from] ImageError),
    /// The thread pool could not start.
    #[error("thread pool: {0}")]
    Threads(String),
    /// The kernel lost or invented credit: a bug, reported rather than hidden.
    #[error("internal error: tile {tile} returned {returned} of {expected} credit")]
    Credit {
        /// The tile.
        tile: u32,
        /// Credit that came back.
        returned: u64,
        /// Credit it started with.
        expected: u64,
    },
}

struct QueueSink<'a> {
    out: Batch<'a>,
    film: &'a OpenTiles,
    /// Credit returned per tile: the local renderer checks the kernel conserves it exactly,
    /// as the cluster will rely on it to know when a tile is done.
    returned: &'a [AtomicU64],
}

impl RaySink for QueueSink<'_> {
    fn push(&mut self, ray: RayRecord) {
        self.out.push(ray);
    }
    fn retire(&mut self, ray: &RayRecord, rgb: [f32; 3]) {
        self.film.deposit(ray.tile, ray.pixel, rgb);
        if let Some(t) = self.returned.get(ray.tile as usize) {
            t.fetch_add(ray.credit, Ordering::Relaxed);
        }
    }
}

/// How far a local render has come; reported after every queue pass.
#[derive(Clone, Copy, Debug, Default)]
pub struct Progress {
    /// Tiles whose credit has all come back (finished).
    pub tiles_done: u32,
    /// Tiles in the frame.
    pub tiles_total: u32,
    /// Ray segments traced so far.
    pub segments: u64,
    /// Domain loads so far.
    pub loads: u64,
    /// Seconds since the frame started.
    pub elapsed: f64,
}

/// Renders one frame of the scene in `dir` in this process, calling `on_progress` after
/// every queue pass.
pub fn render_local(
    dir: &Path,
    manifest: &Manifest,
    frame: &FrameSpec,
    options: &LocalOptions,
    on_progress: &mut (dyn FnMut(&Progress) + Send),
) -> Result<(Film, RenderStats), RenderError> {
    frame.check().map_err(RenderError::Frame)?;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(options.threads.max(1))
        .build()
        .map_err(|e| RenderError::Threads(e.to_string()))?;
    pool.install(|| render_in_pool(dir, manifest, frame, options, on_progress))
}

fn render_in_pool(
    dir: &Path,
    manifest: &Manifest,
    frame: &FrameSpec,
    options: &LocalOptions,
    on_progress: &mut (dyn FnMut(&Progress) + Send),
) -> Result<(Film, RenderStats), RenderError> {
    let start = Instant::now();
    let _span = info_span!(
        "render_local",
        width = frame.width,
        height = frame.height,
        spp = frame.spp
    )
    .entered();
    let view = SceneView::new(manifest, frame.max_depth as u16);
    let camera = PinholeCamera::new(
        frame.camera.as_ref().unwrap_or(&manifest.camera),
        frame.width,
        frame.height,
    );
    let grid = TileGrid::new(frame.width, frame.height, crate::tile::TILE_SIZE)
        .ok_or_else(|| RenderError::Frame("image does not fit the tile grid".into()))?;
    let film_dir = options.film_dir.clone().unwrap_or_else(std::env::temp_dir);
    let film = Film::temporary_in(&film_dir, grid, frame.spp)?;
    let mut open = OpenTiles::new(grid);
    // Tiles in memory are bounded: past this many, queued rays are traced before more camera
    // rays are issued (a few waves' worth of tiles; a wave covers rows of pixels).
    let wave_tiles =
        options.wave_rays as u64 / (u64::from(frame.spp) * u64::from(TILE_PIXELS)).max(1);
    let max_open = 4 * (wave_tiles as usize + 2 * grid.tiles_x() as usize);
    let returned: Vec<AtomicU64> = (0..grid.count()).map(|_| AtomicU64::new(0)).collect();
    let mut cache = DomainCache::new(dir, manifest, options.cache_bytes);
    let mut queues = Queues::new(
        view.domain_count(),
        options.speculate.then_some(options.depth),
    );
    if options.speculate {
        let eye = frame.camera.as_ref().unwrap_or(&manifest.camera).eye;
        queues.from_eye = view.front_to_back(eye);
    }
    let mut counters = KernelCounters::default();
    let total_primary = frame.width as u64 * frame.height as u64 * frame.spp as u64;
    let mut issued = 0u64;
    let mut passes = 0u64;
    let mut tiles_done = 0u32;
    let wave = options.wave_rays.max(1) as u64;
    let pool = SegmentPool::new();
    loop {
        let queued = queues.total();
        let room = open.in_memory() < max_open || queued == 0;
        if queued < wave as usize && issued < total_primary && room {
            let end = (issued + wave).min(total_primary);
            let new_sink = sinks(&open, &returned, &pool);
            let outs = issue_primaries(&view, &camera, &grid, frame.spp, issued..end, new_sink);
            counters.primary_rays += end - issued;
            issued = end;
            queues.place(&view, outs, &pool);
            // Camera rays that meet nothing retire at once: their tiles may be finished.
            tiles_done += commit_finished(&mut open, &returned, &film)?;
            continue;
        }
        let Some(d) = queues.next(&cache.resident()) else {
            break;
        };
        let mut rays = queues.take(d);
        if let Some(groups) = &mut queues.groups {
            // Copies of rays that a nearer domain already ended need no tracing: when they
            // are all such, the domain need not even be loaded.
            for segment in &mut rays {
                segment.retain(|copy| !groups.skip(copy));
            }
            rays.retain(|segment| !segment.is_empty());
            if rays.is_empty() {
                continue;
            }
        }
        let data = cache.get(d)?;
        let count: usize = rays.iter().map(Vec::len).sum();
        let _pass = info_span!("trace_queue", domain = d, rays = count).entered();
        let new_sink = sinks(&open, &returned, &pool);
        let outs = match &mut queues.groups {
            None => trace_chained(&view, &data, rays, new_sink, &pool, &mut counters),
            Some(groups) => {
                let (outs, mut more) =
                    trace_speculative(&view, &data, rays, groups, new_sink, &pool, &mut counters);
                queues.queue_copies(&mut more, &pool);
                outs
            }
        };
        passes += 1;
        queues.place(&view, outs, &pool);
        tiles_done += commit_finished(&mut open, &returned, &film)?;
        on_progress(&Progress {
            tiles_done,
            tiles_total: grid.count(),
            segments: counters.segments(),
            loads: cache.counters().loads,
            elapsed: start.elapsed().as_secs_f64(),
        });
    }
    tiles_done += commit_finished(&mut open, &returned, &film)?;
    debug_assert!(tiles_done <= grid.count());
    for (tile, r) in returned.iter().enumerate() {
        let r = r.load(Ordering::Relaxed);
        if r != TILE_CREDIT {
            return Err(RenderError::Credit {
                tile: tile as u32,
                returned: r,
                expected: TILE_CREDIT,
            });
        }
    }
    let wall = start.elapsed().as_secs_f64();
    let threads = rayon::current_num_threads();
    let rays_per_s = counters.segments() as f64 / wall.max(1e-9);
    let stats = RenderStats {
        width: frame.width,
        height: frame.height,
        spp: frame.spp,
        max_depth: frame.max_depth,
        threads,
        domains: view.domain_count(),
        wall_seconds: wall,
        rays: counters,
        cache: cache.counters(),
        rays_per_s,
        rays_per_s_per_core: rays_per_s / threads as f64,
        queue_passes: passes,
        peak_rss_bytes: peak_rss_bytes(),
        image_hash: format!("{:016x}", film.hash()?),
    };
    info!(
        wall,
        segments = counters.segments(),
        loads = stats.cache.loads,
        copies = queues.groups.as_ref().map_or(0, |g| g.copies),
        windows_after_the_first = queues.groups.as_ref().map_or(0, |g| g.extensions),
        copies_skipped = queues.groups.as_ref().map_or(0, |g| g.skipped),
        concluded_early = queues.groups.as_ref().map_or(0, |g| g.early),
        "frame done"
    );
    Ok((film, stats))
}

/// Makes the sinks of one pass's chunks.
fn sinks<'a>(
    open: &'a OpenTiles,
    returned: &'a [AtomicU64],
    pool: &'a SegmentPool,
) -> impl Fn() -> QueueSink<'a> + Sync {
    move || QueueSink {
        out: Batch::new(pool),
        film: open,
        returned,
    }
}

/// Pixels of a full tile.
const TILE_PIXELS: u32 = crate::tile::TILE_SIZE * crate::tile::TILE_SIZE;

/// Moves every tile whose credit is all back from memory to the film; returns how many.
fn commit_finished(
    open: &mut OpenTiles,
    returned: &[AtomicU64],
    film: &Film,
) -> Result<u32, RenderError> {
    let mut committed = 0;
    for (tile, r) in (0u32..).zip(returned) {
        if r.load(Ordering::Relaxed) == TILE_CREDIT && !open.is_committed(tile) {
            open.commit(tile, film)?;
            committed += 1;
        }
    }
    Ok(committed)
}

/// Camera rays for the flat (pixel, sample) indices in `range`, each with its share of its
/// tile's credit, routed to their first domain; in segments.
fn issue_primaries<'a>(
    view: &SceneView,
    camera: &PinholeCamera,
    grid: &TileGrid,
    spp: u32,
    range: std::ops::Range<u64>,
    new_sink: impl Fn() -> QueueSink<'a> + Sync,
) -> Vec<Vec<RayRecord>> {
    let starts: Vec<u64> = range.clone().step_by(SEGMENT).collect();
    let per_chunk: Vec<Vec<Vec<RayRecord>>> = starts
        .par_iter()
        .map(|&first| {
            let mut sink = new_sink();
            for i in first..(first + SEGMENT as u64).min(range.end) {
                let (pixel, sample) = ((i / spp as u64) as u32, (i % spp as u64) as u32);
                let ray = primary_ray(camera, grid, Samples::all(spp), pixel, sample);
                view.route_new(ray, &mut sink);
            }
            sink.out.finish()
        })
        .collect();
    per_chunk.into_iter().flatten().collect()
}

/// Traces a domain's queue one domain at a time: rays that miss move on to the next domain.
/// Each segment is one task; it goes back to `pool` once traced, for the outcomes of the
/// next.
fn trace_chained<'a>(
    view: &SceneView,
    data: &DomainData,
    rays: Vec<Vec<RayRecord>>,
    new_sink: impl Fn() -> QueueSink<'a> + Sync,
    pool: &SegmentPool,
    counters: &mut KernelCounters,
) -> Vec<Vec<RayRecord>> {
    let results: Vec<(Vec<Vec<RayRecord>>, KernelCounters)> = rays
        .into_par_iter()
        .map(|segment| {
            let mut sink = new_sink();
            let mut c = KernelCounters::default();
            view.trace(data, &segment, &mut sink, &mut c);
            pool.put(segment);
            (sink.out.finish(), c)
        })
        .collect();
    let mut outs = Vec::with_capacity(results.len());
    for (out, c) in results {
        counters.add(&c);
        outs.extend(out);
    }
    outs
}

/// Traces speculative copies queued for a domain and concludes every ray whose last copy
/// this was; returns the rays those conclusions made, and the copies of the next windows of
/// rays whose last window did not end them.
fn trace_speculative<'a>(
    view: &SceneView,
    data: &DomainData,
    rays: Vec<Vec<RayRecord>>,
    groups: &mut Groups,
    new_sink: impl Fn() -> QueueSink<'a> + Sync,
    pool: &SegmentPool,
    counters: &mut KernelCounters,
) -> (Vec<Vec<RayRecord>>, Vec<RayRecord>) {
    // Per segment: each copy's verdicts (a brick's copy has several), in the order of the rays.
    let verdicts: Vec<(Vec<(usize, Verdict)>, KernelCounters)> = rays
        .par_iter()
        .map(|segment| {
            let mut c = KernelCounters::default();
            let mut scratch = CopyScratch::new();
            let mut found = Vec::new();
            let mut v = Vec::with_capacity(segment.len());
            for (i, r) in segment.iter().enumerate() {
                found.clear();
                view.trace_copy(data, r, &mut scratch, &mut c, &mut found);
                v.extend(found.iter().map(|&f| (i, f)));
            }
            (v, c)
        })
        .collect();
    let mut sink = new_sink();
    let mut more = Vec::new();
    for (segment, (verdicts, c)) in rays.iter().zip(verdicts) {
        counters.add(&c);
        for (i, verdict) in verdicts {
            // Every copy here was made by `Queues::place` in this frame.
            let settled = groups
                .settle(&VerdictRecord::new(&segment[i], verdict), &mut more)
                .expect("copy of a waiting ray");
            if let Some((ray, outcome)) = settled {
                view.conclude(&ray, &outcome, &mut sink, counters);
            }
        }
    }
    for segment in rays {
        pool.put(segment);
    }
    (sink.out.finish(), more)
}
