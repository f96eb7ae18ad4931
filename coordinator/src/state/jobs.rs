//! The user API's side of the state: jobs submitted, admitted, listed, watched, cancelled
//! and fetched.

use super::*;

impl Coordinator {
    /// Checks and queues a job; returns its id. Reads the scene's manifest on the calling
    /// thread: the job API reads it off the async runtime ([`Coordinator::spec_with_defaults`],
    /// [`Coordinator::open_scene`], [`Coordinator::enqueue`]).
    #[cfg(test)]
    pub fn submit(self: &Arc<Self>, spec: Option<proto::JobSpec>) -> Result<String, Status> {
        let spec = self.spec_with_defaults(spec)?;
        let (_, manifest) = self.open_scene(&spec.scene)?;
        self.enqueue(spec, &manifest, None)
    }

    /// The job's spec with the defaults filled in (schedule, scene), or why it has none.
    pub fn spec_with_defaults(
        &self,
        spec: Option<proto::JobSpec>,
    ) -> Result<proto::JobSpec, Status> {
        let mut spec =
            spec.ok_or_else(|| Status::invalid_argument("the request has no job spec"))?;
        let schedule = Schedule::try_from(spec.schedule)
            .map_err(|_| Status::invalid_argument(format!("unknown schedule {}", spec.schedule)))?;
        let schedule = match schedule {
            Schedule::Unspecified => Schedule::Dynamic,
            s => s,
        };
        spec.schedule = schedule as i32;
        if spec.scene.is_empty() {
            spec.scene = self.config.default_scene.clone().unwrap_or_default();
        }
        Ok(spec)
    }

    /// Checks `spec` against its scene's `manifest` and the quotas of `user` (the
    /// authenticated submitter, `None` without user tokens), and queues the job owned by the
    /// user; returns its id.
    pub fn enqueue(
        self: &Arc<Self>,
        spec: proto::JobSpec,
        manifest: &Manifest,
        user: Option<&User>,
    ) -> Result<String, Status> {
        let frame = frame_spec(&spec, &manifest.camera).map_err(Status::invalid_argument)?;
        self.admit(&frame)?;
        let cost = u64::from(frame.width) * u64::from(frame.height) * u64::from(frame.spp);
        let owner = user.map(|u| u.name.clone()).unwrap_or_default();
        let mut st = self.lock();
        self.check_quota(&st, &owner, cost)?;
        st.seq += 1;
        let seq = st.seq;
        let id = format!("job-{}-{seq}", unix_ms() / 1000);
        let summary = proto::JobSummary {
            job_id: id.clone(),
            spec: Some(spec.clone()),
            state: JobState::Queued as i32,
            submitted_unix_ms: unix_ms(),
            owner: owner.clone(),
            ..Default::default()
        };
        let job = Job {
            summary,
            cost,
            seq,
            attempts: 0,
            epoch_floor: 0,
            workers_lost: BTreeMap::new(),
            progress: progress_channel(&id, JobState::Queued, "", ""),
            image_hash: String::new(),
            stats_json: String::new(),
            preview: None,
        };
        // A job the client was told about must survive a restart: on disk before the reply,
        // and queued only then. It counts against the quota meanwhile.
        let (done, written) = std::sync::mpsc::channel();
        st.journal.put_then(
            job.stored(),
            Box::new(move |r| {
                let _ = done.send(r);
            }),
        );
        st.add_job(id.clone(), job);
        drop(st);
        let written = written
            .recv()
            .unwrap_or_else(|_| Err("the job store's writer is gone".into()));
        let mut st = self.lock();
        if let Err(e) = written {
            error!(job = %id, error = %e, "job not recorded");
            if let Some(job) = st.jobs.remove(&id) {
                st.by_seq.remove(&job.seq);
            }
            return Err(Status::internal(format!(
                "the job could not be recorded: {e}"
            )));
        }
        // Cancelled meanwhile: not queued.
        if st
            .jobs
            .get(&id)
            .is_some_and(|j| j.summary.state() == JobState::Queued)
        {
            st.queue.push(id.clone(), spec.priority, seq);
            info!(job = %id, user = %owner, scene = %spec.scene, width = spec.width, height = spec.height, spp = spec.spp, priority = spec.priority, "job queued");
            self.try_start(&mut st);
        }
        Ok(id)
    }

    /// Refuses a frame whose needs pass the limits (see `admission`).
    pub(super) fn admit(
        &self,
        frame: &rayfarm_core::render::local::FrameSpec,
    ) -> Result<(), Status> {
        let needs = Needs::of(frame)
            .ok_or_else(|| Status::invalid_argument("the image does not fit the tile grid"))?;
        let dir = &self.config.data_dir;
        let free = free_disk(dir).map_err(|e| {
            Status::internal(format!("free disk of {} unknown: {e}", dir.display()))
        })?;
        needs
            .check(self.config.max_frame_bytes, dir, free)
            .map_err(|reason| {
                warn!(%reason, "job refused");
                Status::resource_exhausted(reason)
            })
    }

    /// The directory and manifest of `scene`, resolved under the scene root (see
    /// [`scene_ref`]). Errors name the scene and the position of a fault in its manifest,
    /// never the manifest's text nor anything about paths outside the root.
    pub fn open_scene(&self, scene: &str) -> Result<(PathBuf, Manifest), Status> {
        let dir = scene_ref::resolve(
            &self.config.scene_root,
            scene,
            self.config.allow_absolute_scenes,
        )
        .map_err(|e| match e {
            scene_ref::SceneRefError::Missing => Status::failed_precondition(e.to_string()),
            scene_ref::SceneRefError::Escapes(_) | scene_ref::SceneRefError::Absolute(_) => {
                Status::invalid_argument(e.to_string())
            }
            scene_ref::SceneRefError::NotFound(_) => Status::not_found(e.to_string()),
            scene_ref::SceneRefError::Root(..) => {
                error!(error = %e, "scene root unusable");
                Status::unavailable(format!(
                    "scene {scene:?}: the coordinator's scene root is unusable"
                ))
            }
        })?;
        let manifest = Manifest::load(&dir)
            .map_err(|e| Status::failed_precondition(format!("scene {scene:?}: {e}")))?;
        Ok((dir, manifest))
    }

    /// Refuses (`RESOURCE_EXHAUSTED`) a job of `cost` that would take `owner` past a quota.
    pub(super) fn check_quota(&self, st: &State, owner: &str, cost: u64) -> Result<(), Status> {
        let (jobs, queued) = st
            .jobs
            .values()
            .filter(|j| j.summary.owner == owner && !is_terminal(j.summary.state()))
            .fold((0usize, 0u64), |(n, c), j| {
                (n + 1, c.saturating_add(j.cost))
            });
        let who = if owner.is_empty() { "anonymous" } else { owner };
        if jobs >= self.config.max_jobs_per_user {
            warn!(user = %who, jobs, "job refused: queued-jobs quota");
            return Err(Status::resource_exhausted(format!(
                "user {who} has {jobs} jobs queued or running, the most allowed \
                 (--max-jobs-per-user {})",
                self.config.max_jobs_per_user
            )));
        }
        let max = self.config.max_pixel_samples_per_user;
        if queued.saturating_add(cost) > max {
            warn!(user = %who, queued, cost, "job refused: pixel-samples quota");
            return Err(Status::resource_exhausted(format!(
                "user {who} has {queued} pixel-samples queued or running; this job's {cost} \
                 would pass the quota of {max} (--max-pixel-samples-per-user)"
            )));
        }
        Ok(())
    }

    /// Cancels a queued or running job for `user` (`None` without user tokens: anyone may);
    /// returns its state afterwards. Only the job's owner or an admin may cancel it.
    pub fn cancel(self: &Arc<Self>, id: &str, user: Option<&User>) -> Result<JobState, Status> {
        let mut st = self.lock();
        let job = st.jobs.get(id).ok_or_else(|| not_found(id))?;
        check_owner(job, user, "cancel")?;
        let state = job.summary.state();
        if is_terminal(state) {
            return Ok(state);
        }
        if st.queue.remove(id) || st.preparing.as_deref() == Some(id) {
            // A frame being prepared is dropped when it is ready (`begin`).
            set_state(&mut st, id, JobState::Cancelled, "");
        } else if st.running.as_ref().is_some_and(|f| f.job_id == id) {
            if let Some(frame) = st.running.take() {
                end_frame(&mut st, &frame);
            }
            set_state(&mut st, id, JobState::Cancelled, "");
            self.try_start(&mut st);
        }
        info!(job = %id, user = %user.map_or("", |u| u.name.as_str()), "job cancelled");
        Ok(st
            .jobs
            .get(id)
            .map_or(JobState::Cancelled, |j| j.summary.state()))
    }

    /// Sets the priority of job `id` for `user` (as [`cancel`](Self::cancel) checks it);
    /// a queued job moves to its new place in the queue. Returns its state.
    pub fn set_priority(
        &self,
        id: &str,
        priority: i32,
        user: Option<&User>,
    ) -> Result<JobState, Status> {
        let mut st = self.lock();
        let job = st.jobs.get_mut(id).ok_or_else(|| not_found(id))?;
        check_owner(job, user, "change the priority of")?;
        let state = job.summary.state();
        if state != JobState::Queued {
            return Err(Status::failed_precondition(format!(
                "job {id} is {}: only a queued job's priority can change",
                state_name(state)
            )));
        }
        if let Some(spec) = job.summary.spec.as_mut() {
            spec.priority = priority;
        }
        let (stored, seq) = (job.stored(), job.seq);
        st.journal.put(stored);
        if st.queue.remove(id) {
            st.queue.push(id.to_string(), priority, seq);
        }
        info!(job = %id, user = %user.map_or("", |u| u.name.as_str()), priority, "job priority changed");
        Ok(state)
    }

    /// The previews of job `id`'s latest frame, while they are kept.
    pub fn previews(&self, id: &str) -> Result<Arc<Previews>, Status> {
        let st = self.lock();
        let job = st.jobs.get(id).ok_or_else(|| not_found(id))?;
        job.preview.clone().ok_or_else(|| {
            Status::failed_precondition(format!(
                "job {id} has no preview: it is {} and previews are kept only for the running \
                 frame and the last {KEPT_PREVIEWS} frames started by this coordinator",
                state_name(job.summary.state())
            ))
        })
    }

    /// Jobs, newest first.
    pub fn list(&self, page: JobPage) -> (Vec<proto::JobSummary>, Option<u64>) {
        let st = self.lock();
        let mut ids = st.by_seq.range(..=page.from_seq).rev();
        let jobs = ids
            .by_ref()
            .take(page.size)
            .filter_map(|(_, id)| st.jobs.get(id))
            .map(|j| j.summary.clone())
            .collect();
        (jobs, ids.next().map(|(&seq, _)| seq))
    }

    /// A receiver of a job's progress events.
    pub fn watch(&self, id: &str) -> Result<watch::Receiver<proto::WatchJobResponse>, Status> {
        let st = self.lock();
        st.jobs
            .get(id)
            .map(|j| j.progress.subscribe())
            .ok_or_else(|| not_found(id))
    }

    /// Where a finished job's image is, with its statistics and hash.
    pub fn result(
        &self,
        id: &str,
        format: proto::ImageFormat,
    ) -> Result<(PathBuf, String, String), Status> {
        let st = self.lock();
        let job = st.jobs.get(id).ok_or_else(|| not_found(id))?;
        if job.summary.state() != JobState::Succeeded {
            return Err(Status::failed_precondition(format!(
                "job {id} is {} and has no result",
                state_name(job.summary.state())
            )));
        }
        Ok((
            results::image_path(&self.config.data_dir, id, format),
            job.stats_json.clone(),
            job.image_hash.clone(),
        ))
    }
}

/// Refuses (`PERMISSION_DENIED`) `user` doing `action` to `job` unless it is the job's owner
/// or an admin; without user tokens (`None`) anyone may.
fn check_owner(job: &Job, user: Option<&User>, action: &str) -> Result<(), Status> {
    match user {
        Some(user) if !user.admin && job.summary.owner != user.name => {
            let id = &job.summary.job_id;
            warn!(job = %id, user = %user.name, owner = %job.summary.owner, action, "refused: not the owner");
            Err(Status::permission_denied(format!(
                "job {id} belongs to another user: only its owner or an admin may {action} it"
            )))
        }
        _ => Ok(()),
    }
}

/// Pixels times samples per pixel of a spec as given (a field left 0 counts as 1).
pub(super) fn spec_cost(spec: &proto::JobSpec) -> u64 {
    [spec.width, spec.height, spec.spp]
        .iter()
        .map(|&v| u64::from(v.max(1)))
        .product()
}
