//! Test hosts: each process of a test cluster in its own Linux network namespace, with its own
//! address on a private bridge, so that a test can cut, slow down or lose packets on one
//! host's links the way a real network does (loopback never does any of that).
//!
//! Layout of one [`Net`]: a "switch" namespace holding the bridge `br0`, and one namespace per
//! host with `eth0` (address `10.77.0.N/24`) paired with the switch's `vN` on the bridge. The
//! root namespace is never touched, so the same subnet serves every test at once. Faults are
//! `iptables` rules and `tc` qdiscs inside the hosts' namespaces (this kernel has no netem:
//! delay comes from rayfarm's own fault injection).
//!
//! Namespaces are named `rft-<pid>-<n>-<label>`: unique per test process and per test, so
//! tests run in parallel. They are removed when the [`Net`] is dropped (also while a test
//! panics); ones left by a test process that died are removed by the next [`Net::new`].

use std::os::fd::AsRawFd;
use std::path::Path;
use std::process::{Command, Output};
use std::sync::Once;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Prefix of every namespace the harness makes.
const PREFIX: &str = "rft-";
/// The first three octets of every host's address.
const SUBNET: &str = "10.77.0";
/// Most hosts on one net (addresses .1 to .250).
const MAX_HOSTS: usize = 250;

/// A host: its namespace and its address.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Host {
    /// What the test calls it (`coordinator`, `worker-2`, ...).
    pub label: String,
    /// Its network namespace.
    pub ns: String,
    /// Its one address.
    pub addr: String,
    /// Its interface's peer on the switch (where traffic towards the host is shaped).
    switch_port: String,
}

impl Host {
    /// Runs `f` on a thread inside this host's network namespace, so its sockets are the
    /// host's: it reaches what listens on the host's own loopback. (A namespace is a thread's,
    /// so the test's other threads stay where they are.)
    pub fn within<T: Send>(&self, f: impl FnOnce() -> T + Send) -> T {
        let path = format!("/var/run/netns/{}", self.ns);
        std::thread::scope(|scope| {
            scope
                .spawn(|| {
                    let ns =
                        std::fs::File::open(&path).unwrap_or_else(|e| panic!("open {path}: {e}"));
                    // SAFETY: setns on a namespace file this thread holds open; it changes
                    // only this thread's network namespace.
                    let entered = unsafe { libc::setns(ns.as_raw_fd(), libc::CLONE_NEWNET) };
                    assert_eq!(
                        entered,
                        0,
                        "setns {path}: {}",
                        std::io::Error::last_os_error()
                    );
                    f()
                })
                .join()
                .unwrap_or_else(|e| std::panic::resume_unwind(e))
        })
    }
}

/// A private network of [`Host`]s on one bridge.
pub struct Net {
    /// `rft-<pid>-<n>-`: every namespace of this net starts with it.
    prefix: String,
    switch: String,
    hosts: Vec<Host>,
}

/// Why a command failed, with its output.
fn failure(what: &str, out: &Output) -> String {
    format!(
        "`{what}` failed ({}): {}",
        out.status,
        String::from_utf8_lossy(&out.stderr).trim()
    )
}

/// Runs `program args`; `Err` says what failed and why.
fn run(program: &str, args: &[&str]) -> Result<(), String> {
    let what = format!("{program} {}", args.join(" "));
    let out = Command::new(program)
        .args(args)
        .output()
        .map_err(|e| format!("`{what}` could not start: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(failure(&what, &out))
    }
}

/// Runs `program args` inside namespace `ns`.
fn run_in(ns: &str, program: &str, args: &[&str]) -> Result<(), String> {
    let mut all = vec!["netns", "exec", ns, program];
    all.extend_from_slice(args);
    run("ip", &all)
}

/// The namespaces that exist now.
fn namespaces() -> Vec<String> {
    let out = Command::new("ip").args(["netns", "list"]).output();
    let Ok(out) = out else { return Vec::new() };
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| l.split_whitespace().next())
        .map(str::to_string)
        .collect()
}

/// Kills every process in namespace `ns`, then deletes it.
fn remove_namespace(ns: &str) {
    if let Ok(out) = Command::new("ip").args(["netns", "pids", ns]).output() {
        for pid in String::from_utf8_lossy(&out.stdout).split_whitespace() {
            let _ = Command::new("kill").args(["-KILL", pid]).output();
        }
    }
    let _ = Command::new("ip").args(["netns", "del", ns]).output();
}

/// Removes namespaces left by test processes that no longer run (a crashed or killed run).
fn remove_stale_namespaces() {
    let me = std::process::id().to_string();
    for ns in namespaces() {
        let Some(rest) = ns.strip_prefix(PREFIX) else {
            continue;
        };
        let pid = rest.split('-').next().unwrap_or_default();
        if pid != me && !Path::new("/proc").join(pid).exists() {
            eprintln!("removing stale test namespace {ns}");
            remove_namespace(&ns);
        }
    }
}

impl Net {
    /// Makes the switch of a new net. `Err` says why namespaces cannot be made here (not
    /// root, no `ip`, a sandbox without network namespaces).
    pub fn new() -> Result<Net, String> {
        static SWEEP: Once = Once::new();
        static NEXT: AtomicUsize = AtomicUsize::new(0);
        SWEEP.call_once(remove_stale_namespaces);
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let prefix = format!("{PREFIX}{}-{n}-", std::process::id());
        let switch = format!("{prefix}switch");
        run("ip", &["netns", "add", &switch])?;
        // From here on, Drop removes what was made.
        let net = Net {
            prefix,
            switch,
            hosts: Vec::new(),
        };
        run(
            "ip",
            &["-n", &net.switch, "link", "add", "br0", "type", "bridge"],
        )?;
        run("ip", &["-n", &net.switch, "link", "set", "br0", "up"])?;
        Ok(net)
    }

    /// [`Net::new`], or `None` after printing a `SKIPPED` line naming `test` and the reason:
    /// tests on namespaced hosts pass where namespaces cannot be made.
    pub fn or_skip(test: &str) -> Option<Net> {
        match Net::new() {
            Ok(net) => Some(net),
            Err(why) => {
                eprintln!("SKIPPED {test}: network namespaces cannot be made here: {why}");
                None
            }
        }
    }

    /// Adds a host called `label` with the next free address.
    pub fn add_host(&mut self, label: &str) -> Host {
        let n = self.hosts.len() + 1;
        assert!(n <= MAX_HOSTS, "at most {MAX_HOSTS} hosts on one net");
        let host = Host {
            label: label.to_string(),
            ns: format!("{}h{n}", self.prefix),
            addr: format!("{SUBNET}.{n}"),
            switch_port: format!("v{n}"),
        };
        let made = (|| {
            run("ip", &["netns", "add", &host.ns])?;
            self.hosts.push(host.clone());
            let sw = self.switch.as_str();
            let port = host.switch_port.as_str();
            run(
                "ip",
                &[
                    "-n", sw, "link", "add", port, "type", "veth", "peer", "name", "eth0", "netns",
                    &host.ns,
                ],
            )?;
            run(
                "ip",
                &["-n", sw, "link", "set", port, "master", "br0", "up"],
            )?;
            let cidr = format!("{}/24", host.addr);
            run("ip", &["-n", &host.ns, "addr", "add", &cidr, "dev", "eth0"])?;
            run("ip", &["-n", &host.ns, "link", "set", "eth0", "up"])?;
            run("ip", &["-n", &host.ns, "link", "set", "lo", "up"])
        })();
        if let Err(e) = made {
            panic!("cannot add host {label}: {e}");
        }
        host
    }

    /// `iptables args` on `host`, panicking with the reason if it fails.
    fn iptables(host: &Host, args: &[&str]) {
        if let Err(e) = run_in(&host.ns, "iptables", args) {
            panic!("on {}: {e}", host.label);
        }
    }

    /// The rules that drop what `to` receives from `from`.
    fn drop_from(from: &Host) -> [&str; 6] {
        ["INPUT", "-s", from.addr.as_str(), "-j", "DROP", "-w"]
    }

    /// Cuts the link between `a` and `b` both ways: each drops every packet from the other,
    /// as a broken switch port or a firewall would (no resets: connections just go silent).
    pub fn cut(&self, a: &Host, b: &Host) {
        let mut rule = vec!["-A"];
        rule.extend(Self::drop_from(b));
        Self::iptables(a, &rule);
        rule[1..].copy_from_slice(&Self::drop_from(a));
        Self::iptables(b, &rule);
    }

    /// Undoes [`Net::cut`] of `a` and `b`.
    pub fn heal(&self, a: &Host, b: &Host) {
        let mut rule = vec!["-D"];
        rule.extend(Self::drop_from(b));
        Self::iptables(a, &rule);
        rule[1..].copy_from_slice(&Self::drop_from(a));
        Self::iptables(b, &rule);
    }

    /// Cuts `host` off from every one of `others`.
    pub fn isolate(&self, host: &Host, others: &[&Host]) {
        for other in others {
            self.cut(host, other);
        }
    }

    /// Undoes [`Net::isolate`].
    pub fn rejoin(&self, host: &Host, others: &[&Host]) {
        for other in others {
            self.heal(host, other);
        }
    }

    /// Every packet to and from `host` is lost with `probability`, on its own, as on a bad
    /// cable: `host` drops that share of what it receives, every other host that share of
    /// what it receives from `host`.
    pub fn lossy(&self, host: &Host, probability: f64) {
        let p = probability.to_string();
        let random = ["-m", "statistic", "--mode", "random", "--probability", &p];
        let mut rule = vec!["-A", "INPUT", "-i", "eth0"];
        rule.extend(random);
        rule.extend(["-j", "DROP", "-w"]);
        Self::iptables(host, &rule);
        for other in self.hosts.iter().filter(|h| *h != host) {
            let mut rule = vec!["-A", "INPUT", "-s", &host.addr];
            rule.extend(random);
            rule.extend(["-j", "DROP", "-w"]);
            Self::iptables(other, &rule);
        }
    }

    /// Removes every rule of [`Net::cut`], [`Net::lossy`] on every host: the network is whole.
    pub fn heal_all(&self) {
        for host in &self.hosts {
            Self::iptables(host, &["-F", "INPUT", "-w"]);
        }
    }

    /// Limits `host`'s link to `rate` (tc syntax, e.g. `10mbit`) both ways: a token bucket on
    /// its `eth0` (what it sends) and on its switch port (what it receives).
    pub fn shape(&self, host: &Host, rate: &str) {
        let tbf = |ns: &str, dev: &str| {
            // A 32 kbit bucket; packets that would wait over 200 ms are dropped, as a
            // congested link's queue does.
            let args = [
                "-n", ns, "qdisc", "replace", "dev", dev, "root", "tbf", "rate", rate, "burst",
                "32kbit", "latency", "200ms",
            ];
            if let Err(e) = run("tc", &args) {
                panic!("shaping {}: {e}", host.label);
            }
        };
        tbf(&host.ns, "eth0");
        tbf(&self.switch, &host.switch_port);
    }

    /// A command that runs `program` on `host` (`ip netns exec`).
    pub fn command(host: &Host, program: &Path) -> Command {
        let mut cmd = Command::new("ip");
        cmd.args(["netns", "exec", &host.ns]).arg(program);
        cmd
    }
}

impl Drop for Net {
    fn drop(&mut self) {
        for host in &self.hosts {
            remove_namespace(&host.ns);
        }
        remove_namespace(&self.switch);
    }
}
