//! `rayfarm render --local`.

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;
use clap::builder::BoolishValueParser;
use indicatif::{ProgressBar, ProgressStyle};
use rayfarm_core::render::local::{FrameSpec, LocalOptions, Progress, render_local};
use rayfarm_core::scene::MANIFEST_FILE;
use rayfarm_core::scene::Manifest;
use rayfarm_core::schedule::speculation_depth::Depth;

use crate::table::stats_table;
use crate::units;
use crate::view::{CameraArgs, FrameArgs};

/// Options of `rayfarm render`.
#[derive(Args, Clone, Debug)]
pub struct RenderArgs {
    /// Render in this process (required: to render on a cluster, use `rayfarm submit`).
    #[arg(long)]
    pub local: bool,
    /// Scene directory (holding scene.toml).
    #[arg(long, env = "RAYFARM_SCENE")]
    pub scene: PathBuf,
    /// Output image: .png (8-bit sRGB) or .exr (linear float).
    #[arg(long, short, env = "RAYFARM_OUTPUT", default_value = "render.png")]
    pub out: PathBuf,
    #[command(flatten)]
    pub frame: FrameArgs,
    #[command(flatten)]
    pub camera: CameraArgs,
    /// Tracing threads (default: all cores).
    #[arg(long, env = "RAYFARM_THREADS")]
    pub threads: Option<usize>,
    /// Domain cache budget, e.g. 512MiB.
    #[arg(long, env = "RAYFARM_CACHE_BYTES", value_parser = units::bytes, default_value = "4GiB")]
    pub cache_bytes: u64,
    /// Camera rays issued whenever fewer rays than this are queued (bounds memory).
    #[arg(long, env = "RAYFARM_WAVE_RAYS", default_value_t = 1 << 20)]
    pub wave_rays: usize,
    /// Queue each new ray in every domain along it at once and trace the oldest generation
    /// first (predictive scheduling): a domain is loaded about once per bounce instead of once
    /// per pass of rays through it. Same image; more ray segments. Pays when loads dominate.
    #[arg(long, env = "RAYFARM_SPECULATE", value_parser = BoolishValueParser::new())]
    pub speculate: bool,
    /// With --speculate, how many domains ahead a new ray is copied: `full` (every domain
    /// along it), `ahead:N` (N at a time), `predicted` or `predicted:P` (as many as make the
    /// ray end among them with probability P, 0.9 by default, from the termination rates of
    /// the rays concluded before; Park et al.). Same image whatever the depth.
    #[arg(long, env = "RAYFARM_SPECULATION", value_parser = Depth::parse, default_value = "full")]
    pub speculation: Depth,
    /// Also write the statistics as JSON here.
    #[arg(long, env = "RAYFARM_STATS_JSON")]
    pub stats_json: Option<PathBuf>,
    /// Do not print the statistics table.
    #[arg(long, env = "RAYFARM_QUIET", value_parser = BoolishValueParser::new())]
    pub quiet: bool,
}

pub fn run(a: RenderArgs) -> anyhow::Result<()> {
    if !a.local {
        bail!("pass --local (to render on a cluster, use `rayfarm submit` or `rayfarm demo`)");
    }
    // A frame is not rendered only to fail at the end on a name that cannot be written.
    super::fetch::image_format(&a.out)?;
    super::fetch::check_writable(&a.out)?;
    if let Some(p) = &a.stats_json {
        super::fetch::check_writable(p)?;
    }
    if !a.scene.is_dir() {
        bail!(
            "{}: no such scene directory (a prepared scene is a directory holding \
             {MANIFEST_FILE}; make one with `rayfarm prepare`)",
            a.scene.display()
        );
    }
    if !a.scene.join(MANIFEST_FILE).exists() {
        bail!(
            "{} holds no {MANIFEST_FILE}, so it is not a prepared scene: make one with `rayfarm \
             prepare MESH --out {}` (or `--generate nbody`)",
            a.scene.display(),
            a.scene.display()
        );
    }
    let manifest = Manifest::load(&a.scene)?;
    let camera = a
        .camera
        .over(&manifest.camera)
        .map_err(anyhow::Error::msg)?;
    let frame = FrameSpec {
        width: a.frame.width,
        height: a.frame.height,
        spp: a.frame.spp,
        max_depth: a.frame.depth,
        camera,
    };
    let options = LocalOptions {
        threads: a
            .threads
            .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get())),
        cache_bytes: a.cache_bytes,
        wave_rays: a.wave_rays,
        speculate: a.speculate,
        depth: a.speculation,
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
