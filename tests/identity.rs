//! Per-node certificates under mutual TLS, with real processes on loopback: `rayfarm certs
//! --node ID` issues each node a certificate named by its id (and adds nodes to an existing
//! CA without touching any key); a cluster whose workers present their own certificates
//! renders the image of `render --local`; and a node holding the cluster secret and a valid
//! certificate for one id can neither register under another id or at a host its
//! certificate does not name, nor send peer bundles in another node's name.

use std::path::{Path, PathBuf};

use rayfarm_node::proto;
use rayfarm_node::proto::peer_service_client::PeerServiceClient;
use rayfarm_node::proto::worker_control_client::WorkerControlClient;
use rayfarm_node::proto::worker_message::Body as FromWorker;
use rayfarm_node::security::{ClusterSecret, ConnectTlsArgs, Credential, ServeTlsArgs, endpoint};
use rayfarm_tests::{
    Cluster, ClusterOpts, WorkerOpts, bin, domain_bytes, hash_of, local_hash, prepare_nbody,
    rayfarm_err, rayfarm_ok, s, submit_wait,
};
use tonic::Code;
use tonic::transport::Channel;

const FRAME: [&str; 8] = [
    "--width", "96", "--height", "72", "--spp", "2", "--depth", "3",
];

/// A node's certificate and key as `rayfarm certs --node ID` names them in `dir`.
fn node_files(dir: &Path, id: &str) -> (PathBuf, PathBuf) {
    (
        dir.join(format!("node-{id}.pem")),
        dir.join(format!("node-{id}-key.pem")),
    )
}

/// A channel to `addr` over TLS that trusts `dir`'s CA and presents node `id`'s certificate.
async fn connect_as(dir: &Path, id: &str, addr: &str) -> Channel {
    let (cert, key) = node_files(dir, id);
    let identity = ServeTlsArgs {
        tls_cert: Some(cert),
        tls_key: Some(key),
        tls_client_ca: None,
    }
    .identity()
    .expect("identity");
    let tls = ConnectTlsArgs {
        tls_ca: Some(dir.join("ca.pem")),
        tls_domain: None,
    }
    .client_config(identity)
    .expect("tls config");
    endpoint(addr, tls.as_ref())
        .expect("endpoint")
        .connect()
        .await
        .expect("connect over mutual TLS")
}

/// Registers on the coordinator at `url` as `worker_id` at `peer_address`; the status the
/// attach ends with, or `Ok` once it is registered.
async fn register(
    channel: Channel,
    secret: &ClusterSecret,
    worker_id: &str,
    peer_address: &str,
) -> Result<(), tonic::Status> {
    let mut client =
        WorkerControlClient::with_interceptor(channel, Credential::secret(Some(secret)));
    let register = proto::WorkerMessage {
        body: Some(FromWorker::Register(proto::Register {
            protocol_version: proto::PROTOCOL_VERSION,
            worker_id: worker_id.into(),
            peer_address: peer_address.into(),
            cache_bytes: 1 << 30,
            threads: 1,
        })),
    };
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(register).await.expect("queue the registration");
    let mut answers = client
        .attach(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await?
        .into_inner();
    answers.message().await.map(|_| ())
}

/// Sends one empty bundle under `sender` to the worker at `addr`: its acknowledgement, or
/// the status the stream ends with.
async fn push_as(
    channel: Channel,
    secret: &ClusterSecret,
    sender: &str,
) -> Result<proto::PeerAck, tonic::Status> {
    let mut peer = PeerServiceClient::with_interceptor(channel, Credential::secret(Some(secret)));
    let bundle = proto::PeerBundle {
        protocol_version: proto::PROTOCOL_VERSION,
        sender: sender.into(),
        job_id: "no-such-job".into(),
        tier: proto::Tier::Migrated as i32,
        sequence: 1,
        ..Default::default()
    };
    let mut acks = peer
        .exchange_bundles(tokio_stream::iter(vec![bundle]))
        .await?
        .into_inner();
    match acks.message().await? {
        Some(ack) => Ok(ack),
        None => Err(tonic::Status::unknown("the stream ended without an answer")),
    }
}

#[test]
fn per_node_certificates_bind_ids_and_a_mutual_tls_cluster_renders_the_local_image() {
    let root = tempfile::tempdir().expect("temp dir");
    let dir = root.path().join("certs");
    let hosts = ["--node-hosts", "localhost,127.0.0.1"];
    let first = [
        &["certs", "--out", s(&dir), "--hosts", "localhost,127.0.0.1"][..],
        &["--with-secrets", "--node", "w-a,w-b"],
        &hosts,
    ]
    .concat();
    rayfarm_ok(&first);
    // A node added later is issued by the same CA; nothing that exists is rewritten.
    let key_a = std::fs::read(node_files(&dir, "w-a").1).expect("w-a's key");
    rayfarm_ok(&[&["certs", "--out", s(&dir), "--node", "w-c"][..], &hosts].concat());
    let err = rayfarm_err(&[&["certs", "--out", s(&dir), "--node", "w-a"][..], &hosts].concat());
    assert!(err.contains("already holds node-w-a.pem"), "{err}");
    rayfarm_ok(
        &[
            &["certs", "--out", s(&dir), "--if-missing", "--node", "w-a"][..],
            &hosts,
        ]
        .concat(),
    );
    assert_eq!(
        std::fs::read(node_files(&dir, "w-a").1).expect("key"),
        key_a
    );
    use std::os::unix::fs::PermissionsExt;
    for key in ["ca-key.pem", "node-w-c-key.pem"] {
        let mode = std::fs::metadata(dir.join(key))
            .expect("mode")
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o600, "{key}");
    }

    let scene = prepare_nbody(root.path(), "nb", 30_000, 8);
    let expected = local_hash(&scene, &FRAME);
    let (ca, secret_file) = (dir.join("ca.pem"), dir.join("cluster-secret"));
    let opts = ClusterOpts {
        coordinator_args: [
            "--tls-cert",
            s(&dir.join("node.pem")),
            "--tls-key",
            s(&dir.join("node-key.pem")),
            "--tls-client-ca",
            s(&ca),
            "--cluster-secret-file",
            s(&secret_file),
        ]
        .iter()
        .map(|a| a.to_string())
        .collect(),
        client_env: vec![
            ("RAYFARM_TLS_CA".into(), s(&ca).into()),
            ("RAYFARM_TLS_CERT".into(), s(&dir.join("node.pem")).into()),
            (
                "RAYFARM_TLS_KEY".into(),
                s(&dir.join("node-key.pem")).into(),
            ),
        ],
        https: true,
        ..ClusterOpts::default()
    };
    // Each worker presents its own certificate, to the coordinator and to its peers, and
    // asks its peers for theirs; caches of two domains make rays cross between them.
    let member = |id: &str| {
        let (cert, key) = node_files(&dir, id);
        WorkerOpts::cache(2 * domain_bytes(&scene).1).args(&[
            "--tls-cert",
            s(&cert),
            "--tls-key",
            s(&key),
            "--tls-client-ca",
            s(&ca),
            "--tls-ca",
            s(&ca),
            "--cluster-secret-file",
            s(&secret_file),
        ])
    };
    let cluster = Cluster::start_with(
        root.path(),
        Some("nb"),
        &opts,
        &[member("w-a"), member("w-b")],
    );
    let status = cluster.status();
    let mut ids: Vec<&str> = status["workers"]
        .as_array()
        .expect("workers")
        .iter()
        .map(|w| w["worker_id"].as_str().expect("id"))
        .collect();
    ids.sort_unstable();
    assert_eq!(
        ids,
        ["w-a", "w-b"],
        "workers take their certificates' names"
    );

    let stats = submit_wait(&cluster, &FRAME, "per-node");
    assert_eq!(
        hash_of(&stats),
        expected,
        "the image differs from render --local"
    );

    // A worker told to be another node than its certificate says refuses to start.
    let (cert_c, key_c) = node_files(&dir, "w-c");
    let out = std::process::Command::new(bin("rayfarm-worker"))
        .args([
            "--coordinator",
            cluster.coordinator_url(),
            "--worker-id",
            "w-a",
        ])
        .args([
            "--tls-cert",
            s(&cert_c),
            "--tls-key",
            s(&key_c),
            "--tls-client-ca",
            s(&ca),
        ])
        .args(["--tls-ca", s(&ca), "--cluster-secret-file", s(&secret_file)])
        .output()
        .expect("run a worker");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("is not the name of this node's certificate (w-c)"),
        "{err}"
    );

    // A hostile node with the cluster secret and w-c's valid certificate.
    let secret = ClusterSecret::from_file(&secret_file).expect("secret");
    let worker_a = cluster.worker_addr(0).to_string();
    let url = cluster.coordinator_url().to_string();
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    rt.block_on(async {
        for (id, address, why) in [
            (
                "w-a",
                "127.0.0.1:9",
                "is not the name of its client certificate (w-c)",
            ),
            (
                "w-new",
                "127.0.0.1:9",
                "is not the name of its client certificate (w-c)",
            ),
            ("w-c", "10.9.9.9:9", "is not a host of w-c's certificate"),
        ] {
            let refused = register(connect_as(&dir, "w-c", &url).await, &secret, id, address)
                .await
                .expect_err("registered under a name or host its certificate lacks");
            assert_eq!(refused.code(), Code::PermissionDenied, "{refused:?}");
            assert!(refused.message().contains(why), "{refused:?}");
        }
        // Bundles in w-b's name are refused by w-a; in its own name they are taken.
        let refused = push_as(connect_as(&dir, "w-c", &worker_a).await, &secret, "w-b")
            .await
            .expect_err("a bundle in another node's name was taken");
        assert_eq!(refused.code(), Code::PermissionDenied, "{refused:?}");
        assert!(refused.message().contains("w-b"), "{refused:?}");
        let ack = push_as(connect_as(&dir, "w-c", &worker_a).await, &secret, "w-c")
            .await
            .expect("a bundle in its own name is acknowledged");
        assert_eq!(ack.sequence, 1);
    });
    let log = cluster.coordinator_log();
    assert!(log.contains("registration refused"), "{log}");
    assert_eq!(
        cluster.status()["workers"]
            .as_array()
            .expect("workers")
            .len(),
        2,
        "the impostor was registered"
    );
    // The cluster still renders right after all that.
    let again = submit_wait(&cluster, &FRAME, "per-node-again");
    assert_eq!(hash_of(&again), expected);
}

/// The files `rayfarm certs --node-dir` gives one node, and nothing else.
fn listing(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .expect("node directory")
        .map(|e| e.expect("entry").file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

#[test]
fn node_directories_hold_one_nodes_credentials_and_probes_check_the_nodes_own_name() {
    let root = tempfile::tempdir().expect("temp dir");
    let (out, nodes) = (root.path().join("certs"), root.path().join("nodes"));
    rayfarm_ok(&[
        "certs",
        "--out",
        s(&out),
        "--hosts",
        "coordinator",
        "--with-secrets",
        "--node",
        "w-x,w-y",
        "--node-dir",
        s(&nodes),
    ]);
    let files = ["ca.pem", "cluster-secret", "node-key.pem", "node.pem"];
    for id in ["w-x", "w-y"] {
        let dir = nodes.join(id);
        assert_eq!(listing(&dir), files, "{id}'s directory");
        for shared in ["ca.pem", "cluster-secret"] {
            assert_eq!(
                std::fs::read(dir.join(shared)).expect("copy"),
                std::fs::read(out.join(shared)).expect("original"),
                "{id}'s {shared}"
            );
        }
        use std::os::unix::fs::PermissionsExt;
        for secret in ["node-key.pem", "cluster-secret"] {
            let mode = std::fs::metadata(dir.join(secret))
                .expect("mode")
                .permissions()
                .mode();
            assert_eq!(mode & 0o777, 0o600, "{id}'s {secret}");
        }
    }
    assert_ne!(
        std::fs::read(nodes.join("w-x/node-key.pem")).expect("key"),
        std::fs::read(nodes.join("w-y/node-key.pem")).expect("key"),
    );
    assert!(
        !out.join("node-w-x-key.pem").exists(),
        "a node key left in --out"
    );
    // Run again, the keys stay as they are; a directory that is a symlink is refused.
    let key = std::fs::read(nodes.join("w-x/node-key.pem")).expect("key");
    let again = [
        "certs",
        "--out",
        s(&out),
        "--hosts",
        "coordinator",
        "--with-secrets",
        "--node",
        "w-x,w-y",
        "--node-dir",
        s(&nodes),
    ];
    rayfarm_ok(&[&again[..], &["--if-missing"]].concat());
    assert_eq!(
        std::fs::read(nodes.join("w-x/node-key.pem")).expect("key"),
        key
    );
    let elsewhere = root.path().join("elsewhere");
    std::fs::create_dir(&elsewhere).expect("dir");
    std::os::unix::fs::symlink(&elsewhere, nodes.join("w-z")).expect("symlink");
    let err = rayfarm_err(&[
        "certs",
        "--out",
        s(&out),
        "--node",
        "w-z",
        "--node-dir",
        s(&nodes),
    ]);
    assert!(err.contains("is a symbolic link"), "{err}");
    assert_eq!(listing(&elsewhere), Vec::<String>::new());

    // A server whose certificate names only its node (w-x), probed at 127.0.0.1 as a
    // container probes itself: `--own-name` checks for the name of the probe's own
    // certificate, which is the server's.
    let (x, y) = (nodes.join("w-x"), nodes.join("w-y"));
    let opts = ClusterOpts {
        coordinator_args: [
            "--tls-cert",
            s(&x.join("node.pem")),
            "--tls-key",
            s(&x.join("node-key.pem")),
            "--tls-client-ca",
            s(&x.join("ca.pem")),
        ]
        .iter()
        .map(|a| a.to_string())
        .collect(),
        client_env: vec![
            ("RAYFARM_TLS_CA".into(), s(&x.join("ca.pem")).into()),
            ("RAYFARM_TLS_DOMAIN".into(), "w-x".into()),
            ("RAYFARM_TLS_CERT".into(), s(&x.join("node.pem")).into()),
            ("RAYFARM_TLS_KEY".into(), s(&x.join("node-key.pem")).into()),
        ],
        https: true,
        ..ClusterOpts::default()
    };
    let cluster = Cluster::start_with(root.path(), None, &opts, &[]);
    let addr = cluster.coordinator_url().to_string();
    let probe = |node: &Path, own_name: bool| {
        let (ca, cert, key) = (
            x.join("ca.pem"),
            node.join("node.pem"),
            node.join("node-key.pem"),
        );
        let mut args = vec!["health", addr.as_str(), "--tls-ca", s(&ca)];
        args.extend(["--tls-cert", s(&cert), "--tls-key", s(&key)]);
        if own_name {
            args.push("--own-name");
        }
        cluster.rayfarm_as(&[], &args).status.success()
    };
    assert!(probe(&x, true), "w-x probing itself with --own-name");
    assert!(
        !probe(&x, false),
        "127.0.0.1 is not a name of w-x's certificate"
    );
    assert!(!probe(&y, true), "w-y's name is not the server's");
}
