//! Fuzzing the ray-batch decoder, which reads bytes from other processes: garbage, and valid
//! batches broken by bit flips, truncation, splices and lying counts (so inputs get past the
//! magic and reach the deeper checks). Properties: no panic, memory bounded by the input
//! whatever the header claims, every accepted batch is in range and re-encodes to the same
//! bytes, every valid batch round-trips, and every error has a message.
//!
//! `PROPTEST_CASES=N cargo test --release -p rayfarm-common --test wire_fuzz -- --nocapture`
//! tries N inputs per property and prints the counts.

mod fuzz_support;

use fuzz_support::ByteEdit;
use proptest::prelude::*;
use rayfarm_core::ray::RayRecord;
use rayfarm_core::wire::{
    BatchLimits, HEADER_BYTES, WireError, check_batch, decode_batch, encode_batch,
};

const LIMITS: BatchLimits = BatchLimits {
    domains: 8,
    pixels: 10_000,
    max_depth: 6,
    materials: 4,
    max_records: 4096,
};
const RECORD: usize = std::mem::size_of::<RayRecord>();
const DEFAULT_CASES: u32 = 4000;

/// A record that passes every check of `LIMITS`, built from arbitrary values in range.
fn valid_ray() -> impl Strategy<Value = RayRecord> {
    let coord = prop_oneof![-1e6f32..1e6, Just(0.0), Just(-0.0)];
    (
        [coord.clone(), coord.clone(), coord.clone()],
        [coord.clone(), coord.clone(), coord],
        0f32..10.0,
        prop_oneof![Just(f32::INFINITY), 0f32..1e9],
        (
            0u32..LIMITS.pixels,
            any::<u32>(),
            0..=LIMITS.max_depth,
            0u8..2,
        ),
        (0..LIMITS.domains, any::<u32>(), any::<u32>(), any::<u64>()),
        [0f32..4.0, 0f32..4.0, 0f32..4.0],
    )
        .prop_map(
            |(
                origin,
                dir,
                t_min,
                extra,
                (pixel, sample, depth, kind),
                (domain, tile, epoch, credit),
                throughput,
            )| {
                let dir = if dir == [0.0; 3] {
                    [0.0, 0.0, 1.0]
                } else {
                    dir
                };
                RayRecord {
                    origin,
                    t_min,
                    dir,
                    t_max: t_min + extra,
                    throughput,
                    pixel,
                    sample,
                    depth,
                    kind,
                    domain,
                    tile,
                    epoch,
                    credit,
                    ..bytemuck::Zeroable::zeroed()
                }
            },
        )
}

fn valid_batch() -> impl Strategy<Value = Vec<RayRecord>> {
    prop::collection::vec(valid_ray(), 0..24)
}

/// One way of breaking an encoded batch.
#[derive(Clone, Debug)]
enum Mutation {
    Edit(ByteEdit),
    /// Replaces the header's count.
    Count(u32),
    /// Overwrites a whole record field-sized span with an awkward value.
    Poison(usize, [u8; 4]),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    let awkward = prop::sample::select(vec![
        f32::NAN.to_le_bytes(),
        f32::INFINITY.to_le_bytes(),
        (-1f32).to_le_bytes(),
        u32::MAX.to_le_bytes(),
        8u32.to_le_bytes(),
        10_000u32.to_le_bytes(),
        [0xff, 0xff, 2, 0],
        [0; 4],
    ]);
    prop_oneof![
        // Five kinds of byte edit, each as likely as the two below.
        5 => fuzz_support::byte_edit(any::<u8>(), 2 * RECORD).prop_map(Mutation::Edit),
        1 => prop_oneof![
            Just(u32::MAX),
            Just(1 << 31),
            Just(LIMITS.max_records as u32 + 1),
            any::<u32>()
        ]
        .prop_map(Mutation::Count),
        1 => (any::<usize>(), awkward).prop_map(|(at, v)| Mutation::Poison(at, v)),
    ]
}

fn apply(bytes: &mut Vec<u8>, m: &Mutation) {
    match m {
        Mutation::Edit(e) => e.apply(bytes),
        Mutation::Count(c) if bytes.len() >= 12 => bytes[8..12].copy_from_slice(&c.to_le_bytes()),
        // Aligned to a 4-byte field of a record, so the value lands on a whole field.
        Mutation::Poison(i, v) if bytes.len() > HEADER_BYTES => {
            let fields = (bytes.len() - HEADER_BYTES) / 4;
            if fields > 0 {
                let f = HEADER_BYTES + 4 * (i % fields);
                bytes[f..f + 4].copy_from_slice(v);
            }
        }
        _ => {}
    }
}

/// The properties every input must satisfy, valid or not.
fn check_any(bytes: &[u8]) -> Result<(), TestCaseError> {
    let (decoded, peak) = fuzz_support::peak_bytes(|| decode_batch(bytes, &LIMITS));
    // The only allocation is the decoded copy of records that are really there (a 64-byte
    // record of the short layout decodes to a full 104-byte one).
    prop_assert!(
        peak <= bytes.len() * RECORD / 64 + 256,
        "{peak} bytes for a {}-byte input",
        bytes.len()
    );
    let checked = check_batch(bytes, &LIMITS);
    match decoded {
        Ok(rays) => {
            prop_assert_eq!(checked, Ok(rays.len()));
            for r in &rays {
                prop_assert!(r.domain < LIMITS.domains && r.pixel < LIMITS.pixels);
                prop_assert!(r.depth <= LIMITS.max_depth && r.kind < 2);
                prop_assert!(r.dir != [0.0; 3] && r.t_min >= 0.0 && r.t_max >= r.t_min);
            }
            // Accepted means canonical: nothing in the bytes is ignored.
            prop_assert_eq!(encode_batch(&rays), bytes);
        }
        Err(e) => {
            prop_assert_eq!(checked, Err(e.clone()));
            prop_assert!(!e.to_string().is_empty());
        }
    }
    Ok(())
}

#[test]
fn garbage() {
    fuzz_support::check(
        file!(),
        "wire garbage",
        DEFAULT_CASES,
        prop::collection::vec(any::<u8>(), 0..4096),
        |bytes| check_any(&bytes),
    );
}

#[test]
fn garbage_behind_a_valid_header() {
    let header = (
        any::<u32>(),
        prop::collection::vec(any::<u8>(), 0..40 * RECORD),
    );
    fuzz_support::check(
        file!(),
        "wire garbage records",
        DEFAULT_CASES,
        header,
        |(count, body)| {
            let mut bytes = encode_batch(&[]);
            bytes[8..12].copy_from_slice(&count.to_le_bytes());
            bytes.extend_from_slice(&body);
            check_any(&bytes)
        },
    );
}

#[test]
fn mutated_batches() {
    let input = (valid_batch(), prop::collection::vec(mutation(), 1..5));
    fuzz_support::check(
        file!(),
        "wire mutated batches",
        DEFAULT_CASES,
        input,
        |(rays, edits)| {
            let mut bytes = encode_batch(&rays);
            for m in &edits {
                apply(&mut bytes, m);
            }
            check_any(&bytes)
        },
    );
}

#[test]
fn spliced_batches() {
    let input = (valid_batch(), valid_batch(), any::<usize>(), any::<usize>());
    fuzz_support::check(
        file!(),
        "wire spliced batches",
        DEFAULT_CASES,
        input,
        |(a, b, i, j)| {
            let (a, b) = (encode_batch(&a), encode_batch(&b));
            let mut bytes = a[..i % (a.len() + 1)].to_vec();
            bytes.extend_from_slice(&b[j % (b.len() + 1)..]);
            check_any(&bytes)
        },
    );
}

#[test]
fn valid_batches_round_trip() {
    fuzz_support::check(
        file!(),
        "wire round trip",
        DEFAULT_CASES,
        valid_batch(),
        |rays| {
            let bytes = encode_batch(&rays);
            prop_assert_eq!(decode_batch(&bytes, &LIMITS), Ok(rays.clone()));
            prop_assert_eq!(check_batch(&bytes, &LIMITS), Ok(rays.len()));
            check_any(&bytes)
        },
    );
}

/// A header that claims far more records than it holds is refused before anything is
/// allocated for them, and so is a batch over the record limit.
#[test]
fn lying_and_oversized_counts_are_refused_cheaply() {
    let mut bytes = encode_batch(&[]);
    bytes[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
    let (result, peak) = fuzz_support::peak_bytes(|| decode_batch(&bytes, &LIMITS));
    assert_eq!(
        result,
        Err(WireError::Count {
            said: u32::MAX,
            held: 0
        })
    );
    assert_eq!(peak, 0);
    let small = BatchLimits {
        max_records: 3,
        ..LIMITS
    };
    let rays: Vec<RayRecord> = (0..4)
        .map(|_| RayRecord {
            dir: [0.0, 0.0, 1.0],
            t_max: 1.0,
            ..bytemuck::Zeroable::zeroed()
        })
        .collect();
    let bytes = encode_batch(&rays);
    let (result, peak) = fuzz_support::peak_bytes(|| decode_batch(&bytes, &small));
    assert_eq!(result, Err(WireError::TooMany { held: 4, limit: 3 }));
    // Nothing was allocated for the records refused.
    assert_eq!(peak, 0);
}

/// Garbage is named as such rather than as a truncated batch: the identity is checked first.
#[test]
fn errors_name_the_first_thing_wrong() {
    assert_eq!(
        decode_batch(b"GET / HTTP/1.1\r\n", &LIMITS),
        Err(WireError::Magic)
    );
    assert_eq!(decode_batch(b"RF", &LIMITS), Err(WireError::Length(2)));
    let mut b = encode_batch(&[]);
    b[4] = 2;
    b.truncate(7);
    assert_eq!(decode_batch(&b, &LIMITS), Err(WireError::Version(2)));
    let b = encode_batch(&[RayRecord {
        dir: [1.0, 0.0, 0.0],
        ..bytemuck::Zeroable::zeroed()
    }]);
    assert_eq!(
        decode_batch(&b[..b.len() - 1], &LIMITS),
        Err(WireError::Length(b.len() - 1))
    );
}
