//! `rayfarm render --local` gives the same image, to the bit, whatever the domain count, the
//! thread count, the cache budget and the ray placement; and bad scenes get clear errors.

use std::path::{Path, PathBuf};

use rayfarm_core::bvh::Kernel;
use rayfarm_tests::{file_hash, rayfarm_err, rayfarm_ok, rayfarm_ok_env, s, stats_field};

fn generate(dir: &Path, domains: u32) -> PathBuf {
    let out = dir.join(format!("nbody-{domains}"));
    rayfarm_ok(&[
        "prepare",
        "--generate",
        "nbody",
        "--triangles",
        "20000",
        "--seed",
        "3",
        "--domains",
        &domains.to_string(),
        "--out",
        s(&out),
    ]);
    out
}

struct Rendered {
    hash: String,
    png: String,
    loads: u64,
}

fn render(scene: &Path, out_dir: &Path, threads: u32, cache: &str, tag: &str) -> Rendered {
    render_with(scene, out_dir, threads, cache, tag, &[])
}

fn render_with(
    scene: &Path,
    out_dir: &Path,
    threads: u32,
    cache: &str,
    tag: &str,
    extra: &[&str],
) -> Rendered {
    render_env(scene, out_dir, threads, cache, tag, extra, &[])
}

fn render_env(
    scene: &Path,
    out_dir: &Path,
    threads: u32,
    cache: &str,
    tag: &str,
    extra: &[&str],
    env: &[(&str, &str)],
) -> Rendered {
    let png = out_dir.join(format!("{tag}.png"));
    let json = out_dir.join(format!("{tag}.json"));
    let threads = threads.to_string();
    let mut args = vec![
        "render",
        "--local",
        "--scene",
        s(scene),
        "--out",
        s(&png),
        "--width",
        "96",
        "--height",
        "72",
        "--spp",
        "2",
        "--depth",
        "3",
        "--threads",
        &threads,
        "--cache-bytes",
        cache,
        "--stats-json",
        s(&json),
        "--quiet",
    ];
    args.extend_from_slice(extra);
    rayfarm_ok_env(&args, env);
    Rendered {
        hash: stats_field(&json, "/image_hash")
            .as_str()
            .unwrap()
            .to_string(),
        png: file_hash(&png),
        loads: stats_field(&json, "/cache/loads").as_u64().unwrap(),
    }
}

#[test]
fn generated_scene_renders_identically_at_1_8_and_64_domains_any_threads_any_cache() {
    let tmp = tempfile::tempdir().unwrap();
    let reference = render(&generate(tmp.path(), 1), tmp.path(), 1, "1GiB", "ref");
    for domains in [8, 64] {
        let scene = generate(tmp.path(), domains);
        for threads in [1, 2] {
            // "1" byte holds one domain at a time; 1GiB holds them all.
            for cache in ["1", "1GiB"] {
                let r = render(
                    &scene,
                    tmp.path(),
                    threads,
                    cache,
                    &format!("d{domains}t{threads}c{cache}"),
                );
                assert_eq!(
                    r.hash, reference.hash,
                    "{domains} domains, {threads} threads, cache {cache}"
                );
                assert_eq!(r.png, reference.png);
                if cache == "1GiB" {
                    assert_eq!(
                        r.loads, domains as u64,
                        "a cache holding the scene loads each domain once"
                    );
                } else {
                    assert!(
                        r.loads > domains as u64,
                        "a one-domain cache must reload domains"
                    );
                }
            }
        }
    }
}

/// The image hash of `generate(_, 1)` rendered by `render` at 2 threads, as the 4-wide BVH of
/// domain file format 3 (commit 77f3361) drew it: the 8-wide kernels must not move a pixel.
const HASH_BEFORE_8_WIDE: &str = "26496b5f9c8ca2cb";

/// Every kernel, with the render kernel's camera-ray packets on and off (`RAYFARM_PACKETS`).
#[test]
fn every_traversal_kernel_renders_the_hash_of_the_4_wide_tree() {
    let tmp = tempfile::tempdir().unwrap();
    for domains in [1, 8] {
        let scene = generate(tmp.path(), domains);
        for kernel in Kernel::ALL.into_iter().filter(|k| k.supported()) {
            for packets in ["1", "0"] {
                for threads in [1, 2] {
                    let tag = format!("{}-{domains}-{threads}-p{packets}", kernel.name());
                    let env = [
                        ("RAYFARM_KERNEL", kernel.name()),
                        ("RAYFARM_PACKETS", packets),
                    ];
                    let r = render_env(&scene, tmp.path(), threads, "1GiB", &tag, &[], &env);
                    assert_eq!(r.hash, HASH_BEFORE_8_WIDE, "{tag}");
                }
            }
        }
    }
}

/// Domain files mapped and copied into huge pages (`RAYFARM_HUGEPAGES`), with a cache that
/// holds them all and one that reloads them: the same image.
#[test]
fn domains_in_huge_pages_or_mapped_render_the_same_hash() {
    let tmp = tempfile::tempdir().unwrap();
    for domains in [1, 8] {
        let scene = generate(tmp.path(), domains);
        for hugepages in ["1", "0"] {
            for cache in ["1", "1GiB"] {
                let tag = format!("huge{hugepages}-{domains}-c{cache}");
                let env = [("RAYFARM_HUGEPAGES", hugepages)];
                let r = render_env(&scene, tmp.path(), 2, cache, &tag, &[], &env);
                assert_eq!(r.hash, HASH_BEFORE_8_WIDE, "{tag}");
            }
        }
    }
}

#[test]
fn a_scene_of_an_older_domain_format_is_refused_with_re_run_prepare() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = generate(tmp.path(), 1);
    let file = std::fs::read_dir(&scene)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "rfd"))
        .unwrap();
    // What files of formats 3 to 5 start with: the same magic, then their version.
    let current = std::fs::read(&file).unwrap();
    for old in [3u32, 4, 5] {
        let mut bytes = current.clone();
        bytes[8..12].copy_from_slice(&old.to_le_bytes());
        std::fs::write(&file, bytes).unwrap();
        let out = tmp.path().join("old.png");
        let err = rayfarm_err(&args(s(&scene), s(&out)));
        assert!(
            err.contains(&format!("version {old}"))
                && err.contains("version 6")
                && err.contains("re-run `rayfarm prepare`"),
            "{err}"
        );
    }
}

#[test]
fn speculative_placement_renders_the_same_image_with_fewer_loads() {
    let tmp = tempfile::tempdir().unwrap();
    for domains in [8, 64] {
        let scene = generate(tmp.path(), domains);
        let chained = render(&scene, tmp.path(), 2, "1", &format!("chained{domains}"));
        for threads in [1, 2] {
            let tag = format!("speculative{domains}t{threads}");
            let r = render_with(&scene, tmp.path(), threads, "1", &tag, &["--speculate"]);
            assert_eq!(r.hash, chained.hash, "{domains} domains, {threads} threads");
            assert_eq!(r.png, chained.png);
            assert!(
                r.loads < chained.loads,
                "{domains} domains: {} loads speculating, {} chained",
                r.loads,
                chained.loads
            );
        }
        let whole = render_with(&scene, tmp.path(), 2, "1GiB", "whole", &["--speculate"]);
        assert_eq!(whole.hash, chained.hash);
        assert_eq!(whole.loads, domains as u64);
    }
}

#[test]
fn speculation_at_any_depth_renders_the_same_image_and_prediction_saves_segments() {
    // Windows of copies, fixed or predicted, conclude each ray as the chained trace does.
    let tmp = tempfile::tempdir().unwrap();
    for domains in [8, 64] {
        let scene = generate(tmp.path(), domains);
        let chained = render(&scene, tmp.path(), 2, "1", &format!("chained{domains}"));
        let mut segments = Vec::new();
        for depth in ["full", "ahead:1", "ahead:3", "predicted", "predicted:0.5"] {
            let tag = format!("depth{domains}-{}", depth.replace(':', "-"));
            let extra = ["--speculate", "--speculation", depth];
            let r = render_with(&scene, tmp.path(), 2, "1", &tag, &extra);
            assert_eq!(r.hash, chained.hash, "{domains} domains, {depth}");
            assert_eq!(r.png, chained.png);
            let json = tmp.path().join(format!("{tag}.json"));
            let traced: u64 = ["/rays/radiance_segments", "/rays/shadow_segments"]
                .iter()
                .map(|f| stats_field(&json, f).as_u64().unwrap())
                .sum();
            segments.push((depth, traced));
        }
        let seg = |d: &str| segments.iter().find(|s| s.0 == d).unwrap().1;
        assert!(seg("predicted") < seg("full"), "{segments:?}");
        assert!(seg("ahead:1") <= seg("predicted"), "{segments:?}");
    }
    let scene = tmp.path().join("nbody-8");
    let err = rayfarm_err(&[
        "render",
        "--local",
        "--scene",
        s(&scene),
        "--out",
        "x.png",
        "--speculate",
        "--speculation",
        "sometimes",
    ]);
    assert!(err.contains("unknown speculation"), "{err}");
}

/// A sphere over a floor, written as ASCII PLY: crossing triangles and shared edges everywhere.
fn write_ply(path: &Path) {
    let mut verts = Vec::new();
    let mut faces = Vec::new();
    let (nu, nv) = (48, 24);
    for j in 0..=nv {
        for i in 0..nu {
            let (th, ph) = (
                j as f32 / nv as f32 * std::f32::consts::PI,
                i as f32 / nu as f32 * std::f32::consts::TAU,
            );
            verts.push([
                ph.cos() * th.sin() * 0.4 + 0.5,
                th.cos() * 0.4 + 0.5,
                ph.sin() * th.sin() * 0.4 + 0.5,
            ]);
        }
    }
    for j in 0..nv {
        for i in 0..nu {
            let a = j * nu + i;
            let b = j * nu + (i + 1) % nu;
            faces.push([a, b, a + nu]);
            faces.push([b, b + nu, a + nu]);
        }
    }
    let f = verts.len();
    verts.extend([
        [-1.0, 0.05, -1.0],
        [2.0, 0.05, -1.0],
        [2.0, 0.05, 2.0],
        [-1.0, 0.05, 2.0],
    ]);
    faces.push([f, f + 2, f + 1]);
    faces.push([f, f + 3, f + 2]);
    let mut text = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        verts.len(),
        faces.len()
    );
    for v in &verts {
        text += &format!("{:?} {:?} {:?}\n", v[0], v[1], v[2]);
    }
    for t in &faces {
        text += &format!("3 {} {} {}\n", t[0], t[1], t[2]);
    }
    std::fs::write(path, text).unwrap();
}

#[test]
fn mesh_scene_renders_identically_at_1_8_and_64_domains_chained_or_speculative() {
    let tmp = tempfile::tempdir().unwrap();
    let ply = tmp.path().join("sphere.ply");
    write_ply(&ply);
    let mut hashes = Vec::new();
    for domains in [1, 8, 64] {
        let out = tmp.path().join(format!("sphere-{domains}"));
        rayfarm_ok(&[
            "prepare",
            s(&ply),
            "--domains",
            &domains.to_string(),
            "--out",
            s(&out),
        ]);
        hashes.push(render(&out, tmp.path(), 2, "1", &format!("m{domains}")).hash);
        // Triangles crossing domain boundaries: each copy finds its own stretch's hits.
        let tag = format!("m{domains}s");
        hashes.push(render_with(&out, tmp.path(), 2, "1", &tag, &["--speculate"]).hash);
    }
    assert!(hashes.iter().all(|h| *h == hashes[0]), "{hashes:?}");
}

fn args<'a>(scene: &'a str, out: &'a str) -> Vec<&'a str> {
    vec![
        "render", "--local", "--scene", scene, "--out", out, "--width", "32", "--height", "24",
        "--spp", "1", "--quiet",
    ]
}

#[test]
fn bad_scenes_and_frames_get_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = generate(tmp.path(), 4);
    let png = tmp.path().join("x.png");
    let (sc, out) = (s(&scene), s(&png));
    rayfarm_ok(&args(sc, out));

    for (flag, value, expect) in [
        ("--width", "0", "resolution 0x24"),
        ("--width", "100000", "resolution 100000x24"),
        ("--spp", "0", "spp 0"),
        ("--depth", "1000", "depth 1000"),
        ("--fov", "200", "field of view 200"),
    ] {
        let mut a = args(sc, out);
        match a.iter().position(|x| *x == flag) {
            Some(i) => a[i + 1] = value,
            None => a.extend([flag, value]),
        }
        let err = rayfarm_err(&a);
        assert!(err.contains(expect), "{flag} {value}: {err}");
    }
    // A camera override renders another view of the same scene.
    let json = tmp.path().join("s.json");
    let hash = |extra: &[&str]| {
        let mut a = args(sc, out);
        a.extend(["--stats-json", s(&json)]);
        a.extend(extra);
        rayfarm_ok(&a);
        stats_field(&json, "/image_hash")
    };
    assert_ne!(hash(&[]), hash(&["--eye", "0.5,0.9,2.0", "--fov", "30"]));

    let err = rayfarm_err(&args(sc, s(&tmp.path().join("x.gif"))));
    assert!(err.contains("must end in .png"), "{err}");
    let err = rayfarm_err(&args(s(&tmp.path().join("nowhere")), out));
    assert!(
        err.contains("nowhere") && err.contains("scene.toml"),
        "{err}"
    );

    // A flipped byte deep in a domain: the checksum names the file.
    let domain = scene.join("domain-00002.rfd");
    let mut bytes = std::fs::read(&domain).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x40;
    std::fs::write(&domain, &bytes).unwrap();
    let err = rayfarm_err(&args(sc, out));
    assert!(
        err.contains("domain-00002.rfd") && err.contains("corrupt"),
        "{err}"
    );
    // Truncated.
    std::fs::write(&domain, &bytes[..100]).unwrap();
    let err = rayfarm_err(&args(sc, out));
    assert!(
        err.contains("domain-00002.rfd") && err.contains("truncated"),
        "{err}"
    );

    // A manifest that does not parse, and one that lies about its domains.
    let manifest = scene.join("scene.toml");
    let text = std::fs::read_to_string(&manifest).unwrap();
    std::fs::write(&manifest, text.replace("[camera]", "[camera")).unwrap();
    let err = rayfarm_err(&args(sc, out));
    assert!(
        err.contains("scene.toml") && err.contains("malformed manifest"),
        "{err}"
    );
    std::fs::write(&manifest, text.replace("domain = 3", "domain = 7")).unwrap();
    let err = rayfarm_err(&args(sc, out));
    assert!(
        err.contains("malformed manifest") && err.contains("domain 7"),
        "{err}"
    );
}
