//! Speculative ray placement (the predictive schedule of Park, Fussell and Navrátil): a new ray
//! is queued at once in every domain with geometry along it, instead of in the nearest one
//! and then, after a miss there, in the next. Each copy is traced on its own; their verdicts
//! come back to the ray's group, where the ray was born, and once all are in, the ray
//! concludes exactly as tracing it one domain at a time would have.
//!
//! Why: a ray crossing k domains costs k trips through the queues, and each trip can cost a
//! domain load. Placed speculatively, a ray generation needs one visit per domain, whatever
//! the paths' lengths. The price is tracing copies beyond a radiance ray's hit or a shadow
//! ray's occluder, which the answer then ignores.
//!
//! How far ahead a ray is copied is a knob (`schedule::speculation_depth`): the copies go out
//! in windows, nearest domains first, and the next window only once the last one's verdicts
//! are all in and none ended the ray. Every window is a prefix of what is left of the path,
//! so the outcome is the same whatever the windows (the nearest domain with a hit, or any
//! occluder, is always in the first window that has one).
//!
//! A volume ray's copy returns its brick's composited segments (`render::dvr::Segment`: the
//! premultiplied colour and opacity of each stretch of the ray between block faces), one
//! verdict each, then a closing verdict that counts them; the group composites them in order
//! along the ray, the fold the chained trace makes brick after brick, so the bits agree.
//! With shadows, a segment that reflects a light's light is followed by one more verdict per
//! such light ([`Verdict::Light`]), counted by the closing verdict too; the group sends the
//! shadow rays as it folds the segment, as the chained trace does. A brick with surfaces in it
//! sends its nearest hit too ([`Verdict::VolumeHit`], counted with the segments, which stop
//! at it), or a shadow ray's [`Verdict::Blocked`] alone.

mod verdict;

pub use verdict::{MAX_SEGMENTS, SegmentLight, SurfaceHit, Verdict};

use super::dvr::Segment;
use crate::ray::RayKind;
use crate::ray::RayRecord;
use crate::schedule::speculation_depth::{Depth, Windows};
use crate::schedule::speculative::Generations;
use crate::wire::VerdictRecord;

/// All verdicts of a ray combined.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Outcome {
    /// Some copy found an occluder.
    pub blocked: bool,
    /// The nearest place along the ray where a copy found an occluder.
    pub blocker: Option<u32>,
    /// The hit of the nearest domain that has one.
    pub nearest: Option<SurfaceHit>,
    /// A volume ray's segments from all its bricks, in order along the ray once concluded.
    pub segments: Vec<Segment>,
    /// With shadows, the segments' lights, in order of segment then light once concluded.
    pub lights: Vec<SegmentLight>,
}

impl Outcome {
    fn add(&mut self, verdict: Verdict) {
        match verdict {
            Verdict::Clear | Verdict::VolumeEnd(_) => {}
            Verdict::Segment(seg) => self.segments.push(seg),
            Verdict::Light(light) => self.lights.push(light),
            Verdict::Blocked(order) => {
                self.blocked = true;
                self.blocker = Some(self.blocker.map_or(order, |b| b.min(order)));
            }
            Verdict::Hit(hit) | Verdict::VolumeHit(hit) => {
                if self.nearest.is_none_or(|n| hit.order < n.order) {
                    self.nearest = Some(hit);
                }
            }
        }
    }

    /// Where along the ray it ended, if it did (as a place among the domains with geometry
    /// along it): a radiance ray at its nearest hit, a shadow ray at its nearest occluder.
    fn ended(&self, ray: &RayRecord) -> Option<u32> {
        match ray.kind() {
            RayKind::Radiance => self.nearest.map(|h| h.order),
            RayKind::Shadow => self.blocker,
        }
    }
}

/// A ray waiting for its copies' verdicts. It keeps the ray's credit: copies carry none.
struct Group {
    ray: RayRecord,
    /// The domains with geometry along the ray, nearest first.
    path: Vec<u32>,
    /// How many of them have been sent copies (the windows so far).
    copied: usize,
    /// The worker holding the group, named in the copies.
    resolver: u32,
    /// Copies of the current window whose last verdict is still to come.
    waiting: u32,
    /// Segments announced by closing verdicts minus segments received: a copy's segments
    /// may arrive before or after its closing verdict, so this dips below zero meanwhile.
    segments_due: i64,
    /// Which places along `path` have answered.
    answered: Answered,
    /// A volume verdict came: the ray concludes only once every copy has answered.
    volume: bool,
    /// The ray has concluded before all its copies answered (see [`Groups::skip`]): the
    /// group only counts the copies still out, so that their verdicts find it and the id is
    /// not reused while they may come.
    spent: bool,
    outcome: Outcome,
}

impl Group {
    /// Whether the verdicts so far decide the ray as the chained trace would, though copies
    /// farther along it have not answered: a shadow ray's occluder anywhere, or a radiance
    /// ray's hit with every nearer domain answered clear. Volume rays wait for all.
    fn decided_early(&self) -> bool {
        if self.volume {
            return false;
        }
        match self.ray.kind() {
            RayKind::Shadow => self.outcome.blocked,
            RayKind::Radiance => self.outcome.nearest.is_some_and(|h| {
                (h.order as usize) < self.path.len()
                    && self.answered.all_before(h.order as usize, self.path.len())
            }),
        }
    }

    /// Notes that the copy at `place` along the path answered.
    fn answer(&mut self, place: Option<usize>) {
        if let Some(p) = place.filter(|&p| p < self.path.len()) {
            self.answered.set(p, self.path.len());
        }
    }
}

/// Which places along a ray's path have answered: a bit each while the path has at most 64
/// places (every ray born here has a group, so a flag vector per group was an allocation
/// per ray on the worker's event loop), else a flag each.
#[derive(Default)]
struct Answered {
    bits: u64,
    long: Vec<bool>,
}

impl Answered {
    /// Notes that place `p` of a path of `len` places answered (`p < len`).
    fn set(&mut self, p: usize, len: usize) {
        if len <= 64 {
            self.bits |= 1 << p;
        } else {
            if self.long.is_empty() {
                self.long = vec![false; len];
            }
            self.long[p] = true;
        }
    }

    /// Whether every place before `n` (`n < len`) answered; true too while none has.
    fn all_before(&self, n: usize, len: usize) -> bool {
        if len <= 64 {
            let mask = (1u64 << n) - 1;
            self.bits == 0 || self.bits & mask == mask
        } else {
            self.long.is_empty() || self.long[..n].iter().all(|&a| a)
        }
    }
}

/// Why a verdict could not be taken.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum GroupError {
    /// No ray waits under this group: a verdict for a group already concluded, or never made.
    #[error("verdict for group {0}, which is not waiting")]
    Unknown(u32),
    /// The group's ray is another one: a stale verdict for an id since reused.
    #[error("verdict for group {0} names another ray")]
    Mismatch(u32),
    /// More segments than the copies announce, or than [`MAX_SEGMENTS`].
    #[error("verdict for group {0} brings more volume segments than its copies can send")]
    TooManySegments(u32),
}

/// The rays born here that wait for their copies; group ids are reused once concluded.
pub struct Groups {
    slots: Vec<Option<Group>>,
    free: Vec<u32>,
    /// Rays waiting per generation (`RayRecord::generation`).
    by_generation: Generations,
    /// How many domains ahead copies go, and what it learned.
    windows: Windows,
    /// Copies sent, in all windows (each is a segment traced).
    pub copies: u64,
    /// Windows sent after a ray's first (each a round trip of verdicts).
    pub extensions: u64,
    /// Copies dropped untraced because their ray had concluded ([`Groups::skip`]).
    pub skipped: u64,
    /// Rays concluded before all their copies answered.
    pub early: u64,
}

impl Default for Groups {
    fn default() -> Self {
        Self::new(Depth::Full)
    }
}

impl Groups {
    /// No rays waiting; copies go `depth` domains ahead.
    pub fn new(depth: Depth) -> Self {
        Groups {
            slots: Vec::new(),
            free: Vec::new(),
            by_generation: Generations::default(),
            windows: Windows::new(depth),
            copies: 0,
            extensions: 0,
            skipped: 0,
            early: 0,
        }
    }

    /// How far ahead copies go.
    pub fn depth(&self) -> Depth {
        self.windows.depth()
    }

    /// Makes `ray` wait for its copies in `path` (the domains with geometry along it, nearest
    /// first; non-empty: a ray that meets no domain concludes at once) and appends the copies
    /// of its first window to `out`, one per domain, without credit, their verdicts
    /// addressed to `resolver` (this worker).
    pub fn spread(
        &mut self,
        ray: RayRecord,
        path: Vec<u32>,
        resolver: u32,
        out: &mut Vec<RayRecord>,
    ) {
        debug_assert!(!path.is_empty());
        let group = Group {
            ray,
            path,
            copied: 0,
            resolver,
            waiting: 0,
            segments_due: 0,
            answered: Answered::default(),
            volume: false,
            spent: false,
            outcome: Outcome::default(),
        };
        self.by_generation.add(ray.generation());
        let id = match self.free.pop() {
            Some(id) => {
                self.slots[id as usize] = Some(group);
                id
            }
            None => {
                self.slots.push(Some(group));
                (self.slots.len() - 1) as u32
            }
        };
        self.next_window(id, out);
    }

    /// Sends group `id`'s next window of copies to `out`.
    fn next_window(&mut self, id: u32, out: &mut Vec<RayRecord>) {
        let Some(group) = self.slots[id as usize].as_mut() else {
            return;
        };
        let n = self.windows.window(&group.ray, &group.path, group.copied);
        let window = &group.path[group.copied..(group.copied + n).min(group.path.len())];
        if group.copied > 0 {
            self.windows.later_window(&group.ray, window);
        }
        group.waiting = window.len() as u32;
        group.copied += window.len();
        self.copies += window.len() as u64;
        let (ray, resolver) = (group.ray, group.resolver);
        // A copy carries only what tracing it reads: the group keeps the ray's weight and
        // credit, and a volume copy composites from nothing. So copies travel in the wire's
        // short layout (`wire::encode_batch`), and a copy traced here is the same as one
        // traced elsewhere.
        out.extend(window.iter().map(|&domain| RayRecord {
            domain,
            group: id,
            resolver,
            credit: 0,
            throughput: [0.0; 3],
            volume_rgb: [0.0; 3],
            volume_alpha: 0.0,
            ..ray
        }));
    }

    /// Takes one copy's verdict; returns the ray and its outcome once they decide it: when
    /// every copy has answered, or earlier when the answers so far decide it as the chained
    /// trace would (a shadow ray's occluder, a radiance ray's hit with every nearer domain
    /// clear). When the last copy of a window that did not end the ray answers, the copies of
    /// the next window go to `more` instead.
    pub fn settle(
        &mut self,
        record: &VerdictRecord,
        more: &mut Vec<RayRecord>,
    ) -> Result<Option<(RayRecord, Outcome)>, GroupError> {
        let id = record.group;
        let slot = self
            .slots
            .get_mut(id as usize)
            .ok_or(GroupError::Unknown(id))?;
        let group = slot.as_mut().ok_or(GroupError::Unknown(id))?;
        let r = &group.ray;
        if (r.tile, r.epoch, r.pixel, r.sample)
            != (record.tile, record.epoch, record.pixel, record.sample)
        {
            return Err(GroupError::Mismatch(id));
        }
        let verdict = record.verdict();
        // The copy's domain has been traced for the ray's generation: a clear verdict names
        // it, a hit or an occluder its place along the path (of a ray not concluded yet).
        let traced_in = match verdict {
            // (A concluded ray's group has given its path up: its clear verdicts teach nothing.)
            Verdict::Clear => Some(record.order).filter(|d| {
                let copied = group.path.get(..group.copied).unwrap_or_default();
                copied.contains(d)
            }),
            Verdict::Blocked(order) | Verdict::Hit(SurfaceHit { order, .. }) => {
                group.path.get(order as usize).copied()
            }
            _ => None,
        };
        if let Some(d) = traced_in {
            self.windows.visited(&group.ray, d);
        }
        if group.spent {
            // The ray concluded already: only count the copies still out.
            if !matches!(
                verdict,
                Verdict::Segment(_) | Verdict::Light(_) | Verdict::VolumeHit(_)
            ) {
                group.waiting = group.waiting.saturating_sub(1);
                if group.waiting == 0 {
                    *slot = None;
                    self.free.push(id);
                }
            }
            return Ok(None);
        }
        match verdict {
            Verdict::Segment(_) | Verdict::Light(_) | Verdict::VolumeHit(_) => {
                group.volume = true;
                let held = (group.outcome.segments.len() + group.outcome.lights.len()) as u32;
                if held >= MAX_SEGMENTS || (group.waiting == 0 && group.segments_due <= 0) {
                    return Err(GroupError::TooManySegments(id));
                }
                group.segments_due -= 1;
            }
            Verdict::VolumeEnd(n) => {
                group.volume = true;
                if n > MAX_SEGMENTS {
                    return Err(GroupError::TooManySegments(id));
                }
                group.segments_due += i64::from(n);
                group.waiting = group.waiting.saturating_sub(1);
            }
            Verdict::Clear => {
                // A clear verdict names its copy's domain; hits and occluders their place.
                let place = group.path[..group.copied]
                    .iter()
                    .position(|&d| d == record.order);
                group.answer(place);
                group.waiting = group.waiting.saturating_sub(1);
            }
            Verdict::Blocked(order) | Verdict::Hit(SurfaceHit { order, .. }) => {
                group.answer(Some(order as usize));
                group.waiting = group.waiting.saturating_sub(1);
            }
        }
        group.outcome.add(verdict);
        if group.waiting > 0 || group.segments_due != 0 {
            if group.waiting == 0 && group.segments_due < 0 {
                // Segments beyond what every copy announced: this group cannot conclude
                // as a chained trace would; drop it rather than conclude it wrongly.
                let dropped = slot.take().map(|g| g.ray);
                self.release(id, &dropped);
                return Err(GroupError::TooManySegments(id));
            }
            if group.decided_early() {
                // Farther copies still out cannot change the answer: conclude now, and keep
                // the id until they are in (or skipped) so no later ray takes it meanwhile.
                self.early += 1;
                group.spent = true;
                let ray = group.ray;
                let outcome = std::mem::take(&mut group.outcome);
                let ended = outcome.ended(&ray).map(|e| e as usize);
                let path = std::mem::take(&mut group.path);
                self.windows.learn(&ray, &path, ended);
                self.by_generation.remove(ray.generation());
                return Ok(Some((ray, outcome)));
            }
            return Ok(None);
        }
        let ended = group.outcome.ended(&group.ray);
        if ended.is_none() && !group.outcome.blocked && group.copied < group.path.len() {
            // The window found nothing that ends the ray: on to the next.
            self.extensions += 1;
            self.next_window(id, more);
            return Ok(None);
        }
        self.windows
            .learn(&group.ray, &group.path, ended.map(|e| e as usize));
        let done = self.slots[id as usize].take().map(|g| {
            let mut outcome = g.outcome;
            // Each segment's first sample is its own: the order along the ray, no ties.
            outcome.segments.sort_unstable_by_key(|s| s.first);
            outcome.lights.sort_unstable_by_key(|l| (l.first, l.light));
            (g.ray, outcome)
        });
        self.release(id, &done.as_ref().map(|d| d.0));
        Ok(done)
    }

    /// Whether `copy`, of a ray born here, may be dropped untraced because its ray has
    /// concluded without it (a nearer domain ended it); if so the copy counts as answered.
    /// The answer the ray concluded with stays the chained trace's, so skipping copies
    /// changes no bit of the image, only the segments traced (and, on a cluster, the copies
    /// moved).
    pub fn skip(&mut self, copy: &RayRecord) -> bool {
        let id = copy.group;
        let Some(slot) = self.slots.get_mut(id as usize) else {
            return false;
        };
        let Some(group) = slot.as_mut().filter(|g| g.spent) else {
            return false;
        };
        let r = &group.ray;
        if (r.tile, r.epoch, r.pixel, r.sample, r.depth, r.kind)
            != (
                copy.tile,
                copy.epoch,
                copy.pixel,
                copy.sample,
                copy.depth,
                copy.kind,
            )
            || group.waiting == 0
        {
            return false;
        }
        group.waiting -= 1;
        self.skipped += 1;
        if group.waiting == 0 {
            *slot = None;
            self.free.push(id);
        }
        true
    }

    fn release(&mut self, id: u32, ray: &Option<RayRecord>) {
        self.free.push(id);
        if let Some(r) = ray {
            self.by_generation.remove(r.generation());
        }
    }

    /// Rays waiting, and rays concluded early whose copies are still out (both hold memory).
    pub fn waiting(&self) -> usize {
        self.slots.len() - self.free.len()
    }

    /// The oldest generation among the rays waiting: copies of it are still to be traced.
    pub fn oldest_waiting(&self) -> Option<u16> {
        self.by_generation.oldest()
    }

    /// Drops waiting rays `keep` refuses (a fault restarted their tiles).
    pub fn retain(&mut self, mut keep: impl FnMut(&RayRecord) -> bool) {
        for id in 0..self.slots.len() {
            if self.slots[id].as_ref().is_some_and(|g| !keep(&g.ray)) {
                // A spent group's ray was counted out of its generation when it concluded.
                let dropped = self.slots[id].take().filter(|g| !g.spent).map(|g| g.ray);
                self.release(id as u32, &dropped);
            }
        }
    }
}

#[cfg(test)]
mod tests;
