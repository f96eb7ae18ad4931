//! Hostile nodes and users: a node registering with another worker's peer address, a user
//! cancelling another's jobs or past their quotas.

use rayfarm_node::proto;
use rayfarm_tests::hostile::runtime;
use rayfarm_tests::{Cluster, ClusterOpts, WorkerOpts, prepare_nbody, s};

/// A node with the cluster credentials (none configured here: loopback) attaches as a worker.
async fn fake_worker(
    url: &str,
    id: &str,
    peer_address: &str,
) -> (
    tokio::sync::mpsc::Sender<proto::WorkerMessage>,
    Result<tonic::Streaming<proto::CoordinatorMessage>, tonic::Status>,
) {
    use proto::worker_message::Body;
    let mut client = proto::worker_control_client::WorkerControlClient::connect(url.to_string())
        .await
        .unwrap();
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    tx.send(proto::WorkerMessage {
        body: Some(Body::Register(proto::Register {
            protocol_version: proto::PROTOCOL_VERSION,
            worker_id: id.into(),
            peer_address: peer_address.into(),
            cache_bytes: 1 << 20,
            threads: 1,
        })),
    })
    .await
    .unwrap();
    let stream = tokio_stream::wrappers::ReceiverStream::new(rx);
    let answer = client.attach(stream).await.map(tonic::Response::into_inner);
    (tx, answer)
}

#[test]
fn a_node_cannot_register_with_another_workers_address() {
    let rt = runtime();
    let root = tempfile::tempdir().unwrap();
    let cluster = Cluster::start(root.path(), None, &[WorkerOpts::default()]);
    let url = cluster.coordinator_url().to_string();
    let victim = cluster.status()["workers"][0]["peer_address"]
        .as_str()
        .unwrap()
        .to_string();
    let (_tx, answer) = rt.block_on(fake_worker(&url, "impostor", &victim));
    let Err(e) = answer else {
        panic!("registered with another worker's address");
    };
    assert_eq!(e.code(), tonic::Code::AlreadyExists, "{e}");
    // Its own address is fine.
    let (_tx, answer) = rt.block_on(fake_worker(&url, "other", "127.0.0.1:9"));
    answer.expect("a fresh address registers");
}

#[test]
fn users_cancel_only_their_own_jobs_and_quotas_refuse() {
    let root = tempfile::tempdir().unwrap();
    prepare_nbody(root.path(), "nb", 2000, 2);
    let tokens = root.path().join("user-tokens");
    std::fs::write(
        &tokens,
        "tok-alice alice\ntok-bob bob\ntok-root root admin\n",
    )
    .unwrap();
    let opts = ClusterOpts {
        coordinator_args: [
            "--user-tokens-file",
            s(&tokens),
            "--max-jobs-per-user",
            "2",
            "--max-pixel-samples-per-user",
            "100000",
        ]
        .iter()
        .map(|a| a.to_string())
        .collect(),
        client_env: vec![("RAYFARM_TOKEN".into(), "tok-root".into())],
        ..ClusterOpts::default()
    };
    // No workers: jobs stay queued.
    let cluster = Cluster::start_with(root.path(), Some("nb"), &opts, &[]);
    let submit = |token: &str, spp: &str| {
        let args = ["submit", "--width", "100", "--height", "100", "--spp", spp];
        cluster.rayfarm_as(&[("RAYFARM_TOKEN", token)], &args)
    };
    let out = submit("tok-alice", "4");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let alices = String::from_utf8_lossy(&out.stdout).trim().to_string();
    // Bob cannot cancel it; an admin can.
    let out = cluster.rayfarm_as(&[("RAYFARM_TOKEN", "tok-bob")], &["cancel", &alices]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("PERMISSION_DENIED"),
        "{err}"
    );
    // Quotas: alice's 40,000 pixel-samples leave room for one more such job of 100,000,
    // then the pixel-samples quota refuses; bob's two jobs fill his job count.
    let out = submit("tok-alice", "4");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = submit("tok-alice", "1");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("RESOURCE_EXHAUSTED"),
        "{err}"
    );
    assert!(err.contains("jobs queued or running"), "{err}");
    for _ in 0..2 {
        let out = submit("tok-bob", "1");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let out = submit("tok-bob", "1");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("RESOURCE_EXHAUSTED"),
        "{err}"
    );
    let out = cluster.rayfarm_as(&[("RAYFARM_TOKEN", "tok-root")], &["cancel", &alices]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // Cancelled, alice's job no longer counts: she may submit again, but not past the
    // pixel-samples quota (40,000 held + 80,000 > 100,000).
    let out = submit("tok-alice", "8");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("pixel-samples"), "{err}");
    let out = submit("tok-alice", "4");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The log names the user of every change.
    let log = cluster.coordinator_log();
    assert!(
        log.contains("user=alice") && log.contains("user=root"),
        "{log}"
    );
}
