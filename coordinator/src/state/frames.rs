//! A frame's preparation, off the lock: its scene's manifest read again (it may have changed
//! since the job was submitted), the frame checked against it, its film file created.

use rayfarm_core::tile::{TILE_SIZE, TileGrid};
use rayfarm_machine::coordinator::cluster::OpenedFrame;

use super::*;

/// How long a frame's start waits for its scene's manifest.
const FRAME_SCENE_READ_TIMEOUT: Duration = Duration::from_secs(10);

impl Coordinator {
    /// `scene`'s manifest, read on a thread of its own and waited for at most `limit`: a
    /// read stuck on storage fails the job with a clear error instead of holding the queue
    /// (no other frame starts while one is prepared). The stuck thread is left to its read.
    fn read_scene_within(
        self: &Arc<Self>,
        scene: &str,
        limit: Duration,
    ) -> Result<Manifest, Status> {
        let (tx, rx) = std::sync::mpsc::channel();
        let (this, name) = (self.clone(), scene.to_string());
        std::thread::Builder::new()
            .name("read-scene".into())
            .spawn(move || {
                let _ = tx.send(this.open_scene(&name).map(|(_, manifest)| manifest));
            })
            .map_err(|e| Status::unavailable(format!("no thread to read the scene: {e}")))?;
        rx.recv_timeout(limit).unwrap_or_else(|_| {
            warn!(scene, "scene read at frame start timed out");
            Err(Status::deadline_exceeded(format!(
                "scene {scene:?}: its manifest could not be read within {limit:?} at the \
                 frame's start"
            )))
        })
    }

    /// Job `id`'s frame of `spec`, ready to start: its film (and previews of it) for the
    /// shell, what the machine needs of the scene.
    pub(super) fn prepare_frame(
        self: &Arc<Self>,
        id: &str,
        spec: proto::JobSpec,
    ) -> Result<(Running, OpenedFrame), Status> {
        let manifest = self.read_scene_within(&spec.scene, FRAME_SCENE_READ_TIMEOUT)?;
        let frame = frame_spec(&spec, &manifest.camera).map_err(Status::invalid_argument)?;
        let grid = TileGrid::new(frame.width, frame.height, TILE_SIZE)
            .ok_or_else(|| Status::invalid_argument("the image does not fit the tile grid"))?;
        let film = results::create_film(&self.config.data_dir, id, grid, frame.spp)
            .map_err(|e| Status::internal(format!("{e:#}")))?;
        let film = Arc::new(film);
        let previews = Arc::new(Previews::new(&film, 0));
        let opened = OpenedFrame {
            frame,
            domain_bytes: manifest.domains.iter().map(|d| d.bytes).collect(),
        };
        Ok((Running { film, previews }, opened))
    }
}
