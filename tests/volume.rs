//! Volumes for direct volume rendering, end to end through the real CLI: `rayfarm prepare
//! --volume` cuts a raw volume (or the generator's density field) into bricks, refusing bad
//! input with errors that name the file; `--spacing` keeps a volume's proportions.

use rayfarm_core::scene::Manifest;
use rayfarm_tests::{file_hash, rayfarm_err, rayfarm_ok, s, stats_field};

/// A 20x16x12 i16 volume: a ball of "bone" (1000) in "soft tissue" (0).
fn ball_volume(path: &std::path::Path) {
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
fn identical_at_any_bricking(dir: &std::path::Path, look: &[&str]) -> (String, u64) {
    let mut hashes = Vec::new();
    let mut shadow_rays = Vec::new();
    let name = look.join(" ");
    for bricks in ["1", "8", "64"] {
        let scene = dir.join(format!("nbody-{bricks}-{name}"));
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
            s(&scene),
        ];
        prepare.extend_from_slice(look);
        rayfarm_ok(&prepare);
        let bytes: u64 = Manifest::load(&scene)
            .unwrap()
            .domains
            .iter()
            .map(|d| d.bytes)
            .sum();
        let small = (bytes / 6).max(1).to_string();
        for (cache, threads, placement) in [
            ("4GiB", "1", "chained"),
            (small.as_str(), "2", "chained"),
            ("4GiB", "2", "chained"),
            ("4GiB", "1", "speculative"),
            (small.as_str(), "2", "speculative"),
        ] {
            let img = dir.join(format!("{bricks}-{threads}-{}.exr", hashes.len()));
            let stats = dir.join("stats.json");
            let mut args = vec![
                "render",
                "--local",
                "--scene",
                s(&scene),
                "--width",
                "96",
                "--height",
                "72",
                "--spp",
                "2",
                "--threads",
                threads,
                "--cache-bytes",
                cache,
                "-o",
                s(&img),
                "--stats-json",
                s(&stats),
                "--quiet",
            ];
            if placement == "speculative" {
                args.push("--speculate");
            }
            rayfarm_ok(&args);
            hashes.push((
                format!("{name}: {bricks} bricks, cache {cache}, {threads} threads, {placement}"),
                file_hash(&img),
            ));
            shadow_rays.push(stats_field(&stats, "/rays/shadow_rays").as_u64().unwrap());
        }
    }
    for (what, h) in &hashes {
        assert_eq!(h, &hashes[0].1, "{what} differs from {}", hashes[0].0);
    }
    // As many shadow rays whatever the bricking and placement.
    assert!(
        shadow_rays.iter().all(|&n| n == shadow_rays[0]),
        "{name}: {shadow_rays:?}"
    );
    (hashes[0].1.clone(), shadow_rays[0])
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
    let scene = root.path().join("vol");
    let mut prepare = vec![
        "prepare",
        "--generate",
        "nbody",
        "--volume",
        "--dims",
        "48,48,48",
        "--bricks",
        "8",
        "--out",
        s(&scene),
    ];
    prepare.extend_from_slice(look);
    rayfarm_ok(&prepare);
    on_a_cluster(root.path(), "vol");
}

/// Renders the scene `name` in `root` on 1, 2 and 4 workers with two-domain caches under
/// every schedule; every image must be `render --local`'s.
fn on_a_cluster(root: &std::path::Path, name: &str) {
    use rayfarm_tests::{Cluster, WorkerOpts, domain_bytes, hash_of, local_hash, submit_wait};
    let scene = root.join(name);
    let frame = ["--width", "96", "--height", "72", "--spp", "2"];
    let expected = local_hash(&scene, &frame);
    let (_, largest) = domain_bytes(&scene);
    for n in [1, 2, 4] {
        // Two-brick caches: bricks page in and out.
        let cluster = Cluster::start(root, Some(name), &vec![WorkerOpts::cache(2 * largest); n]);
        cluster.wait_for_workers(n, rayfarm_tests::START_TIMEOUT);
        for schedule in ["image-plane", "domain", "dynamic", "hybrid", "predictive"] {
            let mut f = frame.to_vec();
            f.extend(["--schedule", schedule, "--cold-cache"]);
            let stats = submit_wait(&cluster, &f, &format!("{schedule}-{n}"));
            assert_eq!(hash_of(&stats), expected, "{schedule} with {n} workers");
        }
    }
}

/// A 40x36x24 i16 volume at 1 x 1 x 1.5 spacing: two overlapping smooth blobs (their sum
/// falls off with distance), so the isosurface at 500 is one curved surface with a saddle.
fn blobs_volume(path: &std::path::Path) {
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

fn prepare_blobs(dir: &std::path::Path, domains: &str, extra: &[&str]) -> std::path::PathBuf {
    let raw = dir.join("blobs.raw");
    if !raw.exists() {
        blobs_volume(&raw);
    }
    let out = dir.join(format!("blobs-{domains}{}", extra.join("")));
    let mut args = vec![
        "prepare",
        s(&raw),
        "--dims",
        "40,36,24",
        "--dtype",
        "i16",
        "--spacing",
        "1,1,1.5",
        "--iso",
        "500",
        "--domains",
        domains,
        "--out",
        s(&out),
    ];
    args.extend_from_slice(extra);
    rayfarm_ok(&args);
    out
}

/// An isosurface shaded with the volume's gradient (the default for `--iso`): the same bits
/// at 1, 8 and 64 domains (a vertex cut across domains gets its normal from the whole
/// volume's gradient, the same in each), any cache, 1-2 threads, chained or speculative
/// (a copy sends the shading normal home); and not the flat-shaded image.
#[test]
fn smooth_isosurfaces_are_identical_at_1_8_and_64_domains_any_cache_and_threads() {
    let tmp = tempfile::tempdir().unwrap();
    let mut hashes = Vec::new();
    for domains in ["1", "8", "64"] {
        let scene = prepare_blobs(tmp.path(), domains, &[]);
        let m = Manifest::load(&scene).unwrap();
        assert_eq!(m.domains.len(), domains.parse::<usize>().unwrap());
        let bytes: u64 = m.domains.iter().map(|d| d.bytes).sum();
        let small = (bytes / 6).max(1).to_string();
        for (cache, threads, speculate) in [
            ("4GiB", "1", false),
            (small.as_str(), "2", false),
            ("4GiB", "1", true),
            (small.as_str(), "2", true),
        ] {
            let img = tmp.path().join(format!("{domains}-{}.exr", hashes.len()));
            let mut args = vec![
                "render",
                "--local",
                "--scene",
                s(&scene),
                "--width",
                "96",
                "--height",
                "72",
                "--spp",
                "2",
                "--depth",
                "2",
                "--threads",
                threads,
                "--cache-bytes",
                cache,
                "-o",
                s(&img),
                "--quiet",
            ];
            if speculate {
                args.push("--speculate");
            }
            rayfarm_ok(&args);
            hashes.push((
                format!(
                    "{domains} domains, cache {cache}, {threads} threads, speculate {speculate}"
                ),
                file_hash(&img),
            ));
        }
    }
    for (what, h) in &hashes {
        assert_eq!(h, &hashes[0].1, "{what} differs from {}", hashes[0].0);
    }
    // Flat normals and a colour map give other images (so the smooth ones were used).
    let render = |scene: &std::path::Path, name: &str| {
        let img = tmp.path().join(name);
        rayfarm_ok(&[
            "render",
            "--local",
            "--scene",
            s(scene),
            "--width",
            "96",
            "--height",
            "72",
            "--spp",
            "2",
            "--depth",
            "2",
            "-o",
            s(&img),
            "--quiet",
        ]);
        file_hash(&img)
    };
    let flat = render(
        &prepare_blobs(tmp.path(), "8", &["--normals", "flat"]),
        "flat.exr",
    );
    assert_ne!(flat, hashes[0].1, "smooth normals change the image");
    let mapped = prepare_blobs(tmp.path(), "8", &["--colour-map", "viridis"]);
    let m = Manifest::load(&mapped).unwrap();
    assert!(matches!(
        m.materials[0],
        rayfarm_core::scene::Material::Mapped { axis: 2, .. }
    ));
    assert_ne!(
        render(&mapped, "mapped.exr"),
        hashes[0].1,
        "the colour map shows"
    );
    // A colour map that does not exist is refused naming the presets.
    let raw = tmp.path().join("blobs.raw");
    let err = rayfarm_err(&[
        "prepare",
        s(&raw),
        "--dims",
        "40,36,24",
        "--dtype",
        "i16",
        "--iso",
        "500",
        "--colour-map",
        "rainbow",
        "--out",
        s(&tmp.path().join("x")),
    ]);
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
