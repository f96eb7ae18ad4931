//! A cluster with security on (TLS on every link, the cluster secret, user tokens), made of
//! real processes on loopback with files from `rayfarm certs`: strangers are refused with
//! precise reasons (a worker without the secret cannot join, a peer push without it is
//! refused, a client without a token gets UNAUTHENTICATED, a plain-text client fails
//! clearly), and the cluster still renders the image of `render --local` to the bit.

use std::time::Duration;

use rayfarm_node::proto;
use rayfarm_node::proto::peer_service_client::PeerServiceClient;
use rayfarm_node::security::{ClusterSecret, ConnectTlsArgs, Credential, endpoint};
use rayfarm_tests::{
    CertFiles as Files, Cluster, ClusterOpts, WorkerOpts, certs, domain_bytes, hash_of, local_hash,
    prepare_nbody, rayfarm_ok, s, stats_field,
};

const FRAME: [&str; 8] = [
    "--width", "96", "--height", "72", "--spp", "2", "--depth", "3",
];

/// Runs a `rayfarm` that must fail; returns its stderr.
fn fails(out: std::process::Output, what: &str) -> String {
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(
        !out.status.success(),
        "{what} should have failed; stdout:\n{}",
        String::from_utf8_lossy(&out.stdout)
    );
    stderr
}

fn registered_workers(cluster: &Cluster) -> usize {
    cluster.status()["workers"]
        .as_array()
        .expect("workers in status")
        .len()
}

#[test]
fn a_secured_cluster_refuses_strangers_and_renders_the_local_image() {
    let root = tempfile::tempdir().expect("temp dir");
    let f = certs(&root.path().join("certs"));
    let scene = prepare_nbody(root.path(), "nb", 30_000, 8);
    let expected = local_hash(&scene, &FRAME);

    let server_tls = [
        "--tls-cert",
        s(&f.cert),
        "--tls-key",
        s(&f.key),
        "--cluster-secret-file",
        s(&f.secret),
    ];
    let mut coordinator_args: Vec<String> = server_tls.iter().map(|a| a.to_string()).collect();
    coordinator_args.extend(["--user-tokens-file".into(), s(&f.tokens).into()]);
    let opts = ClusterOpts {
        coordinator_args,
        client_env: vec![
            ("RAYFARM_TLS_CA".into(), s(&f.ca).into()),
            ("RAYFARM_TOKEN_FILE".into(), s(&f.tokens).into()),
        ],
        https: true,
        ..ClusterOpts::default()
    };
    // Caches of two domains: rays must cross between the workers, over TLS with the secret.
    let member = WorkerOpts::cache(2 * domain_bytes(&scene).1)
        .args(&server_tls)
        .args(&["--tls-ca", s(&f.ca)]);
    let mut cluster =
        Cluster::start_with(root.path(), Some("nb"), &opts, &[member.clone(), member]);

    // A worker without the secret (TLS right) is refused, exits, and says why.
    let tls_only = WorkerOpts::default().args(&[
        "--tls-cert",
        s(&f.cert),
        "--tls-key",
        s(&f.key),
        "--tls-ca",
        s(&f.ca),
    ]);
    let stranger = cluster.add_worker(&tls_only);
    let status = cluster.wait_worker_exit(stranger, Duration::from_secs(30));
    assert!(
        !status.success(),
        "a worker without the secret exited with {status}"
    );
    let log = cluster.worker_log(stranger);
    assert!(
        log.contains("the coordinator refused this worker: no cluster secret"),
        "{log}"
    );
    // ... and so is one with a wrong secret, which the refusal does not echo.
    let wrong = root.path().join("wrong-secret");
    std::fs::write(&wrong, "not-the-secret\n").expect("write");
    let impostor =
        cluster.add_worker(&tls_only.clone().args(&["--cluster-secret-file", s(&wrong)]));
    let status = cluster.wait_worker_exit(impostor, Duration::from_secs(30));
    assert!(!status.success());
    let log = cluster.worker_log(impostor);
    assert!(log.contains("wrong cluster secret"), "{log}");
    assert!(
        !log.contains("not-the-secret"),
        "the secret was echoed: {log}"
    );
    assert_eq!(registered_workers(&cluster), 2, "a stranger was registered");

    // A peer push without the secret is refused by a member; with it the stream opens.
    push_to_peer(cluster.worker_addr(0), &f);

    // Job API clients: no token, a wrong token, no TLS, a TLS client that trusts another CA.
    let ca = s(&f.ca);
    let err = fails(
        cluster.rayfarm_as(&[("RAYFARM_TLS_CA", ca)], &["jobs"]),
        "jobs without a token",
    );
    assert!(err.contains("UNAUTHENTICATED: no user token"), "{err}");
    let err = fails(
        cluster.rayfarm_as(
            &[("RAYFARM_TLS_CA", ca), ("RAYFARM_TOKEN", "guess")],
            &["submit"],
        ),
        "submit with a wrong token",
    );
    assert!(err.contains("UNAUTHENTICATED: unknown user token"), "{err}");
    let plain = cluster.coordinator_url().replace("https://", "http://");
    let err = fails(
        cluster.rayfarm_as(
            &[
                ("RAYFARM_COORDINATOR", &plain),
                ("RAYFARM_TOKEN_FILE", s(&f.tokens)),
            ],
            &["status"],
        ),
        "status in plain text against TLS",
    );
    assert!(err.contains("is unreachable"), "{err}");
    assert!(err.contains("--tls-ca"), "no hint at TLS: {err}");
    let other = certs(&root.path().join("other-ca"));
    let err = fails(
        cluster.rayfarm_as(
            &[
                ("RAYFARM_TLS_CA", s(&other.ca)),
                ("RAYFARM_TOKEN_FILE", s(&f.tokens)),
            ],
            &["status"],
        ),
        "status trusting another CA",
    );
    assert!(err.contains("is unreachable"), "{err}");
    assert!(err.to_lowercase().contains("certificate"), "{err}");
    // Health needs TLS but no credentials.
    let coordinator_addr = cluster
        .coordinator_url()
        .trim_start_matches("https://")
        .to_string();
    let out = cluster.rayfarm_as(&[], &["health", &coordinator_addr, "--tls-ca", ca]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    // After all that, the members render the local image, moving rays between them.
    let json = root.path().join("secure.json");
    let png = root.path().join("secure.png");
    let mut args = vec!["submit", "--wait", "--quiet", "--output", s(&png)];
    args.extend(["--stats-json", s(&json)]);
    args.extend_from_slice(&FRAME);
    cluster.rayfarm_ok(&args);
    assert_eq!(hash_of(&json), expected);
    assert_eq!(stats_field(&json, "/workers"), 2);
    let migrated = stats_field(&json, "/rays_migrated").as_u64().unwrap_or(0);
    assert!(migrated > 0, "no rays crossed between the workers");
    assert!(
        cluster.coordinator_log().contains("user=admin"),
        "the submitting user is not logged"
    );

    // `rayfarm bench` measures a secured cluster with the same CA and token.
    let csv = root.path().join("bench.csv");
    let url = cluster.coordinator_url().to_string();
    cluster.rayfarm_ok(&[
        "bench",
        "--coordinator",
        &url,
        "--scene",
        s(&scene),
        "--schedules",
        "dynamic",
        "--repeats",
        "1",
        "--width",
        "64",
        "--height",
        "48",
        "--spp",
        "1",
        "--csv",
        s(&csv),
    ]);
    let rows = std::fs::read_to_string(&csv).expect("bench CSV");
    assert_eq!(rows.lines().count(), 2, "{rows}");
}

/// Opens a peer stream to the worker at `addr`: refused without the secret
/// (UNAUTHENTICATED), accepted with it. Sends no bundle, so the worker's frame is untouched.
fn push_to_peer(addr: &str, f: &Files) {
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    runtime.block_on(async {
        let tls = ConnectTlsArgs {
            tls_ca: Some(f.ca.clone()),
            tls_domain: None,
        }
        .client_config(None)
        .expect("tls config");
        let channel = endpoint(addr, tls.as_ref())
            .expect("endpoint")
            .connect()
            .await
            .expect("connect to the worker over TLS");
        let bundle = proto::PeerBundle {
            protocol_version: proto::PROTOCOL_VERSION,
            sender: "stranger".into(),
            job_id: "none".into(),
            ..Default::default()
        };
        let refused = PeerServiceClient::new(channel.clone())
            .exchange_bundles(tokio_stream::iter(vec![bundle]))
            .await
            .expect_err("a peer push without the secret was accepted");
        assert_eq!(refused.code(), tonic::Code::Unauthenticated, "{refused:?}");
        assert!(
            refused.message().contains("no cluster secret"),
            "{refused:?}"
        );
        let secret = ClusterSecret::from_file(&f.secret).expect("secret");
        let mut member =
            PeerServiceClient::with_interceptor(channel, Credential::secret(Some(&secret)));
        member
            .exchange_bundles(tokio_stream::iter(Vec::<proto::PeerBundle>::new()))
            .await
            .expect("a peer stream with the secret is accepted");
    });
}

#[test]
fn mutual_tls_refuses_clients_without_a_certificate() {
    let root = tempfile::tempdir().expect("temp dir");
    let f = certs(&root.path().join("certs"));
    let ca = s(&f.ca);
    let opts = ClusterOpts {
        coordinator_args: [
            "--tls-cert",
            s(&f.cert),
            "--tls-key",
            s(&f.key),
            "--tls-client-ca",
            ca,
        ]
        .iter()
        .map(|a| a.to_string())
        .collect(),
        client_env: vec![
            ("RAYFARM_TLS_CA".into(), ca.into()),
            ("RAYFARM_TLS_CERT".into(), s(&f.cert).into()),
            ("RAYFARM_TLS_KEY".into(), s(&f.key).into()),
        ],
        https: true,
        ..ClusterOpts::default()
    };
    let cluster = Cluster::start_with(root.path(), None, &opts, &[]);
    // With its certificate the client is served (no tokens configured here).
    assert_eq!(registered_workers(&cluster), 0);
    let err = fails(
        cluster.rayfarm_as(&[("RAYFARM_TLS_CA", ca)], &["status"]),
        "status without a client certificate",
    );
    assert!(err.contains("is unreachable"), "{err}");
    // `rayfarm health` presents a certificate too, so probes work against mutual TLS.
    let addr = cluster.coordinator_url().to_string();
    let tls = ["--tls-ca", ca, "--tls-domain", "localhost"];
    let mut with_cert = vec!["health", &addr];
    with_cert.extend_from_slice(&tls);
    with_cert.extend(["--tls-cert", s(&f.cert), "--tls-key", s(&f.key)]);
    let out = cluster.rayfarm_as(&[], &with_cert);
    assert!(
        out.status.success(),
        "{}{}{with_cert:?}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let mut without = vec!["health", &addr];
    without.extend_from_slice(&tls);
    fails(
        cluster.rayfarm_as(&[], &without),
        "health without a client certificate",
    );
}

#[test]
fn the_demo_ignores_a_real_clusters_credentials_in_the_environment() {
    let root = tempfile::tempdir().expect("temp dir");
    let f = certs(&root.path().join("certs"));
    let demo = root.path().join("demo");
    // A shell set up for a secured cluster: the demo's local cluster must not turn security
    // on in its children while its own client talks plain text.
    let out = std::process::Command::new(rayfarm_tests::bin("rayfarm"))
        .args([
            "demo",
            "--dir",
            s(&demo),
            "--triangles",
            "20000",
            "--domains",
            "8",
        ])
        .args([
            "--width",
            "64",
            "--height",
            "48",
            "--spp",
            "1",
            "--workers",
            "2",
        ])
        .env("RUST_LOG", "warn")
        .env("RAYFARM_TLS_CERT", &f.cert)
        .env("RAYFARM_TLS_KEY", &f.key)
        .env("RAYFARM_TLS_CA", &f.ca)
        .env("RAYFARM_CLUSTER_SECRET_FILE", &f.secret)
        .env("RAYFARM_USER_TOKENS_FILE", &f.tokens)
        .output()
        .expect("run rayfarm demo");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(stats_field(&demo.join("demo-stats.json"), "/workers"), 2);
}

#[test]
fn certs_keeps_existing_credentials_and_refuses_bad_names() {
    let root = tempfile::tempdir().expect("temp dir");
    let dir = root.path().join("certs");
    let f = certs(&dir);
    let secret = std::fs::read(&f.secret).expect("secret");
    let tokens = std::fs::read_to_string(&f.tokens).expect("tokens");
    assert!(tokens.contains(" admin"), "{tokens}");
    // Overwriting a cluster's credentials by accident is refused ...
    let err = rayfarm_tests::rayfarm_err(&["certs", "--out", s(&dir), "--hosts", "localhost"]);
    assert!(err.contains("already holds ca.pem"), "{err}");
    assert!(err.contains("--if-missing"), "{err}");
    // ... --if-missing never overwrites a key: half a TLS set is refused ...
    let key = std::fs::read(&f.key).expect("key");
    std::fs::remove_file(&f.cert).expect("remove");
    let args = ["certs", "--out", s(&dir), "--hosts", "localhost"];
    let if_missing = [&args[..], &["--with-secrets", "--if-missing"]].concat();
    let err = rayfarm_tests::rayfarm_err(&if_missing);
    assert!(err.contains("not the whole set"), "{err}");
    assert_eq!(
        std::fs::read(&f.key).expect("key"),
        key,
        "the key was overwritten"
    );
    // ... a missing set is written anew, keys 0600, and the secret is kept ...
    std::fs::remove_file(&f.ca).expect("remove");
    std::fs::remove_file(&f.key).expect("remove");
    let ca_key = dir.join("ca-key.pem");
    std::fs::remove_file(&ca_key).expect("remove");
    rayfarm_ok(&if_missing);
    assert!(f.cert.exists());
    assert_eq!(std::fs::read(&f.secret).expect("secret"), secret);
    use std::os::unix::fs::PermissionsExt;
    for file in [&f.key, &ca_key, &f.secret, &f.tokens] {
        let mode = std::fs::metadata(file).expect("mode").permissions().mode();
        assert_eq!(mode & 0o777, 0o600, "{}", file.display());
    }
    // ... and a symlink, even a dangling one, is never written through.
    let elsewhere = root.path().join("elsewhere-key.pem");
    for file in [&f.ca, &ca_key, &f.cert, &f.key] {
        std::fs::remove_file(file).expect("remove");
    }
    std::os::unix::fs::symlink(&elsewhere, &f.key).expect("symlink");
    let err = rayfarm_tests::rayfarm_err(&if_missing);
    assert!(err.contains("symbolic link"), "{err}");
    assert!(
        !elsewhere.exists(),
        "the key was written through the symlink"
    );
    let err = rayfarm_tests::rayfarm_err(&[
        "certs",
        "--out",
        s(&root.path().join("bad")),
        "--hosts",
        "not a name",
    ]);
    assert!(err.contains("--hosts"), "{err}");
}
