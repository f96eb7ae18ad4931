//! Bundles that arrive for a frame this worker has not started yet. Peers run ahead of this
//! worker's StartFrame by a round trip at most, so such bundles are held, within a byte cap
//! and for a time, and replayed when the frame starts; past either, a peer is sending for a
//! frame that will not come, and its bundles are dropped.

use std::collections::BTreeMap;
use std::time::Duration;

use super::events::Payload;
use crate::Time;

/// One held bundle: its sender and contents.
pub type HeldBundle = (String, Payload);

/// Bundles that arrived for one job.
struct Held {
    /// When the first arrived.
    since: Time,
    /// Every byte they hold, ids and bookkeeping included (see [`cost`]).
    bytes: usize,
    bundles: Vec<HeldBundle>,
}

/// See the module documentation.
pub struct EarlyBundles {
    cap_bytes: usize,
    timeout: Duration,
    jobs: BTreeMap<String, Held>,
    /// Sum of `bytes` over `jobs`, kept up to date (never recounted per bundle).
    bytes: usize,
}

/// Why a bundle was not held.
#[derive(Debug, PartialEq, Eq)]
pub struct Refused {
    /// What holding it would have cost.
    pub bytes: usize,
    /// What is held already.
    pub held: usize,
}

/// What holding one bundle costs: its records, its sender and job ids, and the per-batch and
/// per-bundle bookkeeping.
fn cost(sender: &str, job_id: &str, payload: &Payload) -> usize {
    payload.bytes() + sender.len() + job_id.len() + std::mem::size_of::<HeldBundle>()
}

impl EarlyBundles {
    /// Holds at most `cap_bytes` in all, each job's for at most `timeout` after its first.
    pub fn new(cap_bytes: usize, timeout: Duration) -> Self {
        EarlyBundles {
            cap_bytes,
            timeout,
            jobs: BTreeMap::new(),
            bytes: 0,
        }
    }

    /// Bytes held now.
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// Holds a bundle for `job_id`, unless that would pass the cap.
    pub fn hold(&mut self, job_id: String, bundle: HeldBundle, now: Time) -> Result<(), Refused> {
        // A job's first early bundle also pays for its id as the map's key.
        let key_bytes = if self.jobs.contains_key(&job_id) {
            0
        } else {
            job_id.len()
        };
        let bytes = cost(&bundle.0, &job_id, &bundle.1) + key_bytes;
        if self.bytes + bytes > self.cap_bytes {
            return Err(Refused {
                bytes,
                held: self.bytes,
            });
        }
        let held = self.jobs.entry(job_id).or_insert_with(|| Held {
            since: now,
            bytes: 0,
            bundles: Vec::new(),
        });
        held.bytes += bytes;
        self.bytes += bytes;
        held.bundles.push(bundle);
        Ok(())
    }

    /// Removes and returns the bundles held for `job_id`, in order of arrival.
    pub fn take(&mut self, job_id: &str) -> Vec<HeldBundle> {
        let Some(held) = self.jobs.remove(job_id) else {
            return Vec::new();
        };
        self.bytes -= held.bytes;
        held.bundles
    }

    /// Drops the bundles of jobs whose first came more than the timeout before `now`;
    /// returns each such job with the number of bundles dropped.
    pub fn expire(&mut self, now: Time) -> Vec<(String, usize)> {
        let expired: Vec<String> = self
            .jobs
            .iter()
            .filter(|(_, h)| now.since(h.since) > self.timeout)
            .map(|(job, _)| job.clone())
            .collect();
        expired
            .into_iter()
            .map(|job| {
                let n = self.take(&job).len();
                (job, n)
            })
            .collect()
    }
}
