//! Running the `rayfarm` command: the workspace's binaries, one-shot runs whose output the
//! test reads, a long-running one whose stderr it follows, and the credentials `rayfarm certs`
//! makes.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::mpsc;

use crate::process::START_TIMEOUT;
use crate::s;

/// The files of `rayfarm certs --with-secrets` for loopback (see [`certs`]).
pub struct CertFiles {
    pub ca: PathBuf,
    pub cert: PathBuf,
    pub key: PathBuf,
    pub secret: PathBuf,
    pub tokens: PathBuf,
}

/// Runs `rayfarm certs --with-secrets` for loopback into `dir`.
pub fn certs(dir: &Path) -> CertFiles {
    rayfarm_ok(&[
        "certs",
        "--out",
        s(dir),
        "--hosts",
        "localhost,127.0.0.1",
        "--with-secrets",
    ]);
    CertFiles {
        ca: dir.join("ca.pem"),
        cert: dir.join("node.pem"),
        key: dir.join("node-key.pem"),
        secret: dir.join("cluster-secret"),
        tokens: dir.join("user-tokens"),
    }
}

/// The workspace's root: where the repository's files (README, deploy/, bench/, sim/) are.
pub fn repo_root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("workspace root")
}

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
    rayfarm_env(args, &[])
}

/// Runs `rayfarm` with `args` and extra environment variables; returns its output.
pub fn rayfarm_env(args: &[&str], env: &[(&str, &str)]) -> Output {
    Command::new(bin("rayfarm"))
        .args(args)
        .env("RUST_LOG", "warn")
        .envs(env.iter().copied())
        .output()
        .expect("start rayfarm")
}

/// Runs `rayfarm` and fails the test, showing stderr, unless it succeeds.
pub fn rayfarm_ok(args: &[&str]) -> Output {
    rayfarm_ok_env(args, &[])
}

/// [`rayfarm_ok`] with extra environment variables.
pub fn rayfarm_ok_env(args: &[&str], env: &[(&str, &str)]) -> Output {
    let out = rayfarm_env(args, env);
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

/// Starts `rayfarm args` with `env`, and a channel of its stderr lines.
pub fn spawn_rayfarm(args: &[&str], env: &[(&str, &str)]) -> (Child, mpsc::Receiver<String>) {
    let mut child = Command::new(bin("rayfarm"))
        .args(args)
        .envs(env.iter().copied())
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start rayfarm");
    let stderr = child.stderr.take().expect("piped stderr");
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    (child, rx)
}

/// Waits for a stderr line containing `what`; panics with what was seen.
pub fn wait_line(lines: &mpsc::Receiver<String>, what: &str) {
    let deadline = std::time::Instant::now() + START_TIMEOUT;
    let mut seen = Vec::new();
    while let Some(left) = deadline.checked_duration_since(std::time::Instant::now()) {
        match lines.recv_timeout(left) {
            Ok(line) if line.contains(what) => return,
            Ok(line) => seen.push(line),
            Err(_) => break,
        }
    }
    panic!("no line with {what:?}; stderr so far:\n{}", seen.join("\n"));
}
