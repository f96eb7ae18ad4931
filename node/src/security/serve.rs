//! A server's side of the links: the limits every rayfarm gRPC server sets on its
//! connections, and the refusal to serve a non-loopback address without protection.

use std::time::Duration;

use tonic::transport::Server;
use tower::layer::util::{Identity as NoLayer, Stack};
use tracing::warn;

use super::connect::{KEEPALIVE_INTERVAL, KEEPALIVE_TIMEOUT};
use crate::idle::ActivityLayer;

/// Most streams one client may have open on one connection (HTTP/2
/// `SETTINGS_MAX_CONCURRENT_STREAMS`): rayfarm's clients use a handful; a hostile one that
/// opens thousands and never finishes them is refused past this many.
pub const MAX_STREAMS_PER_CONNECTION: u32 = 64;
/// Largest header list (the request's metadata) a server accepts. Credentials and gRPC's own
/// headers need well under 1 KiB.
pub const MAX_HEADER_LIST_BYTES: u32 = 16 << 10;
/// A handler that has not answered within this is cancelled (`DEADLINE_EXCEEDED`); for a
/// unary call this includes receiving its body, so a request left unfinished ends here. The
/// long-lived streams (a worker's control stream, ray bundles) answer at once and run on.
pub const REQUEST_TIMEOUT: Duration = Duration::from_secs(60);

/// A server builder whose connections ping their clients (see [`KEEPALIVE_INTERVAL`]) and
/// are bounded in streams, header size and request time, with each request counted on its
/// connection for the idle timeout ([`crate::idle`]). Connections themselves are capped,
/// handshaken and closed when idle by [`crate::listen::incoming`].
pub fn server_builder() -> Server<Stack<ActivityLayer, NoLayer>> {
    Server::builder()
        .http2_keepalive_interval(Some(KEEPALIVE_INTERVAL))
        .http2_keepalive_timeout(Some(KEEPALIVE_TIMEOUT))
        .max_concurrent_streams(MAX_STREAMS_PER_CONNECTION)
        .http2_max_header_list_size(MAX_HEADER_LIST_BYTES)
        .http2_max_pending_accept_reset_streams(Some(32))
        .timeout(REQUEST_TIMEOUT)
        .layer(ActivityLayer)
}

/// Why a server refuses to listen where it was asked to.
#[derive(Debug, thiserror::Error)]
#[error(
    "refusing to serve {listen} without {missing}: anyone who can reach that address could \
     use this node. Listen on loopback (127.0.0.1), configure them, or pass --insecure on a \
     network you trust"
)]
pub struct Exposed {
    /// The address asked for.
    pub listen: std::net::SocketAddr,
    /// The missing protections, e.g. "TLS and user tokens".
    pub missing: String,
}

/// [`check_exposure`] of every address a server listens on (its gRPC listener and its HTTP
/// one, if any), with the protections marked absent in `protections` (`(present, "TLS
/// (--tls-cert, --tls-key)")`, ...) as missing: the one check both servers make at start.
pub fn check_listeners(
    listeners: impl IntoIterator<Item = std::net::SocketAddr>,
    protections: &[(bool, &str)],
    insecure: bool,
) -> Result<(), Exposed> {
    let missing: Vec<&str> = protections
        .iter()
        .filter_map(|&(present, what)| (!present).then_some(what))
        .collect();
    listeners
        .into_iter()
        .try_for_each(|listen| check_exposure(listen, &missing, insecure))
}

/// Checks that a server listening on `listen` is not reachable from other machines without
/// the protections it lacks (`missing`, each like "TLS"): a loopback address is always fine;
/// any other needs `insecure`, and then a warning is logged.
pub fn check_exposure(
    listen: std::net::SocketAddr,
    missing: &[&str],
    insecure: bool,
) -> Result<(), Exposed> {
    if missing.is_empty() || listen.ip().is_loopback() {
        return Ok(());
    }
    let missing = match missing {
        [one] => one.to_string(),
        [init @ .., last] => format!("{} and {last}", init.join(", ")),
        [] => unreachable!("checked above"),
    };
    if insecure {
        warn!(
            %listen,
            "--insecure: serving without {missing}; anyone who can reach this address can use \
             this node"
        );
        return Ok(());
    }
    Err(Exposed { listen, missing })
}
