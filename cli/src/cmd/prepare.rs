//! `rayfarm prepare`: a mesh file, a raw volume, or the built-in generator into a scene.

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};
use rayfarm_core::colour_map::ColourMap;
use rayfarm_core::prepare::brick_scene::MAX_BRICKS;
use rayfarm_core::prepare::brick_scene::VolumeLook;
use rayfarm_core::prepare::generate::{
    NbodyLook, NbodyOptions, prepare_nbody_volume, prepare_nbody_with,
};
use rayfarm_core::prepare::mesh_scene::MAX_DOMAINS;
use rayfarm_core::prepare::prepare_mesh;
use rayfarm_core::prepare::volume_scene::{ColourBy, IsoLook, prepare_raw_bricks, prepare_volume};
use rayfarm_core::scene::Manifest;
use rayfarm_core::transfer::TransferFunction;

use crate::units;

/// Built-in scene generators.
#[derive(ValueEnum, Clone, Copy, Debug)]
pub enum Generator {
    /// Isosurface of a clustered particle-density field, with a ground plane and a mirror.
    Nbody,
}

/// Options of `rayfarm prepare`.
#[derive(Args, Clone, Debug)]
pub struct PrepareArgs {
    /// Mesh (.ply, .obj, .stl, optionally .gz) or raw volume (with --dims); omit with --generate.
    pub input: Option<PathBuf>,
    /// Scene directory to create.
    #[arg(long, short)]
    pub out: PathBuf,
    /// Number of domains to cut the scene into, 1 to 65536.
    #[arg(long, default_value_t = 8,
          value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_DOMAINS)))]
    pub domains: u32,
    /// Replace `--out` if it exists.
    #[arg(long)]
    pub force: bool,
    /// Do nothing if `--out` already holds a scene whose manifest and domain files check out
    /// (for one-shot jobs that may run again, e.g. a docker-compose service).
    #[arg(long, conflicts_with = "force")]
    pub if_missing: bool,
    /// Scene name (default: the input's file stem or the generator's name).
    #[arg(long)]
    pub name: Option<String>,
    /// Generate a built-in scene instead of reading INPUT.
    #[arg(long, value_enum)]
    pub generate: Option<Generator>,
    /// Generator: approximate triangle count.
    #[arg(long, default_value_t = 200_000)]
    pub triangles: u64,
    /// Generator: random seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Generator: keep peak memory under this (adds domains if needed), e.g. 256MiB.
    #[arg(long, value_parser = units::bytes)]
    pub max_memory: Option<u64>,
    /// Volume: dimensions X,Y,Z of the raw file.
    #[arg(long, value_parser = units::triple::<u32>)]
    pub dims: Option<[u32; 3]>,
    /// Volume: voxel type.
    #[arg(long, default_value = "u8")]
    pub dtype: String,
    /// Volume: iso value of the surface; with --volume, that isosurface as surfaces inside
    /// the volume, rendered with it (compositing stops where a ray meets the surface).
    #[arg(long)]
    pub iso: Option<f32>,
    /// Volume: distance between voxel centres SX,SY,SZ (e.g. a CT's 0.957,0.957,1.5 mm).
    #[arg(long, value_parser = units::triple::<f32>, default_value = "1,1,1")]
    pub spacing: [f32; 3],
    /// Keep the volume for direct volume rendering, cut into bricks, instead of extracting
    /// an isosurface; with --generate nbody, the generator's density field (--dims N,N,N,
    /// default 128 per axis).
    #[arg(long)]
    pub volume: bool,
    /// --volume: bricks to cut the volume into (default: --domains).
    #[arg(long, requires = "volume",
          value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_BRICKS)))]
    pub bricks: Option<u32>,
    /// --volume: transfer function, a preset (ct-bone, ct-skin, density) or a TOML file of
    /// [[point]] value, colour, opacity.
    #[arg(long, requires = "volume", default_value = "density")]
    pub transfer: String,
    /// --volume: distance between samples along a ray (default: half the smallest spacing).
    #[arg(long, requires = "volume")]
    pub step: Option<f32>,
    /// --volume: shade samples by the volume's gradient and the scene's lights.
    #[arg(long, requires = "volume")]
    pub shading: bool,
    /// --volume: shading with shadows, by shadow rays from each composited stretch of a ray
    /// towards the lights (implies --shading).
    #[arg(long, requires = "volume")]
    pub shadows: bool,
    /// Isosurfaces: shading normals, `smooth` (the field's gradient at the vertices; the
    /// default for a raw volume's --iso, and always for --volume --iso) or `flat` (the facets';
    /// the generator's default).
    #[arg(long, value_enum)]
    pub normals: Option<Normals>,
    /// Isosurfaces (--iso without --volume, or --generate nbody): colour the surface by height
    /// with this colour map (bone, terrain, viridis, cool-warm) instead of a plain colour (the
    /// generator's: colours by region of space).
    #[arg(long)]
    pub colour_map: Option<String>,
    /// --colour-map: the axis heights run along (default z for a volume, y for the generator).
    #[arg(long, value_enum, requires = "colour_map")]
    pub colour_axis: Option<Axis>,
    /// --colour-map of a raw volume's --iso: what picks the colour, `height` (along
    /// --colour-axis; the default), `gradient` (the volume's gradient magnitude at the
    /// vertices: how sharp the boundary is) or `volume` (the value at the vertices of a second
    /// raw volume, --colour-volume, of the same --dims and --dtype); the last two colour each
    /// triangle from a 256-colour table of the map.
    #[arg(long, value_enum, requires = "colour_map")]
    pub colour_by: Option<ColourSource>,
    /// --colour-by volume: the second raw volume.
    #[arg(long)]
    pub colour_volume: Option<PathBuf>,
}

/// What picks an isosurface's colour from its colour map.
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq)]
pub enum ColourSource {
    /// The height of the point shaded.
    Height,
    /// The volume's gradient magnitude at the vertices.
    Gradient,
    /// A second volume's value at the vertices (--colour-volume).
    Volume,
}

/// Shading normals of an isosurface.
#[derive(ValueEnum, Clone, Copy, Debug, PartialEq)]
pub enum Normals {
    /// The volume's gradient at the vertices, interpolated across each triangle.
    Smooth,
    /// Each triangle's own normal.
    Flat,
}

/// A coordinate axis.
#[derive(ValueEnum, Clone, Copy, Debug)]
pub enum Axis {
    /// x.
    X,
    /// y.
    Y,
    /// z.
    Z,
}

pub fn run(a: PrepareArgs) -> anyhow::Result<()> {
    if a.if_missing
        && let Ok(m) = rayfarm_core::scene::Manifest::load(&a.out)
        && m.check_domains(&a.out, true).is_ok()
    {
        println!("{}: already prepared, left as it is", a.out.display());
        return Ok(());
    }
    let transfer = || {
        let transfer = TransferFunction::load(&a.transfer).map_err(anyhow::Error::msg)?;
        anyhow::Ok(VolumeLook {
            transfer,
            shading: a.shading || a.shadows,
            shadows: a.shadows,
            iso_surface: a.iso,
        })
    };
    let colour_map = a
        .colour_map
        .as_deref()
        .map(ColourMap::parse)
        .transpose()
        .map_err(anyhow::Error::msg)?;
    if a.volume && (colour_map.is_some() || a.normals.is_some()) {
        bail!(
            "--colour-map and --normals are for isosurfaces without --volume (a volume's \
             surfaces are always smooth)"
        );
    }
    if a.colour_volume.is_some() != (a.colour_by == Some(ColourSource::Volume)) {
        bail!("--colour-volume FILE goes with --colour-by volume, and only with it");
    }
    let bricks = a.bricks.unwrap_or(a.domains);
    let nbody = |domains| NbodyOptions {
        name: a.name.clone().unwrap_or_else(|| "nbody".into()),
        triangles: a.triangles,
        seed: a.seed,
        domains,
        max_memory: a.max_memory,
        force: a.force,
    };
    let manifest = match (&a.generate, &a.input, &a.dims) {
        (Some(Generator::Nbody), None, dims) if a.volume => {
            let n = match dims {
                None => 128,
                Some([x, y, z]) if x == y && y == z => *x,
                Some(d) => bail!("the generated volume is a cube: give --dims N,N,N, not {d:?}"),
            };
            prepare_nbody_volume(&a.out, &nbody(bricks), n, transfer()?)?
        }
        (Some(Generator::Nbody), None, None) => {
            if !matches!(a.colour_axis, None | Some(Axis::Y))
                || !matches!(a.colour_by, None | Some(ColourSource::Height))
            {
                bail!("the generator colours by height along y, its up");
            }
            let look = NbodyLook {
                smooth: a.normals == Some(Normals::Smooth),
                colour_map,
            };
            prepare_nbody_with(&a.out, &nbody(a.domains), look)?
        }
        (Some(_), Some(_), _) | (Some(_), _, Some(_)) => {
            bail!("--generate makes a scene without an INPUT or --dims (but for --volume)")
        }
        (None, Some(input), Some(dims)) if a.volume => {
            let dtype = a.dtype.parse().map_err(anyhow::Error::msg)?;
            prepare_raw_bricks(
                input,
                *dims,
                dtype,
                a.spacing,
                transfer()?,
                a.step,
                &name_of(&a),
                &a.out,
                bricks,
                a.force,
            )?
        }
        (None, Some(input), Some(dims)) => {
            let iso = a.iso.context("a volume needs --iso")?;
            let dtype = a.dtype.parse().map_err(anyhow::Error::msg)?;
            prepare_volume(
                input,
                *dims,
                dtype,
                a.spacing,
                iso,
                IsoLook {
                    smooth: a.normals != Some(Normals::Flat),
                    colour_map,
                    colour_by: colour_by(&a)?,
                },
                &name_of(&a),
                &a.out,
                a.domains,
                a.force,
            )?
        }
        (None, Some(input), None) if a.volume => {
            bail!(
                "{}: a raw volume needs --dims X,Y,Z and --dtype",
                input.display()
            )
        }
        (None, Some(input), None) => {
            let mesh = rayfarm_core::mesh::read_mesh(input)?;
            if mesh.triangles.is_empty() {
                bail!(
                    "{}: the mesh has no triangles (an empty file, or only points and lines)",
                    input.display()
                );
            }
            prepare_mesh(&mesh, &name_of(&a), &a.out, a.domains, a.force)?
        }
        (None, None, _) => bail!("give an INPUT mesh or volume, or --generate nbody"),
    };
    print_summary(&a.out, &manifest);
    Ok(())
}

fn name_of(a: &PrepareArgs) -> String {
    a.name.clone().unwrap_or_else(|| {
        a.input
            .as_ref()
            .and_then(|p| p.file_name())
            .map(|s| {
                s.to_string_lossy()
                    .split('.')
                    .next()
                    .unwrap_or("scene")
                    .to_string()
            })
            .unwrap_or_else(|| "scene".into())
    })
}

fn print_summary(out: &std::path::Path, m: &Manifest) {
    if let Some(v) = &m.volume {
        let bytes: u64 = m.domains.iter().map(|d| d.bytes).sum();
        println!(
            "{}: volume {}x{}x{} in {} brick{}, {} on disk",
            out.display(),
            v.dims[0],
            v.dims[1],
            v.dims[2],
            m.domains.len(),
            if m.domains.len() == 1 { "" } else { "s" },
            units::human(bytes)
        );
        let peak = rayfarm_core::render::stats::peak_rss_bytes();
        println!("peak RSS: {} ({peak} bytes)", units::human(peak));
        return;
    }
    let bytes: u64 = m.domains.iter().map(|d| d.bytes).sum();
    let refs: u64 = m.domains.iter().map(|d| d.triangles).sum();
    let largest = m.domains.iter().map(|d| d.bytes).max().unwrap_or(0);
    let domains = m.domains.len();
    println!(
        "{}: {} triangles ({} references) in {domains} domain{}, {} on disk (largest domain {})",
        out.display(),
        m.triangles,
        refs,
        if domains == 1 { "" } else { "s" },
        units::human(bytes),
        units::human(largest)
    );
    // The kernel's own high-water mark (what `/usr/bin/time -v` reports), for scripts and tests.
    let peak = rayfarm_core::render::stats::peak_rss_bytes();
    println!("peak RSS: {} ({peak} bytes)", units::human(peak));
}

/// What colours a raw volume's isosurface, from `--colour-by`, `--colour-axis` and
/// `--colour-volume`.
fn colour_by(a: &PrepareArgs) -> anyhow::Result<ColourBy> {
    let by_height = matches!(a.colour_by, None | Some(ColourSource::Height));
    if !by_height && a.colour_axis.is_some() {
        bail!("--colour-axis is for --colour-by height");
    }
    Ok(match a.colour_by {
        None | Some(ColourSource::Height) => ColourBy::Height {
            axis: match a.colour_axis {
                Some(Axis::X) => 0,
                Some(Axis::Y) => 1,
                Some(Axis::Z) | None => 2,
            },
        },
        Some(ColourSource::Gradient) => ColourBy::Gradient,
        Some(ColourSource::Volume) => ColourBy::Volume(
            a.colour_volume
                .clone()
                .context("--colour-by volume needs --colour-volume FILE")?,
        ),
    })
}
