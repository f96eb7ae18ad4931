//! `rayfarm cancel ID`: stop a queued or running job; prints the state it ended up in (a job
//! that had already ended keeps its state).

use anyhow::Context;
use clap::Args;

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
    println!("job {}: {}", a.job_id, state_name(state));
    Ok(())
}
