//! The running frame as the shell holds it: the machine's `RunningFrame` (which does no I/O)
//! with the film file its committed tiles are written to, and the clock the shell reads for
//! the machine's events.

use std::ops::{Deref, DerefMut};
use std::sync::OnceLock;
use std::time::Instant;

use rayfarm_core::render::Film;
use rayfarm_machine::Time;
use rayfarm_machine::coordinator::{CommittedTile, RunningFrame};

/// A frame and its film: they start, run and end together.
pub struct Running {
    pub frame: RunningFrame,
    pub film: Film,
}

// The frame is what the state reads and changes; the film only takes its committed tiles.
impl Deref for Running {
    type Target = RunningFrame;
    fn deref(&self) -> &RunningFrame {
        &self.frame
    }
}

impl DerefMut for Running {
    fn deref_mut(&mut self) -> &mut RunningFrame {
        &mut self.frame
    }
}

impl Running {
    /// Writes tiles the frame committed to the film.
    pub fn write_tiles(&self, committed: &[CommittedTile]) -> anyhow::Result<()> {
        for (tile, sums) in committed {
            self.film.write_tile(*tile, sums)?;
        }
        Ok(())
    }
}

/// Now, as the machines see it: time since the process first asked.
pub fn now() -> Time {
    static ORIGIN: OnceLock<Instant> = OnceLock::new();
    Time::from_duration(ORIGIN.get_or_init(Instant::now).elapsed())
}
