//! `rayfarm health ADDR`: the standard gRPC health check against a coordinator or a worker,
//! for container health checks (the image has no shell or curl) and for scripts.

use std::time::Duration;

use anyhow::{Context, bail};
use clap::Args;
use rayfarm_node::security::ConnectTlsArgs;
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;

use crate::client::{ClientCertArgs, runtime};

/// Options of `rayfarm health`.
#[derive(Args, Clone, Debug)]
pub struct HealthArgs {
    /// Address of a rayfarm-coordinator or rayfarm-worker: HOST:PORT or http://HOST:PORT.
    pub addr: String,
    /// TLS, for servers started with --tls-cert (the health service needs no credentials).
    #[command(flatten)]
    pub tls: ConnectTlsArgs,
    /// For servers that require client certificates (--tls-client-ca).
    #[command(flatten)]
    pub cert: ClientCertArgs,
    /// Expect the server's certificate to carry this node's own name (the common name of
    /// --tls-cert), not the address's host: the probe a node runs against itself at
    /// 127.0.0.1, when its certificate names only the node (`rayfarm certs --node`).
    #[arg(long, requires = "tls_cert", conflicts_with = "tls_domain")]
    pub own_name: bool,
    /// Seconds to wait for an answer.
    #[arg(long, default_value_t = 3.0)]
    pub timeout: f64,
}

pub fn run(mut a: HealthArgs) -> anyhow::Result<()> {
    if a.own_name
        && let Some(cert) = &a.cert.tls_cert
    {
        let own = rayfarm_node::identity::PeerIdentity::from_pem_file(cert)
            .map_err(|e| anyhow::anyhow!("--own-name: {e}"))?;
        a.tls.tls_domain = Some(own.name);
    }
    let tls = a.tls.client_config(a.cert.identity()?)?;
    let url = rayfarm_node::security::url(&a.addr, tls.is_some());
    let timeout = Duration::try_from_secs_f64(a.timeout).context("--timeout")?;
    let status = runtime()?.block_on(async {
        let channel = rayfarm_node::security::endpoint(&a.addr, tls.as_ref())?
            .connect_timeout(timeout)
            .timeout(timeout)
            .connect()
            .await
            .with_context(|| format!("{url} is unreachable"))?;
        let response = HealthClient::new(channel)
            .check(HealthCheckRequest::default())
            .await
            .with_context(|| {
                // In plain text against a TLS server the error says only "broken pipe".
                let hint = if tls.is_none() {
                    " (if it serves TLS, give --tls-ca)"
                } else {
                    ""
                };
                format!("{url} did not answer the health check{hint}")
            })?;
        anyhow::Ok(response.into_inner().status())
    })?;
    if status != ServingStatus::Serving {
        bail!("{url} is {}", status.as_str_name());
    }
    println!("{url}: serving");
    Ok(())
}
