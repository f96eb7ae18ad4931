//! Talking to a coordinator: one place that connects, and one place that turns gRPC failures
//! into sentences a person can act on ("the coordinator is unreachable", "INVALID_ARGUMENT:
//! width must be ..."), so every cluster command reports errors the same way.

use std::error::Error as _;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, anyhow};
use clap::Args;
use rayfarm_node::proto;
use rayfarm_node::proto::job_service_client::JobServiceClient;
use rayfarm_node::security::{ClientSecurity, ConnectTlsArgs, Credential, first_token};
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{Channel, Identity};

/// Images of big frames travel in one message; the default 4 MiB limit would refuse them.
const MAX_MESSAGE_BYTES: usize = 256 << 20;

/// Deadline of every call until the coordinator's answer begins (a watch stream then runs as
/// long as the job does).
const RPC_DEADLINE: Duration = Duration::from_secs(60);

/// The coordinator cannot be reached, or the connection to it broke: it is down, restarting,
/// or the network is. Worth retrying, unlike a refusal by a coordinator that is up.
#[derive(Debug, thiserror::Error)]
#[error("UNAVAILABLE: coordinator at {url} is unreachable: {reason}")]
pub struct Unavailable {
    /// The coordinator's URL.
    pub url: String,
    /// What the transport said.
    pub reason: String,
}

/// Whether `e` says the coordinator was unreachable (see [`Unavailable`]).
pub fn is_unavailable(e: &anyhow::Error) -> bool {
    e.chain().any(|c| c.is::<Unavailable>())
}

/// Whether a failed call means the connection to the coordinator is gone rather than that a
/// coordinator that is up refused the call.
pub fn connection_lost(status: &tonic::Status) -> bool {
    match status.code() {
        tonic::Code::Unavailable => true,
        // A status the client made up from a broken connection ("h2 protocol error: error
        // reading a body from connection" when the coordinator dies mid-stream) carries the
        // transport's error as its source; a status the server sent carries none.
        tonic::Code::Unknown | tonic::Code::Internal | tonic::Code::Cancelled => {
            status.source().is_some()
        }
        _ => false,
    }
}

/// The `--coordinator` option every cluster command takes.
#[derive(Args, Clone, Debug)]
pub struct CoordinatorArgs {
    /// Coordinator address: http://HOST:PORT, or HOST:PORT.
    #[arg(
        long,
        env = "RAYFARM_COORDINATOR",
        default_value = "http://127.0.0.1:50051"
    )]
    pub coordinator: String,
    #[command(flatten)]
    pub auth: ClientAuthArgs,
}

/// How a client proves itself to a coordinator: TLS and a user token (all off by default).
#[derive(Args, Clone, Debug)]
pub struct ClientAuthArgs {
    #[command(flatten)]
    pub tls: ConnectTlsArgs,
    #[command(flatten)]
    pub cert: ClientCertArgs,
    /// User token for the job API (prefer RAYFARM_TOKEN or --token-file: a flag's value
    /// shows in process lists).
    #[arg(
        long,
        env = "RAYFARM_TOKEN",
        hide_env_values = true,
        conflicts_with = "token_file"
    )]
    pub token: Option<String>,
    /// File whose first token is presented (a coordinator's user tokens file works).
    #[arg(long, env = "RAYFARM_TOKEN_FILE")]
    pub token_file: Option<PathBuf>,
}

/// The certificate a client presents to a server that requires one (mutual TLS).
#[derive(Args, Clone, Debug)]
pub struct ClientCertArgs {
    /// PEM certificate to present when the server requires client certificates.
    #[arg(long, env = "RAYFARM_TLS_CERT", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// PEM private key of --tls-cert.
    #[arg(long, env = "RAYFARM_TLS_KEY", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
}

impl ClientCertArgs {
    /// The certificate and key, read, if given.
    pub fn identity(&self) -> anyhow::Result<Option<Identity>> {
        match (&self.tls_cert, &self.tls_key) {
            (Some(cert), Some(key)) => {
                let read = |p: &PathBuf| {
                    std::fs::read(p).with_context(|| format!("reading {}", p.display()))
                };
                Ok(Some(Identity::from_pem(read(cert)?, read(key)?)))
            }
            _ => Ok(None),
        }
    }
}

impl ClientAuthArgs {
    /// TLS and the user token these options ask for.
    pub fn security(&self) -> anyhow::Result<ClientSecurity> {
        let identity = self.cert.identity()?;
        let token = match &self.token_file {
            Some(path) => Some(first_token(path)?),
            None => self.token.clone(),
        };
        Ok(ClientSecurity {
            tls: self.tls.client_config(identity)?,
            credential: Credential::bearer(token.as_deref())?,
        })
    }
}

impl CoordinatorArgs {
    /// Connects to the coordinator these options name, with their TLS and token.
    pub async fn connect(&self) -> anyhow::Result<Coordinator> {
        Coordinator::connect_with(&self.coordinator, &self.auth.security()?).await
    }
}

/// The async runtime of one command. The commands are I/O-bound request/response clients,
/// so one thread is plenty.
pub fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")
}

/// A connected coordinator. Every call maps a failure to a readable error.
#[derive(Clone)]
pub struct Coordinator {
    url: String,
    /// The address as given and how it was reached, to connect again the same way.
    addr: String,
    security: ClientSecurity,
    client: JobServiceClient<InterceptedService<Channel, Credential>>,
}

impl Coordinator {
    /// Connects to the coordinator at `addr` in plain text without credentials (local
    /// clusters); fails fast if nothing answers there.
    pub async fn connect(addr: &str) -> anyhow::Result<Self> {
        Self::connect_with(addr, &ClientSecurity::default()).await
    }

    /// Connects to the coordinator at `addr` with `security`.
    pub async fn connect_with(addr: &str, security: &ClientSecurity) -> anyhow::Result<Self> {
        let url = security.url(addr);
        let endpoint = security
            .endpoint(addr)
            .map_err(|e| anyhow!("{}", chain(&e)))?
            .timeout(RPC_DEADLINE);
        let channel = endpoint.connect().await.map_err(|e| Unavailable {
            url: url.clone(),
            reason: chain(&e),
        })?;
        let client = JobServiceClient::with_interceptor(channel, security.credential.clone())
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES);
        Ok(Self {
            url,
            addr: addr.to_string(),
            security: security.clone(),
            client,
        })
    }

    /// Connects again to the same coordinator, retrying unreachable ones with exponential
    /// backoff (250 ms to 5 s, with jitter) until `deadline`; then fails with the last
    /// [`Unavailable`].
    pub async fn reconnect(&mut self, deadline: tokio::time::Instant) -> anyhow::Result<()> {
        let mut delay = Duration::from_millis(250);
        loop {
            match Self::connect_with(&self.addr, &self.security).await {
                Ok(fresh) => {
                    *self = fresh;
                    return Ok(());
                }
                Err(e) if is_unavailable(&e) && tokio::time::Instant::now() < deadline => {
                    tracing::debug!(error = %e, ?delay, "coordinator still unreachable");
                }
                Err(e) => return Err(e),
            }
            // Jitter from the clock's nanoseconds: many clients of a restarted coordinator do
            // not come back in step.
            let nanos = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.subsec_nanos());
            let jitter = delay.mul_f64(f64::from(nanos % 1000) / 2000.0);
            let now = tokio::time::Instant::now();
            tokio::time::sleep_until((now + delay + jitter).min(deadline)).await;
            delay = (delay * 2).min(Duration::from_secs(5));
        }
    }

    /// The URL connected to.
    pub fn url(&self) -> &str {
        &self.url
    }

    /// A failed call as a readable error.
    pub fn rpc_error(&self, status: &tonic::Status) -> anyhow::Error {
        rpc_error(&self.url, status)
    }

    /// Queues a job; returns its id.
    pub async fn submit(&mut self, spec: proto::JobSpec) -> anyhow::Result<String> {
        let req = proto::SubmitJobRequest { spec: Some(spec) };
        let resp = self.client.submit_job(req).await;
        Ok(resp.map_err(|s| self.rpc_error(&s))?.into_inner().job_id)
    }

    /// The progress events of a job, until it ends.
    pub async fn watch(
        &mut self,
        job_id: &str,
    ) -> anyhow::Result<tonic::Streaming<proto::WatchJobResponse>> {
        let req = proto::WatchJobRequest {
            job_id: job_id.to_string(),
        };
        let resp = self.client.watch_job(req).await;
        Ok(resp.map_err(|s| self.rpc_error(&s))?.into_inner())
    }

    /// The newest `limit` jobs (every job with `None`), newest first, a page at a time.
    pub async fn jobs(&mut self, limit: Option<usize>) -> anyhow::Result<Vec<proto::JobSummary>> {
        let mut jobs = Vec::new();
        let mut page_token = String::new();
        loop {
            let wanted = limit.map_or(usize::MAX, |l| l - jobs.len());
            let req = proto::ListJobsRequest {
                page_size: wanted.min(1000) as u32,
                page_token,
            };
            let resp = self.client.list_jobs(req).await;
            let page = resp.map_err(|s| self.rpc_error(&s))?.into_inner();
            jobs.extend(page.jobs);
            if page.next_page_token.is_empty() || limit.is_some_and(|l| jobs.len() >= l) {
                jobs.truncate(limit.unwrap_or(usize::MAX));
                return Ok(jobs);
            }
            page_token = page.next_page_token;
        }
    }

    /// Cancels a job; returns its state after the request.
    pub async fn cancel(&mut self, job_id: &str) -> anyhow::Result<proto::JobState> {
        let req = proto::CancelJobRequest {
            job_id: job_id.to_string(),
        };
        let resp = self.client.cancel_job(req).await;
        Ok(resp.map_err(|s| self.rpc_error(&s))?.into_inner().state())
    }

    /// Changes a queued job's priority; returns its state.
    pub async fn set_priority(
        &mut self,
        job_id: &str,
        priority: i32,
    ) -> anyhow::Result<proto::JobState> {
        let req = proto::SetJobPriorityRequest {
            job_id: job_id.to_string(),
            priority,
        };
        let resp = self.client.set_job_priority(req).await;
        Ok(resp.map_err(|s| self.rpc_error(&s))?.into_inner().state())
    }

    /// A finished job's image file as a stream of chunks from byte `offset`; the first
    /// carries the file's size and checksum.
    pub async fn fetch_stream(
        &mut self,
        job_id: &str,
        format: proto::ImageFormat,
        offset: u64,
    ) -> anyhow::Result<tonic::Streaming<proto::FetchResultChunk>> {
        let req = proto::FetchResultStreamRequest {
            job_id: job_id.to_string(),
            format: format as i32,
            offset,
            chunk_bytes: 0,
        };
        let resp = self.client.fetch_result_stream(req).await;
        Ok(resp.map_err(|s| self.rpc_error(&s))?.into_inner())
    }

    /// The latest preview of a running or recently finished job.
    pub async fn preview(&mut self, job_id: &str) -> anyhow::Result<proto::FetchPreviewResponse> {
        let req = proto::FetchPreviewRequest {
            job_id: job_id.to_string(),
        };
        let resp = self.client.fetch_preview(req).await;
        Ok(resp.map_err(|s| self.rpc_error(&s))?.into_inner())
    }

    /// The workers and the running job.
    pub async fn cluster_status(&mut self) -> anyhow::Result<proto::GetClusterStatusResponse> {
        let resp = self
            .client
            .get_cluster_status(proto::GetClusterStatusRequest {})
            .await;
        Ok(resp.map_err(|s| self.rpc_error(&s))?.into_inner())
    }
}

/// A failed call as a readable error: an unreachable coordinator (or a broken connection) is
/// an [`Unavailable`]; anything else is the status code's protobuf name and the server's
/// message.
pub fn rpc_error(url: &str, status: &tonic::Status) -> anyhow::Error {
    let message = if status.message().is_empty() {
        status.code().description().to_string()
    } else {
        status.message().to_string()
    };
    if connection_lost(status) {
        // A failure on this side of the connection carries its cause as a source; a server's
        // answer never does. The cause is the useful part ("certificate required").
        let local = status.source();
        let detail = match local.map(chain) {
            Some(cause) if cause.starts_with(&message) => cause,
            Some(cause) => format!("{message}: {cause}"),
            None => message,
        };
        // A TLS server hangs up on a plain-text client, and on a client without the
        // certificate it requires, with errors that say nothing about TLS: say what to check.
        let hint = if status.code() == tonic::Code::Unavailable || local.is_none() {
            ""
        } else if url.starts_with("http://") {
            " (if it serves TLS, give the CA that signed its certificate: --tls-ca or \
             RAYFARM_TLS_CA)"
        } else {
            " (if it requires client certificates, give --tls-cert and --tls-key)"
        };
        return Unavailable {
            url: url.to_string(),
            reason: format!("{detail}{hint}"),
        }
        .into();
    }
    // A worker's port (or another gRPC server) answers the job API with UNIMPLEMENTED.
    let hint = if status.code() == tonic::Code::Unimplemented {
        format!(
            " (is {url} a rayfarm coordinator? a worker's port serves only its peers and health \
             checks)"
        )
    } else {
        String::new()
    };
    anyhow!("{}: {message}{hint}", code_name(status.code()))
}

/// The protobuf name of a status code, as gRPC documents and other tools print it.
pub fn code_name(code: tonic::Code) -> &'static str {
    use tonic::Code::*;
    match code {
        Ok => "OK",
        Cancelled => "CANCELLED",
        Unknown => "UNKNOWN",
        InvalidArgument => "INVALID_ARGUMENT",
        DeadlineExceeded => "DEADLINE_EXCEEDED",
        NotFound => "NOT_FOUND",
        AlreadyExists => "ALREADY_EXISTS",
        PermissionDenied => "PERMISSION_DENIED",
        ResourceExhausted => "RESOURCE_EXHAUSTED",
        FailedPrecondition => "FAILED_PRECONDITION",
        Aborted => "ABORTED",
        OutOfRange => "OUT_OF_RANGE",
        Unimplemented => "UNIMPLEMENTED",
        Internal => "INTERNAL",
        Unavailable => "UNAVAILABLE",
        DataLoss => "DATA_LOSS",
        Unauthenticated => "UNAUTHENTICATED",
    }
}

/// An error and its sources on one line ("transport error: connection refused"), skipping a
/// source that repeats its parent's text. Transport errors hide the useful part in sources.
fn chain(e: &(dyn std::error::Error + 'static)) -> String {
    let mut parts: Vec<String> = vec![e.to_string()];
    let mut source = e.source();
    while let Some(s) = source {
        let text = s.to_string();
        if parts.last().is_none_or(|last| !last.contains(&text)) {
            parts.push(text);
        }
        source = s.source();
    }
    parts.join(": ")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rpc_errors_name_the_code_or_the_unreachable_coordinator() {
        let url = "http://127.0.0.1:1";
        let e = rpc_error(url, &tonic::Status::invalid_argument("width must be >= 1"));
        assert_eq!(e.to_string(), "INVALID_ARGUMENT: width must be >= 1");
        let e = rpc_error(url, &tonic::Status::unavailable("connection reset"));
        assert!(is_unavailable(&e));
        assert_eq!(
            e.to_string(),
            "UNAVAILABLE: coordinator at http://127.0.0.1:1 is unreachable: connection reset"
        );
        // UNKNOWN from a broken connection (it has the transport's error as its source) is
        // the coordinator going away; UNKNOWN sent by a server is not.
        let broken = tonic::Status::from_error(
            "h2 protocol error: error reading a body from connection".into(),
        );
        assert_eq!(broken.code(), tonic::Code::Unknown);
        assert!(connection_lost(&broken));
        assert!(is_unavailable(&rpc_error(url, &broken)));
        let sent = tonic::Status::unknown("the server says so");
        assert!(!connection_lost(&sent));
        assert!(!is_unavailable(&rpc_error(url, &sent)));
        let e = rpc_error(url, &tonic::Status::new(tonic::Code::NotFound, ""));
        assert!(e.to_string().starts_with("NOT_FOUND: "), "{e}");
        let e = rpc_error(
            url,
            &tonic::Status::from_error(Box::new(std::io::Error::other("broken pipe"))),
        );
        assert!(e.to_string().contains("is unreachable"), "{e}");
        assert!(e.to_string().contains("broken pipe"), "{e}");
        assert!(e.to_string().contains("--tls-ca"), "{e}");
    }

    #[test]
    fn an_unreachable_coordinator_is_reported_as_such() {
        // Port 1 on loopback: nothing listens there in a test environment.
        let rt = runtime().unwrap();
        let err = rt
            .block_on(Coordinator::connect("127.0.0.1:1"))
            .err()
            .unwrap();
        let text = format!("{err:#}");
        assert!(is_unavailable(&err));
        assert!(
            text.starts_with("UNAVAILABLE: coordinator at http://127.0.0.1:1 is unreachable: "),
            "{text}"
        );
    }
}
