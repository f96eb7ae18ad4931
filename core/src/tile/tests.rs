use super::credit::*;
use super::ledger::*;
use super::*;
use proptest::prelude::*;

fn grid() -> TileGrid {
    TileGrid::new(5, 3, 2).unwrap()
}

// ---- credit splitting ----

#[test]
fn split_is_exact_and_never_zero() {
    for (credit, parts) in [(10, 3), (3, 3), (u64::MAX, 7), (TILE_CREDIT, 17), (1, 1)] {
        let shares: Vec<u64> = split_credit(credit, parts).unwrap().collect();
        assert_eq!(shares.len(), parts);
        assert_eq!(
            shares.iter().map(|&s| u128::from(s)).sum::<u128>(),
            credit.into()
        );
        assert!(shares.iter().all(|&s| s >= 1));
    }
    assert_eq!(split_credit(10, 3).unwrap().collect::<Vec<_>>(), [4, 3, 3]);
}

#[test]
fn split_refuses_zero_shares_and_zero_parts() {
    assert_eq!(
        split_credit(2, 3).err(),
        Some(CreditError::Exhausted {
            credit: 2,
            parts: 3
        })
    );
    assert_eq!(split_credit(5, 0).err(), Some(CreditError::NoParts));
    assert_eq!(
        split_credit(0, 1).err(),
        Some(CreditError::Exhausted {
            credit: 0,
            parts: 1
        })
    );
}

#[test]
fn primary_credit_sums_to_tile_credit() {
    let rays = 1000;
    let total: u64 = (0..rays)
        .map(|i| primary_credit(TILE_CREDIT, rays, i).unwrap())
        .sum();
    assert_eq!(total, TILE_CREDIT);
    assert_eq!(
        primary_credit(TILE_CREDIT, rays, rays),
        Err(CreditError::IndexOutOfRange { index: rays, rays })
    );
    assert_eq!(primary_credit(TILE_CREDIT, 0, 0), Err(CreditError::NoParts));
}

#[test]
fn deepest_path_from_poorest_primary_never_runs_out() {
    // The largest tile the ray record can name has 2^32 primary rays.
    let rays = 1u64 << 32;
    let mut credit = primary_credit(TILE_CREDIT, rays, rays - 1).unwrap();
    let mut returned = 0;
    for _ in 0..MAX_DEPTH {
        // MAX_LIGHTS shadow rays plus the vertex's own report.
        let leaves = MAX_LIGHTS as usize + 1;
        let split = split_path_credit(credit, leaves).unwrap();
        returned += split.leaf * leaves as u64;
        credit = split.continuation;
    }
    assert!(credit >= 1 << 29);
    assert_eq!(returned + credit, TILE_CREDIT / rays);
}

#[test]
fn path_split_is_exact_and_refuses_exhaustion() {
    let s = split_path_credit(20, 4).unwrap();
    assert_eq!(s.continuation + 4 * s.leaf, 20);
    assert_eq!(
        split_path_credit(4, 4),
        Err(CreditError::Exhausted {
            credit: 4,
            parts: 5
        })
    );
    assert_eq!(split_path_credit(5, 4).unwrap().continuation, 1);
}

// ---- tile grid ----

#[test]
fn grid_partitions_the_image() {
    let g = grid();
    assert_eq!(g.count(), 6);
    let mut seen = vec![0; g.pixel_count()];
    for tile in 0..g.count() {
        assert_eq!(g.pixels(tile).count(), g.tile_pixel_count(tile));
        for (i, p) in g.pixels(tile).enumerate() {
            seen[p as usize] += 1;
            assert_eq!(g.tile_of(p), Some(tile));
            assert_eq!(g.local_index(tile, p), Some(i));
        }
    }
    assert!(seen.iter().all(|&n| n == 1));
    assert_eq!(g.pixels(2).collect::<Vec<_>>(), [4, 9]);
    assert_eq!(g.tile_of(15), None);
    assert_eq!(g.local_index(0, 4), None);
    assert_eq!(g.pixels(6).count(), 0);
}

#[test]
fn grid_rejects_degenerate_sizes() {
    assert!(TileGrid::new(0, 3, 2).is_none());
    assert!(TileGrid::new(3, 3, 0).is_none());
    assert!(TileGrid::new(1 << 16, 1 << 16, 8).is_none());
}

// ---- ledger ----

#[test]
fn tile_completes_when_all_credit_is_back() {
    let mut l = TileLedger::new(grid(), 10);
    assert_eq!(l.accept(0, 0, 4, &[(0, [1, 2, 3])]), Ok(Accept::Pending));
    assert!(!l.is_tile_done(0));
    assert_eq!(l.accept(0, 0, 6, &[(0, [1, 0, 0])]), Ok(Accept::Completed));
    assert!(l.is_tile_done(0));
    assert_eq!(l.tiles_done(), 1);
    assert_eq!(l.image_sums()[0], [2, 2, 3]);
}

#[test]
fn frame_completes_when_every_tile_does() {
    let mut l = TileLedger::new(grid(), 1);
    for tile in 0..6 {
        assert!(!l.is_complete());
        assert_eq!(l.accept(tile, 0, 1, &[]), Ok(Accept::Completed));
    }
    assert!(l.is_complete());
    assert_eq!(l.unfinished().count(), 0);
}

#[test]
fn stale_results_are_ignored() {
    let mut l = TileLedger::new(grid(), 10);
    l.accept(1, 0, 3, &[(2, [5, 5, 5])]).unwrap();
    assert_eq!(l.bump(&[1]), [(1, 1)]);
    let before = l.clone();
    assert_eq!(l.accept(1, 0, 7, &[(2, [1, 1, 1])]), Ok(Accept::Stale));
    // Even a malformed stale result is simply dropped.
    assert_eq!(
        l.accept(1, 0, u64::MAX, &[(0, [1, 1, 1])]),
        Ok(Accept::Stale)
    );
    assert_eq!(l, before);
}

#[test]
fn malformed_results_leave_the_ledger_unchanged() {
    let mut l = TileLedger::new(grid(), 10);
    l.accept(0, 0, 9, &[(0, [1, 1, 1])]).unwrap();
    let before = l.clone();
    let cases = [
        (0, 0, 2, vec![(0, [7, 7, 7])]),
        (0, 0, u64::MAX, vec![]),
        (0, 1, 1, vec![]),
        (0, 0, 0, vec![(0, [7, 7, 7])]),
        (0, 0, 1, vec![(1, [7, 7, 7]), (2, [7, 7, 7])]),
        (6, 0, 1, vec![]),
    ];
    for (tile, epoch, credit, sums) in cases {
        let err = l.accept(tile, epoch, credit, &sums).unwrap_err();
        assert!(!err.to_string().is_empty());
        assert_eq!(l, before, "{err}");
    }
    assert!(matches!(
        l.accept(0, 0, 2, &[]),
        Err(Reject::Overflow { returned: 9, .. })
    ));
}

#[test]
fn committed_tile_refuses_more_credit() {
    let mut l = TileLedger::new(grid(), 1);
    l.accept(0, 0, 1, &[]).unwrap();
    assert!(matches!(
        l.accept(0, 0, 1, &[]),
        Err(Reject::Overflow { .. })
    ));
}

#[test]
fn bump_resets_unfinished_and_spares_finished() {
    let mut l = TileLedger::new(grid(), 10);
    l.accept(0, 0, 10, &[(0, [1, 1, 1])]).unwrap();
    l.accept(1, 0, 4, &[(2, [2, 2, 2])]).unwrap();
    assert_eq!(l.bump(&[1, 0, 1, 99]), [(1, 1)]);
    assert_eq!((l.epoch(0), l.epoch(1)), (Some(0), Some(1)));
    assert_eq!(l.returned(1), Some(0));
    assert!(l.is_tile_done(0));
    // The dropped partial sum must not reappear once the tile completes.
    l.accept(1, 1, 10, &[(3, [3, 3, 3])]).unwrap();
    let image = l.image_sums();
    assert_eq!((image[0], image[2], image[3]), ([1; 3], [0; 3], [3; 3]));
}

#[test]
fn taken_sums_leave_the_ledger_once() {
    let mut l = TileLedger::new(grid(), 2);
    l.accept(0, 0, 1, &[(0, [1, 2, 3])]).unwrap();
    assert!(l.take_sums(0).is_empty(), "not committed yet");
    l.accept(0, 0, 1, &[(1, [4, 5, 6])]).unwrap();
    assert_eq!(l.take_sums(0), vec![[1, 2, 3], [4, 5, 6], [0; 3], [0; 3]]);
    assert!(l.take_sums(0).is_empty());
    assert!(l.take_sums(99).is_empty());
    assert!(l.is_tile_done(0));
}

#[test]
fn image_sums_hold_only_committed_tiles() {
    let mut l = TileLedger::new(grid(), 10);
    l.accept(0, 0, 5, &[(0, [1, 1, 1])]).unwrap();
    assert!(l.image_sums().iter().all(|s| *s == [0; 3]));
}

// ---- simulated frames ----

/// Small deterministic generator (splitmix64) so ray trees depend only on their seed.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }

    fn shuffle<T>(&mut self, items: &mut [T]) {
        for i in (1..items.len()).rev() {
            items.swap(i, self.below(i as u64 + 1) as usize);
        }
    }
}

#[test]
fn credit_beyond_what_the_named_pixels_hold_is_refused() {
    // 2x1 pixels in one tile, 2 samples: 4 primary rays of 10 credit each (41 in all,
    // the first ray takes the remainder 1).
    let g = TileGrid::new(2, 1, 2).unwrap();
    let mut l = TileLedger::new(g, 41).with_samples(2);
    let forged = l.accept(0, 0, 41, &[]);
    assert_eq!(
        forged,
        Err(Reject::Uncovered {
            tile: 0,
            credit: 41,
            pixels: 0,
            bound: 0
        })
    );
    // Pixel 1 holds 2 x 10; pixel 0 holds 21 with the remainder.
    assert!(matches!(
        l.accept(0, 0, 21, &[(1, [0; 3])]),
        Err(Reject::Uncovered { bound: 20, .. })
    ));
    assert_eq!(l.accept(0, 0, 20, &[(1, [0; 3])]), Ok(Accept::Pending));
    assert_eq!(l.accept(0, 0, 21, &[(0, [5; 3])]), Ok(Accept::Completed));
}

/// A retired ray's message to the coordinator.
#[derive(Clone, Debug)]
struct Msg {
    tile: u32,
    epoch: u32,
    credit: u64,
    sums: Vec<(u32, [i64; 3])>,
}

const MAX_TREE_DEPTH: u32 = 3;

/// Traces one ray: it reports, splits among up to 5 children, or both.
fn trace(ray: &Msg, pixel: u32, depth: u32, rng: &mut Rng, out: &mut Vec<Msg>) {
    let children = if depth >= MAX_TREE_DEPTH || rng.below(2) == 0 {
        0
    } else {
        1 + rng.below(5) as usize
    };
    let light = [0, 1, 2].map(|_| rng.below(1000) as i64 - 500);
    let reports = children == 0 || rng.below(2) == 0;
    let mut shares = split_credit(ray.credit, children + usize::from(reports)).unwrap();
    if reports {
        // A ray that adds no light still names its pixel (as workers do), so the
        // ledger's pixel bound holds.
        let sums = if rng.below(4) == 0 {
            vec![(pixel, [0; 3])]
        } else {
            vec![(pixel, light)]
        };
        let credit = shares.next().unwrap();
        out.push(Msg {
            credit,
            sums,
            ..ray.clone()
        });
    }
    for credit in shares {
        trace(
            &Msg {
                credit,
                ..ray.clone()
            },
            pixel,
            depth + 1,
            rng,
            out,
        );
    }
}

/// All result messages of one tile at `epoch`. The trees depend on `seed`, tile and ray
/// only, never the epoch: rendering is deterministic.
fn trace_tile(g: &TileGrid, tile: u32, epoch: u32, spp: u32, seed: u64) -> Vec<Msg> {
    let rays = g.tile_pixel_count(tile) as u64 * u64::from(spp);
    let mut out = Vec::new();
    for (i, pixel) in g.pixels(tile).enumerate() {
        for s in 0..u64::from(spp) {
            let index = i as u64 * u64::from(spp) + s;
            let credit = primary_credit(TILE_CREDIT, rays, index).unwrap();
            let mut rng = Rng(seed ^ (u64::from(tile) << 40) ^ index);
            let ray = Msg {
                tile,
                epoch,
                credit,
                sums: vec![],
            };
            trace(&ray, pixel, 0, &mut rng, &mut out);
        }
    }
    out
}

/// Delivers `msgs` in order, checking each verdict: stale exactly when its epoch is old,
/// and a tile completes on its last current-epoch message and not a moment before.
fn deliver(l: &mut TileLedger, msgs: &[Msg], pending: &mut [usize]) {
    for m in msgs {
        let current = l.epoch(m.tile).unwrap();
        let expected = if m.epoch < current {
            Accept::Stale
        } else {
            assert!(!l.is_tile_done(m.tile), "tile {} committed early", m.tile);
            pending[m.tile as usize] -= 1;
            match pending[m.tile as usize] {
                0 => Accept::Completed,
                _ => Accept::Pending,
            }
        };
        assert_eq!(l.accept(m.tile, m.epoch, m.credit, &m.sums), Ok(expected));
    }
}

/// Number of messages per tile that belong to the tile's current epoch.
fn current_counts(l: &TileLedger, msgs: &[Msg]) -> Vec<usize> {
    let mut counts = vec![0; l.grid().count() as usize];
    for m in msgs.iter().filter(|m| Some(m.epoch) == l.epoch(m.tile)) {
        counts[m.tile as usize] += 1;
    }
    counts
}

fn trace_frame(g: &TileGrid, spp: u32, seed: u64) -> Vec<Msg> {
    (0..g.count())
        .flat_map(|t| trace_tile(g, t, 0, spp, seed))
        .collect()
}

fn clean_run(g: TileGrid, spp: u32, seed: u64, order: &mut Rng) -> Vec<[i64; 3]> {
    let mut msgs = trace_frame(&g, spp, seed);
    order.shuffle(&mut msgs);
    let mut l = TileLedger::new(g, TILE_CREDIT).with_samples(spp);
    let mut pending = current_counts(&l, &msgs);
    deliver(&mut l, &msgs, &mut pending);
    assert!(l.is_complete());
    l.image_sums()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn frame_with_fault_commits_exactly_and_matches_clean_run(
        width in 1u32..9, height in 1u32..9, tile_size in 1u32..5, spp in 1u32..3,
        seed: u64, order_seed: u64, cut_permille in 0u64..1000, bump_mask: u64,
    ) {
        let g = TileGrid::new(width, height, tile_size).unwrap();
        let mut order = Rng(order_seed);
        let clean = clean_run(g, spp, seed, &mut order);

        // Epoch 0 is cut short by a fault after a random prefix.
        let mut first = trace_frame(&g, spp, seed);
        order.shuffle(&mut first);
        let mut l = TileLedger::new(g, TILE_CREDIT).with_samples(spp);
        let mut pending = current_counts(&l, &first);
        let cut = first.len() * cut_permille as usize / 1000;
        deliver(&mut l, &first[..cut], &mut pending);

        // Bump a random set of tiles, finished ones included: those must be untouched.
        let chosen: Vec<u32> = (0..g.count()).filter(|t| bump_mask >> (t % 64) & 1 == 1).collect();
        let done_before: Vec<bool> = (0..g.count()).map(|t| l.is_tile_done(t)).collect();
        let bumped = l.bump(&chosen);
        let expect_bumped: Vec<(u32, u32)> =
            chosen.iter().filter(|&&t| !done_before[t as usize]).map(|&t| (t, 1)).collect();
        prop_assert_eq!(&bumped, &expect_bumped);

        // The rest of epoch 0, the re-run of bumped tiles, and duplicated stale results.
        let mut rest = first[cut..].to_vec();
        for &(tile, epoch) in &bumped {
            rest.extend(trace_tile(&g, tile, epoch, spp, seed));
            let stale = first[..cut].iter().filter(|m| m.tile == tile);
            rest.extend(stale.filter(|_| order.below(2) == 0).cloned());
        }
        order.shuffle(&mut rest);
        let mut pending = current_counts(&l, &rest);
        deliver(&mut l, &rest, &mut pending);

        prop_assert!(l.is_complete());
        prop_assert_eq!(l.image_sums(), clean);
    }

    #[test]
    fn split_credit_is_exact_and_positive(credit: u64, parts in 1usize..64) {
        match split_credit(credit, parts) {
            Ok(shares) => {
                let shares: Vec<u64> = shares.collect();
                prop_assert!(shares.iter().all(|&s| s >= 1));
                prop_assert_eq!(shares.iter().map(|&s| u128::from(s)).sum::<u128>(), u128::from(credit));
            }
            Err(e) => prop_assert!(credit < parts as u64, "{}", e),
        }
    }

    #[test]
    fn overflow_attempt_leaves_state_unchanged(
        first in 1u64..1000, extra in 1u64..1000, pixel in 0u32..15,
    ) {
        let g = grid();
        let tile = g.tile_of(pixel).unwrap();
        let mut l = TileLedger::new(g, 1000);
        let first = first.min(999);
        l.accept(tile, 0, first, &[(pixel, [1, 2, 3])]).unwrap();
        let before = l.clone();
        let too_much = 1000 - first + extra;
        let verdict = l.accept(tile, 0, too_much, &[(pixel, [9, 9, 9])]);
        let is_overflow = matches!(verdict, Err(Reject::Overflow { .. }));
        prop_assert!(is_overflow);
        prop_assert_eq!(l, before);
    }
}
