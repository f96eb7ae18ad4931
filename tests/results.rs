//! Results at any size: a 16384x16384 frame renders with the coordinator's memory bounded
//! (its film lives in a file, its images are encoded row by row) and equals `render --local`,
//! whose memory is bounded too; results are fetched as a stream that resumes where it broke.

use std::io::BufReader;
use std::path::Path;
use std::process::Command;
use std::time::Instant;

use rayfarm_node::proto::{self, job_service_client::JobServiceClient};
use rayfarm_tests::{
    Cluster, ClusterOpts, WorkerOpts, hash_of, local_hash, prepare_nbody, proc_status_bytes,
    rayfarm_ok, s, stats_field, submit_wait,
};

/// Decodes a PNG row by row; returns its size.
fn png_size_after_decoding(path: &Path) -> (u32, u32) {
    let file = std::fs::File::open(path).expect("open png");
    let mut reader = png::Decoder::new(BufReader::new(file))
        .read_info()
        .expect("png header");
    let (w, h) = (reader.info().width, reader.info().height);
    let mut rows = 0;
    while reader.next_row().expect("png row").is_some() {
        rows += 1;
    }
    assert_eq!(rows, h, "rows decoded");
    (w, h)
}

/// A frame of `size`x`size` pixels, as cheap as it gets: one sample, no bounces, the scene a
/// speck far from the camera (so nearly every ray sees only the sky, yet every pixel of every
/// tile carries a sum to the coordinator).
fn huge_frame(size: &str) -> [&str; 10] {
    [
        "--width",
        size,
        "--height",
        size,
        "--spp",
        "1",
        "--depth",
        "0",
        "--eye",
        "0.5,0.7,200",
    ]
}

/// The largest frame the API takes, 268 M camera rays twice (as cheap as they get). Measured
/// in two runs on this 2-core machine loaded by other builds: 140 and 297 s for `render
/// --local` (peak RSS 93 and 101 MiB), 268 and 249 s on the cluster (coordinator VmHWM 77 and
/// 76 MiB, worker peak RSS 152 and 155 MiB), 413 and 549 s for the whole test; 93 s on the
/// idle machine (CI).
#[test]
fn a_16k_frame_fits_in_512_mib_of_coordinator_and_equals_the_local_render() {
    huge_frame_fits("16384");
}

/// Renders a `size`x`size` frame locally and on a cluster: the same image, the coordinator's
/// VmHWM and `render --local`'s peak RSS under 512 MiB, both PNGs decode to the full size and
/// the coordinator's film file is gone afterwards.
fn huge_frame_fits(size: &str) {
    let frame = huge_frame(size);
    let side: u32 = size.parse().expect("size");
    let root = tempfile::tempdir().unwrap();
    let scene = prepare_nbody(root.path(), "speck", 2000, 2);
    let start = Instant::now();
    let out = tempfile::tempdir().unwrap();
    let (png, json) = (out.path().join("local.png"), out.path().join("local.json"));
    let mut args = vec![
        "render",
        "--local",
        "--scene",
        s(&scene),
        "--out",
        s(&png),
        "--stats-json",
        s(&json),
        "--quiet",
        "--threads",
        "2",
    ];
    args.extend_from_slice(&frame);
    rayfarm_ok(&args);
    let local = hash_of(&json);
    let local_rss = stats_field(&json, "/peak_rss_bytes").as_u64().unwrap();
    let local_secs = start.elapsed().as_secs_f64();

    let cluster = Cluster::start(
        root.path(),
        Some("speck"),
        &[WorkerOpts::cache(64 << 20).threads(2)],
    );
    let start = Instant::now();
    let stats = submit_wait(&cluster, &frame, "huge");
    let cluster_secs = start.elapsed().as_secs_f64();
    let coordinator_rss = proc_status_bytes(cluster.coordinator_pid(), "VmHWM:");
    let worker_rss = stats_field(&stats, "/per_worker/0/peak_rss_bytes")
        .as_u64()
        .unwrap();
    eprintln!(
        "{size}x{size}: render --local {local_secs:.0} s, peak RSS {} MiB; cluster \
         {cluster_secs:.0} s, coordinator VmHWM {} MiB, worker peak RSS {} MiB",
        local_rss >> 20,
        coordinator_rss >> 20,
        worker_rss >> 20
    );
    assert_eq!(hash_of(&stats), local, "cluster and local images differ");
    assert!(
        coordinator_rss < 512 << 20,
        "the coordinator peaked at {} MiB",
        coordinator_rss >> 20
    );
    assert!(
        local_rss < 512 << 20,
        "render --local peaked at {} MiB",
        local_rss >> 20
    );
    let fetched = cluster.dir().join("huge.png");
    assert_eq!(png_size_after_decoding(&fetched), (side, side));
    assert_eq!(png_size_after_decoding(&png), (side, side));
    // The film file goes once the images are written.
    let job = stats_field(&stats, "/job_id");
    let film = cluster
        .data_dir()
        .join("jobs")
        .join(job.as_str().unwrap())
        .join("film.bin");
    assert!(!film.exists(), "{} left behind", film.display());
}

/// Reads a streamed fetch of `job` from `offset`, stopping after `max_chunks` chunks; returns
/// the header (of the first chunk) and the bytes.
async fn fetch_part(
    url: &str,
    job: &str,
    offset: u64,
    max_chunks: usize,
) -> (proto::FetchResultHeader, Vec<u8>) {
    let mut client = JobServiceClient::connect(url.to_string()).await.unwrap();
    let req = proto::FetchResultStreamRequest {
        job_id: job.to_string(),
        format: proto::ImageFormat::Exr as i32,
        offset,
        chunk_bytes: 4096,
    };
    let mut stream = client.fetch_result_stream(req).await.unwrap().into_inner();
    let mut header = None;
    let mut bytes = Vec::new();
    for _ in 0..max_chunks {
        let Some(chunk) = stream.message().await.unwrap() else {
            break;
        };
        header = header.or(chunk.header);
        assert_eq!(chunk.offset, offset + bytes.len() as u64);
        bytes.extend_from_slice(&chunk.data);
    }
    (header.expect("the first chunk has the header"), bytes)
}

#[test]
fn a_fetch_interrupted_halfway_resumes_and_yields_the_same_bytes() {
    let root = tempfile::tempdir().unwrap();
    let scene = prepare_nbody(root.path(), "nb", 3000, 2);
    let frame = [
        "--width", "160", "--height", "120", "--spp", "2", "--depth", "2",
    ];
    let cluster = Cluster::start(root.path(), Some("nb"), &[WorkerOpts::cache(64 << 20)]);
    let stats = submit_wait(&cluster, &frame, "first");
    assert_eq!(hash_of(&stats), local_hash(&scene, &frame));
    let job = stats_field(&stats, "/job_id").as_str().unwrap().to_string();
    let whole = cluster.dir().join("whole.exr");
    cluster.rayfarm_ok(&["fetch", &job, "-o", s(&whole)]);
    let expected = std::fs::read(&whole).unwrap();
    assert!(expected.len() > 3 * 4096, "{} bytes", expected.len());

    // Over the API: half the chunks, the connection dropped, then the rest from that offset.
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let url = cluster.coordinator_url().to_string();
    let half = expected.len().div_ceil(4096) / 2;
    let (header, mut bytes) = runtime.block_on(fetch_part(&url, &job, 0, half));
    assert_eq!(bytes.len(), half * 4096);
    assert_eq!(header.total_bytes, expected.len() as u64);
    let (again, rest) = runtime.block_on(fetch_part(&url, &job, bytes.len() as u64, usize::MAX));
    bytes.extend_from_slice(&rest);
    assert_eq!(bytes, expected);
    let checksum = format!("{:016x}", xxhash_rust::xxh3::xxh3_64(&bytes));
    assert_eq!(
        (header.checksum.as_str(), again.checksum.as_str()),
        (checksum.as_str(), checksum.as_str())
    );

    // The CLI resumes after the bytes an interrupted fetch left in `<output>.part`.
    let out = cluster.dir().join("resumed.exr");
    let part = cluster.dir().join("resumed.exr.part");
    std::fs::write(&part, &expected[..expected.len() / 2]).unwrap();
    cluster.rayfarm_ok(&["fetch", &job, "-o", s(&out)]);
    assert_eq!(std::fs::read(&out).unwrap(), expected);
    assert!(!part.exists());
    // Bytes that are not the result's are caught by the checksum, and removed.
    let mut wrong = expected[..expected.len() / 2].to_vec();
    wrong[100] ^= 0xff;
    std::fs::write(&part, &wrong).unwrap();
    let failed = cluster.rayfarm(&["fetch", &job, "-o", s(&out)]);
    let stderr = String::from_utf8_lossy(&failed.stderr);
    assert!(
        !failed.status.success() && stderr.contains("checksum"),
        "{stderr}"
    );
    assert!(!part.exists());
    // Past the end is refused.
    let past = runtime.block_on(async {
        let mut client = JobServiceClient::connect(url.clone()).await.unwrap();
        let req = proto::FetchResultStreamRequest {
            job_id: job.clone(),
            format: proto::ImageFormat::Png as i32,
            offset: u64::MAX,
            chunk_bytes: 0,
        };
        client
            .fetch_result_stream(req)
            .await
            .err()
            .map(|e| e.code())
    });
    assert_eq!(past, Some(tonic::Code::OutOfRange));
}

#[test]
fn under_a_memory_cap_a_job_past_the_limits_is_refused_at_submit_and_the_next_renders() {
    let root = tempfile::tempdir().unwrap();
    let scene = prepare_nbody(root.path(), "nb", 3000, 2);
    let opts = ClusterOpts {
        coordinator_args: vec!["--max-frame-bytes".into(), "64MiB".into()],
        ..ClusterOpts::default()
    };
    let cluster = Cluster::start_with(
        root.path(),
        Some("nb"),
        &opts,
        &[WorkerOpts::cache(64 << 20)],
    );
    // The cap: 256 MiB of address space beyond what the coordinator has mapped now.
    let pid = cluster.coordinator_pid();
    let cap = proc_status_bytes(pid, "VmSize:") + (256 << 20);
    let prlimit = Command::new("prlimit")
        .args([format!("--pid={pid}"), format!("--as={cap}:{cap}")])
        .status()
        .expect("run prlimit");
    assert!(prlimit.success());
    let limits = std::fs::read_to_string(format!("/proc/{pid}/limits")).unwrap();
    assert!(limits.contains(&cap.to_string()), "{limits}");

    let refused = [
        (
            &["--width", "4096", "--height", "4096", "--spp", "1"][..],
            "384.0 MiB for its film file",
        ),
        (
            &["--width", "64", "--height", "64", "--spp", "1024"][..],
            "104.0 MiB for the camera rays of one tile in a worker",
        ),
    ];
    for (frame, figure) in refused {
        let mut args = vec!["submit"];
        args.extend_from_slice(frame);
        let out = cluster.rayfarm(&args);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{frame:?} was accepted");
        assert!(
            stderr.contains("RESOURCE_EXHAUSTED")
                && stderr.contains(figure)
                && stderr.contains("--max-frame-bytes of 64.0 MiB"),
            "{stderr}"
        );
    }
    let frame = [
        "--width", "96", "--height", "72", "--spp", "2", "--depth", "2",
    ];
    let stats = submit_wait(&cluster, &frame, "next");
    assert_eq!(hash_of(&stats), local_hash(&scene, &frame));
}
