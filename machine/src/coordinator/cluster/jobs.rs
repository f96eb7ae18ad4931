//! Jobs: submission against the owner's quotas, the first record before the job is queued,
//! cancel, priority, state changes (each one a record to persist), and the records of a
//! restarted coordinator.

use tracing::{error, info, warn};

use super::*;

/// Why a priority cannot change.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PriorityRefused {
    NotFound,
    /// Only a queued job's priority changes; this one is in this state.
    NotQueued(JobState),
}

/// Pixels times samples per pixel of a spec as given (a field left 0 counts as 1).
pub fn spec_cost(spec: &proto::JobSpec) -> u64 {
    [spec.width, spec.height, spec.spp]
        .iter()
        .map(|&v| u64::from(v.max(1)))
        .product()
}

impl Coordinator {
    /// Takes one stored job in, as a restarting coordinator does: queued jobs queued in their
    /// old order; a job that was running queued again in its place (its frame died with the
    /// old process and starts over at fresh tile epochs, since its record counts the
    /// attempt); a finished job whose result file is gone (`missing_result`, as the shell
    /// found it) failed. A finished job is only counted: the store answers for it.
    pub fn restore(
        &mut self,
        now: Time,
        mut record: JobRecord,
        missing_result: Option<String>,
    ) -> Vec<Action> {
        let id = record.id().to_string();
        if id.is_empty() {
            warn!(seq = record.seq, "a stored job without a summary; skipped");
            return Vec::new();
        }
        let priority = record.summary.spec.as_ref().map_or(0, |s| s.priority);
        let mut changed = None;
        match record.state() {
            JobState::Queued | JobState::Unspecified => {
                self.queue.push(id.clone(), priority, record.seq)
            }
            JobState::Running => {
                // It keeps its sequence number: ahead of later jobs of its priority.
                info!(job = %id, "job was running when the coordinator stopped: queued again");
                self.queue.push(id.clone(), priority, record.seq);
                changed = Some((JobState::Queued, String::new()));
            }
            JobState::Succeeded if missing_result.is_some() => {
                let path = missing_result.unwrap_or_default();
                let error = format!("its result file {path} is gone");
                warn!(job = %id, %error, "finished job without its result");
                changed = Some((JobState::Failed, error));
            }
            JobState::Succeeded | JobState::Failed | JobState::Cancelled => {}
        }
        let mut out = Vec::new();
        if let Some((state, error)) = changed {
            record.summary.state = state as i32;
            record.summary.error = error;
            if state == JobState::Failed {
                record.summary.finished_unix_ms = self.unix_ms(now);
            }
            out.push(Action::Persist {
                record: record.clone(),
                barrier: None,
            });
        }
        self.seq = self.seq.max(record.seq);
        if is_terminal(record.state()) {
            // The store's, not the machine's (see `KEPT_FINISHED_JOBS`).
            self.count_ended(record.state());
            return out;
        }
        let job = Job {
            cost: record.summary.spec.as_ref().map_or(0, spec_cost),
            record,
            workers_lost: BTreeMap::new(),
        };
        self.add_job(id, job);
        out
    }

    fn add_job(&mut self, id: String, job: Job) {
        self.by_seq.insert(job.record.seq, id.clone());
        self.jobs.insert(id, job);
    }

    /// A job of `spec` (checked by the shell against its scene) submitted by `owner` at
    /// `now`, weighing `cost` pixel-samples: its record, to be stored before the job is
    /// queued ([`Input::Recorded`]); meanwhile it counts against the quota. Refused (with
    /// why) past the owner's quotas.
    pub fn submit(
        &mut self,
        now: Time,
        spec: proto::JobSpec,
        cost: u64,
        owner: &str,
    ) -> Result<JobRecord, String> {
        self.check_quota(owner, cost)?;
        self.seq += 1;
        let seq = self.seq;
        let id = format!("job-{}-{seq}", self.unix_ms(now) / 1000);
        let record = JobRecord {
            summary: proto::JobSummary {
                job_id: id.clone(),
                spec: Some(spec),
                state: JobState::Queued as i32,
                submitted_unix_ms: self.unix_ms(now),
                owner: owner.to_string(),
                ..Default::default()
            },
            seq,
            attempts: 0,
            epoch_floor: 0,
            image_hash: String::new(),
            stats_json: String::new(),
        };
        let job = Job {
            record: record.clone(),
            cost,
            workers_lost: BTreeMap::new(),
        };
        self.add_job(id, job);
        Ok(record)
    }

    /// The first record of a submitted job is stored (it is queued, unless cancelled
    /// meanwhile), or could not be (the job is forgotten).
    pub(super) fn recorded(
        &mut self,
        now: Time,
        id: &str,
        result: Result<(), String>,
        out: &mut Vec<Action>,
    ) {
        if let Err(e) = result {
            error!(job = %id, error = %e, "job not recorded");
            if let Some(job) = self.jobs.remove(id) {
                self.by_seq.remove(&job.record.seq);
            }
            return;
        }
        let Some(job) = self
            .jobs
            .get(id)
            .filter(|j| j.record.state() == JobState::Queued)
        else {
            return;
        };
        let spec = job.record.summary.spec.clone().unwrap_or_default();
        self.queue
            .push(id.to_string(), spec.priority, job.record.seq);
        info!(job = %id, user = %job.record.summary.owner, scene = %spec.scene, width = spec.width, height = spec.height, spp = spec.spp, priority = spec.priority, "job queued");
        self.try_start(now, out);
    }

    /// Refuses a job of `cost` that would take `owner` past a quota, saying why.
    fn check_quota(&self, owner: &str, cost: u64) -> Result<(), String> {
        let (jobs, queued) = self
            .jobs
            .values()
            .filter(|j| j.record.summary.owner == owner && !is_terminal(j.record.state()))
            .fold((0usize, 0u64), |(n, c), j| {
                (n + 1, c.saturating_add(j.cost))
            });
        let who = if owner.is_empty() { "anonymous" } else { owner };
        if jobs >= self.config.max_jobs_per_user {
            warn!(user = %who, jobs, "job refused: queued-jobs quota");
            return Err(format!(
                "user {who} has {jobs} jobs queued or running, the most allowed \
                 (--max-jobs-per-user {})",
                self.config.max_jobs_per_user
            ));
        }
        let max = self.config.max_pixel_samples_per_user;
        if queued.saturating_add(cost) > max {
            warn!(user = %who, queued, cost, "job refused: pixel-samples quota");
            return Err(format!(
                "user {who} has {queued} pixel-samples queued or running; this job's {cost} \
                 would pass the quota of {max} (--max-pixel-samples-per-user)"
            ));
        }
        Ok(())
    }

    /// Cancels job `id` if queued or running (the caller checked who may); its state
    /// afterwards, or `None` if there is no such job.
    pub fn cancel(&mut self, now: Time, id: &str) -> Option<(JobState, Vec<Action>)> {
        let state = self.jobs.get(id)?.record.state();
        let mut out = Vec::new();
        if is_terminal(state) {
            return Some((state, out));
        }
        if self.queue.remove(id) || self.preparing.as_deref() == Some(id) {
            // A frame being prepared is discarded when it is ready (`begin`).
            self.set_state(now, id, JobState::Cancelled, "", &mut out);
        } else if self.running.as_ref().is_some_and(|f| f.job_id == id) {
            if let Some(frame) = self.running.take() {
                self.send(frame.end_messages(), &mut out);
                out.push(Action::Discard {
                    job_id: id.to_string(),
                });
            }
            self.set_state(now, id, JobState::Cancelled, "", &mut out);
            self.try_start(now, &mut out);
        }
        let state = self
            .jobs
            .get(id)
            .map_or(JobState::Cancelled, |j| j.record.state());
        Some((state, out))
    }

    /// Sets a queued job's priority; it moves to its new place in the queue. Its state, and
    /// the record to persist.
    pub fn set_priority(
        &mut self,
        id: &str,
        priority: i32,
    ) -> Result<(JobState, Vec<Action>), PriorityRefused> {
        let job = self.jobs.get_mut(id).ok_or(PriorityRefused::NotFound)?;
        let state = job.record.state();
        if state != JobState::Queued {
            return Err(PriorityRefused::NotQueued(state));
        }
        if let Some(spec) = job.record.summary.spec.as_mut() {
            spec.priority = priority;
        }
        let (record, seq) = (job.record.clone(), job.record.seq);
        if self.queue.remove(id) {
            self.queue.push(id.to_string(), priority, seq);
        }
        info!(job = %id, priority, "job priority changed");
        let persist = Action::Persist {
            record,
            barrier: None,
        };
        Ok((state, vec![persist]))
    }

    /// Sets job `id`'s state and records it (`barrier`: see [`Action::Persist`]).
    pub(super) fn set_state_stored(
        &mut self,
        now: Time,
        id: &str,
        state: JobState,
        error: &str,
        barrier: Option<u64>,
        out: &mut Vec<Action>,
    ) {
        let finished = self.unix_ms(now);
        let Some(job) = self.jobs.get_mut(id) else {
            return;
        };
        let newly_ended = is_terminal(state) && !is_terminal(job.record.state());
        let summary = &mut job.record.summary;
        summary.state = state as i32;
        summary.error = error.to_string();
        info!(job = %id, user = %summary.owner, state = ?state, "job state");
        if is_terminal(state) {
            summary.finished_unix_ms = finished;
        }
        if state == JobState::Failed {
            error!(job = %id, error, "job failed");
        }
        // In the order the changes happened; once per state change. A finished job's
        // statistics go to the store with this record and are not kept here: memory must not
        // grow with the jobs a coordinator has finished (the shell reads them from the store).
        let mut record = job.record.clone();
        if is_terminal(state) {
            record.stats_json = std::mem::take(&mut job.record.stats_json);
        }
        out.push(Action::Persist { record, barrier });
        if newly_ended {
            self.count_ended(state);
            // Stored with `barrier`, or before the next barrier made after it.
            let stored_by = barrier.unwrap_or(self.barriers + 1);
            self.finished.push_back((id.to_string(), stored_by));
            self.forget_finished();
        }
    }

    fn count_ended(&mut self, state: JobState) {
        let i = match state {
            JobState::Succeeded => 0,
            JobState::Failed => 1,
            _ => 2,
        };
        self.ended[i] += 1;
    }

    /// Forgets the oldest finished jobs past [`KEPT_FINISHED_JOBS`] whose final records are
    /// known to be stored: from then on the shell answers for them from the store.
    pub(super) fn forget_finished(&mut self) {
        while self.finished.len() > KEPT_FINISHED_JOBS
            && let Some((id, stored_by)) = self.finished.front()
            && *stored_by <= self.stored_barriers
        {
            if let Some(job) = self.jobs.remove(id) {
                self.by_seq.remove(&job.record.seq);
            }
            self.finished.pop_front();
        }
    }

    pub(super) fn set_state(
        &mut self,
        now: Time,
        id: &str,
        state: JobState,
        error: &str,
        out: &mut Vec<Action>,
    ) {
        self.set_state_stored(now, id, state, error, None, out);
    }
}
