//! The bench's plan: the schedules, repeats and job of every run, the scene's size, and the
//! output files, all checked before any process starts.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use rayfarm_core::progressive::Progressive;
use rayfarm_core::scene::Manifest;
use rayfarm_node::job::schedule_name;
use rayfarm_node::proto;

use crate::bench::progressive::SUFFIX;
use crate::local_cluster::scene_root_and_name;

use super::*;

/// What one row of the bench runs: a schedule, in one pass or subframes, with its
/// speculation setting, prefetching or not, loading domains from peers or not.
#[derive(Clone, Debug)]
pub(super) struct Run {
    pub(super) schedule: proto::Schedule,
    pub(super) progressive: Option<proto::Progressive>,
    pub(super) speculation: String,
    pub(super) prefetch: bool,
    pub(super) peer_domains: bool,
}

/// The name suffix of a row that prefetches (`--prefetch`).
pub(super) const PREFETCH_SUFFIX: &str = "+prefetch";

/// The name suffix of a row that loads domains from peers (`--peer-domains`).
pub(super) const PEERS_SUFFIX: &str = "+peers";

/// Everything the bench needs, checked before any process starts.
pub(super) struct Plan {
    /// (name, run), in the order given; with `--progressive`, each schedule's one-pass row
    /// is followed by its progressive one.
    pub(super) schedules: Vec<(String, Run)>,
    pub(super) repeats: usize,
    /// The job of every run, with its schedule left to fill in.
    pub(super) spec: proto::JobSpec,
    pub(super) scene_dir: PathBuf,
    pub(super) scene_name: String,
    pub(super) scene_bytes: u64,
    /// Bytes of each domain file (the bound's unavoidable loads).
    pub(super) domain_bytes: Vec<u64>,
    pub(super) domains: usize,
    pub(super) csv: Option<PathBuf>,
    pub(super) chart: Option<PathBuf>,
}

impl Plan {
    pub(super) fn new(a: &BenchArgs) -> anyhow::Result<Self> {
        let mut schedules: Vec<(String, Run)> = Vec::new();
        for (s, speculation) in &a.schedules {
            let mut name = schedule_name(*s).to_string();
            if !speculation.is_empty() {
                name = format!("{name}:{speculation}");
            }
            if schedules.iter().any(|(n, _)| *n == name) {
                bail!("--schedules names {name} twice");
            }
            let run = Run {
                schedule: *s,
                progressive: None,
                speculation: speculation.clone(),
                prefetch: false,
                peer_domains: false,
            };
            // A row, and with --peer-domains its twin loading from peers.
            let mut push = |name: String, run: Run| {
                if a.peer_domains {
                    let peers = Run {
                        peer_domains: true,
                        ..run.clone()
                    };
                    schedules.push((name.clone(), run));
                    schedules.push((format!("{name}{PEERS_SUFFIX}"), peers));
                } else {
                    schedules.push((name, run));
                }
            };
            push(name.clone(), run.clone());
            // Only the dynamic schedules plan one step ahead.
            if a.prefetch && matches!(s, proto::Schedule::Dynamic | proto::Schedule::Predictive) {
                let run = Run {
                    prefetch: true,
                    ..run.clone()
                };
                push(format!("{name}{PREFETCH_SUFFIX}"), run);
            }
            if let Some(field) = a.progressive.and_then(Progressive::field) {
                let progressive = proto::Progressive {
                    subframe_spp: field,
                };
                let run = Run {
                    progressive: Some(progressive),
                    ..run
                };
                schedules.push((format!("{name}{SUFFIX}"), run));
            }
        }
        if schedules.is_empty() {
            bail!("--schedules names no schedule");
        }
        let chart = a
            .chart
            .clone()
            .or_else(|| a.csv.as_ref().map(|c| c.with_extension("png")));
        if let Some(chart) = &chart
            && !chart
                .extension()
                .is_some_and(|e| e.eq_ignore_ascii_case("png"))
        {
            bail!(
                "--chart {}: the chart is a PNG; name it .png",
                chart.display()
            );
        }
        for out in a.csv.iter().chain(&chart) {
            writable_parent(out)?;
        }
        let manifest = Manifest::load(&a.scene)
            .and_then(|m| m.check_domains(&a.scene, false).map(|()| m))
            .with_context(|| {
                format!(
                    "{} is not a usable prepared scene (make one with `rayfarm prepare`)",
                    a.scene.display()
                )
            })?;
        let (_, scene_name) = scene_root_and_name(&a.scene)?;
        Ok(Self {
            schedules,
            repeats: a.repeats as usize,
            spec: proto::JobSpec {
                scene: scene_name.clone(),
                camera: None,
                width: a.width,
                height: a.height,
                spp: a.spp,
                max_depth: a.depth,
                schedule: proto::Schedule::Dynamic as i32,
                priority: 0,
                cold_cache: true,
                progressive: None,
                speculation: String::new(),
                prefetch: false,
                peer_domains: false,
            },
            scene_dir: a.scene.clone(),
            scene_name,
            scene_bytes: manifest.domains.iter().map(|d| d.bytes).sum(),
            domain_bytes: manifest.domains.iter().map(|d| d.bytes).collect(),
            domains: manifest.domains.len(),
            csv: a.csv.clone(),
            chart,
        })
    }

    pub(super) fn names(&self) -> Vec<String> {
        self.schedules.iter().map(|(n, _)| n.clone()).collect()
    }
}

/// Creates the directory of an output file now, so a path that cannot be written is an error
/// before an hour of frames is spent, not after.
pub(super) fn writable_parent(path: &Path) -> anyhow::Result<()> {
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(parent)
        .with_context(|| format!("{}: creating {}", path.display(), parent.display()))
}
