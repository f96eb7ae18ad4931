//! Slurm for real: a one-node Slurm cluster on this machine (`munged`, `slurmctld` and `slurmd`
//! from Debian's `slurm-wlm` and `munge`, with a generated configuration in a temporary
//! directory and ports of their own), `deploy/slurm/rayfarm.sbatch` submitted through
//! `sbatch --wait`, and its image compared with `render --local`.
//!
//! Skipped, with a `SKIPPED` line, where Slurm or munge is not installed or the test is not
//! root (slurmd must be); `.ci/run` installs both.

use std::fs;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use rayfarm_tests::{bin, fixed_port, hash_of, local_hash, prepare_nbody, s, wait_until};

/// The frame the batch job renders.
const FRAME: [&str; 8] = [
    "--width", "96", "--height", "72", "--spp", "2", "--depth", "3",
];

/// How long the daemons may take to come up, and the batch job to run.
const SLURM_TIMEOUT: Duration = Duration::from_secs(120);

/// Where a program is, on PATH or in the system directories daemons live in.
fn find(program: &str) -> Option<PathBuf> {
    let path = std::env::var("PATH").unwrap_or_default();
    path.split(':')
        .chain(["/usr/sbin", "/sbin"])
        .map(|dir| Path::new(dir).join(program))
        .find(|p| p.is_file())
}

/// This machine's short host name, as Slurm names the node.
fn short_hostname() -> String {
    let out = Command::new("hostname")
        .arg("-s")
        .output()
        .expect("hostname");
    String::from_utf8_lossy(&out.stdout).trim().to_string()
}

/// A one-node Slurm cluster. Dropping it cancels its jobs, waits for them to end (their
/// steps are no children of ours), and kills the daemons.
struct Slurm {
    dir: tempfile::TempDir,
    conf: PathBuf,
    daemons: Vec<(&'static str, Child)>,
}

impl Slurm {
    /// Starts munged, slurmctld and slurmd, each in the foreground as our child, and waits
    /// until the node is idle.
    fn start(tools: &Tools) -> Slurm {
        let dir = tempfile::tempdir().expect("temp dir");
        let d = dir.path();
        for sub in ["run", "state", "spool"] {
            fs::create_dir_all(d.join(sub)).expect("slurm dirs");
        }
        let mut slurm = Slurm {
            conf: d.join("slurm.conf"),
            dir,
            daemons: Vec::new(),
        };
        let d = slurm.dir.path().to_path_buf();
        // A key of our own: this cluster trusts nothing else on the machine.
        let key = d.join("munge.key");
        let mut bytes = vec![0u8; 1024];
        let mut random = fs::File::open("/dev/urandom").expect("open /dev/urandom");
        std::io::Read::read_exact(&mut random, &mut bytes).expect("read /dev/urandom");
        fs::write(&key, bytes).expect("write munge key");
        fs::set_permissions(&key, fs::Permissions::from_mode(0o600)).expect("key mode");
        let socket = d.join("run/munge.sock");
        slurm.spawn(
            "munged",
            Command::new(&tools.munged).args([
                "--foreground",
                "--force",
                &format!("--socket={}", s(&socket)),
                &format!("--key-file={}", s(&key)),
                &format!("--pid-file={}", s(&d.join("run/munged.pid"))),
                &format!("--log-file={}", s(&d.join("munged.log"))),
                &format!("--seed-file={}", s(&d.join("munge.seed"))),
            ]),
        );
        wait_until("munged's socket", SLURM_TIMEOUT, || socket.exists());
        let host = short_hostname();
        let conf = format!(
            "ClusterName=rayfarmtest\n\
             SlurmctldHost={host}(127.0.0.1)\n\
             SlurmctldPort={ctld}\n\
             SlurmdPort={slurmd}\n\
             SlurmUser=root\n\
             SlurmdUser=root\n\
             AuthType=auth/munge\n\
             AuthInfo=socket={socket}\n\
             CredType=cred/munge\n\
             StateSaveLocation={d}/state\n\
             SlurmdSpoolDir={d}/spool\n\
             SlurmctldPidFile={d}/run/slurmctld.pid\n\
             SlurmdPidFile={d}/run/slurmd.pid\n\
             SlurmctldLogFile={d}/slurmctld.log\n\
             SlurmdLogFile={d}/slurmd.log\n\
             ProctrackType=proctrack/linuxproc\n\
             TaskPlugin=task/none\n\
             SchedulerType=sched/builtin\n\
             SelectType=select/cons_tres\n\
             SelectTypeParameters=CR_Core\n\
             MpiDefault=none\n\
             ReturnToService=2\n\
             JobAcctGatherType=jobacct_gather/none\n\
             AccountingStorageType=accounting_storage/none\n\
             JobCompType=jobcomp/none\n\
             SwitchType=switch/none\n\
             NodeName={host} NodeAddr=127.0.0.1 CPUs={cpus} State=UNKNOWN\n\
             PartitionName=rayfarm Nodes=ALL Default=YES MaxTime=INFINITE State=UP\n",
            ctld = fixed_port(),
            slurmd = fixed_port(),
            socket = s(&socket),
            d = s(&d),
            cpus = std::thread::available_parallelism().map_or(1, |n| n.get()),
        );
        fs::write(&slurm.conf, conf).expect("write slurm.conf");
        let conf = s(&slurm.conf).to_string();
        slurm.spawn(
            "slurmctld",
            Command::new(&tools.slurmctld).args(["-D", "-f", &conf]),
        );
        slurm.spawn(
            "slurmd",
            Command::new(&tools.slurmd).args(["-D", "-f", &conf]),
        );
        wait_until("the Slurm node to be idle", SLURM_TIMEOUT, || {
            let out = slurm.client("sinfo").args(["-h", "-o", "%t"]).output();
            out.is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "idle")
        });
        slurm
    }

    fn spawn(&mut self, name: &'static str, cmd: &mut Command) {
        let log = fs::File::create(self.dir.path().join(format!("{name}.out"))).expect("log");
        let child = cmd
            .env("SLURM_CONF", &self.conf)
            .stdin(Stdio::null())
            .stdout(log.try_clone().expect("log"))
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| panic!("start {name}: {e}"));
        self.daemons.push((name, child));
    }

    /// A Slurm client command (`sbatch`, `sinfo`, ...) for this cluster.
    fn client(&self, program: &str) -> Command {
        let mut cmd = Command::new(program);
        cmd.env("SLURM_CONF", &self.conf);
        cmd
    }

    /// The end of every daemon's log, for a failing test.
    fn dump_logs(&self) {
        for name in ["munged.log", "slurmctld.log", "slurmd.log"] {
            let text = fs::read_to_string(self.dir.path().join(name)).unwrap_or_default();
            let lines: Vec<&str> = text.lines().collect();
            let tail = lines[lines.len().saturating_sub(30)..].join("\n    ");
            eprintln!("---- {name}:\n    {tail}");
        }
    }
}

impl Drop for Slurm {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.dump_logs();
        }
        let _ = self
            .client("scancel")
            .arg("--full")
            .arg("--user=root")
            .output();
        let start = Instant::now();
        while start.elapsed() < Duration::from_secs(30) {
            let out = self.client("squeue").args(["-h", "-o", "%i"]).output();
            if out.is_ok_and(|o| o.status.success() && o.stdout.is_empty()) {
                break;
            }
            std::thread::sleep(Duration::from_millis(200));
        }
        for (_, child) in self.daemons.iter_mut().rev() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// The Slurm and munge programs the test needs.
struct Tools {
    munged: PathBuf,
    slurmctld: PathBuf,
    slurmd: PathBuf,
}

/// The tools, or why the test cannot run here.
fn tools() -> Result<Tools, String> {
    let need = |p: &str| find(p).ok_or_else(|| format!("{p} is not installed"));
    for client in ["sbatch", "sinfo", "squeue", "scancel", "srun", "scontrol"] {
        need(client)?;
    }
    let uid = Command::new("id")
        .arg("-u")
        .output()
        .map_err(|e| e.to_string())?;
    if String::from_utf8_lossy(&uid.stdout).trim() != "0" {
        return Err("slurmd must run as root".into());
    }
    Ok(Tools {
        munged: need("munged")?,
        slurmctld: need("slurmctld")?,
        slurmd: need("slurmd")?,
    })
}

#[test]
fn the_sbatch_script_renders_the_local_image() {
    let tools = match tools() {
        Ok(t) => t,
        Err(why) => {
            eprintln!("SKIPPED the_sbatch_script_renders_the_local_image: {why}");
            return;
        }
    };
    let slurm = Slurm::start(&tools);
    let work = slurm.dir.path().join("work");
    let scenes = work.join("scenes");
    fs::create_dir_all(&scenes).expect("scene dir");
    let scene = prepare_nbody(&scenes, "nb", 20_000, 4);
    let expected = local_hash(&scene, &FRAME);
    let png = work.join("frame.png");
    let stats = work.join("frame.json");
    let submit = format!(
        "--scene nb {} -o {} --stats-json {}",
        FRAME.join(" "),
        s(&png),
        s(&stats)
    );
    let bin_dir = bin("rayfarm").parent().expect("bin dir").to_path_buf();
    let script = rayfarm_tests::repo_root().join("deploy/slurm/rayfarm.sbatch");
    let log = work.join("rayfarm-%j.log");
    let started = Instant::now();
    // One node: the script's --nodes=4 is the example's, sbatch's option overrides it.
    let out = slurm
        .client("sbatch")
        .args(["--wait", "--nodes=1", &format!("--output={}", s(&log))])
        .arg(&script)
        .env("RAYFARM_BIN", &bin_dir)
        .env("RAYFARM_SCENE_ROOT", &scenes)
        .env("RAYFARM_DATA_DIR", work.join("data"))
        .env("RAYFARM_CACHE_BYTES", "256MiB")
        .env("RAYFARM_PORT", fixed_port().to_string())
        .env("RAYFARM_PEER_PORT", fixed_port().to_string())
        .env("RAYFARM_SUBMIT", &submit)
        .env("SLURM_CONF", &slurm.conf)
        .output()
        .expect("run sbatch");
    let job_log = fs::read_dir(&work)
        .expect("work dir")
        .filter_map(Result::ok)
        .find(|e| e.file_name().to_string_lossy().starts_with("rayfarm-"))
        .map(|e| fs::read_to_string(e.path()).unwrap_or_default())
        .unwrap_or_default();
    assert!(
        out.status.success(),
        "sbatch --wait failed ({}): {}\njob log:\n{job_log}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        started.elapsed() < SLURM_TIMEOUT,
        "the batch job took too long"
    );
    assert!(
        png.exists(),
        "the batch job wrote no image; its log:\n{job_log}"
    );
    assert_eq!(
        hash_of(&stats),
        expected,
        "the Slurm job's image is not the local one"
    );
    eprintln!(
        "Slurm batch job rendered the local image in {:?}",
        started.elapsed()
    );
}
