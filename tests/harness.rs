//! Shared pieces of the integration tests: find the real binaries, run them, read their output.
//! The binaries are built by `cargo build --release --bins` (README's test command does it).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Path of a workspace binary built in the same profile as this test.
pub fn bin(name: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/<test> -> target/<profile>/<name>
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .expect("target directory");
    let path = dir.join(name);
    assert!(
        path.exists(),
        "{} is missing: run `cargo build --release --bins` before the tests",
        path.display()
    );
    path
}

/// Runs `rayfarm` with `args`; returns its output, whatever the exit status.
pub fn rayfarm(args: &[&str]) -> Output {
    Command::new(bin("rayfarm"))
        .args(args)
        .env("RUST_LOG", "warn")
        .output()
        .expect("start rayfarm")
}

/// Runs `rayfarm` and fails the test, showing stderr, unless it succeeds.
pub fn rayfarm_ok(args: &[&str]) -> Output {
    let out = rayfarm(args);
    assert!(
        out.status.success(),
        "rayfarm {} failed:\n{}",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Runs `rayfarm` expecting failure; returns its stderr.
pub fn rayfarm_err(args: &[&str]) -> String {
    let out = rayfarm(args);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(
        !out.status.success(),
        "rayfarm {} should have failed; stdout:\n{}",
        args.join(" "),
        String::from_utf8_lossy(&out.stdout)
    );
    stderr
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

/// `p` as a `&str` for argument lists.
pub fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}
