//! Progressive frames on a real cluster: a job's samples rendered in subframes, each a whole
//! image pass committed into the coordinator's film. The final image hash equals the
//! one-pass job's and `render --local`'s under every schedule, and with a worker killed once
//! a subframe has committed (under every schedule too); the statistics' per-subframe costs
//! add up to the frame's; the previews' subframe numbers (and sequence numbers) only grow,
//! a preview exists between subframes, and the last one is the result PNG byte for byte.

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use rayfarm_node::proto::{self, JobState, job_service_client::JobServiceClient};
use rayfarm_tests::{
    Cluster, WorkerOpts, bin, domain_bytes, hash_of, local_hash, prepare_nbody, s, stats_field,
    submit_wait, wait_child,
};

/// 6 samples: doubling makes subframes of 1, 1, 2 and 2 samples.
const FRAME: [&str; 8] = [
    "--width", "96", "--height", "64", "--spp", "6", "--depth", "3",
];

const SCHEDULES: [&str; 5] = ["image-plane", "domain", "dynamic", "hybrid", "predictive"];

#[test]
fn a_progressive_frame_is_the_one_pass_image_under_every_schedule() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 20_000, 4);
    let (_, largest) = domain_bytes(&scene);
    let expected = local_hash(&scene, &FRAME);
    // Caches of two domains: domains are loaded and evicted within and across subframes.
    let cluster = Cluster::start(
        root.path(),
        Some("nb"),
        &vec![WorkerOpts::cache(2 * largest); 2],
    );
    for schedule in SCHEDULES {
        let mut one_pass = FRAME.to_vec();
        one_pass.extend(["--schedule", schedule]);
        let json = submit_wait(&cluster, &one_pass, &format!("{schedule}-one"));
        assert_eq!(hash_of(&json), expected, "{schedule}, one pass");
        assert_eq!(stats_field(&json, "/subframes"), 1, "{schedule}");
        for (progressive, subframes) in [("doubling", 4), ("4", 2)] {
            let mut args = one_pass.clone();
            args.extend(["--progressive", progressive]);
            let tag = format!("{schedule}-{progressive}");
            let json = submit_wait(&cluster, &args, &tag);
            assert_eq!(
                hash_of(&json),
                expected,
                "{schedule}, progressive {progressive}"
            );
            assert_eq!(stats_field(&json, "/subframes"), subframes, "{tag}");
            assert_subframe_costs(&json, subframes, 6, &tag);
            // Every worker's reports of every subframe are one row per worker.
            assert_eq!(
                stats_field(&json, "/per_worker").as_array().map(Vec::len),
                Some(2),
                "{tag}"
            );
        }
    }
}

/// The statistics' per-subframe costs: `subframes` of them in sample order, their samples
/// adding up to `spp`, each done no earlier than the one before, and their loads adding up to
/// the frame's (every subframe's reports are in the job's statistics).
fn assert_subframe_costs(json: &Path, subframes: u64, spp: u64, tag: &str) {
    let costs = stats_field(json, "/subframe_costs");
    let costs = costs.as_array().expect("subframe_costs is a list");
    assert_eq!(costs.len() as u64, subframes, "{tag}: {costs:?}");
    let mut next_sample = 0;
    let mut done = 0.0;
    let mut loads = 0;
    for c in costs {
        assert_eq!(
            c["first_sample"].as_u64(),
            Some(next_sample),
            "{tag}: {costs:?}"
        );
        next_sample += c["samples"].as_u64().unwrap();
        let at = c["done_seconds"].as_f64().unwrap();
        assert!(at >= done, "{tag}: {costs:?}");
        done = at;
        loads += c["loads"].as_u64().unwrap();
    }
    assert_eq!(next_sample, spp, "{tag}");
    assert_eq!(stats_field(json, "/cache/loads"), loads, "{tag}: {costs:?}");
}

fn spawn_submit_wait(cluster: &Cluster, args: &[&str], png: &Path, json: &Path) -> Child {
    Command::new(bin("rayfarm"))
        .args(["submit", "--wait", "--quiet", "-o", s(png), "--stats-json"])
        .arg(json)
        .args(args)
        .env("RAYFARM_COORDINATOR", cluster.coordinator_url())
        .stdout(Stdio::null())
        .spawn()
        .expect("start rayfarm submit")
}

/// Follows job `id` until an event has `subframes_done >= done` (or the job ends); returns
/// that event.
async fn until_subframes(
    client: &mut JobServiceClient<tonic::transport::Channel>,
    id: &str,
    done: u32,
) -> proto::WatchJobResponse {
    let req = proto::WatchJobRequest {
        job_id: id.to_string(),
    };
    let mut events = client.watch_job(req).await.unwrap().into_inner();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    loop {
        let event = tokio::time::timeout_at(deadline, events.message())
            .await
            .expect("subframes commit in time")
            .unwrap()
            .expect("the job's events go on");
        let settled = event.subframes_done >= done || event.state() != JobState::Running;
        if settled && event.state() != JobState::Queued {
            return event;
        }
    }
}

/// The newest job's id, as `rayfarm jobs` lists it.
fn newest_job(cluster: &Cluster) -> Option<String> {
    let jobs = rayfarm_tests::jobs(cluster);
    jobs.first()
        .and_then(|j| j["job_id"].as_str())
        .map(str::to_string)
}

#[test]
fn a_worker_killed_between_subframes_keeps_the_committed_ones_and_the_image() {
    let root = tempfile::tempdir().expect("temp dir");
    let scene = prepare_nbody(root.path(), "nb", 20_000, 4);
    let (_, largest) = domain_bytes(&scene);
    let frame = [
        "--width", "128", "--height", "96", "--spp", "16", "--depth", "3",
    ];
    let expected = local_hash(&scene, &frame);
    let runtime = tokio::runtime::Runtime::new().unwrap();
    for schedule in SCHEDULES {
        let mut cluster = Cluster::start(
            root.path(),
            Some("nb"),
            &vec![WorkerOpts::cache(largest); 3],
        );
        let json = cluster.dir().join("killed.json");
        let png = cluster.dir().join("killed.png");
        let mut args = frame.to_vec();
        args.extend(["--schedule", schedule, "--progressive", "1"]);
        let mut waiter = spawn_submit_wait(&cluster, &args, &png, &json);
        rayfarm_tests::wait_until("the job to be listed", Duration::from_secs(30), || {
            newest_job(&cluster).is_some()
        });
        let id = newest_job(&cluster).unwrap();
        let url = cluster.coordinator_url().to_string();
        let at_kill = runtime.block_on(async {
            let mut client = JobServiceClient::connect(url).await.unwrap();
            until_subframes(&mut client, &id, 1).await
        });
        assert_eq!(
            at_kill.state(),
            JobState::Running,
            "{schedule}: {at_kill:?}"
        );
        assert_eq!(at_kill.subframes, 16, "{schedule}");
        assert!(
            at_kill.subframes_done >= 1 && at_kill.subframes_done < 16,
            "{schedule}: {at_kill:?}"
        );
        cluster.kill_worker(1);
        let ok = wait_child(&mut waiter, "the frame", Duration::from_secs(120));
        assert!(ok, "{schedule}: the frame failed after a worker was killed");
        assert_eq!(hash_of(&json), expected, "{schedule}");
        assert_eq!(stats_field(&json, "/subframes"), 16, "{schedule}");
        assert_subframe_costs(&json, 16, 16, schedule);
        // The job ran once: the committed subframes were kept, not rendered again.
        let log = cluster.coordinator_log();
        assert_eq!(
            log.matches("frame started").count(),
            1,
            "{schedule}: the job started over"
        );
    }
}

#[test]
fn preview_subframe_numbers_only_grow_and_the_last_preview_is_the_result_png() {
    let root = tempfile::tempdir().expect("temp dir");
    prepare_nbody(root.path(), "nb", 20_000, 4);
    let cluster = Cluster::start(root.path(), Some("nb"), &vec![WorkerOpts::default(); 2]);
    let mut args = vec!["submit", "--progressive", "doubling"];
    args.extend_from_slice(&[
        "--width", "160", "--height", "128", "--spp", "16", "--depth", "3",
    ]);
    let out = cluster.rayfarm_ok(&args);
    let id = String::from_utf8_lossy(&out.stdout).trim().to_string();
    let url = cluster.coordinator_url().to_string();
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let (seen, last, subframes) = runtime.block_on(async {
        let mut client = JobServiceClient::connect(url).await.unwrap();
        let req = proto::WatchJobRequest { job_id: id.clone() };
        let mut events = client.watch_job(req).await.unwrap().into_inner();
        let mut seen: Vec<(u32, u64, u32)> = Vec::new();
        let mut last = None;
        let mut subframes = 0;
        let deadline = tokio::time::Instant::now() + Duration::from_secs(300);
        while let Some(event) = tokio::time::timeout_at(deadline, events.message())
            .await
            .expect("the frame ends in time")
            .unwrap()
        {
            if event.state() == JobState::Queued {
                continue;
            }
            assert!(
                matches!(event.state(), JobState::Running | JobState::Succeeded),
                "{event:?}"
            );
            subframes = event.subframes;
            let req = proto::FetchPreviewRequest { job_id: id.clone() };
            let preview = client.fetch_preview(req).await.unwrap().into_inner();
            assert!(preview.sequence >= event.preview_sequence);
            assert!(preview.subframe <= event.subframes, "{preview:?}");
            seen.push((event.subframes_done, preview.sequence, preview.subframe));
            last = Some(preview);
            if event.state() == JobState::Succeeded {
                break;
            }
        }
        (seen, last.expect("a preview"), subframes)
    });
    // 16 samples doubling: 1, 1, 2, 4, 8.
    assert_eq!(subframes, 5);
    for w in seen.windows(2) {
        assert!(w[0].0 <= w[1].0, "event subframes went down: {seen:?}");
        assert!(w[0].1 <= w[1].1, "preview sequence went down: {seen:?}");
        assert!(w[0].2 <= w[1].2, "preview subframe went down: {seen:?}");
    }
    assert!(
        seen.iter().any(|&(_, _, sub)| sub > 0 && sub < subframes),
        "no preview between subframes: {seen:?}"
    );
    assert_eq!(last.subframe, subframes);
    // 20 tiles, committed once per subframe.
    assert_eq!(last.sequence, 20 * 5);
    let png = cluster.dir().join("result.png");
    cluster.rayfarm_ok(&["fetch", &id, "-o", s(&png)]);
    assert!(
        last.png[..] == std::fs::read(&png).unwrap()[..],
        "last preview != result PNG"
    );
}
