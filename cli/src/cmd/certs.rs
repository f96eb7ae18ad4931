//! `rayfarm certs`: a private CA, a shared node certificate and one certificate per node
//! (`--node ID`, named by the node's id, for mutual TLS) for a cluster's TLS (and, on
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

/// The CA's private key: kept (0600) so `--node` can issue node certificates later. Keep it
/// off the nodes: whoever holds it can mint any node's certificate.
pub const CA_KEY_FILE: &str = "ca-key.pem";

/// A node certificate's file: `node-ID.pem`.
pub fn node_cert_file(id: &str) -> String {
    format!("node-{id}.pem")
}

/// A node certificate's key: `node-ID-key.pem`.
pub fn node_key_file(id: &str) -> String {
    format!("node-{id}-key.pem")
}

/// Options of `rayfarm certs`.
#[derive(Args, Clone, Debug)]
pub struct CertsArgs {
    /// Directory to write into (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Names and IP addresses the shared node certificate (`node.pem`, the coordinator's) is
    /// valid for, comma-separated (e.g. coordinator,rayfarm,localhost,127.0.0.1). Clients
    /// check the name they connect to, or their --tls-domain, against this list. Needed when
    /// the CA is made; without it, only the --node certificates are issued, by the CA in --out.
    #[arg(long, value_delimiter = ',', required_unless_present = "node")]
    pub hosts: Vec<String>,
    /// Issue a certificate of its own for the node (worker) ID, by the CA in --out or the one
    /// made now: `node-ID.pem` and `node-ID-key.pem`, with ID as its subject's common name
    /// (under mutual TLS, the worker id it must register with) and valid for ID (when ID is
    /// a DNS name) and --node-hosts. Repeatable or comma-separated.
    #[arg(long, value_delimiter = ',')]
    pub node: Vec<String>,
    /// More names and IP addresses every --node certificate is valid for (the hosts its
    /// node is reached at: its peer address's host must be one of them). `{id}` stands for
    /// the node's id, e.g. `{id}.rayfarm-workers.default.svc` for a StatefulSet's pods.
    #[arg(long, value_delimiter = ',', requires = "node")]
    pub node_hosts: Vec<String>,
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
    /// Write each --node's files into a directory of its own, `DIR/ID/`, instead of --out:
    /// `node.pem`, `node-key.pem`, a copy of `ca.pem` and (with --with-secrets) of
    /// `cluster-secret`: everything that node needs and no other node's key, so it can be
    /// given to that node alone (a volume or Secret of its own).
    #[arg(long, requires = "node")]
    pub node_dir: Option<PathBuf>,
    /// Owner (`UID:GID`) of every file and directory written, for a one-shot container that
    /// runs as root to write into volumes the nodes read as an unprivileged user.
    #[arg(long, value_parser = parse_owner)]
    pub owner: Option<(u32, u32)>,
}

fn parse_owner(s: &str) -> Result<(u32, u32), String> {
    let (uid, gid) = s
        .split_once(':')
        .ok_or_else(|| format!("{s:?}: expected UID:GID, e.g. 10001:10001"))?;
    let id = |v: &str| {
        v.parse::<u32>()
            .map_err(|_| format!("{s:?}: {v:?} is not a number"))
    };
    Ok((id(uid)?, id(gid)?))
}

/// Where one node's certificate and key go: `--out/node-ID.pem` and `--out/node-ID-key.pem`,
/// or with `--node-dir`, `DIR/ID/node.pem` and `DIR/ID/node-key.pem` beside copies of the
/// CA certificate and the cluster secret.
struct NodeFiles {
    dir: PathBuf,
    cert: PathBuf,
    key: PathBuf,
    /// Copies of the CA certificate and (with --with-secrets) the cluster secret, in a node
    /// directory only.
    copies: Vec<(PathBuf, &'static str)>,
}

impl NodeFiles {
    fn of(a: &CertsArgs, id: &str) -> NodeFiles {
        match &a.node_dir {
            None => NodeFiles {
                dir: a.out.clone(),
                cert: a.out.join(node_cert_file(id)),
                key: a.out.join(node_key_file(id)),
                copies: Vec::new(),
            },
            Some(root) => {
                let dir = root.join(id);
                let mut copies = vec![(dir.join(CA_FILE), CA_FILE)];
                if a.with_secrets {
                    copies.push((dir.join(SECRET_FILE), SECRET_FILE));
                }
                NodeFiles {
                    cert: dir.join(CERT_FILE),
                    key: dir.join(KEY_FILE),
                    copies,
                    dir,
                }
            }
        }
    }

    /// Every path this node's files are written to.
    fn paths(&self) -> impl Iterator<Item = &Path> {
        [self.cert.as_path(), self.key.as_path()]
            .into_iter()
            .chain(self.copies.iter().map(|(p, _)| p.as_path()))
    }
}

/// Names as given: trimmed, empty ones dropped, each a DNS name or an IP address.
fn hosts(flag: &str, given: &[String]) -> anyhow::Result<Vec<String>> {
    let hosts: Vec<String> = given
        .iter()
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty())
        .collect();
    if let Some(bad) = hosts.iter().find(|h| !valid_host(h)) {
        bail!("{flag}: {bad:?} is neither a DNS name nor an IP address");
    }
    Ok(hosts)
}

/// A node id that can name files and a certificate: letters, digits, `.`, `_` and `-`, not
/// starting with `.`, at most 200 bytes.
fn valid_node_id(id: &str) -> bool {
    !id.is_empty()
        && id.len() <= 200
        && !id.starts_with('.')
        && id
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'))
}

pub fn run(a: CertsArgs) -> anyhow::Result<()> {
    let shared_hosts = hosts("--hosts", &a.hosts)?;
    // Checked with a stand-in id now, and for each node's own id below.
    hosts(
        "--node-hosts",
        &a.node_hosts
            .iter()
            .map(|h| h.replace("{id}", "node"))
            .collect::<Vec<_>>(),
    )?;
    let nodes: Vec<String> = a
        .node
        .iter()
        .map(|n| n.trim().to_string())
        .filter(|n| !n.is_empty())
        .collect();
    if let Some(bad) = nodes.iter().find(|n| !valid_node_id(n)) {
        bail!(
            "--node: {bad:?} is not a node id (letters, digits, '.', '_' and '-', at most 200 \
             bytes)"
        );
    }
    if shared_hosts.is_empty() && nodes.is_empty() {
        bail!("--hosts names no host");
    }
    let owner = a.owner;
    make_dir(&a.out, owner)?;
    let path = |name: &str| a.out.join(name);
    let node_files: Vec<(&String, NodeFiles)> =
        nodes.iter().map(|id| (id, NodeFiles::of(&a, id))).collect();
    // With --hosts this run makes (or, --if-missing, keeps) the CA set; without, it only
    // reads the CA to issue node certificates.
    let set = [CA_FILE, CA_KEY_FILE, CERT_FILE, KEY_FILE];
    let mut wanted: Vec<PathBuf> = Vec::new();
    if !shared_hosts.is_empty() {
        wanted.extend(set.iter().map(|f| path(f)));
    }
    if a.with_secrets {
        wanted.extend([path(SECRET_FILE), path(TOKENS_FILE)]);
    }
    for (_, files) in &node_files {
        wanted.push(files.dir.clone());
        wanted.extend(files.paths().map(Path::to_path_buf));
    }
    // A symlink is never followed (it could point a key anywhere), a dangling one included.
    let is_link = |p: &Path| {
        p.symlink_metadata()
            .is_ok_and(|m| m.file_type().is_symlink())
    };
    if let Some(link) = wanted
        .iter()
        .cloned()
        .chain(set.iter().map(|f| path(f)))
        .find(|p| is_link(p))
    {
        bail!(
            "{} is a symbolic link: refusing to write through it (remove it)",
            link.display()
        );
    }
    let exists = |p: &Path| p.symlink_metadata().is_ok();
    let existing: Vec<String> = wanted
        .iter()
        .filter(|p| exists(p) && !p.is_dir())
        .map(|p| p.strip_prefix(&a.out).unwrap_or(p).display().to_string())
        .collect();
    if !a.if_missing && !existing.is_empty() {
        bail!(
            "{} already holds {}: remove them or pass --if-missing",
            a.out.display(),
            existing.join(", ")
        );
    }
    let write = |p: &Path, text: &str, mode: u32| write(p, text, mode, owner);
    let mut issuer = None;
    if !shared_hosts.is_empty() {
        // The CA files only work as a set: one missing means a new CA and certificate.
        let kept: Vec<&str> = set.into_iter().filter(|f| exists(&path(f))).collect();
        if kept.len() == set.len() {
            println!("kept the certificates in {}", a.out.display());
        } else if !kept.is_empty() {
            // A new set would overwrite what exists, a key included: never with --if-missing.
            bail!(
                "{} holds {} but not the whole set ({}): restore the missing files or remove \
                 the others",
                a.out.display(),
                kept.join(", "),
                set.join(", ")
            );
        } else {
            let (ca, ca_key, ca_issuer) = new_ca(a.days)?;
            let (cert, key) = issue(&ca_issuer, "rayfarm node", &shared_hosts, a.days)?;
            write(&path(CA_FILE), &ca, 0o644)?;
            write(&path(CA_KEY_FILE), &ca_key, 0o600)?;
            write(&path(CERT_FILE), &cert, 0o644)?;
            write(&path(KEY_FILE), &key, 0o600)?;
            println!(
                "wrote {CA_FILE}, {CA_KEY_FILE}, {CERT_FILE}, {KEY_FILE} in {} (names: {})",
                a.out.display(),
                shared_hosts.join(", ")
            );
            issuer = Some(ca_issuer);
        }
    }
    // The secrets come before the node directories, which may hold copies of them.
    if a.with_secrets {
        if !exists(&path(SECRET_FILE)) {
            write(&path(SECRET_FILE), &format!("{}\n", random_hex()?), 0o600)?;
            println!("wrote {SECRET_FILE}");
        }
        if !exists(&path(TOKENS_FILE)) {
            let text = format!(
                "# TOKEN [USER [ROLE]], one per line; ROLE admin may cancel anyone's jobs\n{} admin admin\n",
                random_hex()?
            );
            write(&path(TOKENS_FILE), &text, 0o600)?;
            println!("wrote {TOKENS_FILE}");
        }
    }
    for (id, files) in &node_files {
        make_dir(&files.dir, owner)?;
        for (copy, of) in &files.copies {
            if !exists(copy) {
                let text = std::fs::read_to_string(path(of))
                    .with_context(|| format!("reading {}", path(of).display()))?;
                let mode = if *of == CA_FILE { 0o644 } else { 0o600 };
                write(copy, &text, mode)?;
            }
        }
        let shown = |p: &Path| p.display().to_string();
        match (exists(&files.cert), exists(&files.key)) {
            (true, true) => {
                println!("kept {}", shown(&files.cert));
                continue;
            }
            (false, false) => {}
            _ => bail!(
                "one of {} and {} exists: restore the other or remove it",
                shown(&files.cert),
                shown(&files.key)
            ),
        }
        if issuer.is_none() {
            issuer = Some(load_ca(&a.out)?);
        }
        let issuer = issuer.as_ref().expect("loaded above");
        let mut names: Vec<String> = Vec::new();
        if valid_host(id) {
            names.push((*id).clone());
        }
        let own: Vec<String> = a.node_hosts.iter().map(|h| h.replace("{id}", id)).collect();
        names.extend(
            hosts("--node-hosts", &own)?
                .into_iter()
                .filter(|h| h != *id),
        );
        if names.is_empty() {
            bail!("--node {id}: give the hosts it is reached at (--node-hosts)");
        }
        let (cert, key) = issue(issuer, id, &names, a.days)?;
        write(&files.cert, &cert, 0o644)?;
        write(&files.key, &key, 0o600)?;
        println!(
            "wrote {}, {} (node {id}; names: {})",
            shown(&files.cert),
            shown(&files.key),
            names.join(", ")
        );
    }
    Ok(())
}

/// Creates `dir` (and its parents) if missing, then gives it to `owner`.
fn make_dir(dir: &Path, owner: Option<(u32, u32)>) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    chown(dir, owner)
}

/// Gives `path` to `owner` (`--owner`), never through a symlink.
fn chown(path: &Path, owner: Option<(u32, u32)>) -> anyhow::Result<()> {
    #[cfg(unix)]
    if let Some((uid, gid)) = owner {
        std::os::unix::fs::lchown(path, Some(uid), Some(gid))
            .with_context(|| format!("giving {} to {uid}:{gid}", path.display()))?;
    }
    #[cfg(not(unix))]
    let _ = (path, owner);
    Ok(())
}

/// The validity of a certificate made now: from an hour ago (clocks slightly behind this
/// one) for `days`.
fn validity(days: u32) -> (OffsetDateTime, OffsetDateTime) {
    let now = OffsetDateTime::now_utc();
    (
        now - Duration::hours(1),
        now + Duration::days(i64::from(days.max(1))),
    )
}

/// A new CA: (certificate PEM, key PEM, the issuer that signs with it).
fn new_ca(days: u32) -> anyhow::Result<(String, String, Issuer<'static, KeyPair>)> {
    let mut ca = CertificateParams::new(Vec::<String>::new())?;
    ca.distinguished_name = name("rayfarm cluster CA");
    ca.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
    ca.key_usages = vec![
        KeyUsagePurpose::KeyCertSign,
        KeyUsagePurpose::CrlSign,
        KeyUsagePurpose::DigitalSignature,
    ];
    (ca.not_before, ca.not_after) = validity(days);
    let ca_key = KeyPair::generate().context("generating the CA key")?;
    let ca_cert = ca.self_signed(&ca_key).context("signing the CA")?;
    let key_pem = ca_key.serialize_pem();
    Ok((ca_cert.pem(), key_pem, Issuer::new(ca, ca_key)))
}

/// The CA kept in `dir` (`ca.pem` and `ca-key.pem`), to issue node certificates with.
fn load_ca(dir: &Path) -> anyhow::Result<Issuer<'static, KeyPair>> {
    let read = |f: &str| {
        std::fs::read_to_string(dir.join(f)).with_context(|| {
            format!(
                "reading {} (node certificates are issued by the CA that `rayfarm certs --hosts` \
                 made there; a CA made before rayfarm kept {CA_KEY_FILE} cannot issue more: \
                 make a new one)",
                dir.join(f).display()
            )
        })
    };
    let (ca, key) = (read(CA_FILE)?, read(CA_KEY_FILE)?);
    let key = KeyPair::from_pem(&key)
        .with_context(|| format!("{} is not a key", dir.join(CA_KEY_FILE).display()))?;
    Issuer::from_ca_cert_pem(&ca, key)
        .with_context(|| format!("{} is not a CA certificate", dir.join(CA_FILE).display()))
}

/// A certificate named `common` (a node's id), valid for `hosts`, signed by `issuer`, for
/// servers and clients both (nodes present it to each other under mutual TLS): (PEM, key PEM).
fn issue(
    issuer: &Issuer<'_, KeyPair>,
    common: &str,
    hosts: &[String],
    days: u32,
) -> anyhow::Result<(String, String)> {
    let mut node = CertificateParams::new(hosts.to_vec())
        .context("a host is not a valid DNS name or IP address")?;
    node.distinguished_name = name(common);
    node.key_usages = vec![KeyUsagePurpose::DigitalSignature];
    node.extended_key_usages = vec![
        ExtendedKeyUsagePurpose::ServerAuth,
        ExtendedKeyUsagePurpose::ClientAuth,
    ];
    (node.not_before, node.not_after) = validity(days);
    let key = KeyPair::generate().context("generating a node key")?;
    let cert = node
        .signed_by(&key, issuer)
        .with_context(|| format!("signing the certificate of {common}"))?;
    Ok((cert.pem(), key.serialize_pem()))
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

/// Creates `path` with `mode` and writes `text`: never over an existing file (the callers
/// checked; a file that appeared since is an error) and never through a symlink.
fn write(path: &Path, text: &str, mode: u32, owner: Option<(u32, u32)>) -> anyhow::Result<()> {
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
        .with_context(|| format!("writing {}", path.display()))?;
    chown(path, owner)
}

#[cfg(test)]
mod tests {
    use super::{valid_host, valid_node_id};

    #[test]
    fn node_ids_name_files_safely() {
        for ok in ["w-a", "worker-1", "rayfarm-worker-0", "n_1.x"] {
            assert!(valid_node_id(ok), "{ok}");
        }
        for bad in ["", ".hidden", "a/b", "../x", "a b", "a:1"] {
            assert!(!valid_node_id(bad), "{bad}");
        }
    }

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
