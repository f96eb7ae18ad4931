//! What the worker machine sends to peers: rays and verdicts encoded in batches and handed to
//! the bundler in their tier, and the bundles it lets go turned into `ToPeer` actions. The
//! receiving half is `inbound`.

use std::time::Duration;

use bytes::Bytes;
use rayfarm_core::bundler::{Bundle, PushErrorKind, Tier};
use rayfarm_core::ray::RayRecord;
use rayfarm_core::wire::{self, VerdictRecord};
use tracing::{debug, error};

use super::events::Action;
use super::machine::Worker;
use super::queues::RaySpill;
use crate::Time;

/// Rays per encoded batch sent to a peer (160 KiB).
const BATCH_RAYS: usize = 2048;

impl<S: RaySpill> Worker<S> {
    /// The bundler's clock: the machine's time as a duration since its origin.
    pub(super) fn bundler_now(&self) -> Duration {
        self.now.since(Time::default())
    }

    /// Queues rays for a peer in the bundler's migrated-ray tier.
    pub(super) fn send_rays(&mut self, peer: String, rays: &[RayRecord]) {
        self.send_in_tier(peer, rays, Tier::Migrated);
    }

    /// Queues demand-driven tasks for an idle peer in the bundler's tasks tier.
    pub(super) fn send_tasks(&mut self, peer: String, rays: &[RayRecord]) {
        self.send_in_tier(peer, rays, Tier::Tasks);
    }

    fn send_in_tier(&mut self, peer: String, rays: &[RayRecord], tier: Tier) {
        if let Some(frame) = self.frame.as_mut() {
            frame.counters.rays_sent += rays.len() as u64;
        }
        for chunk in rays.chunks(BATCH_RAYS) {
            self.push_bundled(&peer, tier, Bytes::from(wire::encode_batch(chunk)));
        }
    }

    /// Queues verdicts for a peer in the bundler's results tier (they free its memory).
    pub(super) fn send_verdicts(&mut self, peer: String, verdicts: &[VerdictRecord]) {
        for chunk in verdicts.chunks(BATCH_RAYS) {
            let msg = Bytes::from(wire::encode_verdicts(chunk));
            self.push_bundled(&peer, Tier::Results, msg);
        }
    }

    fn push_bundled(&mut self, peer: &String, tier: Tier, mut msg: Bytes) {
        if let Some(frame) = self.frame.as_mut() {
            frame.counters.bytes_sent += msg.len() as u64;
        }
        loop {
            match self
                .bundler
                .push(peer.clone(), tier, msg, self.bundler_now())
            {
                Ok(()) => break,
                Err(e) if matches!(e.kind, PushErrorKind::PeerFull { .. }) => {
                    // The peer's bulk queue is full: send what it holds, then retry.
                    let bundles = self.bundler.flush_peer(peer);
                    self.send_bundles(bundles);
                    msg = e.into_message();
                }
                Err(e) => {
                    error!(%peer, error = %e, "batch refused by the bundler");
                    break;
                }
            }
        }
    }

    pub(super) fn send_due_bundles(&mut self) {
        let bundles = self.bundler.poll(self.bundler_now());
        self.send_bundles(bundles);
    }

    pub(super) fn send_bundles(&mut self, bundles: Vec<Bundle<String>>) {
        let Some(job_id) = self.frame.as_ref().map(|f| &f.job_id) else {
            return;
        };
        for b in bundles {
            debug!(peer = %b.peer, tier = ?b.tier, bytes = b.bytes, "bundle sent");
            self.actions.push(Action::ToPeer {
                peer: b.peer,
                job_id: job_id.clone(),
                tier: b.tier,
                batches: b.messages,
            });
        }
    }
}
