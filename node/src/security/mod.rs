//! Transport security and credentials of the gRPC links: TLS from PEM files, the cluster
//! secret that workers present to the coordinator and to each other, and the user tokens of
//! the job API.
//!
//! Everything is off unless configured, so a loopback demo needs no files. The credentials
//! are checked by tonic interceptors ([`RequireSecret`], [`RequireToken`]) wrapped around the
//! services that need them; the health service is never wrapped, so probes work without
//! credentials.
//!
//! The parts: [`tls`] (a server's certificate and a client's CA from PEM files), [`connect`]
//! (how a client reaches a server: endpoint, timeouts, the credential it presents), [`serve`]
//! (a server's connection limits and its exposure check), [`credentials`] (the cluster secret,
//! user tokens and the interceptors that check them).

use std::path::{Path, PathBuf};

mod connect;
mod credentials;
mod serve;
mod tls;

pub use connect::{
    CONNECT_TIMEOUT, ClientSecurity, KEEPALIVE_INTERVAL, KEEPALIVE_TIMEOUT, endpoint, url,
};
pub use credentials::{
    ClusterSecret, Credential, InvalidToken, RequireSecret, RequireToken, User, UserTokens,
    first_token,
};
pub use serve::{
    Exposed, MAX_HEADER_LIST_BYTES, MAX_STREAMS_PER_CONNECTION, REQUEST_TIMEOUT, check_exposure,
    check_listeners, server_builder,
};
pub use tls::{ConnectTlsArgs, ServeTlsArgs};

/// The metadata header carrying the cluster secret.
pub const SECRET_HEADER: &str = "x-rayfarm-secret";

/// The metadata header carrying a user token (`Bearer TOKEN`).
pub const TOKEN_HEADER: &str = "authorization";

/// The environment variables that turn security on in the binaries and the CLI.
pub const ENV_VARS: &[&str] = &[
    "RAYFARM_TLS_CERT",
    "RAYFARM_TLS_KEY",
    "RAYFARM_TLS_CLIENT_CA",
    "RAYFARM_TLS_CA",
    "RAYFARM_TLS_DOMAIN",
    "RAYFARM_CLUSTER_SECRET_FILE",
    "RAYFARM_USER_TOKENS_FILE",
    "RAYFARM_TOKEN",
    "RAYFARM_TOKEN_FILE",
];

/// Why security configuration could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum SecurityError {
    /// A file could not be read.
    #[error("cannot read {what} {}: {reason}", path.display())]
    Read {
        /// What the file was for ("TLS certificate", "cluster secret file", ...).
        what: &'static str,
        /// The file.
        path: PathBuf,
        /// The I/O error (in the message, not a source: printed once).
        reason: std::io::Error,
    },
    /// A PEM file holds no PEM block.
    #[error("{what} {} is not PEM (no -----BEGIN line)", path.display())]
    NotPem {
        /// What the file was for.
        what: &'static str,
        /// The file.
        path: PathBuf,
    },
    /// The cluster secret file is empty.
    #[error("cluster secret file {} is empty", path.display())]
    EmptySecret {
        /// The file.
        path: PathBuf,
    },
    /// A secret or token has characters a gRPC header cannot carry.
    #[error(
        "{what} in {} must be printable ASCII without spaces (it travels in a gRPC header)",
        path.display()
    )]
    NotHeaderSafe {
        /// "the cluster secret" or "the token on line N".
        what: String,
        /// The file.
        path: PathBuf,
    },
    /// The user tokens file holds no token.
    #[error("user tokens file {} holds no token", path.display())]
    NoTokens {
        /// The file.
        path: PathBuf,
    },
    /// A token appears twice in the user tokens file.
    #[error("user tokens file {}: the token on line {line} repeats an earlier one", path.display())]
    DuplicateToken {
        /// The file.
        path: PathBuf,
        /// 1-based line of the repeat.
        line: usize,
    },
    /// A role other than `admin` or `user` in the user tokens file.
    #[error("user tokens file {}: the role on line {line} must be `admin` or `user`", path.display())]
    BadRole {
        /// The file.
        path: PathBuf,
        /// 1-based line.
        line: usize,
    },
    /// An `https://` address was given but no CA to verify the server with.
    #[error("{url} asks for TLS: give the CA that signed its certificate (--tls-ca)")]
    HttpsWithoutCa {
        /// The address.
        url: String,
    },
    /// An address that is no URL.
    #[error("{url:?} is not a valid address: {reason}")]
    BadAddress {
        /// The address.
        url: String,
        /// tonic's reason, with its causes.
        reason: String,
    },
    /// tonic refused the TLS configuration (e.g. a key that does not parse).
    #[error("TLS configuration refused: {0}")]
    Tls(String),
}

fn read(path: &Path, what: &'static str) -> Result<Vec<u8>, SecurityError> {
    std::fs::read(path).map_err(|reason| SecurityError::Read {
        what,
        path: path.to_path_buf(),
        reason,
    })
}

fn read_pem(path: &Path, what: &'static str) -> Result<Vec<u8>, SecurityError> {
    let pem = read(path, what)?;
    // A PEM check here names the file; rustls would only say "no certificates" later.
    if !pem.windows(11).any(|w| w == b"-----BEGIN ") {
        return Err(SecurityError::NotPem {
            what,
            path: path.to_path_buf(),
        });
    }
    Ok(pem)
}

/// True for bytes a gRPC ASCII header value can carry and that survive trimming.
fn header_safe(bytes: &[u8]) -> bool {
    !bytes.is_empty() && bytes.iter().all(|b| b.is_ascii_graphic())
}

#[cfg(test)]
mod tests;
