//! How long things take in virtual time. The model is deliberately simple and stated in the
//! README: a domain load costs a fixed latency plus its bytes over the storage bandwidth; a
//! pass costs its traced segments and issued camera rays over the worker's threads; a
//! message costs its link's latency plus its bytes over the bandwidth (`net`). Nothing else
//! takes time (the coordinator's and the machines' own work is free).

use std::time::Duration;

use rayfarm_core::render::KernelCounters;

/// The cost model. See the module documentation.
#[derive(Clone, Copy, Debug)]
pub struct CostModel {
    /// Fixed cost of opening and mapping one domain file.
    pub load_latency: Duration,
    /// Storage bandwidth a load reads at, bytes per second.
    pub load_bytes_per_second: u64,
    /// One ray segment traced against a domain, on one thread.
    pub segment: Duration,
    /// One camera ray generated and routed, on one thread.
    pub primary: Duration,
    /// Tracing threads per worker.
    pub threads: u32,
}

impl Default for CostModel {
    /// Figures of this project's machines: a shared disk of 500 MB/s with 2 ms to open a
    /// domain, and about 2 M segments per second per core (`NOTES.md`, coherent rays).
    fn default() -> Self {
        CostModel {
            load_latency: Duration::from_millis(2),
            load_bytes_per_second: 500_000_000,
            segment: Duration::from_nanos(500),
            primary: Duration::from_nanos(100),
            threads: 1,
        }
    }
}

impl CostModel {
    /// Virtual time of `loads` domain loads of `bytes` in all.
    pub fn loads(&self, loads: u64, bytes: u64) -> Duration {
        self.load_latency * loads as u32
            + Duration::from_nanos(
                (u128::from(bytes) * 1_000_000_000 / u128::from(self.load_bytes_per_second.max(1)))
                    as u64,
            )
    }

    /// Virtual time of a pass that did the work of `c`, its loads aside.
    pub fn pass(&self, c: &KernelCounters) -> Duration {
        let work = self.segment.as_nanos() as u64 * c.segments()
            + self.primary.as_nanos() as u64 * c.primary_rays;
        Duration::from_nanos(work / u64::from(self.threads.max(1)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pass_costs_its_segments_over_its_threads_and_a_load_its_bytes() {
        let m = CostModel {
            threads: 2,
            ..CostModel::default()
        };
        let c = KernelCounters {
            radiance_segments: 3000,
            shadow_segments: 1000,
            primary_rays: 2000,
            ..KernelCounters::default()
        };
        // (4000 x 500 ns + 2000 x 100 ns) / 2 threads.
        assert_eq!(m.pass(&c), Duration::from_micros(1100));
        assert_eq!(m.loads(2, 1_000_000), Duration::from_millis(6));
    }
}
