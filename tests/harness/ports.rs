//! Ports for programs that take a fixed port as a flag (Slurm's daemons, the sbatch script,
//! Prometheus) rather than binding port 0 and reporting it.
//!
//! Asking the OS for a free port (bind port 0, read it, close) hands out a port from the
//! ephemeral range, which every outgoing connection and every `srun` I/O listener also draws
//! from: between the test closing it and the program binding it, another program can take it
//! (a CI run lost the Slurm test that way: "Address already in use" on the worker's port).
//! So these ports come from below the ephemeral range, where the OS never hands out a port by
//! itself, checked free on every address, and never twice in one test process.

use std::collections::HashSet;
use std::net::TcpListener;
use std::sync::Mutex;

/// Ports this process has handed out, so two calls never return the same one.
static GIVEN: Mutex<Option<HashSet<u16>>> = Mutex::new(None);

/// The lowest port of the OS's ephemeral range (`ip_local_port_range`), 32768 if unreadable.
fn ephemeral_start() -> u16 {
    std::fs::read_to_string("/proc/sys/net/ipv4/ip_local_port_range")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse().ok())
        .unwrap_or(32768)
}

/// A port free on every address now, outside the range the OS hands out by itself, not handed
/// out before by this process. Starts at a place set by the process id so parallel test
/// processes rarely try the same ports.
pub fn fixed_port() -> u16 {
    let high = ephemeral_start();
    // Below the ephemeral range and above the well-known ports: from 10,000 up where the
    // range leaves room.
    let low = if high > 11_000 { 10_000 } else { 1_024 };
    assert!(
        high > low,
        "the ephemeral range starts at {high}: no port below it to use"
    );
    let span = u32::from(high - low);
    let start = std::process::id() * 97 % span;
    let mut given = GIVEN.lock().unwrap_or_else(|e| e.into_inner());
    let given = given.get_or_insert_with(HashSet::new);
    for i in 0..span {
        let port = low + ((start + i) % span) as u16;
        if given.contains(&port) {
            continue;
        }
        if TcpListener::bind(("0.0.0.0", port)).is_ok() {
            given.insert(port);
            return port;
        }
    }
    panic!("no free port between {low} and {high}");
}
