//! What the coordinator, the workers and the CLI agree on beyond the protobuf messages:
//! how a job names its scene, how tile sums travel, and the statistics a frame reports.

pub mod scene_ref;
pub mod stats;
pub mod tile_sums;
