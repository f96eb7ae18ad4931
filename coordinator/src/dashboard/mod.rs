//! The web dashboard on the coordinator's `--http` listener: one page (HTML, CSS and plain
//! JavaScript compiled into the binary, no request to anywhere else) and the JSON API under
//! `/api/` it polls: jobs, workers, the running frame's preview, and the figures over time
//! its charts draw (`history`).
//!
//! With user tokens on, every `/api/` request needs `Authorization: Bearer TOKEN` (the page
//! asks for it), checked by the job API's own check (`RequireToken::authenticate`), and
//! cancelling or changing a priority goes through the same `Coordinator` calls as the gRPC
//! API, ownership checks included. Mutating requests are POSTs with a JSON body
//! (`Content-Type: application/json`, refused otherwise), which a page of another origin
//! cannot send without a CORS preflight this server never grants.

mod history;

use std::sync::Arc;

use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use rayfarm_node::bounds::check_field;
use rayfarm_node::job::state_name;
use rayfarm_node::proto::JobState;
use rayfarm_node::security::{RequireToken, User};
use serde::{Deserialize, Serialize};
use tonic::{Code, Status};

use crate::state::{Coordinator, JobPage};

const INDEX: &str = include_str!("index.html");
const SCRIPT: &str = include_str!("dashboard.js");
const STYLE: &str = include_str!("dashboard.css");

/// The page may load only its own script, style and images (previews come as blobs).
const CSP: &str = "default-src 'none'; script-src 'self'; style-src 'self'; \
                   img-src 'self' blob:; connect-src 'self'; frame-ancestors 'none'";

/// Jobs the page lists (the newest).
const LISTED_JOBS: usize = 100;

#[derive(Clone)]
struct Ctx {
    coordinator: Arc<Coordinator>,
    tokens: RequireToken,
    history: Arc<history::History>,
}

/// The dashboard's routes; starts sampling the figures its charts show.
pub fn router(coordinator: Arc<Coordinator>, tokens: RequireToken) -> Router {
    let history = history::History::start(coordinator.clone());
    let ctx = Ctx {
        coordinator,
        tokens,
        history,
    };
    Router::new()
        .route(
            "/",
            get(|| async { page("text/html; charset=utf-8", INDEX) }),
        )
        .route(
            "/dashboard.js",
            get(|| async { page("text/javascript; charset=utf-8", SCRIPT) }),
        )
        .route(
            "/dashboard.css",
            get(|| async { page("text/css; charset=utf-8", STYLE) }),
        )
        .route("/api/jobs", get(jobs))
        .route("/api/cluster", get(cluster))
        .route("/api/history", get(samples))
        .route("/api/jobs/{id}/preview", get(preview))
        .route("/api/jobs/{id}/cancel", post(cancel))
        .route("/api/jobs/{id}/priority", post(priority))
        .with_state(ctx)
}

fn page(content_type: &'static str, body: &'static str) -> Response {
    (
        [
            (header::CONTENT_TYPE, content_type),
            (header::CONTENT_SECURITY_POLICY, CSP),
            (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
        ],
        body,
    )
        .into_response()
}

/// An error as the page shows it: an HTTP status and `{"error": "..."}`.
struct ApiError(StatusCode, String);

impl From<Status> for ApiError {
    fn from(s: Status) -> Self {
        let code = match s.code() {
            Code::NotFound => StatusCode::NOT_FOUND,
            Code::InvalidArgument | Code::OutOfRange => StatusCode::BAD_REQUEST,
            Code::PermissionDenied => StatusCode::FORBIDDEN,
            Code::Unauthenticated => StatusCode::UNAUTHORIZED,
            Code::FailedPrecondition => StatusCode::CONFLICT,
            Code::ResourceExhausted => StatusCode::TOO_MANY_REQUESTS,
            Code::Unavailable => StatusCode::SERVICE_UNAVAILABLE,
            _ => StatusCode::INTERNAL_SERVER_ERROR,
        };
        ApiError(code, s.message().to_string())
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let body = serde_json::json!({ "error": self.1 });
        (self.0, Json(body)).into_response()
    }
}

/// The user of a request (`None` without user tokens), or its refusal.
fn user(ctx: &Ctx, headers: &HeaderMap) -> Result<Option<User>, ApiError> {
    let presented = headers.get(header::AUTHORIZATION).map(|v| v.as_bytes());
    ctx.tokens.authenticate(presented).map_err(|refusal| {
        tracing::warn!("dashboard request refused: {refusal}");
        ApiError(StatusCode::UNAUTHORIZED, refusal.to_string())
    })
}

fn job_id(id: &str) -> Result<(), ApiError> {
    check_field("job_id", id).map_err(ApiError::from)
}

/// A job as the page lists it.
#[derive(Serialize)]
struct JobRow {
    job_id: String,
    state: &'static str,
    owner: String,
    scene: String,
    width: u32,
    height: u32,
    spp: u32,
    priority: i32,
    submitted_unix_ms: i64,
    started_unix_ms: i64,
    finished_unix_ms: i64,
    error: String,
    tiles_done: u32,
    tiles_total: u32,
    rays_per_second: f64,
    eta_seconds: f64,
    preview_sequence: u64,
    /// Subframes of a progressive job (1: one pass), and those committed so far.
    subframes: u32,
    subframes_done: u32,
}

async fn jobs(State(ctx): State<Ctx>, headers: HeaderMap) -> Result<Response, ApiError> {
    user(&ctx, &headers)?;
    let (jobs, _) = ctx
        .coordinator
        .off_runtime(|c| c.list(JobPage::newest(LISTED_JOBS)))
        .await?;
    let rows: Vec<JobRow> = jobs
        .into_iter()
        .map(|j| {
            let progress = ctx.coordinator.progress(&j.job_id).unwrap_or_default();
            let spec = j.spec.clone().unwrap_or_default();
            JobRow {
                state: state_name(j.state()),
                owner: j.owner,
                scene: spec.scene,
                width: spec.width,
                height: spec.height,
                spp: spec.spp,
                priority: spec.priority,
                submitted_unix_ms: j.submitted_unix_ms,
                started_unix_ms: j.started_unix_ms,
                finished_unix_ms: j.finished_unix_ms,
                error: j.error,
                tiles_done: progress.tiles_done,
                tiles_total: progress.tiles_total,
                rays_per_second: progress.rays_per_second,
                eta_seconds: progress.eta_seconds,
                preview_sequence: progress.preview_sequence,
                subframes: progress.subframes,
                subframes_done: progress.subframes_done,
                job_id: j.job_id,
            }
        })
        .collect();
    Ok(Json(rows).into_response())
}

/// A worker as the page lists it.
#[derive(Serialize)]
struct WorkerRow {
    worker_id: String,
    peer_address: String,
    resident_domains: Vec<u32>,
    queued_rays: u64,
    queue_bytes: u64,
    spill_bytes: u64,
    domain_loads: u64,
    rays_per_second: f64,
    last_seen_ms: u64,
    left_out: String,
}

async fn cluster(State(ctx): State<Ctx>, headers: HeaderMap) -> Result<Response, ApiError> {
    user(&ctx, &headers)?;
    let status = ctx.coordinator.status();
    let workers: Vec<WorkerRow> = status
        .workers
        .into_iter()
        .map(|w| WorkerRow {
            rays_per_second: ctx.history.worker_rate(&w.worker_id),
            queued_rays: w.queued_rays.values().sum(),
            worker_id: w.worker_id,
            peer_address: w.peer_address,
            resident_domains: w.resident_domains,
            queue_bytes: w.queue_bytes,
            spill_bytes: w.spill_bytes,
            domain_loads: w.domain_loads,
            last_seen_ms: w.last_seen_ms,
            left_out: w.left_out,
        })
        .collect();
    let body = serde_json::json!({
        "workers": workers,
        "lost": ctx.coordinator.lost_workers(),
        "running_job_id": status.running_job_id,
        "round": status.round,
    });
    Ok(Json(body).into_response())
}

async fn samples(State(ctx): State<Ctx>, headers: HeaderMap) -> Result<Response, ApiError> {
    user(&ctx, &headers)?;
    Ok(Json(ctx.history.samples()).into_response())
}

async fn preview(
    State(ctx): State<Ctx>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    user(&ctx, &headers)?;
    job_id(&id)?;
    let previews = ctx
        .coordinator
        .off_runtime(move |c| c.previews(&id))
        .await?;
    let latest = previews.latest().await?;
    Ok((
        [
            (header::CONTENT_TYPE, "image/png".to_string()),
            (header::CACHE_CONTROL, "no-store".to_string()),
            (
                header::HeaderName::from_static("x-preview-sequence"),
                latest.sequence.to_string(),
            ),
        ],
        latest.preview.png.clone(),
    )
        .into_response())
}

/// The body of a cancel: nothing, but it must be JSON (see the module documentation).
#[derive(Deserialize)]
struct CancelBody {}

async fn cancel(
    State(ctx): State<Ctx>,
    Path(id): Path<String>,
    headers: HeaderMap,
    Json(CancelBody {}): Json<CancelBody>,
) -> Result<Response, ApiError> {
    let user = user(&ctx, &headers)?;
    job_id(&id)?;
    let state: JobState = ctx
        .coordinator
        .off_runtime(move |c| c.cancel(&id, user.as_ref()))
        .await?;
    Ok(Json(serde_json::json!({ "state": state_name(state) })).into_response())
}

#[derive(Deserialize)]
struct PriorityBody {
    priority: i32,
}

async fn priority(
    State(ctx): State<Ctx>,
    Path(id): Path<String>,
    headers: HeaderMap,
    Json(body): Json<PriorityBody>,
) -> Result<Response, ApiError> {
    let user = user(&ctx, &headers)?;
    job_id(&id)?;
    let state = ctx
        .coordinator
        .off_runtime(move |c| c.set_priority(&id, body.priority, user.as_ref()))
        .await?;
    Ok(Json(serde_json::json!({ "state": state_name(state) })).into_response())
}
