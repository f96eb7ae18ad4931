//! Shared pieces of the integration tests: find the real binaries, run them, read their output,
//! and run a real cluster of them on loopback or on namespaced test hosts ([`Cluster`],
//! [`hosts`]).
//! The binaries are built by `cargo build --release --bins` (README's test command does it).
//!
//! The parts: [`cli`] runs the `rayfarm` command, [`scenes`] prepares scenes and reads image
//! hashes, [`process`] starts, signals and waits on processes, [`cluster`] runs a coordinator
//! and its workers, [`identical`] renders a scene every way that must give the same image,
//! [`http`] speaks plain HTTP/1.1 to their dashboards and metrics, [`hostile`] is an attacker's
//! raw connections and HTTP/2 frames, [`ports`] picks ports for programs that need one fixed.

use std::path::Path;

pub mod cli;
pub mod cluster;
pub mod hostile;
pub mod hosts;
pub mod http;
pub mod identical;
pub mod ports;
pub mod process;
pub mod scenes;

pub use cli::{
    CertFiles, bin, certs, rayfarm, rayfarm_env, rayfarm_err, rayfarm_ok, rayfarm_ok_env,
    repo_root, spawn_rayfarm, wait_line,
};
pub use cluster::{Cluster, ClusterOpts, WorkerOpts, job, jobs, submit_wait};
pub use http::{http_get, http_request, try_http_request};
pub use ports::fixed_port;
pub use process::{START_TIMEOUT, proc_status_bytes, signal_pid, wait_child, wait_until};
pub use scenes::{domain_bytes, file_hash, hash_of, local_hash, prepare_nbody, stats_field};

/// `p` as a `&str` for argument lists.
pub fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}
