//! Direct volume rendering throughput: volume samples per second on one core, with empty-space
//! skipping inside the brick on and off, unlit and shaded by the gradient and the lights. The
//! generator's density field at 128^3 in one brick, camera rays of a 256x256 image through the
//! whole kernel (`SceneView::trace`: march, composite, retire). A sample is one position on a
//! ray's sample grid inside the volume, taken or skipped, so both runs count the same work.
//!
//! `cargo bench -p rayfarm-core --bench volume`

use std::hint::black_box;
use std::path::{Path, PathBuf};

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use rayfarm_core::camera::PinholeCamera;
use rayfarm_core::prepare::brick_scene::VolumeLook;
use rayfarm_core::prepare::generate::{NbodyOptions, prepare_nbody_volume};
use rayfarm_core::ray::RayRecord;
use rayfarm_core::render::kernel::{KernelCounters, RaySink, SceneView};
use rayfarm_core::scene::{DomainData, Manifest};
use rayfarm_core::transfer::TransferFunction;

/// Voxels per side of the benchmark volume.
const SIDE: u32 = 128;

fn scene(name: &str, shading: bool) -> (Manifest, DomainData) {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../target/bench-scenes")
        .join(name);
    let current = Manifest::load(&dir).is_ok_and(|m| m.open_domain(&dir, 0, false).is_ok());
    if !current {
        let options = NbodyOptions {
            name: name.into(),
            triangles: 0,
            seed: 1,
            domains: 1,
            max_memory: None,
            force: true,
        };
        let look = VolumeLook {
            transfer: TransferFunction::preset("density").expect("preset"),
            shading,
            shadows: false,
            iso_surface: None,
        };
        prepare_nbody_volume(&dir, &options, SIDE, look).expect("generate the benchmark volume");
    }
    let manifest = Manifest::load(&dir).expect("benchmark volume");
    let data = open(&dir, &manifest);
    (manifest, data)
}

fn open(dir: &Path, m: &Manifest) -> DomainData {
    m.open_domain(dir, 0, false).expect("benchmark brick")
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

fn trace(view: &SceneView, data: &DomainData, rays: &[RayRecord]) -> KernelCounters {
    let mut sink = CountSink(0);
    let mut counters = KernelCounters::default();
    view.trace(data, rays, &mut sink, &mut counters);
    black_box(sink.0);
    counters
}

fn volume(c: &mut Criterion) {
    let mut g = c.benchmark_group("dvr_128_one_core");
    for (name, shading) in [("unlit", false), ("shaded", true)] {
        let (manifest, data) = scene(&format!("nbody-volume-{SIDE}-{name}"), shading);
        let cam = PinholeCamera::new(&manifest.camera, 256, 256);
        let rays: Vec<RayRecord> = (0..256 * 256)
            .map(|p| RayRecord {
                domain: 0,
                credit: 1,
                ..cam.primary(p, 0)
            })
            .collect();
        for skipping in [true, false] {
            let mut view = SceneView::new(&manifest, 0);
            view.set_volume_skipping(skipping);
            let counted = trace(&view, &data, &rays);
            let samples = counted.volume_samples + counted.volume_skipped;
            eprintln!(
                "{name}, skipping {skipping}: {samples} sample positions, {} interpolated",
                counted.volume_samples
            );
            g.throughput(Throughput::Elements(samples));
            let id = BenchmarkId::new(name, if skipping { "skipping" } else { "no_skipping" });
            g.bench_function(id, |b| b.iter(|| trace(&view, &data, &rays)));
        }
    }
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10);
    targets = volume
}
criterion_main!(benches);
