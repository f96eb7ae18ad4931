//! The child processes of a local cluster: each started in a process group of its own that
//! dies with this one, its stderr in a log file, waited on until it prints its address, and
//! stopped in order (SIGTERM, a grace period, then SIGKILL).

use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;

use anyhow::{Context, anyhow};
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, ChildStdout, Command};
use tokio::time::{Instant, timeout_at};

/// What a process prints on stdout, alone on a line, once its gRPC server is bound.
const LISTENING: &str = "listening on ";

/// What a server prints before [`LISTENING`] when it serves HTTP (`--http`).
const HTTP_ON: &str = "http on ";

/// How long a child may take to bind its port (and all workers to register).
pub(super) const START_TIMEOUT: Duration = Duration::from_secs(30);

/// How long children get to stop after SIGTERM before they are killed.
const STOP_GRACE: Duration = Duration::from_secs(10);

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
