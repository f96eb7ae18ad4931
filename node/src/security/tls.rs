//! TLS from PEM files: a server's certificate and key (and, for mutual TLS, the CA its
//! clients' certificates must chain to), a client's CA and the name it expects.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use tokio_rustls::TlsAcceptor;
use tokio_rustls::rustls;
use tokio_rustls::rustls::pki_types::pem::PemObject;
use tokio_rustls::rustls::pki_types::{CertificateDer, PrivateKeyDer};
use tokio_rustls::rustls::server::WebPkiClientVerifier;
use tonic::transport::{Certificate, ClientTlsConfig, Identity};

use super::{SecurityError, read_pem};

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

fn certificate(path: &Path, what: &'static str) -> Result<Certificate, SecurityError> {
    read_pem(path, what).map(Certificate::from_pem)
}

fn identity(cert: &Path, key: &Path) -> Result<Identity, SecurityError> {
    Ok(Identity::from_pem(
        read_pem(cert, "TLS certificate")?,
        read_pem(key, "TLS key")?,
    ))
}
