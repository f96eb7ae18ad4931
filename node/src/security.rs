//! Transport security and credentials of the gRPC links: TLS from PEM files, the cluster
//! secret that workers present to the coordinator and to each other, and the user tokens of
//! the job API.
//!
//! Everything is off unless configured, so a loopback demo needs no files. The credentials
//! are checked by tonic interceptors ([`RequireSecret`], [`RequireToken`]) wrapped around the
//! services that need them; the health service is never wrapped, so probes work without
//! credentials.

use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use subtle::ConstantTimeEq;
use tokio_rustls::TlsAcceptor;
use tokio_rustls::rustls;
use tokio_rustls::rustls::pki_types::pem::PemObject;
use tokio_rustls::rustls::pki_types::{CertificateDer, PrivateKeyDer};
use tokio_rustls::rustls::server::WebPkiClientVerifier;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::Interceptor;
use tonic::transport::{Certificate, ClientTlsConfig, Endpoint, Identity};
use tonic::{Request, Status};
use tower::layer::util::{Identity as NoLayer, Stack};
use tracing::warn;

use crate::idle::ActivityLayer;

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

/// TLS options of a server (the coordinator, a worker's peer service).
#[derive(clap::Args, Clone, Debug, Default)]
pub struct ServeTlsArgs {
    /// PEM certificate (chain) this node presents; with --tls-key, its services are served
    /// over TLS only. A worker also presents it to servers that ask for client certificates.
    #[arg(long, env = "RAYFARM_TLS_CERT", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// PEM private key of --tls-cert.
    #[arg(long, env = "RAYFARM_TLS_KEY", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// Mutual TLS: refuse clients that present no certificate signed by this PEM CA.
    #[arg(long, env = "RAYFARM_TLS_CLIENT_CA", requires = "tls_cert")]
    pub tls_client_ca: Option<PathBuf>,
}

impl ServeTlsArgs {
    /// The server TLS configuration, or `None` when no certificate is given (plain text).
    /// The handshake itself is done by [`crate::listen`], under its deadline.
    pub fn server_config(&self) -> Result<Option<TlsAcceptor>, SecurityError> {
        // gRPC is HTTP/2 only.
        self.server_config_for(b"h2", self.tls_client_ca.as_deref())
    }

    /// [`ServeTlsArgs::server_config`] for the HTTP/1.1 listener ([`crate::http`]): the same
    /// certificate, but no client certificate is asked for even under mutual TLS. Browsers
    /// and Prometheus hold none; `/metrics` is read-only and the dashboard's `/api/` needs a
    /// user token (`RequireToken::authenticate`).
    pub fn http_server_config(&self) -> Result<Option<TlsAcceptor>, SecurityError> {
        self.server_config_for(b"http/1.1", None)
    }

    fn server_config_for(
        &self,
        alpn: &[u8],
        client_ca: Option<&Path>,
    ) -> Result<Option<TlsAcceptor>, SecurityError> {
        let (Some(cert), Some(key)) = (&self.tls_cert, &self.tls_key) else {
            return Ok(None);
        };
        let chain = CertificateDer::pem_slice_iter(&read_pem(cert, "TLS certificate")?)
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| SecurityError::Tls(format!("{}: {e}", cert.display())))?;
        let key_der = PrivateKeyDer::from_pem_slice(&read_pem(key, "TLS key")?)
            .map_err(|e| SecurityError::Tls(format!("{}: {e}", key.display())))?;
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let builder = rustls::ServerConfig::builder_with_provider(provider.clone())
            .with_safe_default_protocol_versions()
            .map_err(|e| SecurityError::Tls(e.to_string()))?;
        let builder = match client_ca {
            None => builder.with_no_client_auth(),
            Some(ca) => {
                let mut roots = rustls::RootCertStore::empty();
                for c in CertificateDer::pem_slice_iter(&read_pem(ca, "TLS client CA")?) {
                    let c = c.map_err(|e| SecurityError::Tls(format!("{}: {e}", ca.display())))?;
                    roots
                        .add(c)
                        .map_err(|e| SecurityError::Tls(format!("{}: {e}", ca.display())))?;
                }
                let verifier = WebPkiClientVerifier::builder_with_provider(roots.into(), provider)
                    .build()
                    .map_err(|e| SecurityError::Tls(format!("{}: {e}", ca.display())))?;
                builder.with_client_cert_verifier(verifier)
            }
        };
        let mut config = builder.with_single_cert(chain, key_der).map_err(|e| {
            SecurityError::Tls(format!("{} and {}: {e}", cert.display(), key.display()))
        })?;
        config.alpn_protocols = vec![alpn.to_vec()];
        Ok(Some(TlsAcceptor::from(Arc::new(config))))
    }

    /// This node's certificate and key, when it has them (presented as a client identity).
    pub fn identity(&self) -> Result<Option<Identity>, SecurityError> {
        match (&self.tls_cert, &self.tls_key) {
            (Some(cert), Some(key)) => identity(cert, key).map(Some),
            _ => Ok(None),
        }
    }
}

/// TLS options of a process that connects to rayfarm servers.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct ConnectTlsArgs {
    /// PEM CA certificate(s) the servers' certificates must chain to. Turns TLS on for every
    /// connection this process makes (addresses become https://).
    #[arg(long, env = "RAYFARM_TLS_CA")]
    pub tls_ca: Option<PathBuf>,
    /// Name the servers' certificates must carry, instead of the host of their address (for
    /// addresses no certificate names, e.g. container ids or published ports).
    #[arg(long, env = "RAYFARM_TLS_DOMAIN", requires = "tls_ca")]
    pub tls_domain: Option<String>,
}

impl ConnectTlsArgs {
    /// The client TLS configuration, or `None` without --tls-ca (plain text). `identity` is
    /// presented to servers that ask for a client certificate.
    pub fn client_config(
        &self,
        identity: Option<Identity>,
    ) -> Result<Option<ClientTlsConfig>, SecurityError> {
        let Some(ca) = &self.tls_ca else {
            return Ok(None);
        };
        let mut config = ClientTlsConfig::new().ca_certificate(certificate(ca, "TLS CA")?);
        if let Some(domain) = &self.tls_domain {
            config = config.domain_name(domain.clone());
        }
        if let Some(identity) = identity {
            config = config.identity(identity);
        }
        Ok(Some(config))
    }
}

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
pub fn server_builder() -> tonic::transport::Server<Stack<ActivityLayer, NoLayer>> {
    tonic::transport::Server::builder()
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

fn certificate(path: &Path, what: &'static str) -> Result<Certificate, SecurityError> {
    read_pem(path, what).map(Certificate::from_pem)
}

fn identity(cert: &Path, key: &Path) -> Result<Identity, SecurityError> {
    Ok(Identity::from_pem(
        read_pem(cert, "TLS certificate")?,
        read_pem(key, "TLS key")?,
    ))
}

/// True for bytes a gRPC ASCII header value can carry and that survive trimming.
fn header_safe(bytes: &[u8]) -> bool {
    !bytes.is_empty() && bytes.iter().all(|b| b.is_ascii_graphic())
}

/// The secret every worker presents to the coordinator and to its peers. Never printed.
#[derive(Clone)]
pub struct ClusterSecret(Arc<[u8]>);

impl fmt::Debug for ClusterSecret {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("ClusterSecret(<redacted>)")
    }
}

impl ClusterSecret {
    /// Reads the secret from `path`; surrounding whitespace (a final newline) is ignored.
    pub fn from_file(path: &Path) -> Result<Self, SecurityError> {
        let bytes = read(path, "cluster secret file")?;
        let secret = bytes.trim_ascii();
        if secret.is_empty() {
            return Err(SecurityError::EmptySecret {
                path: path.to_path_buf(),
            });
        }
        if !header_safe(secret) {
            return Err(SecurityError::NotHeaderSafe {
                what: "the cluster secret".into(),
                path: path.to_path_buf(),
            });
        }
        Ok(ClusterSecret(secret.into()))
    }

    /// Reads the secret if a file is given.
    pub fn load(path: Option<&Path>) -> Result<Option<Self>, SecurityError> {
        path.map(Self::from_file).transpose()
    }

    fn matches(&self, presented: &[u8]) -> bool {
        bool::from(self.0.as_ref().ct_eq(presented))
    }

    fn header_value(&self) -> MetadataValue<Ascii> {
        let mut v =
            MetadataValue::try_from(self.0.as_ref()).expect("checked printable ASCII when loaded");
        v.set_sensitive(true);
        v
    }
}

/// The user tokens the job API accepts, each with its user (name and role).
#[derive(Clone)]
pub struct UserTokens(Arc<Vec<(Vec<u8>, User)>>);

impl fmt::Debug for UserTokens {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let names: Vec<&str> = self.0.iter().map(|(_, u)| u.name.as_str()).collect();
        f.debug_tuple("UserTokens").field(&names).finish()
    }
}

impl UserTokens {
    /// Reads `path`: one token per line, optionally followed by the user's name and then a
    /// role (`admin` may cancel anyone's jobs; `user`, the default, only their own); blank
    /// lines and lines starting with `#` are ignored. A token without a name is called
    /// `user-LINE`.
    pub fn from_file(path: &Path) -> Result<Self, SecurityError> {
        let bytes = read(path, "user tokens file")?;
        let text = String::from_utf8_lossy(&bytes);
        let mut tokens: Vec<(Vec<u8>, User)> = Vec::new();
        for (i, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let (token, name) = line.split_once(char::is_whitespace).unwrap_or((line, ""));
            if !header_safe(token.as_bytes()) {
                return Err(SecurityError::NotHeaderSafe {
                    what: format!("the token on line {}", i + 1),
                    path: path.to_path_buf(),
                });
            }
            if tokens.iter().any(|(t, _)| t == token.as_bytes()) {
                return Err(SecurityError::DuplicateToken {
                    path: path.to_path_buf(),
                    line: i + 1,
                });
            }
            let mut words = name.split_whitespace();
            let name = match words.next() {
                None => format!("user-{}", i + 1),
                Some(n) => n.to_string(),
            };
            let admin = match words.next() {
                None | Some("user") => false,
                Some("admin") => true,
                Some(_) => {
                    return Err(SecurityError::BadRole {
                        path: path.to_path_buf(),
                        line: i + 1,
                    });
                }
            };
            tokens.push((token.as_bytes().to_vec(), User { name, admin }));
        }
        if tokens.is_empty() {
            return Err(SecurityError::NoTokens {
                path: path.to_path_buf(),
            });
        }
        Ok(UserTokens(Arc::new(tokens)))
    }

    /// Reads the tokens if a file is given.
    pub fn load(path: Option<&Path>) -> Result<Option<Self>, SecurityError> {
        path.map(Self::from_file).transpose()
    }

    /// Number of tokens.
    pub fn len(&self) -> usize {
        self.0.len()
    }

    /// Never true for a loaded file (an empty one is refused).
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// The name of `presented`'s user. Every token is compared, in constant time, so the
    /// time taken tells nothing about which one nearly matched.
    fn user(&self, presented: &[u8]) -> Option<&User> {
        let mut found = None;
        for (token, user) in self.0.iter() {
            if bool::from(token.as_slice().ct_eq(presented)) {
                found = Some(user);
            }
        }
        found
    }
}

/// The user a request was authenticated as (in the request's extensions).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct User {
    /// The name from the tokens file: owner of the jobs the user submits.
    pub name: String,
    /// The admin role: may cancel anyone's jobs.
    pub admin: bool,
}

/// Server interceptor: refuses requests without the cluster secret (`UNAUTHENTICATED`).
/// Without a secret configured, every request passes.
#[derive(Clone, Debug)]
pub struct RequireSecret(pub Option<ClusterSecret>);

impl Interceptor for RequireSecret {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        let Some(secret) = &self.0 else {
            return Ok(request);
        };
        let refusal = match request.metadata().get(SECRET_HEADER) {
            Some(v) if secret.matches(v.as_bytes()) => return Ok(request),
            None => format!(
                "no cluster secret: this service requires the {SECRET_HEADER} header \
                 (start the worker with --cluster-secret-file)"
            ),
            Some(_) => "wrong cluster secret (check --cluster-secret-file)".to_string(),
        };
        warn!(client = ?crate::listen::remote_addr(&request), "refused: {refusal}");
        Err(Status::unauthenticated(refusal))
    }
}

/// Server interceptor: refuses requests without a known user token (`UNAUTHENTICATED`) and
/// records the [`User`] of the others. Without tokens configured, every request passes.
#[derive(Clone, Debug)]
pub struct RequireToken(pub Option<UserTokens>);

impl RequireToken {
    /// Who the `authorization` header value `presented` authenticates (`None` when user
    /// tokens are off), or why it is refused: the one check of the job API and of the
    /// dashboard's HTTP API.
    pub fn authenticate(&self, presented: Option<&[u8]>) -> Result<Option<User>, &'static str> {
        let Some(tokens) = &self.0 else {
            return Ok(None);
        };
        match presented.map(|v| v.strip_prefix(b"Bearer ")) {
            None => Err(
                "no user token: the job API requires `authorization: Bearer TOKEN` \
                 (rayfarm: --token, --token-file or RAYFARM_TOKEN)",
            ),
            Some(None) => Err("the authorization header must be `Bearer TOKEN`"),
            Some(Some(token)) => match tokens.user(token.trim_ascii()) {
                Some(user) => Ok(Some(user.clone())),
                None => Err("unknown user token"),
            },
        }
    }
}

impl Interceptor for RequireToken {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        let presented = request.metadata().get(TOKEN_HEADER).map(|v| v.as_bytes());
        match self.authenticate(presented) {
            Ok(None) => Ok(request),
            Ok(Some(user)) => {
                request.extensions_mut().insert(user);
                Ok(request)
            }
            Err(refusal) => {
                warn!(client = ?crate::listen::remote_addr(&request), "refused: {refusal}");
                Err(Status::unauthenticated(refusal))
            }
        }
    }
}

/// Client interceptor: adds a credential header to every request (nothing when `None`).
#[derive(Clone, Debug, Default)]
pub struct Credential(Option<(&'static str, MetadataValue<Ascii>)>);

impl Credential {
    /// No credential.
    pub fn none() -> Self {
        Credential(None)
    }

    /// The cluster secret, if any.
    pub fn secret(secret: Option<&ClusterSecret>) -> Self {
        Credential(secret.map(|s| (SECRET_HEADER, s.header_value())))
    }

    /// A user token, if any. Fails when it cannot travel in a header.
    pub fn bearer(token: Option<&str>) -> Result<Self, InvalidToken> {
        let Some(token) = token.map(str::trim) else {
            return Ok(Credential(None));
        };
        if !header_safe(token.as_bytes()) {
            return Err(InvalidToken);
        }
        let mut v = MetadataValue::try_from(format!("Bearer {token}")).map_err(|_| InvalidToken)?;
        v.set_sensitive(true);
        Ok(Credential(Some((TOKEN_HEADER, v))))
    }
}

/// A user token that cannot travel in a gRPC header.
#[derive(Debug, thiserror::Error)]
#[error("the user token must be printable ASCII without spaces")]
pub struct InvalidToken;

impl Interceptor for Credential {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some((key, value)) = &self.0 {
            request.metadata_mut().insert(*key, value.clone());
        }
        Ok(request)
    }
}

/// The first token of a user tokens file (what a client presents when given the file).
pub fn first_token(path: &Path) -> Result<String, SecurityError> {
    let tokens = UserTokens::from_file(path)?;
    Ok(String::from_utf8_lossy(&tokens.0[0].0).into_owned())
}

#[cfg(test)]
mod tests;
