//! Rendering: the kernel that traces one domain's queue, the fixed-point film, and the
//! single-process reference renderer.

pub mod cache;
pub mod dvr;
pub mod film;
pub mod kernel;
pub mod local;
pub mod primary;
pub mod speculation;
pub mod stats;
pub mod volume_light;

pub use film::Film;
pub use kernel::{KernelCounters, RaySink, SceneView};
