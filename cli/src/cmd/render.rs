//! `rayfarm render --local`.

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use rayfarm_core::render::local::{FrameSpec, LocalOptions, Progress, render_local};
use rayfarm_core::scene::{Camera, Manifest};

use crate::table::stats_table;
use crate::units;

/// Options of `rayfarm render`.
#[derive(Args, Clone, Debug)]
pub struct RenderArgs {
    /// Render in this process (the only mode until the cluster is up).
    #[arg(long)]
    pub local: bool,
    /// Scene directory (holding scene.toml).
    #[arg(long, env = "RAYFARM_SCENE")]
    pub scene: PathBuf,
    /// Output image: .png (8-bit sRGB) or .exr (linear float).
    #[arg(long, short, default_value = "render.png")]
    pub out: PathBuf,
    /// Image width.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Image height.
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Samples per pixel.
    #[arg(long, default_value_t = 4)]
    pub spp: u32,
    /// Maximum bounces.
    #[arg(long, default_value_t = 3)]
    pub depth: u32,
    /// Camera position X,Y,Z (default: the scene's camera).
    #[arg(long, value_parser = units::triple::<f32>)]
    pub eye: Option<[f32; 3]>,
    /// Point the camera looks at, X,Y,Z.
    #[arg(long, value_parser = units::triple::<f32>)]
    pub look_at: Option<[f32; 3]>,
    /// Vertical field of view in degrees.
    #[arg(long)]
    pub fov: Option<f32>,
    /// Tracing threads (default: all cores).
    #[arg(long, env = "RAYFARM_THREADS")]
    pub threads: Option<usize>,
    /// Domain cache budget, e.g. 512MiB.
    #[arg(long, env = "RAYFARM_CACHE_BYTES", value_parser = units::bytes, default_value = "4GiB")]
    pub cache_bytes: u64,
    /// Camera rays issued whenever fewer rays than this are queued (bounds memory).
    #[arg(long, default_value_t = 1 << 20)]
    pub wave_rays: usize,
    /// Queue each new ray in every domain along it at once and trace the oldest generation
    /// first (predictive scheduling): a domain is loaded about once per bounce instead of once
    /// per pass of rays through it. Same image; more ray segments. Pays when loads dominate.
    #[arg(long)]
    pub speculate: bool,
    /// Also write the statistics as JSON here.
    #[arg(long)]
    pub stats_json: Option<PathBuf>,
    /// Do not print the statistics table.
    #[arg(long)]
    pub quiet: bool,
}

/// The scene's camera with whatever the command line overrides.
fn camera_override(scene: &Camera, a: &RenderArgs) -> Option<Camera> {
    if a.eye.is_none() && a.look_at.is_none() && a.fov.is_none() {
        return None;
    }
    Some(Camera {
        eye: a.eye.unwrap_or(scene.eye),
        look_at: a.look_at.unwrap_or(scene.look_at),
        up: scene.up,
        fov_y_degrees: a.fov.unwrap_or(scene.fov_y_degrees),
    })
}

pub fn run(a: RenderArgs) -> anyhow::Result<()> {
    if !a.local {
        bail!("pass --local (to render on a cluster, use `rayfarm submit` or `rayfarm demo`)");
    }
    let manifest = Manifest::load(&a.scene)?;
    let frame = FrameSpec {
        width: a.width,
        height: a.height,
        spp: a.spp,
        max_depth: a.depth,
        camera: camera_override(&manifest.camera, &a),
    };
    let options = LocalOptions {
        threads: a
            .threads
            .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get())),
        cache_bytes: a.cache_bytes,
        wave_rays: a.wave_rays,
        speculate: a.speculate,
        // Next to the output: the temporary directory may be memory (tmpfs).
        film_dir: Some(match a.out.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        }),
    };
    let bar = if a.quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(0)
    };
    bar.set_style(
        ProgressStyle::with_template("{spinner} [{bar:30}] {pos}/{len} tiles  {msg}  eta {eta}")
            .map_err(anyhow::Error::msg)?
            .progress_chars("=> "),
    );
    let mut on_progress = |p: &Progress| {
        bar.set_length(p.tiles_total as u64);
        bar.set_position(p.tiles_done as u64);
        bar.set_message(format!(
            "{:.2} Mrays/s, {} loads",
            p.segments as f64 / p.elapsed.max(1e-9) / 1e6,
            p.loads
        ));
    };
    let result = render_local(&a.scene, &manifest, &frame, &options, &mut on_progress);
    bar.finish_and_clear();
    let (film, stats) = result?;
    film.save(&a.out)?;
    if let Some(p) = &a.stats_json {
        std::fs::write(p, serde_json::to_string_pretty(&stats)?)
            .with_context(|| p.display().to_string())?;
    }
    if !a.quiet {
        println!("{}", stats_table(&stats));
        println!("wrote {}", a.out.display());
    }
    Ok(())
}
