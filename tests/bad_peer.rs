//! Bad input from outside, against a real cluster: a client that speaks the peer protocol
//! (the generated tonic client) sends a worker garbage batches, truncated batches, lying
//! counts, bad records, verdicts in the wrong tier or naming unknown materials, bundles of a
//! tier there is not (none, the retired control tier 1, 99), and bundles of another protocol
//! version while a (predictive) frame runs. Each gets a precise gRPC
//! status and a log line with context, and the frame the bad bundles claim to belong to
//! still renders the image of `rayfarm render --local`. Then scenes whose manifest does not
//! parse or lies about its domains fail their jobs precisely, and the next job renders the
//! reference image.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use bytes::Bytes;
use rayfarm_core::ray::RayRecord;
use rayfarm_core::wire::{self, VerdictRecord};
use rayfarm_node::proto::peer_service_client::PeerServiceClient;
use rayfarm_node::proto::{self, PROTOCOL_VERSION};
use rayfarm_tests::{
    Cluster, WorkerOpts, bin, hash_of, local_hash, prepare_nbody, s, submit_wait, wait_child,
    wait_until,
};
use tonic::Code;

/// A frame long enough to still be running while the bad bundles arrive (usually; the test
/// holds either way), deep enough to send rays between workers. It runs predictive, so that
/// verdicts travel too.
const FRAME: [&str; 8] = [
    "--width", "192", "--height", "144", "--spp", "8", "--depth", "3",
];

/// A quick frame for after the bad input.
const NEXT: [&str; 8] = [
    "--width", "96", "--height", "72", "--spp", "2", "--depth", "3",
];

fn prepare(root: &Path, name: &str) -> PathBuf {
    prepare_nbody(root, name, 20_000, 4)
}

/// Runs `rayfarm` against the cluster expecting failure; returns stderr.
fn refused(cluster: &Cluster, args: &[&str]) -> String {
    let out = cluster.rayfarm(args);
    assert!(
        !out.status.success(),
        "rayfarm {} should have failed",
        args.join(" ")
    );
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A ray valid in any frame of the test scene.
fn ray() -> RayRecord {
    RayRecord {
        origin: [0.0, 0.0, -5.0],
        dir: [0.0, 0.0, 1.0],
        t_max: f32::INFINITY,
        throughput: [1.0; 3],
        ..bytemuck::Zeroable::zeroed()
    }
}

/// A verdict on a speculative copy of `ray()`, hitting material `material`.
fn verdict(material: u32) -> VerdictRecord {
    VerdictRecord {
        group: 12345,
        kind: VerdictRecord::HIT,
        t: 1.0,
        normal: [0.0, 1.0, 0.0],
        material,
        ..bytemuck::Zeroable::zeroed()
    }
}

fn results(job_id: &str, batches: Vec<Vec<u8>>) -> proto::PeerBundle {
    proto::PeerBundle {
        tier: proto::Tier::Results as i32,
        ..bundle(job_id, batches)
    }
}

fn bundle(job_id: &str, batches: Vec<Vec<u8>>) -> proto::PeerBundle {
    proto::PeerBundle {
        protocol_version: PROTOCOL_VERSION,
        sender: "bad-peer".into(),
        job_id: job_id.into(),
        tier: proto::Tier::Migrated as i32,
        sequence: 1,
        batches: batches.into_iter().map(Bytes::from).collect(),
    }
}

/// Opens an `ExchangeBundles` stream to the worker at `addr`, sends `bundle`, and returns the
/// status the stream ends with (`Ok` if the bundle was acknowledged).
async fn exchange(addr: &str, bundle: proto::PeerBundle) -> Result<(), tonic::Status> {
    let mut client = PeerServiceClient::connect(format!("http://{addr}"))
        .await
        .expect("connect to the worker's peer endpoint");
    let mut acks = client
        .exchange_bundles(tokio_stream::iter(vec![bundle]))
        .await?
        .into_inner();
    match acks.message().await? {
        Some(ack) => {
            assert_eq!(ack.sequence, 1);
            Ok(())
        }
        None => panic!("the stream ended with neither an acknowledgement nor an error"),
    }
}

#[test]
fn bad_peers_get_precise_statuses_and_the_frame_they_claim_still_renders() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare(root.path(), "nb");
    let expected = local_hash(&scene, &FRAME);
    let cluster = Cluster::start(root.path(), Some("nb"), &vec![WorkerOpts::default(); 2]);
    let json = cluster.dir().join("frame.json");
    let png = cluster.dir().join("frame.png");
    let mut waiter = Command::new(bin("rayfarm"))
        .args([
            "submit",
            "--wait",
            "--quiet",
            "-o",
            s(&png),
            "--stats-json",
            s(&json),
        ])
        .args(FRAME)
        .args(["--schedule", "predictive"])
        .env("RAYFARM_COORDINATOR", cluster.coordinator_url())
        .stdout(Stdio::null())
        .spawn()
        .expect("start rayfarm submit");
    let mut job = String::new();
    wait_until("the frame to start", Duration::from_secs(60), || {
        job = cluster.status()["running_job_id"]
            .as_str()
            .unwrap_or_default()
            .to_string();
        !job.is_empty()
    });

    let valid = wire::encode_batch(&[ray(), ray(), ray()]);
    let truncated = valid[..valid.len() - 7].to_vec();
    let mut lying_count = valid.clone();
    lying_count[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
    let mut other_layout = valid.clone();
    other_layout[4] = 9;
    let mut nan_ray = ray();
    nan_ray.dir = [f32::NAN, 0.0, 1.0];
    let bad_record = wire::encode_batch(&[ray(), nan_ray]);
    let mut other_protocol = bundle(&job, vec![valid.clone()]);
    other_protocol.protocol_version = PROTOCOL_VERSION + 1;
    let other_protocol_message = format!("speaks protocol {}", PROTOCOL_VERSION + 1);
    let mut unknown_tier = bundle(&job, vec![valid.clone()]);
    unknown_tier.tier = 99;
    // The control tier's number before protocol 6: reserved, so refused, never read as rays.
    let mut control_tier = bundle(&job, vec![valid.clone()]);
    control_tier.tier = 1;
    let mut no_tier = bundle(&job, vec![valid.clone()]);
    no_tier.tier = proto::Tier::Unspecified as i32;
    let garbage = b"GET / HTTP/1.1\r\nHost: worker\r\n\r\n".repeat(5);
    let cases: Vec<(&str, proto::PeerBundle, Code, &str)> = vec![
        (
            "garbage",
            bundle(&job, vec![garbage]),
            Code::InvalidArgument,
            "bad magic",
        ),
        (
            "truncated",
            bundle(&job, vec![truncated]),
            Code::DataLoss,
            "truncated",
        ),
        (
            "lying count",
            bundle(&job, vec![lying_count]),
            Code::DataLoss,
            "says 4294967295 records, holds 3",
        ),
        (
            "batch layout of another version",
            bundle(&job, vec![other_layout]),
            Code::FailedPrecondition,
            "version 9",
        ),
        (
            "bad record after a good batch",
            bundle(&job, vec![valid.clone(), bad_record]),
            Code::InvalidArgument,
            "batch 1: record 1: non-finite",
        ),
        (
            "verdicts in the rays' tier",
            bundle(&job, vec![wire::encode_verdicts(&[verdict(0)])]),
            Code::InvalidArgument,
            "bad magic",
        ),
        (
            "rays in the verdicts' tier",
            results(&job, vec![valid.clone()]),
            Code::InvalidArgument,
            "bad magic",
        ),
        (
            "a verdict hitting a material the scene lacks",
            results(
                &job,
                vec![wire::encode_verdicts(&[verdict(0), verdict(u32::MAX)])],
            ),
            Code::InvalidArgument,
            "batch 0: record 1: material out of range",
        ),
        (
            "another protocol version",
            other_protocol,
            Code::FailedPrecondition,
            other_protocol_message.as_str(),
        ),
        (
            "unknown tier",
            unknown_tier,
            Code::InvalidArgument,
            "unknown tier 99",
        ),
        (
            "the retired control tier",
            control_tier,
            Code::InvalidArgument,
            "unknown tier 1",
        ),
        ("no tier", no_tier, Code::InvalidArgument, "has no tier"),
    ];
    let runtime = tokio::runtime::Runtime::new().expect("tokio runtime");
    let addr = cluster.worker_addr(0).to_string();
    for (what, bundle, code, message) in &cases {
        let status = runtime
            .block_on(exchange(&addr, bundle.clone()))
            .expect_err(what);
        assert_eq!(status.code(), *code, "{what}: {status:?}");
        assert!(status.message().contains(message), "{what}: {status:?}");
    }
    // A well-formed bundle for a job the worker does not run is acknowledged: the refusals
    // above are about the input, not the client.
    let unrelated = bundle("job-nobody-runs", vec![wire::encode_batch(&[ray()])]);
    runtime
        .block_on(exchange(&addr, unrelated))
        .expect("a valid bundle is acknowledged");
    // Well-formed verdicts for rays the worker is not waiting on are acknowledged, and
    // refused by the groups (they never settle another ray).
    let strays = results(&job, vec![wire::encode_verdicts(&[verdict(0), verdict(0)])]);
    runtime
        .block_on(exchange(&addr, strays))
        .expect("well-formed verdicts are acknowledged");

    assert!(
        wait_child(&mut waiter, "the frame", Duration::from_secs(180)),
        "the frame failed after bad bundles"
    );
    assert_eq!(hash_of(&json), expected);
    // Each refusal was logged with where it came from and what it claimed to be.
    let log = std::fs::read_to_string(cluster.dir().join("worker-0.log")).expect("worker log");
    let refusals: Vec<&str> = log
        .lines()
        .filter(|l| l.contains("refusing a bundle from a peer"))
        .collect();
    assert_eq!(refusals.len(), cases.len(), "{log}");
    for ((what, _, _, message), line) in cases.iter().zip(&refusals) {
        for context in [
            "remote=127.0.0.1:",
            "sender=bad-peer",
            &format!("job={job}"),
            message,
        ] {
            assert!(line.contains(context), "{what}: {context} not in {line}");
        }
    }
    assert!(!log.contains("panicked"), "{log}");
    // Both workers are still members, and the next job renders the reference image too.
    assert_eq!(
        cluster.status()["workers"].as_array().map(Vec::len),
        Some(2)
    );
    let stats = submit_wait(&cluster, &NEXT, "next");
    assert_eq!(hash_of(&stats), local_hash(&scene, &NEXT));
}

/// A copy of `scene` named `name` under the same root, with its manifest passed through `edit`.
fn variant(scene: &Path, name: &str, edit: impl FnOnce(&str) -> String) -> PathBuf {
    let out = scene.with_file_name(name);
    std::fs::create_dir_all(&out).expect("mkdir");
    for entry in std::fs::read_dir(scene).expect("scene dir") {
        let entry = entry.expect("entry");
        std::fs::copy(entry.path(), out.join(entry.file_name())).expect("copy");
    }
    let manifest = out.join("scene.toml");
    let text = std::fs::read_to_string(&manifest).expect("manifest");
    std::fs::write(&manifest, edit(&text)).expect("write manifest");
    out
}

/// `text` with `key = N` of every `[[domains]]` table replaced by `key = f(N)`.
fn edit_domains(text: &str, key: &str, f: impl Fn(u64) -> u64) -> String {
    let mut in_domain = false;
    let prefix = format!("{key} = ");
    let mut edited = 0;
    let out: Vec<String> = text
        .lines()
        .map(|line| {
            if line.starts_with('[') {
                in_domain = line.trim() == "[[domains]]";
            }
            match line
                .strip_prefix(&prefix)
                .and_then(|n| n.trim().parse().ok())
            {
                Some(n) if in_domain => {
                    edited += 1;
                    format!("{prefix}{}", f(n))
                }
                _ => line.to_string(),
            }
        })
        .collect();
    assert!(edited > 0, "no {key} in the domains of\n{text}");
    out.join("\n")
}

#[test]
fn manifests_that_lie_or_do_not_parse_fail_precisely_and_the_next_job_renders() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare(root.path(), "nb");
    variant(&scene, "garbled", |t| t[..t.len() / 2].replace('=', ":"));
    variant(&scene, "wrong-type", |t| {
        t.replacen("ray_epsilon = ", "ray_epsilon = \"x\" #", 1)
    });
    variant(&scene, "lies-bytes", |t| {
        edit_domains(t, "bytes", |n| n + 4096)
    });
    variant(&scene, "lies-triangles", |t| {
        edit_domains(t, "triangles", |n| n + 1)
    });
    std::fs::create_dir_all(root.path().join("no-manifest")).expect("mkdir");
    let cluster = Cluster::start(root.path(), Some("nb"), &[WorkerOpts::default()]);

    // Refused at submit: the manifest is read there.
    for (name, code, what) in [
        ("garbled", "FAILED_PRECONDITION", "malformed manifest"),
        ("wrong-type", "FAILED_PRECONDITION", "ray_epsilon"),
        ("no-manifest", "FAILED_PRECONDITION", "scene.toml"),
    ] {
        let err = refused(&cluster, &["submit", "--scene", name]);
        assert!(
            err.contains(code) && err.contains(what) && err.contains(name),
            "{name}: {err}"
        );
    }
    // Domain files are opened by the workers: the job fails naming the file and the lie.
    for (name, what) in [
        ("lies-bytes", "bytes, the manifest says"),
        ("lies-triangles", "triangles, the manifest says"),
    ] {
        let mut args = vec!["submit", "--scene", name, "--wait", "--quiet"];
        args.extend_from_slice(&NEXT);
        let err = refused(&cluster, &args);
        assert!(
            err.contains("failed") && err.contains(what) && err.contains(".rfd"),
            "{name}: {err}"
        );
    }
    let stats = submit_wait(&cluster, &NEXT, "after");
    assert_eq!(hash_of(&stats), local_hash(&scene, &NEXT));
}
