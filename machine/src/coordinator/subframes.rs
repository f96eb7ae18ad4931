//! Progressive frames on the cluster: a job's samples in subframes, each rendered as a frame
//! of its own on the workers (its own frame id, dealt afresh, with the same credit and epoch
//! rules) and committed into the one film, which adds the subframes' fixed-point sums. The
//! film after the last subframe holds the one-pass sums exactly (`core::progressive`).
//!
//! Faults: a worker lost mid-subframe bumps only the current subframe's unfinished tiles
//! (the committed subframes are in the film); every worker lost, or a restarted
//! coordinator, starts the job over from its first subframe (the film is made anew).

use rayfarm_core::progressive::{Progressive, Samples};
use rayfarm_core::tile::credit::TILE_CREDIT;
use rayfarm_core::tile::ledger::TileLedger;
use rayfarm_proto as proto;
use tracing::info;

use super::{Member, Outgoing, RunningFrame};
use crate::coordinator::accusations::Accusations;
use crate::coordinator::grants::Grants;
use rayfarm_core::schedule::round_index::RoundIndex;
use rayfarm_core::schedule::tiles::HandOuts;

/// The subframes of a job of `spec` with `spp` samples per pixel.
pub fn plan(spec: &proto::JobSpec, spp: u32) -> Vec<Samples> {
    Progressive::from_field(spec.progressive.map(|p| p.subframe_spp)).subframes(spp)
}

/// The frame id of subframe `subframe` of job `job_id` (see [`RunningFrame::frame_id`]).
pub fn subframe_id(job_id: &str, subframe: usize) -> String {
    if subframe == 0 {
        job_id.to_string()
    } else {
        format!("{job_id}~{subframe}")
    }
}

/// The job of a frame id [`subframe_id`] made.
pub fn job_of_frame(frame_id: &str) -> &str {
    frame_id.split_once('~').map_or(frame_id, |(job, _)| job)
}

impl RunningFrame {
    /// The name the workers know the current subframe's frame by: the job id for the first
    /// (so a one-pass job's frame is the job), `JOB~K` for subframe K. Each subframe being a
    /// frame of its own, the workers' frame start, early bundles, end and statistics work
    /// unchanged, and nothing of one subframe can be taken for another's.
    pub fn frame_id(&self) -> String {
        subframe_id(&self.job_id, self.subframe)
    }

    /// The samples the current subframe renders.
    pub fn samples(&self) -> Samples {
        self.subframes[self.subframe]
    }

    /// Subframes of the job, and those committed so far.
    pub fn subframes(&self) -> (u32, u32) {
        let done = self.subframe as u32 + u32::from(self.ledger.is_complete());
        (done, self.subframes.len() as u32)
    }

    /// Samples of every pixel in the subframes committed before the current one.
    pub fn samples_before(&self) -> u32 {
        self.samples().first
    }

    /// Rounds planned in the whole frame, every subframe's.
    pub fn rounds_total(&self) -> u64 {
        self.rounds_before + self.round
    }

    /// Whether another subframe follows the current one.
    pub fn has_next_subframe(&self) -> bool {
        self.subframe + 1 < self.subframes.len()
    }

    /// The current subframe is complete (its tiles committed to the film): ends its frame on
    /// the members (they send its statistics) and starts the next one on the same members,
    /// dealt afresh like a frame's start, every tile at an epoch above all the last one
    /// used. Its camera rays carry the next samples; its sums add to the film's.
    pub fn next_subframe(&mut self) -> Vec<Outgoing> {
        let mut out = self.end_messages();
        let floor = self.epoch_floor();
        self.subframe += 1;
        let grid = *self.ledger.grid();
        self.ledger = TileLedger::new(grid, TILE_CREDIT)
            .with_samples(self.samples().count)
            .starting_at(floor);
        self.rounds_before += self.round;
        self.round = 0;
        // A report of the subframe before asks nothing of this one.
        self.round_asked = false;
        self.grants = Grants::new(grid.count());
        self.hand_outs = HandOuts::default();
        self.tasks = super::TaskDirections::default();
        self.accusations = Accusations::default();
        // The workers open the next subframe as a new frame, with no holders yet.
        self.sent_holders.reset();
        self.index = RoundIndex::new(
            &self.domain_bytes,
            self.schedule == proto::Schedule::Predictive,
        )
        .copying_from(self.options.copy_rays);
        let members: Vec<(u32, Member)> = std::mem::take(&mut self.members)
            .into_iter()
            .map(|(k, m)| {
                self.segments_before += m.segments;
                self.segments_now -= m.segments;
                (k, Member::new(m.peer_address, m.rounds.cache_bytes))
            })
            .collect();
        info!(
            subframe = self.subframe,
            first_sample = self.samples().first,
            samples = self.samples().count,
            "next subframe"
        );
        out.extend(self.start(members));
        out
    }
}
