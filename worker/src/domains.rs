//! Domains between workers (the paper's data requests): this worker serves the domains it
//! has loaded to its peers (`FetchDomain`, [`Serving`]), and fetches a domain from a peer
//! that holds it when its cache decides that is cheaper than storage ([`Fetcher`], the
//! cache's `PeerSource`). The cache checks what arrives like a file from storage; here only
//! the transfer's own bounds are kept: the sizes the manifest gives, chunk sizes, one
//! deadline for the whole transfer.
//!
//! Serving is guarded like the bundle stream (the cluster secret by the service's
//! interceptor; under mutual TLS the requester is its certificate's name), answers only for
//! the worker's current frame, when that frame loads from peers, by domain index (never a
//! path), and runs at most [`MAX_TRANSFERS`] transfers at once, one per requester.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
use rayfarm_core::render::cache::Shelf;
use rayfarm_core::render::cache::peers::{PeerError, PeerSource};
use rayfarm_core::scene::Received;
use rayfarm_node::proto::peer_service_client::PeerServiceClient;
use rayfarm_node::proto::{self, PROTOCOL_VERSION};
use rayfarm_node::security::ClientSecurity;
use rayfarm_node::{bounds, metrics};
use tokio::sync::{Semaphore, mpsc};
use tokio_stream::Stream;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;
use tonic::{Request, Status};
use tracing::{debug, warn};

/// Most transfers this worker serves at once; more requests are refused at once (the
/// requester loads from storage), so serving never takes more than this many domains' worth
/// of memory past the cache's budget nor more of the link.
pub const MAX_TRANSFERS: usize = 4;

/// Largest chunk served (and taken), and the smallest served whatever the request asks:
/// defined with the request's checks, which clamp to them.
pub use rayfarm_node::requests::{MAX_DOMAIN_CHUNK as MAX_CHUNK, MIN_DOMAIN_CHUNK as MIN_CHUNK};

/// A requester that takes no chunk for this long ends its transfer (its slot is freed).
const SEND_DEADLINE: Duration = Duration::from_secs(10);

/// How long connecting to a peer for a domain may take, within the transfer's deadline.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(2);

/// Test instrumentation, off unless `RAYFARM_FAULT_SERVE_DOMAINS` is set: how this worker
/// misbehaves when serving domains, so process tests can show a requester refusing it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ServeFault {
    /// One byte of the file flipped.
    Corrupt,
    /// Sizes announced one byte larger than the file, and a byte more sent.
    Oversize,
    /// Chunks of the smallest size, each after the first held back 300 ms (a stalling
    /// peer; killed mid-transfer in tests).
    Slow,
}

impl ServeFault {
    /// Reads `RAYFARM_FAULT_SERVE_DOMAINS` (`corrupt`, `oversize`, `slow`).
    pub fn from_env() -> Option<ServeFault> {
        match std::env::var("RAYFARM_FAULT_SERVE_DOMAINS").ok()?.trim() {
            "corrupt" => Some(ServeFault::Corrupt),
            "oversize" => Some(ServeFault::Oversize),
            "slow" => Some(ServeFault::Slow),
            _ => None,
        }
    }
}

/// What this worker serves: its current frame's loaded domains, when that frame loads
/// domains from peers. Set by the engine when a frame opens, cleared when it goes.
#[derive(Clone, Default)]
pub struct Serving {
    current: Arc<Mutex<Option<(String, Shelf)>>>,
    slots: Arc<SlotsInner>,
    fault: Option<ServeFault>,
}

struct SlotsInner {
    transfers: Arc<Semaphore>,
    requesters: Mutex<HashSet<String>>,
}

impl Default for SlotsInner {
    fn default() -> Self {
        SlotsInner {
            transfers: Arc::new(Semaphore::new(MAX_TRANSFERS)),
            requesters: Mutex::new(HashSet::new()),
        }
    }
}

/// A requester's one transfer; leaving frees its name.
struct Requester {
    slots: Arc<SlotsInner>,
    name: String,
}

impl Drop for Requester {
    fn drop(&mut self) {
        lock(&self.slots.requesters).remove(&self.name);
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// The stream of a served domain's chunks.
pub type ChunkStream = Pin<Box<dyn Stream<Item = Result<proto::DomainChunk, Status>> + Send>>;

impl Serving {
    /// Nothing served until a frame that loads from peers opens.
    pub fn new(fault: Option<ServeFault>) -> Self {
        if let Some(f) = fault {
            warn!(
                ?f,
                "domain serving misbehaves on purpose (test instrumentation)"
            );
        }
        Serving {
            fault,
            ..Serving::default()
        }
    }

    /// Serves `shelf`'s domains to peers asking for frame `job_id`; `None`: serves nothing.
    pub fn set(&self, current: Option<(String, Shelf)>) {
        *lock(&self.current) = current;
    }

    /// The `FetchDomain` call: checks the request, takes a slot, and streams the domain.
    pub fn serve(&self, request: Request<proto::DomainRequest>) -> Result<ChunkStream, Status> {
        let remote = rayfarm_node::listen::remote_addr(&request)
            .map_or_else(|| "unknown".to_string(), |a| a.to_string());
        let certified = rayfarm_node::identity::of_request(&request);
        let req = request.into_inner();
        let chunk = rayfarm_node::requests::domain_request(&req)?;
        if let Some(id) = &certified
            && req.sender != id.name
        {
            warn!(%remote, sender = %req.sender, certificate = %id.name,
                "refusing a domain request whose sender is not its certificate's name");
            return Err(Status::permission_denied(format!(
                "sender {} is not the name of the client certificate ({})",
                req.sender, id.name
            )));
        }
        let shelf = match &*lock(&self.current) {
            Some((job, shelf)) if *job == req.job_id => shelf.clone(),
            _ => {
                return Err(Status::failed_precondition(format!(
                    "frame {} is not this worker's current frame loading from peers",
                    bounds::shown(&req.job_id)
                )));
            }
        };
        let data = shelf.get(req.domain).ok_or_else(|| {
            Status::not_found(format!("domain {} is not loaded here", req.domain))
        })?;
        let permit = self
            .slots
            .transfers
            .clone()
            .try_acquire_owned()
            .map_err(|_| Status::resource_exhausted("serving the most domains at once"))?;
        if !lock(&self.slots.requesters).insert(req.sender.clone()) {
            return Err(Status::resource_exhausted(
                "already serving this requester a domain",
            ));
        }
        let requester = Requester {
            slots: self.slots.clone(),
            name: req.sender.clone(),
        };
        let fault = self.fault;
        let chunk = match fault {
            Some(ServeFault::Slow) => MIN_CHUNK,
            _ => chunk,
        };
        let (tx, rx) = mpsc::channel(2);
        debug!(%remote, sender = %req.sender, domain = req.domain, bytes = data.bytes(),
            "serving a domain to a peer");
        tokio::spawn(async move {
            let _slot = (permit, requester);
            let file = data.file_bytes();
            let surfaces = data.surfaces().map_or(&[][..], |s| s.file_bytes());
            let mut announced = [file.len() as u64, surfaces.len() as u64];
            if fault == Some(ServeFault::Oversize) {
                announced[0] += 1;
            }
            let mut first = true;
            let mut sent = 0u64;
            let pieces = file.chunks(chunk).chain(surfaces.chunks(chunk));
            let extra = (fault == Some(ServeFault::Oversize)).then_some(&[0u8][..]);
            for piece in pieces.chain(extra) {
                let mut bytes = piece.to_vec();
                if fault == Some(ServeFault::Corrupt) && sent == 0 {
                    let last = bytes.len() - 1;
                    bytes[last] ^= 0x40;
                }
                if fault == Some(ServeFault::Slow) && sent > 0 {
                    tokio::time::sleep(Duration::from_millis(300)).await;
                }
                sent += bytes.len() as u64;
                let (file_bytes, surfaces_bytes) = match std::mem::take(&mut first) {
                    true => (announced[0], announced[1]),
                    false => (0, 0),
                };
                let msg = proto::DomainChunk {
                    file_bytes,
                    surfaces_bytes,
                    data: Bytes::from(bytes),
                };
                if tx.send_timeout(Ok(msg), SEND_DEADLINE).await.is_err() {
                    debug!(domain = req.domain, sent, "the requester left the transfer");
                    return;
                }
            }
            metrics::worker().domain_bytes_served.inc_by(sent);
            debug!(domain = req.domain, sent, "domain served");
        });
        Ok(Box::pin(ReceiverStream::new(rx)))
    }
}

/// A worker's side of domains between workers, as the engine holds it.
pub struct PeerDomains {
    /// What the cache loads from peers with, when a frame asks for it (rates are kept
    /// across frames).
    pub loads: Arc<rayfarm_core::render::cache::peers::PeerLoads>,
    /// Who holds the domains about to be loaded.
    pub hints: FetchHints,
    /// What this worker serves.
    pub serving: Serving,
}

/// Which frame this worker fetches for and who holds what, as the engine last told it: the
/// holders of the domains a pass or prefetch is about to load.
#[derive(Default)]
struct Hints {
    job_id: String,
    holders: BTreeMap<u32, Vec<String>>,
}

/// Most domains whose holders are remembered (a pass's and a prefetch's at a time).
const HINTS: usize = 8;

/// The cache's way to a peer's domains: the `FetchDomain` client, blocking on the runtime
/// from a loading thread (a pass on the tracing pool, a prefetch on a blocking thread).
pub struct Fetcher {
    me: String,
    security: ClientSecurity,
    runtime: tokio::runtime::Handle,
    link_bandwidth: Option<u64>,
    hints: Arc<Mutex<Hints>>,
    channels: Mutex<HashMap<String, Channel>>,
}

/// The engine's handle on what the [`Fetcher`] knows of the frame.
#[derive(Clone, Default)]
pub struct FetchHints(Arc<Mutex<Hints>>);

impl FetchHints {
    /// Fetches are for frame `job_id` from now on; holders of another frame are forgotten.
    pub fn set_frame(&self, job_id: &str) {
        let mut h = lock(&self.0);
        if h.job_id != job_id {
            h.job_id = job_id.to_string();
            h.holders.clear();
        }
    }

    /// Other workers holding `domain` now (the latest plan's word), for its next load.
    pub fn set_holders(&self, domain: u32, holders: &[String]) {
        let mut h = lock(&self.0);
        if h.holders.len() >= HINTS && !h.holders.contains_key(&domain) {
            h.holders.clear();
        }
        h.holders.insert(domain, holders.to_vec());
    }
}

impl Fetcher {
    /// A fetcher for the worker `me`, connecting with `security`; `link_bandwidth` when the
    /// peer links' speed is known (else measured). Returns the engine's hints handle too.
    pub fn new(
        me: String,
        security: ClientSecurity,
        runtime: tokio::runtime::Handle,
        link_bandwidth: Option<u64>,
    ) -> (Fetcher, FetchHints) {
        let hints = FetchHints::default();
        let fetcher = Fetcher {
            me,
            security,
            runtime,
            link_bandwidth,
            hints: hints.0.clone(),
            channels: Mutex::new(HashMap::new()),
        };
        (fetcher, hints)
    }

    async fn channel(&self, peer: &str) -> Result<Channel, String> {
        if let Some(c) = lock(&self.channels).get(peer) {
            return Ok(c.clone());
        }
        let endpoint = self
            .security
            .endpoint(peer)
            .map_err(|e| e.to_string())?
            .connect_timeout(CONNECT_TIMEOUT);
        let channel = endpoint.connect().await.map_err(|e| e.to_string())?;
        lock(&self.channels).insert(peer.to_string(), channel.clone());
        Ok(channel)
    }

    async fn transfer(
        &self,
        peer: &str,
        job_id: String,
        domain: u32,
        bytes: u64,
        has_surfaces: bool,
    ) -> Result<(Received, Option<Received>), PeerError> {
        let failed = PeerError::Failed;
        let channel = self.channel(peer).await.map_err(failed)?;
        let mut client =
            PeerServiceClient::with_interceptor(channel, self.security.credential.clone())
                .max_decoding_message_size(MAX_CHUNK + 4096);
        let request = proto::DomainRequest {
            protocol_version: PROTOCOL_VERSION,
            sender: self.me.clone(),
            job_id,
            domain,
            max_chunk_bytes: MAX_CHUNK as u32,
        };
        let mut chunks = client
            .fetch_domain(request)
            .await
            .map_err(|s| {
                let reason = format!("{:?}: {}", s.code(), s.message());
                // The peer's own quick answers that it cannot serve this now.
                match s.code() {
                    tonic::Code::NotFound
                    | tonic::Code::FailedPrecondition
                    | tonic::Code::ResourceExhausted => PeerError::Refused(reason),
                    _ => PeerError::Failed(reason),
                }
            })?
            .into_inner();
        let mut parts: Option<(Received, Option<Received>)> = None;
        while let Some(chunk) = chunks
            .message()
            .await
            .map_err(|s| failed(format!("{:?}: {}", s.code(), s.message())))?
        {
            let (file, surfaces) = match &mut parts {
                Some(p) => p,
                None => {
                    // The sizes come first and must be the manifest's before anything is held.
                    let (f, s) = (chunk.file_bytes, chunk.surfaces_bytes);
                    if f.checked_add(s) != Some(bytes) || (s > 0) != has_surfaces || f == 0 {
                        return Err(failed(format!(
                            "announced {f} + {s} bytes; the manifest says {bytes} in {} file{}",
                            1 + has_surfaces as u32,
                            if has_surfaces { "s" } else { "" }
                        )));
                    }
                    let file = Received::new(f, None).map_err(|e| failed(e.to_string()))?;
                    let surfaces = if has_surfaces {
                        Some(Received::new(s, None).map_err(|e| failed(e.to_string()))?)
                    } else {
                        None
                    };
                    parts.insert((file, surfaces))
                }
            };
            if chunk.data.len() > MAX_CHUNK {
                return Err(failed(format!("a chunk of {} bytes", chunk.data.len())));
            }
            // The file's remaining bytes, then the surfaces'.
            let mut data = &chunk.data[..];
            let into_file = (data.len() as u64).min(file.missing()) as usize;
            file.push(&data[..into_file]).map_err(failed)?;
            data = &data[into_file..];
            if !data.is_empty() {
                match surfaces {
                    Some(s) => s.push(data).map_err(failed)?,
                    None => return Err(failed(format!("{} bytes past the file", data.len()))),
                }
            }
        }
        let (file, surfaces) = parts.ok_or_else(|| failed("the peer sent nothing".into()))?;
        let missing = file.missing() + surfaces.as_ref().map_or(0, |s| s.missing());
        if missing > 0 {
            return Err(failed(format!("the transfer ended {missing} bytes short")));
        }
        Ok((file, surfaces))
    }
}

impl PeerSource for Fetcher {
    fn holders(&self, domain: u32) -> Vec<String> {
        lock(&self.hints)
            .holders
            .get(&domain)
            .cloned()
            .unwrap_or_default()
    }

    fn link_bandwidth(&self) -> Option<u64> {
        self.link_bandwidth
    }

    fn fetch(
        &self,
        peer: &str,
        domain: u32,
        bytes: u64,
        surfaces: bool,
        deadline: Instant,
    ) -> Result<(Received, Option<Received>), PeerError> {
        let job_id = lock(&self.hints).job_id.clone();
        let started = Instant::now();
        let transfer = self.transfer(peer, job_id, domain, bytes, surfaces);
        let result = self.runtime.block_on(async {
            match tokio::time::timeout_at(deadline.into(), transfer).await {
                Ok(r) => r,
                Err(_) => Err(PeerError::Failed(format!(
                    "no whole domain within {:.2} s (a stalled peer)",
                    deadline.saturating_duration_since(started).as_secs_f64()
                ))),
            }
        });
        match &result {
            Ok(_) => debug!(%peer, domain, bytes, ms = started.elapsed().as_millis() as u64,
                "domain transferred from a peer"),
            Err(PeerError::Refused(_)) => {}
            Err(PeerError::Failed(_)) => {
                // A broken connection is not reused.
                lock(&self.channels).remove(peer);
            }
        }
        result
    }
}
