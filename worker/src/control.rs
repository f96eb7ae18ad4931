//! The worker's side of the control stream: registers with the coordinator, forwards its
//! messages to the engine, sends the engine's reports and a heartbeat, and reconnects with
//! backoff and jitter when the coordinator goes away.

use std::time::Duration;

use rayfarm_node::proto::worker_control_client::WorkerControlClient;
use rayfarm_node::proto::{
    self, PROTOCOL_VERSION, coordinator_message::Body as FromCoordinator,
    worker_message::Body as ToCoordinator,
};
use rayfarm_node::security::ClientSecurity;
use tokio::sync::mpsc;
use tokio::time::Instant;
use tokio_stream::wrappers::UnboundedReceiverStream;
use tonic::Code;
use tracing::{error, info, warn};

use crate::engine::Event;
use crate::peers::MAX_MESSAGE_BYTES;
use rayfarm_machine::worker as machine;
use rayfarm_node::fault::Faults;

/// Who this worker is, as told to the coordinator.
#[derive(Clone, Debug)]
pub struct Identity {
    pub coordinator: String,
    pub worker_id: String,
    pub advertise: String,
    pub cache_bytes: u64,
    pub threads: u32,
    /// TLS and the cluster secret for the control stream.
    pub security: ClientSecurity,
}

/// Keeps a control stream open for the worker's lifetime. Returns only when the coordinator
/// refuses this worker for good (another protocol version, no or a wrong cluster secret) or
/// the engine is gone.
pub async fn run(
    me: Identity,
    events: mpsc::UnboundedSender<Event>,
    mut outbound: mpsc::UnboundedReceiver<proto::WorkerMessage>,
    faults: Faults,
) -> anyhow::Result<()> {
    let mut failures = 0u32;
    // Once attached in plain text, the coordinator at this address is known not to serve TLS.
    let mut attached_once = false;
    loop {
        let outcome = session(
            &me,
            &events,
            &mut outbound,
            faults,
            &mut failures,
            &mut attached_once,
        )
        .await;
        match outcome {
            Ok(Session::EngineGone) => return Ok(()),
            Ok(Session::Ended) => failures = 0,
            // Retrying cannot fix another protocol or a wrong secret: exit and say why.
            Err(status)
                if matches!(
                    status.code(),
                    Code::FailedPrecondition | Code::Unauthenticated
                ) =>
            {
                anyhow::bail!("the coordinator refused this worker: {}", status.message())
            }
            Err(status) => {
                failures += 1;
                warn!(coordinator = %me.coordinator, %status, "control stream unavailable");
                // A TLS coordinator hangs up on plain text with errors that never say TLS.
                if me.security.tls.is_none() && status.code() != Code::Unavailable && !attached_once
                {
                    warn!("if the coordinator serves TLS, give --tls-ca");
                }
            }
        }
        let _ = events.send(Event::Machine(Box::new(machine::Event::Disconnected)));
        tokio::time::sleep(backoff(failures, &me.worker_id)).await;
    }
}

enum Session {
    /// The coordinator closed the stream; reconnect.
    Ended,
    /// The engine's channel closed; the worker is shutting down.
    EngineGone,
}

async fn session(
    me: &Identity,
    events: &mpsc::UnboundedSender<Event>,
    outbound: &mut mpsc::UnboundedReceiver<proto::WorkerMessage>,
    faults: Faults,
    failures: &mut u32,
    attached_once: &mut bool,
) -> Result<Session, tonic::Status> {
    let unavailable = |e: tonic::transport::Error| tonic::Status::unavailable(e.to_string());
    let channel = me
        .security
        .endpoint(&me.coordinator)
        .map_err(|e| tonic::Status::invalid_argument(e.to_string()))?
        .connect()
        .await
        .map_err(unavailable)?;
    let mut client = WorkerControlClient::with_interceptor(channel, me.security.credential.clone())
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);
    let (tx, rx) = mpsc::unbounded_channel();
    let send = |body| tx.send(proto::WorkerMessage { body: Some(body) }).is_ok();
    send(ToCoordinator::Register(proto::Register {
        protocol_version: PROTOCOL_VERSION,
        worker_id: me.worker_id.clone(),
        peer_address: me.advertise.clone(),
        cache_bytes: me.cache_bytes,
        threads: me.threads,
    }));
    let rx = faults.delayed("coordinator", rx);
    let mut inbound = client
        .attach(UnboundedReceiverStream::new(rx))
        .await?
        .into_inner();
    let started = Instant::now();
    let mut heartbeat = tokio::time::interval(Duration::from_secs(1));
    loop {
        tokio::select! {
            msg = inbound.message() => match msg {
                Ok(Some(msg)) => {
                    if let Some(FromCoordinator::Registered(r)) = &msg.body {
                        info!(coordinator = %me.coordinator, "attached");
                        // The next loss (a coordinator restart) backs off from the start again.
                        *failures = 0;
                        *attached_once = true;
                        let period = Duration::from_millis(u64::from(r.heartbeat_ms.max(10)));
                        heartbeat = tokio::time::interval(period);
                    }
                    if events.send(Event::Control(msg)).is_err() {
                        return Ok(Session::EngineGone);
                    }
                }
                Ok(None) => {
                    warn!("the coordinator closed the control stream");
                    return Ok(Session::Ended);
                }
                Err(status) => return Err(status),
            },
            out = outbound.recv() => match out {
                Some(msg) => {
                    if tx.send(msg).is_err() {
                        return Ok(Session::Ended);
                    }
                }
                None => return Ok(Session::EngineGone),
            },
            _ = heartbeat.tick() => {
                let sent_ms = started.elapsed().as_millis() as u64;
                if !send(ToCoordinator::Heartbeat(heartbeat_now(sent_ms))) {
                    error!("control stream closed");
                    return Ok(Session::Ended);
                }
            }
        }
    }
}

/// A heartbeat with this worker's figures as its metrics hold them (the coordinator shows
/// them per worker on its dashboard).
fn heartbeat_now(sent_ms: u64) -> proto::Heartbeat {
    let m = rayfarm_node::metrics::worker();
    proto::Heartbeat {
        sent_ms,
        domain_loads: m.domain_loads.get(),
        ray_segments: m.radiance_segments.get() + m.shadow_segments.get(),
        queue_bytes: m.queue_bytes.get().max(0) as u64,
        spill_bytes: m.spill_bytes.get().max(0) as u64,
    }
}

/// Exponential backoff from 100 ms to 5 s, with jitter from the worker's id so that a
/// restarted coordinator is not hit by every worker at the same instant.
fn backoff(failures: u32, worker_id: &str) -> Duration {
    let base = 100u64 << failures.min(6);
    let jitter = xxhash_rust::xxh3::xxh3_64_with_seed(worker_id.as_bytes(), u64::from(failures));
    Duration::from_millis(base.min(5000) + jitter % (base / 2 + 1))
}
