//! One pass of work on the tracing pool: issue camera rays for some tiles and/or trace one
//! domain's queue. Retired rays are summed per tile here, off the engine's thread, so the
//! engine only routes continuing rays and forwards the sums.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rayfarm_common::camera::PinholeCamera;
use rayfarm_common::cluster::tile_sums;
use rayfarm_common::frame::TileGrid;
use rayfarm_common::proto;
use rayfarm_common::ray::RayRecord;
use rayfarm_common::render::cache::DomainCache;
use rayfarm_common::render::film::to_fixed;
use rayfarm_common::render::primary::primary_ray;
use rayfarm_common::render::{KernelCounters, RaySink, SceneView};
use rayfarm_common::scene::SceneError;
use rayon::prelude::*;
use tracing::{debug, info_span};

/// Rays traced per rayon task: large enough to amortise, small enough to balance.
const CHUNK: usize = 4096;

/// What the frame looks like to a pass; shared, read-only.
pub struct FrameView {
    pub view: SceneView,
    pub camera: PinholeCamera,
    pub grid: TileGrid,
    pub spp: u32,
}

/// Work for one pass.
pub struct PassInput {
    pub frame: Arc<FrameView>,
    /// Tiles whose camera rays to issue, with the epoch they are issued in.
    pub primaries: Vec<(u32, u32)>,
    /// A domain and the rays queued for it.
    pub trace: Option<(u32, Vec<RayRecord>)>,
    pub cache: Arc<Mutex<DomainCache>>,
}

/// What a pass produced.
pub struct PassOutput {
    /// Rays that continue, each with the domain it continues in.
    pub rays: Vec<RayRecord>,
    /// Credit and pixel sums of the rays that retired, one entry per (tile, epoch).
    pub results: Vec<proto::TileResult>,
    pub counters: KernelCounters,
    /// Wall time of the pass, including a domain load.
    pub busy: Duration,
}

/// Why a pass failed: the domain could not be loaded.
pub type PassError = SceneError;

#[derive(Default)]
struct TileSum {
    credit: u64,
    pixels: HashMap<u32, [i64; 3]>,
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

#[derive(Default)]
struct Sink {
    out: Vec<RayRecord>,
    tiles: HashMap<(u32, u32), TileSum>,
}

impl RaySink for Sink {
    fn push(&mut self, ray: RayRecord) {
        self.out.push(ray);
    }

    fn retire(&mut self, ray: &RayRecord, rgb: [f32; 3]) {
        let sum = self.tiles.entry((ray.tile, ray.epoch)).or_default();
        sum.credit += ray.credit;
        // Fixed point per contribution, exactly as the local film does, so sums agree.
        let fixed = rgb.map(to_fixed);
        if fixed != [0; 3] {
            add_fixed(sum.pixels.entry(ray.pixel).or_default(), &fixed);
        }
    }
}

impl Sink {
    fn merge(mut self, other: Sink) -> Sink {
        if self.out.len() < other.out.len() {
            return other.merge(self);
        }
        self.out.extend(other.out);
        for (key, sum) in other.tiles {
            self.tiles.entry(key).or_default().merge(sum);
        }
        self
    }
}

/// Runs a pass on the current rayon pool.
pub fn run(input: PassInput) -> Result<PassOutput, PassError> {
    let start = Instant::now();
    let frame = &input.frame;
    let mut counters = KernelCounters::default();
    let mut sink = Sink::default();
    if !input.primaries.is_empty() {
        let _span = info_span!("issue_primaries", tiles = input.primaries.len()).entered();
        sink = input
            .primaries
            .par_iter()
            .map(|&(tile, epoch)| {
                let mut s = Sink::default();
                for pixel in frame.grid.pixels(tile) {
                    for sample in 0..frame.spp {
                        let mut ray =
                            primary_ray(&frame.camera, &frame.grid, frame.spp, pixel, sample);
                        ray.epoch = epoch;
                        frame.view.route_new(ray, &mut s);
                    }
                }
                s
            })
            .reduce(Sink::default, Sink::merge);
        counters.primary_rays = input
            .primaries
            .iter()
            .map(|&(t, _)| frame.grid.tile_pixel_count(t) as u64 * frame.spp as u64)
            .sum();
    }
    if let Some((domain, rays)) = &input.trace {
        let data = {
            // A poisoned lock means a pass panicked; the cache itself is still consistent.
            let mut cache = input.cache.lock().unwrap_or_else(|p| p.into_inner());
            cache.get(*domain)?
        };
        let _span = info_span!("trace_queue", domain, rays = rays.len()).entered();
        debug!("tracing a queue");
        let (traced, c) = rays
            .par_chunks(CHUNK)
            .map(|chunk| {
                let mut s = Sink {
                    out: Vec::with_capacity(chunk.len() * 2),
                    ..Sink::default()
                };
                let mut c = KernelCounters::default();
                frame.view.trace(&data, chunk, &mut s, &mut c);
                (s, c)
            })
            .reduce(
                || (Sink::default(), KernelCounters::default()),
                |(a, mut ca), (b, cb)| {
                    ca.add(&cb);
                    (a.merge(b), ca)
                },
            );
        sink = sink.merge(traced);
        counters.add(&c);
        debug!("queue traced");
    }
    let results = sink
        .tiles
        .into_iter()
        .map(|((tile, epoch), sum)| {
            let mut pixels: Vec<(u32, [i64; 3])> = sum.pixels.into_iter().collect();
            pixels.sort_unstable_by_key(|&(p, _)| p);
            proto::TileResult {
                tile,
                epoch,
                credit: sum.credit,
                sums: tile_sums::encode(pixels),
            }
        })
        .collect();
    Ok(PassOutput {
        rays: sink.out,
        results,
        counters,
        busy: start.elapsed(),
    })
}
