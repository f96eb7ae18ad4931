//! A synthetic cluster at the papers' scale for measuring planning: the one set of reports
//! that the planning benchmark (`benches/planning.rs`) times and that `rayfarm sim calibrate`
//! prices a planning round by, so both measure the same rounds.
//!
//! Every member's cache holds [`RESIDENT`] domains of [`DOMAIN_BYTES`] each and it has rays
//! queued for [`QUEUED`] domains, all drawn from a fixed hash (`sampling::mix64`), so every
//! run plans the same cluster.

use std::collections::{BTreeMap, BTreeSet};

use super::rounds::{Member, Queues};
use crate::sampling::mix64;

/// Domains each synthetic member's cache holds.
pub const RESIDENT: usize = 2;
/// Domains each synthetic member has rays queued for.
pub const QUEUED: usize = 16;
/// Bytes of every synthetic domain (a member's cache holds [`RESIDENT`] of them).
pub const DOMAIN_BYTES: u64 = 64 << 20;

/// `workers` members over `domains` domains, by key; the first `dry` of them have run dry
/// (their report is of their plan's round), the rest are busy (their plan is of a later
/// round). Each holds its resident domains and has them as its plan.
pub fn members(workers: u32, domains: u32, dry: u32) -> BTreeMap<u32, Member> {
    (0..workers)
        .map(|w| {
            let pick =
                |i: usize| (mix64(u64::from(w) << 20 | i as u64) % u64::from(domains)) as u32;
            let resident: Vec<u32> = (0..RESIDENT).map(pick).collect();
            let queued: BTreeMap<u32, u64> = (RESIDENT..RESIDENT + QUEUED)
                .map(|i| (pick(i), 1 + mix64(i as u64 ^ u64::from(w)) % 10_000))
                .collect();
            let member = Member {
                cache_bytes: RESIDENT as u64 * DOMAIN_BYTES,
                report: Some(Queues {
                    round: 1,
                    resident: resident.clone(),
                    queued,
                    ..Queues::default()
                }),
                plan: resident.into_iter().collect::<BTreeSet<u32>>(),
                planned_round: if w < dry { 1 } else { 2 },
            };
            (w, member)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_members_are_dry_and_the_rest_busy() {
        let members = members(8, 64, 3);
        assert_eq!(members.len(), 8);
        let dry: Vec<u32> = members
            .iter()
            .filter(|(_, m)| m.is_dry())
            .map(|(&k, _)| k)
            .collect();
        assert_eq!(dry, [0, 1, 2]);
        for m in members.values() {
            let report = m.report.as_ref().unwrap();
            assert!(report.resident.iter().all(|&d| d < 64));
            assert!(report.queued.iter().all(|(&d, &n)| d < 64 && n > 0));
        }
        // The same hash, the same cluster.
        let again = super::members(8, 64, 3);
        assert!(members.iter().zip(&again).all(|(a, b)| a.0 == b.0
            && a.1.report.as_ref().map(|r| &r.queued) == b.1.report.as_ref().map(|r| &r.queued)));
    }
}
