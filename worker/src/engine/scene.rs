//! Opening a frame's scene: its directory and manifest read off the runtime within a time
//! limit, the cache kept or opened afresh for it, and why a pass failed when the scene on
//! disk changed under the frame.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use anyhow::Context;
use rayfarm_core::cluster::scene_ref;
use rayfarm_core::render::cache::{CacheCounters, DomainCache};
use rayfarm_core::scene::Manifest;
use rayfarm_machine::pass::FrameView;
use rayfarm_machine::worker::{DomainQueues, OpenedScene, PassFailed};
use rayfarm_node::{job, proto};
use tracing::info;

use super::{Engine, OpenFrame};
use crate::queues::FileSpill;

/// How long opening a frame waits for its scene's manifest.
const SCENE_READ_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(10);

/// What identifies a scene to the cache: its directory and its manifest.
pub(super) type SceneKey = (PathBuf, Manifest);

impl Engine {
    /// The directory and manifest of a StartFrame's scene, read on a blocking thread within
    /// [`SCENE_READ_TIMEOUT`]: storage that hangs (a FIFO that became the manifest, a dead
    /// mount) declines the frame with a clear error instead of stalling this engine and the
    /// runtime's threads. The stuck thread is left to its read.
    pub(super) async fn read_scene(
        &self,
        s: &proto::StartFrame,
    ) -> anyhow::Result<(PathBuf, Manifest)> {
        let spec = s
            .spec
            .as_ref()
            .ok_or_else(|| anyhow::anyhow!("StartFrame without a job spec"))?;
        let (root, allow_absolute) = (
            self.config.scene_root.clone(),
            self.config.allow_absolute_scenes,
        );
        let scene = spec.scene.clone();
        let read = tokio::task::spawn_blocking(move || {
            let dir = scene_ref::resolve(&root, &scene, allow_absolute)?;
            if !dir.is_dir() {
                // Each node names its own mount point of the shared storage.
                anyhow::bail!(
                    "scene {scene:?} not found: {} is not a directory (is --scene-root {} \
                     where this node sees the scenes?)",
                    dir.display(),
                    root.display()
                );
            }
            let manifest = Manifest::load(&dir)?;
            Ok((dir, manifest))
        });
        match tokio::time::timeout(SCENE_READ_TIMEOUT, read).await {
            Ok(Ok(result)) => result,
            Ok(Err(e)) => Err(anyhow::anyhow!(
                "reading scene {:?} failed: {e}",
                spec.scene
            )),
            Err(_) => Err(anyhow::anyhow!(
                "scene {:?}: its manifest could not be read within {SCENE_READ_TIMEOUT:?}",
                spec.scene
            )),
        }
    }

    pub(super) fn open_frame(
        &mut self,
        s: &proto::StartFrame,
        (dir, manifest): (PathBuf, Manifest),
    ) -> anyhow::Result<OpenedScene<FileSpill>> {
        let spec = s
            .spec
            .as_ref()
            .ok_or_else(|| anyhow::anyhow!("StartFrame without a job spec"))?;
        let frame = job::frame_spec(spec, &manifest.camera).map_err(anyhow::Error::msg)?;
        let samples = job::start_samples(s, frame.spp).map_err(anyhow::Error::msg)?;
        let (view, limits) =
            FrameView::open(&manifest, &frame, s.tile_size, samples).map_err(anyhow::Error::msg)?;
        let grid = view.grid;
        // Keyed by the manifest too: the domains mapped for an older version of the scene in
        // this directory are never traced for the new one (their files were replaced by a
        // rename, so the old mappings stay intact for passes still holding them).
        let scene_key = (dir, manifest.clone());
        if self.cache.as_ref().is_none_or(|(key, _)| *key != scene_key) {
            if self.cache.is_some() {
                info!(scene = %spec.scene, "scene changed on disk: opening it afresh");
            }
            // What the old cache did since the last count is counted before it goes.
            self.count_cache();
            self.cache_counted = CacheCounters::default();
            let cache = DomainCache::new(&scene_key.0, &manifest, self.config.cache_bytes)
                .with_storage(self.config.storage);
            self.cache = Some((scene_key, Arc::new(Mutex::new(cache))));
        } else {
            self.with_cache(|cache| {
                cache.pin([]);
                if spec.cold_cache {
                    cache.clear();
                }
            });
        }
        // Loading from peers is the job's choice; this worker serves its loaded domains to
        // the frame's other workers only when the job asks for it.
        let from_peers = spec.peer_domains.then(|| self.domains.loads.clone());
        self.domains.hints.set_frame(&s.job_id);
        let shelf = self.with_cache(|cache| {
            cache.set_peers(from_peers);
            cache.shelf()
        });
        self.domains.serving.set(
            shelf
                .filter(|_| spec.peer_domains)
                .map(|sh| (s.job_id.clone(), sh)),
        );
        let spill = FileSpill::new(&self.config.spill_dir)
            .with_context(|| format!("spill directory {}", self.config.spill_dir.display()))?;
        let queues = DomainQueues::new(
            manifest.domains.len(),
            self.config.queue_bytes,
            self.config.spill_bytes,
            spill,
        );
        let (domain_bytes, resident, cache_at_start) = self
            .with_cache(|c| (c.domain_bytes(), c.resident(), c.counters()))
            .unwrap_or_default();
        self.frame = Some(OpenFrame {
            job_id: s.job_id.clone(),
            view: Arc::new(view),
            cache_at_start,
            cpu_at_start: self.cpu_now(),
            pass_waits: std::time::Duration::ZERO,
            pass_start_waits: std::time::Duration::ZERO,
        });
        Ok(OpenedScene {
            grid,
            spp: samples.count,
            limits,
            domain_bytes,
            resident,
            queues,
        })
    }
}

/// Why a pass failed: this worker could not load a domain, unless the scene's manifest on
/// disk is no longer the one the frame opened (the scene was re-prepared in place). Runs on
/// the pass's blocking thread, never the runtime; the manifest is re-read on a thread of its
/// own and waited for at most [`SCENE_READ_TIMEOUT`], so storage that hangs (a manifest
/// replaced by a FIFO, a dead mount) still ends the pass: the frame is declined, not stalled.
pub(super) fn pass_failed((dir, manifest): &SceneKey, e: String) -> PassFailed {
    let (tx, rx) = std::sync::mpsc::channel();
    let reread = dir.clone();
    std::thread::spawn(move || {
        let _ = tx.send(Manifest::load(&reread).ok());
    });
    match rx.recv_timeout(SCENE_READ_TIMEOUT) {
        Ok(now) if now.as_ref() == Some(manifest) => PassFailed::Load(e),
        Ok(_) => PassFailed::SceneReplaced(format!(
            "scene {} was replaced on disk while its frame ran (re-prepared in place?): \
             {e}; submit the job again to render the new version",
            dir.display()
        )),
        Err(_) => PassFailed::Load(format!(
            "{e}; the scene's manifest {} could not be re-read within {SCENE_READ_TIMEOUT:?}",
            dir.join(rayfarm_core::scene::MANIFEST_FILE).display()
        )),
    }
}
