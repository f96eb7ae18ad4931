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

use std::cell::RefCell;
use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;

use anyhow::{Context, anyhow, bail};
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, ChildStdout, Command};
use tokio::time::{Instant, timeout_at};

use crate::client::Coordinator;
use crate::cmd::status::wait_for_workers;

/// What a process prints on stdout, alone on a line, once its gRPC server is bound.
const LISTENING: &str = "listening on ";
/// What a server prints before [`LISTENING`] when it serves HTTP (`--http`).
const HTTP_ON: &str = "http on ";

/// How long a child may take to bind its port (and all workers to register).
const START_TIMEOUT: Duration = Duration::from_secs(30);

/// How long children get to stop after SIGTERM before they are killed.
const STOP_GRACE: Duration = Duration::from_secs(10);

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

/// The job a session is waiting for, if any, and where it runs: what an interrupted or
/// failed session cancels so the cluster does not go on rendering it.
#[derive(Default)]
pub struct JobInFlight(RefCell<Option<(Coordinator, String)>>);

impl JobInFlight {
    /// Records job `job_id` on `coordinator` as the one in flight.
    pub fn set(&self, coordinator: &Coordinator, job_id: &str) {
        self.0
            .replace(Some((coordinator.clone(), job_id.to_string())));
    }

    /// The job in flight has ended.
    pub fn clear(&self) {
        self.0.replace(None);
    }

    /// Cancels the job in flight (if any), giving up quietly after a moment: this is cleanup
    /// on the way out.
    pub async fn cancel_quietly(&self) {
        let Some((mut coord, job_id)) = self.0.take() else {
            return;
        };
        let cancel = coord.cancel(&job_id);
        let _ = tokio::time::timeout(Duration::from_secs(3), cancel).await;
    }
}

/// The session was stopped by a signal (Ctrl-C, SIGTERM or SIGHUP).
#[derive(Debug, thiserror::Error)]
#[error("interrupted by {0}")]
pub struct Interrupted(pub &'static str);

/// Completes with the signal's name on Ctrl-C (SIGINT) or, on Unix, SIGTERM or SIGHUP; fails
/// if a handler cannot be installed.
pub async fn stop_signal() -> anyhow::Result<&'static str> {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        let mut term = signal(SignalKind::terminate()).context("listening for SIGTERM")?;
        let mut hup = signal(SignalKind::hangup()).context("listening for SIGHUP")?;
        tokio::select! {
            r = tokio::signal::ctrl_c() => r.map(|()| "Ctrl-C").context("listening for Ctrl-C"),
            _ = term.recv() => Ok("SIGTERM"),
            _ = hup.recv() => Ok("SIGHUP"),
        }
    }
    #[cfg(not(unix))]
    {
        tokio::signal::ctrl_c()
            .await
            .context("listening for Ctrl-C")?;
        Ok("Ctrl-C")
    }
}

/// Runs `session` until it ends or a stop signal arrives (an [`Interrupted`] error); if it
/// did not succeed, cancels the job it left in flight.
pub async fn interruptible<T>(
    in_flight: &JobInFlight,
    session: impl Future<Output = anyhow::Result<T>>,
) -> anyhow::Result<T> {
    let outcome = tokio::select! {
        r = session => r,
        r = stop_signal() => match r {
            Ok(signal) => {
                // End whatever progress line was being written.
                eprintln!();
                Err(Interrupted(signal).into())
            }
            Err(e) => Err(e),
        },
    };
    if outcome.is_err() {
        in_flight.cancel_quietly().await;
    }
    outcome
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

/// One child process.
struct Proc {
    name: String,
    child: Child,
    log: PathBuf,
}

/// Children started by this process; stopped by [`LocalCluster::shutdown`], or killed on drop.
pub struct LocalCluster {
    log_dir: PathBuf,
    procs: Vec<Proc>,
}

impl LocalCluster {
    /// An empty cluster whose children log to `<log_dir>/<name>.log`.
    pub fn new(log_dir: &Path) -> anyhow::Result<Self> {
        std::fs::create_dir_all(log_dir)
            .with_context(|| format!("creating {}", log_dir.display()))?;
        Ok(Self {
            log_dir: log_dir.to_path_buf(),
            procs: Vec::new(),
        })
    }

    /// Where the children's logs are.
    pub fn log_dir(&self) -> &Path {
        &self.log_dir
    }

    /// Starts `program args` as `name` (its stderr going to `<name>.log`) and waits until it
    /// prints `listening on ADDR`; returns ADDR. A child that exits or stays silent for
    /// [`START_TIMEOUT`] is an error quoting the end of its log.
    pub async fn start(
        &mut self,
        name: &str,
        program: &Path,
        args: &[OsString],
    ) -> anyhow::Result<String> {
        let log = self.log_dir.join(format!("{name}.log"));
        let log_file = std::fs::File::create(&log)
            .with_context(|| format!("creating the log file {}", log.display()))?;
        let mut cmd = Command::new(program);
        cmd.args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::from(log_file))
            // Logs go to a file: no terminal colour codes in it.
            .env("NO_COLOR", "1");
        // The local cluster talks plain text on loopback: credentials this shell holds for a
        // real cluster would turn security on in the children but not in this client.
        for var in rayfarm_node::security::ENV_VARS {
            cmd.env_remove(var);
        }
        #[cfg(unix)]
        cmd.process_group(0);
        #[cfg(target_os = "linux")]
        die_with_parent(&mut cmd);
        let mut child = cmd
            .spawn()
            .with_context(|| format!("starting {}", program.display()))?;
        let stdout = child
            .stdout
            .take()
            .ok_or_else(|| anyhow!("{name}: stdout was not captured"))?;
        self.procs.push(Proc {
            name: name.to_string(),
            child,
            log: log.clone(),
        });
        match listening_address(stdout, Instant::now() + START_TIMEOUT).await {
            Ok((addr, http)) => {
                // The demo's coordinator serves the dashboard: say where.
                if let Some(http) = http {
                    eprintln!("{name}: dashboard and /metrics at http://{http}/");
                }
                Ok(addr)
            }
            Err(why) => {
                // A child that closed stdout is usually exiting: give it a moment to say how.
                let status = match self.procs.last_mut() {
                    Some(p) => tokio::time::timeout(Duration::from_secs(1), p.child.wait()).await,
                    None => Ok(Err(std::io::Error::other("no child"))),
                };
                let status = match status {
                    Ok(Ok(status)) => format!(" ({status})"),
                    _ => String::new(),
                };
                Err(anyhow!(
                    "{name} {why}{status}; the end of its log {}:\n{}",
                    log.display(),
                    log_tail(&log, 20)
                ))
            }
        }
    }

    /// Stops every child with SIGTERM, then SIGKILL for any still running after a grace
    /// period. The first child started (the coordinator) is stopped last, after all the others
    /// (the workers) have been signalled together and have exited, so no worker sees its
    /// coordinator vanish. Returns one note per child that had died on its own, failed, or did
    /// not stop in time, naming its log.
    pub async fn shutdown(&mut self) -> Vec<String> {
        let mut notes = Vec::new();
        let rest = if self.procs.is_empty() {
            Vec::new()
        } else {
            self.procs.split_off(1)
        };
        for mut group in [rest, std::mem::take(&mut self.procs)] {
            for p in &mut group {
                terminate(&mut p.child);
            }
            let deadline = Instant::now() + STOP_GRACE;
            for mut p in group {
                if let Some(note) = stop(&mut p, deadline).await {
                    notes.push(note);
                }
            }
        }
        notes
    }
}

/// Waits for a signalled child until `deadline`, then kills it; a note if it did not end
/// cleanly.
async fn stop(p: &mut Proc, deadline: Instant) -> Option<String> {
    let status = match timeout_at(deadline, p.child.wait()).await {
        Ok(Ok(status)) => status,
        Ok(Err(e)) => return Some(format!("waiting for {}: {e}", p.name)),
        Err(_) => {
            let killed = match p.child.kill().await {
                Ok(()) => String::new(),
                Err(e) => format!(" (killing it failed: {e})"),
            };
            return Some(format!(
                "{} did not stop within {STOP_GRACE:?} of SIGTERM and was killed{killed}; see {}",
                p.name,
                p.log.display()
            ));
        }
    };
    (!stopped_cleanly(status))
        .then(|| format!("{} ended with {status}; see {}", p.name, p.log.display()))
}

/// Exited with success, or by the SIGTERM it was sent.
fn stopped_cleanly(status: std::process::ExitStatus) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::process::ExitStatusExt;
        if status.signal() == Some(libc::SIGTERM) {
            return true;
        }
    }
    status.success()
}

impl Drop for LocalCluster {
    /// Last resort when `shutdown` was not reached: kill what is left. (Tokio reaps them.)
    fn drop(&mut self) {
        for p in &mut self.procs {
            let _ = p.child.start_kill();
        }
    }
}

/// Makes the child receive SIGKILL when this process dies, however it dies (SIGKILL
/// included), so no coordinator or worker outlives the `rayfarm` that started it.
#[cfg(target_os = "linux")]
fn die_with_parent(cmd: &mut Command) {
    let parent = std::process::id();
    // SAFETY: the closure runs in the child between fork and exec and calls only prctl(2) and
    // getppid(2), which are async-signal-safe, and allocates nothing on success.
    unsafe {
        cmd.pre_exec(move || {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // The parent may have died before the prctl took effect: then nothing will
            // signal this child, so it must not start.
            if u32::try_from(libc::getppid()).ok() != Some(parent) {
                return Err(std::io::Error::other("the parent exited while starting"));
            }
            Ok(())
        });
    }
}

/// Asks a child to stop: SIGTERM on Unix, kill elsewhere.
fn terminate(child: &mut Child) {
    #[cfg(unix)]
    if let Some(pid) = child.id().and_then(|id| libc::pid_t::try_from(id).ok()) {
        // SAFETY: kill(2) has no memory-safety preconditions. `pid` is our child and has not
        // been reaped (`id()` is `Some`), so it cannot name a recycled, unrelated process.
        unsafe {
            libc::kill(pid, libc::SIGTERM);
        }
        return;
    }
    let _ = child.start_kill();
}

/// Reads stdout until the `listening on ADDR` line, then keeps draining it in the background
/// so a chatty child can never block on a full pipe. Returns ADDR and the address of an
/// `http on ADDR` line printed before it.
async fn listening_address(
    stdout: ChildStdout,
    deadline: Instant,
) -> Result<(String, Option<String>), String> {
    let mut lines = BufReader::new(stdout).lines();
    let mut http = None;
    let found = timeout_at(deadline, async {
        loop {
            match lines.next_line().await {
                Ok(Some(line)) => {
                    if let Some(addr) = line.trim().strip_prefix(LISTENING) {
                        return Ok(addr.trim().to_string());
                    }
                    if let Some(addr) = line.trim().strip_prefix(HTTP_ON) {
                        http = Some(addr.trim().to_string());
                    }
                }
                Ok(None) => return Err("exited before it was listening".to_string()),
                Err(e) => return Err(format!("stdout could not be read: {e}")),
            }
        }
    })
    .await
    .unwrap_or_else(|_| {
        Err(format!(
            "did not print `{LISTENING}ADDR` within {START_TIMEOUT:?}"
        ))
    })?;
    tokio::spawn(async move { while let Ok(Some(_)) = lines.next_line().await {} });
    Ok((found, http))
}

/// The last `n` lines of a log file (or why it cannot be read).
pub fn log_tail(path: &Path, n: usize) -> String {
    match std::fs::read(path) {
        Ok(bytes) => {
            let text = String::from_utf8_lossy(&bytes);
            let lines: Vec<&str> = text.lines().collect();
            let tail = &lines[lines.len().saturating_sub(n)..];
            if tail.is_empty() {
                "  (empty)".into()
            } else {
                tail.iter()
                    .map(|l| format!("  {l}"))
                    .collect::<Vec<_>>()
                    .join("\n")
            }
        }
        Err(e) => format!("  (unreadable: {e})"),
    }
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;

    fn sh(script: &str) -> Vec<OsString> {
        vec!["-c".into(), script.into()]
    }

    #[test]
    fn children_report_their_address_and_stop_on_sigterm() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("logs");
        let rt = crate::client::runtime().unwrap();
        rt.block_on(async {
            let mut c = LocalCluster::new(&dir).unwrap();
            let addr = c
                .start(
                    "fake",
                    Path::new("/bin/sh"),
                    &sh("echo starting >&2; echo 'listening on 127.0.0.1:4242'; exec sleep 60"),
                )
                .await
                .unwrap();
            assert_eq!(addr, "127.0.0.1:4242");
            let err = c
                .start("dead", Path::new("/bin/sh"), &sh("echo boom >&2; exit 3"))
                .await
                .unwrap_err()
                .to_string();
            assert!(err.contains("exited before it was listening"), "{err}");
            assert!(
                err.contains("boom") && err.contains("(exit status: 3)"),
                "{err}"
            );
            let started = Instant::now();
            let notes = c.shutdown().await;
            assert!(
                started.elapsed() < STOP_GRACE,
                "sleep should die on SIGTERM"
            );
            assert_eq!(notes.len(), 1, "{notes:?}");
            assert!(
                notes[0].contains("dead ended with exit status: 3"),
                "{notes:?}"
            );
        });
        assert_eq!(log_tail(&dir.join("fake.log"), 5), "  starting");
    }
}
