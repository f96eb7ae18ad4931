//! Volumes for direct volume rendering, end to end through the real CLI: `rayfarm prepare
//! --volume` cuts a raw volume (or the generator's density field) into bricks, refusing bad
//! input with errors that name the file; `--spacing` keeps a volume's proportions; the image
//! is the same bits at any bricking, cache, threads and placement, and on clusters under every
//! schedule. Isosurfaces of raw volumes are in `isosurface.rs`.

use std::path::{Path, PathBuf};

use rayfarm_core::scene::Manifest;
use rayfarm_tests::identical::{DVR_RUNS, on_a_cluster, same_image_every_way};
use rayfarm_tests::{rayfarm_err, rayfarm_ok, s, stats_field};

/// The generator's density field as a 48^3 volume cut into `bricks` bricks, looking as `look`
/// says (`prepare --volume` options), at `scene`.
fn prepare_density(scene: &Path, bricks: &str, look: &[&str]) {
    let mut prepare = vec![
        "prepare",
        "--generate",
        "nbody",
        "--volume",
        "--dims",
        "48,48,48",
        "--bricks",
        bricks,
        "--out",
        s(scene),
    ];
    prepare.extend_from_slice(look);
    rayfarm_ok(&prepare);
}

/// A 20x16x12 i16 volume: a ball of "bone" (1000) in "soft tissue" (0).
fn ball_volume(path: &Path) {
    let mut bytes = Vec::new();
    for k in 0..12i32 {
        for j in 0..16i32 {
            for i in 0..20i32 {
                let d2 = (i - 10).pow(2) + (j - 8).pow(2) + (2 * (k - 6)).pow(2);
                let v: i16 = if d2 < 36 { 1000 } else { (d2 % 7) as i16 };
                bytes.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
    std::fs::write(path, bytes).unwrap();
}

#[test]
fn a_raw_volume_becomes_bricks_with_its_spacing() {
    let tmp = tempfile::tempdir().unwrap();
    let raw = tmp.path().join("ball.raw");
    ball_volume(&raw);
    let out = tmp.path().join("ball");
    let o = rayfarm_ok(&[
        "prepare",
        s(&raw),
        "--volume",
        "--dims",
        "20,16,12",
        "--dtype",
        "i16",
        "--spacing",
        "0.5,0.5,1.0",
        "--bricks",
        "8",
        "--transfer",
        "ct-bone",
        "--out",
        s(&out),
    ]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("volume 20x16x12 in 8 bricks"), "{text}");
    let m = Manifest::load(&out).unwrap();
    m.check_domains(&out, true).unwrap();
    assert_eq!(m.domains.len(), 8);
    assert_eq!(m.bounds.max, [9.5, 7.5, 11.0]);
    let v = m.volume.unwrap();
    assert_eq!(v.spacing, [0.5, 0.5, 1.0]);
    assert_eq!(v.step, 0.25);
    assert_eq!(v.transfer.points[0].value, -1024.0, "the ct-bone preset");
    // Every brick's range holds the soft tissue; those touching the ball also hold bone.
    assert!(m.domains.iter().all(|d| d.values.unwrap()[0] == 0.0));
    assert!(m.domains.iter().any(|d| d.values.unwrap()[1] == 1000.0));

    // The same volume as an isosurface keeps its proportions with --spacing.
    let iso = tmp.path().join("iso");
    rayfarm_ok(&[
        "prepare",
        s(&raw),
        "--dims",
        "20,16,12",
        "--dtype",
        "i16",
        "--iso",
        "500",
        "--spacing",
        "0.5,0.5,1.0",
        "--domains",
        "2",
        "--out",
        s(&iso),
    ]);
    let m = Manifest::load(&iso).unwrap();
    let size: Vec<f32> = (0..3).map(|a| m.bounds.max[a] - m.bounds.min[a]).collect();
    // The ball is a sphere in space: 2*6 cells of 0.5 across in x, 2*3 cells of 1.0 in z.
    let ratio = size[2] / size[0];
    assert!((0.8..1.25).contains(&ratio), "z/x {ratio} ({size:?})");
}

#[test]
fn bad_volumes_and_transfer_functions_name_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("scene");
    let raw = tmp.path().join("ball.raw");
    ball_volume(&raw);
    let volume = |extra: &[&str]| {
        let mut args = vec![
            "prepare",
            s(&raw),
            "--volume",
            "--dims",
            "20,16,12",
            "--dtype",
            "i16",
            "--out",
            s(&out),
        ];
        args.extend_from_slice(extra);
        args.iter().map(|a| a.to_string()).collect::<Vec<_>>()
    };
    let err = |args: Vec<String>| rayfarm_err(&args.iter().map(String::as_str).collect::<Vec<_>>());

    // Size not matching dims x dtype.
    let mut a = volume(&[]);
    a[4] = "20,16,13".into();
    let e = err(a);
    assert!(
        e.contains("ball.raw") && e.contains("7680") && e.contains("8320"),
        "{e}"
    );
    let mut a = volume(&[]);
    a[6] = "f32".into();
    let e = err(a);
    assert!(
        e.contains("ball.raw") && e.contains("expected 15360 bytes"),
        "{e}"
    );

    // Non-finite values.
    let nan = tmp.path().join("nan.raw");
    let mut bytes: Vec<u8> = (0..2 * 3 * 4).flat_map(|_| 1.0f32.to_le_bytes()).collect();
    bytes[4 * 13..4 * 14].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(&nan, bytes).unwrap();
    let e = rayfarm_err(&[
        "prepare",
        s(&nan),
        "--volume",
        "--dims",
        "2,3,4",
        "--dtype",
        "f32",
        "--bricks",
        "1",
        "--out",
        s(&out),
    ]);
    assert!(
        e.contains("nan.raw") && e.contains("[1, 0, 2]") && e.contains("not finite"),
        "{e}"
    );

    // Transfer functions: not TOML, values not increasing, a missing file.
    let tf = tmp.path().join("tf.toml");
    std::fs::write(&tf, "[[point]]\nvalue = 1\ncolour = [1, 1").unwrap();
    let e = err(volume(&["--transfer", s(&tf)]));
    assert!(
        e.contains("tf.toml") && e.contains("bad transfer function"),
        "{e}"
    );
    std::fs::write(
        &tf,
        "[[point]]\nvalue = 5.0\ncolour = [0, 0, 0]\nopacity = 0\n\
         [[point]]\nvalue = 2.0\ncolour = [1, 1, 1]\nopacity = 1\n",
    )
    .unwrap();
    let e = err(volume(&["--transfer", s(&tf)]));
    assert!(
        e.contains("tf.toml") && e.contains("strictly increasing"),
        "{e}"
    );
    let e = err(volume(&["--transfer", "ct-bones"]));
    assert!(
        e.contains("ct-bones") && e.contains("ct-bone, ct-skin, density"),
        "{e}"
    );

    // Spacing and bricks that cannot make a scene.
    let e = err(volume(&["--spacing", "1,0,1"]));
    assert!(e.contains("ball.raw") && e.contains("spacing"), "{e}");
    let e = err(volume(&["--bricks", "5000"]));
    assert!(e.contains("ball.raw: 5000 bricks do not fit"), "{e}");
    assert!(!out.exists(), "a failed prepare leaves no scene");
    assert_eq!(
        std::fs::read_dir(tmp.path()).unwrap().count(),
        3,
        "only the inputs remain"
    );
}

#[test]
fn the_generator_emits_its_density_field_as_a_volume() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("nbody");
    rayfarm_ok(&[
        "prepare",
        "--generate",
        "nbody",
        "--volume",
        "--dims",
        "40,40,40",
        "--bricks",
        "4",
        "--out",
        s(&out),
    ]);
    let m = Manifest::load(&out).unwrap();
    m.check_domains(&out, true).unwrap();
    assert_eq!(m.domains.len(), 4);
    assert_eq!(m.volume.as_ref().unwrap().dims, [40; 3]);
    // In units of the mesh scene's iso value: empty space near 0, the blobs above 1.
    let top = m
        .domains
        .iter()
        .map(|d| d.values.unwrap()[1])
        .fold(0.0, f32::max);
    assert!(top > 1.0, "{top}");
    let e = rayfarm_err(&[
        "prepare",
        "--generate",
        "nbody",
        "--volume",
        "--dims",
        "40,40,41",
        "--out",
        s(&out),
        "--force",
    ]);
    assert!(e.contains("cube"), "{e}");
}

/// Direct volume rendering: the image is the same bits however the volume is cut into bricks,
/// whatever the cache budget (bricks paged in and out), however many threads trace it, and
/// traced one brick after another or speculatively (every brick's segments composited by the
/// ray's group); unlit, shaded by the gradient and the scene's lights, and with shadow rays
/// towards the lights.
#[test]
fn dvr_images_are_identical_at_1_8_and_64_bricks_any_cache_and_threads() {
    let tmp = tempfile::tempdir().unwrap();
    let mut per_look = Vec::new();
    for look in [&[][..], &["--shading"], &["--shadows"]] {
        let (hash, shadow_rays) = identical_at_any_bricking(tmp.path(), look);
        assert_eq!(shadow_rays > 0, look == ["--shadows"], "{look:?}");
        per_look.push(hash);
    }
    // Shading and shadows change the image.
    assert_ne!(per_look[0], per_look[1]);
    assert_ne!(per_look[1], per_look[2]);
}

/// Volumes and surfaces in one scene (the density field's isosurface inside it, `--iso`):
/// compositing stops at the nearest surface a ray meets and the surface is shaded behind the
/// volume in front of it, the same bits at 1, 8 and 64 bricks (a surface crossing bricks is
/// referenced by each), any cache, 1-2 threads, chained or speculative (a brick's copy sends
/// its hit with its segments); unlit and with shadow rays, which surfaces block.
#[test]
fn volumes_with_surfaces_are_identical_at_1_8_and_64_bricks_any_cache_and_threads() {
    let tmp = tempfile::tempdir().unwrap();
    let (volume_only, _) = identical_at_any_bricking(tmp.path(), &["--shadows"]);
    let (unlit, _) = identical_at_any_bricking(tmp.path(), &["--iso", "1.5"]);
    let (shadowed, shadow_rays) =
        identical_at_any_bricking(tmp.path(), &["--iso", "1.5", "--shadows"]);
    assert!(shadow_rays > 0);
    assert_ne!(unlit, shadowed);
    assert_ne!(volume_only, shadowed, "the surfaces show");
    let m = Manifest::load(&tmp.path().join("nbody-8---iso 1.5 --shadows")).unwrap();
    assert!(m.triangles > 0);
    assert!(m.domains.iter().any(|d| d.surfaces.is_some()));
}

/// Renders the generator's density volume prepared with `look` at 1, 8 and 64 bricks under
/// several caches, threads and placements; asserts every image and shadow-ray count is the
/// same and returns the image's hash and the shadow rays.
fn identical_at_any_bricking(dir: &Path, look: &[&str]) -> (String, u64) {
    let name = look.join(" ");
    let scenes: Vec<PathBuf> = ["1", "8", "64"]
        .iter()
        .map(|bricks| {
            let scene = dir.join(format!("nbody-{bricks}-{name}"));
            prepare_density(&scene, bricks, look);
            scene
        })
        .collect();
    let (hash, stats) = same_image_every_way(dir, &scenes, &DVR_RUNS, &[]);
    let shadow_rays: Vec<u64> = stats
        .iter()
        .map(|f| stats_field(f, "/rays/shadow_rays").as_u64().unwrap())
        .collect();
    // As many shadow rays whatever the bricking and placement.
    assert!(
        shadow_rays.iter().all(|&n| n == shadow_rays[0]),
        "{name}: {shadow_rays:?}"
    );
    (hash, shadow_rays[0])
}

/// On a real cluster of 1, 2 and 4 workers, every schedule gives the image of `render --local`
/// to the bit, predictive included (speculative copies send their bricks' segments back).
#[test]
fn dvr_on_a_cluster_matches_the_local_image_under_every_schedule() {
    dvr_on_a_cluster(&[]);
}

/// The same with gradient shading and shadow rays: shadow rays are born where a ray's
/// segment is folded in (on the worker tracing it, or speculating, at its group) and march
/// the bricks like any volume ray.
#[test]
fn shadowed_dvr_on_a_cluster_matches_the_local_image_under_every_schedule() {
    dvr_on_a_cluster(&["--shadows"]);
}

/// The same with surfaces in the volume: a brick's surfaces travel with its voxels, and a
/// speculative copy sends its hit with its segments.
#[test]
fn volumes_with_surfaces_on_a_cluster_match_the_local_image_under_every_schedule() {
    dvr_on_a_cluster(&["--shadows", "--iso", "1.5"]);
}

fn dvr_on_a_cluster(look: &[&str]) {
    let root = tempfile::tempdir().unwrap();
    prepare_density(&root.path().join("vol"), "8", look);
    on_a_cluster(root.path(), "vol");
}
