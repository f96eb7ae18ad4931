//! A scene re-prepared in place (`rayfarm prepare ... --force`) while the cluster keeps
//! running renders as the new scene: workers key what they keep of a scene by its manifest,
//! never by its directory alone. A scene re-prepared while a frame of it runs fails that frame
//! naming the scene (never an image of two versions), and the next job renders the new one.

use std::process::{Command, Stdio};
use std::time::Duration;

use rayfarm_tests::{
    Cluster, WorkerOpts, bin, domain_bytes, hash_of, local_hash, prepare_nbody, rayfarm_ok, s,
    stats_field, submit_wait, wait_child, wait_until,
};

/// Small, and deep enough that rays move between domains and so between workers.
const FRAME: [&str; 8] = [
    "--width", "96", "--height", "72", "--spp", "2", "--depth", "3",
];

/// Prepares other content (seed 6 instead of 5) into `scene` in place, the same number of
/// domains.
fn re_prepare(scene: &std::path::Path) {
    rayfarm_ok(&[
        "prepare",
        "--generate",
        "nbody",
        "--triangles",
        "30000",
        "--seed",
        "6",
        "--domains",
        "8",
        "--out",
        s(scene),
        "--force",
    ]);
}

#[test]
fn a_scene_re_prepared_in_place_renders_as_the_new_scene_on_the_same_workers() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 30_000, 8);
    let (_, largest) = domain_bytes(&scene);
    let old = local_hash(&scene, &FRAME);
    // Caches of two domains: workers keep some of the old scene mapped, and load others later.
    let workers = vec![WorkerOpts::cache(2 * largest); 2];
    let cluster = Cluster::start(root.path(), Some("nb"), &workers);
    cluster.wait_for_workers(2, Duration::from_secs(30));
    let first = submit_wait(&cluster, &FRAME, "old");
    assert_eq!(hash_of(&first), old, "the scene as first prepared");

    // Other content, the same directory, the same number of domains.
    re_prepare(&scene);
    let new = local_hash(&scene, &FRAME);
    assert_ne!(new, old, "the re-prepared scene looks different");
    let second = submit_wait(&cluster, &FRAME, "new");
    assert_eq!(
        hash_of(&second),
        new,
        "the same workers render the new scene"
    );
    assert_eq!(
        stats_field(&second, "/workers"),
        2,
        "both workers took part"
    );
    for i in 0..2 {
        assert!(
            cluster.worker_log(i).contains("scene changed on disk"),
            "worker {i} opened the new scene afresh"
        );
    }
}

#[test]
fn a_scene_re_prepared_while_its_frame_runs_fails_that_frame_naming_the_scene() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 30_000, 8);
    let (_, largest) = domain_bytes(&scene);
    // Caches of one domain and slow loads: the frame loads domains again and again for many
    // seconds, so it is still loading when the scene is replaced.
    let slow = WorkerOpts::cache(largest).args(&["--storage-latency", "300ms"]);
    let cluster = Cluster::start(root.path(), Some("nb"), &[slow.clone(), slow]);
    cluster.wait_for_workers(2, Duration::from_secs(30));
    let err = cluster.dir().join("mid.stderr");
    let mut client = Command::new(bin("rayfarm"))
        .args(["submit", "--wait", "--quiet"])
        .args(FRAME)
        .env("RAYFARM_COORDINATOR", cluster.coordinator_url())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&err).expect("stderr file"))
        .spawn()
        .expect("start rayfarm submit --wait");
    wait_until(
        "the frame to be two rounds in",
        Duration::from_secs(60),
        || cluster.status()["round"].as_u64() >= Some(2),
    );
    re_prepare(&scene);
    let ok = wait_child(&mut client, "submit --wait", Duration::from_secs(120));
    let err = std::fs::read_to_string(&err).expect("client stderr");
    assert!(!ok, "the frame of two scene versions failed: {err}");
    assert!(
        err.contains(&format!("scene {} was replaced on disk", scene.display()))
            && err.contains("submit the job again"),
        "the error names the scene: {err}"
    );
    // The same workers render the new version next.
    let new = local_hash(&scene, &FRAME);
    let stats = submit_wait(&cluster, &FRAME, "after");
    assert_eq!(hash_of(&stats), new, "the next job renders the new scene");
}
