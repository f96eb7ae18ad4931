//! The processes of a test cluster: one started with its log in a file and waited on until it
//! prints `listening on ADDR` (on loopback or on a test host), and the signals, waits and
//! memory readings tests use on processes.

use std::fs::File;
use std::io::{BufRead, BufReader};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdout, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use crate::hosts::{Host, Net};

/// How long a started process may take to print `listening on ADDR`.
pub const START_TIMEOUT: Duration = Duration::from_secs(30);

/// Lines of each process's log shown when a test fails.
pub(crate) const LOG_TAIL_LINES: usize = 40;

/// Flags a server needs to serve on an address other than loopback without TLS (the test
/// hosts' addresses).
const OFF_LOOPBACK_FLAGS: &[&str] = &["--insecure"];

/// One process of a test cluster.
pub(crate) struct Proc {
    pub(crate) name: String,
    pub(crate) child: Child,
    pub(crate) log: PathBuf,
    pub(crate) addr: String,
    /// Its HTTP address, when it printed `http on ADDR` before `listening on`.
    pub(crate) http: Option<String>,
    /// The test host it runs on (`None`: this machine's loopback).
    pub(crate) host: Option<Host>,
    /// Killed by the test (its log is still shown).
    pub(crate) killed: bool,
}

/// A command running `program` on `host`, or here when there is none.
pub(crate) fn command_on(host: Option<&Host>, program: &Path) -> Command {
    match host {
        Some(host) => Net::command(host, program),
        None => Command::new(program),
    }
}

impl Proc {
    /// Starts `program args` (on `host` if any, in a process group of its own) with its
    /// stderr in `log`, and waits for its `listening on ADDR` line (panicking, with the end of
    /// its log, if it exits or stays silent).
    pub(crate) fn start(
        name: &str,
        program: &Path,
        args: &[String],
        env: &[(String, String)],
        descriptor_limit: Option<u64>,
        log: &Path,
        host: Option<&Host>,
    ) -> Proc {
        let log_file = File::create(log).expect("create log file");
        let mut cmd = command_on(host, program);
        if let Some(limit) = descriptor_limit {
            let limit = libc::rlimit {
                rlim_cur: limit,
                rlim_max: limit,
            };
            // SAFETY: setrlimit is async-signal-safe and touches only the child's limits.
            unsafe {
                cmd.pre_exec(move || {
                    if libc::setrlimit(libc::RLIMIT_NOFILE, &limit) == 0 {
                        Ok(())
                    } else {
                        Err(std::io::Error::last_os_error())
                    }
                });
            }
        }
        if host.is_some() {
            // On a test host: `stop` kills the group, whatever `ip netns exec` started.
            // (Loopback processes stay in the test's group: an interrupted run takes them.)
            cmd.process_group(0);
        }
        cmd.args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(log_file);
        // Logs go to a file: useful detail, no terminal colour codes.
        cmd.env("NO_COLOR", "1");
        if std::env::var_os("RUST_LOG").is_none() {
            cmd.env("RUST_LOG", "info");
        }
        cmd.envs(env.iter().map(|(k, v)| (k, v)));
        let mut child = cmd
            .spawn()
            .unwrap_or_else(|e| panic!("start {}: {e}", program.display()));
        let stdout = child.stdout.take().expect("piped stdout");
        match listening_address(stdout).recv_timeout(START_TIMEOUT) {
            Ok(Ok((addr, http))) => Proc {
                name: name.to_string(),
                child,
                log: log.to_path_buf(),
                addr,
                http,
                host: host.cloned(),
                killed: false,
            },
            failure => {
                let why = match failure {
                    Ok(Err(e)) => e,
                    _ => format!("printed no `listening on ADDR` within {START_TIMEOUT:?}"),
                };
                let _ = child.kill();
                let status = child.wait().map(|s| s.to_string()).unwrap_or_default();
                panic!(
                    "{name} {why} ({status}); {} args {args:?}; its log:\n{}",
                    program.display(),
                    log_tail(log, LOG_TAIL_LINES)
                );
            }
        }
    }

    /// Kills it (on a test host its whole process group) and reaps it.
    pub(crate) fn stop(&mut self) {
        if self.host.is_some() && self.child.try_wait().ok().flatten().is_none() {
            let group = format!("-{}", self.child.id());
            let _ = Command::new("kill").args(["-KILL", "--", &group]).output();
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// What a started server printed: its address and, with `--http`, its HTTP address.
type Listening = Result<(String, Option<String>), String>;

/// Reads a child's stdout on a thread: sends the address of its `listening on ADDR` line,
/// with that of an `http on ADDR` line before it (or why there is none), then drains the rest
/// so the child never blocks on a full pipe.
fn listening_address(stdout: ChildStdout) -> mpsc::Receiver<Listening> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let mut sent = false;
        let mut http = None;
        for line in BufReader::new(stdout).lines() {
            match line {
                Ok(line) if !sent => {
                    if let Some(addr) = line.trim().strip_prefix("http on ") {
                        http = Some(addr.trim().to_string());
                    } else if let Some(addr) = line.trim().strip_prefix("listening on ") {
                        let _ = tx.send(Ok((addr.trim().to_string(), http.take())));
                        sent = true;
                    }
                }
                Ok(_) => {}
                Err(e) => {
                    if !sent {
                        let _ = tx.send(Err(format!("stdout unreadable: {e}")));
                    }
                    return;
                }
            }
        }
        if !sent {
            let _ = tx.send(Err("exited before it was listening".into()));
        }
    });
    rx
}

/// The last `n` lines of a file, indented.
pub(crate) fn log_tail(path: &Path, n: usize) -> String {
    let text = std::fs::read(path)
        .map(|b| String::from_utf8_lossy(&b).into_owned())
        .unwrap_or_else(|e| format!("(unreadable: {e})"));
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(n)..]
        .iter()
        .map(|l| format!("    {l}\n"))
        .collect()
}

/// `--listen ADDR` for a server on `host` (its address, or loopback), on a port the OS
/// chooses, with the flags serving off loopback needs.
pub(crate) fn listen_args(host: Option<&Host>) -> Vec<String> {
    let mut args = vec!["--listen".to_string()];
    match host {
        Some(h) => {
            args.push(format!("{}:0", h.addr));
            args.extend(OFF_LOOPBACK_FLAGS.iter().map(|f| f.to_string()));
        }
        None => args.push("127.0.0.1:0".to_string()),
    }
    args
}

/// Sends `signal` (as `kill` takes it, e.g. "-TERM") to process `pid`.
pub fn signal_pid(pid: u32, signal: &str) {
    let pid = pid.to_string();
    let status = Command::new("kill")
        .args([signal, &pid])
        .status()
        .expect("run kill");
    assert!(status.success(), "kill {signal} {pid} failed");
}

/// Polls `check` until it holds; fails the test after `timeout`.
pub fn wait_until(what: &str, timeout: Duration, mut check: impl FnMut() -> bool) {
    let start = Instant::now();
    while !check() {
        assert!(start.elapsed() < timeout, "timed out waiting for {what}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Waits for a child process with a timeout, killing it and failing the test after.
pub fn wait_child(child: &mut std::process::Child, what: &str, timeout: Duration) -> bool {
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().expect("child status") {
            return status.success();
        }
        if start.elapsed() > timeout {
            let _ = child.kill();
            panic!("{what} did not end within {timeout:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// A field of `/proc/PID/status` in bytes (its value is in kB), e.g. `VmHWM:` (peak
/// resident memory) or `VmSize:`.
pub fn proc_status_bytes(pid: u32, field: &str) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("proc status");
    let kib: u64 = status
        .lines()
        .find_map(|l| l.strip_prefix(field))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap_or_else(|| panic!("no {field} in {status}"));
    kib * 1024
}
