//! Attacks on real processes by hostile clients written here: a server reachable from other
//! machines only with protection (or --insecure); silent connections that would hold every
//! descriptor; oversized fields, thousands of unfinished HTTP/2 streams and result fetches
//! that are never read, which would hold memory. Each time a legitimate client keeps being served and the coordinator's memory
//! (VmRSS) stays within a stated bound.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use rayfarm_node::proto;
use rayfarm_node::proto::job_service_client::JobServiceClient;
use rayfarm_tests::{
    Cluster, ClusterOpts, WorkerOpts, bin, certs, hash_of, local_hash, prepare_nbody,
    proc_status_bytes, s, stats_field, submit_wait, wait_child, wait_until,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};

/// Where the hostile connections come from: another loopback address than the legitimate
/// client's 127.0.0.1, as an attacker on another machine would.
const HOSTILE_IP: [u8; 4] = [127, 0, 0, 2];

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
}

/// A connection from [`HOSTILE_IP`] to `addr`.
async fn hostile_connect(addr: &str) -> std::io::Result<TcpStream> {
    let socket = TcpSocket::new_v4()?;
    socket.bind((std::net::Ipv4Addr::from(HOSTILE_IP), 0).into())?;
    socket.connect(addr.parse().unwrap()).await
}

#[test]
fn only_loopback_is_served_without_protection_unless_insecure() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let coordinator = |extra: &[&str]| {
        let mut cmd = Command::new(bin("rayfarm-coordinator"));
        cmd.args(["--listen", "0.0.0.0:0", "--data-dir", s(&data)])
            .args(extra)
            .env("NO_COLOR", "1")
            .env("RUST_LOG", "warn")
            .stdin(Stdio::null());
        cmd
    };
    let out = coordinator(&[]).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "served 0.0.0.0 without protection");
    for word in [
        "0.0.0.0",
        "TLS",
        "cluster secret",
        "user tokens",
        "--insecure",
    ] {
        assert!(err.contains(word), "{word:?} missing from: {err}");
    }
    let out = Command::new(bin("rayfarm-worker"))
        .args(["--listen", "0.0.0.0:0"])
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "a worker served 0.0.0.0 unprotected");
    assert!(err.contains("--insecure"), "{err}");

    // With --insecure it serves, and says so.
    let log = dir.path().join("insecure.log");
    let mut child = coordinator(&["--insecure"])
        .env("RUST_LOG", "info")
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufRead::read_line(
        &mut std::io::BufReader::new(child.stdout.take().unwrap()),
        &mut line,
    )
    .unwrap();
    let _ = child.kill();
    wait_child(&mut child, "insecure coordinator", Duration::from_secs(10));
    assert!(line.starts_with("listening on 0.0.0.0:"), "{line:?}");
    let log = std::fs::read_to_string(&log).unwrap();
    assert!(log.contains("--insecure: serving without"), "{log}");
}

/// Holds `n` hostile connections that never send a byte; returns them and how many the
/// coordinator closed at once (past its per-peer cap).
async fn hold_silent(addr: &str, n: usize) -> (Vec<TcpStream>, usize) {
    let mut held = Vec::new();
    for _ in 0..n {
        match hostile_connect(addr).await {
            Ok(c) => held.push(c),
            Err(e) => panic!("hostile connect failed: {e}"),
        }
    }
    // A connection past the cap is closed by the server: reading it ends at once.
    let mut closed = 0;
    let mut open = Vec::new();
    for mut c in held {
        let mut b = [0u8; 1];
        match tokio::time::timeout(Duration::from_millis(20), c.read(&mut b)).await {
            Ok(_) => closed += 1,
            Err(_) => open.push(c),
        }
    }
    (open, closed)
}

/// Waits until every connection in `held` is closed by the server.
async fn all_closed(held: Vec<TcpStream>, limit: Duration) {
    let start = Instant::now();
    for mut c in held {
        let mut b = [0u8; 64];
        let left = limit.saturating_sub(start.elapsed());
        match tokio::time::timeout(left, c.read(&mut b)).await {
            Ok(Ok(0)) | Ok(Err(_)) => {}
            Ok(Ok(_)) => panic!("the server sent bytes to a silent connection"),
            Err(_) => panic!("a silent connection was still open after {limit:?}"),
        }
    }
}

#[test]
fn silent_connections_do_not_starve_a_legitimate_client_under_a_low_descriptor_limit() {
    let rt = runtime();
    let tls_dir = tempfile::tempdir().unwrap();
    let f = certs(tls_dir.path());
    let scenes = tempfile::tempdir().unwrap();
    // Long enough that 300 connects finish before the first deadline on a loaded machine.
    let limits = ["--handshake-timeout-ms", "4000"];
    let plain = ClusterOpts {
        coordinator_args: limits.iter().map(|a| a.to_string()).collect(),
        coordinator_descriptor_limit: Some(256),
        ..ClusterOpts::default()
    };
    let mut tls_args: Vec<String> = [
        "--tls-cert",
        s(&f.cert),
        "--tls-key",
        s(&f.key),
        "--cluster-secret-file",
        s(&f.secret),
        "--user-tokens-file",
        s(&f.tokens),
    ]
    .iter()
    .map(|a| a.to_string())
    .collect();
    tls_args.extend(limits.iter().map(|a| a.to_string()));
    let tls = ClusterOpts {
        coordinator_args: tls_args,
        client_env: vec![
            ("RAYFARM_TLS_CA".into(), s(&f.ca).into()),
            ("RAYFARM_TOKEN_FILE".into(), s(&f.tokens).into()),
        ],
        https: true,
        coordinator_descriptor_limit: Some(256),
        ..ClusterOpts::default()
    };
    for (name, opts) in [("plain text", plain), ("TLS", tls)] {
        let cluster = Cluster::start_with(scenes.path(), None, &opts, &[]);
        // More silent connections than the coordinator has descriptors.
        let connected = Instant::now();
        let (held, closed) = rt.block_on(hold_silent(cluster.coordinator_addr(), 300));
        assert_eq!(
            held.len(),
            64,
            "{name}: the per-peer cap (64) holds, {closed} closed"
        );
        // While they are held, a client at another address is served, in time.
        for _ in 0..3 {
            let start = Instant::now();
            cluster.rayfarm_ok(&["jobs"]);
            assert!(
                start.elapsed() < Duration::from_secs(5),
                "{name}: jobs took {:?}",
                start.elapsed()
            );
        }
        // And the silent ones are closed by the handshake deadline.
        rt.block_on(all_closed(held, Duration::from_secs(15)));
        eprintln!(
            "{name}: 300 silent connections, {closed} closed at once, 64 held, all found closed \
             {:?} after connecting (handshake deadline 1.5 s; the client calls came between)",
            connected.elapsed()
        );
        cluster.rayfarm_ok(&["jobs"]);
    }
}

/// A hostile HTTP/2 client from [`HOSTILE_IP`]: sends the preface and SETTINGS, then opens
/// no stream but answers what a live client answers (SETTINGS and PING acknowledgements), so
/// keepalives never close it. Returns how long the connection lasted, or `None` if it was
/// still open after `limit`.
async fn idle_h2(addr: &str, limit: Duration) -> Option<Duration> {
    let mut conn = hostile_connect(addr).await.unwrap();
    let start = Instant::now();
    let mut hello = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n".to_vec();
    frame(&mut hello, 0x4, 0, 0, &[]);
    conn.write_all(&hello).await.ok()?;
    let answer = async {
        let mut header = [0u8; 9];
        loop {
            if conn.read_exact(&mut header).await.is_err() {
                return start.elapsed();
            }
            let len = u32::from_be_bytes([0, header[0], header[1], header[2]]) as usize;
            let mut payload = vec![0u8; len];
            if conn.read_exact(&mut payload).await.is_err() {
                return start.elapsed();
            }
            let mut reply = Vec::new();
            match (header[3], header[4] & 1) {
                (0x4, 0) => frame(&mut reply, 0x4, 1, 0, &[]), // SETTINGS -> ACK
                (0x6, 0) => frame(&mut reply, 0x6, 1, 0, &payload), // PING -> ACK
                _ => {}
            }
            if !reply.is_empty() && conn.write_all(&reply).await.is_err() {
                return start.elapsed();
            }
        }
    };
    tokio::time::timeout(limit, answer).await.ok()
}

#[test]
fn idle_http2_connections_are_closed_and_streams_and_clients_go_on() {
    let rt = runtime();
    let root = tempfile::tempdir().unwrap();
    let scene = prepare_nbody(root.path(), "nb", 2000, 2);
    // Long-lived streams (the worker's control stream) outlast the idle timeout many times.
    let opts = ClusterOpts {
        coordinator_args: vec!["--idle-timeout-ms".into(), "1500".into()],
        coordinator_descriptor_limit: Some(256),
        ..ClusterOpts::default()
    };
    let cluster = Cluster::start_with(root.path(), Some("nb"), &opts, &[WorkerOpts::default()]);
    // As many idle connections as one peer may hold, each past its handshake and answering
    // pings: without an idle timeout they would be held for as long as they like.
    let addr = cluster.coordinator_addr().to_string();
    let idle: Vec<_> = (0..64)
        .map(|_| {
            let addr = addr.clone();
            rt.spawn(async move { idle_h2(&addr, Duration::from_secs(20)).await })
        })
        .collect();
    // Meanwhile a client at another address is served.
    for _ in 0..3 {
        cluster.rayfarm_ok(&["jobs"]);
    }
    let lasted: Vec<Duration> = idle
        .into_iter()
        .map(|h| {
            rt.block_on(h)
                .unwrap()
                .expect("an idle connection was still open after 20 s")
        })
        .collect();
    let (shortest, longest) = (lasted.iter().min().unwrap(), lasted.iter().max().unwrap());
    // Closed by the idle timeout, not at once.
    assert!(*shortest >= Duration::from_millis(1400), "{shortest:?}");
    eprintln!("64 idle HTTP/2 connections closed after {shortest:?} to {longest:?} (idle 1.5 s)");
    // The worker's control stream outlived them: it renders the frame, and the image is
    // the one `render --local` makes.
    let frame = ["--width", "64", "--height", "48", "--spp", "2"];
    let stats = submit_wait(&cluster, &frame, "after-idle");
    assert_eq!(hash_of(&stats), local_hash(&scene, &frame));
    let status = cluster.status();
    assert_eq!(status["workers"].as_array().unwrap().len(), 1, "{status}");
}

/// The HPACK encoding of one header as a literal with a literal name (RFC 7541, 6.2.2).
fn hpack_literal(out: &mut Vec<u8>, name: &str, value: &str) {
    assert!(name.len() < 127 && value.len() < 127);
    out.push(0x00);
    out.push(name.len() as u8);
    out.extend_from_slice(name.as_bytes());
    out.push(value.len() as u8);
    out.extend_from_slice(value.as_bytes());
}

/// An HTTP/2 frame header.
fn frame(out: &mut Vec<u8>, kind: u8, flags: u8, stream: u32, payload: &[u8]) {
    let len = payload.len() as u32;
    out.extend_from_slice(&len.to_be_bytes()[1..]);
    out.push(kind);
    out.push(flags);
    out.extend_from_slice(&stream.to_be_bytes());
    out.extend_from_slice(payload);
}

/// Opens `streams` CancelJob requests on one connection, each with headers and no body (never
/// finished), reading everything the server sends; returns the number of RST_STREAM and
/// GOAWAY frames it answered with.
async fn unfinished_streams(addr: &str, streams: u32) -> (u32, u32) {
    let mut conn = hostile_connect(addr).await.unwrap();
    let mut headers = Vec::new();
    hpack_literal(&mut headers, ":method", "POST");
    hpack_literal(&mut headers, ":scheme", "http");
    hpack_literal(&mut headers, ":path", "/rayfarm.v1.JobService/CancelJob");
    hpack_literal(&mut headers, ":authority", "localhost");
    hpack_literal(&mut headers, "content-type", "application/grpc");
    hpack_literal(&mut headers, "te", "trailers");
    let mut out = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n".to_vec();
    frame(&mut out, 0x4, 0, 0, &[]); // SETTINGS
    for i in 0..streams {
        // HEADERS with END_HEADERS, without END_STREAM.
        frame(&mut out, 0x1, 0x4, 1 + 2 * i, &headers);
    }
    let (mut rd, mut wr) = conn.split();
    let read = async {
        let (mut resets, mut goaways) = (0, 0);
        let mut header = [0u8; 9];
        loop {
            let got = tokio::time::timeout(Duration::from_secs(3), rd.read_exact(&mut header));
            match got.await {
                Ok(Ok(_)) => {}
                _ => break,
            }
            let len = u32::from_be_bytes([0, header[0], header[1], header[2]]) as usize;
            let mut payload = vec![0u8; len];
            if rd.read_exact(&mut payload).await.is_err() {
                break;
            }
            match header[3] {
                0x3 => resets += 1,
                0x7 => goaways += 1,
                _ => {}
            }
        }
        (resets, goaways)
    };
    let write = async {
        let _ = wr.write_all(&out).await;
    };
    let (counts, ()) = tokio::join!(read, write);
    counts
}

#[test]
fn oversized_fields_and_unfinished_streams_hold_no_memory() {
    let rt = runtime();
    let scenes = tempfile::tempdir().unwrap();
    let cluster = Cluster::start(scenes.path(), None, &[]);
    let url = cluster.coordinator_url().to_string();
    let before = cluster.coordinator_rss();
    let mut client = rt
        .block_on(JobServiceClient::connect(url.clone()))
        .unwrap()
        .max_encoding_message_size(usize::MAX);

    // A field a little too long: refused by its size, never echoed.
    let long = "x".repeat(1000);
    let e = rt
        .block_on(client.cancel_job(proto::CancelJobRequest {
            job_id: long.clone(),
        }))
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument, "{e}");
    assert!(e.message().contains("1000 bytes"), "{}", e.message());
    assert!(!e.message().contains("xxxx"), "{}", e.message());
    let spec = proto::JobSpec {
        scene: long.clone(),
        ..Default::default()
    };
    let e = rt
        .block_on(client.submit_job(proto::SubmitJobRequest { spec: Some(spec) }))
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument, "{e}");
    assert!(!e.message().contains("xxxx"), "{}", e.message());

    // Huge ones (three 64 MiB job ids, a 64 MiB scene name): refused before decoding.
    let huge = "y".repeat(64 << 20);
    for _ in 0..3 {
        let e = rt
            .block_on(client.cancel_job(proto::CancelJobRequest {
                job_id: huge.clone(),
            }))
            .unwrap_err();
        assert!(
            e.message().len() < 1000,
            "{} bytes of error",
            e.message().len()
        );
        assert!(!e.message().contains("yyyy"));
    }
    let spec = proto::JobSpec {
        scene: huge.clone(),
        ..Default::default()
    };
    let e = rt
        .block_on(client.submit_job(proto::SubmitJobRequest { spec: Some(spec) }))
        .unwrap_err();
    assert!(
        e.message().len() < 1000,
        "{} bytes of error",
        e.message().len()
    );
    let after_fields = cluster.coordinator_rss();

    // 10,000 streams opened and never finished on one connection.
    let (resets, goaways) = rt.block_on(unfinished_streams(cluster.coordinator_addr(), 10_000));
    let after_streams = cluster.coordinator_rss();
    // Everything past the stream cap is refused (or the connection ended).
    assert!(
        resets >= 10_000 - 64 || goaways > 0,
        "{resets} streams reset, {goaways} GOAWAY"
    );
    cluster.rayfarm_ok(&["jobs"]);
    let mib = |b: u64| b as f64 / (1 << 20) as f64;
    eprintln!(
        "coordinator VmRSS: {:.1} MiB at start, {:.1} MiB after oversized fields, {:.1} MiB \
         after 10,000 unfinished streams ({resets} reset, {goaways} GOAWAY)",
        mib(before),
        mib(after_fields),
        mib(after_streams)
    );
    // The bound: 64 MiB over the start (the requests themselves were 256 MiB and more).
    assert!(
        after_fields.max(after_streams) < before + (64 << 20),
        "VmRSS grew from {:.1} to {:.1} MiB",
        mib(before),
        mib(after_fields.max(after_streams))
    );
}

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

/// A FetchResultStream request as a gRPC message: `job_id` (field 1), EXR (field 2 = 2) and
/// 4 MiB chunks asked for (field 4), behind the 5-byte gRPC prefix.
fn fetch_request(job_id: &str) -> Vec<u8> {
    let mut msg = vec![0x0a, job_id.len() as u8];
    msg.extend_from_slice(job_id.as_bytes());
    msg.extend_from_slice(&[0x10, 2, 0x20, 0x80, 0x80, 0x80, 0x02]);
    let mut out = vec![0];
    out.extend_from_slice(&(msg.len() as u32).to_be_bytes());
    out.extend_from_slice(&msg);
    out
}

/// Opens `streams` result fetches of `job_id` on one connection from [`HOSTILE_IP`], with the
/// largest flow-control window (so the server may send all it likes), and never reads a byte.
async fn stalled_fetches(addr: &str, job_id: &str, streams: u32) -> TcpStream {
    let mut conn = hostile_connect(addr).await.unwrap();
    let mut headers = Vec::new();
    hpack_literal(&mut headers, ":method", "POST");
    hpack_literal(&mut headers, ":scheme", "http");
    hpack_literal(
        &mut headers,
        ":path",
        "/rayfarm.v1.JobService/FetchResultStream",
    );
    hpack_literal(&mut headers, ":authority", "localhost");
    hpack_literal(&mut headers, "content-type", "application/grpc");
    hpack_literal(&mut headers, "te", "trailers");
    let mut out = PREFACE_BYTES.to_vec();
    // SETTINGS_INITIAL_WINDOW_SIZE (0x4) = 2^31 - 1, and the connection's window as large.
    frame(&mut out, 0x4, 0, 0, &[0, 4, 0x7f, 0xff, 0xff, 0xff]);
    frame(&mut out, 0x8, 0, 0, &0x7fff_0000u32.to_be_bytes());
    for i in 0..streams {
        let stream = 1 + 2 * i;
        frame(&mut out, 0x1, 0x4, stream, &headers); // HEADERS, END_HEADERS
        frame(&mut out, 0x0, 0x1, stream, &fetch_request(job_id)); // DATA, END_STREAM
    }
    conn.write_all(&out).await.unwrap();
    conn
}

const PREFACE_BYTES: &[u8] = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n";

#[test]
fn readers_that_never_read_hold_bounded_memory_and_other_clients_still_fetch() {
    let rt = runtime();
    let root = tempfile::tempdir().unwrap();
    let scene = prepare_nbody(root.path(), "nb", 3000, 2);
    let frame_args = [
        "--width", "1024", "--height", "1024", "--spp", "1", "--depth", "0",
    ];
    let cluster = Cluster::start(root.path(), Some("nb"), &[WorkerOpts::cache(64 << 20)]);
    let stats = submit_wait(&cluster, &frame_args, "big");
    assert_eq!(hash_of(&stats), local_hash(&scene, &frame_args));
    let job = stats_field(&stats, "/job_id").as_str().unwrap().to_string();
    let exr = cluster.dir().join("big.exr");
    cluster.rayfarm_ok(&["fetch", &job, "-o", s(&exr)]);
    let expected = std::fs::read(&exr).unwrap();
    // Several times what the server lets one fetch hold, so every stalled fetch is full.
    assert!(expected.len() > 8 << 20, "{} bytes", expected.len());
    // Too large to return in one message: the unary call says to stream it.
    let unary = rt.block_on(async {
        let mut client = JobServiceClient::connect(cluster.coordinator_url().to_string())
            .await
            .unwrap();
        let req = proto::FetchResultRequest {
            job_id: job.clone(),
            format: proto::ImageFormat::Exr as i32,
        };
        client.fetch_result(req).await.unwrap_err()
    });
    assert_eq!(unary.code(), tonic::Code::FailedPrecondition, "{unary}");
    assert!(unary.message().contains("FetchResultStream"), "{unary}");
    let peak_before = proc_status_bytes(cluster.coordinator_pid(), "VmHWM:");

    // 40 fetches on 5 connections whose client never reads.
    let held: Vec<TcpStream> = rt.block_on(async {
        let mut held = Vec::new();
        for _ in 0..5 {
            held.push(stalled_fetches(cluster.coordinator_addr(), &job, 8).await);
        }
        held
    });
    // The server takes a few of them and refuses the rest (it logs each one it streams).
    wait_until(
        "the stalled fetches to start",
        Duration::from_secs(20),
        || {
            cluster
                .coordinator_log()
                .matches("streaming a result")
                .count()
                >= 2 + 4
        },
    );
    // A client at another address is still served, and gets the same bytes.
    let again = cluster.dir().join("again.exr");
    cluster.rayfarm_ok(&["fetch", &job, "-o", s(&again)]);
    assert_eq!(std::fs::read(&again).unwrap(), expected);
    let streamed = cluster
        .coordinator_log()
        .matches("streaming a result")
        .count();
    let peak_after = proc_status_bytes(cluster.coordinator_pid(), "VmHWM:");
    let mib = |b: u64| b as f64 / (1 << 20) as f64;
    eprintln!(
        "coordinator VmHWM {:.1} MiB before, {:.1} MiB with 40 stalled fetches of a {:.1} MiB \
         result ({} streamed in all)",
        mib(peak_before),
        mib(peak_after),
        mib(expected.len() as u64),
        streamed
    );
    // Three fetches by the CLI (`submit --wait` fetches its PNG), and four of the hostile
    // client's: the other 36 were refused.
    assert_eq!(streamed, 3 + 4, "{}", cluster.coordinator_log());
    assert!(
        peak_after < peak_before + (32 << 20),
        "VmHWM grew from {:.1} to {:.1} MiB",
        mib(peak_before),
        mib(peak_after)
    );

    // Closing the connections gives the slots back: a new stalled fetch from the same
    // address is streamed again.
    drop(held);
    let mut retries = Vec::new();
    wait_until(
        "the slots to be free again",
        Duration::from_secs(20),
        || {
            retries.push(rt.block_on(stalled_fetches(cluster.coordinator_addr(), &job, 1)));
            cluster
                .coordinator_log()
                .matches("streaming a result")
                .count()
                > streamed
        },
    );
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
