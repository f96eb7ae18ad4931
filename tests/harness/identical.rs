//! Images that must be the same bits however they are made: a scene rendered locally every
//! way (domain cuts, caches, threads, placements), and on clusters of 1, 2 and 4 workers under
//! every schedule against `render --local`. The volume and isosurface tests share these.

use std::path::{Path, PathBuf};

use rayfarm_core::scene::Manifest;

use crate::cli::rayfarm_ok;
use crate::cluster::{Cluster, WorkerOpts, submit_wait};
use crate::process::START_TIMEOUT;
use crate::s;
use crate::scenes::{domain_bytes, file_hash, hash_of, local_hash};

/// The frame every render here makes: small, and crossing every brick.
pub const FRAME: [&str; 6] = ["--width", "96", "--height", "72", "--spp", "2"];

/// A local render's cache budget.
#[derive(Clone, Copy, Debug)]
pub enum Cache {
    /// The whole scene fits.
    Ample,
    /// A sixth of the scene's bytes: domains page in and out.
    Sixth,
}

/// One way of rendering a scene locally that must not change its image.
#[derive(Clone, Copy, Debug)]
pub struct Run {
    /// The cache budget.
    pub cache: Cache,
    /// Tracing threads.
    pub threads: &'static str,
    /// Speculative placement (`--speculate`), or chained.
    pub speculate: bool,
}

/// Caches, threads and placements a volume is rendered with.
pub const DVR_RUNS: [Run; 5] = [
    run(Cache::Ample, "1", false),
    run(Cache::Sixth, "2", false),
    run(Cache::Ample, "2", false),
    run(Cache::Ample, "1", true),
    run(Cache::Sixth, "2", true),
];

/// Caches, threads and placements an isosurface is rendered with.
pub const SURFACE_RUNS: [Run; 4] = [
    run(Cache::Ample, "1", false),
    run(Cache::Sixth, "2", false),
    run(Cache::Ample, "1", true),
    run(Cache::Sixth, "2", true),
];

/// A [`Run`].
pub const fn run(cache: Cache, threads: &'static str, speculate: bool) -> Run {
    Run {
        cache,
        threads,
        speculate,
    }
}

/// `render --local` of `scene` at [`FRAME`] with `extra` arguments into `img`, its statistics
/// beside it (`img` with the extension `json`); returns the image file's hash.
pub fn render_local(scene: &Path, img: &Path, extra: &[&str]) -> String {
    let stats = img.with_extension("json");
    let mut args = vec!["render", "--local", "--scene", s(scene)];
    args.extend(FRAME);
    args.extend(["-o", s(img), "--stats-json", s(&stats), "--quiet"]);
    args.extend_from_slice(extra);
    rayfarm_ok(&args);
    file_hash(img)
}

/// Renders each of `scenes` (one image, cut into different domains) every way of `runs` with
/// `extra` arguments and asserts every image is the first one to the bit; returns its hash and
/// each render's statistics file.
pub fn same_image_every_way(
    dir: &Path,
    scenes: &[PathBuf],
    runs: &[Run],
    extra: &[&str],
) -> (String, Vec<PathBuf>) {
    let mut hashes: Vec<(String, String)> = Vec::new();
    let mut stats = Vec::new();
    for scene in scenes {
        let bytes: u64 = Manifest::load(scene)
            .unwrap()
            .domains
            .iter()
            .map(|d| d.bytes)
            .sum();
        let sixth = (bytes / 6).max(1).to_string();
        for run in runs {
            let cache = match run.cache {
                Cache::Ample => "4GiB",
                Cache::Sixth => sixth.as_str(),
            };
            let mut args = vec!["--threads", run.threads, "--cache-bytes", cache];
            if run.speculate {
                args.push("--speculate");
            }
            args.extend_from_slice(extra);
            let name = scene.file_name().unwrap().to_string_lossy();
            let img = dir.join(format!("{name}-{}.exr", stats.len()));
            let hash = render_local(scene, &img, &args);
            hashes.push((format!("{name}, {run:?}"), hash));
            stats.push(img.with_extension("json"));
        }
    }
    for (what, h) in &hashes {
        assert_eq!(h, &hashes[0].1, "{what} differs from {}", hashes[0].0);
    }
    (hashes[0].1.clone(), stats)
}

/// Renders the scene `name` in `root` on 1, 2 and 4 workers with two-domain caches under
/// every schedule; every image must be `render --local`'s.
pub fn on_a_cluster(root: &Path, name: &str) {
    let scene = root.join(name);
    let expected = local_hash(&scene, &FRAME);
    let (_, largest) = domain_bytes(&scene);
    for n in [1, 2, 4] {
        // Two-brick caches: bricks page in and out.
        let cluster = Cluster::start(root, Some(name), &vec![WorkerOpts::cache(2 * largest); n]);
        cluster.wait_for_workers(n, START_TIMEOUT);
        for schedule in ["image-plane", "domain", "dynamic", "hybrid", "predictive"] {
            let mut f = FRAME.to_vec();
            f.extend(["--schedule", schedule, "--cold-cache"]);
            let stats = submit_wait(&cluster, &f, &format!("{schedule}-{n}"));
            assert_eq!(hash_of(&stats), expected, "{schedule} with {n} workers");
        }
    }
}
