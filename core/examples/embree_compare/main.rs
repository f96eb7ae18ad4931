//! Benchmark: rayfarm's BVH traversal (`bvh::Traverser::nearest_hit`) against Embree 3, one core each, on
//! the same one-domain scene and the same rays, in one run.
//!
//! Three ray sets: coherent camera rays (one per pixel of a square image from the manifest's
//! camera) and incoherent diffuse rays (one cosine-distributed bounce from every camera hit),
//! both closest-hit, and shadow rays (from every camera hit towards each of the scene's
//! lights, any-hit: `Traverser::any_hit` against Embree's `rtcOccluded1`), each ray over the
//! finite interval the render kernel would give it in the domain; rays that miss the domain are left out, as a render never traces them. Embree is not a dependency of rayfarm: this example writes the mesh
//! and the rays to files, runs `bench/embree/embree_trace` on them, and reads its timings and
//! hits back. `bench/embree/run.sh` builds that program and the scene, then runs this.
//!
//! ```text
//! embree_compare SCENE_DIR --embree PATH [--size N] [--reps N] [--high] [--keep DIR]
//! embree_compare SCENE_DIR --count SET [--size N]
//! ```
//!
//! `--rebuild` traces a BVH built in memory with this build's settings instead of the file's
//! (to compare build settings without preparing again). Times are the tracing thread's CPU
//! time on both sides, so a shared machine's other processes do not count against either.
//!
//! `--count coherent|incoherent|shadow` traces that set once on rayfarm's side only, in
//! `counted_pass`, for instruction counts: `valgrind --tool=callgrind
//! --toggle-collect='*counted_pass*' embree_compare SCENE --count coherent` (README, "Benchmarks").
//! Built with `--features counters` it also prints the node visits, leaf visits and block
//! tests per ray.

use std::error::Error;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use rayfarm_core::bvh::{Bvh, BvhNode, Hit, PACKET, SLOT_EMPTY, SLOT_INNER, TraceRay, Traverser};
use rayfarm_core::camera::PinholeCamera;
use rayfarm_core::geometry::{PackedTriangle, TriangleBlock, leave_surface};
use rayfarm_core::sampling::{Purpose, uniform};
use rayfarm_core::scene::{DomainData, DomainTree, Light, Manifest};
use serde_json::{Value, json};

type Result<T> = std::result::Result<T, Box<dyn Error>>;

mod embree;
mod rays;

use embree::*;
use rays::*;

struct Options {
    scene: PathBuf,
    embree: PathBuf,
    count: Option<String>,
    rebuild: bool,
    size: u32,
    reps: usize,
    high: bool,
    keep: Option<PathBuf>,
}

fn parse_args() -> Result<Options> {
    let usage = "usage: embree_compare SCENE_DIR (--embree PATH | --count SET) [--size N] [--reps N] [--high] [--rebuild] [--keep DIR]";
    let mut scene = None;
    let mut embree = None;
    let mut count = None;
    let mut rebuild = false;
    let mut size = 1024;
    let mut reps = 5;
    let mut high = false;
    let mut keep = None;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut value = || {
            args.next()
                .ok_or_else(|| format!("{a} needs a value\n{usage}"))
        };
        match a.as_str() {
            "--embree" => embree = Some(PathBuf::from(value()?)),
            "--count" => count = Some(value()?),
            "--size" => size = value()?.parse()?,
            "--reps" => reps = value()?.parse()?,
            "--high" => high = true,
            "--keep" => keep = Some(PathBuf::from(value()?)),
            "--rebuild" => rebuild = true,
            "-h" | "--help" => return Err(usage.into()),
            s if s.starts_with("--") => return Err(format!("unknown option {s}\n{usage}").into()),
            _ if scene.is_none() => scene = Some(PathBuf::from(a)),
            _ => return Err(format!("unexpected argument {a}\n{usage}").into()),
        }
    }
    Ok(Options {
        scene: scene.ok_or(usage)?,
        embree: match (&embree, &count) {
            (None, None) => return Err(usage.into()),
            _ => embree.unwrap_or_default(),
        },
        count,
        rebuild,
        size,
        reps: reps.max(1),
        high,
        keep,
    })
}

/// The huge-page lines of `/proc/self/smaps_rollup` (anonymous and file-backed), or why not.
fn huge_pages_in_use() -> String {
    match std::fs::read_to_string("/proc/self/smaps_rollup") {
        Ok(text) => text
            .lines()
            .filter(|l| l.contains("HugePages") || l.contains("PmdMapped"))
            .map(|l| l.split_whitespace().collect::<Vec<_>>().join(" "))
            .collect::<Vec<_>>()
            .join(", "),
        Err(e) => format!("no smaps_rollup ({e})"),
    }
}

/// Seconds per repetition of one tracer over one ray set.
struct Timing(Vec<f64>);

impl Timing {
    fn sorted(&self) -> Vec<f64> {
        let mut s = self.0.clone();
        s.sort_by(f64::total_cmp);
        s
    }

    /// Median throughput: robust to one disturbed repetition on a shared machine.
    fn median_mrays(&self, rays: usize) -> f64 {
        let s = self.sorted();
        rays as f64 / s[s.len() / 2] / 1e6
    }

    fn best_mrays(&self, rays: usize) -> f64 {
        rays as f64 / self.sorted()[0] / 1e6
    }
}

/// CPU seconds of this thread: on a shared machine, time spent descheduled is not the
/// tracer's (the C++ side measures the same way).
fn thread_seconds() -> f64 {
    let mut t = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `t` is a valid timespec to write; the clock id is a constant the kernel knows.
    unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) };
    t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9
}

/// How a set is traced.
#[derive(Clone, Copy, PartialEq)]
enum Mode {
    /// Closest hit, in packets of eight neighbours as the render kernel traces camera rays
    /// (unless `RAYFARM_PACKETS=0`).
    Packets,
    /// Closest hit, one ray at a time.
    Single,
    /// Any hit (shadow rays), one ray at a time.
    Any,
}

/// The mode of the set named `name`.
fn mode_of(name: &str) -> Mode {
    match name {
        "coherent" => Mode::Packets,
        "shadow" => Mode::Any,
        _ => Mode::Single,
    }
}

/// A blocked shadow ray, as `hits` record it (only hit or miss is compared).
const BLOCKED: Hit = Hit {
    t: 0.0,
    block: 0,
    lane: 0,
    id: 0,
};

/// One pass of rayfarm's kernel over `rays` on this thread, in thread CPU seconds.
/// Preparing each `TraceRay` is inside the timed loop, as filling each `RTCRayHit` is on the
/// Embree side.
fn trace_rayfarm(bvh: Bvh, rays: &[BenchRay], mode: Mode, hits: &mut Vec<Option<Hit>>) -> f64 {
    hits.clear();
    hits.resize(rays.len(), None);
    let mut traverser = Traverser::new();
    let start = thread_seconds();
    trace_all(&mut traverser, bvh, rays, mode, hits);
    thread_seconds() - start
}

/// Traces `rays` into `hits`, in packets or one at a time ([`BLOCKED`] for a blocked
/// shadow ray).
#[inline(always)]
fn trace_all(
    traverser: &mut Traverser,
    bvh: Bvh,
    rays: &[BenchRay],
    mode: Mode,
    hits: &mut [Option<Hit>],
) {
    if mode == Mode::Any {
        for (r, hit) in rays.iter().zip(hits) {
            let ray = TraceRay::new(r.origin.into(), r.dir.into());
            *hit = traverser
                .any_hit(bvh, &ray, r.t_min, r.t_max)
                .then_some(BLOCKED);
        }
        return;
    }
    if !(mode == Mode::Packets && traverser.packets()) {
        for (r, hit) in rays.iter().zip(hits) {
            let ray = TraceRay::new(r.origin.into(), r.dir.into());
            *hit = traverser.nearest_hit(bvh, &ray, r.t_min, r.t_max);
        }
        return;
    }
    for (chunk, out) in rays.chunks(PACKET).zip(hits.chunks_mut(PACKET)) {
        let n = chunk.len();
        let mut tr = [TraceRay::new(Vec3::ZERO, Vec3::X); PACKET];
        let (mut t0, mut t1) = ([0.0; PACKET], [0.0; PACKET]);
        for (i, r) in chunk.iter().enumerate() {
            tr[i] = TraceRay::new(r.origin.into(), r.dir.into());
            (t0[i], t1[i]) = (r.t_min, r.t_max);
        }
        traverser.nearest_hits(bvh, &tr[..n], &t0[..n], &t1[..n], out);
    }
}

/// One untimed pass for instruction counts; returns the number of hits.
#[inline(never)]
fn counted_pass(bvh: Bvh, rays: &[BenchRay], mode: Mode) -> usize {
    let mut traverser = Traverser::new();
    let mut hits = vec![None; rays.len()];
    trace_all(&mut traverser, bvh, rays, mode, &mut hits);
    hits.iter().filter(|h| h.is_some()).count()
}

/// A tree's surface-area cost (the expected work of a ray through it: node visits plus block
/// tests, each weighted by its box's area relative to the root's, both costed 1 as Embree's
/// builder does) and how full its nodes and blocks are, to compare build settings.
fn tree_stats(nodes: &[BvhNode], blocks: &[TriangleBlock], triangles: usize) -> String {
    let area = |lo: [f32; 3], hi: [f32; 3]| {
        let e = [0, 1, 2].map(|a| (hi[a] - lo[a]).max(0.0) as f64);
        e[0] * e[1] + e[1] * e[2] + e[2] * e[0]
    };
    let slot_box = |n: &BvhNode, s: usize| {
        (
            [0, 1, 2].map(|a| n.bounds[a][s]),
            [3, 4, 5].map(|a| n.bounds[a][s]),
        )
    };
    let (mut inner, mut leaf, mut slots) = (0.0f64, 0.0f64, 0usize);
    let (mut root_lo, mut root_hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for (i, n) in nodes.iter().enumerate() {
        for s in 0..8 {
            let (lo, hi) = slot_box(n, s);
            let a = area(lo, hi);
            match n.meta[s] {
                SLOT_EMPTY => continue,
                SLOT_INNER => inner += a,
                count => leaf += a * count as f64,
            }
            slots += 1;
            if i == 0 {
                for k in 0..3 {
                    root_lo[k] = root_lo[k].min(lo[k]);
                    root_hi[k] = root_hi[k].max(hi[k]);
                }
            }
        }
    }
    // The root node is visited by every ray that enters the root box: its own cost is one.
    let root = area(root_lo, root_hi).max(f64::MIN_POSITIVE);
    format!(
        "SAH cost {:.1} (node visits {:.1} + block tests {:.1}), {:.2} children per node, \
         {:.2} triangles per block",
        1.0 + (inner + leaf) / root,
        1.0 + inner / root,
        leaf / root,
        slots as f64 / nodes.len().max(1) as f64,
        triangles as f64 / blocks.len().max(1) as f64
    )
}

/// The machine's load when the run ended: other processes on a 2-core machine skew timings.
fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next().map(str::to_owned))
        .unwrap_or_default()
}

fn main() -> Result<()> {
    let opts = parse_args()?;
    let manifest = Manifest::load(&opts.scene)?;
    let [entry] = manifest.domains.as_slice() else {
        return Err(format!(
            "{} has {} domains; the comparison needs one (prepare with --domains 1)",
            opts.scene.display(),
            manifest.domains.len()
        )
        .into());
    };
    let checksum = u64::from_str_radix(&entry.checksum, 16)?;
    let materials = manifest.materials.len() as u32;
    // Verifying the checksum also reads the whole file, so no timed pass pays for page faults.
    let domain = DomainData::open(&opts.scene.join(&entry.file), checksum, true, materials)?;
    // Huge pages or not is most of the difference on incoherent rays (README, "Benchmarks"):
    // say how the domain is held, and how much of the process the kernel gave huge pages.
    eprintln!(
        "domain held as {:?} ({} bytes); process: {}",
        domain.residence(),
        domain.bytes(),
        huge_pages_in_use()
    );

    // `--rebuild`: this build's BVH settings on the scene's triangles, without preparing again.
    let rebuilt = opts.rebuild.then(|| {
        let mut p: Vec<PackedTriangle> = domain.bvh().triangles().collect();
        let t = std::time::Instant::now();
        let b = rayfarm_core::bvh::build(&mut p);
        eprintln!(
            "rebuilt the BVH in {:.2} s: {} nodes, {} blocks; {}",
            t.elapsed().as_secs_f64(),
            b.nodes.len(),
            b.blocks.len(),
            tree_stats(&b.nodes, &b.blocks, p.len())
        );
        (p, b)
    });
    let bvh = match &rebuilt {
        Some((_, b)) => Bvh::new(&b.nodes, &b.blocks)?,
        None => domain.bvh(),
    };
    // A first untimed pass over the camera rays finds the hits the diffuse rays start from.
    let tree = manifest.domain_tree();
    let (camera, pixels) = camera_rays(&manifest, &tree, opts.size);
    let mut hits = Vec::new();
    trace_rayfarm(bvh, &camera, Mode::Single, &mut hits);
    let diffuse = diffuse_rays(&camera, &pixels, &hits, bvh, &tree, manifest.ray_epsilon);
    let light = (manifest.ray_epsilon, manifest.lights.as_slice());
    let shadow = shadow_rays(&camera, &hits, bvh, &tree, light);
    let sets: [(&str, &[BenchRay]); 3] = [
        ("coherent", &camera),
        ("incoherent", &diffuse),
        ("shadow", &shadow),
    ];
    if let Some(name) = &opts.count {
        let (_, rays) = sets
            .iter()
            .find(|(n, _)| n == name)
            .ok_or_else(|| format!("--count {name}: expected coherent, incoherent or shadow"))?;
        let mode = mode_of(name);
        let packets = mode == Mode::Packets && Traverser::new().packets();
        rayfarm_core::bvh::counters::take();
        let found = counted_pass(bvh, rays, mode);
        println!(
            "{name}: {} rays, {found} hits, kernel {}, packets {}",
            rays.len(),
            Traverser::new().kernel().name(),
            if packets { "on" } else { "off" }
        );
        // Built with `--features counters`: what the pass touched, per ray.
        if rayfarm_core::bvh::counters::ENABLED {
            let c = rayfarm_core::bvh::counters::take();
            let per = |v: u64| v as f64 / rays.len().max(1) as f64;
            println!(
                "per ray: {:.3} node visits, {:.3} leaf visits, {:.3} block tests",
                per(c.nodes),
                per(c.leaves),
                per(c.blocks)
            );
        }
        return Ok(());
    }

    let temp = tempfile::Builder::new()
        .prefix("embree-compare")
        .tempdir()?;
    // `--keep DIR`: the mesh, ray and hit files stay there, to run `embree_trace` on its own
    // (under callgrind, for example).
    let dir = match &opts.keep {
        Some(keep) => {
            std::fs::create_dir_all(keep)?;
            keep.clone()
        }
        None => temp.path().to_path_buf(),
    };
    let mesh: Vec<PackedTriangle> = bvh.triangles().collect();
    let mesh_ids: Vec<u64> = mesh.iter().map(PackedTriangle::id).collect();
    write_mesh(&dir.join("mesh.bin"), &mesh)?;
    let ray_files: Vec<PathBuf> = sets
        .iter()
        .map(|(name, rays)| {
            let path = dir.join(format!("{name}.rays"));
            write_rays(&path, rays).map(|()| path)
        })
        .collect::<Result<_>>()?;

    eprintln!(
        "{} triangles; {} of {} camera rays enter the domain, {} diffuse rays, {} shadow rays; \
         {} repetitions each",
        mesh.len(),
        camera.len(),
        opts.size * opts.size,
        diffuse.len(),
        shadow.len(),
        opts.reps
    );
    let mut ours = Vec::new();
    for (name, rays) in &sets {
        let mut hits = Vec::new();
        let seconds = (0..opts.reps)
            .map(|_| trace_rayfarm(bvh, rays, mode_of(name), &mut hits))
            .collect();
        ours.push((Timing(seconds), hits));
    }

    let named_files: Vec<(&str, &Path)> = sets
        .iter()
        .zip(&ray_files)
        .map(|((name, _), path)| (*name, path.as_path()))
        .collect();
    let report = run_embree(&opts, dir.as_path(), &named_files)?;

    // Which ISA each side may use, so a table made from this output can say so.
    println!(
        "rayfarm kernel {}, Embree {} capped at {}",
        Traverser::new().kernel().name(),
        report["embree"].as_str().unwrap_or("?"),
        report["max_isa"].as_str().unwrap_or("?")
    );
    println!(
        "{:<11} {:>9} {:>12} {:>12} {:>12} {:>10} {:>10}",
        "rays", "count", "rayfarm", "embree med", "embree high", "rf/embree", "agree"
    );
    let mut summary = serde_json::Map::new();
    for ((name, rays), (timing, hits)) in sets.iter().zip(&ours) {
        let n = rays.len();
        let theirs: Vec<EmbreeHit> =
            bytemuck::pod_collect_to_vec(&std::fs::read(dir.join(format!("{name}.hits")))?);
        if theirs.len() != n {
            return Err(format!("embree_trace wrote {} hits for {n} rays", theirs.len()).into());
        }
        let agreement = compare(hits, &theirs, &mesh_ids, mode_of(name) == Mode::Any);
        let medium = embree_timing(&report, "medium", name).ok_or("no medium-quality timing")?;
        let high = embree_timing(&report, "high", name);
        let (rf, em) = (timing.median_mrays(n), medium.median_mrays(n));
        let high_mrays = high.as_ref().map(|h| h.median_mrays(n));
        println!(
            "{:<11} {:>9} {:>12.3} {:>12.3} {:>12} {:>10.3} {:>9.4}%",
            name,
            n,
            rf,
            em,
            high_mrays.map_or("-".into(), |h| format!("{h:.3}")),
            rf / em,
            agreement.fraction() * 100.0
        );
        for e in &agreement.examples {
            println!("    differs: {e}");
        }
        summary.insert(
            (*name).into(),
            json!({
                "rays": n,
                "rayfarm_mrays": rf,
                "rayfarm_mrays_best": timing.best_mrays(n),
                "embree_mrays": em,
                "embree_mrays_best": medium.best_mrays(n),
                "embree_high_mrays": high_mrays,
                "ratio_rayfarm_over_embree": rf / em,
                "agreement": agreement.fraction(),
                "both_hit": agreement.both_hit,
                "same_triangle_of_both_hit":
                    agreement.same_triangle as f64 / agreement.both_hit.max(1) as f64,
                "only_rayfarm_hits": agreement.only_rayfarm_hits,
                "only_embree_hits": agreement.only_embree_hits,
                "distance_differs": agreement.distance_differs,
            }),
        );
    }
    println!(
        "Mrays/s, median of {} single-thread passes; rf/embree = rayfarm / Embree medium; \
         agree = same hit/miss and t within {T_TOLERANCE} relative",
        opts.reps
    );
    let build_seconds: serde_json::Map<String, Value> = report["builds"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|b| {
            Some((
                b["quality"].as_str()?.to_owned(),
                b["build_seconds"].clone(),
            ))
        })
        .collect();
    let summary = json!({
        "bench": "embree_compare",
        "scene": opts.scene.display().to_string(),
        "triangles": mesh.len(),
        "bvh_nodes": domain.nodes().len(),
        "rayfarm_kernel": Traverser::new().kernel().name(),
        "image": [opts.size, opts.size],
        "reps": opts.reps,
        "embree": report["embree"],
        "embree_max_isa": report["max_isa"],
        "embree_build_seconds": build_seconds,
        "load_average": load_average(),
        "sets": summary,
    });
    println!("{summary}");
    Ok(())
}
