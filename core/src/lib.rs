//! rayfarm's pure core: geometry, scenes cut into domains, the render kernel, the film, tiles
//! and credit, the schedules, the bundler, the ray wire format and the single-process reference
//! renderer. It depends on no async runtime, RPC or command-line crate: the node library
//! (`rayfarm-node`), the coordinator, the workers and the CLI are layers over it. See
//! `docs/ARCHITECTURE.md` for where each concept lives.

pub mod bundler;
pub mod bvh;
pub mod camera;
pub mod cluster;
pub mod colour_map;
pub mod geometry;
pub mod isosurface;
pub mod mesh;
pub mod nbody;
pub mod prepare;
pub mod progressive;
pub mod ray;
pub mod render;
pub mod sampling;
pub mod scene;
pub mod schedule;
pub mod tile;
pub mod transfer;
pub mod units;
pub mod volume;
pub mod wire;
