//! A scene re-prepared in place (`rayfarm prepare ... --force`) while the cluster keeps
//! running renders as the new scene: workers key what they keep of a scene by its manifest,
//! never by its directory alone.

use std::time::Duration;

use rayfarm_tests::{
    Cluster, WorkerOpts, domain_bytes, hash_of, local_hash, prepare_nbody, rayfarm_ok, s,
    stats_field, submit_wait,
};

/// Small, and deep enough that rays move between domains and so between workers.
const FRAME: [&str; 8] = [
    "--width", "96", "--height", "72", "--spp", "2", "--depth", "3",
];

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
        s(&scene),
        "--force",
    ]);
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
