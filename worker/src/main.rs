//! `rayfarm-worker`: attaches to a coordinator, maps domains from shared storage into a
//! byte-budgeted cache, traces the rays queued for the domains it is given each round, and
//! streams rays that leave its domains to the workers holding the next ones.

mod control;
mod domains;
mod engine;
mod pass;
mod peers;
mod queues;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use rayfarm_core::bundler::BundlerConfig;
use rayfarm_core::render::cache::StorageModel;
use rayfarm_core::render::cache::peers::PeerLoads;
use rayfarm_core::units::{parse_bytes, parse_rate};
use rayfarm_node::proto::peer_service_server::PeerServiceServer;
use rayfarm_node::security::{
    ClientSecurity, ClusterSecret, ConnectTlsArgs, Credential, RequireSecret, ServeTlsArgs,
};
use tokio::sync::mpsc;
use tonic::service::interceptor::InterceptedService;
use tracing::{info, warn};

use crate::domains::{Fetcher, PeerDomains, ServeFault, Serving};
use crate::engine::{Engine, EngineConfig};
use crate::peers::{LinkLimits, MAX_MESSAGE_BYTES, PeerLinks, PeerServer};
use rayfarm_node::fault::Faults;
use rayfarm_node::http::HttpArgs;
use rayfarm_node::listen::ConnectionArgs;
use rayfarm_node::metrics;

/// rayfarm-worker: traces rays for a rayfarm coordinator.
#[derive(Parser, Debug)]
#[command(version, about)]
struct Args {
    /// The coordinator's URL.
    #[arg(
        long,
        env = "RAYFARM_COORDINATOR",
        default_value = "http://127.0.0.1:50051"
    )]
    coordinator: String,
    /// Address to serve peers on; port 0 lets the OS choose (the chosen address is printed).
    /// Other than loopback it needs TLS and the cluster secret, or --insecure.
    #[arg(long, env = "RAYFARM_WORKER_LISTEN", default_value = "127.0.0.1:0")]
    listen: SocketAddr,
    /// Serve a non-loopback --listen address without TLS or cluster secret (anyone reaching
    /// it may push rays into this worker's frames): a trusted network only.
    #[arg(long, env = "RAYFARM_INSECURE")]
    insecure: bool,
    #[command(flatten)]
    connections: ConnectionArgs,
    #[command(flatten)]
    http: HttpArgs,
    /// Address peers reach this worker at (host:port). Default: the listen address, or this
    /// host's name with the listen port when listening on all interfaces.
    #[arg(long, env = "RAYFARM_ADVERTISE")]
    advertise: Option<String>,
    /// Bundles sent to one peer and not yet acknowledged; more wait here.
    #[arg(long, env = "RAYFARM_PEER_WINDOW", default_value_t = 64)]
    peer_window: usize,
    /// A peer that acknowledges none of this worker's bundles for this many milliseconds is
    /// reported to the coordinator, which drops it as lost.
    #[arg(long, env = "RAYFARM_PEER_ACK_TIMEOUT_MS", default_value_t = 30_000)]
    peer_ack_timeout_ms: u64,
    /// Worker id shown in status and statistics. Default: the advertised address, or with
    /// mutual TLS (--tls-client-ca) the name of this node's certificate, which it must equal.
    #[arg(long, env = "RAYFARM_WORKER_ID")]
    worker_id: Option<String>,
    /// Domain cache budget, e.g. 512MiB or 2GB.
    #[arg(long, env = "RAYFARM_CACHE_BYTES", default_value = "1GiB", value_parser = parse_bytes)]
    cache_bytes: u64,
    /// Directory that job scene names are relative to (this node's mount point).
    #[arg(long, env = "RAYFARM_SCENE_ROOT", default_value = ".")]
    scene_root: PathBuf,
    /// Accept absolute scene paths as well as names under --scene-root (give it to the
    /// coordinator and every worker alike).
    #[arg(long, env = "RAYFARM_ALLOW_ABSOLUTE_SCENES")]
    allow_absolute_scenes: bool,
    /// Tracing threads (default: all cores).
    #[arg(long, env = "RAYFARM_THREADS")]
    threads: Option<usize>,
    /// Camera rays are issued while fewer rays than this are queued on the worker.
    #[arg(long, env = "RAYFARM_WAVE_RAYS", default_value_t = 1 << 20)]
    wave_rays: usize,
    /// Most rays traced in one pass (smaller passes react faster to new plans).
    #[arg(long, env = "RAYFARM_PASS_RAYS", default_value_t = 1 << 18)]
    pass_rays: usize,
    /// Most bytes of queued rays kept in memory; past it rays spill to --spill-dir.
    #[arg(long, env = "RAYFARM_QUEUE_BYTES", default_value = "512MiB", value_parser = parse_bytes)]
    queue_bytes: u64,
    /// Most bytes of rays spilled to disk; past it the frame fails with a clear error.
    #[arg(long, env = "RAYFARM_SPILL_BYTES", default_value = "8GiB", value_parser = parse_bytes)]
    spill_bytes: u64,
    /// Directory for spilled rays (default: the system's temporary directory). While it is
    /// unwritable or full, this worker declines frames (the others render them).
    #[arg(long, env = "RAYFARM_SPILL_DIR")]
    spill_dir: Option<PathBuf>,
    /// EMULATION for benchmarks: charge every domain load as if storage delivered this many
    /// bytes per second (e.g. 100MiB/s), so one machine shows the I/O-bound regime.
    #[arg(long, env = "RAYFARM_STORAGE_BANDWIDTH", value_parser = parse_rate)]
    storage_bandwidth: Option<u64>,
    /// EMULATION for benchmarks: a fixed delay added to every domain load (e.g. 5ms).
    #[arg(long, env = "RAYFARM_STORAGE_LATENCY", value_parser = parse_duration)]
    storage_latency: Option<Duration>,
    /// Bandwidth of the links to peers (e.g. 1GiB/s), for jobs that load domains from peers
    /// (`submit --peer-domains`): a load asks a peer holding the domain when that is cheaper
    /// than storage. Default: measured from completed transfers.
    #[arg(long, env = "RAYFARM_PEER_LINK_BANDWIDTH", value_parser = parse_rate)]
    peer_link_bandwidth: Option<u64>,
    #[command(flatten)]
    serve_tls: ServeTlsArgs,
    #[command(flatten)]
    connect_tls: ConnectTlsArgs,
    /// File holding the cluster secret, presented to the coordinator and to peers and
    /// required of peers (off without it). A file, so the secret shows in no process list.
    #[arg(long, env = "RAYFARM_CLUSTER_SECRET_FILE")]
    cluster_secret_file: Option<PathBuf>,
    /// More log output (-v debug, -vv trace); RUST_LOG overrides.
    #[arg(short, long, action = clap::ArgAction::Count)]
    verbose: u8,
}

/// A duration such as `5ms`, `1.5s` or `200us`.
fn parse_duration(s: &str) -> Result<Duration, String> {
    let s = s.trim();
    let split = s
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(s.len());
    let (number, unit) = s.split_at(split);
    let value: f64 = number
        .parse()
        .map_err(|_| format!("{s:?}: expected a number with a unit, e.g. 5ms"))?;
    let seconds = match unit.trim() {
        "s" => value,
        "ms" => value / 1e3,
        "us" => value / 1e6,
        _ => return Err(format!("{s:?}: unit must be s, ms or us")),
    };
    Duration::try_from_secs_f64(seconds).map_err(|e| format!("{s:?}: {e}"))
}

/// This node's certificate name when mutual TLS is on (`--tls-client-ca` with a certificate):
/// its id on the cluster.
fn own_name(args: &Args) -> anyhow::Result<Option<String>> {
    match (&args.serve_tls.tls_client_ca, &args.serve_tls.tls_cert) {
        (Some(_), Some(cert)) => rayfarm_node::identity::PeerIdentity::from_pem_file(cert)
            .map(|id| Some(id.name))
            .map_err(|e| anyhow::anyhow!("this node's certificate: {e}")),
        _ => Ok(None),
    }
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    // Two async threads route and talk; tracing has its own pool.
    rayfarm_node::telemetry::server_main(args.verbose, Some(2), run(args))
}

async fn run(args: Args) -> anyhow::Result<()> {
    // Credentials are read before binding, so a bad file stops the start with its reason.
    let serve_tls = args.serve_tls.server_config()?;
    let secret = ClusterSecret::load(args.cluster_secret_file.as_deref())?;
    let security = ClientSecurity {
        tls: args.connect_tls.client_config(args.serve_tls.identity()?)?,
        credential: Credential::secret(secret.as_ref()),
    };
    rayfarm_node::security::check_listeners(
        std::iter::once(args.listen).chain(args.http.http),
        &[
            (serve_tls.is_some(), "TLS (--tls-cert, --tls-key)"),
            (secret.is_some(), "a cluster secret (--cluster-secret-file)"),
        ],
        args.insecure,
    )?;
    let http_tls = args.serve_tls.http_server_config()?;
    let worker_id = match own_name(&args)? {
        // Under mutual TLS the coordinator and peers take this node for the name in its
        // certificate: an id of its own would only be refused there.
        Some(name) => match &args.worker_id {
            Some(id) if *id != name => anyhow::bail!(
                "--worker-id {id} is not the name of this node's certificate ({name}): with \
                 mutual TLS (--tls-client-ca) a worker's id is its certificate's name; leave \
                 --worker-id out or issue a certificate for it (rayfarm certs --node {id})"
            ),
            _ => Some(name),
        },
        None => args.worker_id.clone(),
    };

    let listener = tokio::net::TcpListener::bind(args.listen)
        .await
        .with_context(|| format!("cannot listen on {}", args.listen))?;
    let bound = listener.local_addr()?;
    let advertise = args.advertise.clone().unwrap_or_else(|| {
        if bound.ip().is_unspecified() {
            format!(
                "{}:{}",
                gethostname::gethostname().to_string_lossy(),
                bound.port()
            )
        } else {
            bound.to_string()
        }
    });
    let worker_id = worker_id.unwrap_or_else(|| advertise.clone());
    let threads = args.threads.unwrap_or_else(|| {
        std::thread::available_parallelism().map_or(1, std::num::NonZeroUsize::get)
    });
    // Bound before the `listening on` line, so whoever waits for that line has both.
    let router = rayfarm_node::http::metrics_route(|| metrics::worker().encode());
    let http =
        rayfarm_node::http::serve(args.http.http, http_tls, &args.connections, router).await?;
    // The one line scripts and tests wait for; logs go to stderr.
    println!("listening on {bound}");
    info!(%bound, %advertise, %worker_id, threads, cache_bytes = args.cache_bytes, "worker up");
    if args.storage_bandwidth.is_some() || args.storage_latency.is_some() {
        info!(
            bandwidth = ?args.storage_bandwidth,
            latency = ?args.storage_latency,
            "EMULATING slower storage: every domain load is delayed"
        );
    }

    info!(
        serve_tls = serve_tls.is_some(),
        connect_tls = security.tls.is_some(),
        cluster_secret = secret.is_some(),
        "security"
    );
    if secret.is_some() && (serve_tls.is_none() || security.tls.is_none()) {
        warn!(
            "the cluster secret travels in clear text on links without TLS: give --tls-cert, \
             --tls-key and --tls-ca"
        );
    }
    let faults = Faults::from_env();
    if faults.active() {
        info!(?faults, "fault injection is on (test instrumentation)");
    }
    let (events_tx, events_rx) = mpsc::unbounded_channel();
    let (to_coordinator, outbound) = mpsc::unbounded_channel();
    let (fetcher, hints) = Fetcher::new(
        worker_id.clone(),
        security.clone(),
        tokio::runtime::Handle::current(),
        args.peer_link_bandwidth,
    );
    let serving = Serving::new(ServeFault::from_env());
    let domains = PeerDomains {
        loads: Arc::new(PeerLoads::new(Box::new(fetcher))),
        hints,
        serving: serving.clone(),
    };
    let engine = Engine::new(
        EngineConfig {
            worker_id: worker_id.clone(),
            advertise: advertise.clone(),
            scene_root: args.scene_root.clone(),
            allow_absolute_scenes: args.allow_absolute_scenes,
            cache_bytes: args.cache_bytes,
            threads,
            wave_rays: args.wave_rays.max(1),
            pass_rays: args.pass_rays.max(1),
            bundler: BundlerConfig::default(),
            storage: StorageModel {
                bandwidth: args.storage_bandwidth,
                latency: args.storage_latency.unwrap_or_default(),
            },
            queue_bytes: args.queue_bytes,
            spill_bytes: args.spill_bytes,
            spill_dir: args.spill_dir.clone().unwrap_or_else(std::env::temp_dir),
        },
        to_coordinator,
        PeerLinks::new(
            worker_id.clone(),
            faults,
            security.clone(),
            LinkLimits {
                window: args.peer_window.max(1),
                ack_deadline: Duration::from_millis(args.peer_ack_timeout_ms.max(100)),
            },
            events_tx.clone(),
        ),
        domains,
    )?;
    let peer_service = PeerServiceServer::new(PeerServer::new(events_tx.clone(), serving))
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);
    let peer_service = InterceptedService::new(peer_service, RequireSecret(secret));
    // The standard gRPC health service, for container health checks.
    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<PeerServiceServer<PeerServer>>().await;
    let incoming = rayfarm_node::listen::incoming(listener, serve_tls, &args.connections);
    // Health stays outside the interceptor: probes carry no credentials.
    let server = rayfarm_node::security::server_builder()
        .layer(rayfarm_node::metrics::rpc_error_layer())
        .add_service(health_service)
        .add_service(peer_service)
        .serve_with_incoming(incoming);
    let control = control::run(
        control::Identity {
            coordinator: args.coordinator.clone(),
            worker_id,
            advertise,
            cache_bytes: args.cache_bytes,
            threads: threads as u32,
            security,
        },
        events_tx,
        outbound,
        faults,
    );
    tokio::select! {
        r = server => r.context("peer server failed"),
        r = control => r,
        () = engine.run(events_rx) => Ok(()),
        () = http => Ok(()),
        _ = rayfarm_node::telemetry::shutdown_signal() => {
            info!("shutting down");
            Ok(())
        }
    }
}
