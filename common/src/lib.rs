//! rayfarm's shared library: geometry, scenes cut into domains, the render kernel and the
//! single-process reference renderer. The coordinator, the workers and the CLI are thin layers
//! over it. See `docs/ARCHITECTURE.md` for where each concept lives.

pub mod bundler;
pub mod bvh;
pub mod camera;
pub mod cluster;
pub mod fault;
pub mod frame;
pub mod geometry;
pub mod isosurface;
pub mod mesh;
pub mod nbody;
pub mod prepare;
pub mod proto;
pub mod ray;
pub mod render;
pub mod sampling;
pub mod scene;
pub mod schedule;
pub mod security;
pub mod telemetry;
pub mod units;
pub mod volume;
pub mod wire;
