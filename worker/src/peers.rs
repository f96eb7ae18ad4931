//! Worker-to-worker ray traffic: outbound links (one long-lived `ExchangeBundles` stream per
//! peer, opened on first use) and the service that receives peers' bundles.

use std::collections::HashMap;
use std::pin::Pin;
use std::time::Duration;

use bytes::Bytes;
use rayfarm_common::bundler::Tier;
use rayfarm_common::proto::peer_service_client::PeerServiceClient;
use rayfarm_common::proto::peer_service_server::PeerService;
use rayfarm_common::proto::{self, PROTOCOL_VERSION};
use rayfarm_common::security::ClientSecurity;
use rayfarm_common::wire::{self, BatchLimits, WireError};
use tokio::sync::mpsc;
use tokio_stream::Stream;
use tokio_stream::wrappers::UnboundedReceiverStream;
use tonic::{Request, Response, Status, Streaming};
use tracing::{debug, error, warn};

use crate::engine::Event;
use rayfarm_common::fault::Faults;

/// Largest gRPC message accepted or sent between workers.
pub const MAX_MESSAGE_BYTES: usize = 64 << 20;

/// Most records in one batch from a peer: the engine's own limit.
const MAX_BATCH_RECORDS: usize = 1 << 20;

/// Times a link tries to connect before giving up on the peer.
const CONNECT_ATTEMPTS: u32 = 20;

/// Outbound streams to peers, by peer address.
pub struct PeerLinks {
    me: String,
    faults: Faults,
    security: ClientSecurity,
    links: HashMap<String, mpsc::UnboundedSender<proto::PeerBundle>>,
    sequence: u64,
}

impl PeerLinks {
    /// Links from the worker called `me`, connecting with `security`.
    pub fn new(me: String, faults: Faults, security: ClientSecurity) -> Self {
        PeerLinks {
            me,
            faults,
            security,
            links: HashMap::new(),
            sequence: 0,
        }
    }

    /// Sends one bundle to `peer`, opening the link if needed. Never blocks.
    pub fn send(&mut self, peer: &str, job_id: &str, tier: Tier, batches: Vec<Bytes>) {
        self.sequence += 1;
        let bundle = proto::PeerBundle {
            protocol_version: PROTOCOL_VERSION,
            sender: self.me.clone(),
            job_id: job_id.to_string(),
            tier: proto_tier(tier) as i32,
            sequence: self.sequence,
            batches,
        };
        debug!(%peer, sequence = self.sequence, "bundle sent");
        let link = self
            .links
            .entry(peer.to_string())
            .or_insert_with(|| open_link(peer.to_string(), self.faults, &self.security));
        if let Err(mpsc::error::SendError(bundle)) = link.send(bundle) {
            // The link task gave up on this peer; try a fresh link once.
            let fresh = open_link(peer.to_string(), self.faults, &self.security);
            if fresh.send(bundle).is_err() {
                error!(%peer, "cannot reach peer: bundle dropped");
            }
            self.links.insert(peer.to_string(), fresh);
        }
    }
}

fn proto_tier(tier: Tier) -> proto::Tier {
    match tier {
        Tier::Control => proto::Tier::Control,
        Tier::Results => proto::Tier::Results,
        Tier::Migrated => proto::Tier::Migrated,
        Tier::Tasks => proto::Tier::Tasks,
    }
}

fn open_link(
    peer: String,
    faults: Faults,
    security: &ClientSecurity,
) -> mpsc::UnboundedSender<proto::PeerBundle> {
    let (tx, rx) = mpsc::unbounded_channel();
    let rx = faults.delayed(&peer, rx);
    let security = security.clone();
    tokio::spawn(async move {
        if let Err(e) = run_link(&peer, &security, rx).await {
            warn!(%peer, error = %e, "peer link ended");
        }
    });
    tx
}

async fn run_link(
    peer: &str,
    security: &ClientSecurity,
    rx: mpsc::UnboundedReceiver<proto::PeerBundle>,
) -> anyhow::Result<()> {
    let endpoint = security
        .endpoint(peer)?
        .tcp_nodelay(true)
        .connect_timeout(Duration::from_secs(5));
    let mut attempt = 0;
    let channel = loop {
        match endpoint.connect().await {
            Ok(c) => break c,
            Err(e) if attempt < CONNECT_ATTEMPTS => {
                attempt += 1;
                warn!(%peer, error = %e, attempt, "connecting to peer");
                tokio::time::sleep(Duration::from_millis(50 << attempt.min(5))).await;
            }
            Err(e) => return Err(e.into()),
        }
    };
    let mut client = PeerServiceClient::with_interceptor(channel, security.credential.clone())
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);
    let mut acks = client
        .exchange_bundles(UnboundedReceiverStream::new(rx))
        .await?
        .into_inner();
    while let Some(ack) = acks.message().await? {
        debug!(%peer, sequence = ack.sequence, "bundle acknowledged");
    }
    Ok(())
}

/// The `PeerService` of this worker: decodes nothing itself, hands bundles to the engine.
pub struct PeerServer {
    events: mpsc::UnboundedSender<Event>,
}

impl PeerServer {
    pub fn new(events: mpsc::UnboundedSender<Event>) -> Self {
        PeerServer { events }
    }
}

type AckStream = Pin<Box<dyn Stream<Item = Result<proto::PeerAck, Status>> + Send>>;

#[tonic::async_trait]
impl PeerService for PeerServer {
    type ExchangeBundlesStream = AckStream;

    async fn exchange_bundles(
        &self,
        request: Request<Streaming<proto::PeerBundle>>,
    ) -> Result<Response<AckStream>, Status> {
        let remote = request
            .remote_addr()
            .map_or_else(|| "unknown".to_string(), |a| a.to_string());
        let mut inbound = request.into_inner();
        let events = self.events.clone();
        let (acks, ack_rx) = mpsc::unbounded_channel();
        tokio::spawn(async move {
            loop {
                let bundle = match inbound.message().await {
                    Ok(Some(b)) => b,
                    Ok(None) => break,
                    Err(status) => {
                        warn!(%remote, %status, "peer stream ended with an error");
                        break;
                    }
                };
                if let Err(status) = check_bundle(&bundle) {
                    // The whole bundle is refused, so the engine never sees half of one; the
                    // stream ends because a peer that sends one bad bundle cannot be trusted
                    // with the next.
                    error!(
                        %remote,
                        sender = %bundle.sender,
                        job = %bundle.job_id,
                        sequence = bundle.sequence,
                        code = ?status.code(),
                        error = %status.message(),
                        "refusing a bundle from a peer"
                    );
                    let _ = acks.send(Err(status));
                    break;
                }
                let sequence = bundle.sequence;
                let event = Event::PeerBundle {
                    sender: bundle.sender,
                    job_id: bundle.job_id,
                    batches: bundle.batches,
                };
                if events.send(event).is_err() {
                    break;
                }
                let _ = acks.send(Ok(proto::PeerAck {
                    sequence,
                    window_bytes: 0,
                }));
            }
        });
        Ok(Response::new(Box::pin(UnboundedReceiverStream::new(
            ack_rx,
        ))))
    }
}

/// Checks what can be checked before the bundle's frame is known: the protocol version, the
/// tier, and each batch's structure and frame-independent record fields. The engine checks the
/// rest (domain, pixel and depth ranges) against the frame.
fn check_bundle(bundle: &proto::PeerBundle) -> Result<(), Status> {
    if bundle.protocol_version != PROTOCOL_VERSION {
        return Err(Status::failed_precondition(format!(
            "peer {} speaks protocol {}, this worker {PROTOCOL_VERSION}",
            bundle.sender, bundle.protocol_version
        )));
    }
    if proto::Tier::try_from(bundle.tier).is_err() {
        return Err(Status::invalid_argument(format!(
            "bundle {} has unknown tier {}",
            bundle.sequence, bundle.tier
        )));
    }
    let limits = BatchLimits::any_frame(MAX_BATCH_RECORDS);
    for (i, batch) in bundle.batches.iter().enumerate() {
        if let Err(e) = wire::check_batch(batch, &limits) {
            let msg = format!("bundle {} batch {i}: {e}", bundle.sequence);
            return Err(match e {
                WireError::Magic | WireError::Reserved | WireError::Record { .. } => {
                    Status::invalid_argument(msg)
                }
                WireError::Version(_) => Status::failed_precondition(msg),
                WireError::Length(_) | WireError::Count { .. } => Status::data_loss(msg),
                WireError::TooMany { .. } => Status::resource_exhausted(msg),
            });
        }
    }
    Ok(())
}
