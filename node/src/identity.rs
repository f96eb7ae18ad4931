//! Node identity under mutual TLS: the names a verified client certificate carries, and the
//! checks that bind a worker's id and peer address to them.
//!
//! A node certificate from `rayfarm certs --node ID` names the node in its subject's common
//! name (the worker id) and lists the hosts it may be reached at as subject alternative names.
//! The TLS handshake (`crate::listen`) has already verified the chain to the cluster CA before
//! any of this runs; here the names are only read and compared.

use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;

use tonic::Request;
use tonic::Status;
use x509_parser::extensions::GeneralName;
use x509_parser::prelude::{FromDer, X509Certificate};

use crate::listen::ConnInfo;

/// The names of a peer's verified certificate.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PeerIdentity {
    /// The subject's common name: for a node certificate, the node's (worker's) id.
    pub name: String,
    /// The DNS names and IP addresses the certificate is valid for.
    pub hosts: Vec<String>,
}

impl PeerIdentity {
    /// The names of the certificate `der`, or `None` when it does not parse or has no
    /// common name (nothing can then be bound to it).
    pub fn from_der(der: &[u8]) -> Option<PeerIdentity> {
        let (_, cert) = X509Certificate::from_der(der).ok()?;
        let name = cert
            .subject()
            .iter_common_name()
            .next()?
            .as_str()
            .ok()?
            .to_string();
        let mut hosts = Vec::new();
        if let Ok(Some(san)) = cert.subject_alternative_name() {
            for general in &san.value.general_names {
                match general {
                    GeneralName::DNSName(dns) => hosts.push(dns.to_ascii_lowercase()),
                    GeneralName::IPAddress(bytes) => {
                        let ip = match bytes.len() {
                            4 => <[u8; 4]>::try_from(*bytes).ok().map(IpAddr::from),
                            16 => <[u8; 16]>::try_from(*bytes).ok().map(IpAddr::from),
                            _ => None,
                        };
                        hosts.extend(ip.map(|ip| ip.to_string()));
                    }
                    _ => {}
                }
            }
        }
        Some(PeerIdentity { name, hosts })
    }

    /// The names of the first certificate in the PEM file `path` (this node's own).
    pub fn from_pem_file(path: &std::path::Path) -> Result<PeerIdentity, String> {
        use tokio_rustls::rustls::pki_types::CertificateDer;
        use tokio_rustls::rustls::pki_types::pem::PemObject;
        let der = CertificateDer::pem_file_iter(path)
            .map_err(|e| format!("{}: {e}", path.display()))?
            .next()
            .ok_or_else(|| format!("{} holds no certificate", path.display()))?
            .map_err(|e| format!("{}: {e}", path.display()))?;
        PeerIdentity::from_der(&der).ok_or_else(|| {
            format!(
                "{}: no subject common name to use as a node id",
                path.display()
            )
        })
    }

    /// Whether the certificate is valid for `host` (a DNS name, compared without case, a
    /// leading `*.` wildcard matching one label; or an IP address).
    pub fn names_host(&self, host: &str) -> bool {
        if let Ok(ip) = host.parse::<IpAddr>() {
            return self
                .hosts
                .iter()
                .any(|h| h.parse::<IpAddr>().is_ok_and(|h| h == ip));
        }
        let host = host.trim_end_matches('.').to_ascii_lowercase();
        self.hosts.iter().any(|h| match h.strip_prefix("*.") {
            Some(suffix) => host
                .split_once('.')
                .is_some_and(|(label, rest)| !label.is_empty() && rest == suffix),
            None => *h == host,
        })
    }

    /// Refuses (`PERMISSION_DENIED`) a worker registering as `worker_id` at `peer_address`
    /// unless its certificate names that id and the address's host.
    pub fn check_registration(&self, worker_id: &str, peer_address: &str) -> Result<(), Status> {
        if worker_id != self.name {
            return Err(Status::permission_denied(format!(
                "worker id {} is not the name of its client certificate ({}): with mutual TLS \
                 a worker registers under its certificate's name",
                crate::bounds::shown(worker_id),
                crate::bounds::shown(&self.name),
            )));
        }
        let host = host_of(peer_address);
        if !self.names_host(host) {
            return Err(Status::permission_denied(format!(
                "peer address {} is not a host of {}'s certificate (it names {}): issue its \
                 certificate with that host (rayfarm certs --node-hosts)",
                crate::bounds::shown(peer_address),
                self.name,
                crate::bounds::shown(&self.hosts.join(", ")),
            )));
        }
        Ok(())
    }
}

/// The host of `address` (`host:port`, `[v6]:port` or a URL), without scheme, port or path.
pub fn host_of(address: &str) -> &str {
    let rest = address.split_once("://").map_or(address, |(_, rest)| rest);
    let rest = rest.split('/').next().unwrap_or(rest);
    if rest.parse::<SocketAddr>().is_ok() {
        // `[v6]:port`: the brackets go.
        let ip = &rest[..rest.rfind(':').unwrap_or(rest.len())];
        return ip.trim_start_matches('[').trim_end_matches(']');
    }
    match rest.rsplit_once(':') {
        Some((host, port)) if port.bytes().all(|b| b.is_ascii_digit()) => host,
        _ => rest,
    }
}

/// The verified certificate names of the client that sent `request`, when it presented one
/// (mutual TLS on the connection).
pub fn of_request<T>(request: &Request<T>) -> Option<Arc<PeerIdentity>> {
    request
        .extensions()
        .get::<ConnInfo>()
        .and_then(|info| info.peer.clone())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn identity(hosts: &[&str]) -> PeerIdentity {
        PeerIdentity {
            name: "w-a".into(),
            hosts: hosts.iter().map(|h| h.to_string()).collect(),
        }
    }

    #[test]
    fn hosts_are_taken_from_addresses() {
        assert_eq!(host_of("worker-1:7000"), "worker-1");
        assert_eq!(host_of("https://worker-1:7000/"), "worker-1");
        assert_eq!(host_of("127.0.0.1:9"), "127.0.0.1");
        assert_eq!(host_of("[::1]:9"), "::1");
        assert_eq!(host_of("plain"), "plain");
    }

    #[test]
    fn names_match_hosts_ips_and_one_label_wildcards() {
        let id = identity(&["worker-1", "127.0.0.1", "*.workers.svc"]);
        assert!(id.names_host("WORKER-1"));
        assert!(id.names_host("127.0.0.1"));
        assert!(!id.names_host("127.0.0.2"));
        assert!(id.names_host("w0.workers.svc"));
        assert!(!id.names_host("a.w0.workers.svc"));
        assert!(!id.names_host("workers.svc"));
        assert!(!id.names_host("worker-2"));
    }

    #[test]
    fn registration_needs_the_certificates_name_and_host() {
        let id = identity(&["localhost", "127.0.0.1"]);
        assert!(id.check_registration("w-a", "127.0.0.1:4000").is_ok());
        let other = id.check_registration("w-b", "127.0.0.1:4000").unwrap_err();
        assert_eq!(other.code(), tonic::Code::PermissionDenied);
        assert!(other.message().contains("w-b"), "{}", other.message());
        let away = id.check_registration("w-a", "10.0.0.9:4000").unwrap_err();
        assert_eq!(away.code(), tonic::Code::PermissionDenied);
    }
}
