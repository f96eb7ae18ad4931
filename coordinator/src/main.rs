//! `rayfarm-coordinator`: accepts render jobs, runs one frame at a time across the attached
//! workers, plans the rounds of the dynamic schedule from their queue reports, and collects
//! tile results until every tile's credit is back. Jobs are kept in a database in the data
//! directory, so a restarted coordinator carries on with them (`store`).

mod admission;
mod api;
mod control;
mod dashboard;
mod journal;
mod preview;
mod results;
mod running;
mod state;
mod store;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use rayfarm_core::schedule::dynamic::{DEFAULT_COPY_RAYS, Options};
use rayfarm_node::fault::Faults;
use rayfarm_node::http::HttpArgs;
use rayfarm_node::listen::ConnectionArgs;
use rayfarm_node::proto::job_service_server::JobServiceServer;
use rayfarm_node::proto::worker_control_server::WorkerControlServer;
use rayfarm_node::security::{
    ClusterSecret, RequireSecret, RequireToken, ServeTlsArgs, UserTokens,
};
use tonic::service::interceptor::InterceptedService;
use tracing::{info, warn};

use crate::state::{Config, Coordinator};
use rayfarm_machine::coordinator::Rounds;
use rayfarm_machine::coordinator::cluster::ReportHold;

/// Largest gRPC message accepted or sent on the worker link (tile results of a big pass) and
/// sent by the job API (fetched images).
const MAX_MESSAGE_BYTES: usize = 256 << 20;
/// Largest request the job API accepts: job specs and ids are a few hundred bytes, so a
/// bigger message is refused before it is decoded (a token holder cannot make the
/// coordinator hold a 250 MiB scene name).
const MAX_API_REQUEST_BYTES: usize = 64 << 10;

/// How long connections (watching clients) may stay open after a stop signal.
const STOP_GRACE: Duration = Duration::from_secs(2);

/// Extensions of the dynamic schedule that copy domains.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum Replicate {
    None,
    Idle,
    FreeSlots,
}

/// `--rounds`: how the dynamic schedule's rounds advance (`Rounds`, named for the command line).
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum RoundsArg {
    Barrier,
    Async,
}

/// rayfarm-coordinator: the job queue and scheduler of a rayfarm cluster.
#[derive(Parser, Debug)]
#[command(version, about)]
struct Args {
    /// Address to serve the job API and workers on; port 0 lets the OS choose (the chosen
    /// address is printed on stdout). Other than loopback it needs TLS, the cluster secret
    /// and user tokens, or --insecure.
    #[arg(long, env = "RAYFARM_LISTEN", default_value = "127.0.0.1:50051")]
    listen: SocketAddr,
    /// Serve a non-loopback --listen address without TLS, cluster secret or user tokens
    /// (anyone reaching it may submit, cancel, or attach as a worker): a trusted network only.
    #[arg(long, env = "RAYFARM_INSECURE")]
    insecure: bool,
    #[command(flatten)]
    connections: ConnectionArgs,
    #[command(flatten)]
    http: HttpArgs,
    /// Where jobs and results are kept: the job database `rayfarm.redb` (queued, running and
    /// finished jobs survive a restart; a damaged file stops the coordinator, never replaced)
    /// and `jobs/<id>/` with each finished job's images and statistics. One coordinator per
    /// directory.
    #[arg(long, env = "RAYFARM_DATA_DIR", default_value = "rayfarm-data")]
    data_dir: PathBuf,
    /// Directory that job scene names are relative to (this node's mount point).
    #[arg(long, env = "RAYFARM_SCENE_ROOT", default_value = ".")]
    scene_root: PathBuf,
    /// Accept absolute scene paths as well as names under --scene-root (for clusters where
    /// every node sees the same paths). Off: a job cannot name files elsewhere on the host.
    #[arg(long, env = "RAYFARM_ALLOW_ABSOLUTE_SCENES")]
    allow_absolute_scenes: bool,
    /// Most jobs one user (one token; everyone, without tokens) may have queued or running;
    /// more are refused with RESOURCE_EXHAUSTED.
    #[arg(long, env = "RAYFARM_MAX_JOBS_PER_USER", default_value_t = 64)]
    max_jobs_per_user: usize,
    /// Most pixels x samples per pixel one user may have queued or running (default 2^40,
    /// over a hundred 4K frames at 1024 spp); more are refused with RESOURCE_EXHAUSTED.
    #[arg(long, env = "RAYFARM_MAX_PIXEL_SAMPLES_PER_USER", default_value_t = 1 << 40)]
    max_pixel_samples_per_user: u64,
    /// Scene rendered by jobs that name none.
    #[arg(long, env = "RAYFARM_DEFAULT_SCENE")]
    default_scene: Option<String>,
    /// Heartbeat interval asked of workers, milliseconds.
    #[arg(long, env = "RAYFARM_HEARTBEAT_MS", default_value_t = 1000)]
    heartbeat_ms: u64,
    /// A worker silent for this many milliseconds is dropped.
    #[arg(long, env = "RAYFARM_WORKER_TIMEOUT_MS", default_value_t = 10_000)]
    worker_timeout_ms: u64,
    /// Copies of busy domains beyond the paper's algorithm (each costs a load): `none` is
    /// Fig. 5 as written; `idle` gives workers left idle a copy of the busiest domain;
    /// `free-slots` fills every free cache slot with copies of wanted domains. The dynamic
    /// schedule only: predictive never copies.
    #[arg(long, env = "RAYFARM_REPLICATE", value_enum, default_value_t = Replicate::FreeSlots)]
    replicate: Replicate,
    /// A copy (`--replicate`) is made only if every holder of the domain keeps at least this
    /// many of its rays: a copy costs a load from shared storage, which a few rays do not
    /// repay (README "Simulator"). 1 copies while a holder would keep one ray.
    #[arg(long, env = "RAYFARM_COPY_RAYS", default_value_t = DEFAULT_COPY_RAYS)]
    copy_rays: u64,
    /// How the dynamic schedule's rounds advance: `async` plans a worker as soon as it runs
    /// dry; `barrier` (Fig. 5 as written) waits until every worker has reported.
    #[arg(long, env = "RAYFARM_ROUNDS", value_enum, default_value_t = RoundsArg::Async)]
    rounds: RoundsArg,
    /// Under asynchronous rounds, a busy worker is told of new holders of the domains at most
    /// once per this many milliseconds (a worker planned, or one whose reported rays a round
    /// counts at a new holder, is told at once): every round changes some, and telling every
    /// busy worker after every round was most of the coordinator's messages at scale (README
    /// "Simulator"). Until it hears, a worker keeps rays for a domain whose holder it does not
    /// know, and a former holder forwards what reaches it. 0 (the default) tells them after
    /// every round: at 8 workers 1-2 ms made the simulated predictive frame 13% longer.
    #[arg(long, env = "RAYFARM_HOLDERS_INTERVAL_MS", default_value_t = 0)]
    holders_interval_ms: u64,
    /// Under asynchronous rounds, a worker planned with nothing to trace yet waits up to this
    /// many milliseconds for the rays its plan moves to it (other workers forward them once
    /// they hear it holds their domain) before it reports its queues again; it reports as soon
    /// as it has traced something and run dry. 0 reports at once: the coordinator then hears
    /// queues without the rays in flight and plans the worker again and again (97% of a
    /// 256-worker dynamic simulation's reports, README "Simulator").
    #[arg(long, env = "RAYFARM_REPORT_HOLD_MS", value_parser = clap::value_parser!(u64).range(0..=10_000),
          default_value_t = ReportHold::DEFAULT.least.as_millis() as u64)]
    report_hold_ms: u64,
    /// ...or this many microseconds for each worker of the frame when that is longer: idle
    /// workers then send at most one report a `--report-hold-per-worker-us` between them,
    /// however many there are (the default 100 holds 50 ms up to 500 workers, 102 ms at
    /// 1,024). 0: the hold is `--report-hold-ms` at any size.
    #[arg(long, env = "RAYFARM_REPORT_HOLD_PER_WORKER_US", value_parser = clap::value_parser!(u64).range(0..=10_000),
          default_value_t = ReportHold::DEFAULT.per_member.as_micros() as u64)]
    report_hold_per_worker_us: u64,
    /// Largest film file, set of images, or worker memory for one tile's camera rays a job's
    /// frame may need; a job past it (or past the data directory's free disk) is refused at
    /// submit with RESOURCE_EXHAUSTED. A 16384x16384 frame's film is 6 GiB.
    #[arg(long, env = "RAYFARM_MAX_FRAME_BYTES", value_parser = rayfarm_core::units::parse_bytes, default_value = "16GiB")]
    max_frame_bytes: u64,
    /// A job whose frame has started this many times without finishing (coordinator crashes
    /// and lost workers included) fails instead of being queued again.
    #[arg(long, env = "RAYFARM_MAX_ATTEMPTS", default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..))]
    max_attempts: u32,
    #[command(flatten)]
    tls: ServeTlsArgs,
    /// File holding the cluster secret workers must present to attach (off without it).
    /// A file, not a value, so the secret shows in no process list.
    #[arg(long, env = "RAYFARM_CLUSTER_SECRET_FILE")]
    cluster_secret_file: Option<PathBuf>,
    /// File of the user tokens the job API accepts, one per line with an optional user name
    /// after it (off without it: anyone reaching the port may submit).
    #[arg(long, env = "RAYFARM_USER_TOKENS_FILE")]
    user_tokens_file: Option<PathBuf>,
    /// More log output (-v debug, -vv trace); RUST_LOG overrides.
    #[arg(short, long, action = clap::ArgAction::Count)]
    verbose: u8,
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    rayfarm_node::telemetry::server_main(args.verbose, None, run(args))
}

async fn run(args: Args) -> anyhow::Result<()> {
    // Credentials are read before binding, so a bad file stops the start with its reason.
    let tls = args.tls.server_config()?;
    let secret = ClusterSecret::load(args.cluster_secret_file.as_deref())?;
    let tokens = UserTokens::load(args.user_tokens_file.as_deref())?;
    rayfarm_node::security::check_listeners(
        std::iter::once(args.listen).chain(args.http.http),
        &[
            (tls.is_some(), "TLS (--tls-cert, --tls-key)"),
            (secret.is_some(), "a cluster secret (--cluster-secret-file)"),
            (tokens.is_some(), "user tokens (--user-tokens-file)"),
        ],
        args.insecure,
    )?;
    let http_tls = args.tls.http_server_config()?;
    std::fs::create_dir_all(&args.data_dir)
        .with_context(|| format!("creating data directory {}", args.data_dir.display()))?;
    let listen = args.listen;
    let config = Config {
        data_dir: args.data_dir,
        scene_root: args.scene_root,
        allow_absolute_scenes: args.allow_absolute_scenes,
        max_jobs_per_user: args.max_jobs_per_user,
        max_pixel_samples_per_user: args.max_pixel_samples_per_user,
        default_scene: args.default_scene,
        heartbeat: Duration::from_millis(args.heartbeat_ms.max(10)),
        worker_timeout: Duration::from_millis(args.worker_timeout_ms.max(100)),
        report_timeout: Duration::from_secs(5),
        schedule_options: Options {
            replicate_onto_idle: matches!(args.replicate, Replicate::Idle),
            fill_free_slots: matches!(args.replicate, Replicate::FreeSlots),
            copy_rays: args.copy_rays,
        },
        rounds: match args.rounds {
            RoundsArg::Barrier => Rounds::Barrier,
            RoundsArg::Async => Rounds::Async,
        },
        holders_interval: Duration::from_millis(args.holders_interval_ms.min(60_000)),
        report_hold: ReportHold {
            least: Duration::from_millis(args.report_hold_ms),
            per_member: Duration::from_micros(args.report_hold_per_worker_us),
        },
        max_frame_bytes: args.max_frame_bytes,
        max_attempts: args.max_attempts,
    };
    // The jobs are loaded before listening: nobody sees a coordinator without them.
    let coordinator = Coordinator::open(config.clone())?;
    // Bound before the `listening on` line, so whoever waits for that line has both.
    let http = match args.http.http {
        Some(_) => {
            let c = coordinator.clone();
            let metrics = rayfarm_node::http::metrics_route(move || {
                c.refresh_metrics();
                rayfarm_node::metrics::coordinator().encode()
            });
            let page = dashboard::router(coordinator.clone(), RequireToken(tokens.clone()));
            metrics.merge(page)
        }
        None => axum::Router::new(),
    };
    let http = rayfarm_node::http::serve(args.http.http, http_tls, &args.connections, http).await?;
    let listener = tokio::net::TcpListener::bind(listen)
        .await
        .with_context(|| format!("cannot listen on {listen}"))?;
    let bound = listener.local_addr()?;
    // The one line scripts and tests wait for; logs go to stderr.
    println!("listening on {bound}");
    info!(%bound, ?config, "coordinator up");
    info!(
        tls = tls.is_some(),
        mutual_tls = args.tls.tls_client_ca.is_some(),
        cluster_secret = secret.is_some(),
        user_tokens = tokens.as_ref().map_or(0, UserTokens::len),
        "security"
    );
    if tls.is_none() && (secret.is_some() || tokens.is_some()) {
        warn!("credentials without TLS travel in clear text: give --tls-cert and --tls-key");
    }
    let faults = Faults::from_env();
    if faults.active() {
        info!(?faults, "fault injection is on (test instrumentation)");
    }
    let reaper = {
        let c = coordinator.clone();
        let period = c.config().heartbeat;
        async move {
            // Each heartbeat, or sooner when the machine has a deadline (a finished frame's
            // report timeout) before then.
            loop {
                let wait = c.tick().map_or(period, |d| d.min(period));
                tokio::time::sleep(wait.max(Duration::from_millis(1))).await;
            }
        }
    };
    let api = JobServiceServer::new(api::Api::new(coordinator.clone()))
        .max_decoding_message_size(MAX_API_REQUEST_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);
    let api = InterceptedService::new(api, RequireToken(tokens));
    let control = WorkerControlServer::new(control::Control::new(coordinator.clone(), faults))
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);
    let control = InterceptedService::new(control, RequireSecret(secret));
    // The standard gRPC health service, for container health checks and load balancers.
    let (health, health_service) = tonic_health::server::health_reporter();
    health.set_serving::<JobServiceServer<api::Api>>().await;
    info!(
        max_connections = args.connections.effective_max_connections(),
        per_peer = args.connections.max_connections_per_peer,
        handshake_timeout_ms = args.connections.handshake_timeout_ms,
        "connection limits"
    );
    let incoming = rayfarm_node::listen::incoming(listener, tls, &args.connections);
    // Health stays outside the interceptors: probes carry no credentials.
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let server = rayfarm_node::security::server_builder()
        .layer(rayfarm_node::metrics::rpc_error_layer())
        .add_service(health_service)
        .add_service(api)
        .add_service(control)
        .serve_with_incoming_shutdown(incoming, async {
            let _ = stop_rx.await;
        });
    tokio::pin!(server);
    tokio::select! {
        r = &mut server => r.context("server failed")?,
        () = reaper => {}
        () = http => {}
        () = rayfarm_node::telemetry::shutdown_signal() => {
            // Workers hold their control streams open for as long as they live, so waiting
            // for connections to close would wait for ever: tell the workers first (they
            // reconnect with backoff), release the database, then give the remaining clients
            // a moment before their connections are dropped.
            info!("stopping: telling the workers, closing the job database");
            coordinator.shut_down();
            let _ = stop_tx.send(());
            if tokio::time::timeout(STOP_GRACE, &mut server).await.is_err() {
                info!(grace = ?STOP_GRACE, "clients still connected: closing their connections");
            }
        }
    }
    info!("coordinator stopped");
    Ok(())
}
