//! `JobService`: the user API, a thin layer over [`Coordinator`].

use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

use rayfarm_core::scene::Manifest;

use rayfarm_node::bounds::check_field;
use rayfarm_node::proto::job_service_server::JobService;
use rayfarm_node::proto::{self, JobState};
use rayfarm_node::security::User;
use tokio::sync::{Semaphore, mpsc};
use tokio_stream::Stream;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status};
use tracing::warn;

use crate::state::Coordinator;

/// The user API served by the coordinator.
pub struct Api {
    coordinator: Arc<Coordinator>,
    /// Scene reads in progress: storage that hangs holds at most this many blocking threads.
    scene_reads: Arc<Semaphore>,
}

/// A scene manifest not read within this fails its submission (`DEADLINE_EXCEEDED`).
const SCENE_READ_TIMEOUT: Duration = Duration::from_secs(10);
/// Most scene manifests read at once.
const MAX_SCENE_READS: usize = 8;

impl Api {
    pub fn new(coordinator: Arc<Coordinator>) -> Self {
        Api {
            coordinator,
            scene_reads: Arc::new(Semaphore::new(MAX_SCENE_READS)),
        }
    }

    /// Reads `scene`'s manifest on a blocking thread, within [`SCENE_READ_TIMEOUT`], so slow
    /// or hung storage never stalls the async runtime (heartbeats, other calls).
    async fn read_scene(&self, scene: &str) -> Result<Manifest, Status> {
        let permit = self.scene_reads.clone().try_acquire_owned().map_err(|_| {
            Status::resource_exhausted(format!(
                "{MAX_SCENE_READS} scene reads are in progress; try again"
            ))
        })?;
        let coordinator = self.coordinator.clone();
        let name = scene.to_string();
        let read = tokio::task::spawn_blocking(move || {
            let _permit = permit;
            coordinator.open_scene(&name)
        });
        match tokio::time::timeout(SCENE_READ_TIMEOUT, read).await {
            Ok(Ok(result)) => result.map(|(_, manifest)| manifest),
            Ok(Err(e)) => Err(Status::internal(format!(
                "reading scene {scene:?} failed: {e}"
            ))),
            Err(_) => {
                warn!(scene, "scene read timed out");
                Err(Status::deadline_exceeded(format!(
                    "scene {scene:?} could not be read within {SCENE_READ_TIMEOUT:?}"
                )))
            }
        }
    }
}

type WatchStream = Pin<Box<dyn Stream<Item = Result<proto::WatchJobResponse, Status>> + Send>>;

#[tonic::async_trait]
impl JobService for Api {
    async fn submit_job(
        &self,
        request: Request<proto::SubmitJobRequest>,
    ) -> Result<Response<proto::SubmitJobResponse>, Status> {
        // Set by the token check when user tokens are on: who submitted what, for the log.
        let user = request.extensions().get::<User>().cloned();
        let spec = request.into_inner().spec;
        if let Some(spec) = &spec {
            check_field("scene", &spec.scene)?;
        }
        let spec = self.coordinator.spec_with_defaults(spec)?;
        let manifest = self.read_scene(&spec.scene).await?;
        let job_id = self.coordinator.enqueue(spec, &manifest, user.as_ref())?;
        Ok(Response::new(proto::SubmitJobResponse { job_id }))
    }

    type WatchJobStream = WatchStream;

    async fn watch_job(
        &self,
        request: Request<proto::WatchJobRequest>,
    ) -> Result<Response<WatchStream>, Status> {
        let job_id = request.into_inner().job_id;
        check_field("job_id", &job_id)?;
        let mut rx = self.coordinator.watch(&job_id)?;
        let (tx, out) = mpsc::channel(4);
        tokio::spawn(async move {
            loop {
                let event = rx.borrow_and_update().clone();
                let ended = matches!(
                    event.state(),
                    JobState::Succeeded | JobState::Failed | JobState::Cancelled
                );
                if tx.send(Ok(event)).await.is_err() || ended {
                    break;
                }
                if rx.changed().await.is_err() {
                    break;
                }
            }
        });
        Ok(Response::new(Box::pin(ReceiverStream::new(out))))
    }

    async fn list_jobs(
        &self,
        _request: Request<proto::ListJobsRequest>,
    ) -> Result<Response<proto::ListJobsResponse>, Status> {
        Ok(Response::new(proto::ListJobsResponse {
            jobs: self.coordinator.list(),
        }))
    }

    async fn cancel_job(
        &self,
        request: Request<proto::CancelJobRequest>,
    ) -> Result<Response<proto::CancelJobResponse>, Status> {
        let user = request.extensions().get::<User>().cloned();
        let job_id = request.into_inner().job_id;
        check_field("job_id", &job_id)?;
        let state = self.coordinator.cancel(&job_id, user.as_ref())?;
        Ok(Response::new(proto::CancelJobResponse {
            state: state as i32,
        }))
    }

    async fn fetch_result(
        &self,
        request: Request<proto::FetchResultRequest>,
    ) -> Result<Response<proto::FetchResultResponse>, Status> {
        let r = request.into_inner();
        check_field("job_id", &r.job_id)?;
        let (path, stats_json, image_hash) = self.coordinator.result(&r.job_id, r.format())?;
        let image = tokio::fs::read(&path).await.map_err(|e| {
            Status::data_loss(format!(
                "result of {} unreadable: {}: {e}",
                r.job_id,
                path.display()
            ))
        })?;
        Ok(Response::new(proto::FetchResultResponse {
            image: image.into(),
            stats_json,
            image_hash,
        }))
    }

    async fn get_cluster_status(
        &self,
        _request: Request<proto::GetClusterStatusRequest>,
    ) -> Result<Response<proto::GetClusterStatusResponse>, Status> {
        Ok(Response::new(self.coordinator.status()))
    }
}
