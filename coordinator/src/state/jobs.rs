//! The user API's side of the state: jobs submitted, admitted, listed, watched, cancelled
//! and fetched.

use rayfarm_machine::coordinator::cluster::PriorityRefused;

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
        let record = st
            .machine
            .submit(now(), spec, cost, &owner)
            .map_err(Status::resource_exhausted)?;
        let id = record.id().to_string();
        // A job the client was told about must survive a restart: on disk before the reply,
        // and queued only then. It counts against the quota meanwhile.
        let (done, written) = std::sync::mpsc::channel();
        st.journal.put_then(
            StoredJob::from_record(&record),
            Box::new(move |r| {
                let _ = done.send(r);
            }),
        );
        let view = JobView {
            progress: progress_channel(&record),
            preview: None,
        };
        st.views.insert(id.clone(), view);
        drop(st);
        let written = written
            .recv()
            .unwrap_or_else(|_| Err("the job store's writer is gone".into()));
        let mut st = self.lock();
        let failed = written.as_ref().err().cloned();
        let input = Input::Recorded {
            job_id: id.clone(),
            result: written,
        };
        self.feed(&mut st, input);
        if let Some(e) = failed {
            st.views.remove(&id);
            return Err(Status::internal(format!(
                "the job could not be recorded: {e}"
            )));
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

    /// Cancels a queued or running job for `user` (`None` without user tokens: anyone may);
    /// returns its state afterwards. Only the job's owner or an admin may cancel it. May read
    /// the store (a job finished long ago): call it off the async runtime.
    pub fn cancel(self: &Arc<Self>, id: &str, user: Option<&User>) -> Result<JobState, Status> {
        let mut st = self.lock();
        let Some(job) = st.machine.job(id) else {
            drop(st);
            // Finished long ago: there is nothing to cancel.
            let job = self.stored_record(id)?;
            check_owner(&job, user, "cancel")?;
            return Ok(job.state());
        };
        check_owner(job, user, "cancel")?;
        let (state, actions) = st.machine.cancel(now(), id).ok_or_else(|| not_found(id))?;
        self.carry_out(&mut st, actions, Instant::now());
        info!(job = %id, user = %user.map_or("", |u| u.name.as_str()), "job cancelled");
        Ok(state)
    }

    /// Sets the priority of job `id` for `user` (as [`cancel`](Self::cancel) checks it);
    /// a queued job moves to its new place in the queue. Returns its state. May read the
    /// store: call it off the async runtime.
    pub fn set_priority(
        self: &Arc<Self>,
        id: &str,
        priority: i32,
        user: Option<&User>,
    ) -> Result<JobState, Status> {
        let not_queued = |state| {
            Status::failed_precondition(format!(
                "job {id} is {}: only a queued job's priority can change",
                state_name(state)
            ))
        };
        let mut st = self.lock();
        let Some(job) = st.machine.job(id) else {
            drop(st);
            let job = self.stored_record(id)?;
            check_owner(&job, user, "change the priority of")?;
            return Err(not_queued(job.state()));
        };
        check_owner(job, user, "change the priority of")?;
        let (state, actions) =
            st.machine
                .set_priority(id, priority)
                .map_err(|refused| match refused {
                    PriorityRefused::NotFound => not_found(id),
                    PriorityRefused::NotQueued(state) => not_queued(state),
                })?;
        self.carry_out(&mut st, actions, Instant::now());
        info!(job = %id, user = %user.map_or("", |u| u.name.as_str()), priority, "job priority changed");
        Ok(state)
    }

    /// The previews of job `id`'s latest frame, while they are kept. May read the store (a
    /// job finished long ago): call it off the async runtime.
    pub fn previews(&self, id: &str) -> Result<Arc<Previews>, Status> {
        let state = {
            let st = self.lock();
            if let Some(preview) = st.views.get(id).and_then(|v| v.preview.clone()) {
                return Ok(preview);
            }
            st.machine.job(id).map(|j| j.state())
        };
        let state = match state {
            Some(state) => state,
            None => self.stored_record(id)?.state(),
        };
        Err(Status::failed_precondition(format!(
            "job {id} has no preview: it is {} and previews are kept only for the running \
             frame and the last {KEPT_PREVIEWS} frames started by this coordinator",
            state_name(state)
        )))
    }

    /// Jobs, newest first, read from the store, each as the machine has it if it holds the
    /// job (its record may be newer than the stored one). A job whose first record is not
    /// stored yet is not listed: its submitter has not been told of it either. Call it off
    /// the async runtime.
    pub fn list(&self, page: JobPage) -> Result<(Vec<proto::JobSummary>, Option<u64>), Status> {
        let (stored, next) = self
            .store
            .page(page.size, page.from_seq)
            .map_err(|e| Status::unavailable(format!("the job store cannot be read: {e}")))?;
        let st = self.lock();
        let jobs = stored
            .into_iter()
            .filter_map(|stored| match st.machine.job(stored.id()) {
                Some(held) => Some(held.summary.clone()),
                None => stored.summary,
            })
            .collect();
        Ok((jobs, next))
    }

    /// A job's latest progress event, while it has a progress channel (queued, running, or
    /// among the last finished); never reads the store, so the runtime may call it.
    pub fn progress(&self, id: &str) -> Option<proto::WatchJobResponse> {
        self.lock()
            .views
            .get(id)
            .map(|v| v.progress.borrow().clone())
    }

    /// A receiver of a job's progress events. A job finished long ago has no channel any
    /// more: it gets one holding its final event, statistics read from the store. Call it
    /// off the async runtime (it may wait for the store).
    pub fn watch(&self, id: &str) -> Result<watch::Receiver<proto::WatchJobResponse>, Status> {
        let mut record = {
            let st = self.lock();
            if let Some(view) = st.views.get(id) {
                return Ok(view.progress.subscribe());
            }
            st.machine.job(id).cloned()
        };
        match &mut record {
            Some(record) => record.stats_json = self.stored_stats(id),
            None => record = Some(self.stored_record(id)?),
        }
        let record = record.unwrap_or_default();
        Ok(progress_channel(&record).subscribe())
    }

    /// Where a finished job's image is, with its statistics and hash. Call it off the async
    /// runtime (it may wait for the store).
    pub fn result(
        &self,
        id: &str,
        format: proto::ImageFormat,
    ) -> Result<(PathBuf, String, String), Status> {
        let held = {
            let st = self.lock();
            st.machine.job(id).map(|job| {
                // A job that just finished: its final record may still be on its way to the
                // store, and its progress channel holds the statistics.
                let recent = st
                    .views
                    .get(id)
                    .map(|v| v.progress.borrow().stats_json.clone())
                    .filter(|s| !s.is_empty());
                (job.state(), job.image_hash.clone(), recent)
            })
        };
        let (state, hash, stats_json) = match held {
            Some((state, hash, recent)) => {
                let stats = match (state, recent) {
                    (JobState::Succeeded, Some(stats)) => stats,
                    (JobState::Succeeded, None) => self.stored_stats(id),
                    _ => String::new(),
                };
                (state, hash, stats)
            }
            None => {
                let job = self.stored_record(id)?;
                (job.state(), job.image_hash, job.stats_json)
            }
        };
        if state != JobState::Succeeded {
            return Err(Status::failed_precondition(format!(
                "job {id} is {} and has no result",
                state_name(state)
            )));
        }
        Ok((
            results::image_path(&self.config.data_dir, id, format),
            stats_json,
            hash,
        ))
    }

    /// Job `id`'s stored record, for a job the machine no longer holds (finished long ago):
    /// `NOT_FOUND` if there is none.
    fn stored_record(&self, id: &str) -> Result<JobRecord, Status> {
        match self.store.get(id) {
            Ok(stored) => stored
                .and_then(StoredJob::into_record)
                .ok_or_else(|| not_found(id)),
            Err(e) => {
                error!(job = %id, error = %e, "the job's record could not be read");
                Err(Status::unavailable(format!(
                    "job {id}'s record cannot be read from the job store"
                )))
            }
        }
    }

    /// A finished job's statistics from the store (the machine keeps none); empty, and
    /// logged, if they cannot be read.
    fn stored_stats(&self, id: &str) -> String {
        match self.store.get(id) {
            Ok(Some(stored)) => stored.stats_json,
            Ok(None) => {
                warn!(job = %id, "no stored record: its statistics are not known");
                String::new()
            }
            Err(e) => {
                error!(job = %id, error = %e, "the job's statistics could not be read");
                String::new()
            }
        }
    }
}

/// Refuses (`PERMISSION_DENIED`) `user` doing `action` to `job` unless it is the job's owner
/// or an admin; without user tokens (`None`) anyone may.
fn check_owner(job: &JobRecord, user: Option<&User>, action: &str) -> Result<(), Status> {
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
