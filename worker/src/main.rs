//! `rayfarm-worker`: part of the cluster, which is not built yet (see the cluster issue).
//! Until then it refuses to start, so that no script mistakes it for a working worker.

fn main() -> std::process::ExitCode {
    eprintln!("rayfarm-worker: the cluster is not built yet; use `rayfarm render --local`");
    std::process::ExitCode::from(2)
}
