//! The running frame's rounds: the owner map given once (domain, and hybrid whose owned
//! domains fit the caches), barrier and asynchronous rounds planned from the members'
//! reports by `schedule::rounds` (dynamic and predictive), and what each member is told of
//! the holders afterwards (whole, or only what changed, by view class). The policies are
//! `rayfarm_core::schedule`'s; this applies them to the frame's members and makes the
//! messages.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use rayfarm_core::schedule::DomainId;
use rayfarm_core::schedule::dynamic::WorkerPlan;
use rayfarm_core::schedule::rounds;
use rayfarm_core::schedule::static_plans::domain_owner;
use rayfarm_proto::{self as proto, Schedule, coordinator_message::Body};
use tracing::{debug, info};

use super::{Member, Outgoing, RunningFrame, msg};
use crate::Time;
use crate::coordinator::holders::{
    ClassLines, HolderChange, HolderMap, class_of, view, view_classes,
};

impl RunningFrame {
    /// Whether the frame's domains go to owners once (domain, and hybrid whose owned domains
    /// fit the caches) rather than by rounds.
    pub(super) fn owners_once(&self) -> bool {
        match self.schedule {
            Schedule::Domain => true,
            Schedule::Hybrid => !self.hybrid_rounds,
            _ => false,
        }
    }

    /// The static domain schedule: domain `d` belongs to the `d mod n`-th worker.
    pub(super) fn owner_plans(&mut self) -> Vec<Outgoing> {
        let keys: Vec<u32> = self.members.keys().copied().collect();
        let n = keys.len() as u32;
        let owner = |d: u32| keys[domain_owner(DomainId(d), n) as usize];
        let domains = self.domain_bytes.len() as u32;
        for d in 0..domains {
            self.grants.name_holder(owner(d));
        }
        // One owner a domain: the map goes packed, a key a domain (`sole_holders`).
        let sole_holders: Vec<u32> = (0..domains).map(|d| owner(d).saturating_add(1)).collect();
        // Every member gets the whole map; no asynchronous round follows these schedules'
        // one plan, but the record stays true.
        self.sent_holders
            .update((0..domains).map(|d| (d, vec![owner(d)])).collect());
        self.sent_holders.synced_only(keys.iter().copied());
        self.round = 1;
        self.planning.owner_map();
        keys.iter()
            .map(|&key| {
                let body = Body::RoundPlan(proto::RoundPlan {
                    job_id: self.frame_id(),
                    round: 1,
                    work_on: (0..domains).filter(|&d| owner(d) == key).collect(),
                    evict: Vec::new(),
                    holders: Vec::new(),
                    next: Vec::new(),
                    holders_delta: false,
                    sole_holders: sole_holders.clone(),
                    report_hold_ms: 0,
                });
                (key, msg(body))
            })
            .collect()
    }

    /// Under barrier rounds: once every member's round is over, plans the next round for all
    /// of them from their reports (nothing while anyone still works).
    pub(super) fn plan_if_round_over(&mut self) -> Vec<Outgoing> {
        let Some((plan, wanted)) = self.cluster().barrier_round(self.round) else {
            return Vec::new();
        };
        self.round += 1;
        self.planning.whole(self.members.len());
        self.planned_loads += plan.load_count() as u64;
        let map: HolderMap = plan
            .routes()
            .into_iter()
            .map(|(d, ws)| (d.0, ws.into_iter().map(|w| w.0).collect()))
            .collect();
        let holders = self.holders(map.clone());
        // Only the planned members get this map, whole.
        self.sent_holders.update(map);
        self.sent_holders
            .synced_only(plan.workers().iter().map(|p| p.worker.0));
        info!(
            round = self.round,
            loads = plan.load_count(),
            wanted,
            "round planned"
        );
        plan.workers()
            .iter()
            .map(|p| self.plan_message(p, &holders, Vec::new(), false, 0))
            .collect()
    }

    /// `p` as this round's message to its worker, with `holders` (only the changed ones if
    /// `delta`) and the domains it will most likely be given next (`next`, for its prefetch).
    pub(super) fn plan_message(
        &self,
        p: &WorkerPlan,
        holders: &[proto::DomainHolders],
        next: Vec<u32>,
        delta: bool,
        report_hold_ms: u32,
    ) -> Outgoing {
        debug!(worker = p.worker.0, keep = ?p.keep, load = ?p.load, evict = ?p.evict, ?next, "plan");
        let body = Body::RoundPlan(proto::RoundPlan {
            job_id: self.frame_id(),
            round: self.round,
            work_on: p.work().map(|d| d.0).collect(),
            evict: p.evict.iter().map(|d| d.0).collect(),
            holders: holders.to_vec(),
            next,
            holders_delta: delta,
            sole_holders: Vec::new(),
            report_hold_ms,
        });
        (p.worker.0, msg(body))
    }

    /// Planning one step ahead, for jobs that prefetch: for each of `plans` in turn, the
    /// domain its worker will most likely be given when it runs dry, from the same
    /// ray-weighted planning: the fullest wanted domain nobody holds once these plans are
    /// adopted (what Fig. 5 would hand out next), each guessed for one worker only.
    pub(super) fn next_domains(&self, plans: &[WorkerPlan]) -> Vec<Vec<u32>> {
        if !self.spec.prefetch {
            return vec![Vec::new(); plans.len()];
        }
        let mut unheld = self.index.unheld();
        plans
            .iter()
            .map(|p| {
                unheld
                    .by_ref()
                    .find(|&d| !p.works_on(DomainId(d)))
                    .into_iter()
                    .collect()
            })
            .collect()
    }

    /// Asynchronous rounds: plans every member that has run dry, from the latest reports of
    /// all, kept in `index` (the plans of `rounds::Cluster::dry_plans`, at the cost of the
    /// dry members' plans); members whose plan did not change learn the new holders. A member
    /// that holds the last map sent gets only the domains whose holders changed
    /// (`SentHolders`), so a round costs what it changed, not members x held domains.
    pub(super) fn plan_dry_members(&mut self) -> Vec<Outgoing> {
        // In a subframe after the first, its first plan waits until every member has reported
        // once: the members hold what they loaded for the subframe before, but a member that
        // has not reported takes no part in a plan, so the first to report would be planned
        // alone and given every domain it has rays for (predictive, caches holding the scene
        // of 48 domains: 48 + 45 + 26 + 15 loads over four subframes, 48 + 0 + 0 + 0 with the
        // wait). A frame's first subframe does not wait: caches are cold or unknown there, and
        // waiting for the slowest member's first report cost the dynamic schedule 36% of a
        // simulated frame (b48, 4 workers, 8 spp) for no load saved. Every member reports when
        // it first runs out of work; one that never does is dropped by its heartbeat timeout,
        // which lets the plan go ahead.
        if self.subframe > 0 && self.round == 0 && self.members.values().any(|m| !m.reported) {
            return Vec::new();
        }
        let whole = self.index.dry_count() >= self.members.len();
        let changed = self.index.dry_plans(&self.members, self.options);
        if changed.is_empty() {
            return Vec::new();
        }
        self.round += 1;
        // Nobody busy: `dry_plans` planned every member from the whole cluster.
        if whole {
            self.planning.whole(self.members.len());
        } else {
            self.planning.incremental(changed.len(), self.members.len());
        }
        let (loads, touched) = self.index.adopt(&mut self.members, &changed, self.round);
        self.planned_loads += loads;
        let holder_changes = self.index.take_holder_changes();
        let members = &self.members;
        let was_in_step = self.sent_holders.in_step();
        let changes = self
            .sent_holders
            .update_from_index(holder_changes, || rounds::current_holders(members));
        if !was_in_step {
            // The map before was another kind's (a barrier round's, the owner map's): its
            // lists were whole, not views, so every member starts from the whole view.
            self.sent_holders.synced_only(std::iter::empty());
        }
        let classes = *self
            .view_classes
            .get_or_insert_with(|| view_classes(self.members.len()));
        // Every holder in the map is named in `Grants`: those a domain gained here, the others
        // when the map that first listed them was sent.
        let deltas = self.holder_changes(&changes, classes);
        // The round's changes wait with what is pending for each class: the members planned
        // or touched here take some of them now (below), everyone the rest at the next flush.
        self.sent_holders.absorb(&deltas, classes, self.round);
        // What a member planned or touched here is told with its plan or at once: when busy
        // members are told after every round (no interval), its class's pending lines, all of
        // them, as the flush that follows tells everyone; else only the lines of the domains
        // whose rays this round moved from it (it must forward those now: the next plans count
        // on it), the rest at the flush, as any busy member (`round_lines`). Telling every
        // member planned or touched every line a round changed made a round of n dry members
        // cost n x n lines (25 ms with 64 dry at 1,024 x 8,192, `rayfarm sim calibrate`).
        let mut lines: BTreeMap<(u32, bool), (Vec<proto::DomainHolders>, bool)> = BTreeMap::new();
        debug!(
            round = self.round,
            planned = changed.len(),
            changed_domains = changes.len(),
            "dry workers planned"
        );
        let next = self.next_domains(&changed);
        let hold = self.report_hold.for_members(self.members.len());
        let hold = u32::try_from(hold.as_millis()).unwrap_or(u32::MAX);
        let mut out: Vec<Outgoing> = Vec::with_capacity(changed.len());
        for (p, next) in changed.iter().zip(next) {
            let key = p.worker.0;
            let (l, all) = self.round_lines(key, classes, &mut lines);
            let synced = self.sent_holders.is_synced(key);
            out.push(self.plan_message(p, &l, next, synced, hold));
            if all {
                self.sent_holders.told(key, self.round);
            }
        }
        // Members whose reported rays the index now counts at a domain's new holder
        // (`RoundIndex::adopt` moved them) are told at once, as before the flush existed: the
        // next plans count on those rays being forwarded, and a member told only at the flush
        // could miss a holder that gained and dropped the domain within one interval, and keep
        // rays nobody counts (a hybrid frame at 8 workers never ended that way).
        let planned: BTreeSet<u32> = changed.iter().map(|p| p.worker.0).collect();
        for key in touched {
            if planned.contains(&key) || !self.members.contains_key(&key) {
                continue;
            }
            let Some((_, synced)) = self.owes_holders(key, classes) else {
                continue;
            };
            let (holders, all) = self.round_lines(key, classes, &mut lines);
            if !synced || !holders.is_empty() {
                let h = proto::Holders {
                    job_id: self.frame_id(),
                    holders,
                    delta: synced,
                };
                out.push((key, msg(Body::Holders(h))));
            }
            if all {
                self.sent_holders.told(key, self.round);
            }
        }
        // Counted, not looked up member by member: a round costs what it planned.
        debug_assert!(self.members.len() >= self.sent_holders.synced_count());
        if self.sent_holders.synced_count() < self.members.len() {
            self.sent_holders.mark_dirty();
        }
        out
    }

    /// Whether member `key` is owed a `Holders`: its view class and whether it holds a map
    /// from the last flush on, unless it does and was told its class's pending lines already.
    fn owes_holders(&self, key: u32, classes: u32) -> Option<(u32, bool)> {
        let class = class_of(key, classes);
        let synced = self.sent_holders.is_synced(key);
        (!(synced && self.sent_holders.is_told(key, class))).then_some((class, synced))
    }

    /// What member `key`, planned or touched by this round, is told with it (see
    /// `plan_dry_members`): the whole map as its class sees it if it holds no map from the
    /// last flush on, its class's pending lines if busy members are told after every round
    /// (both kept in `lines` by class and state for the other members), else its class's
    /// pending lines of the domains whose rays the round moved from it; and whether that is
    /// every line it lacks (then the flush may pass it over).
    fn round_lines(
        &self,
        key: u32,
        classes: u32,
        lines: &mut BTreeMap<(u32, bool), (Vec<proto::DomainHolders>, bool)>,
    ) -> (Vec<proto::DomainHolders>, bool) {
        let class = class_of(key, classes);
        let synced = self.sent_holders.is_synced(key);
        if !synced || self.holders_interval.is_zero() {
            return lines
                .entry((class, synced))
                .or_insert_with(|| (self.lines_for(class, classes, synced), true))
                .clone();
        }
        let members = &self.members;
        let empty = BTreeSet::new();
        let moved = self.index.moved_from(key).unwrap_or(&empty);
        self.sent_holders
            .pending()
            .lines_of(class, moved, |k| members.contains_key(&k))
    }

    /// The one `Holders` every member of view `class` in state `synced` is owed at a flush
    /// ([`Self::lines_for`]), and the lines made for it; no message when they hold a map from
    /// the last flush on and their class has no pending line.
    fn holders_message(
        &self,
        class: u32,
        classes: u32,
        synced: bool,
    ) -> (Option<Arc<proto::CoordinatorMessage>>, usize) {
        let holders = self.lines_for(class, classes, synced);
        let made = holders.len();
        if synced && holders.is_empty() {
            return (None, made);
        }
        let h = proto::Holders {
            job_id: self.frame_id(),
            holders,
            delta: synced,
        };
        (Some(msg(Body::Holders(h))), made)
    }

    /// What a member of view `class` is told of the holders: its class's pending lines if it
    /// holds a map from the last flush on (`synced`), else the whole map as its class sees it.
    fn lines_for(&self, class: u32, classes: u32, synced: bool) -> Vec<proto::DomainHolders> {
        if !synced {
            return self.whole_view(class, classes);
        }
        let lost = &self.lost;
        self.sent_holders
            .pending()
            .lines(class, |k| !lost.contains(&k))
    }

    /// When the members' next holders flush is due, if a round changed anything since the last.
    pub fn holders_due(&self) -> Option<Time> {
        self.sent_holders.due(self.holders_interval)
    }

    /// Tells every member what changed in the holders since the last flush, if it is due at
    /// `now` (at most once per holders interval): a member that holds a map from the last flush
    /// on gets its class's pending lines (none if its plan carried them already), any other
    /// the whole map as its class sees it. Between flushes a busy member routes by what it
    /// was told last: a ray for a domain whose new holder it has not heard of waits in its
    /// queue, and one sent to a former holder is forwarded or waits there, until the next
    /// flush or plan (README "Simulator": one message a round to every busy member was 91% of
    /// a 256-worker dynamic simulation's messages).
    pub fn flush_holders(&mut self, now: Time) -> Vec<Outgoing> {
        if self.holders_due().is_none_or(|t| now < t) {
            return Vec::new();
        }
        let Some(classes) = self.view_classes else {
            return Vec::new();
        };
        // One message per (class, synced), made when its first member is met and shared by
        // reference with the rest (`Outgoing`): a flush costs lines + members, not lines x
        // members.
        let mut messages: BTreeMap<(u32, bool), Option<Arc<proto::CoordinatorMessage>>> =
            BTreeMap::new();
        let mut lines = 0;
        let mut out = Vec::new();
        for &key in self.members.keys() {
            let Some((class, synced)) = self.owes_holders(key, classes) else {
                continue;
            };
            let m = messages.entry((class, synced)).or_insert_with(|| {
                let (m, made) = self.holders_message(class, classes, synced);
                lines += made;
                m
            });
            if let Some(m) = m {
                out.push((key, Arc::clone(m)));
            }
        }
        self.flushing.flushes += 1;
        self.flushing.members += self.members.len() as u64;
        self.flushing.told += out.len() as u64;
        self.flushing.lines += lines as u64;
        let round = self.round;
        self.sent_holders
            .flushed(now, self.members.keys().copied().collect::<Vec<_>>(), round);
        out
    }

    /// Takes member `key`'s report, plan and presence as they are now into `index`.
    pub(super) fn touch(&mut self, key: u32) {
        self.index
            .update(key, self.members.get(&key).map(|m| &m.rounds));
    }

    /// The frame's members as the rounds see them. Only the predictive schedule plans the
    /// oldest generation first.
    pub(super) fn cluster(&self) -> rounds::Cluster<'_, Member> {
        rounds::Cluster {
            members: &self.members,
            domain_bytes: &self.domain_bytes,
            oldest_first: self.schedule == Schedule::Predictive,
            options: self.options,
        }
    }

    /// Holders by member key, as the workers get them (they know every member's address
    /// from the roster). Every key named is recorded as a holder (`Grants`).
    pub(super) fn holders(
        &mut self,
        by_domain: impl IntoIterator<Item = (u32, Vec<u32>)>,
    ) -> Vec<proto::DomainHolders> {
        let by_domain: Vec<(u32, Vec<u32>)> = by_domain.into_iter().collect();
        for k in by_domain.iter().flat_map(|(_, keys)| keys) {
            if self.members.contains_key(k) {
                self.grants.name_holder(*k);
            }
        }
        by_domain
            .into_iter()
            .map(|(domain, keys)| proto::DomainHolders {
                domain,
                workers: keys
                    .into_iter()
                    .filter(|k| self.members.contains_key(k))
                    .collect(),
                lost: Vec::new(),
            })
            .collect()
    }

    /// The deltas the members get, by view class (`holders::view`): each changed domain's
    /// keys gained and lost in the views of the classes that hold it, and in every other
    /// class's (`ClassLines`). Every key gained is recorded as a holder (`Grants`); one no
    /// longer a member is left out (a lost member's domains are listed with it as lost, and the
    /// workers forgot it already).
    pub(super) fn holder_changes(
        &mut self,
        changes: &[HolderChange],
        classes: u32,
    ) -> Vec<ClassLines> {
        for c in changes {
            for k in c.whole().gained {
                if self.members.contains_key(&k) {
                    self.grants.name_holder(k);
                }
            }
        }
        let members = &self.members;
        changes
            .iter()
            .map(|c| c.lines(classes).keeping(|k| members.contains_key(&k)))
            .collect()
    }

    /// The last map sent as a member of view `class` sees it, whole.
    pub(super) fn whole_view(&self, class: u32, classes: u32) -> Vec<proto::DomainHolders> {
        self.sent_holders
            .sent()
            .iter()
            .map(|(&domain, keys)| proto::DomainHolders {
                domain,
                workers: view(keys, class, classes)
                    .into_iter()
                    .filter(|k| self.members.contains_key(k))
                    .collect(),
                lost: Vec::new(),
            })
            .collect()
    }
}
