//! A soak: a stream of jobs while a chaos loop kills and restarts workers and the coordinator,
//! freezes workers and cuts links at random. Every job submitted must finish with the image of
//! `render --local`, none may be lost or fail, and memory must not grow with the jobs: the
//! coordinator is killed only in the first 40% of the chaos (workers, links and freezes all
//! along), and over the second half the heap in use (the allocator's live bytes, from each
//! process's `/metrics`) of the coordinator and of worker 0 (never killed) must grow by less
//! than 10% (a worker 25% and 2 MiB in soaks under half an hour: see
//! [`WORKER_SLACK_SHORT`]; the coordinator 10% and its store's page cache: see
//! [`STORE_CACHE_BYTES`]). In soaks of half an hour or more their heap as the system sees it
//! (RssAnon) must too: the pages the allocator holds around its objects settle only over many
//! hundreds of jobs.
//!
//! Memory is read at quiet points: every [`QUIET_EVERY`] jobs the stream pauses until no job is
//! queued or running and no fault is in force, then one more job runs, so what a process holds
//! then is what it keeps between jobs, not a running frame's queues (read while the next job
//! ran, a worker's heap swung 10-57 MiB from job to job, and the least of a window of such
//! reads moved by a third between runs). Each measure is compared by its floor, the least of
//! the quiet points in a window: the last window against the one from halfway. The first quiet
//! point is reported beside them: the first jobs warm up caches (the job store's page cache,
//! the allocator's arenas) that a process keeps from then on.
//!
//! CI runs the short mode (`SOAK_SECS`, two and a half minutes of chaos). The long mode is a
//! benchmark: `RAYFARM_SOAK_SECS=3600 cargo test --release -p rayfarm-tests --test soak --
//! --nocapture` (README has its figures). `RAYFARM_SOAK_SEED` picks another sequence of faults;
//! the seed is printed, so a failing run can be replayed.
//!
//! Processes run on test hosts of their own (network namespaces) so links can be cut; where
//! namespaces cannot be made the soak runs on loopback without link cuts, saying so.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use rayfarm_core::sampling::mix64;
use rayfarm_tests::hosts::Net;
use rayfarm_tests::{
    Cluster, ClusterOpts, WorkerOpts, domain_bytes, hash_of, jobs, local_hash, prepare_nbody,
    proc_status_bytes, s,
};

/// Seconds of chaos in CI.
const SOAK_SECS: u64 = 150;

/// Workers kept running; a killed one is replaced at once.
const WORKERS: usize = 3;

/// Jobs queued or running at once.
const IN_FLIGHT: usize = 2;

/// How long a job may take once the chaos has stopped (faults cost time, never the image).
const DRAIN_TIMEOUT: Duration = Duration::from_secs(300);

/// Frames of the stream, each rendered under every schedule in turn.
const FRAMES: [[&str; 8]; 2] = [
    [
        "--width", "96", "--height", "72", "--spp", "4", "--depth", "3",
    ],
    [
        "--width", "64", "--height", "64", "--spp", "8", "--depth", "2",
    ],
];

const SCHEDULES: [&str; 5] = ["dynamic", "image-plane", "domain", "hybrid", "predictive"];

/// Growth of a process's heap allowed over the second half of the soak.
const MEMORY_SLACK: f64 = 0.10;

/// The coordinator's job store's page cache (`coordinator/src/store.rs`): it fills as the
/// store is read and written after the coordinator's last restart, over a thousand jobs or
/// more, and then stays. In a half-hour soak the coordinator's heap floor rose 5.5 -> 6.2 MiB
/// over the second half, leveling off at 6.5-6.7 MiB for the last thousand jobs; it is
/// allowed on top of [`MEMORY_SLACK`].
const STORE_CACHE_BYTES: u64 = 1 << 20;

/// The allowance for a worker's heap in use in a soak shorter than [`WARM_SECS`], with
/// [`WORKER_BYTES_SHORT`]: a worker's live objects between jobs swing: 3.0-4.4 MiB at the quiet
/// points of one 150 s soak with no trend over 377 jobs; under seed 7 the floor rose 3.15 ->
/// 4.82 and 3.05 -> 3.89 MiB over the second half in two runs and held (3.26 -> 3.21) in a
/// third. What swings: heaptrack attached to worker 0 over the second half of seed 7 found,
/// of what was still held at the end, 0.8 MiB in the decode buffers of 11 inbound peer streams
/// and 0.7 MiB in the encode buffers of outbound ones (tonic keeps each stream's buffer at the
/// largest bundle it carried, up to the bundler's 256 KiB migrated and 1 MiB tasks bundles),
/// (and 1.2 MiB in decoded verdicts and pass outputs, which a frame holds while it runs: the
/// worker was killed as the last job ended, so this run does not show whether they outlive a
/// frame; the quiet points say they do not grow). Streams come and go with replaced workers
/// (a dead peer's connection is closed by the keepalive within 30 s), so the sum moves by a
/// MiB or two from one quiet point to the next, bounded by peers x bundle size. A leak of the
/// coordinator's old kind (17 KiB a job, over 4 MiB in a short soak's second half) would
/// still show, and the long soak checks 10%. Its RssAnon is not checked in short soaks: at
/// the quiet points of three 150 s soaks it went 11.3 -> 12.9 MiB, 11.6 -> 14.2 and 12.8 ->
/// 16.0 over the second half while its heap in use went 3.56 -> 2.97 MiB in the last: pages
/// the allocator holds, not objects kept.
const WORKER_SLACK_SHORT: f64 = 0.25;

/// See [`WORKER_SLACK_SHORT`].
const WORKER_BYTES_SHORT: u64 = 2 << 20;

/// Soaks at least this long check workers at [`MEMORY_SLACK`].
const WARM_SECS: u64 = 1800;

/// Jobs between quiet points, where the stream pauses and memory is read.
const QUIET_EVERY: u32 = 20;

/// Reads of a process's memory at a quiet point, [`QUIET_READ_GAP`] apart; the least counts. A
/// worker gives its free memory back to the system on a thread of its own after a frame
/// ends, which may still be running when the job is seen to have succeeded.
const QUIET_READS: u32 = 5;

/// See [`QUIET_READS`].
const QUIET_READ_GAP: Duration = Duration::from_millis(100);

/// SplitMix64: the chaos loop's faults from a seed.
struct Rng(u64);

impl Rng {
    fn below(&mut self, n: u64) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix64(self.0) % n
    }

    fn millis(&mut self, from: u64, to: u64) -> Duration {
        Duration::from_millis(from + self.below(to - from))
    }
}

/// A job of the stream: its id, the hash it must end with, and what it is.
struct Job {
    id: String,
    expected: String,
    what: String,
}

/// What the chaos loop did, for the report.
#[derive(Default, Debug)]
struct Faults {
    workers_killed: u32,
    coordinator_killed: u32,
    workers_frozen: u32,
    links_cut: u32,
}

/// A fault to undo later.
enum Pending {
    /// Worker `i` is frozen (SIGSTOP) until then.
    Frozen(usize),
    /// A worker is cut off from every other host until then.
    Cut,
}

/// A process's memory at a quiet point, bytes: the least of [`QUIET_READS`] reads of each.
#[derive(Clone, Copy, Debug)]
struct Memory {
    /// What the allocator has handed out and not had back (`rayfarm_heap_in_use_bytes`): the
    /// objects the process keeps, whatever pages they sit on.
    in_use: u64,
    /// Its heap as the system sees it (RssAnon): those objects, the pages the allocator holds
    /// around them, and thread stacks.
    anon: u64,
    /// Resident memory (VmRSS), mapped files included.
    resident: u64,
}

impl Memory {
    fn read(pid: u32, in_use: impl Fn() -> u64) -> Memory {
        let once = || Memory {
            in_use: in_use(),
            anon: proc_status_bytes(pid, "RssAnon:"),
            resident: proc_status_bytes(pid, "VmRSS:"),
        };
        let mut least = once();
        for _ in 1..QUIET_READS {
            std::thread::sleep(QUIET_READ_GAP);
            let m = once();
            least = Memory {
                in_use: least.in_use.min(m.in_use),
                anon: least.anon.min(m.anon),
                resident: least.resident.min(m.resident),
            };
        }
        least
    }

    fn line(&self) -> String {
        let mib = |b: u64| b as f64 / 1048576.0;
        format!(
            "heap in use {:.1} MiB, RssAnon {:.1}, VmRSS {:.1}",
            mib(self.in_use),
            mib(self.anon),
            mib(self.resident)
        )
    }
}

#[test]
fn jobs_stream_through_chaos_none_lost_every_image_the_local_one() {
    let secs: u64 = std::env::var("RAYFARM_SOAK_SECS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(SOAK_SECS);
    let seed: u64 = std::env::var("RAYFARM_SOAK_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1);
    eprintln!("soak: {secs} s of chaos, seed {seed} (RAYFARM_SOAK_SECS, RAYFARM_SOAK_SEED)");
    let mut rng = Rng(seed);

    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 20_000, 8);
    let (_, largest) = domain_bytes(&scene);
    let expected: Vec<String> = FRAMES.iter().map(|f| local_hash(&scene, f)).collect();

    let net = match Net::new() {
        Ok(net) => Some(net),
        Err(why) => {
            eprintln!("SKIPPED link cuts in the soak: network namespaces cannot be made: {why}");
            None
        }
    };
    // `/metrics` on each process's own loopback tells its heap in use.
    let worker = WorkerOpts::cache(2 * largest)
        .arg("--peer-ack-timeout-ms", "1500")
        .arg("--http", "127.0.0.1:0");
    let opts = ClusterOpts {
        // Crashes here are the chaos loop's, not the job's: never fail a job for them.
        coordinator_args: [
            "--heartbeat-ms",
            "200",
            "--worker-timeout-ms",
            "2000",
            "--max-attempts",
            "1000",
            "--http",
            "127.0.0.1:0",
        ]
        .map(String::from)
        .to_vec(),
        ..ClusterOpts::default()
    };
    let workers = vec![worker.clone(); WORKERS];
    let mut cluster = match net {
        Some(net) => Cluster::start_on_hosts(net, root.path(), Some("nb"), &opts, &workers),
        None => Cluster::start_with(root.path(), Some("nb"), &opts, &workers),
    };
    let on_hosts = cluster.has_hosts();

    // Worker 0 is never killed (only frozen and cut off), so one worker lives through it all.
    let mut alive: Vec<usize> = (0..WORKERS).collect();
    let mut queue: VecDeque<Job> = VecDeque::new();
    let mut pending: Vec<(Instant, Pending)> = Vec::new();
    let mut faults = Faults::default();
    let mut finished = 0u32;
    let mut submitted = 0u32;
    // At each quiet point: (jobs finished, the coordinator's pid, its memory, worker 0's).
    let mut samples: Vec<Sample> = Vec::new();
    // Jobs finished by which the stream pauses for the next quiet point, and how far it is.
    let mut quiet_at = 1;
    let mut quiet = Quiet::Streaming;

    let start = Instant::now();
    let chaos_until = start + Duration::from_secs(secs);
    let mut next_fault = start + rng.millis(2000, 6000);
    let mut drain_until = None;
    loop {
        let now = Instant::now();
        let chaos = now < chaos_until;
        if !chaos && drain_until.is_none() {
            // Undo every fault still in force; from here on the jobs in flight must finish.
            for (_, fault) in pending.drain(..) {
                undo(&cluster, fault);
            }
            drain_until = Some(now + DRAIN_TIMEOUT);
        }

        // Keep the stream full while the chaos lasts, except at a quiet point.
        if quiet == Quiet::Streaming && finished >= quiet_at {
            quiet = Quiet::Pausing;
        }
        if quiet == Quiet::Pausing && queue.is_empty() && pending.is_empty() {
            // Every worker back, then one job with no fault in force: a worker frozen or cut
            // off in the last job still held that frame, and gives its memory back only when
            // a frame of its own ends.
            cluster.wait_for_workers(WORKERS, DRAIN_TIMEOUT);
            quiet = Quiet::Settling;
            queue.push_back(submit(&cluster, submitted, &expected));
            submitted += 1;
        }
        while chaos && quiet == Quiet::Streaming && queue.len() < IN_FLIGHT {
            queue.push_back(submit(&cluster, submitted, &expected));
            submitted += 1;
        }

        // Jobs that ended: each must have succeeded with the local image.
        let listed = jobs(&cluster);
        while let Some(job) = queue.front() {
            let state = listed
                .iter()
                .find(|j| j["job_id"] == job.id.as_str())
                .map(|j| {
                    (
                        j["state"].as_str().unwrap_or("").to_string(),
                        j["error"].clone(),
                    )
                })
                .unwrap_or_else(|| panic!("job {} ({}) is lost: not listed", job.id, job.what));
            match state.0.as_str() {
                "succeeded" => {}
                "queued" | "running" => break,
                other => panic!("job {} ({}) ended {other}: {}", job.id, job.what, state.1),
            }
            let job = queue.pop_front().expect("front job");
            let stats = cluster.dir().join(format!("{}.json", job.id));
            let png = cluster.dir().join(format!("{}.png", job.id));
            cluster.rayfarm_ok(&["fetch", &job.id, "-o", s(&png), "--stats-json", s(&stats)]);
            assert_eq!(
                hash_of(&stats),
                job.expected,
                "job {} ({}) is not the local image",
                job.id,
                job.what
            );
            let _ = std::fs::remove_file(&png);
            finished += 1;
        }
        if quiet == Quiet::Settling && queue.is_empty() {
            let sample = quiet_sample(&cluster, finished, start.elapsed());
            if samples.len().is_multiple_of(5) {
                eprintln!("{}", sample.line());
            }
            samples.push(sample);
            quiet_at = finished + QUIET_EVERY;
            quiet = Quiet::Streaming;
        }
        if let Some(until) = drain_until {
            if queue.is_empty() {
                break;
            }
            assert!(
                now < until,
                "jobs still unfinished {DRAIN_TIMEOUT:?} after the chaos stopped: {:?}",
                queue.iter().map(|j| &j.id).collect::<Vec<_>>()
            );
        }

        // Faults whose time is up are undone.
        let (due, later): (Vec<_>, Vec<_>) = pending.drain(..).partition(|(t, _)| *t <= now);
        pending = later;
        for (_, fault) in due {
            undo(&cluster, fault);
        }

        if chaos && quiet == Quiet::Streaming && now >= next_fault && pending.is_empty() {
            next_fault = now + rng.millis(2000, 6000);
            let kinds = if on_hosts { 4 } else { 3 };
            match rng.below(kinds) {
                0 => {
                    // A worker crashes and a replacement joins (worker 0 is spared).
                    let victims: Vec<usize> = alive.iter().copied().filter(|&w| w != 0).collect();
                    let victim = victims[rng.below(victims.len() as u64) as usize];
                    cluster.kill_worker(victim);
                    alive.retain(|&w| w != victim);
                    alive.push(cluster.add_worker(&worker));
                    faults.workers_killed += 1;
                }
                // The coordinator only in the first 40%: its last life spans the second half
                // and has warmed up by then.
                1 if now < start + Duration::from_secs(secs * 2 / 5) => {
                    cluster.kill_coordinator();
                    cluster.restart_coordinator();
                    faults.coordinator_killed += 1;
                }
                1 | 2 => {
                    let i = alive[rng.below(alive.len() as u64) as usize];
                    cluster.pause_worker(i);
                    pending.push((now + rng.millis(500, 4000), Pending::Frozen(i)));
                    faults.workers_frozen += 1;
                }
                _ => {
                    let i = alive[rng.below(alive.len() as u64) as usize];
                    let others = peers_and_coordinator(&cluster, &alive, i);
                    cluster.net().isolate(cluster.worker_host(i), &others);
                    pending.push((now + rng.millis(500, 4000), Pending::Cut));
                    faults.links_cut += 1;
                }
            }
        }
        std::thread::sleep(Duration::from_millis(100));
    }

    // After the last job, with every fault undone: memory over the second half, the floor of
    // the last window of quiet points against the floor of the window from halfway; the first
    // point for the record.
    assert!(finished >= 20, "only {finished} jobs finished");
    let n = samples.len();
    assert!(n >= 8, "only {n} quiet points");
    let width = (n / 8).max(2);
    let (middle, end) = (&samples[n / 2..n / 2 + width], &samples[n - width..]);
    let floor = |window: &[Sample], of: fn(&Sample) -> u64| {
        window.iter().map(of).min().expect("a window holds samples")
    };
    let peak = |window: &[Sample], of: fn(&Sample) -> u64| {
        window.iter().map(of).max().expect("a window holds samples")
    };
    let mib = |b: u64| b as f64 / 1048576.0;
    let window = |w: &[Sample], of: fn(&Sample) -> u64| {
        format!(
            "after jobs {}..{}: {:.2} MiB ({:.2})",
            w[0].finished,
            w[w.len() - 1].finished,
            mib(floor(w, of)),
            mib(peak(w, of))
        )
    };
    let measures: [(&str, Measure); 4] = [
        ("coordinator heap in use", |s| s.coordinator_memory.in_use),
        ("coordinator RssAnon", |s| s.coordinator_memory.anon),
        ("worker 0 heap in use", |s| s.worker0.in_use),
        ("worker 0 RssAnon", |s| s.worker0.anon),
    ];
    let mut report = format!(
        "soak of {secs} s (seed {seed}): {finished} jobs finished, none lost, every image the \
         local one; {faults:?}; {} s in all\n  first:   {}\n  halfway: {}\n  last:    {}\n  \
         floors (peaks) at quiet points:",
        start.elapsed().as_secs(),
        samples[0].line(),
        samples[n / 2].line(),
        samples[n - 1].line(),
    );
    for (name, of) in measures {
        report += &format!(
            "\n    {name}: {} -> {}",
            window(middle, of),
            window(end, of)
        );
    }
    eprintln!("{report}");
    assert!(
        samples[n / 2..]
            .iter()
            .all(|s| s.coordinator == samples[n - 1].coordinator),
        "the coordinator was restarted in the second half: {report}"
    );
    let grew = |of: fn(&Sample) -> u64, slack: f64, cache: u64| {
        floor(end, of) as f64 > floor(middle, of) as f64 * (1.0 + slack) + cache as f64
    };
    let long = secs >= WARM_SECS;
    let (worker_slack, worker_bytes) = if long {
        (MEMORY_SLACK, 0)
    } else {
        (WORKER_SLACK_SHORT, WORKER_BYTES_SHORT)
    };
    assert!(
        !grew(measures[2].1, worker_slack, worker_bytes),
        "worker 0's heap in use grew by {:.0}% and {} MiB or more over the second half: {report}",
        worker_slack * 100.0,
        worker_bytes >> 20
    );
    assert!(
        !grew(measures[0].1, MEMORY_SLACK, STORE_CACHE_BYTES),
        "the coordinator's heap in use grew by 10% and its job store's page cache or more over \
         the second half: {report}"
    );
    // Pages the allocator holds around its objects settle only over a long soak.
    if long {
        assert!(
            !grew(measures[3].1, MEMORY_SLACK, 0),
            "worker 0's RssAnon grew by 10% or more over the second half: {report}"
        );
        assert!(
            !grew(measures[1].1, MEMORY_SLACK, STORE_CACHE_BYTES),
            "the coordinator's RssAnon grew by 10% and its job store's page cache or more over \
             the second half: {report}"
        );
    }
}

/// One figure of a quiet point.
type Measure = fn(&Sample) -> u64;

/// Where the stream is on its way to the next quiet point.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Quiet {
    /// Jobs stream in and faults happen.
    Streaming,
    /// Neither: the jobs in flight finish and the faults in force are undone.
    Pausing,
    /// One job runs with no fault in force; when it has finished, memory is read.
    Settling,
}

/// Submits the stream's job number `n`: the frames in turn, each under every schedule.
fn submit(cluster: &Cluster, n: u32, expected: &[String]) -> Job {
    let frame = n as usize % FRAMES.len();
    let schedule = SCHEDULES[(n as usize / FRAMES.len()) % SCHEDULES.len()];
    let mut args = vec!["submit", "--quiet", "--schedule", schedule];
    args.extend(FRAMES[frame]);
    let out = cluster.rayfarm_ok(&args);
    let id = String::from_utf8_lossy(&out.stdout).trim().to_string();
    assert!(!id.is_empty(), "submit printed no job id");
    Job {
        id,
        expected: expected[frame].clone(),
        what: format!("frame {frame} under {schedule}"),
    }
}

/// The memory of the long-lived processes at a quiet point.
fn quiet_sample(cluster: &Cluster, finished: u32, at: Duration) -> Sample {
    let coordinator = cluster.coordinator_pid();
    Sample {
        finished,
        at,
        coordinator,
        coordinator_memory: Memory::read(coordinator, || cluster.coordinator_heap_in_use()),
        worker0: Memory::read(cluster.worker_pid(0), || cluster.worker_heap_in_use(0)),
    }
}

/// The memory of the long-lived processes at a quiet point.
struct Sample {
    finished: u32,
    /// When, from the start of the soak.
    at: Duration,
    coordinator: u32,
    coordinator_memory: Memory,
    worker0: Memory,
}

impl Sample {
    fn line(&self) -> String {
        format!(
            "after {} jobs, {} s: coordinator {}; worker 0 {}",
            self.finished,
            self.at.as_secs(),
            self.coordinator_memory.line(),
            self.worker0.line(),
        )
    }
}

/// Worker `i`'s peers among `alive` and the coordinator's host, on test hosts.
fn peers_and_coordinator<'a>(
    cluster: &'a Cluster,
    alive: &[usize],
    i: usize,
) -> Vec<&'a rayfarm_tests::hosts::Host> {
    let mut hosts: Vec<_> = alive
        .iter()
        .filter(|&&w| w != i)
        .map(|&w| cluster.worker_host(w))
        .collect();
    hosts.push(cluster.coordinator_host());
    hosts
}

/// Undoes a fault (one is in force at a time, so a cut is undone by healing every link).
fn undo(cluster: &Cluster, fault: Pending) {
    match fault {
        Pending::Frozen(i) => cluster.resume_worker(i),
        Pending::Cut => cluster.net().heal_all(),
    }
}
