//! The transport part of a peer bundle's price: real bundles (those the calibration run's
//! workers sent) carried by the real gRPC peer service (`PeerService.ExchangeBundles`, the
//! stream and acknowledgements the worker binary uses) over loopback, without TLS as
//! `rayfarm bench`'s cluster runs, with the worker's window of unacknowledged bundles. Both
//! ends run in this process, so the process's CPU time over many sends is what one bundle
//! costs the sender's and the receiver's gRPC stacks together (framing, HTTP/2, the kernel's
//! sockets, protobuf encoding and decoding), the bundle's own decoding and the worker
//! machine's handling aside (`rayfarm_sim::calibrate` times those).

use std::pin::Pin;
use std::time::Duration;

use anyhow::Context;
use bytes::Bytes;
use rayfarm_node::proto::peer_service_client::PeerServiceClient;
use rayfarm_node::proto::peer_service_server::{PeerService, PeerServiceServer};
use rayfarm_node::proto::{self, PROTOCOL_VERSION};
use tokio::sync::mpsc;
use tokio_stream::Stream;
use tokio_stream::wrappers::{ReceiverStream, TcpListenerStream, UnboundedReceiverStream};
use tonic::{Request, Response, Status, Streaming};

/// Largest message either end accepts (the worker's `MAX_MESSAGE_BYTES`).
const MAX_MESSAGE_BYTES: usize = 64 << 20;
/// Bundles in flight on the link, unacknowledged (the worker's default `--peer-window`).
const WINDOW: usize = 64;
/// Bundle sizes timed: this many of the captured bundles, spread over their sizes.
const SIZES: usize = 12;
/// Bytes sent per timed size (at least `MIN_SENDS` bundles), so every size takes a while.
const BYTES_PER_SIZE: usize = 256 << 20;
const MIN_SENDS: usize = 200;
const MAX_SENDS: usize = 4000;

/// One timed size: payload bytes of the bundle and CPU nanoseconds a bundle took (both
/// ends), the mean over its sends.
#[derive(Clone, Copy, Debug)]
pub struct TransportSample {
    pub bytes: usize,
    pub sends: usize,
    pub ns: f64,
}

/// The receiving end: acknowledges every bundle once it is read, as the worker's peer service
/// does once it has queued it.
struct Sink;

type AckStream = Pin<Box<dyn Stream<Item = Result<proto::PeerAck, Status>> + Send>>;

#[tonic::async_trait]
impl PeerService for Sink {
    type ExchangeBundlesStream = AckStream;
    type FetchDomainStream = Pin<Box<dyn Stream<Item = Result<proto::DomainChunk, Status>> + Send>>;

    /// Not timed: the calibration prices bundles only.
    async fn fetch_domain(
        &self,
        _: Request<proto::DomainRequest>,
    ) -> Result<Response<Self::FetchDomainStream>, Status> {
        Err(Status::unimplemented(
            "the calibration sink serves no domains",
        ))
    }

    async fn exchange_bundles(
        &self,
        request: Request<Streaming<proto::PeerBundle>>,
    ) -> Result<Response<AckStream>, Status> {
        let mut inbound = request.into_inner();
        let (acks, rx) = mpsc::unbounded_channel();
        tokio::spawn(async move {
            while let Ok(Some(bundle)) = inbound.message().await {
                std::hint::black_box(&bundle.batches);
                let ack = proto::PeerAck {
                    sequence: bundle.sequence,
                    window_bytes: 0,
                };
                if acks.send(Ok(ack)).is_err() {
                    break;
                }
            }
        });
        Ok(Response::new(Box::pin(UnboundedReceiverStream::new(rx))))
    }
}

/// CPU time of this process (every thread, user and system), in nanoseconds.
fn process_cpu_ns() -> u64 {
    // SAFETY: `usage` is a valid rusage to write into; RUSAGE_SELF is a libc constant.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut usage) } != 0 {
        return 0;
    }
    let ns = |t: libc::timeval| t.tv_sec as u64 * 1_000_000_000 + t.tv_usec as u64 * 1_000;
    ns(usage.ru_utime) + ns(usage.ru_stime)
}

/// Times bundles of `SIZES` sizes picked from `bundles` (tier, batches) over the loopback
/// peer service, on a runtime of `threads` threads (the worker's: one per core).
pub fn measure(
    bundles: &[(i32, Vec<Bytes>)],
    threads: usize,
) -> anyhow::Result<Vec<TransportSample>> {
    let mut by_size: Vec<&(i32, Vec<Bytes>)> = bundles.iter().collect();
    by_size.sort_by_key(|(_, b)| b.iter().map(Bytes::len).sum::<usize>());
    by_size.dedup_by_key(|(_, b)| b.iter().map(Bytes::len).sum::<usize>());
    if by_size.len() < 2 {
        anyhow::bail!("fewer than two bundle sizes to time the transport with");
    }
    let picked: Vec<&(i32, Vec<Bytes>)> = (0..SIZES)
        .map(|i| by_size[i * (by_size.len() - 1) / (SIZES - 1)])
        .collect();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(threads.max(1))
        .enable_all()
        .build()
        .context("a runtime for the transport measurement")?;
    runtime.block_on(async move {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let server = tonic::transport::Server::builder()
            .add_service(
                PeerServiceServer::new(Sink)
                    .max_decoding_message_size(MAX_MESSAGE_BYTES)
                    .max_encoding_message_size(MAX_MESSAGE_BYTES),
            )
            .serve_with_incoming(TcpListenerStream::new(listener));
        let server = tokio::spawn(server);
        let mut out = Vec::new();
        for (tier, batches) in picked {
            let bytes: usize = batches.iter().map(Bytes::len).sum();
            let sends = (BYTES_PER_SIZE / bytes.max(1)).clamp(MIN_SENDS, MAX_SENDS);
            // One untimed round to open the connection and warm its buffers.
            send_all(addr, *tier, batches, 8).await?;
            let start = process_cpu_ns();
            send_all(addr, *tier, batches, sends).await?;
            let ns = process_cpu_ns().saturating_sub(start) as f64 / sends as f64;
            out.push(TransportSample { bytes, sends, ns });
        }
        server.abort();
        Ok(out)
    })
}

/// Opens a link to `addr` as a worker does and sends `sends` copies of the bundle, at most
/// `WINDOW` unacknowledged, until the last is acknowledged. The connection is opened before
/// the sends, so its cost is in the untimed warm-up only in part: a link is opened once per
/// peer and lives for the frame, so that share is small per bundle.
async fn send_all(
    addr: std::net::SocketAddr,
    tier: i32,
    batches: &[Bytes],
    sends: usize,
) -> anyhow::Result<()> {
    let mut client = PeerServiceClient::connect(format!("http://{addr}"))
        .await?
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);
    let (tx, rx) = mpsc::channel(WINDOW);
    let mut acks = client
        .exchange_bundles(ReceiverStream::new(rx))
        .await?
        .into_inner();
    let bundle = |sequence: u64| proto::PeerBundle {
        protocol_version: PROTOCOL_VERSION,
        sender: "calibrate:7000".to_string(),
        job_id: "calibrate".to_string(),
        tier,
        sequence,
        batches: batches.to_vec(),
    };
    let mut sent = 0u64;
    let mut acked = 0u64;
    let last = sends as u64;
    while acked < last {
        if sent < last && sent - acked < WINDOW as u64 {
            sent += 1;
            tx.send(bundle(sent))
                .await
                .map_err(|_| anyhow::anyhow!("the loopback stream closed"))?;
            continue;
        }
        let ack = tokio::time::timeout(Duration::from_secs(30), acks.message())
            .await
            .context("no acknowledgement within 30 s")??
            .context("the loopback stream ended")?;
        acked = acked.max(ack.sequence);
    }
    Ok(())
}
