//! One misconfigured worker does not fail every job: a worker that cannot take part in a frame
//! (its scene root lacks the scene, its spill directory is unwritable or full, a domain fails
//! its checksum) declines it with the reason, the coordinator leaves
//! it out of that frame and says so in `rayfarm status`, and the job fails only when no worker
//! can take part, with every worker's reason.

use std::time::Duration;

use rayfarm_tests::{
    Cluster, WorkerOpts, domain_bytes, hash_of, local_hash, prepare_nbody, s, stats_field,
    submit_wait,
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

/// A tmpfs of `size` mounted on a new directory, unmounted when dropped; `None` when this
/// process may not mount (not root).
struct Tmpfs(tempfile::TempDir);

impl Tmpfs {
    fn mount(size: &str, options: &str) -> Option<Tmpfs> {
        let dir = tempfile::tempdir().expect("temp dir");
        let ok = std::process::Command::new("mount")
            .args([
                "-t",
                "tmpfs",
                "-o",
                &format!("size={size}{options}"),
                "tmpfs",
            ])
            .arg(dir.path())
            .stderr(std::process::Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        ok.then_some(Tmpfs(dir))
    }

    fn path(&self) -> &std::path::Path {
        self.0.path()
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount")
            .arg(self.0.path())
            .status();
    }
}

/// Fills the file system of `dir` until a write fails.
fn fill(dir: &std::path::Path) {
    use std::io::Write;
    let mut f = std::fs::File::create(dir.join("filler")).expect("filler");
    let block = vec![0xa5u8; 4096];
    while f.write_all(&block).is_ok() {}
}

/// The frame the spill tests render: big enough that a worker holding 4 KiB of rays in memory
/// spills megabytes.
const SPILLING: [&str; 8] = [
    "--width", "160", "--height", "120", "--spp", "4", "--depth", "3",
];

#[test]
fn a_worker_whose_spill_directory_fails_is_left_out_and_the_others_render_the_local_image() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 30_000, 8);
    let (_, largest) = domain_bytes(&scene);
    let expected = local_hash(&scene, &SPILLING);
    let good = WorkerOpts::cache(2 * largest);
    // A spill directory that cannot be made: its parent is a regular file.
    let file = root.path().join("not-a-dir");
    std::fs::write(&file, b"x").expect("file");
    let unwritable = file.join("spill");
    let mut workers = vec![
        good.clone(),
        good.clone().arg("--spill-dir", s(&unwritable)),
    ];
    // As root, also a full tmpfs (found when the frame starts) and a small one that fills up
    // halfway through the frame (the worker leaves it then).
    let full = Tmpfs::mount("1M", "");
    let small = Tmpfs::mount("256K", "");
    if let (Some(full), Some(small)) = (&full, &small) {
        fill(full.path());
        workers.push(good.clone().arg("--spill-dir", s(full.path())));
        workers.push(
            good.clone()
                .args(&["--spill-dir", s(small.path()), "--queue-bytes", "4KiB"]),
        );
    } else {
        eprintln!("SKIPPED the full spill directories: mounting a tmpfs needs root");
    }
    let n = workers.len();
    let cluster = Cluster::start(root.path(), Some("nb"), &workers);
    cluster.wait_for_workers(n, Duration::from_secs(30));
    let stats = submit_wait(&cluster, &SPILLING, "spill");
    assert_eq!(hash_of(&stats), expected, "the image of the good worker(s)");
    let left: Vec<String> =
        serde_json::from_value(stats_field(&stats, "/left_out")).expect("left_out is a list");
    let reason = |i: usize| {
        left.iter()
            .find(|r| r.starts_with(&format!("worker {}: ", cluster.worker_addr(i))))
            .unwrap_or_else(|| panic!("worker {i} is not left out: {left:?}"))
    };
    let why = reason(1);
    assert!(
        why.contains(&format!("spill directory {}", unwritable.display()))
            && why.contains("Not a directory"),
        "{why}"
    );
    if let (Some(full), Some(small)) = (&full, &small) {
        let why = reason(2);
        assert!(
            why.contains(&format!("spill directory {}", full.path().display()))
                && why.contains("No space left on device"),
            "{why}"
        );
        let why = reason(3);
        assert!(
            why.contains(&format!("spill directory {}", small.path().display()))
                && why.contains("spilling rays to disk")
                && why.contains("No space left on device"),
            "the small one fills up mid-frame: {why}"
        );
    }
    assert_eq!(left.len(), n - 1, "{left:?}");
    assert_eq!(stats_field(&stats, "/workers"), 1, "one worker rendered");
}

#[test]
fn a_domain_failing_its_checksum_on_every_worker_fails_the_job_naming_the_file() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 10_000, 2);
    // Flip one byte at the end of every domain file: headers intact, contents not.
    let mut damaged = Vec::new();
    for entry in std::fs::read_dir(&scene).expect("scene dir") {
        let path = entry.expect("entry").path();
        if path.extension().is_some_and(|e| e == "rfd") {
            let mut bytes = std::fs::read(&path).expect("domain");
            *bytes.last_mut().expect("not empty") ^= 0x40;
            std::fs::write(&path, &bytes).expect("damage");
            damaged.push(path.file_name().unwrap().to_string_lossy().to_string());
        }
    }
    assert_eq!(damaged.len(), 2, "{damaged:?}");
    let workers = vec![WorkerOpts::default(), WorkerOpts::default()];
    let cluster = Cluster::start(root.path(), Some("nb"), &workers);
    cluster.wait_for_workers(2, Duration::from_secs(30));
    let mut args = vec!["submit", "--wait", "--quiet"];
    args.extend_from_slice(&FRAME);
    let out = cluster.rayfarm(&args);
    assert!(
        !out.status.success(),
        "no worker can render the damaged scene"
    );
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(err.contains("no worker can take part"), "{err}");
    for i in 0..2 {
        let start = format!("worker {}: ", cluster.worker_addr(i));
        let reason = err
            .split("; ")
            .find_map(|r| r.split_once(&start).map(|(_, why)| why))
            .unwrap_or_else(|| panic!("worker {i} has no reason: {err}"));
        assert!(
            damaged.iter().any(|d| reason.contains(d.as_str()))
                && reason.contains("bad domain file"),
            "the reason names the damaged file: {reason}"
        );
    }
    // The reasons name files and hashes, never the contents.
    assert!(err.len() < 2000, "{} bytes of error: {err}", err.len());
    assert!(!err.contains('\u{fffd}'), "{err}");
}
