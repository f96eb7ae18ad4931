//! `rayfarm cancel ID`: stop a queued or running job and print `job ID: cancelled`. A job that
//! had already succeeded or failed keeps its state, and saying so is an error: nothing was
//! cancelled. Cancelling a cancelled job again is not.

use anyhow::{Context, bail};
use clap::Args;
use rayfarm_node::proto::JobState;

use super::watch::state_name;
use crate::client::{CoordinatorArgs, runtime};

/// Options of `rayfarm cancel`.
#[derive(Args, Clone, Debug)]
pub struct CancelArgs {
    #[command(flatten)]
    pub coordinator: CoordinatorArgs,
    /// The job to cancel.
    pub job_id: String,
}

pub fn run(a: CancelArgs) -> anyhow::Result<()> {
    let state = runtime()?.block_on(async {
        let mut coord = a.coordinator.connect().await?;
        coord
            .cancel(&a.job_id)
            .await
            .with_context(|| format!("cancelling job {}", a.job_id))
    })?;
    if state != JobState::Cancelled {
        bail!(
            "job {} had already {} (nothing to cancel)",
            a.job_id,
            state_name(state)
        );
    }
    println!("job {}: {}", a.job_id, state_name(state));
    Ok(())
}
