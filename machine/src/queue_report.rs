//! A worker's queue reports as deltas (`QueueReport.delta`, protocol 9): after a frame's first
//! report, a worker names only the queues that changed since its previous one, and the
//! coordinator puts them into what it heard before. In a predictive frame at 4,096 workers a
//! report names about 150 queues of which one or two changed; taking every report in whole
//! was 90% of the coordinator's CPU there (README "Simulator"). Both ends are here, so that
//! what one writes is what the other reads: the worker's [`Heard`], the coordinator's
//! [`changes`].

use std::collections::BTreeMap;

use rayfarm_core::schedule::round_index::Queue;
use rayfarm_proto as proto;

/// What the coordinator has heard of one worker's queues in the current frame: the whole of
/// them as its reports so far add up to.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Heard {
    /// Whether a report was sent: the next is a delta.
    sent: bool,
    queued: BTreeMap<u32, u64>,
    oldest: BTreeMap<u32, u32>,
}

/// The queue fields of one report: maps and cleared domains as [`proto::QueueReport`] carries
/// them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Named {
    pub delta: bool,
    pub queued_rays: BTreeMap<u32, u64>,
    pub oldest_generation: BTreeMap<u32, u32>,
    pub cleared_domains: Vec<u32>,
}

impl Heard {
    /// The queue fields of a report saying that this worker's queues are now `queued` (rays
    /// per domain) with the oldest generations `oldest`: whole if none was sent yet, else
    /// what differs from the last; they are then what the coordinator has heard.
    pub fn report(&mut self, queued: BTreeMap<u32, u64>, oldest: BTreeMap<u32, u32>) -> Named {
        if !std::mem::replace(&mut self.sent, true) {
            let named = Named {
                delta: false,
                queued_rays: queued.clone(),
                oldest_generation: oldest.clone(),
                cleared_domains: Vec::new(),
            };
            (self.queued, self.oldest) = (queued, oldest);
            return named;
        }
        let mut named = Named {
            delta: true,
            ..Named::default()
        };
        let before = |d: u32| (self.queued.get(&d).copied(), self.oldest.get(&d).copied());
        let now = |d: u32| (queued.get(&d).copied(), oldest.get(&d).copied());
        let mut domains: Vec<u32> = self
            .queued
            .keys()
            .chain(self.oldest.keys())
            .chain(queued.keys())
            .chain(oldest.keys())
            .copied()
            .collect();
        domains.sort_unstable();
        domains.dedup();
        for d in domains {
            let (rays, generation) = now(d);
            if (rays, generation) == before(d) {
                continue;
            }
            match (rays, generation) {
                (None, None) => named.cleared_domains.push(d),
                // Named in a map even if only its generation changed: then the missing entry
                // of the other says it has none now.
                _ => {
                    if let Some(n) = rays {
                        named.queued_rays.insert(d, n);
                    }
                    if let Some(g) = generation {
                        named.oldest_generation.insert(d, g);
                    }
                }
            }
        }
        (self.queued, self.oldest) = (queued, oldest);
        named
    }
}

/// The queues a report names, read once by the coordinator for both the cluster status and
/// the frame.
#[derive(Clone, Debug, PartialEq)]
pub enum Read {
    /// A whole report: its maps are the worker's queues.
    Whole,
    /// A delta: (domain, its queue now) of each queue that changed, as [`changes`] reads them.
    Changes(Vec<(u32, Queue)>),
}

/// Reads `report`'s queues: [`Read::Whole`] or a delta's [`changes`]; an error if it
/// contradicts itself.
pub fn read(report: &proto::QueueReport) -> Result<Read, String> {
    Ok(match report.delta {
        false => Read::Whole,
        true => Read::Changes(changes(report)?),
    })
}

/// A delta report's queues as (domain, its queue now), ascending by domain, each once; an
/// error if the report contradicts itself (a domain cleared and given entries).
pub fn changes(report: &proto::QueueReport) -> Result<Vec<(u32, Queue)>, String> {
    let mut domains: Vec<u32> = report
        .queued_rays
        .keys()
        .chain(report.oldest_generation.keys())
        .copied()
        .collect();
    domains.sort_unstable();
    domains.dedup();
    let named = domains.len();
    domains.extend(&report.cleared_domains);
    domains.sort_unstable();
    domains.dedup();
    if domains.len() != named + report.cleared_domains.len() {
        return Err("a domain is both cleared and given a queue, or cleared twice".to_string());
    }
    Ok(domains
        .into_iter()
        .map(|d| {
            let q = (
                report.queued_rays.get(&d).copied(),
                report.oldest_generation.get(&d).copied(),
            );
            (d, q)
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report(named: Named) -> proto::QueueReport {
        proto::QueueReport {
            delta: named.delta,
            queued_rays: named.queued_rays,
            oldest_generation: named.oldest_generation,
            cleared_domains: named.cleared_domains,
            ..Default::default()
        }
    }

    /// What the coordinator holds after taking `r` on top of `held`.
    fn take(held: &mut (BTreeMap<u32, u64>, BTreeMap<u32, u32>), r: &proto::QueueReport) {
        if !r.delta {
            *held = (r.queued_rays.clone(), r.oldest_generation.clone());
            return;
        }
        for (d, (rays, generation)) in changes(r).unwrap() {
            match rays {
                Some(n) => held.0.insert(d, n),
                None => held.0.remove(&d),
            };
            match generation {
                Some(g) => held.1.insert(d, g),
                None => held.1.remove(&d),
            };
        }
    }

    #[test]
    fn the_first_report_is_whole_and_later_ones_name_what_changed() {
        let mut heard = Heard::default();
        let first = heard.report(
            BTreeMap::from([(1, 10), (2, 20), (3, 30)]),
            BTreeMap::from([(1, 0), (2, 1), (3, 1)]),
        );
        assert!(!first.delta);
        assert_eq!(first.queued_rays.len(), 3);
        // Domain 1 gains rays, 2 loses its generation entry only, 3 goes, 4 comes.
        let second = heard.report(
            BTreeMap::from([(1, 11), (2, 20), (4, 40)]),
            BTreeMap::from([(1, 0), (4, 2)]),
        );
        assert!(second.delta);
        assert_eq!(
            second.queued_rays,
            BTreeMap::from([(1, 11), (2, 20), (4, 40)])
        );
        assert_eq!(second.oldest_generation, BTreeMap::from([(1, 0), (4, 2)]));
        assert_eq!(second.cleared_domains, vec![3]);
        // Nothing changed: nothing named.
        let third = heard.report(
            BTreeMap::from([(1, 11), (2, 20), (4, 40)]),
            BTreeMap::from([(1, 0), (4, 2)]),
        );
        assert_eq!(
            third,
            Named {
                delta: true,
                ..Named::default()
            }
        );
    }

    #[test]
    fn deltas_taken_in_order_add_up_to_the_queues() {
        // A fixed walk of queues changing every way: the coordinator's sum of the reports is
        // the worker's queues after each.
        let mut heard = Heard::default();
        let mut held = (BTreeMap::new(), BTreeMap::new());
        let mut x: u64 = 7;
        for _ in 0..200 {
            let mut queued = BTreeMap::new();
            let mut oldest = BTreeMap::new();
            for d in 0..12u32 {
                x = x
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                // Queues and generations come and go apart (a worker's generations follow its
                // queues, but the encoding does not rely on it).
                if (x >> 60) < 10 {
                    queued.insert(d, (x >> 40) % 4);
                }
                if !(x >> 50).is_multiple_of(3) {
                    oldest.insert(d, ((x >> 30) % 3) as u32);
                }
            }
            let r = report(heard.report(queued.clone(), oldest.clone()));
            take(&mut held, &r);
            assert_eq!(held, (queued, oldest));
        }
    }

    #[test]
    fn a_domain_cleared_and_named_is_refused() {
        let r = proto::QueueReport {
            delta: true,
            queued_rays: BTreeMap::from([(5, 1)]),
            cleared_domains: vec![5],
            ..Default::default()
        };
        assert!(changes(&r).is_err());
        let twice = proto::QueueReport {
            delta: true,
            cleared_domains: vec![6, 6],
            ..Default::default()
        };
        assert!(changes(&twice).is_err());
    }
}
