//! Worker-to-worker ray traffic: outbound links (one long-lived `ExchangeBundles` stream per
//! peer, opened on first use) and the service that receives peers' bundles.

use std::collections::{HashMap, VecDeque};
use std::pin::Pin;
use std::time::{Duration, Instant};

use bytes::Bytes;
use rayfarm_core::bundler::Tier;
use rayfarm_core::wire::{self, BatchLimits, WireError};
use rayfarm_node::proto::peer_service_client::PeerServiceClient;
use rayfarm_node::proto::peer_service_server::PeerService;
use rayfarm_node::proto::{self, PROTOCOL_VERSION};
use rayfarm_node::security::ClientSecurity;
use tokio::sync::mpsc;
use tokio_stream::Stream;
use tokio_stream::wrappers::{ReceiverStream, UnboundedReceiverStream};
use tonic::{Request, Response, Status, Streaming};
use tracing::{debug, error, warn};

use crate::domains::{ChunkStream, Serving};
use crate::engine::Event;
use rayfarm_machine::worker as machine;
use rayfarm_node::fault::Faults;

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
    limits: LinkLimits,
    /// Where a link reports a peer that stopped acknowledging.
    events: mpsc::UnboundedSender<Event>,
    links: HashMap<String, Link>,
    sequence: u64,
}

/// How much a link lets a peer owe it.
#[derive(Clone, Copy, Debug)]
pub struct LinkLimits {
    /// Bundles sent and not yet acknowledged; more wait in this worker.
    pub window: usize,
    /// A peer that acknowledges nothing for this long is reported as unresponsive.
    pub ack_deadline: Duration,
}

/// One outbound stream: its queue and the task that drains it.
struct Link {
    tx: mpsc::UnboundedSender<proto::PeerBundle>,
    task: tokio::task::JoinHandle<()>,
}

impl PeerLinks {
    /// Links from the worker called `me`, connecting with `security`.
    pub fn new(
        me: String,
        faults: Faults,
        security: ClientSecurity,
        limits: LinkLimits,
        events: mpsc::UnboundedSender<Event>,
    ) -> Self {
        PeerLinks {
            me,
            faults,
            security,
            limits,
            events,
            links: HashMap::new(),
            sequence: 0,
        }
    }

    /// Closes the links to `peers` (they are gone) and frees what waits for them.
    pub fn drop_peers(&mut self, peers: &[String]) {
        for peer in peers {
            if let Some(link) = self.links.remove(peer) {
                link.task.abort();
            }
        }
    }

    fn open(&self, peer: &str) -> Link {
        open_link(
            peer.to_string(),
            self.faults,
            &self.security,
            self.limits,
            self.events.clone(),
        )
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
        if !self.links.contains_key(peer) {
            let link = self.open(peer);
            self.links.insert(peer.to_string(), link);
        }
        let Some(link) = self.links.get(peer) else {
            return;
        };
        if let Err(mpsc::error::SendError(bundle)) = link.tx.send(bundle) {
            // The link task gave up on this peer; try a fresh link once. A bundle lost here
            // belongs to tiles whose epochs the coordinator bumps when it drops the peer.
            let fresh = self.open(peer);
            if fresh.tx.send(bundle).is_err() {
                error!(%peer, "cannot reach peer: bundle dropped");
            }
            self.links.insert(peer.to_string(), fresh);
        }
    }
}

fn proto_tier(tier: Tier) -> proto::Tier {
    match tier {
        Tier::Results => proto::Tier::Results,
        Tier::Migrated => proto::Tier::Migrated,
        Tier::Tasks => proto::Tier::Tasks,
    }
}

fn open_link(
    peer: String,
    faults: Faults,
    security: &ClientSecurity,
    limits: LinkLimits,
    events: mpsc::UnboundedSender<Event>,
) -> Link {
    let (tx, rx) = mpsc::unbounded_channel();
    let rx = faults.delayed(&peer, rx);
    let security = security.clone();
    let task = tokio::spawn(async move {
        match run_link(&peer, &security, limits, rx).await {
            Ok(()) => {}
            Err(LinkError::Unresponsive(reason)) => {
                error!(%peer, %reason, "peer unresponsive: reporting it to the coordinator");
                let lost = machine::Event::PeerUnresponsive { peer, reason };
                let _ = events.send(Event::Machine(Box::new(lost)));
            }
            Err(LinkError::Other(e)) => warn!(%peer, error = %e, "peer link ended"),
        }
    });
    Link { tx, task }
}

/// Why a link ended.
#[derive(Debug, thiserror::Error)]
enum LinkError {
    /// The peer holds bundles it never acknowledges: it is stuck or gone.
    #[error("{0}")]
    Unresponsive(String),
    #[error(transparent)]
    Other(#[from] anyhow::Error),
}

impl From<tonic::Status> for LinkError {
    fn from(s: tonic::Status) -> Self {
        LinkError::Other(s.into())
    }
}

async fn run_link(
    peer: &str,
    security: &ClientSecurity,
    limits: LinkLimits,
    mut rx: mpsc::UnboundedReceiver<proto::PeerBundle>,
) -> Result<(), LinkError> {
    let endpoint = security.endpoint(peer).map_err(anyhow::Error::from)?;
    let mut attempt = 0;
    // A hung peer accepts the TCP connection in its kernel and then answers nothing: every
    // step that waits on it has the acknowledgement deadline.
    let silent = |what: &str| {
        LinkError::Unresponsive(format!(
            "{what} within {:.1} s",
            limits.ack_deadline.as_secs_f64()
        ))
    };
    let channel = loop {
        let connected = tokio::time::timeout(limits.ack_deadline, endpoint.connect())
            .await
            .map_err(|_| silent("no connection"))?;
        match connected {
            Ok(c) => break c,
            Err(e) if attempt < CONNECT_ATTEMPTS => {
                attempt += 1;
                warn!(%peer, error = %e, attempt, "connecting to peer");
                tokio::time::sleep(Duration::from_millis(50 << attempt.min(5))).await;
            }
            Err(e) => return Err(anyhow::Error::from(e).into()),
        }
    };
    let mut client = PeerServiceClient::with_interceptor(channel, security.credential.clone())
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);
    // Never more than the window in the stream, so the window bounds what the peer owes.
    let (stream_tx, stream_rx) = mpsc::channel(limits.window.max(1));
    let opened = client.exchange_bundles(ReceiverStream::new(stream_rx));
    let mut acks = tokio::time::timeout(limits.ack_deadline, opened)
        .await
        .map_err(|_| silent("no answer to opening the bundle stream"))??
        .into_inner();
    // Sequence and send time of every bundle not yet acknowledged, oldest first.
    let mut owed: VecDeque<(u64, Instant)> = VecDeque::new();
    let mut check = tokio::time::interval(limits.ack_deadline / 4);
    loop {
        tokio::select! {
            bundle = rx.recv(), if owed.len() < limits.window.max(1) => {
                let Some(bundle) = bundle else { return Ok(()) };
                owed.push_back((bundle.sequence, Instant::now()));
                if stream_tx.send(bundle).await.is_err() {
                    return Err(anyhow::anyhow!("the stream to the peer closed").into());
                }
            }
            ack = acks.message() => {
                let Some(ack) = ack? else { return Ok(()) };
                debug!(%peer, sequence = ack.sequence, "bundle acknowledged");
                while owed.front().is_some_and(|&(s, _)| s <= ack.sequence) {
                    owed.pop_front();
                }
            }
            _ = check.tick() => {
                if let Some(&(_, sent)) = owed.front()
                    && sent.elapsed() > limits.ack_deadline
                {
                    return Err(LinkError::Unresponsive(format!(
                        "{} bundles unacknowledged, the oldest for {:.1} s",
                        owed.len(),
                        sent.elapsed().as_secs_f64()
                    )));
                }
            }
        }
    }
}

/// The `PeerService` of this worker: decodes each bundle once (`decode_bundle`) and hands it
/// to the engine; serves loaded domains (`crate::domains`).
pub struct PeerServer {
    events: mpsc::UnboundedSender<Event>,
    domains: Serving,
}

impl PeerServer {
    pub fn new(events: mpsc::UnboundedSender<Event>, domains: Serving) -> Self {
        PeerServer { events, domains }
    }
}

type AckStream = Pin<Box<dyn Stream<Item = Result<proto::PeerAck, Status>> + Send>>;

#[tonic::async_trait]
impl PeerService for PeerServer {
    type ExchangeBundlesStream = AckStream;
    type FetchDomainStream = ChunkStream;

    async fn fetch_domain(
        &self,
        request: Request<proto::DomainRequest>,
    ) -> Result<Response<ChunkStream>, Status> {
        self.domains.serve(request).map(Response::new)
    }

    async fn exchange_bundles(
        &self,
        request: Request<Streaming<proto::PeerBundle>>,
    ) -> Result<Response<AckStream>, Status> {
        let remote = rayfarm_node::listen::remote_addr(&request)
            .map_or_else(|| "unknown".to_string(), |a| a.to_string());
        // Under mutual TLS the sender is who its certificate names: a node holding another
        // node's cluster credentials still cannot send bundles under that node's id.
        let certified = rayfarm_node::identity::of_request(&request);
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
                if let Some(id) = &certified
                    && bundle.sender != id.name
                {
                    error!(
                        %remote,
                        sender = %rayfarm_node::bounds::shown(&bundle.sender),
                        certificate = %id.name,
                        "refusing a bundle whose sender is not its certificate's name"
                    );
                    let _ = acks.send(Err(Status::permission_denied(format!(
                        "bundle sender {} is not the name of the client certificate ({})",
                        rayfarm_node::bounds::shown(&bundle.sender),
                        id.name
                    ))));
                    break;
                }
                let payload = match decode_bundle(&bundle) {
                    Ok(payload) => payload,
                    // The whole bundle is refused, so the engine never sees half of one; the
                    // stream ends because a peer that sends one bad bundle cannot be trusted
                    // with the next.
                    Err(status) => {
                        error!(
                            %remote,
                            sender = %rayfarm_node::bounds::shown(&bundle.sender),
                            job = %rayfarm_node::bounds::shown(&bundle.job_id),
                            sequence = bundle.sequence,
                            code = ?status.code(),
                            error = %status.message(),
                            "refusing a bundle from a peer"
                        );
                        let _ = acks.send(Err(status));
                        break;
                    }
                };
                let sequence = bundle.sequence;
                let event = Event::Machine(Box::new(machine::Event::PeerBundle {
                    sender: bundle.sender,
                    job_id: bundle.job_id,
                    payload,
                }));
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

/// Decodes a bundle as far as it can be before its frame is known: the protocol version, the
/// tier, and each batch's structure and frame-independent record fields. The machine checks
/// the decoded records' frame ranges (domain, pixel, depth) against its frame; nothing is
/// decoded twice.
fn decode_bundle(bundle: &proto::PeerBundle) -> Result<machine::Payload, Status> {
    rayfarm_node::bounds::check_field("sender", &bundle.sender)?;
    rayfarm_node::bounds::check_field("job_id", &bundle.job_id)?;
    if bundle.protocol_version != PROTOCOL_VERSION {
        return Err(Status::failed_precondition(format!(
            "peer {} speaks protocol {}, this worker {PROTOCOL_VERSION}",
            bundle.sender, bundle.protocol_version
        )));
    }
    // The results tier carries verdicts (predictive schedule), the other two rays. Tier 1,
    // the control tier retired in protocol 6, is no `proto::Tier`: refused as unknown.
    let verdicts = match proto::Tier::try_from(bundle.tier) {
        Ok(proto::Tier::Results) => true,
        Ok(proto::Tier::Migrated | proto::Tier::Tasks) => false,
        Ok(proto::Tier::Unspecified) => {
            return Err(Status::invalid_argument(format!(
                "bundle {} has no tier",
                bundle.sequence
            )));
        }
        Err(_) => {
            return Err(Status::invalid_argument(format!(
                "bundle {} has unknown tier {}",
                bundle.sequence, bundle.tier
            )));
        }
    };
    let limits = BatchLimits::any_frame(MAX_BATCH_RECORDS);
    let refused = |i: usize, e: WireError| {
        let msg = format!("bundle {} batch {i}: {e}", bundle.sequence);
        match e {
            WireError::Magic
            | WireError::Reserved
            | WireError::Layout
            | WireError::Record { .. } => Status::invalid_argument(msg),
            WireError::Version(_) => Status::failed_precondition(msg),
            WireError::Length(_) | WireError::Count { .. } => Status::data_loss(msg),
            WireError::TooMany { .. } => Status::resource_exhausted(msg),
        }
    };
    let batches = bundle.batches.iter().enumerate();
    Ok(if verdicts {
        machine::Payload::Verdicts(
            batches
                .map(|(i, b)| wire::decode_verdicts(b, &limits).map_err(|e| refused(i, e)))
                .collect::<Result<_, _>>()?,
        )
    } else {
        machine::Payload::Rays(
            batches
                .map(|(i, b)| wire::decode_batch(b, &limits).map_err(|e| refused(i, e)))
                .collect::<Result<_, _>>()?,
        )
    })
}
