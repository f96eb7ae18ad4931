//! `rayfarm certs`: a private CA and one node certificate for a cluster's TLS (and, on
//! request, a random cluster secret and user token), so the compose and Kubernetes examples
//! turn TLS on without openssl. A real cluster may use certificates from any CA instead.

use std::fs::OpenOptions;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::Args;
use rcgen::{
    BasicConstraints, CertificateParams, DistinguishedName, DnType, ExtendedKeyUsagePurpose, IsCa,
    Issuer, KeyPair, KeyUsagePurpose,
};
use time::{Duration, OffsetDateTime};

/// The CA certificate every node and client trusts.
pub const CA_FILE: &str = "ca.pem";
/// The node certificate (all `--hosts` as names), served by the coordinator and workers.
pub const CERT_FILE: &str = "node.pem";
/// The node certificate's private key.
pub const KEY_FILE: &str = "node-key.pem";
/// The cluster secret (`--with-secrets`).
pub const SECRET_FILE: &str = "cluster-secret";
/// The user tokens file (`--with-secrets`): one token, for the user `admin`.
pub const TOKENS_FILE: &str = "user-tokens";

/// Options of `rayfarm certs`.
#[derive(Args, Clone, Debug)]
pub struct CertsArgs {
    /// Directory to write into (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Names and IP addresses the node certificate is valid for, comma-separated (e.g.
    /// coordinator,rayfarm,localhost,127.0.0.1). Clients check the name they connect to, or
    /// their --tls-domain, against this list.
    #[arg(long, value_delimiter = ',', required = true)]
    pub hosts: Vec<String>,
    /// Days the certificates are valid.
    #[arg(long, default_value_t = 3650)]
    pub days: u32,
    /// Also write a random cluster secret (`cluster-secret`) and user token (`user-tokens`).
    #[arg(long)]
    pub with_secrets: bool,
    /// Keep files that exist and write only the missing ones (for one-shot containers that
    /// run at every start). Without it, existing files are an error.
    #[arg(long)]
    pub if_missing: bool,
}

pub fn run(a: CertsArgs) -> anyhow::Result<()> {
    let hosts: Vec<String> = a
        .hosts
        .iter()
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty())
        .collect();
    if hosts.is_empty() {
        bail!("--hosts names no host");
    }
    if let Some(bad) = hosts.iter().find(|h| !valid_host(h)) {
        bail!("--hosts: {bad:?} is neither a DNS name nor an IP address");
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let path = |name: &str| a.out.join(name);
    let mut wanted = vec![CA_FILE, CERT_FILE, KEY_FILE];
    if a.with_secrets {
        wanted.extend([SECRET_FILE, TOKENS_FILE]);
    }
    // A symlink is never followed (it could point a key anywhere), a dangling one included.
    if let Some(link) = wanted.iter().find(|f| {
        path(f)
            .symlink_metadata()
            .is_ok_and(|m| m.file_type().is_symlink())
    }) {
        bail!(
            "{} is a symbolic link: refusing to write through it (remove it)",
            path(link).display()
        );
    }
    let existing: Vec<&str> = wanted
        .iter()
        .copied()
        .filter(|f| path(f).symlink_metadata().is_ok())
        .collect();
    if !a.if_missing && !existing.is_empty() {
        bail!(
            "{} already holds {}: remove them or pass --if-missing",
            a.out.display(),
            existing.join(", ")
        );
    }
    // The three TLS files only work as a set: one missing means a new CA and certificate.
    let tls_missing = [CA_FILE, CERT_FILE, KEY_FILE]
        .iter()
        .any(|f| !existing.contains(f));
    let kept_tls: Vec<&str> = [CA_FILE, CERT_FILE, KEY_FILE]
        .into_iter()
        .filter(|f| existing.contains(f))
        .collect();
    if tls_missing && !kept_tls.is_empty() {
        // A new set would overwrite what exists, the key included: never with --if-missing.
        bail!(
            "{} holds {} but not the whole set ({CA_FILE}, {CERT_FILE}, {KEY_FILE}): restore the \
             missing files or remove the others",
            a.out.display(),
            kept_tls.join(", ")
        );
    }
    if tls_missing {
        let (ca, cert, key) = generate(&hosts, a.days)?;
        write(&path(CA_FILE), &ca, 0o644)?;
        write(&path(CERT_FILE), &cert, 0o644)?;
        write(&path(KEY_FILE), &key, 0o600)?;
        println!(
            "wrote {CA_FILE}, {CERT_FILE}, {KEY_FILE} in {} (names: {})",
            a.out.display(),
            hosts.join(", ")
        );
    } else {
        println!("kept the certificates in {}", a.out.display());
    }
    if a.with_secrets {
        if !existing.contains(&SECRET_FILE) {
            write(&path(SECRET_FILE), &format!("{}\n", random_hex()?), 0o600)?;
            println!("wrote {SECRET_FILE}");
        }
        if !existing.contains(&TOKENS_FILE) {
            let text = format!(
                "# TOKEN [USER [ROLE]], one per line; ROLE admin may cancel anyone's jobs\n{} admin admin\n",
                random_hex()?
            );
            write(&path(TOKENS_FILE), &text, 0o600)?;
            println!("wrote {TOKENS_FILE}");
        }
    }
    Ok(())
}

/// A new CA and a node certificate for `hosts` signed by it: (CA PEM, node PEM, key PEM).
/// The CA's key is dropped: nothing more can be signed, so a leak of the output cannot mint
/// certificates; new hosts mean running this again.
fn generate(hosts: &[String], days: u32) -> anyhow::Result<(String, String, String)> {
    // An hour of slack for clocks slightly behind this one.
    let not_before = OffsetDateTime::now_utc() - Duration::hours(1);
    let not_after = OffsetDateTime::now_utc() + Duration::days(i64::from(days.max(1)));

    let mut ca = CertificateParams::new(Vec::<String>::new())?;
    ca.distinguished_name = name("rayfarm cluster CA");
    ca.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
    ca.key_usages = vec![
        KeyUsagePurpose::KeyCertSign,
        KeyUsagePurpose::CrlSign,
        KeyUsagePurpose::DigitalSignature,
    ];
    ca.not_before = not_before;
    ca.not_after = not_after;
    let ca_key = KeyPair::generate().context("generating the CA key")?;
    let ca_cert = ca.self_signed(&ca_key).context("signing the CA")?;
    let issuer = Issuer::new(ca, ca_key);

    let mut node = CertificateParams::new(hosts.to_vec())
        .context("--hosts: a name is not a valid DNS name or IP address")?;
    node.distinguished_name = name("rayfarm node");
    node.key_usages = vec![KeyUsagePurpose::DigitalSignature];
    // Servers and clients both: workers present it to the coordinator and peers for mTLS.
    node.extended_key_usages = vec![
        ExtendedKeyUsagePurpose::ServerAuth,
        ExtendedKeyUsagePurpose::ClientAuth,
    ];
    node.not_before = not_before;
    node.not_after = not_after;
    let node_key = KeyPair::generate().context("generating the node key")?;
    let node_cert = node
        .signed_by(&node_key, &issuer)
        .context("signing the node certificate")?;
    Ok((ca_cert.pem(), node_cert.pem(), node_key.serialize_pem()))
}

/// An IP address, or a DNS name (letters, digits and hyphens in dot-separated labels, a
/// leading `*.` wildcard allowed). rcgen would put any ASCII in the certificate, which no
/// client could then match.
fn valid_host(host: &str) -> bool {
    if host.parse::<std::net::IpAddr>().is_ok() {
        return true;
    }
    let name = host.strip_prefix("*.").unwrap_or(host);
    name.len() <= 253
        && name.split('.').all(|label| {
            !label.is_empty()
                && label.len() <= 63
                && !label.starts_with('-')
                && !label.ends_with('-')
                && label
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b == b'-')
        })
}

fn name(common: &str) -> DistinguishedName {
    let mut dn = DistinguishedName::new();
    dn.push(DnType::CommonName, common);
    dn
}

/// 32 random bytes in hex.
fn random_hex() -> anyhow::Result<String> {
    let mut bytes = [0u8; 32];
    getrandom::fill(&mut bytes).map_err(|e| anyhow::anyhow!("no system randomness: {e}"))?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// Writes `text` to a new file with `mode` (on Unix), replacing any file there.
/// Creates `path` with `mode` and writes `text`: never over an existing file (the callers
/// checked; a file that appeared since is an error) and never through a symlink.
fn write(path: &Path, text: &str, mode: u32) -> anyhow::Result<()> {
    let mut options = OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.mode(mode).custom_flags(libc::O_NOFOLLOW);
    }
    #[cfg(not(unix))]
    let _ = mode;
    let mut file = options
        .open(path)
        .with_context(|| format!("creating {}", path.display()))?;
    file.write_all(text.as_bytes())
        .with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::valid_host;

    #[test]
    fn hosts_are_dns_names_or_ip_addresses() {
        for ok in [
            "localhost",
            "rayfarm",
            "a-b.c.svc",
            "*.rayfarm-workers",
            "10.0.0.1",
            "::1",
        ] {
            assert!(valid_host(ok), "{ok}");
        }
        for bad in ["not a name", "", "a..b", "-a", "a_b", "*", "a.*.b"] {
            assert!(!valid_host(bad), "{bad}");
        }
    }
}
