//! Frames: starting the next queued job (its scene read and film created off the lock),
//! sending what the frame machine decides, finishing and failing frames.

use super::*;

/// How long a frame's start waits for its scene's manifest.
const FRAME_SCENE_READ_TIMEOUT: Duration = Duration::from_secs(10);

impl Coordinator {
    /// Starts the next queued job if the cluster is free and has workers.
    pub(super) fn try_start(self: &Arc<Self>, st: &mut State) {
        while !st.stopping
            && st.running.is_none()
            && st.preparing.is_none()
            && !st.workers.is_empty()
        {
            let Some(id) = st.queue.pop() else {
                return;
            };
            let Some(spec) = st.jobs.get(&id).and_then(|j| j.summary.spec.clone()) else {
                continue;
            };
            let _span = info_span!("start_job", job = %id).entered();
            let attempts = st.jobs.get(&id).map_or(0, |j| j.attempts);
            if attempts >= self.config.max_attempts {
                // A job that kills the coordinator (or loses every worker) each time it runs
                // would otherwise be a crash loop; the queue moves on.
                let reason = format!(
                    "its frame started {attempts} times without finishing (the coordinator \
                     stopped or every worker was lost each time); --max-attempts is {}",
                    self.config.max_attempts
                );
                set_state(st, &id, JobState::Failed, &reason);
                continue;
            }
            // The scene's manifest is read and the film file created off the lock; no other
            // frame starts meanwhile.
            st.preparing = Some(id.clone());
            let (this, job) = (self.clone(), id.clone());
            let prepare = move || {
                let prepared = this.prepare_frame(&job, spec);
                let mut st = this.lock();
                this.begin(&mut st, &job, prepared);
            };
            if let Err(e) = std::thread::Builder::new()
                .name("prepare-frame".into())
                .spawn(prepare)
            {
                st.preparing = None;
                let reason = format!("no thread to prepare its frame: {e}");
                set_state(st, &id, JobState::Failed, &reason);
                continue;
            }
            return;
        }
    }

    /// Starts the frame `prepare_frame` made for job `id`, unless the job was cancelled, the
    /// coordinator is stopping, or every worker left meanwhile (then it is queued again).
    pub(super) fn begin(
        self: &Arc<Self>,
        st: &mut State,
        id: &str,
        prepared: Result<Running, Status>,
    ) {
        st.preparing = None;
        let Some(job) = st.jobs.get(id) else {
            return self.try_start(st);
        };
        let (attempts, floor) = (job.attempts, job.epoch_floor);
        if job.summary.state() != JobState::Queued || st.stopping {
            return self.try_start(st);
        }
        if st.workers.is_empty() {
            let priority = job.summary.spec.as_ref().map_or(0, |s| s.priority);
            let seq = job.seq;
            st.queue.push(id.to_string(), priority, seq);
            return;
        }
        let _span = info_span!("start_job", job = %id).entered();
        match prepared {
            Ok(mut frame) => {
                // A job started before (by a coordinator since restarted, or before its
                // workers were all lost) starts every tile at a new epoch, so rays and
                // results of the abandoned run still in flight are dropped as stale.
                frame.restart_epochs(attempts.max(floor));
                let members: Vec<(u32, Member)> = st
                    .workers
                    .iter()
                    .map(|(&k, w)| (k, Member::new(w.peer_address.clone(), w.cache_bytes)))
                    .collect();
                let planning = Instant::now();
                let out = frame.start(members);
                let m = rayfarm_node::metrics::coordinator();
                m.rounds.inc_by(frame.round);
                m.planning_seconds.observe(planning.elapsed().as_secs_f64());
                info!(
                    workers = out.len(),
                    tiles = frame.ledger.grid().count(),
                    attempt = attempts + 1,
                    "frame started"
                );
                if let Some(job) = st.jobs.get_mut(id) {
                    job.summary.started_unix_ms = unix_ms();
                    job.attempts = attempts.saturating_add(1);
                    // Numbered on from the job's last frame, so its previews' numbers only grow.
                    let floor = job.preview.as_ref().map_or(0, |p| p.sequence());
                    frame.previews = Arc::new(Previews::new(&frame.film, floor));
                    job.preview = Some(frame.previews.clone());
                }
                keep_preview(st, id);
                // The start is on disk before any worker hears of it: a frame that kills
                // the coordinator counts against the job's attempts all the same.
                st.starts += 1;
                let start = st.starts;
                let this = Arc::downgrade(self);
                let stored = Box::new(move |_| release_held(&this, start));
                set_state_then(st, id, JobState::Running, "", Some(stored));
                send(st, out);
                publish_progress(st, &frame);
                st.running = Some(frame);
            }
            Err(status) => {
                error!(error = %status.message(), "job cannot start");
                set_state(st, id, JobState::Failed, status.message());
                self.try_start(st);
            }
        }
    }

    /// `scene`'s manifest, read on a thread of its own and waited for at most `limit`: a
    /// read stuck on storage fails the job with a clear error instead of holding the queue
    /// (no other frame starts while one is prepared). The stuck thread is left to its read.
    fn read_scene_within(
        self: &Arc<Self>,
        scene: &str,
        limit: Duration,
    ) -> Result<Manifest, Status> {
        let (tx, rx) = std::sync::mpsc::channel();
        let (this, name) = (self.clone(), scene.to_string());
        std::thread::Builder::new()
            .name("read-scene".into())
            .spawn(move || {
                let _ = tx.send(this.open_scene(&name).map(|(_, manifest)| manifest));
            })
            .map_err(|e| Status::unavailable(format!("no thread to read the scene: {e}")))?;
        rx.recv_timeout(limit).unwrap_or_else(|_| {
            warn!(scene, "scene read at frame start timed out");
            Err(Status::deadline_exceeded(format!(
                "scene {scene:?}: its manifest could not be read within {limit:?} at the \
                 frame's start"
            )))
        })
    }

    pub(super) fn prepare_frame(
        self: &Arc<Self>,
        id: &str,
        spec: proto::JobSpec,
    ) -> Result<Running, Status> {
        // The scene was checked at submission; check again, it may have changed since.
        let manifest = self.read_scene_within(&spec.scene, FRAME_SCENE_READ_TIMEOUT)?;
        let frame = frame_spec(&spec, &manifest.camera).map_err(Status::invalid_argument)?;
        let domain_bytes = manifest.domains.iter().map(|d| d.bytes).collect();
        let spp = frame.spp;
        let frame = RunningFrame::new(
            now(),
            id.to_string(),
            spec,
            frame,
            domain_bytes,
            self.config.schedule_options,
            self.config.rounds,
        )
        .map_err(Status::invalid_argument)?;
        let grid = *frame.ledger.grid();
        let film = results::create_film(&self.config.data_dir, id, grid, spp)
            .map_err(|e| Status::internal(format!("{e:#}")))?;
        let film = Arc::new(film);
        let previews = Arc::new(Previews::new(&film, 0));
        Ok(Running {
            frame,
            film,
            previews,
        })
    }

    pub(super) fn fail_running(self: &Arc<Self>, st: &mut State, error: &str) {
        if let Some(frame) = st.running.take() {
            rayfarm_node::metrics::coordinator().frames_failed.inc();
            end_frame(st, &frame);
            // Statistics of its committed subframes are of no use now.
            st.finishing.retain(|_, f| f.job != frame.job_id);
            set_state(st, &frame.job_id, JobState::Failed, error);
        }
        self.try_start(st);
    }

    /// The running frame's current subframe has all its credit back and another follows:
    /// its tiles are in the film; its frame ends on the workers (their statistics are kept
    /// for the job's) and the next subframe starts on them at once.
    pub(super) fn next_subframe(self: &Arc<Self>, st: &mut State) {
        let Some(frame) = st.running.as_mut() else {
            return;
        };
        let wall = now().since(frame.started).as_secs_f64();
        let (done, total) = frame.subframes();
        info!(job = %frame.job_id, subframe = done, subframes = total, wall, "subframe committed");
        rayfarm_node::metrics::coordinator()
            .subframes_committed
            .inc();
        st.finishing.insert(
            frame.frame_id(),
            Finishing {
                job: frame.job_id.clone(),
                waiting: frame.members().collect(),
                reports: Vec::new(),
                done: None,
            },
        );
        let planning = Instant::now();
        let out = frame.next_subframe();
        let m = rayfarm_node::metrics::coordinator();
        m.rounds.inc_by(frame.round);
        m.planning_seconds.observe(planning.elapsed().as_secs_f64());
        send(st, out);
        if let Some(f) = st.running.as_ref() {
            publish_progress(st, f);
        }
    }

    /// The running frame has all its credit back: end it on the workers, collect their
    /// statistics, write the results, and move on to the next job at once.
    pub(super) fn complete(self: &Arc<Self>, st: &mut State) {
        let Some(frame) = st.running.take() else {
            return;
        };
        let wall = now().since(frame.started).as_secs_f64();
        info!(job = %frame.job_id, wall, rounds = frame.rounds_total(), "frame complete");
        let m = rayfarm_node::metrics::coordinator();
        m.frames_committed.inc();
        m.subframes_committed.inc();
        end_frame(st, &frame);
        let (done_tx, done_rx) = oneshot::channel();
        st.finishing.insert(
            frame.frame_id(),
            Finishing {
                job: frame.job_id.clone(),
                waiting: frame.members().collect(),
                reports: Vec::new(),
                done: Some(done_tx),
            },
        );
        let this = self.clone();
        tokio::spawn(async move {
            let _ = tokio::time::timeout(this.config.report_timeout, done_rx).await;
            this.finish(frame, wall).await;
        });
        self.try_start(st);
    }

    async fn finish(self: Arc<Self>, running: Running, wall: f64) {
        let Running {
            frame,
            film,
            previews,
        } = running;
        let id = frame.job_id.clone();
        let reports = {
            // The last subframe's reports, and every earlier one's that came in.
            let mut st = self.lock();
            let mut reports = Vec::new();
            st.finishing.retain(|_, f| {
                let mine = f.job == id;
                if mine {
                    reports.append(&mut f.reports);
                }
                !mine
            });
            WorkerFrameStats::merge_by_worker(reports)
        };
        let spec = &frame.frame;
        let mut stats = ClusterStats {
            job_id: id.clone(),
            scene: frame.spec.scene.clone(),
            schedule: schedule_name(frame.schedule).into(),
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
        stats.absorb(reports);
        let data_dir = self.config.data_dir.clone();
        let job = id.clone();
        let written = tokio::task::spawn_blocking(move || {
            // The film file goes with `film` once both images are written; the final
            // preview is made of it first.
            let written = results::write(&data_dir, &job, &film, &mut stats);
            previews.seal();
            written
        })
        .await;
        let mut st = self.lock();
        match written {
            Ok(Ok((json, hash))) => {
                if let Some(job) = st.jobs.get_mut(&id) {
                    job.stats_json = json;
                    job.image_hash = hash.clone();
                }
                info!(job = %id, %hash, "results written");
                set_state(&mut st, &id, JobState::Succeeded, "");
            }
            Ok(Err(e)) => set_state(&mut st, &id, JobState::Failed, &format!("{e:#}")),
            Err(e) => set_state(&mut st, &id, JobState::Failed, &format!("{e}")),
        }
    }
}

pub(super) fn send(st: &mut State, out: Vec<Outgoing>) {
    if st.stored_starts < st.starts {
        let start = st.starts;
        st.held.extend(out.into_iter().map(|o| (start, o)));
        return;
    }
    deliver(st, out);
}

/// Frame start `start` is on disk: the messages held for it (and earlier starts) go out.
pub(super) fn release_held(coordinator: &Weak<Coordinator>, start: u64) {
    let Some(c) = coordinator.upgrade() else {
        return;
    };
    let mut st = c.lock();
    st.stored_starts = st.stored_starts.max(start);
    let ready = st.held.iter().take_while(|(s, _)| *s <= start).count();
    let out: Vec<Outgoing> = st.held.drain(..ready).map(|(_, o)| o).collect();
    deliver(&st, out);
}

pub(super) fn deliver(st: &State, out: Vec<Outgoing>) {
    for (key, msg) in out {
        if let Some(w) = st.workers.get(&key) {
            // A closed channel means the worker is going; worker_gone will handle it.
            let _ = w.tx.send(Ok(msg));
        }
    }
}

pub(super) fn end_frame(st: &mut State, frame: &RunningFrame) {
    send(st, frame.end_messages());
}

/// Job `id`'s frame has started: its previews are kept, and the oldest frame's beyond
/// [`KEPT_PREVIEWS`] let go.
fn keep_preview(st: &mut State, id: &str) {
    st.previewed.retain(|j| j != id);
    st.previewed.push_back(id.to_string());
    while st.previewed.len() > KEPT_PREVIEWS {
        if let Some(old) = st.previewed.pop_front()
            && let Some(job) = st.jobs.get_mut(&old)
        {
            job.preview = None;
        }
    }
}

pub(super) fn publish_progress(st: &State, frame: &RunningFrame) {
    let Some(job) = st.jobs.get(&frame.job_id) else {
        return;
    };
    let (done, total, rate, eta) = frame.progress(now());
    let preview_sequence = job.preview.as_ref().map_or(0, |p| p.sequence());
    let (subframes_done, subframes) = frame.subframes();
    job.progress.send_modify(|p| {
        p.preview_sequence = preview_sequence;
        p.subframes_done = subframes_done;
        p.subframes = subframes;
        p.tiles_done = done;
        p.tiles_total = total;
        p.round = frame.round;
        p.rays_per_second = rate;
        p.eta_seconds = eta;
    });
}
