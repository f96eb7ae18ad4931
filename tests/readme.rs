//! Every shell command in README.md and deploy/README.md runs here, so the documentation
//! cannot break silently. The ```sh blocks are read from the files themselves; each command
//! (continuation lines joined, comments dropped) must match an entry of [`plan`], which says
//! how it runs on this machine: as written but with small scenes and frames (an explicit
//! list of substitutions, [`SMALL`]), as a synopsis whose flags must all exist, or skipped
//! with the reason (Docker, Kubernetes). A command added to a README without an entry fails
//! the test until it is given one.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use rayfarm_tests::{START_TIMEOUT, bin, prepare_nbody, repo_root};

/// How one documented command is run here.
enum Plan {
    /// Run through `sh` with the substitutions of [`SMALL`] and these more.
    Run(&'static [(&'static str, &'static str)]),
    /// Started as a server: runs until the test ends; its `listening on ADDR` is awaited.
    Serve(&'static [(&'static str, &'static str)]),
    /// A synopsis: every `--flag` it shows must be in the command's `--help`.
    Synopsis,
    /// Cannot run on this machine, for this reason.
    Skip(&'static str),
}

/// Documented sizes and the small ones the test uses instead (same flags, seconds not hours).
const SMALL: &[(&str, &str)] = &[
    ("cargo build --release --bins && ", ""),
    ("target/release/rayfarm", "rayfarm"),
    ("--triangles 10000000", "--triangles 20000"),
    ("--domains 64", "--domains 4"),
    ("--width 1280 --height 720", "--width 64 --height 48"),
    (
        "--width 1920 --height 1080 --spp 64",
        "--width 64 --height 48 --spp 1",
    ),
    (
        "--width 256 --height 256 --spp 4",
        "--width 32 --height 32 --spp 1",
    ),
    ("--spp 16", "--spp 1"),
    // Progressive against one pass: still two subframes (1 and 1 sample).
    (
        "--width 256 --height 256 --spp 8",
        "--width 32 --height 32 --spp 2",
    ),
    ("--width 512 --height 512", "--width 32 --height 32"),
    // The skull CT's dims, for a small int16 ball of the same name.
    ("--dims 256,256,108", "--dims 64,64,32"),
    // 64 bricks need 64 blocks of 8 cells: 8 x 8 x 4 of them.
    ("--dims 256,256,128", "--dims 64,64,32"),
    ("--workers 4", "--workers 2"),
    ("--repeats 3", "--repeats 1"),
    (
        "--schedules predictive,dynamic,image-plane,domain,hybrid",
        "--schedules predictive,dynamic",
    ),
    ("--storage-bandwidth 100MiB/s", "--storage-bandwidth 1GiB/s"),
    ("--cache-bytes 7.5MiB", "--cache-bytes 4MiB"),
];

const COMPOSE: &str =
    "needs Docker and the compose cluster; tests/compose.rs runs it where Docker exists";

/// A documented command's beginning and how commands that begin so are run.
type Entry = (&'static str, fn() -> Plan);

/// Every documented command, by how it begins.
fn plan(command: &str) -> Option<Plan> {
    const TABLE: &[Entry] = &[
        (
            "cargo build --release --bins && target/release/rayfarm demo",
            || {
                Plan::Run(&[(
                    "rayfarm demo",
                    "rayfarm demo --triangles 20000 --domains 4 --width 64 --height 48 --workers 2",
                )])
            },
        ),
        ("cargo build --release --bins && cargo test", || {
            Plan::Skip("the test suite itself (CI runs it)")
        }),
        ("rayfarm prepare", || Plan::Run(&[])),
        ("rayfarm render", || Plan::Run(&[])),
        ("rayfarm sim", || {
            Plan::Run(&[
                ("--seeds 0..100000", "--seeds 0..20"),
                // The runs at scale take minutes: the same commands on two and three workers,
                // a small frame.
                ("--workers 64,256", "--workers 2,3"),
                ("--workers 64", "--workers 2"),
                ("--workers 256", "--workers 3"),
                ("--workers 1024", "--workers 3"),
                ("--workers 4096", "--workers 3"),
                (
                    "--width 1024 --height 1024 --spp 1",
                    "--width 32 --height 32 --spp 1",
                ),
                (
                    "--width 256 --height 256 --spp 1",
                    "--width 32 --height 32 --spp 1",
                ),
            ])
        }),
        ("rayfarm-coordinator", || {
            Plan::Serve(&[
                ("0.0.0.0:50051", "127.0.0.1:0"),
                ("/var/lib/rayfarm", "var-lib-rayfarm"),
                ("/mnt/scenes", "scenes"),
            ])
        }),
        ("rayfarm-worker", || {
            Plan::Serve(&[
                ("http://nodeA:50051", "$COORDINATOR"),
                (
                    "--listen 0.0.0.0:7000 --advertise nodeB:7000",
                    "--listen 127.0.0.1:0",
                ),
                ("--cache-bytes 8GiB", "--cache-bytes 64MiB"),
                ("/shared/scenes", "scenes"),
            ])
        }),
        ("rayfarm submit --coordinator nodeA:50051", || {
            Plan::Run(&[("nodeA:50051", "$COORDINATOR")])
        }),
        (
            "target/release/rayfarm submit --coordinator localhost:50051",
            || Plan::Run(&[("localhost:50051", "$COORDINATOR")]),
        ),
        ("target/release/rayfarm fetch JOB_ID", || {
            Plan::Run(&[(
                "JOB_ID",
                "$(rayfarm jobs --json | sed -n 's/.*\"job_id\": \"\\(.*\\)\",/\\1/p' | head -1)",
            )])
        }),
        (
            "rayfarm submit --wait --output frame.png",
            || Plan::Run(&[]),
        ),
        ("rayfarm submit [", || Plan::Synopsis),
        ("rayfarm watch JOB", || Plan::Synopsis),
        ("rayfarm jobs [", || Plan::Synopsis),
        ("rayfarm status [", || Plan::Synopsis),
        ("rayfarm fetch JOB", || Plan::Synopsis),
        ("rayfarm cancel JOB", || Plan::Synopsis),
        ("rayfarm health HOST:PORT", || Plan::Synopsis),
        ("rayfarm bench --scene DIR", || Plan::Synopsis),
        ("rayfarm bench-api [", || Plan::Synopsis),
        ("rayfarm bench --scene scenes/", || Plan::Run(&[])),
        // The simulator's validation: the same scene through the real cluster.
        ("rayfarm bench --scene b32", || Plan::Run(&[])),
        ("rayfarm certs", || Plan::Run(&[])),
        ("deploy/build-image.sh", || Plan::Skip(COMPOSE)),
        ("docker ", || Plan::Skip(COMPOSE)),
        ("c=$(docker", || Plan::Skip(COMPOSE)),
        ("for f in ca.pem node-client.pem", || Plan::Skip(COMPOSE)),
        ("export RAYFARM_TLS_CA", || {
            Plan::Skip("the compose cluster's CA and token (see the docker lines)")
        }),
        ("export RAYFARM_TLS_CERT", || {
            Plan::Skip("the compose cluster's client certificate (see the docker lines)")
        }),
        ("kubectl ", || Plan::Skip("needs a Kubernetes cluster")),
        ("bench/larger-than-memory/run.sh", || {
            Plan::Skip("a benchmark: a 32.8 GiB scene, about 50 GiB of disk and half an hour")
        }),
        ("bench/validation/run.sh", || {
            Plan::Skip("a benchmark: every schedule benched at 4 and 8 workers, about 22 minutes")
        }),
        ("bench/scanned-mesh/run.sh", || {
            Plan::Skip("a benchmark: reads Debian's libcgal-demo, five schedules on 4 workers")
        }),
        ("apt-get download invesalius-examples", || {
            Plan::Skip("fetches a Debian package; the test writes a small cranium.raw instead")
        }),
        ("tar -xOf inv/", || {
            Plan::Skip("reads the Debian package fetched above")
        }),
    ];
    TABLE
        .iter()
        .find(|(prefix, _)| command.starts_with(prefix))
        .map(|(_, p)| p())
}

/// The commands of the ```sh blocks of `text`: continuation lines joined, comments dropped.
/// A synopsis line starting with `[` continues the command above it.
fn commands(text: &str) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    let mut in_block = false;
    let mut continuing = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            in_block = line.trim() == "```sh";
            continue;
        }
        let line = line.trim();
        if !in_block || line.is_empty() || line.starts_with('#') {
            continue;
        }
        // A comment after two spaces ends the command text.
        let line = line.split("  #").next().unwrap_or(line).trim_end();
        let (body, more) = match line.strip_suffix('\\') {
            Some(head) => (head.trim_end(), true),
            None => (line, false),
        };
        match out.last_mut() {
            Some(last) if continuing || body.starts_with('[') => {
                last.push(' ');
                last.push_str(body);
            }
            _ => out.push(body.to_string()),
        }
        continuing = more;
    }
    out.into_iter()
        .map(|c| c.split_whitespace().collect::<Vec<_>>().join(" "))
        .collect()
}

fn substitute(command: &str, extra: &[(&str, &str)]) -> String {
    let mut c = command.to_string();
    for (from, to) in SMALL.iter().chain(extra) {
        c = c.replace(from, to);
    }
    c
}

/// A small closed mesh (a UV sphere) as ASCII PLY.
fn write_sphere_ply(path: &Path) {
    let (rings, segments) = (12u32, 16u32);
    let mut verts = Vec::new();
    for r in 0..=rings {
        let theta = std::f32::consts::PI * r as f32 / rings as f32;
        for g in 0..segments {
            let phi = 2.0 * std::f32::consts::PI * g as f32 / segments as f32;
            verts.push([
                theta.sin() * phi.cos(),
                theta.cos(),
                theta.sin() * phi.sin(),
            ]);
        }
    }
    let mut faces = Vec::new();
    for r in 0..rings {
        for g in 0..segments {
            let a = r * segments + g;
            let b = r * segments + (g + 1) % segments;
            let (c, d) = (a + segments, b + segments);
            faces.push([a, c, b]);
            faces.push([b, c, d]);
        }
    }
    let mut text = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        verts.len(),
        faces.len()
    );
    for v in &verts {
        text.push_str(&format!("{} {} {}\n", v[0], v[1], v[2]));
    }
    for f in &faces {
        text.push_str(&format!("3 {} {} {}\n", f[0], f[1], f[2]));
    }
    std::fs::write(path, text).expect("write ply");
}

/// A 64x64x32 volume of u16 (or i16) holding a ball (squashed in z) whose surface is at 900,
/// 22 voxels out.
fn write_ball_raw(path: &Path, signed: bool) {
    let mut bytes = Vec::new();
    for z in 0..32 {
        for y in 0..64 {
            for x in 0..64 {
                let d = ((x as f32 - 31.5).powi(2)
                    + (y as f32 - 31.5).powi(2)
                    + ((z as f32 - 15.5) * 2.0).powi(2))
                .sqrt();
                let v = (5300.0 - d * 200.0).clamp(0.0, 65535.0);
                if signed {
                    bytes.extend_from_slice(&(v as i16).to_le_bytes());
                } else {
                    bytes.extend_from_slice(&(v as u16).to_le_bytes());
                }
            }
        }
    }
    std::fs::write(path, bytes).expect("write raw");
}

/// A server started by the test, killed when it ends.
struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn shell(dir: &Path, path: &str, coordinator: &str, command: &str) -> Command {
    let mut cmd = Command::new("sh");
    cmd.arg("-c")
        .arg(command)
        .current_dir(dir)
        .env("PATH", path)
        .env("COORDINATOR", coordinator)
        .env("RAYFARM_COORDINATOR", coordinator)
        .env("RUST_LOG", "warn");
    cmd
}

#[test]
fn every_readme_command_runs_or_is_skipped_with_its_reason() {
    let root = repo_root();
    let tmp = tempfile::tempdir().expect("temp dir");
    let dir = tmp.path();
    // What the commands expect to find.
    write_sphere_ply(&dir.join("bunny.ply"));
    write_ball_raw(&dir.join("ct.raw"), false);
    write_ball_raw(&dir.join("cranium.raw"), true);
    std::fs::create_dir_all(dir.join("docs/bench")).expect("docs/bench");
    std::fs::create_dir_all(dir.join("docs/cranium")).expect("docs/cranium");
    // The simulator's chart is drawn from the runs' committed CSV files.
    let runs = dir.join("docs/bench/sim-scale");
    std::fs::create_dir_all(&runs).expect("docs/bench/sim-scale");
    for entry in std::fs::read_dir(root.join("docs/bench/sim-scale")).expect("sim-scale runs") {
        let path = entry.expect("entry").path();
        std::fs::copy(&path, runs.join(path.file_name().expect("name"))).expect("copy CSV");
    }
    let scenes = dir.join("scenes");
    for name in ["b48", "big48"] {
        prepare_nbody(&scenes, name, 20_000, 4);
    }
    // The simulator's section names its scene from the working directory, and calibrates into
    // sim/.
    for name in ["b32", "s2048", "s8192", "s32768"] {
        prepare_nbody(dir, name, 20_000, 4);
    }
    std::fs::create_dir_all(dir.join("sim")).expect("sim");
    let bins: PathBuf = bin("rayfarm").parent().expect("bin dir").to_path_buf();
    let path = format!(
        "{}:{}",
        bins.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let mut coordinator = String::new();
    let mut servers: Vec<Server> = Vec::new();
    let mut ran = 0;
    let mut skipped = Vec::new();
    for file in ["README.md", "deploy/README.md"] {
        let text = std::fs::read_to_string(root.join(file)).expect("read README");
        for command in commands(&text) {
            let plan = plan(&command).unwrap_or_else(|| {
                panic!("{file}: no plan for `{command}`: add it to tests/readme.rs")
            });
            match plan {
                Plan::Skip(why) => skipped.push(format!("{file}: `{command}`: {why}")),
                Plan::Synopsis => {
                    let mut words = command.split_whitespace().skip(1);
                    let sub = words.next().expect("subcommand");
                    let help = rayfarm_tests::rayfarm_ok(&[sub, "--help"]);
                    let help = String::from_utf8_lossy(&help.stdout);
                    for flag in command
                        .split(|c: char| c.is_whitespace() || c == '[' || c == ']')
                        .filter(|w| w.starts_with('-') && w.len() > 1)
                    {
                        let flag = flag.split('=').next().unwrap_or(flag);
                        assert!(
                            help.contains(flag),
                            "{file}: `{command}`: {flag} is not in `rayfarm {sub} --help`"
                        );
                    }
                    ran += 1;
                }
                Plan::Serve(extra) => {
                    let line = substitute(&command, extra);
                    let mut child = shell(dir, &path, &coordinator, &format!("exec {line}"))
                        .stdout(Stdio::piped())
                        .stderr(Stdio::null())
                        .spawn()
                        .expect("start server");
                    let stdout = child.stdout.take().expect("stdout");
                    servers.push(Server(child));
                    let (tx, rx) = std::sync::mpsc::channel();
                    std::thread::spawn(move || {
                        for l in BufReader::new(stdout).lines().map_while(Result::ok) {
                            if let Some(a) = l.strip_prefix("listening on ") {
                                let _ = tx.send(a.to_string());
                            }
                        }
                    });
                    let addr = rx.recv_timeout(START_TIMEOUT).unwrap_or_else(|_| {
                        panic!("{file}: `{line}` printed no `listening on ADDR`")
                    });
                    if command.starts_with("rayfarm-coordinator") {
                        // Its default scene is the one the README's prepare made.
                        coordinator = format!("http://{addr}");
                    } else {
                        rayfarm_tests::rayfarm_ok(&[
                            "status",
                            "--coordinator",
                            &coordinator,
                            "--wait-workers",
                            "1",
                        ]);
                    }
                    ran += 1;
                }
                Plan::Run(extra) => {
                    let line = substitute(&command, extra);
                    let out = shell(dir, &path, &coordinator, &line).output().expect("sh");
                    assert!(
                        out.status.success(),
                        "{file}: `{command}` ran as `{line}` and failed:\n{}{}",
                        String::from_utf8_lossy(&out.stdout),
                        String::from_utf8_lossy(&out.stderr)
                    );
                    ran += 1;
                }
            }
        }
    }
    // deploy/README's prose shows this one outside a block.
    let out = shell(
        dir,
        &path,
        &coordinator,
        "rayfarm status --coordinator $COORDINATOR",
    )
    .output()
    .expect("sh");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // What the commands say they write.
    for f in [
        "frame.png",
        "frame.json",
        "view.png",
        "frame.exr",
        "rayfarm-demo/demo.png",
        "rayfarm-secrets/ca.pem",
        "docs/bench/schedules-cache-holds-scene.png",
        "docs/cranium/dvr-bone.png",
        "docs/cranium/dvr-skin.png",
        "docs/cranium/isosurface.png",
        "docs/cranium/isosurface-smooth.png",
        "docs/cranium/isosurface-bone.png",
        "docs/cranium/dvr-skin-bone-surface.png",
    ] {
        assert!(dir.join(f).exists(), "{f} was not written");
    }
    eprintln!(
        "{ran} README commands ran; skipped:\n  {}",
        skipped.join("\n  ")
    );
    assert!(ran >= 20, "only {ran} commands ran");
    drop(servers);
}
