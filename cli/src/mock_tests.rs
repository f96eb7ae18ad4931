//! The cluster commands end to end over real gRPC, against a scripted coordinator on loopback:
//! what the CLI sends, how it follows a job, what it writes and how it reports failures. (The
//! real coordinator is exercised by the integration tests in `tests/`.)

use clap::Parser;
use rayfarm_common::cluster::stats::ClusterStats;
use rayfarm_common::proto::job_service_server::{JobService, JobServiceServer};
use rayfarm_common::proto::{self, JobState};
use tonic::{Request, Response, Status};

use crate::{Cli, dispatch};

/// Larger than tonic's 4 MiB default message limit, so the client's raised limit is tested.
const IMAGE_BYTES: usize = 5 << 20;

/// A coordinator that knows three jobs: `ok` succeeds, `bad` fails, `cut` loses its watch.
struct Mock;

fn event(job: &str, state: JobState, done: u32) -> Result<proto::WatchJobResponse, Status> {
    Ok(proto::WatchJobResponse {
        job_id: job.into(),
        state: state as i32,
        tiles_done: done,
        tiles_total: 4,
        round: u64::from(done),
        rays_per_second: 1e6,
        eta_seconds: -1.0,
        ..Default::default()
    })
}

fn stats() -> String {
    serde_json::to_string(&ClusterStats {
        job_id: "ok".into(),
        width: 64,
        height: 64,
        workers: 2,
        rounds: 3,
        image_hash: "00000000deadbeef".into(),
        ..Default::default()
    })
    .unwrap()
}

#[tonic::async_trait]
impl JobService for Mock {
    async fn submit_job(
        &self,
        request: Request<proto::SubmitJobRequest>,
    ) -> Result<Response<proto::SubmitJobResponse>, Status> {
        let spec = request.into_inner().spec.unwrap_or_default();
        if spec.width == 0 {
            return Err(Status::invalid_argument("width must be in 1..=16384"));
        }
        let id = if spec.scene == "broken" { "bad" } else { "ok" };
        Ok(Response::new(proto::SubmitJobResponse {
            job_id: id.into(),
        }))
    }

    type WatchJobStream =
        tokio_stream::Iter<std::vec::IntoIter<Result<proto::WatchJobResponse, Status>>>;

    async fn watch_job(
        &self,
        request: Request<proto::WatchJobRequest>,
    ) -> Result<Response<Self::WatchJobStream>, Status> {
        let id = request.into_inner().job_id;
        let events = match id.as_str() {
            "ok" => {
                let mut end = event("ok", JobState::Succeeded, 4)?;
                end.stats_json = stats();
                vec![
                    event("ok", JobState::Queued, 0),
                    event("ok", JobState::Running, 2),
                    Ok(end),
                ]
            }
            "bad" => {
                let mut end = event("bad", JobState::Failed, 1)?;
                end.error = "scene \"broken\" not found under the scene root".into();
                vec![event("bad", JobState::Running, 1), Ok(end)]
            }
            "cut" => vec![event("cut", JobState::Running, 1)],
            _ => return Err(Status::not_found(format!("no job {id}"))),
        };
        Ok(Response::new(tokio_stream::iter(events)))
    }

    async fn list_jobs(
        &self,
        _: Request<proto::ListJobsRequest>,
    ) -> Result<Response<proto::ListJobsResponse>, Status> {
        Ok(Response::new(proto::ListJobsResponse::default()))
    }

    async fn cancel_job(
        &self,
        _: Request<proto::CancelJobRequest>,
    ) -> Result<Response<proto::CancelJobResponse>, Status> {
        Ok(Response::new(proto::CancelJobResponse {
            state: JobState::Cancelled as i32,
        }))
    }

    async fn fetch_result(
        &self,
        request: Request<proto::FetchResultRequest>,
    ) -> Result<Response<proto::FetchResultResponse>, Status> {
        let r = request.into_inner();
        if r.job_id != "ok" {
            return Err(Status::failed_precondition("the job has not succeeded"));
        }
        let mut image = vec![0u8; IMAGE_BYTES];
        image[0] = r.format as u8;
        Ok(Response::new(proto::FetchResultResponse {
            image: image.into(),
            stats_json: stats(),
            image_hash: "00000000deadbeef".into(),
        }))
    }

    async fn get_cluster_status(
        &self,
        _: Request<proto::GetClusterStatusRequest>,
    ) -> Result<Response<proto::GetClusterStatusResponse>, Status> {
        Ok(Response::new(proto::GetClusterStatusResponse {
            workers: vec![proto::WorkerStatus::default(); 2],
            ..Default::default()
        }))
    }
}

/// Serves a `Mock` on a loopback port, on its own thread and runtime (the commands
/// under test build their own runtime); returns `host:port`.
fn serve() -> String {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    listener.set_nonblocking(true).unwrap();
    std::thread::spawn(move || {
        let rt = crate::client::runtime().unwrap();
        rt.block_on(async move {
            let listener = tokio::net::TcpListener::from_std(listener).unwrap();
            let service = JobServiceServer::new(Mock).max_encoding_message_size(64 << 20);
            tonic::transport::Server::builder()
                .add_service(service)
                .serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(listener))
                .await
                .unwrap();
        });
    });
    addr
}

fn rayfarm(args: &[&str]) -> anyhow::Result<()> {
    let cli = Cli::try_parse_from(std::iter::once("rayfarm").chain(args.iter().copied()))?;
    dispatch(cli.command)
}

#[test]
fn submit_wait_follows_the_job_and_saves_image_and_statistics() {
    let addr = serve();
    let tmp = tempfile::tempdir().unwrap();
    let png = tmp.path().join("f.png");
    let json = tmp.path().join("s.json");
    rayfarm(&[
        "submit",
        "--coordinator",
        &addr,
        "--wait",
        "--quiet",
        "--output",
        png.to_str().unwrap(),
        "--stats-json",
        json.to_str().unwrap(),
    ])
    .unwrap();
    let image = std::fs::read(&png).unwrap();
    assert_eq!(image.len(), IMAGE_BYTES);
    assert_eq!(image[0], proto::ImageFormat::Png as u8);
    let stats: ClusterStats =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(stats.rounds, 3);

    let exr = tmp.path().join("f.exr");
    rayfarm(&[
        "fetch",
        "ok",
        "--coordinator",
        &addr,
        "-o",
        exr.to_str().unwrap(),
    ])
    .unwrap();
    assert_eq!(
        std::fs::read(&exr).unwrap()[0],
        proto::ImageFormat::Exr as u8
    );

    rayfarm(&["watch", "ok", "--coordinator", &addr]).unwrap();
    rayfarm(&["status", "--coordinator", &addr, "--wait-workers", "2"]).unwrap();
    rayfarm(&["jobs", "--coordinator", &addr]).unwrap();
    rayfarm(&["cancel", "ok", "--coordinator", &addr]).unwrap();
}

#[test]
fn failures_are_errors_that_say_what_happened() {
    let addr = serve();
    let err = |args: &[&str]| format!("{:#}", rayfarm(args).unwrap_err());

    let e = err(&["submit", "--coordinator", &addr, "--width", "0"]);
    assert_eq!(
        e,
        "submitting the job: INVALID_ARGUMENT: width must be in 1..=16384"
    );
    let e = err(&[
        "submit",
        "--coordinator",
        &addr,
        "--scene",
        "broken",
        "--wait",
        "--quiet",
    ]);
    assert_eq!(
        e,
        "job bad failed: scene \"broken\" not found under the scene root"
    );
    let e = err(&["watch", "cut", "--coordinator", &addr, "--quiet"]);
    assert!(e.contains("before the job ended"), "{e}");
    let e = err(&["watch", "nope", "--coordinator", &addr]);
    assert!(e.contains("NOT_FOUND: no job nope"), "{e}");
    let e = err(&[
        "status",
        "--coordinator",
        &addr,
        "--wait-workers",
        "3",
        "--timeout",
        "0.2",
    ]);
    assert!(e.contains("2 workers registered"), "{e}");
    let e = err(&[
        "submit",
        "--coordinator",
        &addr,
        "--wait",
        "--output",
        "x.jpg",
    ]);
    assert!(e.contains(".png"), "{e}");
}
