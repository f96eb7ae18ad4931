//! Logging and process lifecycle shared by the binaries: logs go to stderr (stdout is for
//! results and the `listening on` line), coloured only on a terminal.

use std::future::Future;
use std::io::IsTerminal;
use std::process::ExitCode;

use tracing_subscriber::EnvFilter;

/// Installs the log subscriber: `RUST_LOG` if set, else `default` (e.g. "info").
pub fn init_logging(default: &str) {
    tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(default)),
        )
        .with_ansi(std::io::stderr().is_terminal())
        .with_writer(std::io::stderr)
        .init();
}

/// Completes on Ctrl-C or, on Unix, SIGTERM (what `docker stop`, Slurm and Kubernetes send).
pub async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        if let Ok(mut term) = signal(SignalKind::terminate()) {
            tokio::select! {
                _ = tokio::signal::ctrl_c() => {}
                _ = term.recv() => {}
            }
            return;
        }
    }
    // Without a signal handler there is nothing to wait for but Ctrl-C.
    let _ = tokio::signal::ctrl_c().await;
}

/// How long a server's blocking tasks get to finish once `run` has returned.
const SHUTDOWN_GRACE: std::time::Duration = std::time::Duration::from_secs(1);

/// The `main` of a server binary: the allocator's arenas capped ([`crate::heap::limit_arenas`]),
/// logging at the level `-v` asks for, a tokio runtime (with
/// `worker_threads` threads, or one per core), then `run`; an error is logged, printed and
/// turned into a failing exit code.
pub fn server_main<F>(verbose: u8, worker_threads: Option<usize>, run: F) -> ExitCode
where
    F: Future<Output = anyhow::Result<()>>,
{
    crate::heap::limit_arenas();
    init_logging(match verbose {
        0 => "info",
        1 => "debug",
        _ => "trace",
    });
    let mut builder = tokio::runtime::Builder::new_multi_thread();
    if let Some(n) = worker_threads {
        builder.worker_threads(n);
    }
    let runtime = match builder.enable_all().build() {
        Ok(r) => r,
        Err(e) => {
            tracing::error!(error = %e, "cannot start the runtime");
            return ExitCode::FAILURE;
        }
    };
    let code = match runtime.block_on(run) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!("{e:#}");
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    };
    // Blocking work still in flight (a tracing pass, a file being written) must not hold the
    // process past a stop signal: dropping the runtime would wait for it.
    runtime.shutdown_timeout(SHUTDOWN_GRACE);
    code
}
