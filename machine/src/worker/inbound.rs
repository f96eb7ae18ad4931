//! What the worker machine does with a peer's bundle: hold it for a frame not started yet
//! (see `early`), or check it against the frame's ranges and route its rays or settle its
//! verdicts. The shell decoded it once already (see [`Payload`]); nothing is decoded here.

use std::collections::BTreeMap;

use rayfarm_core::ray::RayRecord;
use rayfarm_core::wire::{self, VerdictRecord};
use tracing::{debug, error, warn};

use super::events::Payload;
use super::machine::Worker;
use super::queues::RaySpill;

impl<S: RaySpill> Worker<S> {
    /// Holds a bundle for a frame not started here yet, within the cap.
    fn hold_early(&mut self, sender: String, job_id: String, payload: Payload) {
        for (job, bundles) in self.early.expire(self.now) {
            warn!(
                %job, bundles,
                "dropping bundles for a frame that did not start here within {:?}",
                self.config.early_timeout
            );
        }
        // Sender and job ids were bounded by the shell (`MAX_FIELD_BYTES`) before they came.
        let held = self
            .early
            .hold(job_id.clone(), (sender.clone(), payload), self.now);
        if let Err(refused) = held {
            error!(
                %sender, job = %job_id, bytes = refused.bytes, held = refused.held,
                "dropping a bundle for a frame not started here: {} bytes are held already",
                self.config.early_bytes
            );
        }
    }

    pub(super) fn peer_bundle(&mut self, sender: String, job_id: String, payload: Payload) {
        debug!(%sender, verdicts = matches!(payload, Payload::Verdicts(_)), "bundle taken");
        let Some(frame) = self.frame.as_mut().filter(|f| f.job_id == job_id) else {
            if !self.ended.contains(&job_id) {
                self.hold_early(sender, job_id, payload);
            }
            return;
        };
        let batches = match payload {
            Payload::Verdicts(batches) => return self.peer_verdicts(&sender, batches),
            Payload::Rays(batches) => batches,
        };
        let mut forward: BTreeMap<String, Vec<RayRecord>> = BTreeMap::new();
        for rays in batches {
            if let Err(e) = wire::check_ray_ranges(&rays, &frame.limits) {
                error!(%sender, error = %e, "dropping a ray batch outside the frame from a peer");
                continue;
            }
            frame.counters.rays_received += rays.len() as u64;
            let rays = match frame.set_aside_newer(rays, self.config.ahead_bytes) {
                Ok(rays) => rays,
                Err(full) => return self.decline_frame(full.to_string()),
            };
            match frame.route(rays) {
                Ok(out) => {
                    for (peer, mut rays) in out {
                        forward.entry(peer).or_default().append(&mut rays);
                    }
                }
                Err(e) => return self.queue_failed(e),
            }
        }
        for (peer, rays) in forward {
            self.send_rays(peer, &rays);
        }
    }

    /// Verdicts from a peer for rays born here.
    fn peer_verdicts(&mut self, sender: &str, batches: Vec<Vec<VerdictRecord>>) {
        let Some(frame) = self.frame.as_mut() else {
            return;
        };
        if frame.speculation().is_none() {
            warn!(%sender, "dropping verdicts: this frame places no rays speculatively");
            return;
        }
        for verdicts in batches {
            match wire::check_verdict_ranges(&verdicts, &frame.limits) {
                Ok(()) => {
                    frame.settle(&verdicts);
                }
                Err(e) => error!(%sender, error = %e, "dropping a verdict batch outside the frame"),
            }
        }
        // Rays whose window ended clear go on to their next window's domains.
        let next = frame.take_next_windows();
        if next.is_empty() {
            return;
        }
        match frame.route(next) {
            Ok(out) => {
                for (peer, rays) in out {
                    self.send_rays(peer, &rays);
                }
            }
            Err(e) => self.queue_failed(e),
        }
    }
}
