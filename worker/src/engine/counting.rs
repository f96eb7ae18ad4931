//! What the engine adds to the worker's metrics (passes, the cache's loads) and the CPU
//! clocks a frame's statistics count from.

use rayfarm_machine::worker::PassOutput;
use rayfarm_node::cpu::process_cpu_seconds;
use rayfarm_node::metrics;

use super::Engine;

impl Engine {
    /// The tracing pool's and the whole process's CPU seconds so far.
    pub(super) fn cpu_now(&self) -> (f64, f64) {
        (self.trace_clocks.seconds(), process_cpu_seconds())
    }

    /// Adds what the cache did since the last call to the metrics (after each pass and at
    /// a frame's end: loads and evictions happen in passes and on the machine's orders).
    pub(super) fn count_cache(&mut self) {
        let Some(now) = self.with_cache(|c| c.counters()) else {
            return;
        };
        let d = now.since(&self.cache_counted);
        let m = metrics::worker();
        m.domain_loads.inc_by(d.loads);
        m.domain_load_bytes.inc_by(d.bytes_loaded);
        m.domain_evictions.inc_by(d.evictions);
        m.domain_load_seconds.inc_by(d.load_nanos as f64 / 1e9);
        m.domain_load_bytes_from_peers.inc_by(d.bytes_from_peers);
        m.domain_peer_failures.inc_by(d.peer_failures);
        self.cache_counted = now;
    }
}

/// Adds a finished pass's rays and time to the metrics.
pub(super) fn count_pass(output: &PassOutput) {
    let (m, c) = (metrics::worker(), &output.counters);
    m.passes.inc();
    m.busy_seconds.inc_by(output.busy.as_secs_f64());
    m.radiance_segments.inc_by(c.radiance_segments);
    m.shadow_segments.inc_by(c.shadow_segments);
    for (counter, n) in m.rays_created.iter().zip([
        c.primary_rays,
        c.shadow_rays,
        c.bounce_rays,
        c.reflection_rays,
    ]) {
        counter.inc_by(n);
    }
}
