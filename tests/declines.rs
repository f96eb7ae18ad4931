//! One misconfigured worker does not fail every job: a worker that cannot take part in a frame
//! (here: its scene root lacks the scene) declines it with the reason, the coordinator leaves
//! it out of that frame and says so in `rayfarm status`, and the job fails only when no worker
//! can take part, with every worker's reason.

use std::time::Duration;

use rayfarm_tests::{
    Cluster, WorkerOpts, domain_bytes, hash_of, local_hash, prepare_nbody, stats_field, submit_wait,
};

const FRAME: [&str; 8] = [
    "--width", "96", "--height", "72", "--spp", "2", "--depth", "3",
];

#[test]
fn a_worker_without_the_scene_is_left_out_and_the_others_render_the_local_image() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 30_000, 8);
    let (_, largest) = domain_bytes(&scene);
    let expected = local_hash(&scene, &FRAME);
    let empty = tempfile::tempdir().expect("temp dir");
    let good = WorkerOpts::cache(2 * largest);
    let workers = vec![good.clone(), good.clone().scene_root(empty.path()), good];
    let cluster = Cluster::start(root.path(), Some("nb"), &workers);
    cluster.wait_for_workers(3, Duration::from_secs(30));
    for tag in ["first", "second"] {
        let stats = submit_wait(&cluster, &FRAME, tag);
        assert_eq!(
            hash_of(&stats),
            expected,
            "{tag} job on the two good workers"
        );
        assert_eq!(
            stats_field(&stats, "/workers"),
            2,
            "{tag}: two workers took part"
        );
        let left: Vec<String> =
            serde_json::from_value(stats_field(&stats, "/left_out")).expect("left_out is a list");
        assert_eq!(
            left.len(),
            1,
            "{tag}: the statistics name the left-out worker: {left:?}"
        );
        assert!(
            left[0].starts_with(&format!(
                "worker {}: scene \"nb\" not found",
                cluster.worker_addr(1)
            )),
            "{left:?}"
        );
    }
    let status = cluster.status();
    let workers = status["workers"].as_array().expect("workers");
    assert_eq!(workers.len(), 3, "the left-out worker stays registered");
    let left_out: Vec<(&str, &str)> = workers
        .iter()
        .filter_map(|w| {
            let why = w["left_out"].as_str().filter(|r| !r.is_empty())?;
            Some((w["worker_id"].as_str().unwrap_or_default(), why))
        })
        .collect();
    assert_eq!(left_out.len(), 1, "one worker left out: {status}");
    let (id, why) = left_out[0];
    assert_eq!(id, cluster.worker_addr(1), "the worker without the scene");
    assert!(
        why.contains(r#"scene "nb" not found"#) && why.contains("scene root"),
        "the reason names the missing scene: {why}"
    );
    let text = String::from_utf8_lossy(&cluster.rayfarm_ok(&["status"]).stdout).to_string();
    assert!(text.contains("left out of job"), "status says so:\n{text}");
}

#[test]
fn with_every_worker_misconfigured_the_job_fails_with_all_their_reasons() {
    let root = tempfile::tempdir().expect("temp dir");
    prepare_nbody(root.path(), "nb", 10_000, 4);
    let empty = [
        tempfile::tempdir().expect("temp dir"),
        tempfile::tempdir().expect("temp dir"),
    ];
    let workers: Vec<WorkerOpts> = empty
        .iter()
        .map(|d| WorkerOpts::default().scene_root(d.path()))
        .collect();
    let cluster = Cluster::start(root.path(), Some("nb"), &workers);
    cluster.wait_for_workers(2, Duration::from_secs(30));
    let mut args = vec!["submit", "--wait", "--quiet"];
    args.extend_from_slice(&FRAME);
    let out = cluster.rayfarm(&args);
    assert!(!out.status.success(), "the job cannot render anywhere");
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(err.contains("no worker can take part"), "{err}");
    for i in 0..2 {
        let reason = format!("worker {}: scene \"nb\" not found", cluster.worker_addr(i));
        assert!(err.contains(&reason), "every worker's reason: {err}");
    }
}
