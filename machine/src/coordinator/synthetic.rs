//! A coordinator at the papers' scale in its steady state, for measuring what one asynchronous
//! round costs the real machine: the whole [`Coordinator`] (the one `rayfarm-coordinator` and
//! the simulator drive) running a dynamic frame on `workers` registered workers over `domains`
//! domains, every member planned once already, then members running dry one after another.
//! `rayfarm sim calibrate` prices the simulator's rounds by timing these, and the `rounds`
//! benchmark of this crate times the same ones, so both measure what the coordinator does with
//! a report: taking it in, planning the dry members, the holders' deltas by view class, the
//! messages, the tallies and the progress.
//!
//! Reports follow `schedule::synthetic`: every member's cache holds two domains of
//! [`DOMAIN_BYTES`], and it reports rays queued for [`QUEUED`] domains drawn from a fixed hash,
//! so every run plans the same rounds.

use std::collections::{BTreeMap, HashMap};
use std::time::Duration;

use rayfarm_core::render::local::FrameSpec;
use rayfarm_core::sampling::mix64;
use rayfarm_core::schedule::dynamic::{DEFAULT_COPY_RAYS, Options};
use rayfarm_core::schedule::synthetic::{DOMAIN_BYTES, QUEUED, RESIDENT};
use rayfarm_proto::{
    self as proto, PROTOCOL_VERSION, Schedule, coordinator_message::Body,
    worker_message::Body as FromWorker,
};

use super::cluster::{Action, Config, Coordinator, Input, OpenedFrame, Tally};
use super::{FlushWork, PlanningWork, Rounds};
use crate::Time;

/// Virtual time between two reports: about what 1,024 simulated workers gave (2,600 rounds a
/// virtual second, README "Simulator"), so holders flushes come as often among the rounds.
const REPORT_GAP: Duration = Duration::from_micros(400);

/// The coordinator in its steady state, and what its members were last told to work on.
pub struct SteadyFrame {
    pub coordinator: Coordinator,
    job_id: String,
    domains: u32,
    keys: Vec<u32>,
    /// By member: the round of its latest plan and the domains it works on.
    plans: HashMap<u32, (u64, Vec<u32>)>,
    /// Reports made so far (the next member to run dry, and the hash's input).
    reports: u64,
    /// Domains each report has rays queued for ([`QUEUED`] unless set).
    report_queues: usize,
    now: Time,
}

impl SteadyFrame {
    /// A coordinator running a dynamic frame (asynchronous rounds, free cache slots filled,
    /// busy members told the holders at most every `holders_interval`) on `workers` workers
    /// over `domains` domains, each member having reported and been planned once.
    pub fn new(workers: u32, domains: u32, holders_interval: Duration) -> SteadyFrame {
        let config = Config {
            heartbeat: Duration::from_secs(3600),
            worker_timeout: Duration::from_secs(36_000),
            report_timeout: Duration::from_secs(5),
            schedule_options: Options {
                replicate_onto_idle: false,
                fill_free_slots: true,
                copy_rays: DEFAULT_COPY_RAYS,
            },
            rounds: Rounds::Async,
            holders_interval,
            report_hold: super::cluster::ReportHold::DEFAULT,
            max_attempts: 3,
            max_jobs_per_user: 16,
            max_pixel_samples_per_user: u64::MAX,
            unix_origin_ms: 0,
        };
        let mut s = SteadyFrame {
            coordinator: Coordinator::new(config, 0),
            job_id: String::new(),
            domains: domains.max(1),
            keys: Vec::new(),
            plans: HashMap::new(),
            reports: 0,
            report_queues: QUEUED,
            now: Time(0),
        };
        for w in 0..workers {
            let id = format!("w{w}");
            let r = proto::Register {
                protocol_version: PROTOCOL_VERSION,
                worker_id: id.clone(),
                peer_address: format!("{id}:7000"),
                cache_bytes: RESIDENT as u64 * DOMAIN_BYTES,
                threads: 1,
            };
            if let Ok((key, actions)) = s.coordinator.register(s.now, &r) {
                s.keys.push(key);
                s.follow(actions);
            }
        }
        let frame = FrameSpec {
            width: 256,
            height: 256,
            spp: 1,
            max_depth: 3,
            camera: None,
        };
        let spec = proto::JobSpec {
            scene: "synthetic".into(),
            width: frame.width,
            height: frame.height,
            spp: frame.spp,
            max_depth: frame.max_depth,
            schedule: Schedule::Dynamic as i32,
            ..Default::default()
        };
        let Ok(record) = s.coordinator.submit(s.now, spec, 1, "") else {
            return s;
        };
        s.job_id = record.id().to_string();
        let mut todo = vec![Input::Recorded {
            job_id: s.job_id.clone(),
            result: Ok(()),
        }];
        // The shell's answers: the scene read, the start stored.
        while let Some(input) = todo.pop() {
            let actions = s.coordinator.handle(s.now, input);
            for a in &actions {
                match a {
                    Action::PrepareFrame { job_id, .. } => todo.push(Input::FrameOpened {
                        job_id: job_id.clone(),
                        opened: Ok(OpenedFrame {
                            frame: frame.clone(),
                            domain_bytes: vec![DOMAIN_BYTES; domains as usize],
                        }),
                    }),
                    Action::Persist {
                        barrier: Some(b), ..
                    } => todo.push(Input::Stored { barrier: *b }),
                    _ => {}
                }
            }
            s.follow(actions);
        }
        // Every member reports once (nothing resident yet) and is planned.
        for _ in 0..workers {
            let input = s.next_report();
            s.handle(input);
        }
        s
    }

    /// Members of the frame.
    pub fn members(&self) -> usize {
        self.keys.len()
    }

    /// Reports from now on name `queues` domains with rays queued (a predictive report names
    /// hundreds: speculation copies each new ray into the domains along it).
    pub fn set_report_queues(&mut self, queues: usize) {
        self.report_queues = queues;
    }

    /// The next member in turn runs dry: its report, of its latest plan's round, with the
    /// domains that plan gave it resident and rays queued for [`QUEUED`] domains (or as many
    /// as [`SteadyFrame::set_report_queues`] set).
    pub fn next_report(&mut self) -> Input {
        let n = self.reports;
        self.reports += 1;
        let key = self.keys[(n % self.keys.len().max(1) as u64) as usize];
        let (round, resident) = self.plans.get(&key).cloned().unwrap_or_default();
        let pick = |i: u64| (mix64(n << 20 | i) % u64::from(self.domains)) as u32;
        let queued_rays: BTreeMap<u32, u64> = (0..self.report_queues as u64)
            .map(|i| (pick(i), 1 + mix64(i ^ n) % 10_000))
            .collect();
        Input::WorkerMessage {
            key,
            body: FromWorker::QueueReport(proto::QueueReport {
                job_id: self.job_id.clone(),
                round,
                resident_domains: resident,
                queued_rays,
                ..Default::default()
            }),
        }
    }

    /// The next member in turn reports while it works (a delta naming one queue changed, of
    /// a round before its plan's, so no round plans it): what a report costs the coordinator
    /// when no round follows (`PlanningWork::reports`). Every member must have reported
    /// whole once (as [`SteadyFrame::new`] leaves them).
    pub fn next_busy_report(&mut self) -> Input {
        let n = self.reports;
        self.reports += 1;
        let key = self.keys[(n % self.keys.len().max(1) as u64) as usize];
        let (round, resident) = self.plans.get(&key).cloned().unwrap_or_default();
        let d = (mix64(n << 20) % u64::from(self.domains)) as u32;
        Input::WorkerMessage {
            key,
            body: FromWorker::QueueReport(proto::QueueReport {
                job_id: self.job_id.clone(),
                round: round.saturating_sub(1),
                resident_domains: resident,
                queued_rays: BTreeMap::from([(d, 1 + mix64(n) % 10_000)]),
                delta: true,
                ..Default::default()
            }),
        }
    }

    /// Hands the coordinator `input` a report's gap after the last, as a shell does: the
    /// actions, with the plans they carry noted for the members' next reports.
    pub fn handle(&mut self, input: Input) -> Vec<Action> {
        self.now = self.now + REPORT_GAP;
        let actions = self.coordinator.handle(self.now, input);
        self.follow(actions)
    }

    /// Hands the coordinator `inputs` together a report's gap after the last
    /// (`Coordinator::take` each, then `Coordinator::plan_round` once): `n` reports of running
    /// dry make one round that plans those `n` members. The holders flush that may be due is
    /// [`SteadyFrame::flush`]'s.
    pub fn handle_all(&mut self, inputs: Vec<Input>) -> Vec<Action> {
        self.now = self.now + REPORT_GAP;
        let mut actions = Vec::new();
        for input in inputs {
            actions.extend(self.coordinator.take(self.now, input));
        }
        actions.extend(self.coordinator.plan_round(self.now));
        self.follow(actions)
    }

    /// Hands the coordinator `input` a report's gap after the last, as [`SteadyFrame::handle`]
    /// does, but plans its round only: the holders flush that may be due with it is
    /// [`SteadyFrame::flush`]'s, so `rayfarm sim calibrate` times flushes alone (a flush follows
    /// the round of the report that finds it due).
    pub fn handle_round(&mut self, input: Input) -> Vec<Action> {
        self.handle_all(vec![input])
    }

    /// The holders flush, if it is due at the last report's time (after
    /// [`SteadyFrame::handle_round`]).
    pub fn flush(&mut self) -> Vec<Action> {
        let actions = self.coordinator.flush(self.now);
        self.follow(actions)
    }

    /// Notes the plans among `actions`.
    fn follow(&mut self, actions: Vec<Action>) -> Vec<Action> {
        for a in &actions {
            if let Action::Send((key, m)) = a
                && let Some(Body::RoundPlan(p)) = &m.body
            {
                self.plans.insert(*key, (p.round, p.work_on.clone()));
            }
        }
        actions
    }
}

/// What the rounds among `actions` planned, summed.
pub fn planned(actions: &[Action]) -> PlanningWork {
    let mut sum = PlanningWork::default();
    for a in actions {
        if let Action::Tally(Tally::Rounds(w)) = a {
            sum.add(w);
        }
    }
    sum
}

/// What the holders flushes among `actions` did, summed.
pub fn flushed(actions: &[Action]) -> FlushWork {
    let mut sum = FlushWork::default();
    for a in actions {
        if let Action::Tally(Tally::HoldersFlushed(w)) = a {
            sum.flushes += w.flushes;
            sum.members += w.members;
            sum.told += w.told;
            sum.lines += w.lines;
        }
    }
    sum
}

/// Messages among `actions` by kind: plans, holders, other.
pub fn messages(actions: &[Action]) -> BTreeMap<&'static str, usize> {
    let mut by = BTreeMap::new();
    for a in actions {
        if let Action::Send((_, m)) = a {
            let kind = match &m.body {
                Some(Body::RoundPlan(_)) => "plan",
                Some(Body::Holders(_)) => "holders",
                _ => "other",
            };
            *by.entry(kind).or_default() += 1;
        }
    }
    by
}

/// Holder lines in the plans and `Holders` among `actions`.
pub fn holder_lines(actions: &[Action]) -> usize {
    actions
        .iter()
        .map(|a| match a {
            Action::Send((_, m)) => match &m.body {
                Some(Body::RoundPlan(p)) => p.holders.len(),
                Some(Body::Holders(h)) => h.holders.len(),
                _ => 0,
            },
            _ => 0,
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reports_taken_together_make_one_round() {
        let mut s = SteadyFrame::new(64, 512, Duration::from_secs(3600));
        s.set_report_queues(40);
        let inputs: Vec<Input> = (0..8).map(|_| s.next_report()).collect();
        // The round's tally carries the queues its reports named, for their price.
        let named: usize = inputs
            .iter()
            .map(|i| match i {
                Input::WorkerMessage {
                    body: FromWorker::QueueReport(r),
                    ..
                } => r.queued_rays.len(),
                _ => 0,
            })
            .sum();
        let work = planned(&s.handle_all(inputs));
        assert_eq!((work.rounds, work.whole_rounds, work.planned), (1, 0, 8));
        assert_eq!(work.reports, 8);
        assert!(named > 8 * 30, "{named}");
        assert_eq!(work.queues, named as u64);
        s.set_report_queues(QUEUED);
        // Every member at once is a round planned from the whole cluster.
        let inputs: Vec<Input> = (0..64).map(|_| s.next_report()).collect();
        let work = planned(&s.handle_all(inputs));
        assert_eq!(
            (work.rounds, work.whole_rounds, work.whole_members),
            (1, 1, 64)
        );
    }

    #[test]
    fn a_round_tells_what_it_moved_not_every_line_since_the_flush() {
        // No flush for an hour: the lines pending for each class grow round after round
        // (hundreds after 300 rounds), but a round tells its members only the lines of the
        // domains whose rays it moved from them.
        let mut s = SteadyFrame::new(256, 2048, Duration::from_secs(3600));
        let mut most = 0;
        for _ in 0..300 {
            let input = s.next_report();
            most = most.max(holder_lines(&s.handle(input)));
        }
        assert!(most <= 100, "{most} lines in one round's messages");
        // Told after every round, a member gets every line: there is only the round's.
        let mut s = SteadyFrame::new(64, 512, Duration::ZERO);
        let input = s.next_report();
        let actions = s.handle(input);
        assert!(holder_lines(&actions) > 0);
    }

    #[test]
    fn a_flush_apart_from_its_round_tells_every_busy_member_once_an_interval() {
        // 128 members: two view classes. A report every 0.4 ms, a flush due every 10 ms.
        let mut s = SteadyFrame::new(128, 1024, Duration::from_millis(10));
        let mut flushes = Vec::new();
        for _ in 0..200 {
            let input = s.next_report();
            let round = s.handle_round(input);
            let flush = s.flush();
            assert_eq!(
                flushed(&round),
                FlushWork::default(),
                "no flush in the round"
            );
            assert!(!messages(&flush).contains_key("plan"));
            let work = flushed(&flush);
            if work.flushes > 0 {
                assert_eq!(work.told as usize, messages(&flush)["holders"]);
                assert_eq!(work.members, 128);
                flushes.push((work, holder_lines(&flush)));
            }
        }
        // 80 ms of reports: a flush every 25 reports, after the one due at once.
        assert!((7..=9).contains(&flushes.len()), "{flushes:?}");
        // Each class's lines are made once, not once for each member of the class told them.
        let (later, told_lines) = flushes.last().expect("flushed");
        assert!(later.told > 100, "{later:?}");
        assert!(
            later.lines > 0 && *told_lines as u64 >= 32 * later.lines,
            "{later:?}, {told_lines} lines told"
        );
    }

    #[test]
    fn a_busy_members_report_is_counted_and_plans_nothing() {
        let mut s = SteadyFrame::new(64, 512, Duration::from_secs(3600));
        for _ in 0..100 {
            let input = s.next_busy_report();
            let work = planned(&s.handle_round(input));
            assert_eq!((work.rounds, work.reports, work.queues), (0, 1, 1));
        }
        // Reports of members that ran dry are counted too, round or not.
        let inputs: Vec<Input> = (0..8).map(|_| s.next_report()).collect();
        assert_eq!(planned(&s.handle_all(inputs)).reports, 8);
    }

    #[test]
    fn a_dry_member_is_planned_alone_from_the_steady_state() {
        let mut s = SteadyFrame::new(64, 512, Duration::from_millis(100));
        assert_eq!(s.members(), 64);
        for _ in 0..200 {
            let input = s.next_report();
            let actions = s.handle(input);
            let work = planned(&actions);
            // One round, one member planned, the other members busy.
            if work.rounds > 0 {
                assert_eq!((work.rounds, work.whole_rounds, work.planned), (1, 0, 1));
                assert_eq!(messages(&actions)["plan"], 1);
            }
        }
    }
}
