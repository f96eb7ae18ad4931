//! The local renderer's ray queues, one per domain, held in fixed-size segments drawn from a
//! pool. A chunk of a pass writes its outcomes into segments, a segment of rays all bound
//! for one domain moves to that domain's queue whole (no copy), and a traced segment goes
//! back to the pool for the next chunk's outcomes. So a frame faults in about its largest
//! queue's memory once, instead of fresh queues and chunk outputs every pass: zeroing those
//! pages was a tenth of a one-thread render (README, "Benchmarks").

use std::sync::Mutex;

use super::super::kernel::SceneView;
use super::super::speculation::Groups;
use crate::ray::RayRecord;
use crate::schedule::speculation_depth::Depth;
use crate::schedule::speculative::{GenerationCounts, QueueView, next_queue};

/// Rays a segment holds; also the rays one rayon task traces.
pub(super) const SEGMENT: usize = 4096;

/// Empty segments (capacity [`SEGMENT`]) handed back after use. It holds at most what was in
/// flight at once, which the frame needed anyway, and is freed with the frame.
pub(super) struct SegmentPool(Mutex<Vec<Vec<RayRecord>>>);

impl SegmentPool {
    pub(super) fn new() -> Self {
        SegmentPool(Mutex::new(Vec::new()))
    }

    /// An empty segment: a kept one, or a new one.
    pub(super) fn get(&self) -> Vec<RayRecord> {
        let kept = self.0.lock().unwrap_or_else(|p| p.into_inner()).pop();
        kept.unwrap_or_else(|| Vec::with_capacity(SEGMENT))
    }

    /// Gives `segment`'s memory back (a vector of another capacity is freed instead).
    pub(super) fn put(&self, mut segment: Vec<RayRecord>) {
        if segment.capacity() != SEGMENT {
            return;
        }
        segment.clear();
        self.0
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .push(segment);
    }
}

/// Rays appended one at a time into pool segments: the outcomes of one chunk.
pub(super) struct Batch<'a> {
    pool: &'a SegmentPool,
    full: Vec<Vec<RayRecord>>,
    open: Vec<RayRecord>,
}

impl<'a> Batch<'a> {
    pub(super) fn new(pool: &'a SegmentPool) -> Self {
        Batch {
            pool,
            full: Vec::new(),
            open: Vec::new(),
        }
    }

    pub(super) fn push(&mut self, ray: RayRecord) {
        if self.open.len() == self.open.capacity() {
            let filled = std::mem::replace(&mut self.open, self.pool.get());
            if filled.capacity() != 0 {
                self.full.push(filled);
            }
        }
        self.open.push(ray);
    }

    /// The segments written, none empty.
    pub(super) fn finish(mut self) -> Vec<Vec<RayRecord>> {
        if self.open.is_empty() {
            self.pool.put(self.open);
        } else {
            self.full.push(self.open);
        }
        self.full
    }
}

/// One domain's queue.
#[derive(Default)]
struct DomainQueue {
    /// Segments at least half full (a partial one is copied into `open` instead, so a queue's
    /// segments never hold less than half their rays on average).
    full: Vec<Vec<RayRecord>>,
    /// Where single rays go.
    open: Vec<RayRecord>,
    len: usize,
}

impl DomainQueue {
    fn push(&mut self, ray: RayRecord, pool: &SegmentPool) {
        if self.open.len() == self.open.capacity() {
            let filled = std::mem::replace(&mut self.open, pool.get());
            if filled.capacity() != 0 {
                self.full.push(filled);
            }
        }
        self.open.push(ray);
        self.len += 1;
    }
}

/// One queue per domain. Rays are placed in the first domain along them, or, speculating,
/// in all of them at once.
pub(super) struct Queues {
    rays: Vec<DomainQueue>,
    /// Speculating: the rays waiting for their copies, and the generations queued.
    pub(super) groups: Option<Groups>,
    generations: GenerationCounts,
    /// Speculating: each domain's place in the order camera rays meet domains
    /// (`SceneView::front_to_back` from the eye), so camera rays are traced front to back.
    pub(super) from_eye: Vec<u32>,
}

impl Queues {
    /// Queues for `domains` domains; speculating when `depth` is given.
    pub(super) fn new(domains: usize, depth: Option<Depth>) -> Self {
        Queues {
            rays: (0..domains).map(|_| DomainQueue::default()).collect(),
            groups: depth.map(Groups::new),
            generations: GenerationCounts::default(),
            from_eye: Vec::new(),
        }
    }

    pub(super) fn total(&self) -> usize {
        self.rays.iter().map(|q| q.len).sum()
    }

    /// Queues rays routed to their first domain (`SceneView::route_new` or the kernel). A
    /// segment at least half full whose rays all go to one domain is moved there whole; the
    /// others are copied ray by ray and go back to `pool`.
    pub(super) fn place(
        &mut self,
        view: &SceneView,
        segments: impl IntoIterator<Item = Vec<RayRecord>>,
        pool: &SegmentPool,
    ) {
        let mut copies = Vec::new();
        for segment in segments {
            match &mut self.groups {
                None => {
                    if let Some(first) = segment.first()
                        && 2 * segment.len() >= SEGMENT
                        && segment.iter().all(|r| r.domain == first.domain)
                    {
                        let queue = &mut self.rays[first.domain as usize];
                        queue.len += segment.len();
                        queue.full.push(segment);
                        continue;
                    }
                    for ray in &segment {
                        self.rays[ray.domain as usize].push(*ray, pool);
                    }
                }
                Some(groups) => {
                    for ray in &segment {
                        groups.spread(*ray, view.domains_along(ray), 0, &mut copies);
                        queue_copies(&mut self.rays, &mut self.generations, &mut copies, pool);
                    }
                }
            }
            pool.put(segment);
        }
    }

    /// Queues speculative copies in their domains.
    pub(super) fn queue_copies(&mut self, copies: &mut Vec<RayRecord>, pool: &SegmentPool) {
        queue_copies(&mut self.rays, &mut self.generations, copies, pool);
    }

    /// The queue to trace next: the fullest, or, speculating, `speculative::next_queue`.
    pub(super) fn next(&self, resident: &[u32]) -> Option<u32> {
        let lens = (0u32..).zip(self.rays.iter().map(|q| q.len));
        if self.groups.is_none() {
            // Ties go to the lowest domain id.
            return lens
                .filter(|&(_, len)| len > 0)
                .max_by_key(|&(d, len)| (len, std::cmp::Reverse(d)))
                .map(|(d, _)| d);
        }
        next_queue(lens.filter_map(|(domain, len)| {
            Some(QueueView {
                domain,
                rays: len as u64,
                oldest: self.generations.oldest(domain)?,
                resident: resident.contains(&domain),
                from_eye: self.from_eye.get(domain as usize).copied().unwrap_or(0),
            })
        }))
    }

    /// Domain `domain`'s rays, in segments of at most [`SEGMENT`], none empty; its queue is
    /// left empty.
    pub(super) fn take(&mut self, domain: u32) -> Vec<Vec<RayRecord>> {
        self.generations.clear(domain);
        let queue = &mut self.rays[domain as usize];
        queue.len = 0;
        let mut segments = std::mem::take(&mut queue.full);
        if !queue.open.is_empty() {
            segments.push(std::mem::take(&mut queue.open));
        }
        segments
    }
}

/// Queues speculative copies in their domains' queues, counting their generations (the
/// queues' fields apart, for `Queues::place`, which holds the groups meanwhile).
fn queue_copies(
    rays: &mut [DomainQueue],
    generations: &mut GenerationCounts,
    copies: &mut Vec<RayRecord>,
    pool: &SegmentPool,
) {
    for copy in copies.drain(..) {
        generations.add(copy.domain, copy.generation());
        rays[copy.domain as usize].push(copy, pool);
    }
}
