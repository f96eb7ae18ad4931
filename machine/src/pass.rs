//! One pass of a worker's work, the kernel on real data: issue camera rays for some tiles
//! and/or trace one domain's queue, summing retired rays per tile. The worker shell runs it on
//! its tracing pool; the simulator runs the very same function, so its image is the real one.
//!
//! The output does not depend on how rayon splits the work: chunks are joined in input order
//! and tile results come sorted by (tile, epoch), so a pass given the same work yields the same
//! rays in the same order on any pool (the simulator's determinism rests on it).

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use rayfarm_core::camera::PinholeCamera;
use rayfarm_core::cluster::tile_sums;
use rayfarm_core::progressive::Samples;
use rayfarm_core::ray::RayRecord;
use rayfarm_core::render::cache::DomainCache;
use rayfarm_core::render::film::to_fixed;
use rayfarm_core::render::kernel::CopyScratch;
use rayfarm_core::render::local::FrameSpec;
use rayfarm_core::render::primary::primary_ray;
use rayfarm_core::render::{KernelCounters, RaySink, SceneView};
use rayfarm_core::scene::{DomainData, Manifest, SceneError};
use rayfarm_core::tile::TileGrid;
use rayfarm_core::wire::{BatchLimits, VerdictRecord};
use rayfarm_proto as proto;
use rayon::prelude::*;
use tracing::{debug, info_span};

use crate::worker::{PassOutput, PassWork};

/// Rays traced per rayon task: large enough to amortise, small enough to balance.
const CHUNK: usize = 4096;

/// What the frame looks like to a pass; shared, read-only.
pub struct FrameView {
    pub view: SceneView,
    pub camera: PinholeCamera,
    pub grid: TileGrid,
    /// The samples of each pixel this frame issues (a progressive subframe's, or all).
    pub samples: Samples,
}

impl FrameView {
    /// The view of a frame of `frame` over the scene of `manifest`, in tiles of `tile_size`,
    /// issuing `samples` of each pixel, with the limits a peer's batches for it must keep. What a worker reads from a
    /// StartFrame; the shell and the simulator open frames alike.
    pub fn open(
        manifest: &Manifest,
        frame: &FrameSpec,
        tile_size: u32,
        samples: Samples,
    ) -> Result<(FrameView, BatchLimits), String> {
        let grid = TileGrid::new(frame.width, frame.height, tile_size)
            .ok_or_else(|| format!("bad tile size {tile_size}"))?;
        let camera = PinholeCamera::new(
            frame.camera.as_ref().unwrap_or(&manifest.camera),
            frame.width,
            frame.height,
        );
        let limits = BatchLimits {
            domains: manifest.domains.len() as u32,
            pixels: frame.width * frame.height,
            max_depth: frame.max_depth as u16,
            materials: manifest.materials.len() as u32,
            max_records: 1 << 20,
        };
        let view = FrameView {
            view: SceneView::new(manifest, frame.max_depth as u16),
            camera,
            grid,
            samples,
        };
        Ok((view, limits))
    }
}

/// Work for one pass: what the machine asked for, with the frame and the cache to do it.
pub struct PassInput {
    pub frame: Arc<FrameView>,
    pub work: PassWork,
    pub cache: Arc<Mutex<DomainCache>>,
}

/// Why a pass failed: the domain could not be loaded.
pub type PassError = SceneError;

/// One tile's retired credit and fixed-point pixel sums, pixels in order.
#[derive(Default)]
struct TileSum {
    credit: u64,
    pixels: BTreeMap<u32, [i64; 3]>,
}

impl TileSum {
    fn merge(&mut self, other: TileSum) {
        self.credit += other.credit;
        for (pixel, rgb) in other.pixels {
            add_fixed(self.pixels.entry(pixel).or_default(), &rgb);
        }
    }
}

fn add_fixed(acc: &mut [i64; 3], add: &[i64; 3]) {
    for (a, b) in acc.iter_mut().zip(add) {
        *a = a.wrapping_add(*b);
    }
}

/// Where one chunk's rays go: continuing rays in order, retired ones summed by (tile, epoch).
#[derive(Default)]
struct Sink {
    out: Vec<RayRecord>,
    tiles: BTreeMap<(u32, u32), TileSum>,
}

impl RaySink for Sink {
    fn push(&mut self, ray: RayRecord) {
        self.out.push(ray);
    }

    fn retire(&mut self, ray: &RayRecord, rgb: [f32; 3]) {
        let sum = self.tiles.entry((ray.tile, ray.epoch)).or_default();
        sum.credit += ray.credit;
        // Fixed point per contribution, exactly as the local film does, so sums agree.
        // The pixel is named even when it adds no light: the coordinator refuses credit
        // beyond what the named pixels' rays can hold (`TileLedger::with_samples`).
        let fixed = rgb.map(to_fixed);
        add_fixed(sum.pixels.entry(ray.pixel).or_default(), &fixed);
    }
}

impl Sink {
    /// Appends `later`'s rays after this sink's: the order of the input is kept.
    fn append(&mut self, later: Sink) {
        self.out.extend(later.out);
        for (key, sum) in later.tiles {
            self.tiles.entry(key).or_default().merge(sum);
        }
    }

    /// The sinks of consecutive chunks joined in their order.
    fn joined(parts: Vec<Sink>) -> Sink {
        let mut all = Sink {
            out: Vec::with_capacity(parts.iter().map(|s| s.out.len()).sum()),
            ..Sink::default()
        };
        for part in parts {
            all.append(part);
        }
        all
    }
}

/// Runs a pass on the current rayon pool. `busy` is left zero: the caller knows its clock.
pub fn run(input: PassInput) -> Result<PassOutput, PassError> {
    let frame = &input.frame;
    let work = &input.work;
    let mut counters = KernelCounters::default();
    let mut sink = Sink::default();
    if !work.primaries.is_empty() {
        let _span = info_span!("issue_primaries", tiles = work.primaries.len()).entered();
        let per_tile: Vec<Sink> = work
            .primaries
            .par_iter()
            .map(|&(tile, epoch)| {
                let mut s = Sink::default();
                for pixel in frame.grid.pixels(tile) {
                    for sample in frame.samples.range() {
                        let mut ray =
                            primary_ray(&frame.camera, &frame.grid, frame.samples, pixel, sample);
                        ray.epoch = epoch;
                        frame.view.route_new(ray, &mut s);
                    }
                }
                s
            })
            .collect();
        sink = Sink::joined(per_tile);
        counters.primary_rays = work
            .primaries
            .iter()
            .map(|&(t, _)| frame.grid.tile_pixel_count(t) as u64 * u64::from(frame.samples.count))
            .sum();
    }
    if let Some(conclude) = &work.speculative {
        let (concluded, c) = in_chunks(conclude, |chunk, s, c| {
            for (ray, outcome) in chunk {
                frame.view.conclude(ray, outcome, s, c);
            }
        });
        sink.append(concluded);
        counters.add(&c);
    }
    let mut verdicts = Vec::new();
    if let (Some((domain, rays)), Some(_)) = (&work.trace, &work.speculative) {
        let data = load(&input.cache, *domain)?;
        let _span = info_span!("trace_copies", domain, rays = rays.len()).entered();
        debug!("tracing a queue");
        let parts: Vec<(Vec<(u32, VerdictRecord)>, KernelCounters)> = rays
            .par_chunks(CHUNK)
            .map(|chunk| {
                let mut c = KernelCounters::default();
                let mut scratch = CopyScratch::new();
                let mut found = Vec::new();
                let mut v = Vec::with_capacity(chunk.len());
                for r in chunk {
                    found.clear();
                    frame
                        .view
                        .trace_copy(&data, r, &mut scratch, &mut c, &mut found);
                    v.extend(
                        found
                            .iter()
                            .map(|&f| (r.resolver, VerdictRecord::new(r, f))),
                    );
                }
                (v, c)
            })
            .collect();
        for (v, c) in parts {
            verdicts.extend(v);
            counters.add(&c);
        }
        debug!("queue traced");
    } else if let Some((domain, rays)) = &work.trace {
        let data = load(&input.cache, *domain)?;
        let _span = info_span!("trace_queue", domain, rays = rays.len()).entered();
        debug!("tracing a queue");
        let (traced, c) = in_chunks(rays, |chunk, s, c| frame.view.trace(&data, chunk, s, c));
        sink.append(traced);
        counters.add(&c);
        debug!("queue traced");
    }
    let results = sink
        .tiles
        .into_iter()
        .map(|((tile, epoch), sum)| {
            let pixels: Vec<(u32, [i64; 3])> = sum.pixels.into_iter().collect();
            proto::TileResult {
                tile,
                epoch,
                credit: sum.credit,
                sums: tile_sums::encode(&pixels),
            }
        })
        .collect();
    let paths = match &work.speculative {
        Some(_) => sink
            .out
            .par_iter()
            .map(|r| frame.view.domains_along(r))
            .collect(),
        None => Vec::new(),
    };
    Ok(PassOutput {
        rays: sink.out,
        paths,
        verdicts,
        results,
        counters,
        busy: std::time::Duration::ZERO,
    })
}

/// Runs `work` over `items` in parallel chunks, each with its own sink and counters, and
/// joins what they produced in the order of the chunks.
fn in_chunks<T: Sync>(
    items: &[T],
    work: impl Fn(&[T], &mut Sink, &mut KernelCounters) + Sync + Send,
) -> (Sink, KernelCounters) {
    let parts: Vec<(Sink, KernelCounters)> = items
        .par_chunks(CHUNK)
        .map(|chunk| {
            let mut s = Sink {
                out: Vec::with_capacity(chunk.len() * 2),
                ..Sink::default()
            };
            let mut c = KernelCounters::default();
            work(chunk, &mut s, &mut c);
            (s, c)
        })
        .collect();
    let mut counters = KernelCounters::default();
    let sinks = parts
        .into_iter()
        .map(|(s, c)| {
            counters.add(&c);
            s
        })
        .collect();
    (Sink::joined(sinks), counters)
}

fn load(cache: &Mutex<DomainCache>, domain: u32) -> Result<Arc<DomainData>, PassError> {
    // A poisoned lock means a pass panicked; the cache itself is still consistent.
    let mut cache = cache.lock().unwrap_or_else(|p| p.into_inner());
    cache.get(domain)
}
