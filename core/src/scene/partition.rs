//! Domains: the leaves of a k-d tree over the scene's bounds. The tree is the coarse
//! acceleration structure every process holds; walking it gives the domains a ray crosses,
//! front to back, with intervals that share their end points exactly (no gaps, no overlaps
//! beyond a point), which is what makes "nearest hit in the first domain that has one" exact.

use std::mem::MaybeUninit;
use std::ops::ControlFlow;

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::geometry::Aabb;

/// A node of the domain tree.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "node", rename_all = "snake_case", deny_unknown_fields)]
pub enum KdNode {
    /// Points with coordinate `< position` on `axis` go below, the rest above.
    Split {
        /// 0, 1 or 2.
        axis: u8,
        /// The plane.
        position: f32,
        /// Node index of the lower half.
        below: u32,
        /// Node index of the upper half.
        above: u32,
    },
    /// A domain.
    Leaf {
        /// Domain id.
        domain: u32,
    },
}

/// The domain tree with its root box.
#[derive(Clone, Debug)]
pub struct DomainTree {
    bounds: Aabb,
    nodes: Vec<KdNode>,
    /// How to reach each domain's leaf from the root (see [`Route`]), by domain id.
    routes: Vec<Route>,
}

/// The way from the root to one leaf: at level `l` the upper half (`above`) if bit `l` of
/// `above` is set, else the lower. A leaf deeper than [`Route::MAX_DEPTH`] levels has none
/// and is found by walking.
#[derive(Clone, Copy, Debug, Default)]
struct Route {
    above: u64,
    depth: u8,
}

impl Route {
    /// The deepest leaf a route holds: one bit a level.
    const MAX_DEPTH: u8 = 64;
    /// A leaf no route reaches (deeper than [`Route::MAX_DEPTH`], or no such domain).
    const NONE: Route = Route {
        above: 0,
        depth: u8::MAX,
    };
}

/// Each domain's route from the root of `nodes` (a tree [`DomainTree::check`] accepts, or
/// one `balanced` built).
fn routes(nodes: &[KdNode]) -> Vec<Route> {
    let mut routes = Vec::new();
    let mut todo = vec![(0usize, Route::default())];
    while let Some((i, route)) = todo.pop() {
        match nodes.get(i) {
            Some(&KdNode::Split { below, above, .. }) => {
                let deeper = |up: bool| {
                    if route.depth >= Route::MAX_DEPTH {
                        return Route::NONE;
                    }
                    Route {
                        above: route.above | (u64::from(up) << route.depth),
                        depth: route.depth + 1,
                    }
                };
                todo.push((below as usize, deeper(false)));
                todo.push((above as usize, deeper(true)));
            }
            Some(&KdNode::Leaf { domain }) => {
                let d = domain as usize;
                if routes.len() <= d {
                    routes.resize(d + 1, Route::NONE);
                }
                routes[d] = route;
            }
            None => {}
        }
    }
    routes
}

impl DomainTree {
    /// Wraps nodes already checked by [`DomainTree::check`].
    pub fn new(bounds: Aabb, nodes: Vec<KdNode>) -> Self {
        let routes = routes(&nodes);
        DomainTree {
            bounds,
            nodes,
            routes,
        }
    }

    /// Checks that `nodes` is a tree rooted at 0 whose leaves are domains `0..domains`, each once.
    pub fn check(nodes: &[KdNode], domains: usize) -> Result<(), String> {
        let mut seen_node = vec![false; nodes.len()];
        let mut seen_domain = vec![false; domains];
        let mut todo = vec![0usize];
        if nodes.is_empty() {
            return Err("k-d tree has no nodes".into());
        }
        while let Some(i) = todo.pop() {
            match seen_node.get_mut(i) {
                Some(s) if !*s => *s = true,
                Some(_) => return Err(format!("k-d node {i} is reached twice")),
                None => return Err(format!("k-d tree names node {i} of {}", nodes.len())),
            }
            match nodes[i] {
                KdNode::Split {
                    axis,
                    position,
                    below,
                    above,
                } => {
                    if axis > 2 || !position.is_finite() {
                        return Err(format!("k-d node {i} has a bad axis or position"));
                    }
                    todo.push(below as usize);
                    todo.push(above as usize);
                }
                KdNode::Leaf { domain } => match seen_domain.get_mut(domain as usize) {
                    Some(s) if !*s => *s = true,
                    _ => return Err(format!("k-d leaf {i} names domain {domain} badly")),
                },
            }
        }
        if let Some(d) = seen_domain.iter().position(|s| !s) {
            return Err(format!("domain {d} is not a leaf of the k-d tree"));
        }
        Ok(())
    }

    /// The scene box.
    pub fn bounds(&self) -> Aabb {
        self.bounds
    }

    /// Box of every domain, by domain id.
    pub fn domain_boxes(&self, domains: usize) -> Vec<Aabb> {
        let mut boxes = vec![Aabb::EMPTY; domains];
        let mut todo = vec![(0usize, self.bounds)];
        while let Some((i, b)) = todo.pop() {
            match self.nodes[i] {
                KdNode::Split {
                    axis,
                    position,
                    below,
                    above,
                } => {
                    let (mut lo, mut hi) = (b, b);
                    lo.max[axis as usize] = position;
                    hi.min[axis as usize] = position;
                    todo.push((below as usize, lo));
                    todo.push((above as usize, hi));
                }
                KdNode::Leaf { domain } => boxes[domain as usize] = b,
            }
        }
        boxes
    }

    /// Each domain's place (by domain id) in the order a ray from `point` meets domains: at
    /// every split the half holding `point` comes first, and a ray crosses a plane at most
    /// once, from that half to the other, so every ray leaving `point` meets domains in
    /// increasing place.
    pub fn front_to_back(&self, point: [f32; 3], domains: usize) -> Vec<u32> {
        let mut place = vec![u32::MAX; domains];
        let mut next = 0u32;
        let mut todo = vec![0usize];
        while let Some(i) = todo.pop() {
            match self.nodes[i] {
                KdNode::Split {
                    axis,
                    position,
                    below,
                    above,
                } => {
                    let (near, far) = if point[axis as usize] < position {
                        (below, above)
                    } else {
                        (above, below)
                    };
                    // Last pushed, first visited.
                    todo.push(far as usize);
                    todo.push(near as usize);
                }
                KdNode::Leaf { domain } => {
                    if let Some(p) = place.get_mut(domain as usize) {
                        *p = next;
                        next += 1;
                    }
                }
            }
        }
        place
    }

    /// Every domain whose closed box overlaps `b`.
    pub fn overlapping(&self, b: &Aabb, mut out: impl FnMut(u32)) {
        let mut todo = vec![0usize];
        while let Some(i) = todo.pop() {
            match self.nodes[i] {
                KdNode::Split {
                    axis,
                    position,
                    below,
                    above,
                } => {
                    if b.min[axis as usize] <= position {
                        todo.push(below as usize);
                    }
                    if b.max[axis as usize] >= position {
                        todo.push(above as usize);
                    }
                }
                KdNode::Leaf { domain } => out(domain),
            }
        }
    }

    /// The domain holding point `p` (points on a plane belong above it; points outside the
    /// bounds go to the nearest leaf along the splits).
    pub fn domain_at(&self, p: [f32; 3]) -> u32 {
        let mut i = 0usize;
        loop {
            match self.nodes[i] {
                KdNode::Split {
                    axis,
                    position,
                    below,
                    above,
                } => {
                    i = if p[axis as usize] < position {
                        below
                    } else {
                        above
                    } as usize
                }
                KdNode::Leaf { domain } => return domain,
            }
        }
    }

    /// Calls `visit(domain, t_enter, t_exit)` for the domains the ray crosses within
    /// `[t_min, t_max]`, nearest first, until it breaks. Consecutive intervals share end points.
    pub fn walk(
        &self,
        origin: Vec3,
        dir: Vec3,
        t_min: f32,
        t_max: f32,
        mut visit: impl FnMut(u32, f32, f32) -> ControlFlow<()>,
    ) {
        let Some((t0, t1)) = clip_to_box(&self.bounds, origin, dir, t_min, t_max) else {
            return;
        };
        // One domain (a scene in one piece): no planes to cross.
        if let [KdNode::Leaf { domain }] = self.nodes[..] {
            let _ = visit(domain, t0, t1);
            return;
        }
        // Walked for every ray segment: no heap allocation unless the tree is unusually deep.
        let mut stack = WalkStack::default();
        // Arrays index in one step where a `Vec3` matches on the axis.
        let (origin, dir) = (origin.to_array(), dir.to_array());
        let mut cur = (0u32, t0, t1);
        loop {
            let (i, lo, hi) = cur;
            match self.nodes[i as usize] {
                KdNode::Split {
                    axis,
                    position,
                    below,
                    above,
                } => {
                    let a = axis as usize;
                    cur = match crossing(origin[a], dir[a], position, below, above, lo, hi) {
                        Crossing::One(child) => (child, lo, hi),
                        Crossing::Both { near, far, t } => {
                            stack.push((far, t, hi));
                            (near, lo, t)
                        }
                    };
                    continue;
                }
                KdNode::Leaf { domain } => {
                    if visit(domain, lo, hi).is_break() {
                        return;
                    }
                }
            }
            match stack.pop() {
                Some(next) => cur = next,
                None => return,
            }
        }
    }

    /// `domain`'s interval along the ray within `[t_min, t_max]`, bit for bit the one
    /// [`DomainTree::walk`] visits it with, or `None` when the walk does not visit it. One
    /// descent from the root along the domain's route, where a walk visits every domain
    /// before it: tracing a speculative copy asks this for a domain far along its ray.
    pub fn interval(
        &self,
        domain: u32,
        origin: Vec3,
        dir: Vec3,
        t_min: f32,
        t_max: f32,
    ) -> Option<(f32, f32)> {
        let route = *self.routes.get(domain as usize)?;
        if route.depth > Route::MAX_DEPTH {
            let mut found = None;
            self.walk(origin, dir, t_min, t_max, |d, a, b| {
                if d == domain {
                    found = Some((a, b));
                    return ControlFlow::Break(());
                }
                ControlFlow::Continue(())
            });
            return found;
        }
        let (mut lo, mut hi) = clip_to_box(&self.bounds, origin, dir, t_min, t_max)?;
        // Arrays index in one step where a `Vec3` matches on the axis.
        let (origin, dir) = (origin.to_array(), dir.to_array());
        let mut i = 0usize;
        // Each split by the walk's own rule (`crossing`), so the same end points; where the
        // walk would not go on to the route's side, the domain is not visited.
        for level in 0..route.depth {
            let KdNode::Split {
                axis,
                position,
                below,
                above,
            } = self.nodes[i]
            else {
                return None;
            };
            let next = if route.above >> level & 1 == 1 {
                above
            } else {
                below
            };
            let a = axis as usize;
            match crossing(origin[a], dir[a], position, below, above, lo, hi) {
                Crossing::One(child) if child != next => return None,
                Crossing::One(_) => {}
                Crossing::Both { near, t, .. } if next == near => hi = t,
                Crossing::Both { t, .. } => lo = t,
            }
            i = next as usize;
        }
        matches!(self.nodes[i], KdNode::Leaf { domain: d } if d == domain).then_some((lo, hi))
    }

    /// Splits `bounds` into `domains` boxes so that each holds about the same weight of
    /// `points` (triangle centroids, or surface estimates for generated scenes).
    pub fn balanced(bounds: Aabb, points: &mut [([f32; 3], f64)], domains: u32) -> DomainTree {
        let mut nodes = Vec::new();
        let mut next_domain = 0;
        split(&mut nodes, &mut next_domain, bounds, points, domains.max(1));
        DomainTree::new(bounds, nodes)
    }

    /// The nodes, for the manifest.
    pub fn nodes(&self) -> &[KdNode] {
        &self.nodes
    }
}

fn split(
    nodes: &mut Vec<KdNode>,
    next_domain: &mut u32,
    b: Aabb,
    points: &mut [([f32; 3], f64)],
    leaves: u32,
) -> u32 {
    let me = nodes.len() as u32;
    if leaves == 1 {
        nodes.push(KdNode::Leaf {
            domain: *next_domain,
        });
        *next_domain += 1;
        return me;
    }
    let axis = b.longest_axis();
    let below_leaves = leaves / 2;
    let share = below_leaves as f64 / leaves as f64;
    points.sort_unstable_by(|p, q| p.0[axis].total_cmp(&q.0[axis]));
    let total: f64 = points.iter().map(|p| p.1).sum();
    let mut acc = 0.0;
    let mut cut = points.len();
    for (i, p) in points.iter().enumerate() {
        acc += p.1;
        if acc >= total * share {
            cut = i + 1;
            break;
        }
    }
    let (lo, hi) = (b.min[axis], b.max[axis]);
    let mid = lo + (hi - lo) * share as f32;
    let position = if total > 0.0 && cut < points.len() {
        // Halfway between neighbouring points, so neither lies on the plane.
        0.5 * (points[cut - 1].0[axis] + points[cut].0[axis])
    } else {
        mid
    };
    // A plane on the box face would make an empty slab; fall back to the spatial share.
    let position = if position > lo && position < hi {
        position
    } else {
        mid
    };
    let first_above = points.partition_point(|p| p.0[axis] < position);
    let (pb, pa) = points.split_at_mut(first_above);
    nodes.push(KdNode::Leaf { domain: u32::MAX });
    let (mut bb, mut ba) = (b, b);
    bb.max[axis] = position;
    ba.min[axis] = position;
    let below = split(nodes, next_domain, bb, pb, below_leaves);
    let above = split(nodes, next_domain, ba, pa, leaves - below_leaves);
    nodes[me as usize] = KdNode::Split {
        axis: axis as u8,
        position,
        below,
        above,
    };
    me
}

/// Where a stretch `[lo, hi]` of a ray goes at a split: the one rule of [`DomainTree::walk`]
/// and [`DomainTree::interval`], so that their end points agree bit for bit.
enum Crossing {
    /// All of it into this child.
    One(u32),
    /// `[lo, t]` into the near child (the origin's side), `[t, hi]` into the far one.
    Both { near: u32, far: u32, t: f32 },
}

/// The split at `position` on an axis (children `below` and `above`) of the stretch `[lo,
/// hi]` of a ray whose origin and direction on that axis are `o` and `d`: a ray parallel to
/// the plane stays on its origin's side; one that meets the plane behind its origin or past
/// `hi` stays on the near side, one that met it before `lo` is on the far side.
#[inline(always)]
fn crossing(o: f32, d: f32, position: f32, below: u32, above: u32, lo: f32, hi: f32) -> Crossing {
    if d == 0.0 {
        return Crossing::One(if o < position { below } else { above });
    }
    let origin_below = o < position || (o == position && d > 0.0);
    let (near, far) = if origin_below {
        (below, above)
    } else {
        (above, below)
    };
    let t = (position - o) / d;
    if t < 0.0 || t > hi {
        Crossing::One(near)
    } else if t < lo {
        Crossing::One(far)
    } else {
        Crossing::Both { near, far, t }
    }
}

/// The part of `[t_min, t_max]` in which the ray is inside `b`.
pub fn clip_to_box(
    b: &Aabb,
    origin: Vec3,
    dir: Vec3,
    t_min: f32,
    t_max: f32,
) -> Option<(f32, f32)> {
    let (mut lo, mut hi) = (t_min, t_max);
    for a in 0..3 {
        let (o, d) = (origin[a], dir[a]);
        if d == 0.0 {
            if o < b.min[a] || o > b.max[a] {
                return None;
            }
            continue;
        }
        // Same formula as the split planes in `walk`, so box faces and planes agree bit for bit.
        let t1 = (b.min[a] - o) / d;
        let t2 = (b.max[a] - o) / d;
        lo = lo.max(t1.min(t2));
        hi = hi.min(t1.max(t2));
    }
    (lo <= hi).then_some((lo, hi))
}

/// The far sides a walk will come back to: the first 32 in place, any deeper ones on the heap.
/// The places are left uninitialised: zeroing them cost more than a one-domain walk itself.
struct WalkStack {
    inline: [MaybeUninit<(u32, f32, f32)>; 32],
    len: usize,
    spill: Vec<(u32, f32, f32)>,
}

impl Default for WalkStack {
    #[inline(always)]
    fn default() -> Self {
        WalkStack {
            inline: [const { MaybeUninit::uninit() }; 32],
            len: 0,
            spill: Vec::new(),
        }
    }
}

impl WalkStack {
    #[inline(always)]
    fn push(&mut self, e: (u32, f32, f32)) {
        if self.len < self.inline.len() {
            self.inline[self.len].write(e);
            self.len += 1;
        } else {
            self.spill.push(e);
        }
    }

    #[inline(always)]
    fn pop(&mut self) -> Option<(u32, f32, f32)> {
        // Entries past the inline ones are the newest.
        if let Some(e) = self.spill.pop() {
            return Some(e);
        }
        self.len = self.len.checked_sub(1)?;
        // SAFETY: places below `len` were written by `push`.
        Some(unsafe { self.inline[self.len].assume_init() })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid_points(n: usize) -> Vec<([f32; 3], f64)> {
        let mut v = Vec::new();
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    v.push((
                        [i as f32, j as f32, k as f32].map(|x| (x + 0.5) / n as f32),
                        1.0,
                    ));
                }
            }
        }
        v
    }

    fn unit() -> Aabb {
        Aabb {
            min: [0.0; 3],
            max: [1.0; 3],
        }
    }

    #[test]
    fn balanced_split_gives_every_domain_an_equal_share() {
        let mut pts = grid_points(8);
        for n in [1, 3, 8, 13, 64] {
            let t = DomainTree::balanced(unit(), &mut pts, n);
            DomainTree::check(t.nodes(), n as usize).unwrap();
            let boxes = t.domain_boxes(n as usize);
            for b in &boxes {
                let inside = pts
                    .iter()
                    .filter(|p| {
                        (0..3).all(|a| {
                            p.0[a] >= b.min[a]
                                && p.0[a] < b.max[a].max(if b.max[a] == 1.0 { 2.0 } else { 0.0 })
                        })
                    })
                    .count();
                let ideal = pts.len() as f64 / n as f64;
                assert!(
                    (inside as f64 - ideal).abs() <= ideal * 0.5 + 1.0,
                    "{n}: {inside} vs {ideal}"
                );
            }
        }
    }

    /// A coordinate that often lands on the grid's planes (multiples of 1/8) or outside the
    /// unit box, where a ray's interval is decided by ties.
    fn coordinate() -> impl proptest::strategy::Strategy<Value = f32> {
        use proptest::prelude::*;
        prop_oneof![(-2i32..=10).prop_map(|k| k as f32 / 8.0), -1.5f32..2.5,]
    }

    /// A direction component: often zero (the walk's own case), else any sign.
    fn direction() -> impl proptest::strategy::Strategy<Value = f32> {
        use proptest::prelude::*;
        prop_oneof![Just(0.0f32), Just(1.0), Just(-1.0), -1.0f32..1.0]
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig {
            cases: 2_000,
            failure_persistence: None,
            ..Default::default()
        })]

        /// Every domain's interval from one descent is the walk's, bit for bit, and `None`
        /// exactly where the walk passes the domain by.
        #[test]
        fn a_domains_interval_is_the_one_the_walk_visits_it_with(
            domains in 1u32..40,
            origin in proptest::array::uniform3(coordinate()),
            dir in proptest::array::uniform3(direction()),
            t_min in proptest::prop_oneof![proptest::strategy::Just(0.0f32), 0.0f32..2.0],
            t_len in proptest::prop_oneof![proptest::strategy::Just(f32::INFINITY), 0.0f32..4.0],
        ) {
            let mut pts = grid_points(8);
            let t = DomainTree::balanced(unit(), &mut pts, domains);
            let (origin, dir) = (Vec3::from(origin), Vec3::from(dir));
            let mut walked = vec![None; domains as usize];
            t.walk(origin, dir, t_min, t_min + t_len, |d, a, b| {
                walked[d as usize] = Some((a.to_bits(), b.to_bits()));
                ControlFlow::Continue(())
            });
            for d in 0..domains {
                let found = t
                    .interval(d, origin, dir, t_min, t_min + t_len)
                    .map(|(a, b)| (a.to_bits(), b.to_bits()));
                proptest::prop_assert_eq!(found, walked[d as usize], "domain {}", d);
            }
            proptest::prop_assert_eq!(t.interval(domains, origin, dir, t_min, t_min + t_len), None);
        }
    }

    #[test]
    fn a_leaf_deeper_than_a_route_is_found_by_walking() {
        // A chain of 70 splits on x at 1/2, 1/4, ...: domain 70 sits 70 levels down.
        let levels = 70u32;
        let mut nodes = Vec::new();
        for level in 0..levels {
            let i = nodes.len() as u32;
            nodes.push(KdNode::Split {
                axis: 0,
                position: 0.5f32.powi(level as i32 + 1),
                below: i + 2,
                above: i + 1,
            });
            nodes.push(KdNode::Leaf { domain: level });
        }
        nodes.push(KdNode::Leaf { domain: levels });
        DomainTree::check(&nodes, levels as usize + 1).unwrap();
        let t = DomainTree::new(unit(), nodes);
        let (origin, dir) = (Vec3::new(1.0, 0.5, 0.5), Vec3::new(-1.0, 0.0, 0.0));
        let mut walked = Vec::new();
        t.walk(origin, dir, 0.0, f32::INFINITY, |d, a, b| {
            walked.push((d, a, b));
            ControlFlow::Continue(())
        });
        assert_eq!(walked.len(), levels as usize + 1);
        for (d, a, b) in walked {
            assert_eq!(
                t.interval(d, origin, dir, 0.0, f32::INFINITY),
                Some((a, b)),
                "{d}"
            );
        }
    }

    #[test]
    fn walk_intervals_are_contiguous_and_in_order() {
        let mut pts = grid_points(6);
        let t = DomainTree::balanced(unit(), &mut pts, 27);
        let dirs = [
            [1.0, 0.3, 0.2],
            [-0.2, 1.0, -0.7],
            [0.0, 0.0, -1.0],
            [0.5, -0.5, 0.0],
        ];
        for d in dirs {
            let origin = Vec3::new(0.5, 0.5, 0.5) - Vec3::from(d) * 3.0;
            let mut last: Option<f32> = None;
            let mut count = 0;
            t.walk(origin, Vec3::from(d), 0.0, f32::INFINITY, |_, a, b| {
                assert!(a <= b);
                if let Some(l) = last {
                    assert_eq!(l, a, "gap or overlap between domains");
                }
                last = Some(b);
                count += 1;
                ControlFlow::Continue(())
            });
            assert!(count >= 3);
        }
    }

    #[test]
    fn rays_from_a_point_meet_domains_in_its_front_to_back_order() {
        let mut pts = grid_points(6);
        let t = DomainTree::balanced(unit(), &mut pts, 27);
        let eye = [0.2, -1.5, 0.7];
        let place = t.front_to_back(eye, 27);
        let mut sorted = place.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..27).collect::<Vec<u32>>(), "each place once");
        for d in [
            [0.0, 1.0, 0.0],
            [0.1, 1.0, -0.1],
            [-0.05, 1.0, 0.1],
            [0.2, 1.0, 0.05],
        ] {
            let mut seen = Vec::new();
            t.walk(
                Vec3::from(eye),
                Vec3::from(d),
                0.0,
                f32::INFINITY,
                |dom, _, _| {
                    seen.push(place[dom as usize]);
                    ControlFlow::Continue(())
                },
            );
            assert!(seen.len() >= 3, "{d:?}");
            assert!(seen.windows(2).all(|w| w[0] < w[1]), "{d:?}: {seen:?}");
        }
    }

    #[test]
    fn check_rejects_cycles_and_missing_domains() {
        let cyc = vec![
            KdNode::Split {
                axis: 0,
                position: 0.5,
                below: 0,
                above: 1,
            },
            KdNode::Leaf { domain: 0 },
        ];
        assert!(DomainTree::check(&cyc, 1).is_err());
        let missing = vec![KdNode::Leaf { domain: 0 }];
        assert!(DomainTree::check(&missing, 2).is_err());
        assert!(DomainTree::check(&missing, 1).is_ok());
    }
}
