//! One pass of work on the tracing pool: issue camera rays for some tiles and/or trace one
//! domain's queue. Retired rays are summed per tile here, off the engine's thread, so the
//! engine only routes continuing rays and forwards the sums.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use rayfarm_core::bvh::Traverser;
use rayfarm_core::camera::PinholeCamera;
use rayfarm_core::cluster::tile_sums;
use rayfarm_core::frame::TileGrid;
use rayfarm_core::ray::RayRecord;
use rayfarm_core::render::cache::DomainCache;
use rayfarm_core::render::film::to_fixed;
use rayfarm_core::render::primary::primary_ray;
use rayfarm_core::render::{KernelCounters, RaySink, SceneView};
use rayfarm_core::scene::DomainData;
use rayfarm_core::scene::SceneError;
use rayfarm_core::wire::VerdictRecord;
use rayfarm_machine::worker::{PassOutput, PassWork};
use rayfarm_node::proto;
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

/// Work for one pass: what the machine asked for, with the frame and the cache to do it.
pub struct PassInput {
    pub frame: Arc<FrameView>,
    pub work: PassWork,
    pub cache: Arc<Mutex<DomainCache>>,
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
        // The pixel is named even when it adds no light: the coordinator refuses credit
        // beyond what the named pixels' rays can hold (`FrameLedger::with_samples`).
        let fixed = rgb.map(to_fixed);
        add_fixed(sum.pixels.entry(ray.pixel).or_default(), &fixed);
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
    let work = &input.work;
    let mut counters = KernelCounters::default();
    let mut sink = Sink::default();
    if !work.primaries.is_empty() {
        let _span = info_span!("issue_primaries", tiles = work.primaries.len()).entered();
        sink = work
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
        counters.primary_rays = work
            .primaries
            .iter()
            .map(|&(t, _)| frame.grid.tile_pixel_count(t) as u64 * frame.spp as u64)
            .sum();
    }
    if let Some(conclude) = &work.speculative {
        let (concluded, c) = in_chunks(conclude, |chunk, s, c| {
            for (ray, outcome) in chunk {
                frame.view.conclude(ray, outcome, s, c);
            }
        });
        sink = sink.merge(concluded);
        counters.add(&c);
    }
    let mut verdicts = Vec::new();
    if let (Some((domain, rays)), Some(_)) = (&work.trace, &work.speculative) {
        let data = load(&input.cache, *domain)?;
        let _span = info_span!("trace_copies", domain, rays = rays.len()).entered();
        debug!("tracing a queue");
        let (v, c) = rays
            .par_chunks(CHUNK)
            .map(|chunk| {
                let mut c = KernelCounters::default();
                let mut traverser = Traverser::new();
                let v: Vec<(u32, VerdictRecord)> = chunk
                    .iter()
                    .map(|r| {
                        let verdict = frame.view.trace_copy(&data, r, &mut traverser, &mut c);
                        (r.resolver, VerdictRecord::new(r, verdict))
                    })
                    .collect();
                (v, c)
            })
            .reduce(
                || (Vec::new(), KernelCounters::default()),
                |(mut a, mut ca), (b, cb)| {
                    ca.add(&cb);
                    a.extend(b);
                    (a, ca)
                },
            );
        verdicts = v;
        counters.add(&c);
        debug!("queue traced");
    } else if let Some((domain, rays)) = &work.trace {
        let data = load(&input.cache, *domain)?;
        let _span = info_span!("trace_queue", domain, rays = rays.len()).entered();
        debug!("tracing a queue");
        let (traced, c) = in_chunks(rays, |chunk, s, c| frame.view.trace(&data, chunk, s, c));
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
        busy: start.elapsed(),
    })
}

/// Runs `work` over `items` in parallel chunks, each with its own sink and counters, and
/// merges what they produced.
fn in_chunks<T: Sync>(
    items: &[T],
    work: impl Fn(&[T], &mut Sink, &mut KernelCounters) + Sync + Send,
) -> (Sink, KernelCounters) {
    items
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
        .reduce(
            || (Sink::default(), KernelCounters::default()),
            |(a, mut ca), (b, cb)| {
                ca.add(&cb);
                (a.merge(b), ca)
            },
        )
}

fn load(cache: &Mutex<DomainCache>, domain: u32) -> Result<Arc<DomainData>, PassError> {
    // A poisoned lock means a pass panicked; the cache itself is still consistent.
    let mut cache = cache.lock().unwrap_or_else(|p| p.into_inner());
    cache.get(domain)
}
