//! `JobService`: the user API, a thin layer over [`Coordinator`].

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime};

use rayfarm_core::scene::Manifest;

use rayfarm_node::bounds::check_field;
use rayfarm_node::proto::job_service_server::JobService;
use rayfarm_node::proto::{self, JobState};
use rayfarm_node::security::User;
use tokio::io::{AsyncReadExt, AsyncSeekExt};
use tokio::sync::{Semaphore, mpsc};
use tokio_stream::Stream;
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status};
use tracing::{info, warn};

use crate::state::Coordinator;

/// The user API served by the coordinator.
pub struct Api {
    coordinator: Arc<Coordinator>,
    /// Scene reads in progress: storage that hangs holds at most this many blocking threads.
    scene_reads: Arc<Semaphore>,
    /// Size and checksum of result files already streamed, by path (results never change
    /// once written; the size and modification time guard against a file replaced by hand).
    checksums: Mutex<HashMap<PathBuf, (SystemTime, u64, String)>>,
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
            checksums: Mutex::default(),
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

    /// The size and checksum of a result file, read once per file.
    async fn checksum(&self, path: &Path) -> std::io::Result<(u64, String)> {
        let meta = tokio::fs::metadata(path).await?;
        let modified = meta.modified()?;
        let known = self.lock_checksums().get(path).cloned();
        if let Some((m, len, sum)) = known
            && m == modified
            && len == meta.len()
        {
            return Ok((len, sum));
        }
        let owned = path.to_path_buf();
        let (len, sum) =
            tokio::task::spawn_blocking(move || rayfarm_node::result_file::checksum(&owned))
                .await
                .map_err(std::io::Error::other)??;
        self.lock_checksums()
            .insert(path.to_path_buf(), (modified, len, sum.clone()));
        Ok((len, sum))
    }

    fn lock_checksums(
        &self,
    ) -> std::sync::MutexGuard<'_, HashMap<PathBuf, (SystemTime, u64, String)>> {
        self.checksums.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// Chunk size of a streamed fetch when the client names none, and the largest it may ask.
const DEFAULT_CHUNK: u32 = 1 << 20;
const MAX_CHUNK: u32 = 4 << 20;

type WatchStream = Pin<Box<dyn Stream<Item = Result<proto::WatchJobResponse, Status>> + Send>>;
type ChunkStream = Pin<Box<dyn Stream<Item = Result<proto::FetchResultChunk, Status>> + Send>>;

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

    type FetchResultStreamStream = ChunkStream;

    async fn fetch_result_stream(
        &self,
        request: Request<proto::FetchResultStreamRequest>,
    ) -> Result<Response<ChunkStream>, Status> {
        let r = request.into_inner();
        check_field("job_id", &r.job_id)?;
        let (path, stats_json, image_hash) = self.coordinator.result(&r.job_id, r.format())?;
        let unreadable = |e: std::io::Error| {
            Status::data_loss(format!(
                "result of {} unreadable: {}: {e}",
                r.job_id,
                path.display()
            ))
        };
        let (total, checksum) = self.checksum(&path).await.map_err(unreadable)?;
        if r.offset > total {
            return Err(Status::out_of_range(format!(
                "offset {} is past the end of the {total}-byte result of {}",
                r.offset, r.job_id
            )));
        }
        let chunk = match r.chunk_bytes {
            0 => DEFAULT_CHUNK,
            n => n.min(MAX_CHUNK),
        } as usize;
        let mut file = tokio::fs::File::open(&path).await.map_err(unreadable)?;
        file.seek(std::io::SeekFrom::Start(r.offset))
            .await
            .map_err(unreadable)?;
        let mut header = Some(proto::FetchResultHeader {
            total_bytes: total,
            checksum,
            stats_json,
            image_hash,
        });
        // A few chunks in flight at most: a slow client slows the reads, memory stays bounded.
        let (tx, out) = mpsc::channel(4);
        let job_id = r.job_id.clone();
        let mut offset = r.offset;
        tokio::spawn(async move {
            loop {
                let mut data = vec![0u8; chunk.min((total - offset) as usize)];
                if let Err(e) = file.read_exact(&mut data).await {
                    let status = Status::data_loss(format!("result of {job_id}: {e}"));
                    let _ = tx.send(Err(status)).await;
                    return;
                }
                let len = data.len() as u64;
                let msg = proto::FetchResultChunk {
                    header: header.take(),
                    offset,
                    data,
                };
                if tx.send(Ok(msg)).await.is_err() {
                    return;
                }
                offset += len;
                if offset >= total {
                    return;
                }
            }
        });
        info!(job = %r.job_id, offset = r.offset, total, "streaming a result");
        Ok(Response::new(Box::pin(ReceiverStream::new(out))))
    }

    async fn get_cluster_status(
        &self,
        _request: Request<proto::GetClusterStatusRequest>,
    ) -> Result<Response<proto::GetClusterStatusResponse>, Status> {
        Ok(Response::new(self.coordinator.status()))
    }
}
