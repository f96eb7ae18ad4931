//! A real cluster of `rayfarm-coordinator` and `rayfarm-worker` processes, how it is started,
//! what a test does to it (add, pause, kill and restart processes, run `rayfarm` against it),
//! and the jobs it ran.

use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus, Output};
use std::time::{Duration, Instant};

use crate::cli::bin;
use crate::hosts::{Host, Net};
use crate::http::http_get;
use crate::process::{
    LOG_TAIL_LINES, Proc, START_TIMEOUT, command_on, listen_args, log_tail, signal_pid,
};
use crate::s;

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

    /// The allocator's bytes in use in the coordinator (`rayfarm_heap_in_use_bytes` of its
    /// `/metrics`), when it was started with `--http` on its loopback.
    pub fn coordinator_heap_in_use(&self) -> u64 {
        let addr = self
            .coordinator_http()
            .expect("the coordinator serves --http");
        let host = self.net.as_ref().map(|_| self.coordinator_host());
        heap_in_use(host, addr)
    }

    /// The same for worker `i`.
    pub fn worker_heap_in_use(&self, i: usize) -> u64 {
        let addr = self.worker_http(i).expect("the worker serves --http");
        let host = self.net.as_ref().map(|_| self.worker_host(i));
        heap_in_use(host, addr)
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

/// `rayfarm_heap_in_use_bytes` from the `/metrics` at `addr`, on `host`'s network if given.
fn heap_in_use(host: Option<&Host>, addr: &str) -> u64 {
    let get = || http_get(addr, "/metrics");
    let metrics = match host {
        Some(host) => host.within(get),
        None => get(),
    };
    metrics
        .lines()
        .find_map(|l| l.strip_prefix("rayfarm_heap_in_use_bytes "))
        .and_then(|v| v.trim().parse::<f64>().ok())
        .unwrap_or_else(|| panic!("no rayfarm_heap_in_use_bytes at {addr}: {metrics}")) as u64
}
