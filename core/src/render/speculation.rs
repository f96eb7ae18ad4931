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

use super::dvr::Segment;
use crate::ray::RayKind;
use crate::ray::RayRecord;
use crate::schedule::speculation_depth::{Depth, Windows};
use crate::schedule::speculative::Generations;
use crate::wire::VerdictRecord;

/// What a radiance ray's copy found in its domain: enough to shade the hit later, without
/// the domain's data.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceHit {
    /// The domain's place along the ray among those with geometry (0 is the nearest); the
    /// hit of the nearest such domain wins, as domains cut a ray into ordered intervals.
    pub order: u32,
    /// Distance of the hit along the ray.
    pub t: f32,
    /// The normal to shade the hit with, on the side the ray came from
    /// (`SceneView::surface_at`: the facet normal, or a smooth surface's shading normal).
    pub normal: [f32; 3],
    /// Material of the triangle hit.
    pub material: u32,
}

/// What one copy found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Verdict {
    /// Nothing in this domain's stretch of the ray.
    Clear,
    /// A shadow ray's occluder, in the domain at this place along the ray (see
    /// [`SurfaceHit::order`]).
    Blocked(u32),
    /// A radiance ray's nearest hit in this domain.
    Hit(SurfaceHit),
    /// One segment a volume ray's copy composited in its brick (not the copy's last verdict).
    Segment(Segment),
    /// The light one segment reflects of one light, to be sent on in a shadow ray.
    Light(SegmentLight),
    /// A radiance ray's nearest hit on the surfaces in a brick (not the copy's last verdict:
    /// the brick's segments in front of it come with it).
    VolumeHit(SurfaceHit),
    /// A volume ray's copy is done: it sent this many [`Verdict::Segment`]s,
    /// [`Verdict::Light`]s and [`Verdict::VolumeHit`]s before.
    VolumeEnd(u32),
}

/// What a shadowed segment reflects of one light (`render::volume_light`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SegmentLight {
    /// The segment's first sample: which segment this belongs to.
    pub first: u32,
    /// The light's index.
    pub light: u32,
    /// The segment's depth along the ray, where the shadow ray leaves.
    pub depth: f32,
    /// Premultiplied colour reflected of this light.
    pub rgb: [f32; 3],
}

/// Most segments one ray may collect from all its copies: a bound on what a peer can make a
/// group hold (far above a ray's crossings of block faces in any volume a brick can hold).
pub const MAX_SEGMENTS: u32 = 1 << 16;

impl VerdictRecord {
    /// Kind of a verdict that found nothing.
    pub const CLEAR: u8 = 0;
    /// Kind of a verdict that found an occluder: `order` is the domain's place along the ray.
    pub const BLOCKED: u8 = 1;
    /// Kind of a verdict that found a hit.
    pub const HIT: u8 = 2;
    /// Kind of a volume segment: `order` its first sample, `normal` its premultiplied colour,
    /// `t` its opacity.
    pub const SEGMENT: u8 = 3;
    /// Kind of a volume copy's closing verdict: `material` counts its segments and lights.
    pub const VOLUME_END: u8 = 4;
    /// Kind of a segment's light: `order` the segment's first sample, `material` the light,
    /// `t` the segment's depth, `normal` the premultiplied colour reflected.
    pub const LIGHT: u8 = 5;
    /// Kind of a hit on the surfaces in a brick: the fields of [`VerdictRecord::HIT`].
    pub const VOLUME_HIT: u8 = 6;

    /// `verdict` on `copy`, to go back to the copy's group.
    pub fn new(copy: &RayRecord, verdict: Verdict) -> Self {
        let mut r = VerdictRecord {
            group: copy.group,
            tile: copy.tile,
            epoch: copy.epoch,
            pixel: copy.pixel,
            sample: copy.sample,
            kind: Self::CLEAR,
            _pad: [0; 3],
            order: 0,
            t: 0.0,
            normal: [0.0; 3],
            material: 0,
        };
        match verdict {
            Verdict::Clear => {}
            Verdict::Blocked(order) => {
                r.kind = Self::BLOCKED;
                r.order = order;
            }
            Verdict::Hit(hit) | Verdict::VolumeHit(hit) => {
                r.kind = if matches!(verdict, Verdict::Hit(_)) {
                    Self::HIT
                } else {
                    Self::VOLUME_HIT
                };
                r.order = hit.order;
                r.t = hit.t;
                r.normal = hit.normal;
                r.material = hit.material;
            }
            Verdict::Segment(seg) => {
                r.kind = Self::SEGMENT;
                r.order = seg.first;
                r.t = seg.alpha;
                r.normal = seg.rgb;
            }
            Verdict::Light(light) => {
                r.kind = Self::LIGHT;
                r.order = light.first;
                r.material = light.light;
                r.t = light.depth;
                r.normal = light.rgb;
            }
            Verdict::VolumeEnd(segments) => {
                r.kind = Self::VOLUME_END;
                r.material = segments;
            }
        }
        r
    }

    /// The verdict carried (an unknown kind, refused by the wire checks, reads as clear).
    pub fn verdict(&self) -> Verdict {
        match self.kind {
            Self::BLOCKED => Verdict::Blocked(self.order),
            Self::HIT => Verdict::Hit(SurfaceHit {
                order: self.order,
                t: self.t,
                normal: self.normal,
                material: self.material,
            }),
            Self::VOLUME_HIT => Verdict::VolumeHit(SurfaceHit {
                order: self.order,
                t: self.t,
                normal: self.normal,
                material: self.material,
            }),
            Self::SEGMENT => Verdict::Segment(Segment::plain(self.order, self.normal, self.t)),
            Self::LIGHT => Verdict::Light(SegmentLight {
                first: self.order,
                light: self.material,
                depth: self.t,
                rgb: self.normal,
            }),
            Self::VOLUME_END => Verdict::VolumeEnd(self.material),
            _ => Verdict::Clear,
        }
    }
}

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
    outcome: Outcome,
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
        group.waiting = window.len() as u32;
        group.copied += window.len();
        self.copies += window.len() as u64;
        let (ray, resolver) = (group.ray, group.resolver);
        out.extend(window.iter().map(|&domain| RayRecord {
            domain,
            group: id,
            resolver,
            credit: 0,
            ..ray
        }));
    }

    /// Takes one copy's verdict; returns the ray and its outcome when it was the last. When
    /// it was the last of a window that did not end the ray, the copies of the next window
    /// go to `more` instead.
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
        match verdict {
            Verdict::Segment(_) | Verdict::Light(_) | Verdict::VolumeHit(_) => {
                let held = (group.outcome.segments.len() + group.outcome.lights.len()) as u32;
                if held >= MAX_SEGMENTS || (group.waiting == 0 && group.segments_due <= 0) {
                    return Err(GroupError::TooManySegments(id));
                }
                group.segments_due -= 1;
            }
            Verdict::VolumeEnd(n) => {
                if n > MAX_SEGMENTS {
                    return Err(GroupError::TooManySegments(id));
                }
                group.segments_due += i64::from(n);
                group.waiting -= 1;
            }
            _ => group.waiting -= 1,
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

    fn release(&mut self, id: u32, ray: &Option<RayRecord>) {
        self.free.push(id);
        if let Some(r) = ray {
            self.by_generation.remove(r.generation());
        }
    }

    /// Rays waiting.
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
                let dropped = self.slots[id].take().map(|g| g.ray);
                self.release(id as u32, &dropped);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bytemuck::Zeroable;

    fn hit(order: u32, t: f32) -> Verdict {
        Verdict::Hit(SurfaceHit {
            order,
            t,
            normal: [0.0, 1.0, 0.0],
            material: 0,
        })
    }

    fn ray(credit: u64) -> RayRecord {
        RayRecord {
            credit,
            pixel: 5,
            ..RayRecord::zeroed()
        }
    }

    fn copies(groups: &mut Groups, r: RayRecord, domains: &[u32]) -> Vec<RayRecord> {
        let mut out = Vec::new();
        groups.spread(r, domains.to_vec(), 3, &mut out);
        out
    }

    fn spread(groups: &mut Groups, r: RayRecord, domains: &[u32]) -> RayRecord {
        copies(groups, r, domains)[0]
    }

    fn settle(groups: &mut Groups, copy: &RayRecord, v: Verdict) -> Option<(RayRecord, Outcome)> {
        groups
            .settle(&VerdictRecord::new(copy, v), &mut Vec::new())
            .unwrap()
    }

    #[test]
    fn copies_go_to_every_domain_without_credit() {
        let mut groups = Groups::default();
        let copies = copies(&mut groups, ray(7), &[4, 9, 2]);
        assert_eq!(
            copies.iter().map(|c| c.domain).collect::<Vec<_>>(),
            [4, 9, 2]
        );
        assert!(
            copies
                .iter()
                .all(|c| c.credit == 0 && c.group == copies[0].group)
        );
        assert!(copies.iter().all(|c| c.resolver == 3));
        assert_eq!(groups.waiting(), 1);
        assert_eq!(groups.oldest_waiting(), Some(0));
        let shadow = RayRecord {
            depth: 2,
            kind: crate::ray::RayKind::Shadow as u8,
            ..ray(1)
        };
        let copy = spread(&mut groups, shadow, &[1]);
        assert_eq!(groups.oldest_waiting(), Some(0));
        groups.retain(|r| r.depth > 0);
        assert_eq!(groups.oldest_waiting(), Some(3));
        groups
            .settle(&VerdictRecord::new(&copy, Verdict::Clear), &mut Vec::new())
            .unwrap();
        assert_eq!(groups.oldest_waiting(), None);
    }

    #[test]
    fn the_nearest_domain_with_a_hit_wins_whatever_the_order_verdicts_arrive_in() {
        let mut groups = Groups::default();
        let copy = spread(&mut groups, ray(7), &[1, 2, 3]);
        assert_eq!(settle(&mut groups, &copy, hit(2, 0.5)), None);
        assert_eq!(settle(&mut groups, &copy, Verdict::Clear), None);
        let (r, outcome) = settle(&mut groups, &copy, hit(1, 9.0)).unwrap();
        assert_eq!(r.credit, 7, "the concluded ray keeps its credit");
        assert_eq!(outcome.nearest.map(|h| h.order), Some(1));
        assert!(!outcome.blocked);
        assert_eq!(groups.waiting(), 0);
    }

    #[test]
    fn windows_go_out_one_after_another_until_one_ends_the_ray() {
        // One domain at a time: a hit in the second domain ends the ray there, the third is
        // never copied.
        let mut groups = Groups::new(Depth::Ahead(1));
        let first = copies(&mut groups, ray(7), &[5, 6, 7]);
        assert_eq!(first.iter().map(|c| c.domain).collect::<Vec<_>>(), [5]);
        let mut more = Vec::new();
        let settled = groups.settle(&VerdictRecord::new(&first[0], Verdict::Clear), &mut more);
        assert_eq!(settled, Ok(None));
        assert_eq!(more.iter().map(|c| c.domain).collect::<Vec<_>>(), [6]);
        assert!(
            more.iter()
                .all(|c| c.group == first[0].group && c.credit == 0)
        );
        let (r, outcome) = settle(&mut groups, &more[0], hit(1, 2.0)).unwrap();
        assert_eq!((r.credit, outcome.nearest.map(|h| h.order)), (7, Some(1)));
        assert_eq!((groups.copies, groups.extensions), (2, 1));

        // Two at a time: a shadow ray blocked in the first window ends; one that goes through
        // every window concludes clear after the last.
        let mut groups = Groups::new(Depth::Ahead(2));
        let shadow = RayRecord {
            kind: crate::ray::RayKind::Shadow as u8,
            ..ray(1)
        };
        let w = copies(&mut groups, shadow, &[1, 2, 3]);
        assert_eq!(w.len(), 2);
        assert_eq!(settle(&mut groups, &w[1], Verdict::Blocked(1)), None);
        let (_, outcome) = settle(&mut groups, &w[0], Verdict::Clear).unwrap();
        assert_eq!((outcome.blocked, outcome.blocker), (true, Some(1)));
        let w = copies(&mut groups, shadow, &[1, 2, 3]);
        let mut more = Vec::new();
        for c in &w {
            let v = VerdictRecord::new(c, Verdict::Clear);
            assert_eq!(groups.settle(&v, &mut more), Ok(None));
        }
        assert_eq!(more.iter().map(|c| c.domain).collect::<Vec<_>>(), [3]);
        let (_, outcome) = settle(&mut groups, &more[0], Verdict::Clear).unwrap();
        assert!(!outcome.blocked);
        assert_eq!(groups.waiting(), 0);
    }

    #[test]
    fn one_blocking_copy_blocks_the_shadow_ray() {
        let mut groups = Groups::default();
        let copy = spread(&mut groups, ray(1), &[1, 2]);
        settle(&mut groups, &copy, Verdict::Blocked(1));
        let (_, outcome) = settle(&mut groups, &copy, Verdict::Clear).unwrap();
        assert!(outcome.blocked);
    }

    #[test]
    fn verdicts_survive_the_wire_form() {
        let copy = spread(&mut Groups::default(), ray(1), &[1]);
        for v in [
            Verdict::Clear,
            Verdict::Blocked(1),
            hit(4, 2.5),
            segment(9, 0.25),
            Verdict::Light(SegmentLight {
                first: 9,
                light: 1,
                depth: 2.5,
                rgb: [0.1, 0.2, 0.3],
            }),
            Verdict::VolumeEnd(3),
        ] {
            assert_eq!(VerdictRecord::new(&copy, v).verdict(), v);
        }
    }

    fn segment(first: u32, alpha: f32) -> Verdict {
        Verdict::Segment(Segment::plain(first, [alpha * 0.5; 3], alpha))
    }

    #[test]
    fn volume_segments_conclude_once_all_copies_closed_in_order_along_the_ray() {
        // Two bricks: the far one's segments (and its closing count) arrive first, the near
        // one's closing verdict before its segments.
        let mut groups = Groups::default();
        let copy = spread(&mut groups, ray(7), &[1, 2]);
        assert_eq!(settle(&mut groups, &copy, segment(40, 0.2)), None);
        assert_eq!(settle(&mut groups, &copy, segment(30, 0.1)), None);
        assert_eq!(settle(&mut groups, &copy, Verdict::VolumeEnd(2)), None);
        assert_eq!(settle(&mut groups, &copy, Verdict::VolumeEnd(2)), None);
        assert_eq!(settle(&mut groups, &copy, segment(12, 0.3)), None);
        let (r, outcome) = settle(&mut groups, &copy, segment(3, 0.4)).unwrap();
        assert_eq!(r.credit, 7);
        let firsts: Vec<u32> = outcome.segments.iter().map(|s| s.first).collect();
        assert_eq!(firsts, [3, 12, 30, 40]);
        assert_eq!(groups.waiting(), 0);

        // A copy that sends nothing closes with a count of zero; an empty copy off the path
        // closes with Clear.
        let copy = spread(&mut groups, ray(1), &[1, 2]);
        assert_eq!(settle(&mut groups, &copy, Verdict::VolumeEnd(0)), None);
        let (_, outcome) = settle(&mut groups, &copy, Verdict::Clear).unwrap();
        assert!(outcome.segments.is_empty());
    }

    #[test]
    fn a_hit_on_a_bricks_surfaces_comes_with_its_segments_and_the_nearest_wins() {
        // The near brick's hit arrives after its closing count, which counts it; the far
        // brick's hit is farther along the ray and loses.
        let mut groups = Groups::default();
        let copy = spread(&mut groups, ray(7), &[1, 2]);
        let volume_hit = |order, t| {
            Verdict::VolumeHit(SurfaceHit {
                order,
                t,
                normal: [0.0, 0.0, 1.0],
                material: 0,
            })
        };
        assert_eq!(settle(&mut groups, &copy, segment(3, 0.1)), None);
        assert_eq!(settle(&mut groups, &copy, Verdict::VolumeEnd(2)), None);
        assert_eq!(settle(&mut groups, &copy, volume_hit(1, 9.0)), None);
        assert_eq!(settle(&mut groups, &copy, volume_hit(0, 2.5)), None);
        let (_, outcome) = settle(&mut groups, &copy, Verdict::VolumeEnd(1)).unwrap();
        assert_eq!(outcome.nearest.map(|h| (h.order, h.t)), Some((0, 2.5)));
        assert_eq!(outcome.segments.len(), 1);
        // Through the wire and back, a brick's hit stays one.
        let back = VerdictRecord::new(&copy, volume_hit(0, 2.5)).verdict();
        assert_eq!(back, volume_hit(0, 2.5));
    }

    fn light(first: u32, light: u32) -> Verdict {
        Verdict::Light(SegmentLight {
            first,
            light,
            depth: first as f32,
            rgb: [0.25; 3],
        })
    }

    #[test]
    fn segment_lights_are_counted_and_sorted_by_segment_then_light() {
        let mut groups = Groups::default();
        let copy = spread(&mut groups, ray(7), &[1, 2]);
        // The far brick: one segment lit by lights 1 and 0, in that order; then the near one,
        // its lights before its segment.
        assert_eq!(settle(&mut groups, &copy, segment(40, 0.2)), None);
        assert_eq!(settle(&mut groups, &copy, light(40, 1)), None);
        assert_eq!(settle(&mut groups, &copy, light(40, 0)), None);
        assert_eq!(settle(&mut groups, &copy, Verdict::VolumeEnd(3)), None);
        assert_eq!(settle(&mut groups, &copy, light(3, 2)), None);
        assert_eq!(settle(&mut groups, &copy, Verdict::VolumeEnd(2)), None);
        let (_, outcome) = settle(&mut groups, &copy, segment(3, 0.4)).unwrap();
        let lights: Vec<(u32, u32)> = outcome.lights.iter().map(|l| (l.first, l.light)).collect();
        assert_eq!(lights, [(3, 2), (40, 0), (40, 1)]);
        // A light beyond the count is one verdict too many.
        let copy = spread(&mut groups, ray(1), &[1]);
        settle(&mut groups, &copy, segment(1, 0.5));
        groups
            .settle(&VerdictRecord::new(&copy, light(1, 0)), &mut Vec::new())
            .unwrap();
        let end = VerdictRecord::new(&copy, Verdict::VolumeEnd(1));
        assert_eq!(
            groups.settle(&end, &mut Vec::new()),
            Err(GroupError::TooManySegments(copy.group))
        );
    }

    #[test]
    fn segments_beyond_what_the_copies_announce_are_refused() {
        let mut groups = Groups::default();
        let copy = spread(&mut groups, ray(1), &[1]);
        settle(&mut groups, &copy, segment(1, 0.5));
        let extra = VerdictRecord::new(&copy, segment(2, 0.5));
        groups.settle(&extra, &mut Vec::new()).unwrap();
        let end = VerdictRecord::new(&copy, Verdict::VolumeEnd(1));
        assert_eq!(
            groups.settle(&end, &mut Vec::new()),
            Err(GroupError::TooManySegments(copy.group)),
            "two segments, one announced: the group is dropped"
        );
        assert_eq!(groups.waiting(), 0);
        let copy = spread(&mut groups, ray(1), &[1]);
        let huge = VerdictRecord::new(&copy, Verdict::VolumeEnd(MAX_SEGMENTS + 1));
        assert_eq!(
            groups.settle(&huge, &mut Vec::new()),
            Err(GroupError::TooManySegments(copy.group))
        );
    }

    #[test]
    fn ids_are_reused_and_stale_verdicts_are_refused() {
        let mut groups = Groups::default();
        let a = spread(&mut groups, ray(1), &[1]);
        settle(&mut groups, &a, Verdict::Clear).unwrap();
        let stale = VerdictRecord::new(&a, Verdict::Clear);
        assert_eq!(
            groups.settle(&stale, &mut Vec::new()),
            Err(GroupError::Unknown(a.group))
        );
        let far = VerdictRecord { group: 99, ..stale };
        assert_eq!(
            groups.settle(&far, &mut Vec::new()),
            Err(GroupError::Unknown(99))
        );
        let b = spread(&mut groups, RayRecord { epoch: 1, ..ray(2) }, &[1, 2]);
        assert_eq!(a.group, b.group);
        assert_eq!(
            groups.settle(&stale, &mut Vec::new()),
            Err(GroupError::Mismatch(b.group))
        );
        groups.retain(|r| r.credit != 2);
        assert_eq!(groups.waiting(), 0);
        let late = VerdictRecord::new(&b, Verdict::Clear);
        assert_eq!(
            groups.settle(&late, &mut Vec::new()),
            Err(GroupError::Unknown(b.group))
        );
    }
}
