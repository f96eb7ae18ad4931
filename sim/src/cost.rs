//! How long computing takes in virtual time: a pass costs a fixed overhead plus its radiance
//! segments, shadow segments, camera samples and volume samples, each at its own price, over
//! the worker's threads; a planning round of the coordinator costs what its kind follows
//! (`rayfarm_machine::coordinator::PlanningWork`): an incremental round (someone busy) a fixed
//! part plus a part per member planned (and per member planned per domain), per member of the
//! cluster and per domain (a dry member it leaves as it was costs it nothing); every queue
//! report taken in, round or not, a part of its own and a part per queue it names; a round
//! planned from the whole cluster (barrier rounds, or nobody busy) a part per member and per
//! domain at the whole-cluster planner's prices; a holders flush (`FlushWork`) a fixed part,
//! a part per member of the frame and per holder line it made. The prices are measured on a
//! machine by `rayfarm sim calibrate` (`calibrate`) and kept in a TOML file
//! ([`ComputeCost::load`]); the defaults are one such measurement. Loads are priced by the shared storage (`storage`), messages by the network
//! (`net`).

use std::path::Path;
use std::time::Duration;

use rayfarm_core::render::KernelCounters;
use rayfarm_machine::coordinator::{FlushWork, PlanningWork};
use serde::{Deserialize, Serialize};

/// Prices of computing, in nanoseconds of one core. See the module documentation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ComputeCost {
    /// Fixed cost of one pass (setting it up, sorting its rays, handing its output back).
    pub pass_ns: f64,
    /// One radiance-ray segment traced against a domain.
    pub radiance_segment_ns: f64,
    /// One shadow-ray segment traced against a domain.
    pub shadow_segment_ns: f64,
    /// One camera sample generated and routed to its first domain.
    pub camera_sample_ns: f64,
    /// One volume sample interpolated and composited.
    pub volume_sample_ns: f64,
    /// Fixed cost of one incremental planning round of the coordinator (someone busy: only
    /// the members that ran dry are planned).
    pub round_ns: f64,
    /// An incremental round's cost per member it plans (each ran dry).
    pub round_planned_ns: f64,
    /// An incremental round's cost per member it plans per domain of the scene: planning a
    /// member costs more in a larger cluster (deeper ordered sets, more holders and queues
    /// to look through; coord17: 0.03 ms at 128 members, 0.35 ms at 4,096). Files calibrated
    /// before this price was measured read as zero.
    #[serde(default)]
    pub round_planned_domain_ns: f64,
    /// Per queue a report taken in names (`PlanningWork::queues`): taking the report in and
    /// moving its rays follow its size. Files calibrated before this price was measured read
    /// as zero (their per-member price had reports of 16 queues in it).
    #[serde(default)]
    pub round_queue_ns: f64,
    /// Per queue report taken in (`PlanningWork::reports`), whether or not a round followed:
    /// its message and its member's figures. Files calibrated before this price was measured
    /// read as zero (a report was then free unless it planned something).
    #[serde(default)]
    pub report_ns: f64,
    /// An incremental round's cost per member of the cluster (the holders map is rebuilt from
    /// every member's plan).
    pub round_member_ns: f64,
    /// An incremental round's cost per domain of the scene.
    pub round_domain_ns: f64,
    /// Fixed cost of a round planned from the whole cluster (a barrier round, or an
    /// asynchronous one with nobody busy: every member planned).
    pub whole_round_ns: f64,
    /// A whole-cluster round's cost per member.
    pub whole_round_member_ns: f64,
    /// A whole-cluster round's cost per domain.
    pub whole_round_domain_ns: f64,
    /// Fixed cost of one holders flush of the coordinator (busy members told the holders
    /// changed since the last, `RunningFrame::flush_holders`). Files calibrated before flushes
    /// were priced read as zero.
    #[serde(default)]
    pub flush_ns: f64,
    /// A flush's cost per member of the frame (each is walked, and told or passed over).
    #[serde(default)]
    pub flush_member_ns: f64,
    /// A flush's cost per holder line made (each view class's and state's lines once, shared
    /// by the members told them).
    #[serde(default)]
    pub flush_line_ns: f64,
    /// Sending one peer bundle, per bundle: the sender encoding its rays and its half of the
    /// gRPC stream (protobuf, HTTP/2, the socket).
    pub bundle_send_ns: f64,
    /// Sending a peer bundle, per byte of its batches.
    pub bundle_send_byte_ns: f64,
    /// Receiving one peer bundle, per bundle: the receiver's half of the gRPC stream,
    /// decoding its batches, the worker machine queueing them, the acknowledgement.
    pub bundle_receive_ns: f64,
    /// Receiving a peer bundle, per byte of its batches.
    pub bundle_receive_byte_ns: f64,
    /// A worker's shell taking a finished pass's output (the machine routing it), per pass.
    /// Files calibrated before this price was measured read as zero.
    #[serde(default)]
    pub finished_pass_ns: f64,
    /// Taking a finished pass's output, per ray sent on (queued here or bundled for a peer).
    #[serde(default)]
    pub finished_ray_ns: f64,
    /// Taking a finished pass's output, per domain along the rays born in it (speculative:
    /// the domains their copies go to, window by window).
    #[serde(default)]
    pub finished_path_domain_ns: f64,
    /// Taking a finished pass's output, per verdict addressed.
    #[serde(default)]
    pub finished_verdict_ns: f64,
}

impl Default for ComputeCost {
    /// `rayfarm sim calibrate` on this project's 2-core VM (the file `sim/calibration.toml`,
    /// rounded; the command is in it and in README "Simulator"). Volume samples were not in
    /// that scene: their price is the direct volume benchmark's 14 M samples/s a core (README
    /// "Benchmarks", unlit, skipping on).
    fn default() -> Self {
        ComputeCost {
            pass_ns: 24_300.0,
            radiance_segment_ns: 234.4,
            shadow_segment_ns: 264.2,
            camera_sample_ns: 144.2,
            volume_sample_ns: 71.0,
            round_ns: 4_062.0,
            round_planned_ns: 6_828.1,
            round_planned_domain_ns: 1.144,
            round_queue_ns: 461.5,
            report_ns: 2_204.0,
            round_member_ns: 0.86,
            round_domain_ns: 0.0,
            whole_round_ns: 0.0,
            whole_round_member_ns: 11_991.9,
            whole_round_domain_ns: 1_281.8,
            flush_ns: 24_406.0,
            flush_member_ns: 28.9,
            flush_line_ns: 82.4,
            bundle_send_ns: 3_717.0,
            bundle_send_byte_ns: 0.759,
            bundle_receive_ns: 10_534.0,
            bundle_receive_byte_ns: 1.809,
            finished_pass_ns: 0.0,
            finished_ray_ns: 0.0,
            finished_path_domain_ns: 0.0,
            finished_verdict_ns: 0.0,
        }
    }
}

impl ComputeCost {
    /// Reads a calibration file written by `rayfarm sim calibrate`.
    pub fn load(path: &Path) -> Result<Self, String> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("reading {}: {e}", path.display()))?;
        let c: ComputeCost =
            toml::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?;
        c.check().map_err(|e| format!("{}: {e}", path.display()))?;
        Ok(c)
    }

    /// The file `load` reads back.
    pub fn to_toml(&self) -> String {
        toml::to_string(self).unwrap_or_default()
    }

    /// Refuses prices that are negative, not numbers, or absurd (above a second).
    pub fn check(&self) -> Result<(), String> {
        let all = [
            ("pass_ns", self.pass_ns),
            ("radiance_segment_ns", self.radiance_segment_ns),
            ("shadow_segment_ns", self.shadow_segment_ns),
            ("camera_sample_ns", self.camera_sample_ns),
            ("volume_sample_ns", self.volume_sample_ns),
            ("round_ns", self.round_ns),
            ("round_planned_ns", self.round_planned_ns),
            ("round_planned_domain_ns", self.round_planned_domain_ns),
            ("round_queue_ns", self.round_queue_ns),
            ("report_ns", self.report_ns),
            ("round_member_ns", self.round_member_ns),
            ("round_domain_ns", self.round_domain_ns),
            ("whole_round_ns", self.whole_round_ns),
            ("whole_round_member_ns", self.whole_round_member_ns),
            ("whole_round_domain_ns", self.whole_round_domain_ns),
            ("flush_ns", self.flush_ns),
            ("flush_member_ns", self.flush_member_ns),
            ("flush_line_ns", self.flush_line_ns),
            ("bundle_send_ns", self.bundle_send_ns),
            ("bundle_send_byte_ns", self.bundle_send_byte_ns),
            ("bundle_receive_ns", self.bundle_receive_ns),
            ("bundle_receive_byte_ns", self.bundle_receive_byte_ns),
            ("finished_pass_ns", self.finished_pass_ns),
            ("finished_ray_ns", self.finished_ray_ns),
            ("finished_path_domain_ns", self.finished_path_domain_ns),
            ("finished_verdict_ns", self.finished_verdict_ns),
        ];
        for (name, v) in all {
            if !(0.0..=1e9).contains(&v) {
                return Err(format!("{name} = {v} is not a price in 0..=1e9 ns"));
            }
        }
        Ok(())
    }
}

/// What a worker's shell hands the machine in a finished pass's output: the `finished_*`
/// prices' measures.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FinishedWork {
    /// Rays sent on (queued here or bundled for peers).
    pub rays: usize,
    /// Domains along the rays born in the pass (speculative: where their copies go, window
    /// by window).
    pub path_domains: usize,
    /// Verdicts addressed.
    pub verdicts: usize,
}

impl FinishedWork {
    /// The measures of `out`.
    pub fn of(out: &rayfarm_machine::worker::PassOutput) -> Self {
        FinishedWork {
            rays: out.rays.len(),
            path_domains: out.paths.iter().map(Vec::len).sum(),
            verdicts: out.verdicts.len(),
        }
    }
}

/// The cost model of computing: the prices and the threads of every worker.
#[derive(Clone, Copy, Debug)]
pub struct CostModel {
    pub compute: ComputeCost,
    /// Tracing threads per worker.
    pub threads: u32,
    /// Cores shared by every simulated worker (`--cores`): passes' computing and bundles'
    /// handling are sliced between them (`cores::SharedCores`), as on one machine running the
    /// whole cluster (the validation's `rayfarm bench`); `None`, every worker on machines of
    /// its own.
    pub cores: Option<u32>,
    /// How long a pass waits, after the worker's shell hands it over, for a tracing thread
    /// to start it (`--pass-start-us`): no core time, only delay. Zero by default: a node
    /// with cores of its own wakes its thread in microseconds. Where the whole cluster shares
    /// a few cores (the validation's `rayfarm bench`: nine processes on two), the woken
    /// thread waits for the operating system to give it a core, about a millisecond a pass
    /// (the bench's "pass waiting for a tracing thread").
    pub pass_start: Duration,
    /// How long a peer bundle waits, once its stream has decoded and acknowledged it, for
    /// the worker's engine to take it in (`--bundle-take-us`): no core time, only delay.
    /// Zero by default. Where the whole cluster shares a few cores, the threads that carry a
    /// bundle from one machine to the next wait for cores to wake on: the validation's
    /// cluster took 0.4-3.0 ms on average from a machine's send to the receiver's machine
    /// taking the bundle, where the simulator's network and decoding take about 0.13 at the
    /// default prices and more with the cluster's own (`bench/validation/transit.py` reads
    /// both from debug logs and charges the difference).
    pub bundle_take: Duration,
}

impl Default for CostModel {
    fn default() -> Self {
        CostModel {
            compute: ComputeCost::default(),
            threads: 1,
            cores: None,
            pass_start: Duration::ZERO,
            bundle_take: Duration::ZERO,
        }
    }
}

/// Nanoseconds as a duration, rounded down (never negative).
fn nanos(ns: f64) -> Duration {
    Duration::from_nanos(ns.max(0.0) as u64)
}

impl CostModel {
    /// The single-core time of a pass that did the work of `c`, its loads aside.
    pub fn pass_work_ns(&self, c: &KernelCounters) -> f64 {
        let p = &self.compute;
        p.pass_ns
            + p.radiance_segment_ns * c.radiance_segments as f64
            + p.shadow_segment_ns * c.shadow_segments as f64
            + p.camera_sample_ns * c.primary_rays as f64
            + p.volume_sample_ns * c.volume_samples as f64
    }

    /// Virtual time of a pass that did the work of `c` on the worker's threads, its loads
    /// aside.
    pub fn pass(&self, c: &KernelCounters) -> Duration {
        nanos(self.pass_work_ns(c) / f64::from(self.threads.max(1)))
    }

    /// Virtual time the sender spends on a peer bundle of `bytes` bytes of batches.
    pub fn bundle_send(&self, bytes: usize) -> Duration {
        let p = &self.compute;
        nanos(p.bundle_send_ns + p.bundle_send_byte_ns * bytes as f64)
    }

    /// Virtual time a worker's shell spends taking a finished pass's output of `work`.
    pub fn finished_pass(&self, work: &FinishedWork) -> Duration {
        let p = &self.compute;
        nanos(
            p.finished_pass_ns
                + p.finished_ray_ns * work.rays as f64
                + p.finished_path_domain_ns * work.path_domains as f64
                + p.finished_verdict_ns * work.verdicts as f64,
        )
    }

    /// Virtual time the receiver spends on a peer bundle of `bytes` bytes of batches.
    pub fn bundle_receive(&self, bytes: usize) -> Duration {
        let p = &self.compute;
        nanos(p.bundle_receive_ns + p.bundle_receive_byte_ns * bytes as f64)
    }

    /// Virtual time of the holders flushes `work` counts.
    pub fn flushing(&self, work: &FlushWork) -> Duration {
        let p = &self.compute;
        nanos(
            p.flush_ns * work.flushes as f64
                + p.flush_member_ns * work.members as f64
                + p.flush_line_ns * work.lines as f64,
        )
    }

    /// Virtual time of the planning rounds `work` counts, over a scene of `domains` domains.
    pub fn planning(&self, work: &PlanningWork, domains: usize) -> Duration {
        let p = &self.compute;
        let domains = domains as f64;
        let whole = work.whole_rounds as f64;
        let incremental = work.rounds.saturating_sub(work.whole_rounds) as f64;
        let ns = incremental * (p.round_ns + p.round_domain_ns * domains)
            + (p.round_planned_ns + p.round_planned_domain_ns * domains) * work.planned as f64
            + p.round_queue_ns * work.queues as f64
            + p.report_ns * work.reports as f64
            + p.round_member_ns * work.members as f64
            + whole * (p.whole_round_ns + p.whole_round_domain_ns * domains)
            + p.whole_round_member_ns * work.whole_members as f64;
        nanos(ns)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pass_costs_its_work_over_its_threads_and_a_round_what_it_planned() {
        let m = CostModel {
            threads: 2,
            cores: None,
            pass_start: Duration::ZERO,
            bundle_take: Duration::ZERO,
            compute: ComputeCost {
                pass_ns: 1000.0,
                radiance_segment_ns: 500.0,
                shadow_segment_ns: 250.0,
                camera_sample_ns: 100.0,
                volume_sample_ns: 10.0,
                round_ns: 1000.0,
                round_planned_ns: 100.0,
                round_planned_domain_ns: 0.5,
                round_queue_ns: 7.0,
                report_ns: 11.0,
                round_member_ns: 10.0,
                round_domain_ns: 1.0,
                whole_round_ns: 5000.0,
                whole_round_member_ns: 1000.0,
                whole_round_domain_ns: 50.0,
                flush_ns: 2000.0,
                flush_member_ns: 20.0,
                flush_line_ns: 3.0,
                bundle_send_ns: 2000.0,
                bundle_send_byte_ns: 0.5,
                bundle_receive_ns: 3000.0,
                bundle_receive_byte_ns: 0.25,
                finished_pass_ns: 700.0,
                finished_ray_ns: 10.0,
                finished_path_domain_ns: 5.0,
                finished_verdict_ns: 3.0,
            },
        };
        let c = KernelCounters {
            radiance_segments: 3000,
            shadow_segments: 1000,
            primary_rays: 2000,
            volume_samples: 100,
            ..KernelCounters::default()
        };
        // (1000 + 3000 x 500 + 1000 x 250 + 2000 x 100 + 100 x 10) ns / 2 threads.
        assert_eq!(m.pass(&c), Duration::from_nanos(976_000));
        // Two incremental rounds over 64 members planning 1 and 3 of them: 2 x (1000 + 64 x
        // 10 + 512 x 1) + 4 x (100 + 512 x 0.5) ns; one whole round of 64: 5000 + 64 x 1000 +
        // 512 x 50 ns.
        let work = PlanningWork {
            rounds: 3,
            whole_rounds: 1,
            whole_members: 64,
            planned: 4,
            members: 128,
            queues: 0,
            reports: 0,
        };
        assert_eq!(
            m.planning(&work, 512),
            Duration::from_nanos(4304 + 1424 + 94_600)
        );
        // The reports taken in cost themselves and their queues, rounds or not: 20 reports
        // x 11 ns and 300 queues x 7 ns.
        let reports = PlanningWork {
            queues: 300,
            reports: 20,
            ..work
        };
        assert_eq!(
            m.planning(&reports, 512) - m.planning(&work, 512),
            Duration::from_nanos(220 + 2100)
        );
        // Two flushes of 64 members, 500 lines made in all: 2 x 2000 + 128 x 20 + 500 x 3 ns,
        // whatever the members told (each gets the one message of its class).
        let flushes = FlushWork {
            flushes: 2,
            members: 128,
            told: 100,
            lines: 500,
        };
        assert_eq!(m.flushing(&flushes), Duration::from_nanos(8060));
        // A bundle of 4,000 bytes: 2000 + 2000 ns to send, 3000 + 1000 ns to receive.
        assert_eq!(m.bundle_send(4000), Duration::from_nanos(4000));
        assert_eq!(m.bundle_receive(4000), Duration::from_nanos(4000));
        // A finished pass of 20 rays sent on, 40 path domains and 100 verdicts: 700 + 200 + 200 + 300.
        let work = FinishedWork {
            rays: 20,
            path_domains: 40,
            verdicts: 100,
        };
        assert_eq!(m.finished_pass(&work), Duration::from_nanos(1400));
        // What the rounds planned moves the price, not the cluster's size alone.
        let one = PlanningWork {
            rounds: 1,
            planned: 1,
            members: 64,
            ..PlanningWork::default()
        };
        let many = PlanningWork { planned: 32, ..one };
        assert_eq!(
            m.planning(&many, 512) - m.planning(&one, 512),
            Duration::from_nanos(31 * (100 + 256))
        );
    }

    #[test]
    fn the_defaults_are_the_calibration_files_prices_rounded() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("calibration.toml");
        let file = ComputeCost::load(&path).unwrap();
        let (a, b) = (
            toml::Value::try_from(file).unwrap(),
            toml::Value::try_from(ComputeCost::default()).unwrap(),
        );
        let (a, b) = (a.as_table().unwrap(), b.as_table().unwrap());
        for (name, want) in b {
            let (got, want) = (a[name].as_float().unwrap(), want.as_float().unwrap());
            assert!(
                (got - want).abs() <= 0.005 * want.abs().max(1.0),
                "{name}: the file says {got}, the default {want}"
            );
        }
    }

    #[test]
    fn a_calibration_file_reads_back_and_bad_prices_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.toml");
        let c = ComputeCost {
            shadow_segment_ns: 123.5,
            ..ComputeCost::default()
        };
        std::fs::write(&path, c.to_toml()).unwrap();
        assert_eq!(ComputeCost::load(&path).unwrap(), c);
        let bad = c.to_toml().replace("123.5", "-1.0");
        std::fs::write(&path, bad).unwrap();
        assert!(
            ComputeCost::load(&path)
                .unwrap_err()
                .contains("shadow_segment_ns")
        );
    }
}
