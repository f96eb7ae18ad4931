//! Passes and prefetches on their threads: a pass straight onto the tracing pool, a prefetch
//! on a blocking thread that holds the cache's lock only to decide and to add; each ends
//! with an event on the engine's own channel.

use std::time::Instant;

use rayfarm_machine::pass::PassInput;
use rayfarm_machine::worker::{self as machine, PassFailed};

use super::scene::pass_failed;
use super::{Engine, Event, lock};
use crate::pass;

impl Engine {
    /// Tells the fetcher who holds `domain` now, before a load of it may ask them.
    fn offer_holders(&self, domain: u32) {
        if let Some(frame) = self.machine.frame() {
            self.domains
                .hints
                .set_holders(domain, &frame.plan().holders_of(domain));
        }
    }

    pub(super) fn start_pass(&mut self, job_id: String, work: machine::PassWork) {
        if let Some((domain, _)) = &work.trace {
            self.offer_holders(*domain);
        }
        let events = self.done.clone();
        let (Some(frame), Some((scene, cache))) = (
            self.frame.as_ref().filter(|f| f.job_id == job_id),
            &self.cache,
        ) else {
            // Never: the machine runs passes only of the frame opened last.
            let result = Err(PassFailed::Load("no scene open for the pass".to_string()));
            let finished = Instant::now();
            let _ = events.send(Event::PassDone {
                job_id,
                result,
                finished,
                start_wait: std::time::Duration::ZERO,
            });
            return;
        };
        let input = PassInput {
            frame: frame.view.clone(),
            work,
            cache: cache.clone(),
        };
        let scene = scene.clone();
        // Straight onto the tracing pool: one thread hand-over per pass, not two (a blocking
        // thread waiting in `install`), which on a machine with fewer cores than busy threads
        // costs a scheduler slice each.
        let handed = Instant::now();
        self.pool.spawn(move || {
            let start_wait = handed.elapsed();
            // A panicking pass must not abort the process (rayon's default for a spawned
            // job) nor leave the machine waiting for it: it declines the frame like a pass
            // that could not load its domain.
            let result =
                match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| pass::run(input))) {
                    Ok(r) => r.map_err(|e| pass_failed(&scene, e.to_string())),
                    Err(_) => Err(PassFailed::Load("the pass panicked".to_string())),
                };
            // The engine may be gone at shutdown; nothing is left to do then.
            let finished = Instant::now();
            let _ = events.send(Event::PassDone {
                job_id,
                result,
                finished,
                start_wait,
            });
        });
    }

    /// Loads `domain` ahead of need on a blocking thread, beside any pass: the cache decides
    /// under its lock whether it fits without evicting `keep`, the read (mapping, checksum,
    /// emulated storage) runs off the lock, so passes go on using the cache meanwhile.
    pub(super) fn prefetch(&mut self, job_id: String, domain: u32, keep: Vec<u32>) {
        self.offer_holders(domain);
        let events = self.done.clone();
        let Some((_, cache)) = &self.cache else {
            let result = Err("no scene open for the prefetch".to_string());
            let _ = events.send(Event::PrefetchDone {
                job_id,
                domain,
                result,
            });
            return;
        };
        let cache = cache.clone();
        let keep: std::collections::BTreeSet<u32> = keep.into_iter().collect();
        tokio::task::spawn_blocking(move || {
            let pending = lock(&cache).begin_prefetch(domain, &keep);
            let result = match pending.map(|p| p.read()) {
                None => Ok(false),
                Some(Ok(loaded)) => Ok(lock(&cache).finish_prefetch(loaded, &keep)),
                Some(Err(e)) => Err(e.to_string()),
            };
            let _ = events.send(Event::PrefetchDone {
                job_id,
                domain,
                result,
            });
        });
    }
}
