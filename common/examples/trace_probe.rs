//! Traces the benchmark scene's coherent or incoherent ray set N times and prints the rate, for
//! profiling under `valgrind --tool=callgrind` or `/usr/bin/time` (CPU time is less disturbed
//! by other load than wall time). Needs the scene that `cargo bench --bench kernel` generates.
//!
//! `cargo run --release -p rayfarm-common --example trace_probe -- [coherent|incoherent] N`

use std::path::PathBuf;

use glam::Vec3;
use rayfarm_common::bvh::{TraceRay, Traverser};
use rayfarm_common::camera::PinholeCamera;
use rayfarm_common::sampling::{Purpose, uniform};
use rayfarm_common::scene::{DomainData, Manifest};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let kind = args.get(1).map_or("coherent", String::as_str);
    let reps: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(10);
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../target/bench-scenes/nbody-1m-1");
    let m = Manifest::load(&dir).expect("run `cargo bench --bench kernel` once to make the scene");
    let d = &m.domains[0];
    let sum = u64::from_str_radix(&d.checksum, 16).expect("hex checksum");
    let data = DomainData::open(&dir.join(&d.file), sum, false, 64).expect("domain");
    let (nodes, tris) = (data.nodes(), data.packed());
    let cam = PinholeCamera::new(&m.camera, 256, 256);
    let mut rays: Vec<(Vec3, Vec3)> = (0..256 * 256)
        .map(|p| {
            let r = cam.primary(p, 0);
            (Vec3::from(r.origin), Vec3::from(r.dir))
        })
        .collect();
    if kind == "incoherent" {
        rays = rays
            .iter()
            .enumerate()
            .filter_map(|(i, &(o, d))| {
                let h = Traverser::new().nearest_hit(
                    nodes,
                    tris,
                    &TraceRay::new(o, d),
                    0.0,
                    f32::INFINITY,
                )?;
                let mut n = tris[h.slot as usize].normal();
                if n.dot(d) > 0.0 {
                    n = -n;
                }
                let u = uniform(i as u32, 0, 1, Purpose::BounceU, 0);
                let v = uniform(i as u32, 0, 1, Purpose::BounceV, 0);
                let (t, b) = n.any_orthonormal_pair();
                let phi = std::f32::consts::TAU * v;
                let dir =
                    t * (u.sqrt() * phi.cos()) + b * (u.sqrt() * phi.sin()) + n * (1.0 - u).sqrt();
                Some((o + d * h.t + n * 1e-4, dir.normalize()))
            })
            .collect();
    }
    let start = std::time::Instant::now();
    let mut hits = 0usize;
    let mut traverser = Traverser::new();
    for _ in 0..reps {
        for (o, d) in &rays {
            let ray = TraceRay::new(*o, *d);
            hits += traverser
                .nearest_hit(nodes, tris, &ray, 0.0, f32::INFINITY)
                .is_some() as usize;
        }
    }
    let n = rays.len() * reps;
    let rate = n as f64 / start.elapsed().as_secs_f64() / 1e6;
    println!("{kind}: {n} rays, {hits} hits, {rate:.3} Mrays/s wall");
}
