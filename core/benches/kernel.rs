//! Kernel throughput (coherent primary and incoherent diffuse rays, one core, each ray over
//! the interval the kernel gives it), BVH build time,
//! and domain load time (mapped or copied into huge pages, vs rebuild), on the built-in scene at
//! 1M triangles in one domain. The traced domain is held as the process chooses (huge pages
//! unless `RAYFARM_HUGEPAGES=0`); the `_mapped` rows trace the same file mapped, for comparison.
//!
//! `cargo bench -p rayfarm-core --bench kernel`

use std::hint::black_box;
use std::path::PathBuf;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use glam::Vec3;
use rayfarm_core::bvh::{self, Kernel, TraceRay, Traverser};
use rayfarm_core::camera::PinholeCamera;
use rayfarm_core::geometry::PackedTriangle;
use rayfarm_core::prepare::generate::{NbodyOptions, prepare_nbody};
use rayfarm_core::ray::RayRecord;
use rayfarm_core::render::kernel::{KernelCounters, RaySink, SceneView};
use rayfarm_core::sampling::{Purpose, uniform};
use rayfarm_core::scene::partition::clip_to_box;
use rayfarm_core::scene::{DomainData, Manifest, Residence};

const TRIANGLES: u64 = 1_000_000;
/// Camera rays per side: 1024x1024, as in `bench/embree`.
const SIDE: u32 = 1024;

struct Bench {
    dir: PathBuf,
    manifest: Manifest,
    data: DomainData,
}

fn scene() -> Bench {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../target/bench-scenes/nbody-1m-1");
    // Made again when missing or of an older domain file format.
    let current = Manifest::load(&dir).is_ok_and(|m| m.open_domain(&dir, 0, false).is_ok());
    if !current {
        prepare_nbody(
            &dir,
            &NbodyOptions {
                name: "nbody".into(),
                triangles: TRIANGLES,
                seed: 1,
                domains: 1,
                max_memory: None,
                force: true,
            },
        )
        .expect("generate the benchmark scene");
    }
    let manifest = Manifest::load(&dir).expect("benchmark scene");
    let data = open(&dir, &manifest, false);
    Bench {
        dir,
        manifest,
        data,
    }
}

fn open(dir: &std::path::Path, m: &Manifest, verify: bool) -> DomainData {
    m.open_domain(dir, 0, verify).expect("benchmark domain")
}

fn open_as(dir: &std::path::Path, m: &Manifest, verify: bool, r: Residence) -> DomainData {
    m.open_domain_as(dir, 0, verify, Some(r))
        .expect("benchmark domain")
}

/// A ray with the interval the kernel traces it over: its span inside the (only) domain.
type Segment = (Vec3, Vec3, f32, f32);

fn segment(m: &Manifest, o: Vec3, d: Vec3) -> Option<Segment> {
    clip_to_box(&m.bounds, o, d, 0.0, f32::INFINITY).map(|(a, b)| (o, d, a, b))
}

fn primary_rays(m: &Manifest) -> Vec<Segment> {
    let cam = PinholeCamera::new(&m.camera, SIDE, SIDE);
    (0..SIDE * SIDE)
        .filter_map(|p| {
            let r = cam.primary(p, 0);
            segment(m, Vec3::from(r.origin), Vec3::from(r.dir))
        })
        .collect()
}

/// From every primary hit, a cosine-distributed direction about the surface normal.
fn diffuse_rays(b: &Bench, primary: &[Segment]) -> Vec<Segment> {
    let bvh = b.data.bvh();
    let mut traverser = Traverser::new();
    primary
        .iter()
        .enumerate()
        .filter_map(|(i, &(o, d, t0, t1))| {
            let hit = traverser.nearest_hit(bvh, &TraceRay::new(o, d), t0, t1)?;
            let mut n = bvh.triangle(&hit).normal();
            if n.dot(d) > 0.0 {
                n = -n;
            }
            let p = o + d * hit.t + n * 1e-4;
            let (t, bt) = n.any_orthonormal_pair();
            let u = uniform(i as u32, 0, 1, Purpose::BounceU, 0);
            let phi = std::f32::consts::TAU * uniform(i as u32, 0, 1, Purpose::BounceV, 0);
            let r = u.sqrt();
            let dir = (t * r * phi.cos() + bt * r * phi.sin() + n * (1.0 - u).sqrt()).normalize();
            segment(&b.manifest, p, dir)
        })
        .collect()
}

fn trace_all(data: &DomainData, rays: &[Segment], kernel: Kernel) -> usize {
    let bvh = data.bvh();
    // One traverser for the whole set, as the kernel keeps one per batch.
    let mut traverser = Traverser::with_kernel(kernel).expect("supported kernel");
    rays.iter()
        .filter(|&&(o, d, t0, t1)| {
            traverser
                .nearest_hit(bvh, &TraceRay::new(o, d), t0, t1)
                .is_some()
        })
        .count()
}

/// Shadow rays: from every primary hit towards a fixed point light above the scene.
fn shadow_all(b: &Bench, rays: &[Segment], kernel: Kernel) -> usize {
    let bvh = b.data.bvh();
    let mut traverser = Traverser::with_kernel(kernel).expect("supported kernel");
    rays.iter()
        .filter(|&&(o, d, t0, t1)| traverser.any_hit(bvh, &TraceRay::new(o, d), t0, t1))
        .count()
}

/// From every primary hit, a segment towards a point above the scene's box.
fn shadow_rays(b: &Bench, primary: &[Segment]) -> Vec<Segment> {
    let bvh = b.data.bvh();
    let mut traverser = Traverser::new();
    let bounds = b.manifest.bounds;
    let light = Vec3::new(
        (bounds.min[0] + bounds.max[0]) * 0.3,
        bounds.max[1] * 2.0,
        (bounds.min[2] + bounds.max[2]) * 0.6,
    );
    primary
        .iter()
        .filter_map(|&(o, d, t0, t1)| {
            let hit = traverser.nearest_hit(bvh, &TraceRay::new(o, d), t0, t1)?;
            let mut n = bvh.triangle(&hit).normal();
            if n.dot(d) > 0.0 {
                n = -n;
            }
            let p = o + d * hit.t + n * 1e-4;
            let to = light - p;
            let (a, e) = clip_to_box(&b.manifest.bounds, p, to, 0.0, 1.0)?;
            Some((p, to, a, e))
        })
        .collect()
}

struct CountSink(usize);
impl RaySink for CountSink {
    fn push(&mut self, _: RayRecord) {
        self.0 += 1;
    }
    fn retire(&mut self, _: &RayRecord, _: [f32; 3]) {
        self.0 += 1;
    }
}

fn kernel(c: &mut Criterion) {
    let b = scene();
    let primary = primary_rays(&b.manifest);
    let diffuse = diffuse_rays(&b, &primary);
    let shadow = shadow_rays(&b, &primary);
    let mut g = c.benchmark_group("trace_1m_one_core");
    for kernel in Kernel::ALL.into_iter().filter(|k| k.supported()) {
        g.throughput(Throughput::Elements(primary.len() as u64));
        g.bench_with_input(
            BenchmarkId::new("coherent_primary", kernel.name()),
            &kernel,
            |bch, &k| bch.iter(|| black_box(trace_all(&b.data, &primary, k))),
        );
        g.throughput(Throughput::Elements(diffuse.len() as u64));
        g.bench_with_input(
            BenchmarkId::new("incoherent_diffuse", kernel.name()),
            &kernel,
            |bch, &k| bch.iter(|| black_box(trace_all(&b.data, &diffuse, k))),
        );
        g.throughput(Throughput::Elements(shadow.len() as u64));
        g.bench_with_input(
            BenchmarkId::new("shadow_any_hit", kernel.name()),
            &kernel,
            |bch, &k| bch.iter(|| black_box(shadow_all(&b, &shadow, k))),
        );
    }
    // The same file mapped from the page cache in 4 KiB pages, on the widest kernel: what
    // huge pages change (README, "Benchmarks").
    let mapped = open_as(&b.dir, &b.manifest, false, Residence::Mapped);
    let widest = Kernel::detect();
    for (name, rays) in [
        ("coherent_primary", &primary),
        ("incoherent_diffuse", &diffuse),
    ] {
        g.throughput(Throughput::Elements(rays.len() as u64));
        g.bench_with_input(
            BenchmarkId::new(format!("{name}_mapped"), widest.name()),
            &widest,
            |bch, &k| bch.iter(|| black_box(trace_all(&mapped, rays, k))),
        );
    }
    // The whole kernel on camera rays: traversal plus shading and spawning children.
    let view = SceneView::new(&b.manifest, 3);
    // Camera rays of a 256x256 image (the kernel also shades, so fewer rays suffice).
    let cam = PinholeCamera::new(&b.manifest.camera, 256, 256);
    let records: Vec<RayRecord> = (0..256 * 256)
        .map(|p| RayRecord {
            domain: 0,
            ..cam.primary(p, 0)
        })
        .collect();
    g.throughput(Throughput::Elements(records.len() as u64));
    g.bench_function("kernel_primary_with_shading", |bch| {
        bch.iter(|| {
            let mut sink = CountSink(0);
            let mut counters = KernelCounters::default();
            view.trace(&b.data, &records, &mut sink, &mut counters);
            black_box(sink.0)
        })
    });
    g.finish();
}

fn build_and_load(c: &mut Criterion) {
    let b = scene();
    let tris: Vec<PackedTriangle> = b.data.bvh().triangles().collect();
    let mut g = c.benchmark_group("domain_1m");
    g.sample_size(10);
    g.throughput(Throughput::Elements(tris.len() as u64));
    for builder in bvh::Builder::ALL {
        g.bench_with_input(
            BenchmarkId::new("bvh_build", builder.name()),
            &builder,
            |bch, &builder| {
                bch.iter(|| {
                    let mut t = tris.clone();
                    black_box(bvh::build_with(builder, &mut t).nodes.len())
                })
            },
        );
    }
    for (residence, how) in [
        (Residence::Mapped, "map"),
        (Residence::HugePages, "copy_huge"),
    ] {
        for verify in [false, true] {
            let name = if verify {
                format!("{how}_and_verify_checksum")
            } else {
                how.to_string()
            };
            g.bench_with_input(BenchmarkId::new("load", name), &verify, |bch, &v| {
                bch.iter(|| black_box(open_as(&b.dir, &b.manifest, v, residence).nodes().len()))
            });
        }
    }
    g.bench_with_input(
        BenchmarkId::new("load", "read_triangles_and_rebuild"),
        &(),
        |bch, _| {
            bch.iter(|| {
                let d = open(&b.dir, &b.manifest, false);
                let mut t: Vec<PackedTriangle> = d.bvh().triangles().collect();
                black_box(bvh::build(&mut t).nodes.len())
            })
        },
    );
    g.finish();
}

criterion_group!(benches, kernel, build_and_load);
criterion_main!(benches);
