//! Previews of a running frame, for real: a local cluster renders a frame while the test
//! follows it over gRPC (WatchJob, FetchPreview) and `rayfarm watch --preview FILE` keeps a
//! file of it. The previews' sequence numbers only grow and never pass the tiles
//! committed; the last preview is byte for byte the job's result PNG (the frame is under
//! 1024 pixels a side, so it is not shrunk), and so is the file `watch --preview` left.

use std::time::Duration;

use rayfarm_node::proto::{self, JobState, job_service_client::JobServiceClient};
use rayfarm_tests::{Cluster, WorkerOpts, prepare_nbody, s};

const FRAME: [&str; 8] = [
    "--width", "256", "--height", "192", "--spp", "16", "--depth", "3",
];

#[test]
fn preview_numbers_only_grow_and_the_last_preview_is_the_result_png() {
    let root = tempfile::tempdir().expect("temp dir");
    prepare_nbody(root.path(), "nb", 20_000, 4);
    let cluster = Cluster::start(root.path(), Some("nb"), &vec![WorkerOpts::default(); 2]);
    let mut args = vec!["submit"];
    args.extend_from_slice(&FRAME);
    let out = cluster.rayfarm_ok(&args);
    let id = String::from_utf8_lossy(&out.stdout).trim().to_string();
    let file = cluster.dir().join("live.png");
    let mut watch = cluster
        .client_command(&rayfarm_tests::bin("rayfarm"))
        .args(["watch", &id, "--quiet", "--preview", s(&file)])
        .spawn()
        .expect("rayfarm watch");

    let url = cluster.coordinator_url().to_string();
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let (sequences, last, tiles_total) = runtime.block_on(async {
        let mut client = JobServiceClient::connect(url).await.unwrap();
        let req = proto::WatchJobRequest { job_id: id.clone() };
        let mut events = client.watch_job(req).await.unwrap().into_inner();
        let mut sequences = Vec::new();
        let mut last = None;
        let mut tiles_total = 0;
        let deadline = tokio::time::Instant::now() + Duration::from_secs(300);
        while let Some(event) = tokio::time::timeout_at(deadline, events.message())
            .await
            .expect("the frame ends in time")
            .unwrap()
        {
            tiles_total = event.tiles_total;
            if event.state() == JobState::Queued {
                continue;
            }
            let req = proto::FetchPreviewRequest { job_id: id.clone() };
            let preview = client.fetch_preview(req).await.unwrap().into_inner();
            assert!(
                preview.sequence >= event.preview_sequence,
                "a preview older than the event announcing it"
            );
            // A sequence number counts committed tiles: never more than the frame has.
            assert!(preview.sequence <= u64::from(event.tiles_total.max(1)));
            assert_eq!(
                (preview.width, preview.height, preview.scale),
                (256, 192, 1)
            );
            sequences.push(preview.sequence);
            let ended = matches!(
                event.state(),
                JobState::Succeeded | JobState::Failed | JobState::Cancelled
            );
            assert!(
                matches!(event.state(), JobState::Running | JobState::Succeeded),
                "{event:?}"
            );
            last = Some(preview);
            if ended {
                break;
            }
        }
        (sequences, last.expect("a preview"), tiles_total)
    });
    assert!(
        sequences.windows(2).all(|w| w[0] <= w[1]),
        "preview numbers went down: {sequences:?}"
    );
    assert!(
        sequences
            .iter()
            .any(|&n| n > 0 && n < u64::from(tiles_total)),
        "no preview mid-frame: {sequences:?}"
    );
    assert_eq!(last.sequence, u64::from(tiles_total));

    let png = cluster.dir().join("result.png");
    cluster.rayfarm_ok(&["fetch", &id, "-o", s(&png)]);
    let result = std::fs::read(&png).unwrap();
    assert!(last.png[..] == result[..], "last preview != result PNG");
    assert!(
        rayfarm_tests::wait_child(&mut watch, "rayfarm watch", Duration::from_secs(60)),
        "rayfarm watch failed"
    );
    assert_eq!(
        std::fs::read(&file).unwrap(),
        result,
        "watch --preview file != result"
    );
    // Nothing was left beside it.
    let stray: Vec<_> = std::fs::read_dir(cluster.dir())
        .unwrap()
        .filter_map(Result::ok)
        .filter(|e| e.file_name().to_string_lossy().ends_with(".part"))
        .collect();
    assert!(stray.is_empty(), "{stray:?}");
}
