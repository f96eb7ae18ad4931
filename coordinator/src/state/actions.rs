//! Carrying out the machine's actions, in order, under the state's lock but without waiting
//! on anything: messages onto the workers' channels, records to the journal, a frame's scene
//! read and results written on threads of their own (each answers the machine when done),
//! tiles onto the film, progress onto the watch channels, counts into the metrics.

use std::collections::VecDeque;
use std::time::Instant;

use rayfarm_machine::coordinator::cluster::{Action, Closing, Progress, Tally};

use super::*;

impl Coordinator {
    /// Carries out `actions`, and what the machine answers to the ones that fail at once.
    /// `began`: when the event that decided them came in (rounds planned in it count its
    /// time as planning time).
    pub(super) fn carry_out(
        self: &Arc<Self>,
        st: &mut State,
        actions: Vec<Action>,
        began: Instant,
    ) {
        let mut todo: VecDeque<Action> = actions.into();
        while let Some(action) = todo.pop_front() {
            let answer = match action {
                Action::Send((key, msg)) => {
                    if let Some(tx) = st.senders.get(&key) {
                        // A closed channel means the worker is going; its stream's end says so.
                        let _ = tx.send(Ok(msg));
                    }
                    None
                }
                Action::Close { key, closing } => {
                    if let Some(tx) = st.senders.remove(&key) {
                        let status = match closing {
                            Closing::Dropped => None,
                            Closing::NoHeartbeat => Some(Status::deadline_exceeded("no heartbeat")),
                            Closing::Refused(why) => Some(Status::permission_denied(why)),
                            Closing::ShuttingDown => Some(Status::unavailable(SHUTTING_DOWN)),
                        };
                        if let Some(status) = status {
                            let _ = tx.send(Err(status));
                        }
                    }
                    None
                }
                Action::Persist { record, barrier } => {
                    self.persist(st, &record, barrier);
                    None
                }
                Action::Progress { job_id, progress } => {
                    publish_progress(st, &job_id, progress);
                    None
                }
                Action::PrepareFrame { job_id, spec } => self.prepare(job_id, spec),
                Action::FrameStarted { job_id, attempt } => {
                    frame_started(st, &job_id, attempt);
                    None
                }
                Action::WriteTiles {
                    job_id,
                    tiles,
                    samples,
                    subframes_done,
                } => {
                    let written = st
                        .films
                        .get(&job_id)
                        .map(|f| f.write_tiles(&tiles, samples, subframes_done));
                    match written {
                        Some(Err(e)) => Some(Input::Fail {
                            job_id,
                            error: format!("{e:#}"),
                        }),
                        _ => None,
                    }
                }
                Action::Discard { job_id } => {
                    st.films.remove(&job_id);
                    None
                }
                Action::WriteResults { job_id, stats } => self.write_results(st, job_id, *stats),
                Action::Tally(tally) => {
                    count(tally, began);
                    None
                }
            };
            if let Some(input) = answer {
                todo.extend(st.machine.handle(now(), input));
            }
        }
    }

    /// Hands `record` to the journal and tells the job's watchers its state. With a
    /// `barrier`, the machine hears once it is stored (messages to workers wait for it).
    fn persist(self: &Arc<Self>, st: &mut State, record: &JobRecord, barrier: Option<u64>) {
        let stored = StoredJob::from_record(record);
        match barrier {
            Some(barrier) => {
                let this = Arc::downgrade(self);
                let then = Box::new(move |_| {
                    if let Some(c) = this.upgrade() {
                        let mut st = c.lock();
                        c.feed(&mut st, Input::Stored { barrier });
                    }
                });
                st.journal.put_then(stored, then);
            }
            None => st.journal.put(stored),
        }
        let Some(view) = st.views.get(record.id()) else {
            return;
        };
        let state = record.state();
        let id = record.id().to_string();
        let preview_sequence = view.preview.as_ref().map_or(0, |p| p.sequence());
        view.progress.send_modify(|p| {
            p.state = state as i32;
            p.error = record.summary.error.clone();
            p.stats_json = record.stats_json.clone();
            p.preview_sequence = p.preview_sequence.max(preview_sequence);
            if state == JobState::Succeeded {
                p.tiles_done = p.tiles_total;
                p.subframes_done = p.subframes;
                p.eta_seconds = 0.0;
            }
        });
        if is_terminal(state) {
            st.finished.retain(|j| *j != id);
            st.finished.push_back(id);
            while st.finished.len() > KEPT_FINISHED_VIEWS {
                if let Some(old) = st.finished.pop_front() {
                    st.views.remove(&old);
                }
            }
        }
    }

    /// Reads job `id`'s scene and creates its film on a thread of its own; the machine hears
    /// the outcome. An answer at once if no thread can be had.
    fn prepare(self: &Arc<Self>, id: String, spec: proto::JobSpec) -> Option<Input> {
        let (this, job) = (self.clone(), id.clone());
        let prepare = move || {
            let prepared = this.prepare_frame(&job, spec);
            let mut st = this.lock();
            let opened = match prepared {
                Ok((running, opened)) => {
                    st.films.insert(job.clone(), running);
                    Ok(opened)
                }
                Err(status) => Err(status.message().to_string()),
            };
            let input = Input::FrameOpened {
                job_id: job,
                opened,
            };
            this.feed(&mut st, input);
        };
        match std::thread::Builder::new()
            .name("prepare-frame".into())
            .spawn(prepare)
        {
            Ok(_) => None,
            Err(e) => Some(Input::FrameOpened {
                job_id: id,
                opened: Err(format!("no thread to prepare its frame: {e}")),
            }),
        }
    }

    /// Writes the finished job's images and statistics from its film on a thread of its
    /// own (the final preview is made first); the machine hears the outcome.
    fn write_results(
        self: &Arc<Self>,
        st: &mut State,
        id: String,
        mut stats: rayfarm_core::cluster::stats::ClusterStats,
    ) -> Option<Input> {
        let Some(Running { film, previews }) = st.films.remove(&id) else {
            return Some(Input::ResultsWritten {
                job_id: id,
                result: Err("the frame's film is gone".into()),
            });
        };
        let schedule = st
            .machine
            .job(&id)
            .and_then(|j| j.summary.spec.as_ref())
            .map_or(Schedule::Dynamic, |s| {
                Schedule::try_from(s.schedule).unwrap_or(Schedule::Dynamic)
            });
        stats.schedule = schedule_name(schedule).into();
        let (this, job) = (self.clone(), id.clone());
        let write = move || {
            let written = results::write(&this.config.data_dir, &job, &film, &mut stats);
            // The film file goes with `film` once both images are written; the final
            // preview is made of it first.
            previews.seal();
            drop(film);
            let mut st = this.lock();
            let result = written.map_err(|e| format!("{e:#}"));
            this.feed(
                &mut st,
                Input::ResultsWritten {
                    job_id: job,
                    result,
                },
            );
            drop(st);
            // The frame's film buffers and encoders are freed: back to the system with them.
            rayfarm_node::heap::release_free_memory();
        };
        match std::thread::Builder::new()
            .name("write-results".into())
            .spawn(write)
        {
            Ok(_) => None,
            Err(e) => Some(Input::ResultsWritten {
                job_id: id,
                result: Err(format!("no thread to write its results: {e}")),
            }),
        }
    }
}

/// Job `id`'s frame started: its previews count on from its last frame's, and are kept.
fn frame_started(st: &mut State, id: &str, attempt: u32) {
    let Some(running) = st.films.get_mut(id) else {
        return;
    };
    let Some(view) = st.views.get_mut(id) else {
        return;
    };
    info!(job = %id, attempt, "frame's film ready");
    // Numbered on from the job's last frame, so its previews' numbers only grow.
    let floor = view.preview.as_ref().map_or(0, |p| p.sequence());
    running.previews = Arc::new(Previews::new(&running.film, floor));
    view.preview = Some(running.previews.clone());
    st.previewed.retain(|j| j != id);
    st.previewed.push_back(id.to_string());
    while st.previewed.len() > KEPT_PREVIEWS {
        if let Some(old) = st.previewed.pop_front()
            && let Some(view) = st.views.get_mut(&old)
        {
            view.preview = None;
        }
    }
}

fn publish_progress(st: &State, id: &str, progress: Progress) {
    let Some(view) = st.views.get(id) else {
        return;
    };
    let preview_sequence = view.preview.as_ref().map_or(0, |p| p.sequence());
    view.progress.send_modify(|p| {
        p.preview_sequence = preview_sequence;
        p.tiles_done = progress.tiles_done;
        p.tiles_total = progress.tiles_total;
        p.subframes_done = progress.subframes_done;
        p.subframes = progress.subframes;
        p.round = progress.round;
        p.rays_per_second = progress.rays_per_second;
        p.eta_seconds = progress.eta_seconds;
    });
}

fn count(tally: Tally, began: Instant) {
    let m = rayfarm_node::metrics::coordinator();
    match tally {
        // A tally of reports taken in without a round (`PlanningWork::queues`) is no round.
        Tally::Rounds(work) if work.rounds > 0 => {
            m.rounds.inc_by(work.rounds);
            m.planning_seconds.observe(began.elapsed().as_secs_f64());
        }
        Tally::Rounds(_) => {}
        // Its time is the event's, as a round's: the flush follows the event that made it due.
        Tally::HoldersFlushed(_) => {}
        Tally::TilesCommitted(n) => {
            m.tiles_committed.inc_by(n);
        }
        Tally::SubframeCommitted => {
            m.subframes_committed.inc();
        }
        Tally::FrameCommitted => {
            m.frames_committed.inc();
        }
        Tally::FrameFailed => {
            m.frames_failed.inc();
        }
        Tally::WorkerLost => {
            m.workers_lost.inc();
        }
    }
}
