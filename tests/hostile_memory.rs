//! Attacks on real processes that would hold memory: oversized fields, thousands of unfinished
//! HTTP/2 streams and result fetches that are never read. Each time a legitimate client keeps
//! being served and the coordinator's memory (VmRSS) stays within a stated bound.

use std::time::Duration;

use rayfarm_node::proto;
use rayfarm_node::proto::job_service_client::JobServiceClient;
use rayfarm_tests::hostile::{PREFACE_BYTES, frame, hostile_connect, hpack_literal, runtime};
use rayfarm_tests::{
    Cluster, WorkerOpts, hash_of, local_hash, prepare_nbody, proc_status_bytes, s, stats_field,
    submit_wait, wait_until,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

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
    let mut out = PREFACE_BYTES.to_vec();
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
