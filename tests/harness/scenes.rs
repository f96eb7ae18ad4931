//! Scenes and images: a generated scene prepared with `rayfarm prepare`, the reference hash of
//! `render --local`, and the fields of the statistics files a render writes.

use std::path::{Path, PathBuf};

use crate::cli::rayfarm_ok;
use crate::s;

/// Prepares a generated scene `name` under `root`.
pub fn prepare_nbody(root: &Path, name: &str, triangles: u32, domains: u32) -> PathBuf {
    let out = root.join(name);
    rayfarm_ok(&[
        "prepare",
        "--generate",
        "nbody",
        "--triangles",
        &triangles.to_string(),
        "--seed",
        "5",
        "--domains",
        &domains.to_string(),
        "--out",
        s(&out),
    ]);
    out
}

/// The image hash of `render --local` for `frame`.
pub fn local_hash(scene: &Path, frame: &[&str]) -> String {
    let dir = tempfile::tempdir().expect("temp dir");
    let json = dir.path().join("local.json");
    let png = dir.path().join("local.png");
    let mut args = vec![
        "render",
        "--local",
        "--scene",
        s(scene),
        "--out",
        s(&png),
        "--stats-json",
        s(&json),
        "--quiet",
    ];
    args.extend_from_slice(frame);
    rayfarm_ok(&args);
    hash_of(&json)
}

/// The image hash in a statistics file.
pub fn hash_of(stats: &Path) -> String {
    stats_field(stats, "/image_hash")
        .as_str()
        .expect("hash is a string")
        .to_string()
}

/// A field of the statistics JSON written by `--stats-json`.
pub fn stats_field(path: &Path, pointer: &str) -> serde_json::Value {
    let text = std::fs::read_to_string(path).expect("stats json");
    let v: serde_json::Value = serde_json::from_str(&text).expect("stats json parses");
    v.pointer(pointer)
        .unwrap_or_else(|| panic!("{pointer} missing in {text}"))
        .clone()
}

/// xxh3 of a file's bytes, in hex.
pub fn file_hash(path: &Path) -> String {
    format!(
        "{:016x}",
        xxhash_rust::xxh3::xxh3_64(&std::fs::read(path).expect("read file"))
    )
}

/// Sizes of a scene's domain files: (total, largest).
pub fn domain_bytes(scene: &Path) -> (u64, u64) {
    let sizes: Vec<u64> = std::fs::read_dir(scene)
        .expect("scene dir")
        .filter_map(Result::ok)
        .filter(|e| e.file_name() != "scene.toml")
        .map(|e| e.metadata().expect("metadata").len())
        .collect();
    (sizes.iter().sum(), sizes.iter().copied().max().unwrap_or(0))
}
