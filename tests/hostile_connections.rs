//! Attacks on real processes by hostile connections: a server reachable from other machines
//! only with protection (or --insecure); silent connections that would hold every descriptor;
//! idle HTTP/2 connections that would be kept forever. Each time a legitimate client keeps
//! being served.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use rayfarm_tests::hostile::{PREFACE_BYTES, frame, hostile_connect, runtime};
use rayfarm_tests::{
    Cluster, ClusterOpts, WorkerOpts, bin, certs, hash_of, local_hash, prepare_nbody, s,
    submit_wait, wait_child,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

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
    let mut hello = PREFACE_BYTES.to_vec();
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
