//! Shared pieces of the integration tests: find the real binaries, run them, read their output,
//! and run a real cluster of them on loopback or on namespaced test hosts ([`Cluster`],
//! [`hosts`]).
//! The binaries are built by `cargo build --release --bins` (README's test command does it).

pub mod hosts;

use std::fs::File;
use std::io::{BufRead, BufReader};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdout, Command, ExitStatus, Output, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use crate::hosts::{Host, Net};

/// The files of `rayfarm certs --with-secrets` for loopback (see [`certs`]).
pub struct CertFiles {
    pub ca: PathBuf,
    pub cert: PathBuf,
    pub key: PathBuf,
    pub secret: PathBuf,
    pub tokens: PathBuf,
}

/// Runs `rayfarm certs --with-secrets` for loopback into `dir`.
pub fn certs(dir: &Path) -> CertFiles {
    rayfarm_ok(&[
        "certs",
        "--out",
        s(dir),
        "--hosts",
        "localhost,127.0.0.1",
        "--with-secrets",
    ]);
    CertFiles {
        ca: dir.join("ca.pem"),
        cert: dir.join("node.pem"),
        key: dir.join("node-key.pem"),
        secret: dir.join("cluster-secret"),
        tokens: dir.join("user-tokens"),
    }
}

/// Path of a workspace binary built in the same profile as this test.
pub fn bin(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/<test> -> target/<profile>/<name>
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .expect("target directory");
    let path = dir.join(name);
    assert!(
        path.exists(),
        "{} is missing: run `cargo build --release --bins` before the tests",
        path.display()
    );
    path
}

/// Runs `rayfarm` with `args`; returns its output, whatever the exit status.
pub fn rayfarm(args: &[&str]) -> Output {
    rayfarm_env(args, &[])
}

/// Runs `rayfarm` with `args` and extra environment variables; returns its output.
pub fn rayfarm_env(args: &[&str], env: &[(&str, &str)]) -> Output {
    Command::new(bin("rayfarm"))
        .args(args)
        .env("RUST_LOG", "warn")
        .envs(env.iter().copied())
        .output()
        .expect("start rayfarm")
}

/// Runs `rayfarm` and fails the test, showing stderr, unless it succeeds.
pub fn rayfarm_ok(args: &[&str]) -> Output {
    rayfarm_ok_env(args, &[])
}

/// [`rayfarm_ok`] with extra environment variables.
pub fn rayfarm_ok_env(args: &[&str], env: &[(&str, &str)]) -> Output {
    let out = rayfarm_env(args, env);
    assert!(
        out.status.success(),
        "rayfarm {} failed:\n{}",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Runs `rayfarm` expecting failure; returns its stderr.
pub fn rayfarm_err(args: &[&str]) -> String {
    let out = rayfarm(args);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(
        !out.status.success(),
        "rayfarm {} should have failed; stdout:\n{}",
        args.join(" "),
        String::from_utf8_lossy(&out.stdout)
    );
    stderr
}

/// A field of the statistics JSON written by `--stats-json`.
pub fn stats_field(path: &Path, pointer: &str) -> serde_json::Value {
    let text = std::fs::read_to_string(path).expect("stats json");
    let v: serde_json::Value = serde_json::from_str(&text).expect("stats json parses");
    v.pointer(pointer)
        .unwrap_or_else(|| panic!("{pointer} missing in {text}"))
        .clone()
}

/// xxh3 of a file's bytes, in hex.
pub fn file_hash(path: &Path) -> String {
    format!(
        "{:016x}",
        xxhash_rust::xxh3::xxh3_64(&std::fs::read(path).expect("read file"))
    )
}

/// `p` as a `&str` for argument lists.
pub fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// How long a started process may take to print `listening on ADDR`.
pub const START_TIMEOUT: Duration = Duration::from_secs(30);

/// Lines of each process's log shown when a test fails.
const LOG_TAIL_LINES: usize = 40;

/// How a worker of a [`Cluster`] is started.
#[derive(Clone, Debug)]
pub struct WorkerOpts {
    /// `--cache-bytes`: its domain cache budget.
    pub cache_bytes: u64,
    /// `--threads` (`None`: the worker's default, all cores).
    pub threads: Option<usize>,
    /// Extra environment variables, e.g. fault injection.
    pub env: Vec<(String, String)>,
    /// Extra command-line arguments, e.g. TLS files.
    pub args: Vec<String>,
    /// `--scene-root` (`None`: the cluster's).
    pub scene_root: Option<PathBuf>,
}

impl Default for WorkerOpts {
    /// 1 GiB of cache and one thread: test machines are small and clusters are several
    /// processes.
    fn default() -> Self {
        Self {
            cache_bytes: 1 << 30,
            threads: Some(1),
            env: Vec::new(),
            args: Vec::new(),
            scene_root: None,
        }
    }
}

impl WorkerOpts {
    /// The defaults with a cache budget of `cache_bytes`.
    pub fn cache(cache_bytes: u64) -> Self {
        Self {
            cache_bytes,
            ..Self::default()
        }
    }

    /// With `threads` tracing threads.
    pub fn threads(mut self, threads: usize) -> Self {
        self.threads = Some(threads);
        self
    }

    /// With the environment variable `key=value`.
    pub fn env(mut self, key: &str, value: &str) -> Self {
        self.env.push((key.to_string(), value.to_string()));
        self
    }

    /// With the command-line option `flag value`.
    pub fn arg(mut self, flag: &str, value: &str) -> Self {
        self.args.extend([flag.to_string(), value.to_string()]);
        self
    }

    /// With its own `--scene-root`, e.g. one where the cluster's scenes are missing.
    pub fn scene_root(mut self, root: &Path) -> Self {
        self.scene_root = Some(root.to_path_buf());
        self
    }

    /// With the extra arguments `args`.
    pub fn args(mut self, args: &[&str]) -> Self {
        self.args.extend(args.iter().map(|a| a.to_string()));
        self
    }
}

/// What a [`Cluster`] is started with beyond scenes and workers: flags and environment for
/// the coordinator, environment for every `rayfarm` the cluster runs, and the URL scheme.
#[derive(Clone, Debug, Default)]
pub struct ClusterOpts {
    /// Extra coordinator arguments, e.g. TLS files.
    pub coordinator_args: Vec<String>,
    /// Extra coordinator environment, e.g. fault injection.
    pub coordinator_env: Vec<(String, String)>,
    /// Environment of the cluster's `rayfarm` commands, e.g. a CA and a token.
    pub client_env: Vec<(String, String)>,
    /// The coordinator serves TLS: its URL is `https://`.
    pub https: bool,
    /// The coordinator's limit on open descriptors (`RLIMIT_NOFILE`), set before it starts.
    pub coordinator_descriptor_limit: Option<u64>,
}

/// Flags a server needs to serve on an address other than loopback without TLS (the test
/// hosts' addresses).
const OFF_LOOPBACK_FLAGS: &[&str] = &["--insecure"];

/// One process of a test cluster.
struct Proc {
    name: String,
    child: Child,
    log: PathBuf,
    addr: String,
    /// Its HTTP address, when it printed `http on ADDR` before `listening on`.
    http: Option<String>,
    /// The test host it runs on (`None`: this machine's loopback).
    host: Option<Host>,
    /// Killed by the test (its log is still shown).
    killed: bool,
}

/// A command running `program` on `host`, or here when there is none.
fn command_on(host: Option<&Host>, program: &Path) -> Command {
    match host {
        Some(host) => Net::command(host, program),
        None => Command::new(program),
    }
}

impl Proc {
    /// Starts `program args` (on `host` if any, in a process group of its own) with its
    /// stderr in `log`, and waits for its `listening on ADDR` line (panicking, with the end of
    /// its log, if it exits or stays silent).
    fn start(
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
    fn stop(&mut self) {
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
fn log_tail(path: &Path, n: usize) -> String {
    let text = std::fs::read(path)
        .map(|b| String::from_utf8_lossy(&b).into_owned())
        .unwrap_or_else(|e| format!("(unreadable: {e})"));
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(n)..]
        .iter()
        .map(|l| format!("    {l}\n"))
        .collect()
}

/// A real cluster, on loopback or with every process on a test host of its own
/// ([`Cluster::start_on_hosts`]): `rayfarm-coordinator` and `rayfarm-worker` processes, each
/// logging to a file in a temporary directory. Dropping it kills every process (then removes
/// the hosts); if the test is failing, the tails of all logs are printed first.
pub struct Cluster {
    /// The test hosts (`None`: loopback). Declared first, dropped after the processes
    /// (`Drop::drop` kills those).
    net: Option<Net>,
    /// Where the cluster's `rayfarm` commands run, on test hosts.
    client_host: Option<Host>,
    dir: tempfile::TempDir,
    scene_root: PathBuf,
    url: String,
    client_env: Vec<(String, String)>,
    coordinator: Proc,
    /// How the coordinator was started, to start it again the same way.
    coordinator_args: Vec<String>,
    coordinator_env: Vec<(String, String)>,
    coordinator_descriptor_limit: Option<u64>,
    /// Coordinators killed by the test (their logs are still shown).
    former_coordinators: Vec<Proc>,
    /// By index of start, killed ones included.
    workers: Vec<Proc>,
}

impl Cluster {
    /// Starts a coordinator serving scenes under `scene_root` (with `default_scene` for jobs
    /// that name none) and one worker per entry of `workers`, and waits until all workers are
    /// registered.
    pub fn start(
        scene_root: &Path,
        default_scene: Option<&str>,
        workers: &[WorkerOpts],
    ) -> Cluster {
        Self::start_with_env(scene_root, default_scene, &[], workers)
    }

    /// [`Cluster::start`] with extra environment variables for the coordinator (e.g. fault
    /// injection).
    pub fn start_with_env(
        scene_root: &Path,
        default_scene: Option<&str>,
        coordinator_env: &[(&str, &str)],
        workers: &[WorkerOpts],
    ) -> Cluster {
        let opts = ClusterOpts {
            coordinator_env: coordinator_env
                .iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect(),
            ..ClusterOpts::default()
        };
        Self::start_with(scene_root, default_scene, &opts, workers)
    }

    /// [`Cluster::start`] with extra coordinator flags and environment, and environment for
    /// the cluster's `rayfarm` commands.
    pub fn start_with(
        scene_root: &Path,
        default_scene: Option<&str>,
        opts: &ClusterOpts,
        workers: &[WorkerOpts],
    ) -> Cluster {
        Self::start_inner(None, scene_root, default_scene, opts, workers)
    }

    /// [`Cluster::start_with`] with every process on a host of its own on `net`: the
    /// coordinator on host `coordinator`, worker `i` on `worker-i`, and the cluster's `rayfarm`
    /// commands on `client`, each host with its own address (see [`hosts`]).
    pub fn start_on_hosts(
        net: Net,
        scene_root: &Path,
        default_scene: Option<&str>,
        opts: &ClusterOpts,
        workers: &[WorkerOpts],
    ) -> Cluster {
        Self::start_inner(Some(net), scene_root, default_scene, opts, workers)
    }

    fn start_inner(
        mut net: Option<Net>,
        scene_root: &Path,
        default_scene: Option<&str>,
        opts: &ClusterOpts,
        workers: &[WorkerOpts],
    ) -> Cluster {
        let client_host = net.as_mut().map(|n| n.add_host("client"));
        let host = net.as_mut().map(|n| n.add_host("coordinator"));
        let dir = tempfile::tempdir().expect("cluster temp dir");
        let data_dir = dir.path().join("data");
        std::fs::create_dir_all(&data_dir).expect("create data dir");
        let mut args = listen_args(host.as_ref());
        args.extend([
            "--data-dir".to_string(),
            s(&data_dir).to_string(),
            "--scene-root".to_string(),
            s(scene_root).to_string(),
        ]);
        if let Some(name) = default_scene {
            args.extend(["--default-scene".to_string(), name.to_string()]);
        }
        args.extend(opts.coordinator_args.iter().cloned());
        let coordinator = Proc::start(
            "coordinator",
            &bin("rayfarm-coordinator"),
            &args,
            &opts.coordinator_env,
            opts.coordinator_descriptor_limit,
            &dir.path().join("coordinator.log"),
            host.as_ref(),
        );
        let scheme = if opts.https { "https" } else { "http" };
        let mut cluster = Cluster {
            net,
            client_host,
            url: format!("{scheme}://{}", coordinator.addr),
            client_env: opts.client_env.clone(),
            dir,
            scene_root: scene_root.to_path_buf(),
            coordinator,
            coordinator_args: args,
            coordinator_env: opts.coordinator_env.clone(),
            coordinator_descriptor_limit: opts.coordinator_descriptor_limit,
            former_coordinators: Vec::new(),
            workers: Vec::new(),
        };
        for opts in workers {
            cluster.add_worker(opts);
        }
        cluster.wait_for_workers(workers.len(), START_TIMEOUT);
        cluster
    }

    /// The running coordinator's process id.
    pub fn coordinator_pid(&self) -> u32 {
        self.coordinator.child.id()
    }

    /// Worker `i`'s process id.
    pub fn worker_pid(&self, i: usize) -> u32 {
        self.workers[i].child.id()
    }

    /// Whether the cluster's processes run on test hosts of their own
    /// ([`Cluster::start_on_hosts`]).
    pub fn has_hosts(&self) -> bool {
        self.net.is_some()
    }

    /// The coordinator's HTTP address (host:port), when it was started with `--http`.
    pub fn coordinator_http(&self) -> Option<&str> {
        self.coordinator.http.as_deref()
    }

    /// Worker `i`'s HTTP address (host:port), when it was started with `--http`.
    pub fn worker_http(&self, i: usize) -> Option<&str> {
        self.workers[i].http.as_deref()
    }

    /// The coordinator's URL, `http://127.0.0.1:PORT` (`https://` with TLS).
    pub fn coordinator_url(&self) -> &str {
        &self.url
    }

    /// Starts one more worker (it may join mid-frame); returns its index. Waits until it is
    /// listening, not until it is registered (see [`Cluster::wait_for_workers`]).
    pub fn add_worker(&mut self, opts: &WorkerOpts) -> usize {
        let i = self.workers.len();
        let name = format!("worker-{i}");
        let host = self.net.as_mut().map(|n| n.add_host(&name));
        let mut args = vec!["--coordinator".to_string(), self.url.clone()];
        args.extend(listen_args(host.as_ref()));
        args.extend([
            "--cache-bytes".to_string(),
            opts.cache_bytes.to_string(),
            "--scene-root".to_string(),
            s(opts.scene_root.as_deref().unwrap_or(&self.scene_root)).to_string(),
        ]);
        if let Some(t) = opts.threads {
            args.extend(["--threads".to_string(), t.to_string()]);
        }
        args.extend(opts.args.iter().cloned());
        let log = self.dir.path().join(format!("{name}.log"));
        let proc = Proc::start(
            &name,
            &bin("rayfarm-worker"),
            &args,
            &opts.env,
            None,
            &log,
            host.as_ref(),
        );
        self.workers.push(proc);
        i
    }

    /// Freezes worker `i` (SIGSTOP): alive, connected, and doing nothing, as a hung node.
    pub fn pause_worker(&self, i: usize) {
        self.signal_worker(i, "-STOP");
    }

    /// Lets worker `i` go on after [`Cluster::pause_worker`] (SIGCONT).
    pub fn resume_worker(&self, i: usize) {
        self.signal_worker(i, "-CONT");
    }

    fn signal_worker(&self, i: usize, signal: &str) {
        signal_pid(self.workers[i].child.id(), signal);
    }

    /// Kills worker `i` at once (SIGKILL: a crash, not a shutdown) and reaps it.
    pub fn kill_worker(&mut self, i: usize) {
        let proc = &mut self.workers[i];
        assert!(!proc.killed, "worker {i} was already killed");
        proc.stop();
        proc.killed = true;
    }

    /// Kills the coordinator at once (SIGKILL: a crash, not a shutdown) and reaps it; the
    /// workers keep running. See [`Cluster::restart_coordinator`].
    pub fn kill_coordinator(&mut self) {
        assert!(
            !self.coordinator.killed,
            "the coordinator was already killed"
        );
        self.coordinator.stop();
        self.coordinator.killed = true;
    }

    /// Sends the coordinator `signal` (e.g. "-TERM") and waits up to `timeout` for it to exit;
    /// returns its exit status and how long it took. Panics if it is still running then.
    /// [`Cluster::restart_coordinator`] may follow.
    pub fn stop_coordinator(&mut self, signal: &str, timeout: Duration) -> (ExitStatus, Duration) {
        assert!(
            !self.coordinator.killed,
            "the coordinator was already stopped"
        );
        let pid = self.coordinator.child.id();
        signal_pid(pid, signal);
        let start = Instant::now();
        loop {
            if let Some(status) = self.coordinator.child.try_wait().expect("poll coordinator") {
                self.coordinator.killed = true;
                return (status, start.elapsed());
            }
            assert!(
                start.elapsed() < timeout,
                "the coordinator did not exit within {timeout:?} of kill {signal}"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Starts the coordinator again after [`Cluster::kill_coordinator`], with the same
    /// arguments, on the same address and data directory; its log is a new file. Waits until
    /// it is listening, not until workers have come back.
    pub fn restart_coordinator(&mut self) {
        assert!(self.coordinator.killed, "kill the coordinator first");
        let n = self.former_coordinators.len() + 2;
        let mut args = self.coordinator_args.clone();
        let listen = args
            .iter()
            .position(|a| a == "--listen")
            .expect("--listen among the coordinator's arguments");
        args[listen + 1] = self.coordinator.addr.clone();
        let name = format!("coordinator-{n}");
        let log = self.dir.path().join(format!("{name}.log"));
        let fresh = Proc::start(
            &name,
            &bin("rayfarm-coordinator"),
            &args,
            &self.coordinator_env,
            self.coordinator_descriptor_limit,
            &log,
            self.coordinator.host.as_ref(),
        );
        assert_eq!(
            fresh.addr, self.coordinator.addr,
            "restarted on another address"
        );
        let old = std::mem::replace(&mut self.coordinator, fresh);
        self.former_coordinators.push(old);
    }

    /// The coordinator's resident memory (VmRSS), bytes.
    pub fn coordinator_rss(&self) -> u64 {
        let status =
            std::fs::read_to_string(format!("/proc/{}/status", self.coordinator.child.id()))
                .expect("coordinator's /proc status");
        status
            .lines()
            .find_map(|l| l.strip_prefix("VmRSS:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
            .expect("VmRSS in /proc status")
            * 1024
    }

    /// The coordinator's address, `127.0.0.1:PORT`.
    pub fn coordinator_addr(&self) -> &str {
        &self.coordinator.addr
    }

    /// The coordinator's data directory.
    pub fn data_dir(&self) -> PathBuf {
        self.dir.path().join("data")
    }

    /// Waits until worker `i` exits by itself (panicking after `timeout`); returns its exit
    /// status.
    pub fn wait_worker_exit(&mut self, i: usize, timeout: Duration) -> ExitStatus {
        let start = std::time::Instant::now();
        loop {
            if let Some(status) = self.workers[i].child.try_wait().expect("poll worker") {
                return status;
            }
            assert!(
                start.elapsed() < timeout,
                "worker {i} did not exit within {timeout:?}"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Worker `i`'s log so far.
    pub fn worker_log(&self, i: usize) -> String {
        String::from_utf8_lossy(&std::fs::read(&self.workers[i].log).expect("worker log"))
            .into_owned()
    }

    /// The coordinator's log so far.
    pub fn coordinator_log(&self) -> String {
        String::from_utf8_lossy(&std::fs::read(&self.coordinator.log).expect("coordinator log"))
            .into_owned()
    }

    /// The peer address worker `i` printed (also once it is killed).
    pub fn worker_addr(&self, i: usize) -> &str {
        &self.workers[i].addr
    }

    /// Waits until at least `n` workers are registered with the coordinator (asking as a user
    /// would: `rayfarm status --wait-workers N`); panics after `timeout`.
    pub fn wait_for_workers(&self, n: usize, timeout: Duration) {
        self.rayfarm_ok(&[
            "status",
            "--wait-workers",
            &n.to_string(),
            "--timeout",
            &timeout.as_secs_f64().to_string(),
            "--json",
        ]);
    }

    /// `rayfarm status --json`, parsed.
    pub fn status(&self) -> serde_json::Value {
        let out = self.rayfarm_ok(&["status", "--json"]);
        serde_json::from_slice(&out.stdout).expect("status --json parses")
    }

    /// Runs `rayfarm` against this cluster (`RAYFARM_COORDINATOR` set); returns its output,
    /// whatever the exit status.
    pub fn rayfarm(&self, args: &[&str]) -> Output {
        let env: Vec<(&str, &str)> = self
            .client_env
            .iter()
            .map(|(k, v)| (k.as_str(), v.as_str()))
            .collect();
        self.rayfarm_as(&env, args)
    }

    /// Runs `rayfarm` against this cluster with only `env` added (not the cluster's client
    /// environment): a client with other credentials, or none.
    pub fn rayfarm_as(&self, env: &[(&str, &str)], args: &[&str]) -> Output {
        let mut cmd = self.client_command(&bin("rayfarm"));
        cmd.args(args)
            .env("RUST_LOG", "warn")
            .envs(env.iter().copied())
            .output()
            .expect("start rayfarm")
    }

    /// A command running `program` where the cluster's clients run (here, or on the test
    /// host `client`), with `RAYFARM_COORDINATOR` set: for `rayfarm` runs the test spawns.
    pub fn client_command(&self, program: &Path) -> Command {
        let mut cmd = command_on(self.client_host.as_ref(), program);
        cmd.env("RAYFARM_COORDINATOR", &self.url);
        cmd
    }

    /// The test hosts; panics on a loopback cluster.
    pub fn net(&self) -> &Net {
        self.net
            .as_ref()
            .expect("a cluster started with Cluster::start_on_hosts")
    }

    /// The host the coordinator runs on; panics on a loopback cluster.
    pub fn coordinator_host(&self) -> &Host {
        self.coordinator
            .host
            .as_ref()
            .expect("a cluster started with Cluster::start_on_hosts")
    }

    /// The host worker `i` runs on; panics on a loopback cluster.
    pub fn worker_host(&self, i: usize) -> &Host {
        self.workers[i]
            .host
            .as_ref()
            .expect("a cluster started with Cluster::start_on_hosts")
    }

    /// The hosts of every worker but `i` (killed ones included).
    pub fn other_worker_hosts(&self, i: usize) -> Vec<&Host> {
        (0..self.workers.len())
            .filter(|&j| j != i)
            .map(|j| self.worker_host(j))
            .collect()
    }

    /// [`Cluster::rayfarm`], failing the test (showing stderr) unless it succeeds.
    pub fn rayfarm_ok(&self, args: &[&str]) -> Output {
        let out = self.rayfarm(args);
        assert!(
            out.status.success(),
            "rayfarm {} failed ({}):\n{}",
            args.join(" "),
            out.status,
            String::from_utf8_lossy(&out.stderr)
        );
        out
    }

    /// The directory holding the processes' logs (and the coordinator's data directory).
    pub fn dir(&self) -> &Path {
        self.dir.path()
    }

    /// Prints the end of every process's log to stderr (shown with the failing test).
    pub fn dump_logs(&self) {
        let procs = self.former_coordinators.iter();
        for p in procs.chain([&self.coordinator]).chain(&self.workers) {
            eprintln!(
                "---- {} ({}{}), last {LOG_TAIL_LINES} lines of {}:\n{}",
                p.name,
                p.addr,
                if p.killed { ", killed by the test" } else { "" },
                p.log.display(),
                log_tail(&p.log, LOG_TAIL_LINES)
            );
        }
    }
}

/// `--listen ADDR` for a server on `host` (its address, or loopback), on a port the OS
/// chooses, with the flags serving off loopback needs.
fn listen_args(host: Option<&Host>) -> Vec<String> {
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

impl Drop for Cluster {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.dump_logs();
        }
        for w in &mut self.workers {
            w.stop();
        }
        self.coordinator.stop();
    }
}

// Helpers the integration tests share.

/// Prepares a generated scene `name` under `root`.
pub fn prepare_nbody(root: &Path, name: &str, triangles: u32, domains: u32) -> PathBuf {
    let out = root.join(name);
    rayfarm_ok(&[
        "prepare",
        "--generate",
        "nbody",
        "--triangles",
        &triangles.to_string(),
        "--seed",
        "5",
        "--domains",
        &domains.to_string(),
        "--out",
        s(&out),
    ]);
    out
}

/// The image hash of `render --local` for `frame`.
pub fn local_hash(scene: &Path, frame: &[&str]) -> String {
    let dir = tempfile::tempdir().expect("temp dir");
    let json = dir.path().join("local.json");
    let png = dir.path().join("local.png");
    let mut args = vec![
        "render",
        "--local",
        "--scene",
        s(scene),
        "--out",
        s(&png),
        "--stats-json",
        s(&json),
        "--quiet",
    ];
    args.extend_from_slice(frame);
    rayfarm_ok(&args);
    hash_of(&json)
}

/// The image hash in a statistics file.
pub fn hash_of(stats: &Path) -> String {
    stats_field(stats, "/image_hash")
        .as_str()
        .expect("hash is a string")
        .to_string()
}

/// `rayfarm submit --wait` on the cluster; returns the statistics file.
pub fn submit_wait(cluster: &Cluster, frame: &[&str], tag: &str) -> PathBuf {
    let png = cluster.dir().join(format!("{tag}.png"));
    let json = cluster.dir().join(format!("{tag}.json"));
    let mut args = vec![
        "submit",
        "--wait",
        "--quiet",
        "--output",
        s(&png),
        "--stats-json",
        s(&json),
    ];
    args.extend_from_slice(frame);
    cluster.rayfarm_ok(&args);
    assert!(png.exists(), "{} was not written", png.display());
    json
}

/// Starts `rayfarm args` with `env`, and a channel of its stderr lines.
pub fn spawn_rayfarm(args: &[&str], env: &[(&str, &str)]) -> (Child, mpsc::Receiver<String>) {
    let mut child = Command::new(bin("rayfarm"))
        .args(args)
        .envs(env.iter().copied())
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start rayfarm");
    let stderr = child.stderr.take().expect("piped stderr");
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    (child, rx)
}

/// Waits for a stderr line containing `what`; panics with what was seen.
pub fn wait_line(lines: &mpsc::Receiver<String>, what: &str) {
    let deadline = std::time::Instant::now() + START_TIMEOUT;
    let mut seen = Vec::new();
    while let Some(left) = deadline.checked_duration_since(std::time::Instant::now()) {
        match lines.recv_timeout(left) {
            Ok(line) if line.contains(what) => return,
            Ok(line) => seen.push(line),
            Err(_) => break,
        }
    }
    panic!("no line with {what:?}; stderr so far:\n{}", seen.join("\n"));
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

/// Sizes of a scene's domain files: (total, largest).
pub fn domain_bytes(scene: &Path) -> (u64, u64) {
    let sizes: Vec<u64> = std::fs::read_dir(scene)
        .expect("scene dir")
        .filter_map(Result::ok)
        .filter(|e| e.file_name() != "scene.toml")
        .map(|e| e.metadata().expect("metadata").len())
        .collect();
    (sizes.iter().sum(), sizes.iter().copied().max().unwrap_or(0))
}

/// `rayfarm jobs --json`, by job id.
pub fn jobs(cluster: &Cluster) -> Vec<serde_json::Value> {
    let out = cluster.rayfarm_ok(&["jobs", "--json"]);
    serde_json::from_slice(&out.stdout).expect("jobs --json parses")
}

/// The job `id` among `jobs`.
pub fn job<'a>(jobs: &'a [serde_json::Value], id: &str) -> &'a serde_json::Value {
    jobs.iter()
        .find(|j| j["job_id"] == id)
        .unwrap_or_else(|| panic!("job {id} not listed in {jobs:?}"))
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

/// A plain HTTP/1.1 request to `addr` (host:port): the status code and the body. Panics if
/// the server cannot be reached or does not answer within `START_TIMEOUT`.
pub fn http_request(
    addr: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &str,
) -> (u16, String) {
    try_http_request(addr, method, path, headers, body)
        .unwrap_or_else(|e| panic!("{method} {path} from {addr}: {e}"))
}

/// [`http_request`], with an error for a server that cannot be reached or answers badly.
pub fn try_http_request(
    addr: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &str,
) -> Result<(u16, String), String> {
    use std::io::Write;
    let mut stream = std::net::TcpStream::connect(addr).map_err(|e| format!("connect: {e}"))?;
    stream
        .set_read_timeout(Some(START_TIMEOUT))
        .map_err(|e| e.to_string())?;
    let mut request = format!(
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\nContent-Length: {}\r\n",
        body.len()
    );
    for (k, v) in headers {
        request.push_str(&format!("{k}: {v}\r\n"));
    }
    request.push_str("\r\n");
    request.push_str(body);
    stream
        .write_all(request.as_bytes())
        .map_err(|e| format!("send: {e}"))?;
    read_answer(stream)
}

/// An HTTP/1.1 answer's status and body: the body read to its Content-Length when the answer
/// gives one (some servers, chromedriver among them, keep the connection open whatever the
/// request asks), else to the end of the stream.
fn read_answer(stream: std::net::TcpStream) -> Result<(u16, String), String> {
    use std::io::{BufRead, Read};
    let mut reader = std::io::BufReader::new(stream);
    let mut status_line = String::new();
    reader
        .read_line(&mut status_line)
        .map_err(|e| format!("read: {e}"))?;
    let status = status_line
        .split(' ')
        .nth(1)
        .and_then(|c| c.parse().ok())
        .ok_or_else(|| format!("no status in {status_line:?}"))?;
    let mut length = None;
    loop {
        let mut line = String::new();
        let read = reader
            .read_line(&mut line)
            .map_err(|e| format!("read: {e}"))?;
        let line = line.trim_end();
        if read == 0 || line.is_empty() {
            break;
        }
        if let Some((k, v)) = line.split_once(':')
            && k.eq_ignore_ascii_case("content-length")
        {
            length = Some(v.trim().parse().map_err(|_| format!("bad length {v:?}"))?);
        }
    }
    let mut body = Vec::new();
    match length {
        Some(n) => {
            body.resize(n, 0);
            reader
                .read_exact(&mut body)
                .map_err(|e| format!("read body: {e}"))?;
        }
        None => {
            reader
                .read_to_end(&mut body)
                .map_err(|e| format!("read body: {e}"))?;
        }
    }
    Ok((status, String::from_utf8_lossy(&body).into_owned()))
}

/// `GET path` from `addr`; panics unless the answer is 200.
pub fn http_get(addr: &str, path: &str) -> String {
    let (status, body) = http_request(addr, "GET", path, &[], "");
    assert_eq!(status, 200, "GET {path} from {addr}: {body}");
    body
}
