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
    /// Adds tiles the frame committed, of `samples` samples a pixel, to the film (a
    /// progressive subframe's to those before it); the next preview shows them, and
    /// `subframes_done` whole subframes.
    pub fn write_tiles(
        &self,
        committed: &[CommittedTile],
        samples: u32,
        subframes_done: u32,
    ) -> anyhow::Result<()> {
        for (tile, sums) in committed {
            self.film.add_tile(*tile, sums, samples)?;
        }
        self.previews.advance(committed.len(), subframes_done);
        Ok(())
    }
}

/// Now, as the machines see it: time since the process first asked.
pub fn now() -> Time {
    static ORIGIN: OnceLock<Instant> = OnceLock::new();
    Time::from_duration(ORIGIN.get_or_init(Instant::now).elapsed())
}
