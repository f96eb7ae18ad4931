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

use crate::ray::RayRecord;

/// What a radiance ray's copy found in its domain: enough to shade the hit later, without
/// the domain's data.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceHit {
    /// The domain's place along the ray among those with geometry (0 is the nearest); the
    /// hit of the nearest such domain wins, as domains cut a ray into ordered intervals.
    pub order: u32,
    /// Distance of the hit along the ray.
    pub t: f32,
    /// Geometric normal of the triangle hit.
    pub normal: [f32; 3],
    /// Material of the triangle hit.
    pub material: u32,
}

/// What one copy found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Verdict {
    /// Nothing in this domain's stretch of the ray.
    Clear,
    /// A shadow ray's occluder.
    Blocked,
    /// A radiance ray's nearest hit in this domain.
    Hit(SurfaceHit),
}

/// All verdicts of a ray combined.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Outcome {
    /// Some copy found an occluder.
    pub blocked: bool,
    /// The hit of the nearest domain that has one.
    pub nearest: Option<SurfaceHit>,
}

impl Outcome {
    fn add(&mut self, verdict: Verdict) {
        match verdict {
            Verdict::Clear => {}
            Verdict::Blocked => self.blocked = true,
            Verdict::Hit(hit) => {
                if self.nearest.is_none_or(|n| hit.order < n.order) {
                    self.nearest = Some(hit);
                }
            }
        }
    }
}

/// A ray waiting for its copies' verdicts. It keeps the ray's credit: copies carry none.
struct Group {
    ray: RayRecord,
    waiting: u32,
    outcome: Outcome,
}

/// Why a verdict could not be taken.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum GroupError {
    /// No ray waits under this group: a verdict for a group already concluded, or never made.
    #[error("verdict for group {0}, which is not waiting")]
    Unknown(u32),
}

/// The rays born here that wait for their copies; group ids are reused once concluded.
#[derive(Default)]
pub struct Groups {
    slots: Vec<Option<Group>>,
    free: Vec<u32>,
}

impl Groups {
    /// No rays waiting.
    pub fn new() -> Self {
        Self::default()
    }

    /// Makes `ray` wait for one verdict from each of `domains` (non-empty: a ray that meets
    /// no domain concludes at once) and returns its copies, one per domain, without credit.
    pub fn spread(&mut self, ray: RayRecord, domains: &[u32]) -> impl Iterator<Item = RayRecord> {
        debug_assert!(!domains.is_empty());
        let group = Group {
            ray,
            waiting: domains.len() as u32,
            outcome: Outcome::default(),
        };
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
        domains.iter().map(move |&domain| RayRecord {
            domain,
            group: id,
            credit: 0,
            ..ray
        })
    }

    /// Takes one copy's verdict; returns the ray and its outcome when it was the last.
    pub fn settle(
        &mut self,
        id: u32,
        verdict: Verdict,
    ) -> Result<Option<(RayRecord, Outcome)>, GroupError> {
        let slot = self
            .slots
            .get_mut(id as usize)
            .ok_or(GroupError::Unknown(id))?;
        let group = slot.as_mut().ok_or(GroupError::Unknown(id))?;
        group.outcome.add(verdict);
        group.waiting -= 1;
        if group.waiting > 0 {
            return Ok(None);
        }
        let done = slot.take().map(|g| (g.ray, g.outcome));
        self.free.push(id);
        Ok(done)
    }

    /// Rays waiting.
    pub fn waiting(&self) -> usize {
        self.slots.len() - self.free.len()
    }

    /// Drops waiting rays `keep` refuses (a fault restarted their tiles).
    pub fn retain(&mut self, mut keep: impl FnMut(&RayRecord) -> bool) {
        for (id, slot) in self.slots.iter_mut().enumerate() {
            if slot.as_ref().is_some_and(|g| !keep(&g.ray)) {
                *slot = None;
                self.free.push(id as u32);
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
            ..RayRecord::zeroed()
        }
    }

    #[test]
    fn copies_go_to_every_domain_without_credit() {
        let mut groups = Groups::new();
        let copies: Vec<_> = groups.spread(ray(7), &[4, 9, 2]).collect();
        assert_eq!(
            copies.iter().map(|c| c.domain).collect::<Vec<_>>(),
            [4, 9, 2]
        );
        assert!(
            copies
                .iter()
                .all(|c| c.credit == 0 && c.group == copies[0].group)
        );
        assert_eq!(groups.waiting(), 1);
    }

    #[test]
    fn the_nearest_domain_with_a_hit_wins_whatever_the_order_verdicts_arrive_in() {
        let mut groups = Groups::new();
        let id = groups.spread(ray(7), &[1, 2, 3]).next().unwrap().group;
        assert_eq!(groups.settle(id, hit(2, 0.5)), Ok(None));
        assert_eq!(groups.settle(id, Verdict::Clear), Ok(None));
        let (r, outcome) = groups.settle(id, hit(1, 9.0)).unwrap().unwrap();
        assert_eq!(r.credit, 7, "the concluded ray keeps its credit");
        assert_eq!(outcome.nearest.map(|h| h.order), Some(1));
        assert!(!outcome.blocked);
        assert_eq!(groups.waiting(), 0);
    }

    #[test]
    fn one_blocking_copy_blocks_the_shadow_ray() {
        let mut groups = Groups::new();
        let id = groups.spread(ray(1), &[1, 2]).next().unwrap().group;
        groups.settle(id, Verdict::Blocked).unwrap();
        let (_, outcome) = groups.settle(id, Verdict::Clear).unwrap().unwrap();
        assert!(outcome.blocked);
    }

    #[test]
    fn ids_are_reused_and_stale_verdicts_are_refused() {
        let mut groups = Groups::new();
        let a = groups.spread(ray(1), &[1]).next().unwrap().group;
        groups.settle(a, Verdict::Clear).unwrap().unwrap();
        assert_eq!(
            groups.settle(a, Verdict::Clear),
            Err(GroupError::Unknown(a))
        );
        assert_eq!(
            groups.settle(99, Verdict::Clear),
            Err(GroupError::Unknown(99))
        );
        let b = groups.spread(ray(2), &[1, 2]).next().unwrap().group;
        assert_eq!(a, b);
        groups.retain(|r| r.credit != 2);
        assert_eq!(groups.waiting(), 0);
        assert_eq!(
            groups.settle(b, Verdict::Clear),
            Err(GroupError::Unknown(b))
        );
    }
}
