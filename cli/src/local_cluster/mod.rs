//! A coordinator and workers as child processes of this one, for `rayfarm demo` and `rayfarm
//! bench`: the real binaries talking gRPC over loopback, so both exercise exactly what a farm
//! runs. Both start the cluster the same way ([`ClusterConfig`], [`with_local_cluster`]), so a
//! benchmark measures the cluster the demo shows.
//!
//! Children start in their own process group, so a Ctrl-C in the terminal reaches only
//! `rayfarm`, which then cancels the job in flight ([`JobInFlight`]) and stops them in order
//! (SIGTERM, a grace period, then SIGKILL). SIGTERM and SIGHUP (a closed terminal, `kill`,
//! a service manager) are handled the same way. If `rayfarm` leaves by another path, dropping
//! the [`LocalCluster`] kills what is left, and on Linux every child is started with
//! `PR_SET_PDEATHSIG`, so even a `rayfarm` killed by SIGKILL takes its children with it.
//!
//! The parts: this module says what cluster to start and runs a session on it, [`children`]
//! starts and stops the child processes, [`interrupt`] turns a stop signal into the end of a
//! session and cancels its job in flight.

use std::ffi::OsString;
use std::path::{Path, PathBuf};

use anyhow::{Context, anyhow, bail};

use crate::client::Coordinator;
use crate::cmd::status::wait_for_workers;

mod children;
mod interrupt;

pub use children::LocalCluster;
use children::START_TIMEOUT;
pub use interrupt::{Interrupted, JobInFlight, interruptible, stop_signal};

/// The path of `name`, a binary installed next to this executable (`cargo build --release
/// --bins` puts them all in `target/release`).
pub fn sibling_binary(name: &str) -> anyhow::Result<PathBuf> {
    let exe = std::env::current_exe().context("finding this executable")?;
    let dir = exe
        .parent()
        .ok_or_else(|| anyhow!("{} has no parent directory", exe.display()))?;
    let path = dir.join(format!("{name}{}", std::env::consts::EXE_SUFFIX));
    if !path.is_file() {
        bail!(
            "{name} is missing next to {}: build them with `cargo build --release --bins`",
            exe.display()
        );
    }
    Ok(path)
}

/// Everything a local cluster needs, worked out before any process starts.
#[derive(Clone, Debug)]
pub struct ClusterConfig {
    /// The `rayfarm-coordinator` binary.
    pub coordinator_bin: PathBuf,
    /// The `rayfarm-worker` binary.
    pub worker_bin: PathBuf,
    /// The coordinator's data directory (results), also where every child's log goes.
    pub data_dir: PathBuf,
    /// The scene root of every process (absolute).
    pub scene_root: PathBuf,
    /// The coordinator's default scene, a name under `scene_root`.
    pub default_scene: String,
    /// Worker processes.
    pub workers: usize,
    /// Domain cache budget of each worker, bytes.
    pub cache_bytes: u64,
    /// Tracing threads of each worker.
    pub threads: usize,
    /// More flags for the coordinator (e.g. `--replicate none`).
    pub coordinator_extra: Vec<OsString>,
    /// More flags for every worker (e.g. `--storage-bandwidth 100MiB/s`).
    pub worker_extra: Vec<OsString>,
}

impl ClusterConfig {
    /// A cluster rendering the prepared scene in `scene_dir` (its parent is the scene root,
    /// its directory name the default scene), with the binaries next to this executable,
    /// keeping data and logs in `data_dir`. Fails before anything starts if a binary is
    /// missing.
    pub fn for_scene(
        scene_dir: &Path,
        data_dir: &Path,
        workers: usize,
        cache_bytes: u64,
        threads: usize,
    ) -> anyhow::Result<Self> {
        let (scene_root, default_scene) = scene_root_and_name(scene_dir)?;
        Ok(Self {
            coordinator_bin: sibling_binary("rayfarm-coordinator")?,
            worker_bin: sibling_binary("rayfarm-worker")?,
            data_dir: std::path::absolute(data_dir)
                .with_context(|| format!("{}: no absolute path", data_dir.display()))?,
            scene_root,
            default_scene,
            workers,
            cache_bytes,
            threads,
            coordinator_extra: Vec::new(),
            worker_extra: Vec::new(),
        })
    }

    /// The coordinator's command line: loopback, a port the OS chooses.
    pub fn coordinator_args(&self) -> Vec<OsString> {
        let mut args: Vec<OsString> = vec![
            "--listen".into(),
            "127.0.0.1:0".into(),
            "--data-dir".into(),
            self.data_dir.clone().into(),
            "--scene-root".into(),
            self.scene_root.clone().into(),
            "--default-scene".into(),
            self.default_scene.clone().into(),
        ];
        args.extend(self.coordinator_extra.iter().cloned());
        args
    }

    /// A worker's command line, attached to the coordinator at `coordinator_url`.
    pub fn worker_args(&self, coordinator_url: &str) -> Vec<OsString> {
        let mut args: Vec<OsString> = vec![
            "--coordinator".into(),
            coordinator_url.into(),
            "--listen".into(),
            "127.0.0.1:0".into(),
            "--cache-bytes".into(),
            self.cache_bytes.to_string().into(),
            "--scene-root".into(),
            self.scene_root.clone().into(),
            "--threads".into(),
            self.threads.to_string().into(),
        ];
        args.extend(self.worker_extra.iter().cloned());
        args
    }
}

/// A prepared scene directory as (absolute scene root, scene name): its parent and its
/// directory name, which is how jobs name scenes relative to the nodes' scene root.
pub fn scene_root_and_name(scene_dir: &Path) -> anyhow::Result<(PathBuf, String)> {
    let absolute = std::path::absolute(scene_dir)
        .with_context(|| format!("{}: no absolute path", scene_dir.display()))?;
    let name = absolute
        .file_name()
        .and_then(|n| n.to_str())
        .ok_or_else(|| anyhow!("{}: scene directory name is not UTF-8", scene_dir.display()))?
        .to_string();
    let root = absolute
        .parent()
        .ok_or_else(|| anyhow!("{}: a scene directory has a parent", absolute.display()))?
        .to_path_buf();
    Ok((root, name))
}

/// The machine's cores shared among `workers` worker processes (at least one thread each).
pub fn threads_per_worker(workers: usize) -> usize {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    (cores / workers.max(1)).max(1)
}

/// Starts the cluster `config` describes (the coordinator, then the workers, then waits until
/// all have registered), runs `session` with the coordinator's URL, and stops every process
/// whatever happens: success, error or Ctrl-C. A session that fails or is interrupted has its
/// job in flight cancelled first.
pub async fn with_local_cluster<T>(
    config: &ClusterConfig,
    in_flight: &JobInFlight,
    session: impl AsyncFnOnce(String) -> anyhow::Result<T>,
) -> anyhow::Result<T> {
    let mut cluster = LocalCluster::new(&config.data_dir)?;
    eprintln!(
        "starting a local cluster: a coordinator and {} workers ({} thread{}, {} cache each); logs in {}",
        config.workers,
        config.threads,
        if config.threads == 1 { "" } else { "s" },
        crate::units::human(config.cache_bytes),
        cluster.log_dir().display()
    );
    let outcome = interruptible(in_flight, async {
        let url = start_cluster(&mut cluster, config).await?;
        session(url).await
    })
    .await;
    eprintln!("stopping the local cluster ...");
    for note in cluster.shutdown().await {
        eprintln!("warning: {note}");
    }
    if outcome.is_err() {
        eprintln!(
            "the cluster's logs: {}",
            config.data_dir.join("*.log").display()
        );
    }
    outcome
}

/// Starts the coordinator and the workers and waits for all workers to register; returns the
/// coordinator's URL.
async fn start_cluster(
    cluster: &mut LocalCluster,
    config: &ClusterConfig,
) -> anyhow::Result<String> {
    let addr = cluster
        .start(
            "coordinator",
            &config.coordinator_bin,
            &config.coordinator_args(),
        )
        .await?;
    let url = format!("http://{addr}");
    for i in 0..config.workers {
        cluster
            .start(
                &format!("worker-{i}"),
                &config.worker_bin,
                &config.worker_args(&url),
            )
            .await?;
    }
    let mut coord = Coordinator::connect(&url).await?;
    wait_for_workers(&mut coord, config.workers, START_TIMEOUT)
        .await
        .context("waiting for the workers to register")?;
    Ok(url)
}
