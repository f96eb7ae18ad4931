//! The HTTP/1.1 listener of a server (`--http ADDR`): Prometheus's `/metrics` on every node,
//! and on the coordinator the dashboard. Connections go through the same caps and TLS
//! deadline as the gRPC listeners ([`crate::listen::incoming_http1`]); hyper bounds each
//! request's header bytes and the time to send them, axum bounds request bodies.

use std::net::SocketAddr;
use std::time::Duration;

use anyhow::Context;
use axum::Router;
use axum::extract::DefaultBodyLimit;
use axum::response::IntoResponse;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use tokio::net::TcpListener;
use tokio_rustls::TlsAcceptor;
use tokio_stream::StreamExt;
use tower::ServiceExt;
use tracing::{debug, info};

use crate::listen::{ConnInfo, ConnectionArgs};

/// Most bytes of a request's line and headers (hyper's read buffer): a browser's are a few KiB.
const MAX_HEADER_BYTES: usize = 16 << 10;
/// Most bytes of a request body (the dashboard's POSTs are a few dozen bytes).
const MAX_BODY_BYTES: usize = 16 << 10;
/// Time a client has to send a request's headers, the first and every later one on a
/// kept-alive connection.
const HEADER_TIMEOUT: Duration = Duration::from_secs(10);
/// Longest a handler may take (they read memory only).
const REQUEST_TIMEOUT: Duration = Duration::from_secs(30);

/// `--http`: where a server serves HTTP (off without it).
#[derive(clap::Args, Clone, Debug, Default)]
pub struct HttpArgs {
    /// Address to serve HTTP on: /metrics (Prometheus), and on the coordinator the dashboard
    /// at /. Off by default; port 0 lets the OS choose (printed as `http on ADDR` on stdout).
    /// Other than loopback it needs what --listen needs (or --insecure); with --tls-cert it
    /// is HTTPS.
    #[arg(long, env = "RAYFARM_HTTP")]
    pub http: Option<SocketAddr>,
}

/// The handler of `/metrics` for a process whose metrics `encode` writes.
pub fn metrics_route(encode: impl Fn() -> String + Clone + Send + Sync + 'static) -> Router {
    Router::new().route(
        "/metrics",
        axum::routing::get(move || async move {
            (
                [(http::header::CONTENT_TYPE, crate::metrics::CONTENT_TYPE)],
                encode(),
            )
        }),
    )
}

/// `--http` of a server: binds `addr` when one is given (see [`bind`]) and returns a future
/// serving `router` there; without an address, a future that never ends, so a server's
/// `select!` has the same arm either way.
pub async fn serve(
    addr: Option<SocketAddr>,
    tls: Option<TlsAcceptor>,
    limits: &ConnectionArgs,
    router: Router,
) -> anyhow::Result<impl Future<Output = ()> + use<>> {
    let bound = match addr {
        Some(addr) => Some(bind(addr, tls, limits, router).await?),
        None => None,
    };
    Ok(async move {
        match bound {
            Some(serve) => serve.await,
            None => std::future::pending().await,
        }
    })
}

/// Binds `addr`, prints `http on ADDR` on stdout, and returns a future serving `router`
/// there until the process ends.
pub async fn bind(
    addr: SocketAddr,
    tls: Option<TlsAcceptor>,
    limits: &ConnectionArgs,
    router: Router,
) -> anyhow::Result<impl Future<Output = ()> + use<>> {
    let listener = TcpListener::bind(addr)
        .await
        .with_context(|| format!("cannot serve HTTP on {addr}"))?;
    let bound = listener.local_addr()?;
    // Scripts and tests read the chosen port here, like the `listening on` line.
    println!("http on {bound}");
    info!(%bound, tls = tls.is_some(), "serving HTTP");
    let router = router.layer(DefaultBodyLimit::max(MAX_BODY_BYTES));
    let mut incoming = crate::listen::incoming_http1(listener, tls, limits);
    Ok(async move {
        while let Some(conn) = incoming.next().await {
            let Ok(conn) = conn else { continue };
            let info: ConnInfo = tonic::transport::server::Connected::connect_info(&conn);
            let router = router.clone();
            tokio::spawn(async move {
                // Each request carries its connection's address and certificate, as the gRPC
                // handlers' do.
                let service = tower::service_fn(move |mut request: http::Request<_>| {
                    request.extensions_mut().insert(info.clone());
                    let answer = router.clone().oneshot(request);
                    // Open until answered, so the idle timeout (`crate::idle`) never ends a
                    // connection with a request on it.
                    let open = info.activity.as_ref().map(crate::idle::Activity::begin);
                    async move {
                        let _open = open;
                        match tokio::time::timeout(REQUEST_TIMEOUT, answer).await {
                            Ok(response) => response,
                            Err(_) => Ok(http::StatusCode::SERVICE_UNAVAILABLE.into_response()),
                        }
                    }
                });
                let served = hyper::server::conn::http1::Builder::new()
                    .timer(TokioTimer::new())
                    .header_read_timeout(HEADER_TIMEOUT)
                    .max_buf_size(MAX_HEADER_BYTES)
                    .serve_connection(TokioIo::new(conn), TowerToHyperService::new(service))
                    .await;
                if let Err(e) = served {
                    debug!(error = %e, "HTTP connection ended with an error");
                }
            });
        }
    })
}
