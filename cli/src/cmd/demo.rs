//! `rayfarm demo`: the first thing to run. Prepares the built-in scene if it is missing, then
//! renders it on a real local cluster (a `rayfarm-coordinator` and N `rayfarm-worker`
//! processes on loopback, each with a cache of a quarter of the scene so domains are paged as
//! on a farm) and prints the statistics. `--local` renders in this process instead.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context;
use clap::Args;
use rayfarm_core::scene::Manifest;
use rayfarm_node::proto;

use super::prepare::{Generator, PrepareArgs};
use super::render::RenderArgs;
use super::submit::{WaitOptions, wait_and_save};
use crate::client::{Coordinator, runtime};
use crate::local_cluster::{ClusterConfig, JobInFlight, threads_per_worker, with_local_cluster};
use crate::view::{CameraArgs, FrameArgs};

/// Options of `rayfarm demo`.
#[derive(Args, Clone, Debug)]
pub struct DemoArgs {
    /// Where the demo keeps its scene and image.
    #[arg(long, default_value = "rayfarm-demo", env = "RAYFARM_DEMO_DIR")]
    pub dir: PathBuf,
    /// Triangles in the built-in scene.
    #[arg(long, default_value_t = 300_000)]
    pub triangles: u64,
    /// Domains of the built-in scene.
    #[arg(long, default_value_t = 16)]
    pub domains: u32,
    /// Image width.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Image height.
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Samples per pixel.
    #[arg(long, default_value_t = 4)]
    pub spp: u32,
    /// Worker processes of the local cluster (they share this machine's cores).
    #[arg(long, env = "RAYFARM_DEMO_WORKERS", default_value_t = 4,
          value_parser = clap::value_parser!(u32).range(1..=64))]
    pub workers: u32,
    /// Render in this process instead of on a local cluster.
    #[arg(long)]
    pub local: bool,
}

/// Bounces of the demo's frame.
const DEPTH: u32 = 3;

pub fn run(a: DemoArgs) -> anyhow::Result<()> {
    let scene = a.dir.join(format!("nbody-{}-{}", a.triangles, a.domains));
    // Re-prepare a scene that is missing, damaged or from an older build.
    let usable = Manifest::load(&scene).and_then(|m| m.check_domains(&scene, false));
    if usable.is_err() {
        eprintln!("preparing the built-in scene in {} ...", scene.display());
        super::prepare::run(PrepareArgs {
            input: None,
            out: scene.clone(),
            domains: a.domains,
            force: true,
            if_missing: false,
            name: Some("nbody".into()),
            generate: Some(Generator::Nbody),
            triangles: a.triangles,
            seed: 1,
            max_memory: None,
            dims: None,
            dtype: "u8".into(),
            iso: None,
            spacing: [1.0; 3],
            volume: false,
            bricks: None,
            transfer: "density".into(),
            step: None,
            shading: false,
            shadows: false,
            normals: None,
            colour_map: None,
            colour_axis: None,
            colour_by: None,
            colour_volume: None,
        })?;
    }
    let manifest = Manifest::load(&scene)?;
    let scene_bytes: u64 = manifest.domains.iter().map(|d| d.bytes).sum();
    // A quarter of the scene per renderer: it has to page domains in and out, as on a cluster.
    let cache_bytes = (scene_bytes / 4).max(1);
    if a.local {
        return super::render::run(RenderArgs {
            local: true,
            scene,
            out: a.dir.join("demo.png"),
            frame: FrameArgs {
                width: a.width,
                height: a.height,
                spp: a.spp,
                depth: DEPTH,
            },
            camera: CameraArgs::default(),
            threads: None,
            cache_bytes,
            wave_rays: 1 << 20,
            speculate: false,
            speculation: rayfarm_core::schedule::speculation_depth::Depth::Full,
            stats_json: Some(a.dir.join("demo-stats.json")),
            quiet: false,
        });
    }
    run_cluster(&a, &scene, cache_bytes)
}

/// Starts the local cluster, renders the frame on it and stops it, whatever happens
/// (including Ctrl-C).
fn run_cluster(a: &DemoArgs, scene: &Path, cache_bytes: u64) -> anyhow::Result<()> {
    let workers = a.workers as usize;
    // Finds the binaries before anything starts, so a missing one costs nothing.
    let mut config = ClusterConfig::for_scene(
        scene,
        &a.dir.join("cluster"),
        workers,
        cache_bytes,
        threads_per_worker(workers),
    )?;
    // The dashboard on a port the OS chooses (printed once the coordinator is up).
    config.coordinator_extra = vec!["--http".into(), "127.0.0.1:0".into()];
    let spec = proto::JobSpec {
        scene: config.default_scene.clone(),
        camera: None,
        width: a.width,
        height: a.height,
        spp: a.spp,
        max_depth: DEPTH,
        schedule: proto::Schedule::Dynamic as i32,
        priority: 0,
        cold_cache: false,
        progressive: None,
        speculation: String::new(),
        prefetch: false,
        peer_domains: false,
    };
    let wait = WaitOptions {
        output: Some(a.dir.join("demo.png")),
        stats_json: Some(a.dir.join("demo-stats.json")),
        quiet: false,
        // The demo's coordinator is its own child: if it dies, the demo is over.
        ride_out: Duration::ZERO,
        // The cluster stops with the demo; its results stay in the coordinator's data dir.
        fetch_again: false,
    };
    let in_flight = JobInFlight::default();
    runtime()?.block_on(with_local_cluster(&config, &in_flight, async |url| {
        let mut coord = Coordinator::connect(&url).await?;
        let job_id = coord
            .submit(spec)
            .await
            .context("submitting the demo frame")?;
        in_flight.set(&coord, &job_id);
        eprintln!("job {job_id} submitted to {url}");
        wait_and_save(&mut coord, &job_id, &wait).await?;
        in_flight.clear();
        Ok(())
    }))?;
    println!(
        "image {}, statistics {}, cluster logs {}",
        a.dir.join("demo.png").display(),
        a.dir.join("demo-stats.json").display(),
        config.data_dir.join("*.log").display()
    );
    Ok(())
}
