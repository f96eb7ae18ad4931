//! Isosurfaces of raw volumes, end to end through the real CLI: `rayfarm prepare --iso`
//! with `--spacing`, smooth normals from the volume's gradient, colour maps by height or by a
//! scalar at the vertices; the same bits at any domain cut, cache, threads and placement, and
//! on clusters under every schedule.

use std::path::{Path, PathBuf};

use rayfarm_core::scene::Manifest;
use rayfarm_tests::identical::{SURFACE_RUNS, on_a_cluster, render_local, same_image_every_way};
use rayfarm_tests::{rayfarm_err, rayfarm_ok, s};

/// A 40x36x24 i16 volume at 1 x 1 x 1.5 spacing: two overlapping smooth blobs (their sum
/// falls off with distance), so the isosurface at 500 is one curved surface with a saddle.
fn blobs_volume(path: &Path) {
    let mut bytes = Vec::new();
    for k in 0..24i32 {
        for j in 0..36i32 {
            for i in 0..40i32 {
                let blob = |cx: f32, cy: f32, cz: f32, r: f32| {
                    let d2 = (i as f32 - cx).powi(2)
                        + (j as f32 - cy).powi(2)
                        + (1.5 * (k as f32 - cz)).powi(2);
                    1000.0 * (-d2 / (r * r)).exp()
                };
                let v = blob(15.0, 17.0, 11.0, 9.0) + blob(25.0, 19.0, 13.0, 7.0);
                bytes.extend_from_slice(&(v as i16).to_le_bytes());
            }
        }
    }
    std::fs::write(path, bytes).unwrap();
}

/// The blobs' volume (written once into `dir`) as an isosurface scene at 500 in `domains`
/// domains, with `extra` options of `prepare`.
fn prepare_blobs(dir: &Path, domains: &str, extra: &[&str]) -> PathBuf {
    let raw = dir.join("blobs.raw");
    if !raw.exists() {
        blobs_volume(&raw);
    }
    // Options name the scene; a path among them is flattened into the name.
    let out = dir.join(format!(
        "blobs-{domains}{}",
        extra.join("").replace('/', "_")
    ));
    let domains = ["--domains", domains];
    rayfarm_ok(&blobs_args(&raw, &out, &[&domains[..], extra].concat()));
    out
}

/// The error of preparing the blobs' volume (already written into `dir`) as an isosurface
/// with `extra` options that must be refused.
fn refused_blobs(dir: &Path, extra: &[&str]) -> String {
    rayfarm_err(&blobs_args(
        &dir.join("blobs.raw"),
        &dir.join("refused"),
        extra,
    ))
}

/// `prepare`'s arguments for the blobs' volume `raw` as the isosurface at 500 at `out`, with
/// `extra` options.
fn blobs_args<'a>(raw: &'a Path, out: &'a Path, extra: &[&'a str]) -> Vec<&'a str> {
    let mut args = vec![
        "prepare",
        s(raw),
        "--dims",
        "40,36,24",
        "--dtype",
        "i16",
        "--spacing",
        "1,1,1.5",
        "--iso",
        "500",
        "--out",
        s(out),
    ];
    args.extend_from_slice(extra);
    args
}

/// An isosurface shaded with the volume's gradient (the default for `--iso`): the same bits
/// at 1, 8 and 64 domains (a vertex cut across domains gets its normal from the whole
/// volume's gradient, the same in each), any cache, 1-2 threads, chained or speculative
/// (a copy sends the shading normal home); and not the flat-shaded image.
#[test]
fn smooth_isosurfaces_are_identical_at_1_8_and_64_domains_any_cache_and_threads() {
    let tmp = tempfile::tempdir().unwrap();
    let scenes: Vec<PathBuf> = ["1", "8", "64"]
        .iter()
        .map(|domains| {
            let scene = prepare_blobs(tmp.path(), domains, &[]);
            let m = Manifest::load(&scene).unwrap();
            assert_eq!(m.domains.len(), domains.parse::<usize>().unwrap());
            scene
        })
        .collect();
    let (smooth, _) = same_image_every_way(tmp.path(), &scenes, &SURFACE_RUNS, &["--depth", "2"]);
    // Flat normals and a colour map give other images (so the smooth ones were used).
    let render =
        |scene: &Path, name: &str| render_local(scene, &tmp.path().join(name), &["--depth", "2"]);
    let flat = render(
        &prepare_blobs(tmp.path(), "8", &["--normals", "flat"]),
        "flat.exr",
    );
    assert_ne!(flat, smooth, "smooth normals change the image");
    let mapped = prepare_blobs(tmp.path(), "8", &["--colour-map", "viridis"]);
    let m = Manifest::load(&mapped).unwrap();
    assert!(matches!(
        m.materials[0],
        rayfarm_core::scene::Material::Mapped { axis: 2, .. }
    ));
    assert_ne!(
        render(&mapped, "mapped.exr"),
        smooth,
        "the colour map shows"
    );
    // A colour map that does not exist is refused naming the presets.
    let err = refused_blobs(tmp.path(), &["--colour-map", "rainbow"]);
    assert!(err.contains("rainbow") && err.contains("viridis"), "{err}");
}

/// The smooth isosurface on a real cluster of 1, 2 and 4 workers: every schedule gives the
/// image of `render --local` to the bit, predictive included (copies send the shading normal).
#[test]
fn smooth_isosurfaces_on_a_cluster_match_the_local_image_under_every_schedule() {
    let root = tempfile::tempdir().unwrap();
    let scene = prepare_blobs(root.path(), "8", &["--colour-map", "bone"]);
    let name = scene.file_name().unwrap().to_str().unwrap().to_string();
    on_a_cluster(root.path(), &name);
}

/// An isosurface coloured by a scalar at its vertices through a 256-colour table of the map
/// (the volume's gradient magnitude, or a second volume's value): the same bits at 1, 8 and 64
/// domains, any cache, 1-2 threads, chained or speculative (a triangle's colour is its
/// material, stored in every domain that references it); not the plain surface's image, and
/// one per scalar. A second volume of the wrong size is refused naming it.
#[test]
fn isosurfaces_coloured_by_a_scalar_are_identical_at_1_8_and_64_domains() {
    let tmp = tempfile::tempdir().unwrap();
    // The second volume: a ramp along x and z, in the blobs' dimensions.
    let ramp = tmp.path().join("ramp.raw");
    let mut bytes = Vec::new();
    for k in 0..24i16 {
        for _ in 0..36 {
            for i in 0..40i16 {
                bytes.extend_from_slice(&(25 * i + 10 * k).to_le_bytes());
            }
        }
    }
    std::fs::write(&ramp, bytes).unwrap();
    let mut hashes = Vec::new();
    let by_gradient = ["--colour-map", "viridis", "--colour-by", "gradient"];
    let by_volume = [
        "--colour-map",
        "cool-warm",
        "--colour-by",
        "volume",
        "--colour-volume",
        s(&ramp),
    ];
    for look in [&by_gradient[..], &by_volume[..]] {
        let scenes: Vec<PathBuf> = ["1", "8", "64"]
            .iter()
            .map(|domains| prepare_blobs(tmp.path(), domains, look))
            .collect();
        let m = Manifest::load(&scenes[0]).unwrap();
        assert_eq!(m.materials.len(), 256, "{look:?}: a lookup table");
        let (hash, _) = same_image_every_way(tmp.path(), &scenes, &SURFACE_RUNS, &["--depth", "2"]);
        hashes.push(hash);
    }
    let plain = prepare_blobs(tmp.path(), "8", &[]);
    let plain = render_local(&plain, &tmp.path().join("plain.exr"), &["--depth", "2"]);
    assert_ne!(hashes[0], plain, "the gradient's colours show");
    assert_ne!(hashes[1], plain, "the second volume's colours show");
    assert_ne!(hashes[0], hashes[1]);
    // A second volume whose size does not match --dims and --dtype, named in the error; and
    // --colour-volume without --colour-by volume.
    let short = tmp.path().join("short.raw");
    std::fs::write(&short, [0u8; 100]).unwrap();
    let viridis = ["--colour-map", "viridis", "--colour-by", "volume"];
    let err = refused_blobs(
        tmp.path(),
        &[&viridis[..], &["--colour-volume", s(&short)]].concat(),
    );
    assert!(err.contains("short.raw"), "{err}");
    let err = refused_blobs(
        tmp.path(),
        &["--colour-map", "viridis", "--colour-volume", s(&ramp)],
    );
    assert!(err.contains("--colour-by volume"), "{err}");
}
