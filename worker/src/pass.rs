//! A pass on the worker's tracing pool: the kernel is `rayfarm_machine::pass` (the simulator
//! runs the same function); the shell only times it, since the machine owns no clock.

use std::time::Instant;

use rayfarm_machine::pass::{self, PassError, PassInput};
use rayfarm_machine::worker::PassOutput;

/// Runs a pass on the current rayon pool, with the time it took.
pub fn run(input: PassInput) -> Result<PassOutput, PassError> {
    let start = Instant::now();
    let mut out = pass::run(input)?;
    out.busy = start.elapsed();
    Ok(out)
}
