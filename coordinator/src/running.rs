//! A frame's film as the shell holds it (the frame itself is the machine's): the film file
//! its committed tiles are written to and the previews made of it, from the frame's
//! preparation to its results; and the clock the shell reads for the machine's events.

use std::sync::{Arc, OnceLock};
use std::time::Instant;

use rayfarm_core::render::Film;
use rayfarm_machine::Time;
use rayfarm_machine::coordinator::CommittedTile;

use crate::preview::Previews;

/// A frame's film and its previews. Previews hold the film weakly (its file goes when the
/// frame's film does) and outlive it with their last image.
pub struct Running {
    pub film: Arc<Film>,
    pub previews: Arc<Previews>,
}

impl Running {
    /// Writes tiles the frame committed to the film; the next preview shows them.
    pub fn write_tiles(&self, committed: &[CommittedTile]) -> anyhow::Result<()> {
        for (tile, sums) in committed {
            self.film.write_tile(*tile, sums)?;
        }
        self.previews
            .advance(committed.iter().map(|(tile, _)| *tile));
        Ok(())
    }
}

/// Now, as the machines see it: time since the process first asked.
pub fn now() -> Time {
    static ORIGIN: OnceLock<Instant> = OnceLock::new();
    Time::from_duration(ORIGIN.get_or_init(Instant::now).elapsed())
}
