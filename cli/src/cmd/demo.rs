//! `rayfarm demo`: the first thing to run. Prepares the built-in scene if it is missing and
//! renders it, printing the statistics table.

use std::path::PathBuf;

use clap::Args;
use rayfarm_common::scene::Manifest;

use super::prepare::{Generator, PrepareArgs};
use super::render::RenderArgs;

/// Options of `rayfarm demo`.
#[derive(Args, Clone, Debug)]
pub struct DemoArgs {
    /// Where the demo keeps its scene and image.
    #[arg(long, default_value = "rayfarm-demo", env = "RAYFARM_DEMO_DIR")]
    pub dir: PathBuf,
    /// Triangles in the built-in scene.
    #[arg(long, default_value_t = 300_000)]
    pub triangles: u64,
    /// Domains of the built-in scene.
    #[arg(long, default_value_t = 16)]
    pub domains: u32,
    /// Image width.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Image height.
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Samples per pixel.
    #[arg(long, default_value_t = 4)]
    pub spp: u32,
}

pub fn run(a: DemoArgs) -> anyhow::Result<()> {
    let scene = a.dir.join(format!("nbody-{}-{}", a.triangles, a.domains));
    // Re-prepare a scene that is missing, damaged or from an older build.
    let usable = Manifest::load(&scene).and_then(|m| m.check_domains(&scene, false));
    if usable.is_err() {
        eprintln!("preparing the built-in scene in {} ...", scene.display());
        super::prepare::run(PrepareArgs {
            input: None,
            out: scene.clone(),
            domains: a.domains,
            force: true,
            name: Some("nbody".into()),
            generate: Some(Generator::Nbody),
            triangles: a.triangles,
            seed: 1,
            max_memory: None,
            dims: None,
            dtype: "u8".into(),
            iso: None,
        })?;
    }
    let manifest = Manifest::load(&scene)?;
    let scene_bytes: u64 = manifest.domains.iter().map(|d| d.bytes).sum();
    super::render::run(RenderArgs {
        local: true,
        scene,
        out: a.dir.join("demo.png"),
        width: a.width,
        height: a.height,
        spp: a.spp,
        depth: 3,
        eye: None,
        look_at: None,
        fov: None,
        threads: None,
        // A quarter of the scene: the renderer has to page domains in and out, as on a cluster.
        cache_bytes: (scene_bytes / 4).max(1),
        wave_rays: 1 << 20,
        stats_json: Some(a.dir.join("demo-stats.json")),
        quiet: false,
    })
}
