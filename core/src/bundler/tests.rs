use super::config::{KIB, MIB};
use super::*;

const MS: Duration = Duration::from_millis(1);
const US: Duration = Duration::from_micros(1);

fn at(ms: u64) -> Duration {
    Duration::from_millis(ms)
}

fn bundler() -> Bundler<u32> {
    Bundler::new(BundlerConfig::default()).expect("default config is valid")
}

fn msg(len: usize) -> Vec<u8> {
    vec![7; len]
}

fn tagged(tag: u8, len: usize) -> Bytes {
    Bytes::from(vec![tag; len])
}

#[test]
fn default_config_is_valid_and_ordered() {
    let config = BundlerConfig::default();
    assert_eq!(config.validate(), Ok(()));
    assert_eq!(Tier::MOST_URGENT_FIRST[0], Tier::Results);
    assert!(Tier::Results.is_more_urgent_than(Tier::Migrated));
    assert!(!Tier::Tasks.is_more_urgent_than(Tier::Migrated));
    // No default tier is immediate: even verdicts wait up to a millisecond to share a bundle.
    for tier in Tier::MOST_URGENT_FIRST {
        assert!(!config.policy(tier).is_immediate(), "{tier:?}");
    }
    for (i, tier) in Tier::MOST_URGENT_FIRST.into_iter().enumerate() {
        assert_eq!(Tier::from_index(i), Some(tier));
        assert_eq!(tier.index(), i);
    }
    assert_eq!(Tier::from_index(Tier::COUNT), None);
}

#[test]
fn nonsense_configs_are_rejected() {
    let base = BundlerConfig::default();
    let zero = base.with_policy(
        Tier::Migrated,
        TierPolicy {
            max_bytes: 0,
            max_age: MS,
        },
    );
    assert_eq!(
        zero.validate(),
        Err(ConfigError::ZeroMaxBytes {
            tier: Tier::Migrated
        })
    );
    assert!(
        zero.validate()
            .unwrap_err()
            .to_string()
            .contains("Migrated")
    );

    // Any tier may be immediate, as long as no tier after it waits less.
    let immediate_results = base.with_policy(Tier::Results, TierPolicy::immediate(10));
    assert_eq!(immediate_results.validate(), Ok(()));
    assert_eq!(
        base.with_policy(Tier::Tasks, TierPolicy::immediate(MIB))
            .validate(),
        Err(ConfigError::UrgencyInversion {
            more_urgent: Tier::Migrated,
            less_urgent: Tier::Tasks
        })
    );

    let inverted = base.with_policy(
        Tier::Results,
        TierPolicy {
            max_bytes: 10,
            max_age: at(10),
        },
    );
    assert_eq!(
        inverted.validate(),
        Err(ConfigError::UrgencyInversion {
            more_urgent: Tier::Results,
            less_urgent: Tier::Migrated
        })
    );

    assert_eq!(
        base.with_peer_cap(Some(0)).validate(),
        Err(ConfigError::ZeroPeerCap)
    );
    assert!(matches!(
        base.with_peer_cap(Some(MIB - 1)).validate(),
        Err(ConfigError::PeerCapBelowBundle {
            tier: Tier::Tasks,
            ..
        })
    ));
    assert_eq!(base.with_peer_cap(None).validate(), Ok(()));
    assert!(Bundler::<u32>::new(zero).is_err());
}

#[test]
fn verdicts_are_never_stuck_behind_bulk_traffic() {
    let mut b = bundler();
    for peer in 0..40 {
        for _ in 0..8 {
            b.push(peer, Tier::Tasks, msg(256 * KIB), at(0)).unwrap();
            b.push(peer, Tier::Migrated, msg(128 * KIB), at(0)).unwrap();
        }
    }
    // Due after its millisecond, when every peer's bulk tiers are long due too.
    b.push(39, Tier::Results, msg(32), at(100)).unwrap();
    let out = b.poll(at(101));
    assert_eq!(out[0].peer, 39);
    assert_eq!(out[0].tier, Tier::Results);
    assert_eq!(out[0].messages, vec![Bytes::from(msg(32))]);
    assert!(out[1..].iter().all(|bundle| bundle.tier != Tier::Results));
    assert!(out.len() > 40);
}

#[test]
fn an_immediate_tier_is_due_at_once() {
    let config = BundlerConfig::default().with_policy(Tier::Results, TierPolicy::immediate(KIB));
    let mut b: Bundler<u32> = Bundler::new(config).unwrap();
    b.push(1, Tier::Results, msg(1), at(5)).unwrap();
    b.push(1, Tier::Migrated, msg(1), at(5)).unwrap();
    assert_eq!(b.next_deadline(), Some(at(5)));
    let out = b.poll(at(5));
    assert_eq!(out.len(), 1);
    assert_eq!(out[0].tier, Tier::Results);
    // The other tiers keep their own policies.
    assert_eq!(b.next_deadline(), Some(at(10)));
    // An immediate tier still packs what is pending into bundles of its size.
    for i in 0..5 {
        b.push(1, Tier::Results, tagged(i, KIB / 2), at(6)).unwrap();
    }
    let sizes: Vec<usize> = b.poll(at(6)).iter().map(|x| x.messages.len()).collect();
    assert_eq!(sizes, vec![2, 2, 1]);
}

#[test]
fn size_trigger_fires_exactly_at_max_bytes_for_each_tier() {
    for tier in [Tier::Results, Tier::Migrated, Tier::Tasks] {
        let mut b = bundler();
        let max = b.config().policy(tier).max_bytes;
        b.push(1, tier, msg(max - 1), at(0)).unwrap();
        assert!(b.poll(at(0)).is_empty(), "{tier:?} flushed below max_bytes");
        b.push(1, tier, msg(1), at(0)).unwrap();
        let out = b.poll(at(0));
        assert_eq!(out.len(), 1, "{tier:?}");
        assert_eq!((out[0].bytes, out[0].messages.len()), (max, 2));
        assert!(b.is_empty());
    }
}

#[test]
fn age_trigger_fires_exactly_at_max_age_for_each_tier() {
    for tier in Tier::MOST_URGENT_FIRST {
        let mut b = bundler();
        let age = b.config().policy(tier).max_age;
        let start = at(3);
        b.push(1, tier, msg(10), start).unwrap();
        assert_eq!(b.next_deadline(), Some(start + age));
        assert!(
            b.poll(start + age - US).is_empty(),
            "{tier:?} flushed early"
        );
        let out = b.poll(start + age);
        assert_eq!(out.len(), 1, "{tier:?}");
        assert_eq!(out[0].tier, tier);
    }
}

#[test]
fn urgent_tiers_come_first_across_all_peers() {
    let mut b = bundler();
    for peer in [3, 1, 2] {
        for tier in Tier::MOST_URGENT_FIRST.into_iter().rev() {
            b.push(peer, tier, msg(10), at(0)).unwrap();
        }
    }
    let order: Vec<(Tier, u32)> = b
        .flush_all(at(0))
        .iter()
        .map(|bundle| (bundle.tier, bundle.peer))
        .collect();
    let mut expected = Vec::new();
    for tier in Tier::MOST_URGENT_FIRST {
        expected.extend([1, 2, 3].map(|peer| (tier, peer)));
    }
    assert_eq!(order, expected);
}

#[test]
fn oversized_message_travels_alone_and_whole() {
    let mut b = bundler();
    let max = b.config().policy(Tier::Migrated).max_bytes;
    b.push(1, Tier::Migrated, tagged(1, 10), at(0)).unwrap();
    b.push(1, Tier::Migrated, tagged(2, max + 5), at(0))
        .unwrap();
    b.push(1, Tier::Migrated, tagged(3, 10), at(0)).unwrap();
    let out = b.poll(at(0));
    // The giant made the tier due by size; the small tail waits for its own trigger.
    assert_eq!(out.len(), 2);
    assert_eq!(out[0].messages, vec![tagged(1, 10)]);
    assert_eq!(out[1].messages, vec![tagged(2, max + 5)]);
    assert_eq!(out[1].bytes, max + 5);
    assert_eq!(b.pending_bytes(&1, Tier::Migrated), 10);
    let rest = b.flush_all(at(0));
    assert_eq!(rest[0].messages, vec![tagged(3, 10)]);
}

#[test]
fn due_tier_is_packed_into_bundles_within_max_bytes() {
    let mut b = bundler();
    let max = b.config().policy(Tier::Results).max_bytes;
    for i in 0..10 {
        b.push(1, Tier::Results, tagged(i, max / 4), at(0)).unwrap();
    }
    let out = b.poll(at(1));
    let sizes: Vec<usize> = out.iter().map(|bundle| bundle.messages.len()).collect();
    assert_eq!(sizes, vec![4, 4, 2]);
    let flat: Vec<Bytes> = out.into_iter().flat_map(|bundle| bundle.messages).collect();
    assert_eq!(
        flat,
        (0..10).map(|i| tagged(i, max / 4)).collect::<Vec<_>>()
    );
}

#[test]
fn flush_all_empties_everything() {
    let mut b = bundler();
    for peer in 0..5 {
        for tier in Tier::MOST_URGENT_FIRST {
            b.push(peer, tier, msg(100), at(0)).unwrap();
        }
    }
    let out = b.flush_all(at(0));
    assert_eq!(out.len(), 5 * Tier::COUNT);
    assert!(b.is_empty());
    assert_eq!(b.pending_messages(), 0);
    assert_eq!(b.next_deadline(), None);
    assert!(b.poll(at(1000)).is_empty());
}

#[test]
fn next_deadline_is_the_earliest_age_flush() {
    let mut b = bundler();
    assert_eq!(b.next_deadline(), None);
    b.push(1, Tier::Tasks, msg(10), at(0)).unwrap();
    b.push(2, Tier::Migrated, msg(10), at(10)).unwrap();
    assert_eq!(b.next_deadline(), Some(at(15)));
    assert!(b.poll(at(15) - US).is_empty());
    let out = b.poll(at(15));
    assert_eq!((out.len(), out[0].peer), (1, 2));
    assert_eq!(b.next_deadline(), Some(at(20)));
    b.push(3, Tier::Results, msg(10), at(18)).unwrap();
    assert_eq!(b.next_deadline(), Some(at(19)));
}

#[test]
fn next_deadline_is_now_when_due_by_size() {
    let mut b = bundler();
    b.push(1, Tier::Tasks, msg(MIB), at(7)).unwrap();
    assert_eq!(b.next_deadline(), Some(at(7)));
}

#[test]
fn backpressure_hands_the_message_back() {
    let config = BundlerConfig::default().with_peer_cap(Some(MIB));
    let mut b: Bundler<u32> = Bundler::new(config).unwrap();
    b.push(1, Tier::Migrated, msg(MIB - 10), at(0)).unwrap();
    let err = b.push(1, Tier::Tasks, tagged(9, 11), at(0)).unwrap_err();
    assert_eq!(
        err.kind,
        PushErrorKind::PeerFull {
            pending: MIB - 10,
            cap: MIB
        }
    );
    assert_eq!(err.clone().into_message(), tagged(9, 11));
    assert!(err.to_string().contains("full"));
    // Other peers and the verdicts' tier are unaffected.
    b.push(2, Tier::Tasks, msg(11), at(0)).unwrap();
    b.push(1, Tier::Results, msg(MIB), at(0)).unwrap();
    assert_eq!(b.stats()[Tier::Tasks].rejected, 1);
    // Once the bulk tier is sent there is room again.
    b.poll(at(0));
    b.push(1, Tier::Tasks, err.into_message(), at(0)).unwrap();
    let too_big = b.push(1, Tier::Tasks, msg(MIB + 1), at(0)).unwrap_err();
    assert!(matches!(
        too_big.kind,
        PushErrorKind::MessageTooLarge { len, .. } if len == MIB + 1
    ));
}

#[test]
fn stats_count_bundles_messages_and_bytes() {
    let mut b = bundler();
    b.push(1, Tier::Results, msg(3), at(0)).unwrap();
    b.push(1, Tier::Results, msg(4), at(0)).unwrap();
    b.push(2, Tier::Tasks, msg(5), at(0)).unwrap();
    b.poll(at(1));
    assert_eq!(
        b.stats()[Tier::Results],
        TierStats {
            bundles: 1,
            messages: 2,
            bytes: 7,
            rejected: 0
        }
    );
    assert_eq!(b.stats()[Tier::Tasks], TierStats::default());
    b.flush_all(at(0));
    assert_eq!(b.stats()[Tier::Tasks].bytes, 5);
    assert_eq!(b.stats().total().messages, 3);
    assert_eq!(b.stats().total().bundles, 2);
}

#[test]
fn clock_never_runs_backwards() {
    let mut b = bundler();
    b.poll(at(100));
    // A stale timestamp is read as the latest one, so the message is not "born early".
    b.push(1, Tier::Tasks, msg(1), at(0)).unwrap();
    assert_eq!(b.next_deadline(), Some(at(120)));
    assert!(b.poll(at(119)).is_empty());
    assert_eq!(b.poll(at(120)).len(), 1);
}

#[test]
fn flush_peer_returns_only_that_peers_messages() {
    let mut b = bundler();
    b.push(1, Tier::Tasks, tagged(1, 5), at(0)).unwrap();
    b.push(1, Tier::Results, tagged(2, 5), at(0)).unwrap();
    b.push(2, Tier::Tasks, tagged(3, 5), at(0)).unwrap();
    let out = b.flush_peer(&1);
    let tiers: Vec<Tier> = out.iter().map(|bundle| bundle.tier).collect();
    assert_eq!(tiers, vec![Tier::Results, Tier::Tasks]);
    assert!(out.iter().all(|bundle| bundle.peer == 1));
    assert_eq!(b.pending_messages(), 1);
    assert!(b.flush_peer(&1).is_empty());
    assert_eq!(b.stats().total().messages, 2);
}

mod model {
    //! Property tests against a plain reference model of the pending queues.

    use super::super::*;
    use proptest::prelude::*;
    use std::collections::{BTreeMap, HashSet, VecDeque};

    const CAP: usize = 12_000;

    fn config() -> BundlerConfig {
        let policy = |max_bytes, ms| TierPolicy {
            max_bytes,
            max_age: Duration::from_millis(ms),
        };
        // Verdicts immediate, so that the model covers a tier due at once as well as ones
        // due by age.
        BundlerConfig {
            policies: [
                TierPolicy::immediate(1_000),
                policy(4_000, 3),
                policy(8_000, 7),
            ],
            peer_cap_bytes: Some(CAP),
        }
    }

    #[derive(Debug, Clone)]
    enum Op {
        Push { peer: u8, tier: usize, len: usize },
        Poll,
        FlushAll,
        FlushPeer { peer: u8 },
    }

    fn op() -> impl Strategy<Value = (Op, u64)> {
        let len = prop_oneof![8usize..200, 8usize..3_000, 3_000usize..14_000];
        let op = prop_oneof![
            8 => (0u8..4, 0usize..Tier::COUNT, len)
                .prop_map(|(peer, tier, len)| Op::Push { peer, tier, len }),
            4 => Just(Op::Poll),
            1 => Just(Op::FlushAll),
            1 => (0u8..4).prop_map(|peer| Op::FlushPeer { peer }),
        ];
        (op, 0u64..2_500)
    }

    /// Reference model: per (peer, tier) the accepted messages with arrival times.
    #[derive(Default)]
    struct Model {
        queues: BTreeMap<(u8, Tier), VecDeque<(Bytes, Duration)>>,
        emitted: [TierStats; Tier::COUNT],
        rejected: [u64; Tier::COUNT],
        accepted: HashSet<u64>,
        seen: HashSet<u64>,
    }

    impl Model {
        fn queue_due(&self, key: (u8, Tier), now: Duration) -> bool {
            let policy = config().policy(key.1);
            let Some(queue) = self.queues.get(&key) else {
                return false;
            };
            let bytes: usize = queue.iter().map(|(m, _)| m.len()).sum();
            queue.front().is_some_and(|(_, arrived)| {
                bytes >= policy.max_bytes || now >= *arrived + policy.max_age
            })
        }

        fn capped_bytes(&self, peer: u8) -> usize {
            self.queues
                .iter()
                .filter(|((p, tier), _)| *p == peer && tier.is_capped())
                .flat_map(|(_, queue)| queue.iter().map(|(m, _)| m.len()))
                .sum()
        }

        /// Checks one emitted bundle against the model and consumes its messages.
        fn take(&mut self, bundle: &Bundle<u8>, due_at: Option<Duration>) {
            let key = (bundle.peer, bundle.tier);
            if let Some(now) = due_at {
                assert!(self.queue_due(key, now), "bundle emitted before due");
            }
            let max = config().policy(bundle.tier).max_bytes;
            assert!(!bundle.messages.is_empty());
            assert!(bundle.bytes <= max || bundle.messages.len() == 1);
            let sum: usize = bundle.messages.iter().map(Bytes::len).sum();
            assert_eq!(sum, bundle.bytes);
            let queue = self.queues.get_mut(&key).expect("bundle for empty queue");
            for message in &bundle.messages {
                let (expected, _) = queue.pop_front().expect("more messages than pushed");
                assert_eq!(message, &expected, "order within (peer, tier) broken");
                assert!(self.seen.insert(id(message)), "message emitted twice");
            }
            // Greedy packing: the next message would not have fitted.
            if let Some((next, _)) = queue.front() {
                assert!(bundle.bytes + next.len() > max);
            }
            let stats = &mut self.emitted[bundle.tier.index()];
            stats.record(bundle.messages.len(), bundle.bytes);
        }

        fn check_order(bundles: &[Bundle<u8>]) {
            for pair in bundles.windows(2) {
                let urgency = |b: &Bundle<u8>| (b.tier, b.peer);
                assert!(urgency(&pair[0]) <= urgency(&pair[1]), "tier order broken");
            }
        }
    }

    fn id(message: &Bytes) -> u64 {
        u64::from_le_bytes(message[..8].try_into().unwrap())
    }

    fn message(id: u64, len: usize) -> Bytes {
        let mut bytes = vec![0xAB; len];
        bytes[..8].copy_from_slice(&id.to_le_bytes());
        Bytes::from(bytes)
    }

    fn apply(b: &mut Bundler<u8>, model: &mut Model, op: Op, now: Duration, next_id: u64) {
        match op {
            Op::Push { peer, tier, len } => {
                let tier = Tier::from_index(tier).unwrap();
                let payload = message(next_id, len);
                let over = tier.is_capped() && model.capped_bytes(peer) + len > CAP;
                match b.push(peer, tier, payload.clone(), now) {
                    Ok(()) => {
                        assert!(!over, "push accepted over the cap");
                        model.accepted.insert(next_id);
                        let queue = model.queues.entry((peer, tier)).or_default();
                        queue.push_back((payload, now));
                    }
                    Err(err) => {
                        assert!(over, "push refused under the cap");
                        assert_eq!(err.message, payload, "refused message altered");
                        model.rejected[tier.index()] += 1;
                    }
                }
            }
            Op::Poll => {
                let out = b.poll(now);
                Model::check_order(&out);
                out.iter().for_each(|bundle| model.take(bundle, Some(now)));
                let keys: Vec<_> = model.queues.keys().copied().collect();
                for key in keys {
                    assert!(!model.queue_due(key, now), "due queue left behind");
                }
            }
            Op::FlushAll => {
                let out = b.flush_all(now);
                Model::check_order(&out);
                out.iter().for_each(|bundle| model.take(bundle, None));
                assert!(model.queues.values().all(VecDeque::is_empty));
            }
            Op::FlushPeer { peer } => {
                let out = b.flush_peer(&peer);
                assert!(out.iter().all(|bundle| bundle.peer == peer));
                Model::check_order(&out);
                out.iter().for_each(|bundle| model.take(bundle, None));
            }
        }
    }

    fn check_invariants(b: &Bundler<u8>, model: &Model) {
        for peer in 0..4 {
            assert!(b.capped_pending_bytes(&peer) <= CAP);
            assert_eq!(b.capped_pending_bytes(&peer), model.capped_bytes(peer));
        }
        let pending: usize = model.queues.values().map(VecDeque::len).sum();
        assert_eq!(b.pending_messages(), pending);
        for tier in Tier::MOST_URGENT_FIRST {
            let mut expected = model.emitted[tier.index()];
            expected.rejected = model.rejected[tier.index()];
            assert_eq!(b.stats()[tier], expected, "stats drifted");
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]

        #[test]
        fn every_message_comes_out_once_in_order_and_only_when_due(
            ops in proptest::collection::vec(op(), 1..120)
        ) {
            let mut b = Bundler::new(config()).unwrap();
            let mut model = Model::default();
            let mut now = Duration::ZERO;
            for (next_id, (op, step_us)) in (0u64..).zip(ops) {
                now += Duration::from_micros(step_us);
                apply(&mut b, &mut model, op, now, next_id);
                check_invariants(&b, &model);
            }
            // The deadline is exact: nothing just before it, something at it.
            if let Some(deadline) = b.next_deadline() {
                if deadline > now {
                    prop_assert!(b.poll(deadline - Duration::from_micros(1)).is_empty());
                }
                let out = b.poll(deadline);
                prop_assert!(!out.is_empty());
                // The bundler reads a stale `deadline` as the latest time it has seen.
                let effective = deadline.max(now);
                out.iter().for_each(|bundle| model.take(bundle, Some(effective)));
            }
            let rest = b.flush_all(now);
            rest.iter().for_each(|bundle| model.take(bundle, None));
            check_invariants(&b, &model);
            prop_assert!(b.is_empty());
            prop_assert_eq!(&model.seen, &model.accepted);
        }
    }
}
