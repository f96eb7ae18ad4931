//! How a client reaches a rayfarm server: the endpoint of an address (scheme, TLS,
//! timeouts and HTTP/2 pings) and the credential every request carries.

use std::time::Duration;

use tonic::transport::{ClientTlsConfig, Endpoint};

use super::SecurityError;
use super::credentials::Credential;

/// An endpoint for `addr` (`host:port`, `http://…` or `https://…`). With `tls`, the address
/// becomes `https://` whatever scheme it was given with: tonic would otherwise connect in
/// plain text to an `http://` address despite the TLS configuration.
pub fn endpoint(addr: &str, tls: Option<&ClientTlsConfig>) -> Result<Endpoint, SecurityError> {
    let addr = addr.trim();
    let rest = addr
        .strip_prefix("http://")
        .or_else(|| addr.strip_prefix("https://"))
        .unwrap_or(addr);
    let url = match tls {
        Some(_) => format!("https://{rest}"),
        None if addr.starts_with("https://") => {
            return Err(SecurityError::HttpsWithoutCa {
                url: addr.to_string(),
            });
        }
        None => format!("http://{rest}"),
    };
    let endpoint = Endpoint::from_shared(url.clone()).map_err(|e| SecurityError::BadAddress {
        url,
        reason: causes(&e),
    })?;
    // Small messages must not wait for Nagle (NOTES.md), and a server whose machine died
    // without closing the connection is noticed by HTTP/2 pings, not after TCP's minutes.
    let endpoint = endpoint
        .tcp_nodelay(true)
        .connect_timeout(CONNECT_TIMEOUT)
        .http2_keep_alive_interval(KEEPALIVE_INTERVAL)
        .keep_alive_timeout(KEEPALIVE_TIMEOUT)
        .keep_alive_while_idle(true);
    match tls {
        Some(config) => endpoint
            .tls_config(config.clone())
            .map_err(|e| SecurityError::Tls(causes(&e))),
        None => Ok(endpoint),
    }
}

/// How long a client waits for a TCP connection.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);
/// Interval of HTTP/2 pings on every rayfarm connection, both ways.
pub const KEEPALIVE_INTERVAL: Duration = Duration::from_secs(10);
/// A connection whose ping goes unanswered this long is closed.
pub const KEEPALIVE_TIMEOUT: Duration = Duration::from_secs(20);

/// An error and its sources on one line: tonic's transport errors say only "transport
/// error" and keep the useful part in their sources.
fn causes(e: &(dyn std::error::Error + 'static)) -> String {
    let mut text = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        let part = s.to_string();
        if !text.contains(&part) {
            text = format!("{text}: {part}");
        }
        source = s.source();
    }
    text
}

/// How a process reaches rayfarm servers: with TLS or not, and the credential it presents.
#[derive(Clone, Debug, Default)]
pub struct ClientSecurity {
    /// TLS for every connection (`None`: plain text).
    pub tls: Option<ClientTlsConfig>,
    /// Added to every request.
    pub credential: Credential,
}

impl ClientSecurity {
    /// An endpoint for `addr` with this TLS configuration (see [`endpoint`]).
    pub fn endpoint(&self, addr: &str) -> Result<Endpoint, SecurityError> {
        endpoint(addr, self.tls.as_ref())
    }

    /// The URL connected to for `addr` (for messages).
    pub fn url(&self, addr: &str) -> String {
        url(addr, self.tls.is_some())
    }
}

/// `addr` as the URL [`endpoint`] connects to (for messages).
pub fn url(addr: &str, tls: bool) -> String {
    let addr = addr.trim();
    let rest = addr
        .strip_prefix("http://")
        .or_else(|| addr.strip_prefix("https://"))
        .unwrap_or(addr);
    if tls || addr.starts_with("https://") {
        format!("https://{rest}")
    } else {
        format!("http://{rest}")
    }
}
