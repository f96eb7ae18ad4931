//! Frames: the next queued job started when the cluster is free (its scene read by the shell
//! first), its messages held until its start is stored, and the frame finished (results
//! written once the workers' statistics are in or overdue), failed, re-queued or abandoned.

use tracing::{error, info, warn};

use super::workers::tally_rounds;
use super::*;
use crate::coordinator::frame::Member;

impl Coordinator {
    /// Asks for the next queued job's frame if the cluster is free and has workers.
    pub(super) fn try_start(&mut self, now: Time, out: &mut Vec<Action>) {
        while !self.stopping
            && self.running.is_none()
            && self.preparing.is_none()
            && !self.workers.is_empty()
        {
            let Some(id) = self.queue.pop() else {
                return;
            };
            let Some(job) = self.jobs.get(&id) else {
                continue;
            };
            let Some(spec) = job.record.summary.spec.clone() else {
                continue;
            };
            let attempts = job.record.attempts;
            if attempts >= self.config.max_attempts {
                // A job that kills the coordinator (or loses every worker) each time it runs
                // would otherwise be a crash loop; the queue moves on.
                let reason = format!(
                    "its frame started {attempts} times without finishing (the coordinator \
                     stopped or every worker was lost each time); --max-attempts is {}",
                    self.config.max_attempts
                );
                self.set_state(now, &id, JobState::Failed, &reason, out);
                continue;
            }
            // No other frame starts while the shell reads this one's scene.
            self.preparing = Some(id.clone());
            out.push(Action::PrepareFrame { job_id: id, spec });
            return;
        }
    }

    /// Starts the frame the shell prepared for job `id`, unless the job was cancelled, the
    /// coordinator is stopping, or every worker left meanwhile (then it is queued again).
    pub(super) fn begin(
        &mut self,
        now: Time,
        id: &str,
        opened: Result<OpenedFrame, String>,
        out: &mut Vec<Action>,
    ) {
        if self.preparing.as_deref() != Some(id) {
            // Not the frame asked for (a stale answer): nothing of it is used.
            out.push(Action::Discard { job_id: id.into() });
            return;
        }
        self.preparing = None;
        let discard = Action::Discard { job_id: id.into() };
        let Some(job) = self.jobs.get(id) else {
            out.push(discard);
            return self.try_start(now, out);
        };
        let (attempts, floor, seq) = (job.record.attempts, job.record.epoch_floor, job.record.seq);
        let spec = job.record.summary.spec.clone().unwrap_or_default();
        if job.record.state() != JobState::Queued || self.stopping {
            out.push(discard);
            return self.try_start(now, out);
        }
        if self.workers.is_empty() {
            out.push(discard);
            self.queue.push(id.to_string(), spec.priority, seq);
            return;
        }
        let opened = opened.and_then(|o| {
            RunningFrame::new(
                now,
                id.to_string(),
                spec,
                o.frame,
                o.domain_bytes,
                self.config.schedule_options,
                self.config.rounds,
            )
            .map(|f| {
                f.with_holders_interval(self.config.holders_interval)
                    .with_report_hold(self.config.report_hold)
            })
        });
        let mut frame = match opened {
            Ok(frame) => frame,
            Err(e) => {
                error!(job = %id, error = %e, "job cannot start");
                out.push(discard);
                self.set_state(now, id, JobState::Failed, &e, out);
                return self.try_start(now, out);
            }
        };
        // A job started before (by a coordinator since restarted, or before its workers
        // were all lost) starts every tile at a new epoch, so rays and results of the
        // abandoned run still in flight are dropped as stale.
        // (Records stored before the floor was kept count their attempts instead.)
        frame.restart_epochs(attempts.max(floor));
        let members: Vec<(u32, Member)> = self
            .workers
            .iter()
            .map(|(&k, w)| (k, Member::new(w.peer_address.clone(), w.cache_bytes)))
            .collect();
        let workers = members.len();
        let messages = frame.start(members);
        tally_rounds(&frame, &PlanningWork::default(), out);
        info!(
            job = %id,
            workers,
            tiles = frame.ledger.grid().count(),
            attempt = attempts + 1,
            "frame started"
        );
        let started = self.unix_ms(now);
        if let Some(job) = self.jobs.get_mut(id) {
            job.record.summary.started_unix_ms = started;
            job.record.attempts = attempts.saturating_add(1);
            job.record.epoch_floor = frame.epoch_floor();
        }
        out.push(Action::FrameStarted {
            job_id: id.to_string(),
            attempt: attempts.saturating_add(1),
        });
        // The start is stored before any worker hears of it: a frame that kills the
        // coordinator counts against the job's attempts all the same.
        self.barriers += 1;
        let barrier = self.barriers;
        self.set_state_stored(now, id, JobState::Running, "", Some(barrier), out);
        self.running = Some(frame);
        self.send(messages, out);
        self.publish_progress(now, out);
    }

    /// Messages to workers, held while a barrier's record is not yet stored.
    pub(super) fn send(&mut self, messages: Vec<Outgoing>, out: &mut Vec<Action>) {
        if self.stored_barriers < self.barriers {
            let barrier = self.barriers;
            self.held.extend(messages.into_iter().map(|m| (barrier, m)));
            return;
        }
        out.extend(messages.into_iter().map(Action::Send));
    }

    /// The running frame's messages after a loss bumped its epochs: the job's epoch floor is
    /// raised past them and stored before any worker hears of them.
    pub(super) fn send_bumped(&mut self, messages: Vec<Outgoing>, out: &mut Vec<Action>) {
        let floor = self
            .running
            .as_ref()
            .map(|f| (f.job_id.clone(), f.epoch_floor()));
        if let Some((id, floor)) = floor
            && let Some(job) = self.jobs.get_mut(&id)
            && floor > job.record.epoch_floor
        {
            job.record.epoch_floor = floor;
            self.barriers += 1;
            out.push(Action::Persist {
                record: job.record.clone(),
                barrier: Some(self.barriers),
            });
        }
        self.send(messages, out);
    }

    /// Barrier `barrier`'s record is stored: the messages held for it (and earlier
    /// barriers) go out to the workers still registered.
    pub(super) fn release_held(&mut self, barrier: u64, out: &mut Vec<Action>) {
        self.stored_barriers = self.stored_barriers.max(barrier);
        self.forget_finished();
        let ready = self.held.iter().take_while(|(b, _)| *b <= barrier).count();
        let workers = &self.workers;
        out.extend(
            self.held
                .drain(..ready)
                .filter(|(_, (k, _))| workers.contains_key(k))
                .map(|(_, m)| Action::Send(m)),
        );
    }

    /// The running frame fails with `error`; the next job starts.
    pub(super) fn fail_running(&mut self, now: Time, error: &str, out: &mut Vec<Action>) {
        if let Some(frame) = self.running.take() {
            out.push(Action::Tally(Tally::FrameFailed));
            // The statistics of its committed subframes are of no use now.
            self.finishing.retain(|_, f| f.job != frame.job_id);
            self.send(frame.end_messages(), out);
            out.push(Action::Discard {
                job_id: frame.job_id.clone(),
            });
            self.set_state(now, &frame.job_id, JobState::Failed, error, out);
        }
        self.try_start(now, out);
    }

    /// Job `id`'s frame cannot go on (the shell could not write its film), whether it is
    /// still running or finishing.
    pub(super) fn fail_job(&mut self, now: Time, id: &str, error: &str, out: &mut Vec<Action>) {
        if self.running.as_ref().is_some_and(|f| f.job_id == id) {
            return self.fail_running(now, error, out);
        }
        let finishing = self.finishing.len();
        self.finishing.retain(|_, f| f.job != id);
        if self.finishing.len() < finishing {
            out.push(Action::Discard { job_id: id.into() });
            self.set_state(now, id, JobState::Failed, error, out);
        }
    }

    /// Every member of the running frame is gone: its job goes back to the front of its
    /// priority class, above every epoch it used, and starts over when workers are there
    /// (workers sitting the frame out may be: they start it at once).
    pub(super) fn requeue_running(&mut self, now: Time, out: &mut Vec<Action>) {
        let Some(frame) = self.running.take() else {
            return;
        };
        warn!(job = %frame.job_id, "every worker of the frame is gone: job re-queued");
        let id = frame.job_id.clone();
        // It starts over from its first subframe, in a new film.
        self.finishing.retain(|_, f| f.job != id);
        if let Some(job) = self.jobs.get_mut(&id) {
            job.record.epoch_floor = job.record.epoch_floor.max(frame.epoch_floor());
            self.queue
                .push(id.clone(), frame.spec.priority, job.record.seq);
        }
        out.push(Action::Discard { job_id: id.clone() });
        self.set_state(now, &id, JobState::Queued, "", out);
        self.try_start(now, out);
    }

    /// The running frame's current subframe has all its credit back and another follows:
    /// its tiles are in the film, its frame ends on the workers (their statistics are kept
    /// for the job's) and the next subframe starts on the same workers at once.
    pub(super) fn next_subframe(&mut self, now: Time, out: &mut Vec<Action>) {
        let Some(frame) = self.running.as_mut() else {
            return;
        };
        let (done, total) = frame.subframes();
        let wall = now.since(frame.started).as_secs_f64();
        info!(job = %frame.job_id, subframe = done, subframes = total, wall, "subframe committed");
        out.push(Action::Tally(Tally::SubframeCommitted));
        self.finishing.insert(
            frame.frame_id(),
            Finishing {
                job: frame.job_id.clone(),
                stats: None,
                cost: cost_so_far(frame, wall),
                waiting: frame.members().collect(),
                reports: Vec::new(),
                deadline: now + self.config.report_timeout,
            },
        );
        let before = frame.planning;
        let messages = frame.next_subframe();
        tally_rounds(frame, &before, out);
        self.send(messages, out);
        self.publish_progress(now, out);
    }

    /// The running frame has all its credit back: it ends on the workers, waits for their
    /// statistics (at most the report timeout), and the next job starts at once.
    pub(super) fn complete(&mut self, now: Time, out: &mut Vec<Action>) {
        let Some(frame) = self.running.take() else {
            return;
        };
        let wall = now.since(frame.started).as_secs_f64();
        info!(job = %frame.job_id, wall, rounds = frame.rounds_total(), "frame complete");
        out.push(Action::Tally(Tally::SubframeCommitted));
        out.push(Action::Tally(Tally::FrameCommitted));
        self.send(frame.end_messages(), out);
        let spec = &frame.frame;
        let stats = ClusterStats {
            job_id: frame.job_id.clone(),
            scene: frame.spec.scene.clone(),
            width: spec.width,
            height: spec.height,
            spp: spec.spp,
            max_depth: spec.max_depth,
            domains: frame.domain_count(),
            wall_seconds: wall,
            rounds: frame.rounds_total(),
            subframes: frame.subframes().1,
            left_out: frame.declined.clone(),
            refused_results: frame.refused_results,
            ..Default::default()
        };
        self.finishing.insert(
            frame.frame_id(),
            Finishing {
                job: frame.job_id.clone(),
                stats: Some(stats),
                cost: cost_so_far(&frame, wall),
                waiting: frame.members().collect(),
                reports: Vec::new(),
                deadline: now + self.config.report_timeout,
            },
        );
        self.finish_ready(now, out);
        self.try_start(now, out);
    }

    /// Finished frames whose statistics are all in, or overdue: their results to write,
    /// with the workers' reports of every committed subframe of the job that came in.
    pub(super) fn finish_ready(&mut self, now: Time, out: &mut Vec<Action>) {
        let ready: Vec<String> = self
            .finishing
            .iter()
            .filter(|(_, f)| f.stats.is_some() && (f.waiting.is_empty() || now >= f.deadline))
            .map(|(_, f)| f.job.clone())
            .collect();
        for job in ready {
            let mut stats = None;
            let mut reports = Vec::new();
            let mut costs = Vec::new();
            self.finishing.retain(|_, f| {
                if f.job != job {
                    return true;
                }
                stats = stats.take().or(f.stats.take());
                costs.push(SubframeCost {
                    loads: f.reports.iter().map(|r| r.cache.loads).sum(),
                    ..f.cost
                });
                reports.append(&mut f.reports);
                false
            });
            let Some(mut stats) = stats else {
                continue;
            };
            // Frame ids sort as text (`JOB~10` before `JOB~2`): put them in sample order.
            costs.sort_by_key(|c| c.first_sample);
            stats.subframe_costs = costs;
            stats.absorb(WorkerFrameStats::merge_by_worker(reports));
            out.push(Action::WriteResults {
                job_id: job,
                stats: Box::new(stats),
            });
        }
    }

    pub(super) fn results_written(
        &mut self,
        now: Time,
        id: &str,
        result: Result<(String, String), String>,
        out: &mut Vec<Action>,
    ) {
        match result {
            Ok((json, hash)) => {
                if let Some(job) = self.jobs.get_mut(id) {
                    job.record.stats_json = json;
                    job.record.image_hash = hash.clone();
                }
                info!(job = %id, %hash, "results written");
                self.set_state(now, id, JobState::Succeeded, "", out);
            }
            Err(e) => self.set_state(now, id, JobState::Failed, &e, out),
        }
    }

    /// See [`Input::ShutDown`].
    pub(super) fn shut_down(&mut self, out: &mut Vec<Action>) {
        self.stopping = true;
        for key in std::mem::take(&mut self.workers).into_keys() {
            out.push(Action::Close {
                key,
                closing: Closing::ShuttingDown,
            });
        }
        if let Some(frame) = self.running.take() {
            info!(job = %frame.job_id, "job interrupted: it starts over when a coordinator opens this data directory again");
            out.push(Action::Discard {
                job_id: frame.job_id,
            });
        }
    }

    /// The running frame's figures for its watchers.
    pub(super) fn publish_progress(&self, now: Time, out: &mut Vec<Action>) {
        let Some(frame) = self.running.as_ref() else {
            return;
        };
        let (tiles_done, tiles_total, rays_per_second, eta_seconds) = frame.progress(now);
        let (subframes_done, subframes) = frame.subframes();
        out.push(Action::Progress {
            job_id: frame.job_id.clone(),
            progress: Progress {
                tiles_done,
                tiles_total,
                subframes_done,
                subframes,
                round: frame.round,
                rays_per_second,
                eta_seconds,
            },
        });
    }
}

/// The current subframe's samples and the time its last tile came back (`wall` seconds from
/// the frame's start); its loads come with the workers' reports.
fn cost_so_far(frame: &RunningFrame, wall: f64) -> SubframeCost {
    let samples = frame.samples();
    SubframeCost {
        first_sample: samples.first,
        samples: samples.count,
        done_seconds: wall,
        loads: 0,
    }
}
