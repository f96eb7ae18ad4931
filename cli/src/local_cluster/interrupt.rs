//! A session's end on a stop signal: Ctrl-C, SIGTERM or SIGHUP interrupts it, and the job it
//! left in flight is cancelled so the cluster does not go on rendering it.

use std::cell::RefCell;
use std::time::Duration;

use anyhow::Context;

use crate::client::Coordinator;

/// The job a session is waiting for, if any, and where it runs: what an interrupted or
/// failed session cancels so the cluster does not go on rendering it.
#[derive(Default)]
pub struct JobInFlight(RefCell<Option<(Coordinator, String)>>);

impl JobInFlight {
    /// Records job `job_id` on `coordinator` as the one in flight.
    pub fn set(&self, coordinator: &Coordinator, job_id: &str) {
        self.0
            .replace(Some((coordinator.clone(), job_id.to_string())));
    }

    /// The job in flight has ended.
    pub fn clear(&self) {
        self.0.replace(None);
    }

    /// Cancels the job in flight (if any), giving up quietly after a moment: this is cleanup
    /// on the way out.
    pub async fn cancel_quietly(&self) {
        let Some((mut coord, job_id)) = self.0.take() else {
            return;
        };
        let cancel = coord.cancel(&job_id);
        let _ = tokio::time::timeout(Duration::from_secs(3), cancel).await;
    }
}

/// The session was stopped by a signal (Ctrl-C, SIGTERM or SIGHUP).
#[derive(Debug, thiserror::Error)]
#[error("interrupted by {0}")]
pub struct Interrupted(pub &'static str);

/// Completes with the signal's name on Ctrl-C (SIGINT) or, on Unix, SIGTERM or SIGHUP; fails
/// if a handler cannot be installed.
pub async fn stop_signal() -> anyhow::Result<&'static str> {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        let mut term = signal(SignalKind::terminate()).context("listening for SIGTERM")?;
        let mut hup = signal(SignalKind::hangup()).context("listening for SIGHUP")?;
        tokio::select! {
            r = tokio::signal::ctrl_c() => r.map(|()| "Ctrl-C").context("listening for Ctrl-C"),
            _ = term.recv() => Ok("SIGTERM"),
            _ = hup.recv() => Ok("SIGHUP"),
        }
    }
    #[cfg(not(unix))]
    {
        tokio::signal::ctrl_c()
            .await
            .context("listening for Ctrl-C")?;
        Ok("Ctrl-C")
    }
}

/// Runs `session` until it ends or a stop signal arrives (an [`Interrupted`] error); if it
/// did not succeed, cancels the job it left in flight.
pub async fn interruptible<T>(
    in_flight: &JobInFlight,
    session: impl Future<Output = anyhow::Result<T>>,
) -> anyhow::Result<T> {
    let outcome = tokio::select! {
        r = session => r,
        r = stop_signal() => match r {
            Ok(signal) => {
                // End whatever progress line was being written.
                eprintln!();
                Err(Interrupted(signal).into())
            }
            Err(e) => Err(e),
        },
    };
    if outcome.is_err() {
        in_flight.cancel_quietly().await;
    }
    outcome
}
