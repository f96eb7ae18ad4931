//! Hostile scene files: manifests that are FIFOs, huge, not manifests, symlinks out of the scene
//! root, or that become a FIFO after the job was submitted. Each is refused at once, quoting
//! nothing of the file, and the coordinator keeps serving.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use rayfarm_tests::{
    Cluster, WorkerOpts, bin, hash_of, local_hash, prepare_nbody, s, stats_field, submit_wait,
    wait_child, wait_until,
};

const FRAME: [&str; 8] = [
    "--width", "48", "--height", "32", "--spp", "1", "--depth", "2",
];

#[test]
fn hostile_scene_files_are_refused_at_once_without_their_contents() {
    let root = tempfile::tempdir().unwrap();
    let outside = tempfile::tempdir().unwrap();
    let scene = prepare_nbody(root.path(), "nb", 2000, 2);
    let secret = outside.path().join("secret");
    std::fs::write(&secret, "TOPSECRET-LINE = 42\n").unwrap();
    std::fs::create_dir(outside.path().join("scene")).unwrap();
    std::fs::write(
        outside.path().join("scene/scene.toml"),
        "TOPSECRET-LINE = 1\n",
    )
    .unwrap();
    let r = root.path();
    let link = |target: &std::path::Path, name: &str| {
        std::fs::create_dir_all(r.join(name)).unwrap();
        std::os::unix::fs::symlink(target, r.join(name).join("scene.toml")).unwrap();
    };
    link(&secret, "secret");
    link(std::path::Path::new("/etc/passwd"), "passwd");
    link(std::path::Path::new("/dev/zero"), "zero");
    link(&outside.path().join("nothing"), "dangling");
    std::os::unix::fs::symlink(outside.path().join("scene"), r.join("escape")).unwrap();
    std::fs::create_dir(r.join("fifo")).unwrap();
    let fifo = std::ffi::CString::new(s(&r.join("fifo/scene.toml"))).unwrap();
    // SAFETY: mkfifo reads the path it is given.
    assert_eq!(unsafe { libc::mkfifo(fifo.as_ptr(), 0o644) }, 0);
    std::fs::create_dir(r.join("huge")).unwrap();
    let huge = std::fs::File::create(r.join("huge/scene.toml")).unwrap();
    huge.set_len(64 << 20).unwrap();
    std::fs::create_dir(r.join("inside")).unwrap();
    std::fs::write(r.join("inside/scene.toml"), "password = \"hunter2\"\n").unwrap();

    let cluster = Cluster::start(r, Some("nb"), &[WorkerOpts::default()]);
    let absolute = outside.path().join("scene");
    let cases: [(&str, &str); 10] = [
        ("fifo", "not a regular file"),
        ("fifo", "not a regular file"),
        ("huge", "more than the"),
        ("inside", "line 1, column 1"),
        ("secret", "NOT_FOUND"),
        ("passwd", "NOT_FOUND"),
        ("zero", "NOT_FOUND"),
        ("dangling", "NOT_FOUND"),
        ("escape", "NOT_FOUND"),
        (s(&absolute), "--allow-absolute-scenes"),
    ];
    for (name, why) in cases {
        let start = Instant::now();
        let out = cluster.rayfarm(&["submit", "--scene", name]);
        let took = start.elapsed();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{name}: accepted");
        assert!(err.contains(why), "{name}: {why:?} missing from {err}");
        for secret in ["TOPSECRET", "root:", "hunter2", "password"] {
            assert!(!err.contains(secret), "{name}: {secret:?} in {err}");
        }
        // Nothing about paths outside the root, but what the caller named itself.
        let named = name.starts_with('/');
        assert!(named || !err.contains(s(outside.path())), "{name}: {err}");
        assert!(took < Duration::from_secs(5), "{name}: {took:?}");
    }
    // A missing scene and one leading outside get the same answer.
    let missing = String::from_utf8_lossy(&cluster.rayfarm(&["submit", "--scene", "none"]).stderr)
        .replace("\"none\"", "\"X\"");
    let escape = String::from_utf8_lossy(&cluster.rayfarm(&["submit", "--scene", "escape"]).stderr)
        .replace("\"escape\"", "\"X\"");
    assert_eq!(missing, escape);
    // The coordinator kept serving (heartbeats included): the worker is still there and the
    // next job renders the image of render --local.
    let stats = submit_wait(&cluster, &FRAME, "after");
    assert_eq!(hash_of(&stats), local_hash(&scene, &FRAME));
}

/// Replaces `dir/scene.toml` with a FIFO nobody writes to; returns where the real one went.
fn manifest_to_fifo(dir: &std::path::Path) -> std::path::PathBuf {
    let manifest = dir.join("scene.toml");
    let kept = dir.join("scene.toml.kept");
    std::fs::rename(&manifest, &kept).unwrap();
    let fifo = std::ffi::CString::new(s(&manifest)).unwrap();
    // SAFETY: mkfifo reads the path it is given.
    assert_eq!(unsafe { libc::mkfifo(fifo.as_ptr(), 0o644) }, 0);
    kept
}

#[test]
fn a_manifest_that_becomes_a_fifo_after_submit_fails_clearly_and_freezes_nothing() {
    let frame = ["--width", "64", "--height", "48", "--spp", "2"];
    let root = tempfile::tempdir().unwrap();
    let scene = prepare_nbody(root.path(), "nb", 2000, 2);
    let expected = local_hash(&scene, &frame);
    // No worker yet: the job waits in the queue while its manifest becomes a FIFO.
    let mut cluster = Cluster::start(root.path(), Some("nb"), &[]);
    let err = cluster.dir().join("fifo.stderr");
    let mut client = Command::new(bin("rayfarm"))
        .args(["submit", "--wait", "--quiet"])
        .args(frame)
        .env("RAYFARM_COORDINATOR", cluster.coordinator_url())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&err).unwrap())
        .spawn()
        .unwrap();
    wait_until("the job to be queued", Duration::from_secs(30), || {
        String::from_utf8_lossy(&cluster.rayfarm_ok(&["jobs"]).stdout).contains("nb")
    });
    let kept = manifest_to_fifo(&scene);
    // The coordinator re-reads the manifest when the frame starts: refused, not read.
    cluster.add_worker(&WorkerOpts::default());
    assert!(
        !wait_child(&mut client, "submit --wait", Duration::from_secs(60)),
        "a job whose manifest is a FIFO succeeded"
    );
    let err = std::fs::read_to_string(&err).unwrap();
    assert!(err.contains("scene.toml: not a regular file"), "{err}");
    // Nothing froze: the coordinator serves, its worker still heartbeats.
    cluster.wait_for_workers(1, Duration::from_secs(10));
    std::fs::remove_file(scene.join("scene.toml")).unwrap();
    std::fs::rename(&kept, scene.join("scene.toml")).unwrap();

    // A worker whose own view of the scene has a FIFO for a manifest declines the frame,
    // and the other renders it.
    let other = tempfile::tempdir().unwrap();
    let copy = other.path().join("nb");
    std::fs::create_dir(&copy).unwrap();
    for entry in std::fs::read_dir(&scene).unwrap() {
        let path = entry.unwrap().path();
        std::fs::copy(&path, copy.join(path.file_name().unwrap())).unwrap();
    }
    manifest_to_fifo(&copy);
    cluster.add_worker(&WorkerOpts::default().scene_root(other.path()));
    cluster.wait_for_workers(2, Duration::from_secs(30));
    let stats = submit_wait(&cluster, &frame, "fifo-worker");
    assert_eq!(hash_of(&stats), expected);
    let left_out = stats_field(&stats, "/left_out").to_string();
    assert!(
        left_out.contains("scene.toml: not a regular file"),
        "{left_out}"
    );
    // It is still there, heartbeating, and the coordinator still serves.
    cluster.wait_for_workers(2, Duration::from_secs(10));
    cluster.rayfarm_ok(&["jobs"]);
}
