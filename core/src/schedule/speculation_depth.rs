//! How many domains ahead a new ray is copied when rays are placed speculatively
//! (`render::speculation`): the knob between tracing a ray one domain at a time and copying
//! it into every domain along it at once. Park, Fussell and Navrátil predict it; this is their
//! probability model.
//!
//! A ray's copies go out in windows: the first window holds the nearest domains along the
//! ray, and only once all their verdicts are in and none ends the ray (no hit for a radiance
//! ray, no occluder for a shadow ray) does the next window go out. A window is as long as it
//! takes for the ray to end inside it with at least the target probability, from each
//! domain's termination rate: of the rays of the same class that reached the domain, the
//! share that ended there, learned from the rays concluded before. Full speculation is one
//! window of the whole path; a window of one domain is the chained trace with a verdict's
//! round trip per domain.
//!
//! A cut is priced per ray, but a load is paid per domain: a later window's copies reach
//! their domains only once the window before has answered, and if the schedule has by then
//! traced such a domain for their generation and evicted it, it is loaded again, for however
//! few of them (issue 20, README "Why predicted speculation loads more than full"). So the
//! windows also learn, per domain, whether the later windows sent into it came after it had
//! been traced for their generation (a verdict of that generation had come back from it), and
//! a window is not cut in front of a domain where they mostly did: it reaches at least to the
//! last such domain along the ray (full speculation there, predicted elsewhere).
//!
//! Whatever the windows, a ray concludes exactly as the chained trace does: each window is a
//! prefix of what is left of the path, so the nearest domain with a hit (or any occluder) is
//! found before anything beyond it matters. So the prediction may depend on the order rays
//! concluded in (on a cluster, on timing) without changing a single bit of the image; it only
//! moves work between segments traced and verdict round trips.

use crate::ray::{RayKind, RayRecord};

/// How far ahead of what is known a ray is copied.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Depth {
    /// Every domain along the ray at once (one window).
    Full,
    /// This many domains at a time (at least one).
    Ahead(u32),
    /// As many domains as make the ray end inside the window with at least this
    /// probability (in `[0, 1]`; 0 is one domain at a time, 1 the whole path once a
    /// domain's rate is known to be below 1), from termination rates learned as rays conclude.
    Predicted(f32),
}

impl Depth {
    /// The target termination probability of `--speculation predicted` when none is given.
    pub const DEFAULT_TARGET: f32 = 0.9;

    /// Parses `full`, `ahead:N` (N >= 1), `predicted` or `predicted:P` (P in [0, 1]).
    pub fn parse(s: &str) -> Result<Depth, String> {
        let (name, arg) = match s.split_once(':') {
            Some((n, a)) => (n, Some(a)),
            None => (s, None),
        };
        match (name, arg) {
            ("full", None) => Ok(Depth::Full),
            ("predicted", None) => Ok(Depth::Predicted(Self::DEFAULT_TARGET)),
            ("predicted", Some(p)) => match p.parse::<f32>() {
                Ok(p) if (0.0..=1.0).contains(&p) => Ok(Depth::Predicted(p)),
                _ => Err(format!(
                    "speculation target {p:?} is not a probability in [0, 1]"
                )),
            },
            ("ahead", Some(n)) => match n.parse::<u32>() {
                Ok(n) if n >= 1 => Ok(Depth::Ahead(n)),
                _ => Err(format!(
                    "speculation depth {n:?} is not a whole number >= 1"
                )),
            },
            _ => Err(format!(
                "unknown speculation {s:?} (known: full, ahead:N, predicted, predicted:P)"
            )),
        }
    }
}

/// Longest speculation setting a job may carry.
pub const MAX_SETTING_BYTES: usize = 32;

/// A job's speculation setting: `""` or `full`, `none` (no copies: `None`), or what
/// [`Depth::parse`] reads.
pub fn parse_setting(s: &str) -> Result<Option<Depth>, String> {
    if s.len() > MAX_SETTING_BYTES {
        return Err(format!(
            "speculation setting is {} bytes, at most {MAX_SETTING_BYTES}",
            s.len()
        ));
    }
    match s {
        "" => Ok(Some(Depth::Full)),
        "none" => Ok(None),
        _ => Depth::parse(s).map(Some),
    }
}

impl std::fmt::Display for Depth {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Depth::Full => write!(f, "full"),
            Depth::Ahead(n) => write!(f, "ahead:{n}"),
            Depth::Predicted(p) => write!(f, "predicted:{p}"),
        }
    }
}

/// Classes of rays whose termination rates are learned apart: camera rays enter the scene
/// from outside, bounces leave a surface, shadow rays look for any occluder.
const CLASSES: usize = 3;

fn class(ray: &RayRecord) -> usize {
    match ray.kind() {
        RayKind::Shadow => 2,
        RayKind::Radiance if ray.depth == 0 => 0,
        RayKind::Radiance => 1,
    }
}

/// A domain's rate before rays have shown it: as if `PRIOR_RAYS` rays had reached it and
/// `PRIOR_ENDED` of them had ended there (an even chance, weighed lightly).
const PRIOR_RAYS: f64 = 4.0;
const PRIOR_ENDED: f64 = 2.0;

/// Rays of one class that reached a domain, and those that ended there.
#[derive(Clone, Copy, Debug, Default)]
struct Tally {
    reached: u64,
    ended: u64,
}

impl Tally {
    fn rate(&self) -> f64 {
        (self.ended as f64 + PRIOR_ENDED) / (self.reached as f64 + PRIOR_RAYS)
    }
}

/// Later windows sent into one domain: before any verdict of their generation had come back
/// from it, and after (late: the domain had been traced for their generation already).
#[derive(Clone, Copy, Debug, Default)]
struct Lateness {
    on_time: u64,
    late: u64,
}

impl Lateness {
    /// Whether later windows into the domain mostly came late: at least one did, and at
    /// least as many as came on time. Before any later window into it, a domain is not.
    fn late(&self) -> bool {
        self.late > 0 && self.late >= self.on_time
    }
}

/// The window lengths of [`Depth`], with the termination rates it learns.
#[derive(Clone, Debug)]
pub struct Windows {
    depth: Depth,
    tallies: [Vec<Tally>; CLASSES],
    /// Per domain, one more than the newest generation a verdict came back from it for
    /// (0: none yet): the domain has been traced for that generation.
    visited: Vec<u16>,
    /// Per domain, the later windows sent into it and whether they came late.
    lateness: Vec<Lateness>,
}

impl Windows {
    /// Windows of `depth`, nothing learned yet.
    pub fn new(depth: Depth) -> Self {
        Windows {
            depth,
            tallies: Default::default(),
            visited: Vec::new(),
            lateness: Vec::new(),
        }
    }

    /// The knob.
    pub fn depth(&self) -> Depth {
        self.depth
    }

    /// How many domains of `path` (the domains with geometry along `ray`, nearest first)
    /// from `from` on to copy `ray` into now: at least one, at most what is left.
    pub fn window(&self, ray: &RayRecord, path: &[u32], from: usize) -> usize {
        let left = path.len().saturating_sub(from);
        let n = match self.depth {
            Depth::Full => left,
            Depth::Ahead(n) => n as usize,
            Depth::Predicted(target) => {
                let tallies = &self.tallies[class(ray)];
                let mut goes_on = 1.0f64;
                let mut n = 0;
                for &d in &path[from.min(path.len())..] {
                    n += 1;
                    let rate = tallies.get(d as usize).copied().unwrap_or_default().rate();
                    goes_on *= 1.0 - rate;
                    if 1.0 - goes_on >= f64::from(target) {
                        break;
                    }
                }
                // No cut in front of a domain later windows reach late: the window runs to
                // the last such domain along the ray.
                let rest = path.get(from + n..).unwrap_or_default();
                n + rest
                    .iter()
                    .rposition(|&d| self.late(d))
                    .map_or(0, |i| i + 1)
            }
        };
        n.clamp(1, left.max(1))
    }

    /// Whether later windows into `domain` mostly came after it had been traced for their
    /// generation.
    pub fn late(&self, domain: u32) -> bool {
        self.lateness
            .get(domain as usize)
            .is_some_and(Lateness::late)
    }

    /// Learns that a copy of `ray` was traced in `domain` (its verdict came back): the domain
    /// has been traced for the ray's generation.
    pub fn visited(&mut self, ray: &RayRecord, domain: u32) {
        if !matches!(self.depth, Depth::Predicted(_)) {
            return;
        }
        let d = domain as usize;
        if self.visited.len() <= d {
            self.visited.resize(d + 1, 0);
        }
        let g = ray.generation().saturating_add(1);
        self.visited[d] = self.visited[d].max(g);
    }

    /// Learns from a later window of `ray` (one after its first) sent into `domains`: each
    /// copy comes late where the domain has been traced for the ray's generation already.
    pub fn later_window(&mut self, ray: &RayRecord, domains: &[u32]) {
        if !matches!(self.depth, Depth::Predicted(_)) {
            return;
        }
        for &d in domains {
            let d = d as usize;
            if self.lateness.len() <= d {
                self.lateness.resize(d + 1, Lateness::default());
            }
            let visited = self.visited.get(d).copied().unwrap_or(0);
            if visited > ray.generation() {
                self.lateness[d].late += 1;
            } else {
                self.lateness[d].on_time += 1;
            }
        }
    }

    /// Learns from a concluded ray: it reached every domain of `path` up to `ended` (its index
    /// in `path`), and ended there; with `ended` `None` it went through all of them.
    pub fn learn(&mut self, ray: &RayRecord, path: &[u32], ended: Option<usize>) {
        if !matches!(self.depth, Depth::Predicted(_)) {
            return;
        }
        let tallies = &mut self.tallies[class(ray)];
        let reached = match ended {
            Some(i) => &path[..(i + 1).min(path.len())],
            None => path,
        };
        for &d in reached {
            let d = d as usize;
            if tallies.len() <= d {
                tallies.resize(d + 1, Tally::default());
            }
            tallies[d].reached += 1;
        }
        if let Some(&d) = ended.and_then(|i| path.get(i)) {
            tallies[d as usize].ended += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bytemuck::Zeroable;

    fn camera_ray() -> RayRecord {
        RayRecord::zeroed()
    }

    #[test]
    fn the_knob_parses_and_prints() {
        for s in ["full", "ahead:3", "predicted:0.5"] {
            assert_eq!(Depth::parse(s).unwrap().to_string(), s);
        }
        assert_eq!(
            Depth::parse("predicted").unwrap(),
            Depth::Predicted(Depth::DEFAULT_TARGET)
        );
        for bad in [
            "ahead:0",
            "ahead",
            "predicted:1.5",
            "predicted:x",
            "none",
            "full:2",
        ] {
            assert!(Depth::parse(bad).is_err(), "{bad}");
        }
        assert_eq!(parse_setting(""), Ok(Some(Depth::Full)));
        assert_eq!(parse_setting("none"), Ok(None));
        assert_eq!(parse_setting("ahead:2"), Ok(Some(Depth::Ahead(2))));
        assert!(
            parse_setting(&"x".repeat(40))
                .unwrap_err()
                .contains("at most")
        );
    }

    #[test]
    fn full_and_fixed_windows_cover_the_path_as_asked() {
        let path = [4, 7, 1, 9, 2];
        let r = camera_ray();
        assert_eq!(Windows::new(Depth::Full).window(&r, &path, 0), 5);
        assert_eq!(Windows::new(Depth::Full).window(&r, &path, 3), 2);
        let ahead = Windows::new(Depth::Ahead(2));
        assert_eq!(ahead.window(&r, &path, 0), 2);
        assert_eq!(ahead.window(&r, &path, 4), 1);
        assert_eq!(ahead.window(&r, &[], 0), 1, "never zero");
    }

    #[test]
    fn predicted_windows_grow_past_domains_rays_cross_and_stop_at_those_they_end_in() {
        let path = [0, 1, 2, 3];
        let r = camera_ray();
        let mut w = Windows::new(Depth::Predicted(0.9));
        // Unknown domains: an even chance each, 1 - 0.5^4 >= 0.9 after four.
        assert_eq!(w.window(&r, &path, 0), 4);
        // Rays cross 0 and 1 and end in 2.
        for _ in 0..100 {
            w.learn(&r, &path, Some(2));
        }
        assert_eq!(w.window(&r, &path, 0), 3);
        assert_eq!(w.window(&r, &path, 2), 1);
        // Shadow rays learn apart.
        let shadow = RayRecord {
            kind: RayKind::Shadow as u8,
            ..r
        };
        assert_eq!(w.window(&shadow, &path, 0), 4);
        // No speculation beyond the next domain at target 0; the whole path at 1 (a rate
        // never reaches 1 with the prior).
        assert_eq!(Windows::new(Depth::Predicted(0.0)).window(&r, &path, 0), 1);
        assert_eq!(Windows::new(Depth::Predicted(1.0)).window(&r, &path, 1), 3);
        // Fixed windows learn nothing.
        let mut fixed = Windows::new(Depth::Ahead(1));
        fixed.learn(&r, &path, None);
        assert!(fixed.tallies.iter().all(Vec::is_empty));
    }

    #[test]
    fn a_window_runs_through_the_last_domain_later_windows_reached_late() {
        let path = [0, 1, 2, 3];
        let r = camera_ray();
        let bounce = RayRecord { depth: 1, ..r };
        let mut w = Windows::new(Depth::Predicted(0.9));
        for _ in 0..100 {
            w.learn(&r, &path, Some(0));
        }
        assert_eq!(w.window(&r, &path, 0), 1, "rays end in domain 0");
        // Domains 1 and 3 were traced for generation 0; domain 2 only for generation 1.
        w.visited(&r, 1);
        w.visited(&r, 3);
        w.visited(&bounce, 2);
        // A camera ray's later window reaches domain 3 late, and domain 2 late too (traced
        // for a younger generation already); a bounce's reaches domain 1 on time.
        w.later_window(&r, &[3]);
        assert!(w.late(3));
        assert_eq!(w.window(&r, &path, 0), 4, "through domain 3");
        assert_eq!(w.window(&r, &[0, 1], 0), 1, "no late domain on this path");
        w.later_window(&bounce, &[1]);
        assert!(!w.late(1));
        w.later_window(&r, &[2]);
        assert!(w.late(2));
        // As many on time as late still counts as late; more on time does not.
        let second_bounce = RayRecord { depth: 2, ..r };
        w.later_window(&second_bounce, &[2]);
        assert!(w.late(2));
        w.later_window(&second_bounce, &[2]);
        assert!(!w.late(2));
        // Fixed windows learn none of it.
        let mut full = Windows::new(Depth::Full);
        full.visited(&r, 1);
        full.later_window(&r, &[1]);
        assert!(!full.late(1));
    }
}
