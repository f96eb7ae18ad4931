//! `rayfarm demo`: the first thing to run. Prepares the built-in scene if it is missing, then
//! renders it on a real local cluster (a `rayfarm-coordinator` and N `rayfarm-worker`
//! processes on loopback, each with a cache of a quarter of the scene so domains are paged as
//! on a farm) and prints the statistics. `--local` renders in this process instead.

use std::cell::OnceCell;
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, anyhow};
use clap::Args;
use rayfarm_common::proto;
use rayfarm_common::scene::Manifest;

use super::prepare::{Generator, PrepareArgs};
use super::render::RenderArgs;
use super::status::wait_for_workers;
use super::submit::{WaitOptions, wait_and_save};
use crate::client::{Coordinator, runtime};
use crate::local_cluster::{LocalCluster, START_TIMEOUT, sibling_binary};

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
            name: Some("nbody".into()),
            generate: Some(Generator::Nbody),
            triangles: a.triangles,
            seed: 1,
            max_memory: None,
            dims: None,
            dtype: "u8".into(),
            iso: None,
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
            width: a.width,
            height: a.height,
            spp: a.spp,
            depth: DEPTH,
            eye: None,
            look_at: None,
            fov: None,
            threads: None,
            cache_bytes,
            wave_rays: 1 << 20,
            stats_json: Some(a.dir.join("demo-stats.json")),
            quiet: false,
        });
    }
    run_cluster(&a, &scene, cache_bytes)
}

/// Starts the local cluster, renders the frame on it and stops it, whatever happens
/// (including Ctrl-C).
fn run_cluster(a: &DemoArgs, scene: &Path, cache_bytes: u64) -> anyhow::Result<()> {
    // Find the binaries before anything starts, so a missing one costs nothing.
    let coordinator_bin = sibling_binary("rayfarm-coordinator")?;
    let worker_bin = sibling_binary("rayfarm-worker")?;
    let scene_name = scene
        .file_name()
        .and_then(|n| n.to_str())
        .ok_or_else(|| anyhow!("{}: scene directory name is not UTF-8", scene.display()))?
        .to_string();
    let absolute = |p: &Path| {
        std::path::absolute(p).with_context(|| format!("{}: no absolute path", p.display()))
    };
    let plan = Plan {
        coordinator_bin,
        worker_bin,
        data_dir: absolute(&a.dir.join("cluster"))?,
        scene_root: absolute(&a.dir)?,
        scene_name: scene_name.clone(),
        workers: a.workers as usize,
        cache_bytes,
        threads: threads_per_worker(a.workers as usize),
        spec: proto::JobSpec {
            scene: scene_name,
            camera: None,
            width: a.width,
            height: a.height,
            spp: a.spp,
            max_depth: DEPTH,
            schedule: proto::Schedule::Dynamic as i32,
            priority: 0,
        },
        image: a.dir.join("demo.png"),
        stats_json: a.dir.join("demo-stats.json"),
    };
    runtime()?.block_on(async {
        let mut cluster = LocalCluster::new(&plan.data_dir)?;
        eprintln!(
            "starting a local cluster: a coordinator and {} workers ({} thread{}, {} cache each); logs in {}",
            plan.workers,
            plan.threads,
            if plan.threads == 1 { "" } else { "s" },
            crate::units::human(plan.cache_bytes),
            cluster.log_dir().display()
        );
        let submitted = OnceCell::new();
        let outcome = tokio::select! {
            r = session(&mut cluster, &plan, &submitted) => r,
            r = tokio::signal::ctrl_c() => match r {
                Ok(()) => Err(anyhow!("interrupted")),
                Err(e) => Err(anyhow!("listening for Ctrl-C: {e}")),
            },
        };
        if outcome.is_err()
            && let Some(job) = submitted.get()
        {
            cancel_quietly(&job.url, &job.job_id).await;
        }
        eprintln!("stopping the local cluster ...");
        for note in cluster.shutdown().await {
            eprintln!("warning: {note}");
        }
        let logs = plan.data_dir.join("*.log");
        match outcome {
            Ok(()) => {
                println!(
                    "image {}, statistics {}, cluster logs {}",
                    plan.image.display(),
                    plan.stats_json.display(),
                    logs.display()
                );
                Ok(())
            }
            Err(e) => {
                eprintln!("the cluster's logs: {}", logs.display());
                Err(e)
            }
        }
    })
}

/// A job the session submitted, and where.
struct Submitted {
    url: String,
    job_id: String,
}

/// Everything the cluster session needs, worked out before any process starts.
struct Plan {
    coordinator_bin: PathBuf,
    worker_bin: PathBuf,
    data_dir: PathBuf,
    scene_root: PathBuf,
    scene_name: String,
    workers: usize,
    cache_bytes: u64,
    threads: usize,
    spec: proto::JobSpec,
    image: PathBuf,
    stats_json: PathBuf,
}

/// Starts the coordinator and the workers, waits for all workers to register, then submits
/// the frame and follows it like `submit --wait`. Records the job in `submitted`, so that an
/// interrupted demo can cancel it.
async fn session(
    cluster: &mut LocalCluster,
    plan: &Plan,
    submitted: &OnceCell<Submitted>,
) -> anyhow::Result<()> {
    let addr = cluster
        .start(
            "coordinator",
            &plan.coordinator_bin,
            &coordinator_args(plan),
        )
        .await?;
    let url = format!("http://{addr}");
    for i in 0..plan.workers {
        cluster
            .start(
                &format!("worker-{i}"),
                &plan.worker_bin,
                &worker_args(plan, &url),
            )
            .await?;
    }
    let mut coord = Coordinator::connect(&url).await?;
    wait_for_workers(&mut coord, plan.workers, START_TIMEOUT)
        .await
        .context("waiting for the workers to register")?;
    let job_id = coord
        .submit(plan.spec.clone())
        .await
        .context("submitting the demo frame")?;
    let _ = submitted.set(Submitted {
        url: url.clone(),
        job_id: job_id.clone(),
    });
    eprintln!("job {job_id} submitted to {url}");
    let wait = WaitOptions {
        output: Some(plan.image.clone()),
        stats_json: Some(plan.stats_json.clone()),
        quiet: false,
    };
    wait_and_save(&mut coord, &job_id, &wait).await?;
    Ok(())
}

/// Cancels a job, giving up quietly after a moment: the cluster is being stopped anyway.
async fn cancel_quietly(url: &str, job_id: &str) {
    let cancel = async {
        let mut coord = Coordinator::connect(url).await?;
        coord.cancel(job_id).await
    };
    let _ = tokio::time::timeout(Duration::from_secs(3), cancel).await;
}

fn coordinator_args(plan: &Plan) -> Vec<OsString> {
    vec![
        "--listen".into(),
        "127.0.0.1:0".into(),
        "--data-dir".into(),
        plan.data_dir.clone().into(),
        "--scene-root".into(),
        plan.scene_root.clone().into(),
        "--default-scene".into(),
        plan.scene_name.clone().into(),
    ]
}

fn worker_args(plan: &Plan, coordinator_url: &str) -> Vec<OsString> {
    vec![
        "--coordinator".into(),
        coordinator_url.into(),
        "--listen".into(),
        "127.0.0.1:0".into(),
        "--cache-bytes".into(),
        plan.cache_bytes.to_string().into(),
        "--scene-root".into(),
        plan.scene_root.clone().into(),
        "--threads".into(),
        plan.threads.to_string().into(),
    ]
}

/// The machine's cores shared among the workers (at least one thread each).
fn threads_per_worker(workers: usize) -> usize {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    (cores / workers.max(1)).max(1)
}
