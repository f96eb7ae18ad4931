//! `JobService`: the user API, a thin layer over [`Coordinator`].

use std::collections::HashMap;
use std::net::IpAddr;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime};

use rayfarm_core::scene::Manifest;
use rayfarm_machine::coordinator::cluster::is_terminal;

use rayfarm_node::bounds::check_field;
use rayfarm_node::proto;
use rayfarm_node::proto::job_service_server::JobService;
use rayfarm_node::requests;
use rayfarm_node::security::User;
use tokio::io::{AsyncReadExt, AsyncSeekExt};
use tokio::sync::{Semaphore, mpsc};
use tokio_stream::wrappers::ReceiverStream;
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status};
use tracing::{info, warn};

use crate::state::{Coordinator, JobPage};

/// The user API served by the coordinator.
pub struct Api {
    coordinator: Arc<Coordinator>,
    /// Scene reads in progress: storage that hangs holds at most this many blocking threads.
    scene_reads: Arc<Semaphore>,
    /// Size and checksum of result files already streamed, by path (results never change
    /// once written; the size and modification time guard against a file replaced by hand).
    checksums: Mutex<HashMap<PathBuf, (SystemTime, u64, String)>>,
    /// Result fetches in progress (unary or streamed), in all and by client address: with the
    /// per-fetch bound below, what every fetch together may hold in memory, however slowly the
    /// clients read, and one client's stalled fetches never take every slot.
    fetches: Arc<FetchSlots>,
}

/// Counts of fetches in progress.
#[derive(Default)]
struct FetchSlots {
    by_client: Mutex<HashMap<Option<IpAddr>, usize>>,
}

/// A fetch's place among [`FetchSlots`], given back when dropped.
struct FetchSlot {
    slots: Arc<FetchSlots>,
    client: Option<IpAddr>,
}

impl FetchSlots {
    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<Option<IpAddr>, usize>> {
        self.by_client.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A slot for a fetch from `client`, if both caps leave room.
    fn take(self: &Arc<Self>, client: Option<IpAddr>) -> Result<FetchSlot, Status> {
        let mut counts = self.lock();
        let total: usize = counts.values().sum();
        let mine = counts.get(&client).copied().unwrap_or(0);
        if mine >= MAX_FETCHES_PER_CLIENT {
            return Err(Status::resource_exhausted(format!(
                "{mine} result fetches from this address are in progress; try again"
            )));
        }
        if total >= MAX_FETCHES {
            return Err(Status::resource_exhausted(format!(
                "{total} result fetches are in progress; try again"
            )));
        }
        *counts.entry(client).or_default() += 1;
        Ok(FetchSlot {
            slots: self.clone(),
            client,
        })
    }
}

impl Drop for FetchSlot {
    fn drop(&mut self) {
        let mut counts = self.slots.lock();
        if let Some(n) = counts.get_mut(&self.client) {
            *n -= 1;
            if *n == 0 {
                counts.remove(&self.client);
            }
        }
    }
}

/// A scene manifest not read within this fails its submission (`DEADLINE_EXCEEDED`).
const SCENE_READ_TIMEOUT: Duration = Duration::from_secs(10);
/// Most scene manifests read at once.
const MAX_SCENE_READS: usize = 8;
/// Result files whose checksum is remembered, at most (a few hundred bytes each).
const KEPT_CHECKSUMS: usize = 1024;

/// Most result fetches served at once, in all and to one client address; more are refused
/// with `RESOURCE_EXHAUSTED`.
const MAX_FETCHES: usize = 16;
const MAX_FETCHES_PER_CLIENT: usize = 4;
/// The largest result `FetchResult` returns in one message; larger ones are streamed
/// (`FetchResultStream`, which `rayfarm fetch` uses), so a unary fetch holds at most this.
const MAX_UNARY_RESULT: u64 = 8 << 20;
/// A streamed fetch whose client has not taken the next chunk within this stops reading the
/// file: the client resumes from its offset. Its slot stays taken until the server drops the
/// stream (a client that never reads holds it until its connection closes).
const FETCH_STALL_TIMEOUT: Duration = Duration::from_secs(30);

impl Api {
    pub fn new(coordinator: Arc<Coordinator>) -> Self {
        Api {
            coordinator,
            scene_reads: Arc::new(Semaphore::new(MAX_SCENE_READS)),
            checksums: Mutex::default(),
            fetches: Arc::default(),
        }
    }

    /// A finished job's image path, statistics and hash ([`Coordinator::result`]), read off
    /// the runtime: the statistics may come from the store.
    async fn result(
        &self,
        job_id: &str,
        format: proto::ImageFormat,
    ) -> Result<(std::path::PathBuf, String, String), Status> {
        let id = job_id.to_string();
        self.coordinator
            .off_runtime(move |c| c.result(&id, format))
            .await
    }

    /// Reads `scene`'s manifest on a blocking thread, within [`SCENE_READ_TIMEOUT`], so slow
    /// or hung storage never stalls the async runtime (heartbeats, other calls).
    async fn read_scene(&self, scene: &str) -> Result<Manifest, Status> {
        // A burst of submits waits its turn (waiting holds no thread); only reads stuck on
        // storage for as long as a read may take make the next ones give up.
        let permit = tokio::time::timeout(
            SCENE_READ_TIMEOUT,
            self.scene_reads.clone().acquire_owned(),
        )
        .await
        .ok()
        .and_then(Result::ok)
        .ok_or_else(|| {
            Status::resource_exhausted(format!(
                "{MAX_SCENE_READS} scene reads have been in progress for {SCENE_READ_TIMEOUT:?}; \
                 try again"
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
        let mut known = self.lock_checksums();
        // A cache, not a record of every result ever fetched: memory must not grow with the
        // jobs a coordinator has finished. A result fetched again after a clear is summed again.
        if known.len() >= KEPT_CHECKSUMS {
            known.clear();
        }
        known.insert(path.to_path_buf(), (modified, len, sum.clone()));
        Ok((len, sum))
    }

    fn lock_checksums(
        &self,
    ) -> std::sync::MutexGuard<'_, HashMap<PathBuf, (SystemTime, u64, String)>> {
        self.checksums.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// A result file that could not be read, named with its job.
fn unreadable(job_id: &str, path: &Path, e: std::io::Error) -> Status {
    Status::data_loss(format!(
        "result of {job_id} unreadable: {}: {e}",
        path.display()
    ))
}

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
        // It waits for the job's record to be on disk: off the async runtime.
        let coordinator = self.coordinator.clone();
        let job_id = tokio::task::spawn_blocking(move || {
            coordinator.enqueue(spec, &manifest, user.as_ref())
        })
        .await
        .map_err(|e| Status::internal(format!("the job could not be queued: {e}")))??;
        Ok(Response::new(proto::SubmitJobResponse { job_id }))
    }

    type WatchJobStream = WatchStream;

    async fn watch_job(
        &self,
        request: Request<proto::WatchJobRequest>,
    ) -> Result<Response<WatchStream>, Status> {
        let job_id = request.into_inner().job_id;
        check_field("job_id", &job_id)?;
        // A job finished long ago is read from the store: off the runtime.
        let id = job_id.clone();
        let mut rx = self.coordinator.off_runtime(move |c| c.watch(&id)).await?;
        let (tx, out) = mpsc::channel(4);
        tokio::spawn(async move {
            loop {
                let event = rx.borrow_and_update().clone();
                let ended = is_terminal(event.state());
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
        request: Request<proto::ListJobsRequest>,
    ) -> Result<Response<proto::ListJobsResponse>, Status> {
        let page = requests::list_page(&request.into_inner())?;
        let page = match page.from_seq {
            None => JobPage::newest(page.size),
            Some(from_seq) => JobPage {
                size: page.size,
                from_seq,
            },
        };
        let (jobs, next) = self.coordinator.off_runtime(move |c| c.list(page)).await?;
        Ok(Response::new(proto::ListJobsResponse {
            jobs,
            next_page_token: next.map(requests::page_token).unwrap_or_default(),
        }))
    }

    async fn cancel_job(
        &self,
        request: Request<proto::CancelJobRequest>,
    ) -> Result<Response<proto::CancelJobResponse>, Status> {
        let user = request.extensions().get::<User>().cloned();
        let job_id = request.into_inner().job_id;
        check_field("job_id", &job_id)?;
        let state = self
            .coordinator
            .off_runtime(move |c| c.cancel(&job_id, user.as_ref()))
            .await?;
        Ok(Response::new(proto::CancelJobResponse {
            state: state as i32,
        }))
    }

    async fn fetch_result(
        &self,
        request: Request<proto::FetchResultRequest>,
    ) -> Result<Response<proto::FetchResultResponse>, Status> {
        let client = rayfarm_node::listen::remote_addr(&request).map(|a| a.ip());
        let r = request.into_inner();
        check_field("job_id", &r.job_id)?;
        let (path, stats_json, image_hash) = self.result(&r.job_id, r.format()).await?;
        let _slot = self.fetches.take(client)?;
        let unreadable = |e| unreadable(&r.job_id, &path, e);
        let len = tokio::fs::metadata(&path).await.map_err(unreadable)?.len();
        if len > MAX_UNARY_RESULT {
            return Err(Status::failed_precondition(format!(
                "the result of {} is {len} bytes, more than the {MAX_UNARY_RESULT} bytes \
                 FetchResult returns at once; fetch it with FetchResultStream (`rayfarm fetch` \
                 does)",
                r.job_id
            )));
        }
        // Read at most the cap, should the file have grown since it was measured.
        let mut image = Vec::with_capacity(len as usize);
        tokio::fs::File::open(&path)
            .await
            .map_err(unreadable)?
            .take(MAX_UNARY_RESULT)
            .read_to_end(&mut image)
            .await
            .map_err(unreadable)?;
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
        let client = rayfarm_node::listen::remote_addr(&request).map(|a| a.ip());
        let r = request.into_inner();
        let chunk = requests::result_chunk(&r)?;
        let (path, stats_json, image_hash) = self.result(&r.job_id, r.format()).await?;
        let slot = self.fetches.take(client)?;
        let unreadable = |e| unreadable(&r.job_id, &path, e);
        let (total, checksum) = self.checksum(&path).await.map_err(unreadable)?;
        if r.offset > total {
            return Err(Status::out_of_range(format!(
                "offset {} is past the end of the {total}-byte result of {}",
                r.offset, r.job_id
            )));
        }
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
        // One chunk waiting at most: a slow client slows the reads, memory stays bounded (a
        // fetch holds the chunk queued, the one being encoded and what HTTP/2 buffers).
        let (tx, out) = mpsc::channel(1);
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
                match tokio::time::timeout(FETCH_STALL_TIMEOUT, tx.send(Ok(msg))).await {
                    Ok(Ok(())) => {}
                    // The client went away.
                    Ok(Err(_)) => return,
                    Err(_) => {
                        warn!(job = %job_id, offset, "a result fetch stalled; ending it");
                        return;
                    }
                }
                offset += len;
                if offset >= total {
                    return;
                }
            }
        });
        info!(job = %r.job_id, offset = r.offset, total, "streaming a result");
        // The slot goes with the response stream, not the reading task: it is free again only
        // when the server drops the stream (sent, reset or its connection closed), so what
        // unread chunks hold stays within MAX_FETCHES of them.
        let stream = ReceiverStream::new(out).map(move |chunk| {
            let _held = &slot;
            chunk
        });
        Ok(Response::new(Box::pin(stream)))
    }

    async fn fetch_preview(
        &self,
        request: Request<proto::FetchPreviewRequest>,
    ) -> Result<Response<proto::FetchPreviewResponse>, Status> {
        let job_id = request.into_inner().job_id;
        check_field("job_id", &job_id)?;
        let previews = self
            .coordinator
            .off_runtime(move |c| c.previews(&job_id))
            .await?;
        let latest = previews.latest().await?;
        let p = &latest.preview;
        Ok(Response::new(proto::FetchPreviewResponse {
            png: p.png.clone(),
            sequence: latest.sequence,
            width: p.width,
            height: p.height,
            scale: p.factor,
            subframe: latest.subframe,
        }))
    }

    async fn set_job_priority(
        &self,
        request: Request<proto::SetJobPriorityRequest>,
    ) -> Result<Response<proto::SetJobPriorityResponse>, Status> {
        let user = request.extensions().get::<User>().cloned();
        let r = request.into_inner();
        check_field("job_id", &r.job_id)?;
        let state = self
            .coordinator
            .off_runtime(move |c| c.set_priority(&r.job_id, r.priority, user.as_ref()))
            .await?;
        Ok(Response::new(proto::SetJobPriorityResponse {
            state: state as i32,
        }))
    }

    async fn get_cluster_status(
        &self,
        _request: Request<proto::GetClusterStatusRequest>,
    ) -> Result<Response<proto::GetClusterStatusResponse>, Status> {
        Ok(Response::new(self.coordinator.status()))
    }
}
