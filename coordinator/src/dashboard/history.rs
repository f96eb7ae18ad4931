//! The figures the dashboard's charts draw, sampled once a second from the coordinator's
//! state: the running frame's rays per second and, per worker, rays per second (from the
//! segments its heartbeats count), domain loads and queue bytes. The last
//! [`KEPT_SAMPLES`] samples are kept, so memory stays bounded however long the coordinator
//! runs.

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::state::Coordinator;

/// Time between samples.
const PERIOD: Duration = Duration::from_secs(1);
/// Samples kept: five minutes.
const KEPT_SAMPLES: usize = 300;

/// One worker's figures at one sample.
#[derive(Clone, Serialize)]
pub struct WorkerSample {
    pub worker_id: String,
    pub rays_per_second: f64,
    pub domain_loads: u64,
    pub queue_bytes: u64,
}

/// The cluster at one moment.
#[derive(Clone, Serialize)]
pub struct Sample {
    pub unix_ms: i64,
    /// The running frame's rate (0 without one).
    pub rays_per_second: f64,
    pub workers: Vec<WorkerSample>,
}

/// See the module documentation.
pub struct History {
    inner: Mutex<Inner>,
}

#[derive(Default)]
struct Inner {
    samples: VecDeque<Sample>,
    /// Each worker's ray segments at the last sample, and when.
    last: BTreeMap<String, (u64, Instant)>,
}

impl History {
    /// Starts sampling `coordinator` on the current runtime.
    pub fn start(coordinator: Arc<Coordinator>) -> Arc<Self> {
        let history = Arc::new(History {
            inner: Mutex::new(Inner::default()),
        });
        let weak = Arc::downgrade(&history);
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(PERIOD);
            loop {
                tick.tick().await;
                let Some(history) = weak.upgrade() else {
                    return;
                };
                history.sample(&coordinator);
            }
        });
        history
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn sample(&self, coordinator: &Coordinator) {
        let status = coordinator.status();
        let rays_per_second = if status.running_job_id.is_empty() {
            0.0
        } else {
            coordinator
                .progress(&status.running_job_id)
                .map_or(0.0, |p| p.rays_per_second)
        };
        let now = Instant::now();
        let mut inner = self.lock();
        let mut workers = Vec::with_capacity(status.workers.len());
        let mut last = BTreeMap::new();
        for w in status.workers {
            let rate = match inner.last.get(&w.worker_id) {
                Some(&(segments, at)) if w.ray_segments >= segments => {
                    (w.ray_segments - segments) as f64 / now.duration_since(at).as_secs_f64()
                }
                _ => 0.0,
            };
            last.insert(w.worker_id.clone(), (w.ray_segments, now));
            workers.push(WorkerSample {
                worker_id: w.worker_id,
                rays_per_second: rate,
                domain_loads: w.domain_loads,
                queue_bytes: w.queue_bytes,
            });
        }
        inner.last = last;
        inner.samples.push_back(Sample {
            unix_ms: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_millis() as i64),
            rays_per_second,
            workers,
        });
        while inner.samples.len() > KEPT_SAMPLES {
            inner.samples.pop_front();
        }
    }

    /// The samples kept, oldest first.
    pub fn samples(&self) -> Vec<Sample> {
        self.lock().samples.iter().cloned().collect()
    }

    /// A worker's rays per second at the latest sample (0 if it has none yet).
    pub fn worker_rate(&self, worker_id: &str) -> f64 {
        let inner = self.lock();
        inner
            .samples
            .back()
            .and_then(|s| s.workers.iter().find(|w| w.worker_id == worker_id))
            .map_or(0.0, |w| w.rays_per_second)
    }
}
