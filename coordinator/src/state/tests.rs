use rayfarm_core::prepare::generate::{NbodyOptions, prepare_nbody};

use super::*;
use rayfarm_node::proto::{PROTOCOL_VERSION, coordinator_message::Body};

fn config(root: &std::path::Path) -> Config {
    Config {
        data_dir: root.join("data"),
        scene_root: root.join("scenes"),
        allow_absolute_scenes: false,
        max_jobs_per_user: 64,
        max_pixel_samples_per_user: 1 << 40,
        default_scene: None,
        heartbeat: Duration::from_secs(1),
        worker_timeout: Duration::from_secs(10),
        report_timeout: Duration::from_secs(1),
        schedule_options: Options::default(),
        rounds: Rounds::default(),
        holders_interval: Duration::ZERO,
        report_hold: ReportHold::NONE,
        max_frame_bytes: 16 << 30,
        max_attempts: 3,
    }
}

/// Attaches a worker (its control stream is the channel) and returns the epochs of every
/// tile in the StartFrame it is sent, tile by tile.
fn start_epochs(c: &Arc<Coordinator>) -> BTreeMap<u32, u32> {
    start_epochs_of(c, "w").1
}

/// Registers a worker called `id` whose control stream is a channel: its key and the
/// channel's receiving end.
fn attach(
    c: &Arc<Coordinator>,
    id: &str,
) -> (
    u32,
    mpsc::UnboundedReceiver<Result<Arc<proto::CoordinatorMessage>, Status>>,
) {
    let (tx, rx) = mpsc::unbounded_channel();
    let register = proto::Register {
        protocol_version: PROTOCOL_VERSION,
        worker_id: id.into(),
        peer_address: format!("{id}:1"),
        cache_bytes: 1 << 30,
        threads: 1,
    };
    (c.register(&register, None, tx).expect("registered"), rx)
}

/// Lets go of the job database as a crashed process does (its lock dies with it): the
/// threads that prepare frames and release their messages may hold the coordinator a
/// moment longer than the test, so dropping it alone would not free the file at once.
/// The running job stays recorded as running, as after a crash.
fn let_go(c: Arc<Coordinator>) {
    c.shut_down();
}

/// [`start_epochs`] of a worker called `id`; also returns its key.
fn start_epochs_of(c: &Arc<Coordinator>, id: &str) -> (u32, BTreeMap<u32, u32>) {
    let (key, mut rx) = attach(c, id);
    let s = next_start(&mut rx);
    // Its channel stays open while the test runs, as a live worker's would.
    std::mem::forget(rx);
    (key, s.epochs.into_iter().collect())
}

/// The next StartFrame on a worker's channel. A frame starts once its scene is read off
/// the lock, and goes out once its start is on disk, from other threads: wait for it.
fn next_start(
    rx: &mut mpsc::UnboundedReceiver<Result<Arc<proto::CoordinatorMessage>, Status>>,
) -> proto::StartFrame {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_time()
        .build()
        .expect("runtime");
    let wait = Duration::from_secs(10);
    while let Ok(Some(msg)) = rt.block_on(async { tokio::time::timeout(wait, rx.recv()).await }) {
        if let Some(Body::StartFrame(s)) = Arc::unwrap_or_clone(msg.expect("no error")).body {
            return s;
        }
    }
    panic!("no StartFrame sent");
}

#[test]
fn a_worker_lost_three_times_on_one_job_fails_the_job_and_stays() {
    let root = tempfile::tempdir().unwrap();
    let spec = small_job(root.path());
    let c = Coordinator::open(config(root.path())).unwrap();
    let (_, mut stays) = attach(&c, "stays");
    let id = c.submit(Some(spec)).unwrap();
    next_start(&mut stays);
    for lost in 1..=3 {
        assert_eq!(
            c.list(JobPage::newest(100)).unwrap().0[0].state(),
            JobState::Running,
            "loss {lost}"
        );
        let (key, _rx) = attach(&c, "flaky");
        c.worker_gone(key, "stream closed");
    }
    let job = c
        .list(JobPage::newest(100))
        .unwrap()
        .0
        .into_iter()
        .find(|j| j.job_id == id)
        .unwrap();
    assert_eq!(job.state(), JobState::Failed);
    assert!(
        job.error.contains("worker flaky was lost 3 times")
            && job.error.contains("--max-attempts is 3"),
        "{}",
        job.error
    );
    assert_eq!(c.status().workers.len(), 1, "the other worker stays");
}

/// A scene `nb` under `root` and a small job of it.
fn small_job(root: &std::path::Path) -> proto::JobSpec {
    let options = NbodyOptions {
        name: "nb".into(),
        triangles: 2000,
        seed: 1,
        domains: 2,
        max_memory: None,
        force: false,
    };
    prepare_nbody(&root.join("scenes").join("nb"), &options).unwrap();
    std::fs::create_dir_all(root.join("data")).unwrap();
    proto::JobSpec {
        scene: "nb".into(),
        width: 64,
        height: 32,
        spp: 1,
        max_depth: 1,
        ..Default::default()
    }
}

#[test]
fn a_job_whose_workers_were_all_lost_restarts_above_every_epoch_it_used() {
    let root = tempfile::tempdir().unwrap();
    let spec = small_job(root.path());
    let c = Coordinator::open(config(root.path())).unwrap();
    c.submit(Some(spec)).unwrap();
    let (a, first) = start_epochs_of(&c, "a");
    assert!(first.is_empty(), "a first frame starts at epoch 0");
    let (b, _) = start_epochs_of(&c, "b");
    // Losing a bumps every tile to epoch 1; losing b too re-queues the job.
    c.worker_gone(a, "test");
    c.worker_gone(b, "test");
    assert_eq!(
        c.list(JobPage::newest(100)).unwrap().0[0].state(),
        JobState::Queued
    );
    // Worker b, dropped but still running, may send epoch-1 rays: the new frame is above.
    let (_, again) = start_epochs_of(&c, "c");
    assert!(
        !again.is_empty() && again.values().all(|&e| e >= 2),
        "{again:?}"
    );
}

#[test]
fn a_job_restarted_after_a_coordinator_restart_starts_its_tiles_at_a_new_epoch() {
    let root = tempfile::tempdir().unwrap();
    let spec = small_job(root.path());
    let c = Coordinator::open(config(root.path())).unwrap();
    let id = c.submit(Some(spec.clone())).unwrap();
    assert!(
        start_epochs(&c).is_empty(),
        "a first frame starts at epoch 0"
    );
    assert_eq!(
        c.list(JobPage::newest(100)).unwrap().0[0].state(),
        JobState::Running
    );
    let_go(c);
    for epoch in 1..=2 {
        // As after a crash: the running job is queued again, and its next frame's tiles
        // are all at an epoch the dead run never used.
        let c = Coordinator::open(config(root.path())).unwrap();
        let jobs = c.list(JobPage::newest(100)).unwrap().0;
        assert_eq!((jobs.len(), jobs[0].state()), (1, JobState::Queued));
        let epochs = start_epochs(&c);
        let tiles = epochs.len();
        assert!(tiles >= 2, "{epochs:?}");
        assert!(epochs.values().all(|&e| e == epoch), "{epochs:?}");
        assert_eq!(c.list(JobPage::newest(100)).unwrap().0[0].job_id, id);
        let_go(c);
    }
    // Sequence numbers go on where they stopped.
    let c = Coordinator::open(config(root.path())).unwrap();
    let next = c.submit(Some(spec)).unwrap();
    assert!(next.ends_with("-2"), "{next}");
}

#[test]
fn the_job_list_comes_in_pages_that_new_jobs_do_not_shift() {
    let root = tempfile::tempdir().unwrap();
    let spec = small_job(root.path());
    let c = Coordinator::open(config(root.path())).unwrap();
    let ids: Vec<String> = (0..5)
        .map(|_| c.submit(Some(spec.clone())).unwrap())
        .collect();
    let names = |jobs: &[proto::JobSummary]| -> Vec<String> {
        jobs.iter().map(|j| j.job_id.clone()).collect()
    };
    let (first, next) = c.list(JobPage::newest(2)).unwrap();
    assert_eq!(names(&first), [ids[4].clone(), ids[3].clone()]);
    // A job submitted between two pages is newer than both: the next page goes on.
    let newest = c.submit(Some(spec)).unwrap();
    let (second, next) = c
        .list(JobPage {
            size: 2,
            from_seq: next.expect("more pages"),
        })
        .unwrap();
    assert_eq!(names(&second), [ids[2].clone(), ids[1].clone()]);
    let (last, next) = c
        .list(JobPage {
            size: 2,
            from_seq: next.expect("more pages"),
        })
        .unwrap();
    assert_eq!((names(&last), next), (vec![ids[0].clone()], None));
    assert_eq!(c.list(JobPage::newest(1)).unwrap().0[0].job_id, newest);
    // The order survives a restart.
    drop(c);
    let c = Coordinator::open(config(root.path())).unwrap();
    let all = c.list(JobPage::newest(10)).unwrap().0;
    assert_eq!(all.len(), 6);
    assert_eq!(all[5].job_id, ids[0]);
}

#[test]
fn a_job_the_machine_has_forgotten_is_answered_from_the_store() {
    use rayfarm_machine::coordinator::cluster::KEPT_FINISHED_JOBS;
    let root = tempfile::tempdir().unwrap();
    let spec = small_job(root.path());
    let c = Coordinator::open(config(root.path())).unwrap();
    let cancelled: Vec<String> = (0..KEPT_FINISHED_JOBS + 3)
        .map(|_| {
            let id = c.submit(Some(spec.clone())).unwrap();
            assert_eq!(c.cancel(&id, None).unwrap(), JobState::Cancelled);
            id
        })
        .collect();
    // A frame's start is stored after the cancellations' records: the oldest are forgotten.
    let running = c.submit(Some(spec)).unwrap();
    start_epochs(&c);
    let oldest = &cancelled[0];
    assert!(c.lock().machine.job(oldest).is_none(), "still held");
    // Listed, in order, with the running job first.
    let listed = c.list(JobPage::newest(1000)).unwrap().0;
    assert_eq!(listed.len(), cancelled.len() + 1);
    assert_eq!(
        (listed[0].job_id.as_str(), listed[0].state()),
        (running.as_str(), JobState::Running)
    );
    let last = listed.last().unwrap();
    assert_eq!((&last.job_id, last.state()), (oldest, JobState::Cancelled));
    // Every call answers for it as for a held job.
    assert_eq!(c.cancel(oldest, None).unwrap(), JobState::Cancelled);
    assert_eq!(
        c.watch(oldest).unwrap().borrow().state(),
        JobState::Cancelled
    );
    let no_result = c.result(oldest, proto::ImageFormat::Png).unwrap_err();
    assert!(
        no_result.message().contains("is cancelled"),
        "{no_result:?}"
    );
    let no_priority = c.set_priority(oldest, 5, None).unwrap_err();
    assert_eq!(
        no_priority.code(),
        tonic::Code::FailedPrecondition,
        "{no_priority:?}"
    );
    let no_preview = c.previews(oldest).err().expect("no preview");
    assert_eq!(
        no_preview.code(),
        tonic::Code::FailedPrecondition,
        "{no_preview:?}"
    );
    // A job that never was is still unknown.
    for e in [
        c.cancel("job-0-9999", None).unwrap_err(),
        c.watch("job-0-9999").unwrap_err(),
        c.previews("job-0-9999").err().expect("unknown"),
    ] {
        assert_eq!(e.code(), tonic::Code::NotFound, "{e:?}");
    }
    // The metrics count the forgotten jobs.
    assert_eq!(
        c.lock().machine.job_counts().cancelled,
        cancelled.len() as u64
    );
    let_go(c);
}
