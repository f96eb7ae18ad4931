//! The coordinator machine driven as a plain value: events in with their times, actions out;
//! no process, socket, file or clock. The store is a map of the records it asked to persist.

use std::time::Duration;

use rayfarm_core::cluster::tile_sums;
use rayfarm_proto::{PROTOCOL_VERSION, Schedule, coordinator_message::Body};

use super::*;

fn config() -> Config {
    Config {
        heartbeat: Duration::from_secs(1),
        worker_timeout: Duration::from_secs(10),
        report_timeout: Duration::from_secs(5),
        schedule_options: Options {
            replicate_onto_idle: false,
            fill_free_slots: true,
            copy_rays: 1,
        },
        rounds: Rounds::Async,
        holders_interval: Duration::ZERO,
        report_hold: super::ReportHold::NONE,
        max_attempts: 3,
        max_jobs_per_user: 2,
        max_pixel_samples_per_user: 1 << 20,
        unix_origin_ms: 0,
    }
}

fn secs(s: u64) -> Time {
    Time(s * 1_000_000_000)
}

/// A 64x64 frame of four 32-pixel tiles.
fn spec() -> proto::JobSpec {
    proto::JobSpec {
        scene: "s".into(),
        width: 64,
        height: 64,
        spp: 1,
        max_depth: 3,
        schedule: Schedule::Dynamic as i32,
        ..Default::default()
    }
}

fn opened() -> OpenedFrame {
    OpenedFrame {
        frame: FrameSpec {
            width: 64,
            height: 64,
            spp: 1,
            max_depth: 3,
            camera: None,
        },
        domain_bytes: vec![100; 4],
    }
}

/// The machine, and the records it persisted by job (the store), as a test drives it.
struct Harness {
    c: Coordinator,
    store: BTreeMap<String, JobRecord>,
}

impl Harness {
    fn new() -> Self {
        Harness {
            c: Coordinator::new(config(), 0),
            store: BTreeMap::new(),
        }
    }

    /// Keeps what is persisted; returns the actions.
    fn keep(&mut self, out: Vec<Action>) -> Vec<Action> {
        for a in &out {
            if let Action::Persist { record, .. } = a {
                self.store.insert(record.id().to_string(), record.clone());
            }
        }
        out
    }

    fn handle(&mut self, now: Time, input: Input) -> Vec<Action> {
        let out = self.c.handle(now, input);
        self.keep(out)
    }

    /// [`handle`](Self::handle), then every record persisted with a barrier stored at once:
    /// every action, the released messages included.
    fn handle_stored(&mut self, now: Time, input: Input) -> Vec<Action> {
        let mut out = self.handle(now, input);
        let barriers: Vec<u64> = out
            .iter()
            .filter_map(|a| match a {
                Action::Persist { barrier, .. } => *barrier,
                _ => None,
            })
            .collect();
        for barrier in barriers {
            out.extend(self.handle(now, Input::Stored { barrier }));
        }
        out
    }

    fn register(&mut self, now: Time, id: &str) -> (u32, Vec<Action>) {
        let (key, out) = self.c.register(now, &register(id)).expect("registered");
        (key, self.keep(out))
    }

    /// A job submitted and recorded at `now`.
    fn submit(&mut self, now: Time) -> (String, Vec<Action>) {
        let record = self
            .c
            .submit(now, spec(), 64 * 64, "ann")
            .expect("admitted");
        let id = record.id().to_string();
        self.store.insert(id.clone(), record);
        let out = self.handle(
            now,
            Input::Recorded {
                job_id: id.clone(),
                result: Ok(()),
            },
        );
        (id, out)
    }

    /// The prepared frame opened and its start stored: every action from the opening on.
    fn open(&mut self, now: Time, id: &str) -> Vec<Action> {
        let mut out = self.handle(
            now,
            Input::FrameOpened {
                job_id: id.into(),
                opened: Ok(opened()),
            },
        );
        let start = out
            .iter()
            .find_map(|a| match a {
                Action::Persist { barrier, .. } => *barrier,
                _ => None,
            })
            .expect("the start is persisted");
        out.extend(self.handle(now, Input::Stored { barrier: start }));
        out
    }
}

fn register(id: &str) -> proto::Register {
    proto::Register {
        protocol_version: PROTOCOL_VERSION,
        worker_id: id.into(),
        peer_address: format!("{id}:7000"),
        cache_bytes: 200,
        threads: 1,
    }
}

/// The messages sent to `key`.
fn sent(out: &[Action], key: u32) -> Vec<&Body> {
    out.iter()
        .filter_map(|a| match a {
            Action::Send((k, m)) if *k == key => m.body.as_ref(),
            _ => None,
        })
        .collect()
}

fn starts(out: &[Action], key: u32) -> Vec<&proto::StartFrame> {
    sent(out, key)
        .into_iter()
        .filter_map(|b| match b {
            Body::StartFrame(s) => Some(s),
            _ => None,
        })
        .collect()
}

fn prepares(out: &[Action]) -> Vec<&str> {
    out.iter()
        .filter_map(|a| match a {
            Action::PrepareFrame { job_id, .. } => Some(job_id.as_str()),
            _ => None,
        })
        .collect()
}

fn closed(out: &[Action]) -> Vec<(u32, &Closing)> {
    out.iter()
        .filter_map(|a| match a {
            Action::Close { key, closing } => Some((*key, closing)),
            _ => None,
        })
        .collect()
}

/// A running frame of one job on workers `ids`, registered at time 0.
fn running(ids: &[&str]) -> (Harness, String, Vec<u32>, Vec<Action>) {
    let mut h = Harness::new();
    let (id, out) = h.submit(Time(0));
    assert!(prepares(&out).is_empty(), "no worker yet: nothing starts");
    let keys: Vec<u32> = ids.iter().map(|w| h.register(Time(0), w).0).collect();
    let out = h.open(Time(0), &id);
    (h, id, keys, out)
}

#[test]
fn a_duplicate_worker_id_or_address_is_refused_until_the_first_is_gone() {
    let mut h = Harness::new();
    let (a, out) = h.register(Time(0), "a");
    assert!(
        matches!(sent(&out, a)[..], [Body::Registered(_)]),
        "{out:?}"
    );
    assert_eq!(
        h.c.register(Time(1), &register("a")).err(),
        Some(Refusal::DuplicateId("a".into()))
    );
    let mut same_address = register("b");
    same_address.peer_address = "a:7000".into();
    assert_eq!(
        h.c.register(Time(1), &same_address).err(),
        Some(Refusal::DuplicateAddress("a:7000".into()))
    );
    let mut old = register("c");
    old.protocol_version = PROTOCOL_VERSION + 1;
    assert!(matches!(
        h.c.register(Time(1), &old),
        Err(Refusal::Protocol(_))
    ));
    let out = h.handle(
        Time(2),
        Input::WorkerGone {
            key: a,
            why: "stream closed".into(),
        },
    );
    assert_eq!(closed(&out), [(a, &Closing::Dropped)]);
    let (again, _) = h.register(Time(3), "a");
    assert_ne!(again, a, "a new key for the new stream");
    assert_eq!(h.c.lost_workers().count(), 1);
}

#[test]
fn a_frame_s_messages_wait_until_its_start_is_stored() {
    let mut h = Harness::new();
    let (id, _) = h.submit(Time(0));
    let (a, out) = h.register(Time(0), "a");
    assert_eq!(prepares(&out), [id.as_str()]);
    let out = h.handle(
        Time(1),
        Input::FrameOpened {
            job_id: id.clone(),
            opened: Ok(opened()),
        },
    );
    assert!(starts(&out, a).is_empty(), "sent before stored: {out:?}");
    let start = out.iter().find_map(|a| match a {
        Action::Persist { record, barrier } => {
            assert_eq!(record.state(), JobState::Running);
            assert_eq!(record.attempts, 1);
            *barrier
        }
        _ => None,
    });
    let out = h.handle(
        Time(2),
        Input::Stored {
            barrier: start.unwrap(),
        },
    );
    assert_eq!(starts(&out, a).len(), 1, "{out:?}");
}

#[test]
fn a_silent_worker_is_dropped_at_the_deadline_tick_and_its_tiles_re_dealt() {
    let (mut h, _, keys, out) = running(&["a", "b"]);
    let (a, b) = (keys[0], keys[1]);
    assert_eq!(starts(&out, b)[0].primary_tiles, [1, 3]);
    // b keeps its heartbeats; a falls silent after time 0.
    let beat = |h: &mut Harness, t| {
        h.handle(
            t,
            Input::WorkerMessage {
                key: b,
                body: FromWorker::Heartbeat(Default::default()),
            },
        )
    };
    beat(&mut h, secs(5));
    assert!(
        closed(&h.handle(secs(10), Input::Tick)).is_empty(),
        "not yet"
    );
    beat(&mut h, secs(10));
    let out = h.handle_stored(secs(10) + Duration::from_millis(1), Input::Tick);
    assert_eq!(closed(&out), [(a, &Closing::NoHeartbeat)]);
    // Every unfinished tile moves to a new epoch and all four are dealt to b.
    let bodies = sent(&out, b);
    assert!(
        matches!(bodies[0], Body::EpochBump(e) if e.epochs.len() == 4 && e.lost_peers == ["a:7000"]),
        "{bodies:?}"
    );
    let dealt: Vec<u32> = bodies
        .iter()
        .filter_map(|m| match m {
            Body::HandOutTiles(t) => Some(t.tiles.clone()),
            _ => None,
        })
        .flatten()
        .collect();
    assert_eq!(dealt, [0, 1, 2, 3]);
    assert!(sent(&out, a).is_empty());
}

#[test]
fn a_dry_worker_is_planned_at_once_under_asynchronous_rounds() {
    let (mut h, id, keys, _) = running(&["a", "b"]);
    let (a, b) = (keys[0], keys[1]);
    // a runs dry with rays queued for domain 1; b has not reported and is not waited for.
    let report = proto::QueueReport {
        job_id: id,
        round: 0,
        queued_rays: [(1, 50)].into(),
        oldest_generation: [(1, 0)].into(),
        ..Default::default()
    };
    let out = h.handle(
        Time(5),
        Input::WorkerMessage {
            key: a,
            body: FromWorker::QueueReport(report),
        },
    );
    let plan = sent(&out, a)
        .into_iter()
        .find_map(|m| match m {
            Body::RoundPlan(p) => Some(p.work_on.clone()),
            _ => None,
        })
        .expect("a is planned at once");
    assert!(plan.contains(&1), "{plan:?}");
    assert!(matches!(sent(&out, b)[..], [Body::Holders(_)]), "{out:?}");
    assert!(
        out.iter()
            .any(|x| matches!(x, Action::Tally(Tally::Rounds(w)) if w.rounds == 1))
    );
    assert!(out.iter().any(|x| matches!(x, Action::Progress { .. })));
}

/// The results of all of `tile`'s pixels at `epoch`, with all its credit.
fn whole_tile(c: &Coordinator, tile: u32, epoch: u32) -> proto::TileResult {
    let grid = *c.running().expect("running").ledger.grid();
    let pixels: Vec<(u32, [i64; 3])> = grid.pixels(tile).map(|p| (p, [1, 2, 3])).collect();
    proto::TileResult {
        tile,
        epoch,
        credit: rayfarm_core::tile::credit::TILE_CREDIT,
        sums: tile_sums::encode(&pixels),
    }
}

fn results(id: &str, results: Vec<proto::TileResult>) -> FromWorker {
    FromWorker::TileResults(proto::TileResults {
        job_id: id.into(),
        results,
        segments_traced: 1,
    })
}

#[test]
fn a_complete_frame_is_written_once_its_workers_reported_or_at_the_report_deadline() {
    let (mut h, id, keys, _) = running(&["a", "b"]);
    let (a, b) = (keys[0], keys[1]);
    for (key, tiles) in [(a, [0, 2]), (b, [1, 3])] {
        let r = tiles.iter().map(|&t| whole_tile(&h.c, t, 0)).collect();
        let out = h.handle(
            secs(1),
            Input::WorkerMessage {
                key,
                body: results(&id, r),
            },
        );
        assert!(
            out.iter()
                .any(|x| matches!(x, Action::WriteTiles { tiles, .. } if tiles.len() == 2))
        );
    }
    assert!(h.c.running().is_none(), "complete");
    // a reports, b never does: the results are written at the deadline.
    let report = FromWorker::FrameReport(proto::FrameReport {
        job_id: id.clone(),
        stats_json: "{}".into(),
        ..Default::default()
    });
    let out = h.handle(
        secs(2),
        Input::WorkerMessage {
            key: a,
            body: report,
        },
    );
    assert!(!out.iter().any(|x| matches!(x, Action::WriteResults { .. })));
    assert_eq!(h.c.next_deadline(), Some(secs(6)));
    assert!(h.handle(secs(5), Input::Tick).is_empty());
    let out = h.handle(secs(6), Input::Tick);
    let stats = out.iter().find_map(|x| match x {
        Action::WriteResults { stats, .. } => Some(stats),
        _ => None,
    });
    assert_eq!(stats.expect("written").job_id, id);
    h.handle(
        secs(7),
        Input::ResultsWritten {
            job_id: id.clone(),
            result: Ok(("{\"frame\":1}".into(), "abc".into())),
        },
    );
    assert_eq!(h.store[&id].state(), JobState::Succeeded);
    assert_eq!(h.store[&id].image_hash, "abc");
    // The statistics went to the store; the machine keeps none of a finished job's.
    assert_eq!(h.store[&id].stats_json, "{\"frame\":1}");
    let kept = h.c.job(&id).expect("the job is listed");
    assert_eq!(
        (kept.image_hash.as_str(), kept.stats_json.as_str()),
        ("abc", "")
    );
    // A coordinator that restores it from the store keeps nothing of it but its count.
    let mut restored = Coordinator::new(config(), 0);
    assert!(
        restored
            .restore(secs(8), h.store[&id].clone(), None)
            .is_empty()
    );
    assert!(restored.job(&id).is_none());
    assert_eq!(restored.job_counts().succeeded, 1);
}

#[test]
fn impossible_results_close_the_sender_which_then_sits_the_frame_out() {
    let (mut h, id, keys, _) = running(&["a", "b"]);
    let (a, b) = (keys[0], keys[1]);
    // Tile 1's camera rays went to b, and a holds no domain: a cannot have its credit.
    let forged = whole_tile(&h.c, 1, 0);
    let out = h.handle_stored(
        secs(1),
        Input::WorkerMessage {
            key: a,
            body: results(&id, vec![forged]),
        },
    );
    assert!(
        matches!(closed(&out)[..], [(k, Closing::Refused(_))] if k == a),
        "{out:?}"
    );
    assert!(!out.iter().any(|x| matches!(x, Action::WriteTiles { .. })));
    assert!(matches!(sent(&out, b)[0], Body::EpochBump(_)));
    // It comes back and is registered, but takes no part in this frame.
    let (again, out) = h.register(secs(2), "a");
    assert!(starts(&out, again).is_empty() && sent(&out, b).is_empty());
}

#[test]
fn a_restarted_coordinator_requeues_the_running_job_above_its_epochs() {
    let (h, id, _, _) = running(&["a"]);
    assert_eq!(h.store[&id].state(), JobState::Running);
    // The first coordinator dies; the second starts from the records it persisted.
    let mut again = Harness::new();
    for record in h.store.values() {
        let out = again.c.restore(Time(0), record.clone(), None);
        again.keep(out);
    }
    assert_eq!(again.store[&id].state(), JobState::Queued);
    let (a, out) = again.register(Time(0), "a");
    assert_eq!(prepares(&out), [id.as_str()]);
    let out = again.open(Time(0), &id);
    let start = starts(&out, a);
    let epochs: Vec<u32> = start[0].epochs.values().copied().collect();
    assert_eq!(
        epochs,
        [1, 1, 1, 1],
        "every tile above the dead run's epoch 0"
    );
    assert_eq!(again.store[&id].attempts, 2);
    // A job submitted now numbers on from the restored ones.
    let (next, _) = again.submit(Time(1));
    assert!(next.ends_with("-2"), "{next}");
}

#[test]
fn a_job_that_lost_every_worker_is_requeued_and_restarts_above_every_epoch_it_used() {
    let (mut h, id, keys, _) = running(&["a", "b"]);
    for key in keys {
        h.handle(
            secs(1),
            Input::WorkerGone {
                key,
                why: "test".into(),
            },
        );
    }
    assert_eq!(h.store[&id].state(), JobState::Queued);
    assert!(h.c.running().is_none());
    let (c, out) = h.register(secs(2), "c");
    assert_eq!(prepares(&out), [id.as_str()]);
    let out = h.open(secs(2), &id);
    let epochs = &starts(&out, c)[0].epochs;
    assert!(epochs.values().all(|&e| e >= 2), "{epochs:?}");
}

#[test]
fn quotas_refuse_a_third_job_and_a_cancelled_job_frees_its_place() {
    let mut h = Harness::new();
    let (first, _) = h.submit(Time(0));
    h.submit(Time(0));
    let refused = h.c.submit(Time(0), spec(), 1, "ann").unwrap_err();
    assert!(refused.contains("--max-jobs-per-user 2"), "{refused}");
    // Another user is not counted against ann.
    assert!(h.c.submit(Time(0), spec(), 1, "bob").is_ok());
    let (state, out) = h.c.cancel(Time(1), &first).expect("known");
    assert_eq!(state, JobState::Cancelled);
    assert!(
        matches!(&out[..], [Action::Persist { record, .. }] if record.state() == JobState::Cancelled)
    );
    assert!(h.c.submit(Time(2), spec(), 1, "ann").is_ok());
    assert!(h.c.cancel(Time(2), "job-none").is_none());
}

#[test]
fn finished_jobs_past_the_kept_ones_are_forgotten_once_their_records_are_stored() {
    let mut h = Harness::new();
    let n = KEPT_FINISHED_JOBS + 5;
    let ids: Vec<String> = (0..n)
        .map(|_| {
            let (id, _) = h.submit(Time(0));
            let (state, out) = h.c.cancel(Time(0), &id).expect("known");
            assert_eq!(state, JobState::Cancelled);
            h.keep(out);
            id
        })
        .collect();
    // No barrier stored since they finished, so no proof their records are on disk: all held.
    assert!(ids.iter().all(|id| h.c.job(id).is_some()));
    // A frame's start is stored with a barrier, after every record made before it.
    let (job, _) = h.submit(Time(0));
    h.register(Time(0), "w");
    h.open(Time(0), &job);
    assert!(ids[..5].iter().all(|id| h.c.job(id).is_none()));
    assert!(ids[5..].iter().all(|id| h.c.job(id).is_some()));
    let counts = h.c.job_counts();
    assert_eq!((counts.cancelled, counts.running), (n as u64, 1));
    // A restarted coordinator holds no finished job, and counts them all.
    let mut c = Coordinator::new(config(), 0);
    for record in h.store.values() {
        c.restore(Time(0), record.clone(), None);
    }
    assert!(ids.iter().all(|id| c.job(id).is_none()));
    let counts = c.job_counts();
    assert_eq!((counts.cancelled, counts.queued), (n as u64, 1));
    assert_eq!(c.page(100, u64::MAX).0.len(), 1);
}

#[test]
fn new_epochs_after_a_loss_are_stored_before_workers_hear_and_a_restart_starts_above_them() {
    // The simulator's seeds 92 and 101: a worker killed, then the coordinator crashed; the
    // restarted frame started at epoch 1, the epoch the survivors' stale rays were at, and a
    // stale ray's credit was counted in the new frame.
    let (mut h, id, keys, _) = running(&["a", "b"]);
    let out = h.handle(
        secs(1),
        Input::WorkerGone {
            key: keys[0],
            why: "killed".into(),
        },
    );
    assert!(sent(&out, keys[1]).is_empty(), "the bump waits: {out:?}");
    let barrier = out
        .iter()
        .find_map(|a| match a {
            Action::Persist { record, barrier } => {
                assert_eq!(record.epoch_floor, 2, "one past the bumped epoch 1");
                *barrier
            }
            _ => None,
        })
        .expect("the new floor is persisted");
    let out = h.handle(secs(1), Input::Stored { barrier });
    assert!(
        matches!(sent(&out, keys[1])[0], Body::EpochBump(_)),
        "{out:?}"
    );
    // The coordinator dies; its successor starts the job above epoch 1.
    let mut again = Harness::new();
    for record in h.store.values() {
        again.c.restore(secs(2), record.clone(), None);
    }
    let (c, _) = again.register(secs(2), "c");
    let out = again.open(secs(2), &id);
    let epochs = &starts(&out, c)[0].epochs;
    assert!(
        epochs.len() == 4 && epochs.values().all(|&e| e == 2),
        "{epochs:?}"
    );
}

#[test]
fn a_delta_report_updates_the_status_and_one_contradicting_itself_drops_the_worker() {
    let (mut h, id, keys, _) = running(&["a", "b"]);
    let a = keys[0];
    let mut report = |at: u64, body: proto::QueueReport| {
        h.handle(
            Time(at),
            Input::WorkerMessage {
                key: a,
                body: FromWorker::QueueReport(body),
            },
        )
    };
    let whole = proto::QueueReport {
        job_id: id.clone(),
        queued_rays: [(1, 50), (2, 5)].into(),
        ..Default::default()
    };
    report(5, whole);
    // Domain 2 emptied, domain 3 came: the status lists what the worker holds now.
    let delta = proto::QueueReport {
        job_id: id.clone(),
        delta: true,
        queued_rays: [(3, 4)].into(),
        cleared_domains: vec![2],
        ..Default::default()
    };
    report(6, delta);
    let queued = |h: &Harness| {
        h.c.workers()
            .find(|&(k, _)| k == a)
            .map(|(_, w)| w.last_report.queued_rays.clone())
    };
    assert_eq!(queued(&h), Some(vec![(1, 50), (3, 4)]));
    let impossible = proto::QueueReport {
        job_id: id,
        delta: true,
        queued_rays: [(3, 1)].into(),
        cleared_domains: vec![3],
        ..Default::default()
    };
    let out = h.handle(
        Time(7),
        Input::WorkerMessage {
            key: a,
            body: FromWorker::QueueReport(impossible),
        },
    );
    assert!(
        matches!(closed(&out)[..], [(k, Closing::Refused(why))] if k == a && why.contains("impossible queue report")),
        "{out:?}"
    );
}
