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

mod path;
mod slots;
mod verdict;

pub use verdict::{MAX_SEGMENTS, SegmentLight, SurfaceHit, Verdict};

use super::dvr::Segment;
use crate::ray::RayKind;
use crate::ray::RayRecord;
use crate::schedule::speculation_depth::{Depth, Windows};
use crate::schedule::speculative::Generations;
use crate::wire::VerdictRecord;
use path::Path;
use slots::Slots;

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

/// A ray waiting for its copies' verdicts. It keeps the ray's credit: copies carry none.
///
/// Kept small, since settling a verdict is one random access into the groups, mostly a
/// cache miss (README "Benchmarks"): the path is held in the record for most rays, and what
/// only volume rays need is boxed apart.
struct Group {
    ray: RayRecord,
    /// The domains with geometry along the ray, nearest first.
    path: Path,
    /// How many of them have been sent copies (the windows so far).
    copied: u32,
    /// The worker holding the group, named in the copies.
    resolver: u32,
    /// Copies of the current window whose last verdict is still to come.
    waiting: u32,
    /// The ray has concluded before all its copies answered (see [`Groups::skip`]): the
    /// group only counts the copies still out, so that their verdicts find it and the id is
    /// not reused while they may come.
    spent: bool,
    /// Which places along `path` have answered.
    answered: Answered,
    /// The nearest place along the ray where a copy found an occluder.
    blocker: Option<u32>,
    /// The hit of the nearest domain that has one, and that domain's place along the ray.
    nearest: Option<(u32, SurfaceHit)>,
    /// Once a volume verdict came: the ray concludes only once every copy has answered.
    volume: Option<Box<VolumeParts>>,
}

/// What a group of a volume ray collects besides a surface ray's outcome.
#[derive(Default)]
struct VolumeParts {
    /// Segments announced by closing verdicts minus segments received: a copy's segments
    /// may arrive before or after its closing verdict, so this dips below zero meanwhile.
    segments_due: i64,
    segments: Vec<Segment>,
    lights: Vec<SegmentLight>,
}

impl Group {
    /// Adds one verdict to what the copies found; `place` is its domain's place along the
    /// path, for those that name a domain.
    fn add(&mut self, verdict: Verdict, place: Option<u32>) {
        match (verdict, place) {
            (Verdict::Segment(seg), _) => self.volume_parts().segments.push(seg),
            (Verdict::Light(light), _) => self.volume_parts().lights.push(light),
            (Verdict::Blocked, Some(p)) => {
                self.blocker = Some(self.blocker.map_or(p, |b| b.min(p)));
            }
            (Verdict::Hit(hit) | Verdict::VolumeHit(hit), Some(p))
                if self.nearest.is_none_or(|(n, _)| p < n) =>
            {
                self.nearest = Some((p, hit));
            }
            _ => {}
        }
    }

    /// The volume parts, made on the first volume verdict.
    fn volume_parts(&mut self) -> &mut VolumeParts {
        self.volume.get_or_insert_default()
    }

    /// Segments announced and not yet received (see [`VolumeParts::segments_due`]).
    fn segments_due(&self) -> i64 {
        self.volume.as_ref().map_or(0, |v| v.segments_due)
    }

    /// The outcome so far, taken out of the group.
    fn take_outcome(&mut self) -> Outcome {
        let volume = self.volume.as_mut().map(|v| std::mem::take(&mut **v));
        let (segments, lights) = volume.map_or_else(Default::default, |v| (v.segments, v.lights));
        Outcome {
            blocked: self.blocker.is_some(),
            blocker: self.blocker,
            nearest: self.nearest.map(|(_, hit)| hit),
            segments,
            lights,
        }
    }

    /// Where along the ray it ended, if it did (as [`Outcome::ended`]).
    fn ended(&self) -> Option<u32> {
        match self.ray.kind() {
            RayKind::Radiance => self.nearest.map(|(p, _)| p),
            RayKind::Shadow => self.blocker,
        }
    }

    /// Whether the verdicts so far decide the ray as the chained trace would, though copies
    /// farther along it have not answered: a shadow ray's occluder anywhere, or a radiance
    /// ray's hit with every nearer domain answered clear. Volume rays wait for all.
    fn decided_early(&self) -> bool {
        if self.volume.is_some() {
            return false;
        }
        match self.ray.kind() {
            RayKind::Shadow => self.blocker.is_some(),
            RayKind::Radiance => self.nearest.is_some_and(|(p, _)| {
                (p as usize) < self.path.len()
                    && self.answered.all_before(p as usize, self.path.len())
            }),
        }
    }

    /// Notes that the copy at `place` along the path answered.
    fn answer(&mut self, place: Option<usize>) {
        if let Some(p) = place.filter(|&p| p < self.path.len()) {
            self.answered.set(p, self.path.len());
        }
    }

    /// The domains sent copies so far.
    fn copied(&self) -> &[u32] {
        self.path.get(..self.copied as usize).unwrap_or_default()
    }
}

/// Which places along a ray's path have answered: a bit each while the path has at most 64
/// places (every ray born here has a group, so a flag vector per group was an allocation
/// per ray on the worker's event loop), else a flag each.
#[derive(Default)]
struct Answered {
    bits: u64,
    long: Option<Box<[bool]>>,
}

impl Answered {
    /// Notes that place `p` of a path of `len` places answered (`p < len`).
    fn set(&mut self, p: usize, len: usize) {
        if len <= 64 {
            self.bits |= 1 << p;
        } else {
            self.long.get_or_insert_with(|| vec![false; len].into())[p] = true;
        }
    }

    /// Whether every place before `n` (`n < len`) answered; true too while none has.
    fn all_before(&self, n: usize, len: usize) -> bool {
        if len <= 64 {
            let mask = (1u64 << n) - 1;
            self.bits == 0 || self.bits & mask == mask
        } else {
            self.long.as_ref().is_none_or(|l| l[..n].iter().all(|&a| a))
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
    slots: Slots<Group>,
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
            slots: Slots::default(),
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
            path: Path::from(path),
            copied: 0,
            resolver,
            waiting: 0,
            spent: false,
            answered: Answered::default(),
            blocker: None,
            nearest: None,
            volume: None,
        };
        self.by_generation.add(ray.generation());
        let id = match self.free.pop() {
            Some(id) => {
                if let Some(slot) = self.slots.get_mut(id) {
                    *slot = Some(group);
                }
                id
            }
            None => self.slots.push(group),
        };
        self.next_window(id, out);
    }

    /// Sends group `id`'s next window of copies to `out`.
    fn next_window(&mut self, id: u32, out: &mut Vec<RayRecord>) {
        let Some(group) = self.slots.get_mut(id).and_then(Option::as_mut) else {
            return;
        };
        let from = group.copied as usize;
        let n = self.windows.window(&group.ray, &group.path, from);
        let window = &group.path[from..(from + n).min(group.path.len())];
        if from > 0 {
            self.windows.later_window(&group.ray, window);
        }
        group.waiting = window.len() as u32;
        group.copied += window.len() as u32;
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
        let slot = self.slots.get_mut(id).ok_or(GroupError::Unknown(id))?;
        let group = slot.as_mut().ok_or(GroupError::Unknown(id))?;
        let r = &group.ray;
        if (r.tile, r.epoch, r.pixel, r.sample)
            != (record.tile, record.epoch, record.pixel, record.sample)
        {
            return Err(GroupError::Mismatch(id));
        }
        let verdict = record.verdict();
        // Where along the path the copy was: a clear verdict, an occluder or a hit names the
        // copy's domain, which a copy was sent to. (A concluded ray's group has given its
        // path up: its verdicts teach nothing.)
        let domain = match verdict {
            Verdict::Clear | Verdict::Blocked | Verdict::Hit(_) | Verdict::VolumeHit(_) => {
                Some(record.order)
            }
            _ => None,
        };
        let place = domain.and_then(|d| group.copied().iter().position(|&c| c == d));
        if domain.is_some() && place.is_none() && !group.spent {
            // No copy went there: not a verdict on this ray's copies.
            return Err(GroupError::Mismatch(id));
        }
        // The copy's domain has been traced for the ray's generation.
        if let Some(p) = place
            && !matches!(verdict, Verdict::VolumeHit(_))
        {
            self.windows.visited(&group.ray, group.path[p]);
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
                let waiting = group.waiting;
                let volume = group.volume_parts();
                let held = (volume.segments.len() + volume.lights.len()) as u32;
                if held >= MAX_SEGMENTS || (waiting == 0 && volume.segments_due <= 0) {
                    return Err(GroupError::TooManySegments(id));
                }
                volume.segments_due -= 1;
            }
            Verdict::VolumeEnd(n) => {
                let volume = group.volume_parts();
                if n > MAX_SEGMENTS {
                    return Err(GroupError::TooManySegments(id));
                }
                volume.segments_due += i64::from(n);
                group.waiting = group.waiting.saturating_sub(1);
            }
            Verdict::Clear | Verdict::Blocked | Verdict::Hit(_) => {
                group.answer(place);
                group.waiting = group.waiting.saturating_sub(1);
            }
        }
        group.add(verdict, place.map(|p| p as u32));
        let segments_due = group.segments_due();
        if group.waiting > 0 || segments_due != 0 {
            if group.waiting == 0 && segments_due < 0 {
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
                let ended = group.ended().map(|e| e as usize);
                let outcome = group.take_outcome();
                let path = std::mem::take(&mut group.path);
                group.copied = 0;
                self.windows.learn(&ray, &path, ended);
                self.by_generation.remove(ray.generation());
                return Ok(Some((ray, outcome)));
            }
            return Ok(None);
        }
        let ended = group.ended();
        if ended.is_none() && group.blocker.is_none() && (group.copied as usize) < group.path.len()
        {
            // The window found nothing that ends the ray: on to the next.
            self.extensions += 1;
            self.next_window(id, more);
            return Ok(None);
        }
        self.windows
            .learn(&group.ray, &group.path, ended.map(|e| e as usize));
        let done = slot.take().map(|mut g| {
            let mut outcome = g.take_outcome();
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
        let Some(slot) = self.slots.get_mut(id) else {
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
        for id in 0..self.slots.len() as u32 {
            let Some(slot) = self.slots.get_mut(id) else {
                continue;
            };
            if slot.as_ref().is_some_and(|g| !keep(&g.ray)) {
                // A spent group's ray was counted out of its generation when it concluded.
                let dropped = slot.take().filter(|g| !g.spent).map(|g| g.ray);
                self.release(id, &dropped);
            }
        }
    }
}

#[cfg(test)]
mod tests;
