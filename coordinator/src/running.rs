//! The running frame as the shell holds it: the machine's `RunningFrame` (which does no I/O)
//! with the film file its committed tiles are written to and the previews made of it, and
//! the clock the shell reads for the machine's events.

use std::ops::{Deref, DerefMut};
use std::sync::{Arc, OnceLock};
use std::time::Instant;

use rayfarm_core::render::Film;
use rayfarm_machine::Time;
use rayfarm_machine::coordinator::{CommittedTile, RunningFrame};

use crate::preview::Previews;

/// A frame and its film: they start, run and end together. Previews hold the film weakly
/// (its file goes when the frame does) and outlive it with their last image.
pub struct Running {
    pub frame: RunningFrame,
    pub film: Arc<Film>,
    pub previews: Arc<Previews>,
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
    /// Adds tiles the frame committed to the film (a progressive subframe's to those
    /// before it); the next preview shows them.
    pub fn write_tiles(&self, committed: &[CommittedTile]) -> anyhow::Result<()> {
        let samples = self.frame.samples().count;
        for (tile, sums) in committed {
            self.film.add_tile(*tile, sums, samples)?;
        }
        self.previews
            .advance(committed.len(), self.frame.subframes().0);
        Ok(())
    }
}

/// Now, as the machines see it: time since the process first asked.
pub fn now() -> Time {
    static ORIGIN: OnceLock<Instant> = OnceLock::new();
    Time::from_duration(ORIGIN.get_or_init(Instant::now).elapsed())
}
