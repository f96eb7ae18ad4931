use proptest::prelude::*;

use super::*;

const LIMITS: BatchLimits = BatchLimits {
    domains: 8,
    pixels: 1000,
    max_depth: 4,
    materials: 4,
    max_records: 1 << 16,
};

fn ray(i: u32) -> RayRecord {
    RayRecord {
        origin: [i as f32, 1.0, 2.0],
        t_min: 0.0,
        dir: [0.0, 0.0, 1.0],
        t_max: f32::INFINITY,
        throughput: [0.5; 3],
        pixel: i % 1000,
        sample: i,
        depth: (i % 5) as u16,
        kind: (i % 2) as u8,
        domain: i % 8,
        tile: i / 64,
        epoch: 3,
        credit: 1 << 40,
        ..bytemuck::Zeroable::zeroed()
    }
}

#[test]
fn round_trip() {
    let rays: Vec<RayRecord> = (0..100).map(ray).collect();
    assert_eq!(decode_batch(&encode_batch(&rays), &LIMITS).unwrap(), rays);
    assert_eq!(decode_batch(&encode_batch(&[]), &LIMITS).unwrap(), vec![]);
}

#[test]
fn out_of_range_records_name_their_index() {
    let mut rays: Vec<RayRecord> = (0..10).map(ray).collect();
    rays[7].domain = 8;
    let err = decode_batch(&encode_batch(&rays), &LIMITS).unwrap_err();
    assert_eq!(
        err,
        WireError::Record {
            index: 7,
            reason: "domain out of range"
        }
    );
    rays[7].domain = 0;
    rays[3].dir = [f32::NAN, 0.0, 1.0];
    assert!(matches!(
        decode_batch(&encode_batch(&rays), &LIMITS),
        Err(WireError::Record { index: 3, .. })
    ));
    let mut b = encode_batch(&rays);
    b[4] = 9;
    assert_eq!(decode_batch(&b, &LIMITS), Err(WireError::Version(9)));
}

fn verdict(i: u32) -> VerdictRecord {
    let hit = i % 3 == 2;
    VerdictRecord {
        group: i,
        tile: i / 7,
        epoch: 1,
        pixel: i % 1000,
        sample: i,
        kind: (i % 3) as u8,
        order: if hit { i % 5 } else { 0 },
        t: if hit { i as f32 } else { 0.0 },
        normal: if hit { [0.0, 1.0, 0.0] } else { [0.0; 3] },
        material: if hit { i % 4 } else { 0 },
        ..bytemuck::Zeroable::zeroed()
    }
}

#[test]
fn verdicts_round_trip_and_bad_ones_are_refused() {
    let vs: Vec<VerdictRecord> = (0..30).map(verdict).collect();
    assert_eq!(decode_verdicts(&encode_verdicts(&vs), &LIMITS).unwrap(), vs);
    let refused = |edit: fn(&mut VerdictRecord)| {
        let mut v = vs.clone();
        edit(&mut v[5]);
        decode_verdicts(&encode_verdicts(&v), &LIMITS).unwrap_err()
    };
    let reason = |reason| WireError::Record { index: 5, reason };
    assert_eq!(refused(|v| v.kind = 7), reason("unknown verdict kind"));
    // A hit on a brick's surfaces is checked as any hit.
    assert_eq!(
        refused(|v| {
            v.kind = VerdictRecord::VOLUME_HIT;
            v.t = -1.0;
        }),
        reason("non-finite or negative hit")
    );
    assert_eq!(refused(|v| v.material = 4), reason("material out of range"));
    assert_eq!(
        refused(|v| v.t = f32::NAN),
        reason("non-finite or negative hit")
    );
    assert_eq!(refused(|v| v.pixel = 1000), reason("pixel out of range"));
    assert_eq!(
        refused(|v| v.kind = VerdictRecord::CLEAR),
        reason("a verdict without a hit carries hit fields")
    );
    // A clear verdict names its copy's domain, one of the frame's.
    let clear = |v: &mut VerdictRecord| {
        (v.kind, v.order, v.t, v.normal, v.material) = (VerdictRecord::CLEAR, 3, 0.0, [0.0; 3], 0);
    };
    let mut ok = vs.clone();
    clear(&mut ok[5]);
    assert_eq!(decode_verdicts(&encode_verdicts(&ok), &LIMITS).unwrap(), ok);
    assert_eq!(
        refused(|v| {
            (v.kind, v.order, v.t, v.normal, v.material) =
                (VerdictRecord::CLEAR, 1 << 20, 0.0, [0.0; 3], 0);
        }),
        reason("domain out of range")
    );
    // Volume segments: colour non-negative, opacity a fraction; a closing verdict only
    // counts, and within bounds.
    let segment = |v: &mut VerdictRecord| {
        (v.kind, v.order, v.t, v.normal, v.material) =
            (VerdictRecord::SEGMENT, 7, 0.5, [0.1, 0.2, 0.3], 0);
    };
    let mut ok = vs.clone();
    segment(&mut ok[5]);
    ok[6] = VerdictRecord {
        kind: VerdictRecord::VOLUME_END,
        material: 3,
        ..verdict(6)
    };
    assert_eq!(decode_verdicts(&encode_verdicts(&ok), &LIMITS).unwrap(), ok);
    assert_eq!(
        refused(|v| {
            (v.kind, v.t) = (VerdictRecord::SEGMENT, 1.5);
            v.material = 0;
        }),
        reason("volume segment colour or opacity out of range")
    );
    let negative = |v: &mut VerdictRecord| {
        (v.kind, v.order, v.t, v.normal, v.material) =
            (VerdictRecord::SEGMENT, 1, 0.5, [0.0, -1.0, 0.0], 0);
    };
    assert_eq!(
        refused(negative),
        reason("volume segment colour or opacity out of range")
    );
    // A segment's light: colour non-negative, depth a distance, one of the lit lights.
    let light = |v: &mut VerdictRecord| {
        (v.kind, v.order, v.t, v.normal, v.material) =
            (VerdictRecord::LIGHT, 7, 3.5, [0.1, 0.2, 0.3], 3);
    };
    let mut ok = vs.clone();
    light(&mut ok[5]);
    assert_eq!(decode_verdicts(&encode_verdicts(&ok), &LIMITS).unwrap(), ok);
    assert_eq!(
        refused(|v| {
            (v.kind, v.t, v.normal) = (VerdictRecord::LIGHT, -1.0, [0.0; 3]);
            v.material = 0;
        }),
        reason("volume segment light or depth out of range")
    );
    assert_eq!(
        refused(|v| {
            (v.kind, v.t, v.normal) = (VerdictRecord::LIGHT, 1.0, [0.0; 3]);
            v.material = 4;
        }),
        reason("volume segment light index out of range")
    );
    let too_many = |v: &mut VerdictRecord| {
        (v.kind, v.order, v.t, v.normal) = (VerdictRecord::VOLUME_END, 0, 0.0, [0.0; 3]);
        v.material = crate::render::speculation::MAX_SEGMENTS + 1;
    };
    assert_eq!(
        refused(too_many),
        reason("a closing volume verdict counts too many segments")
    );
    // Neither kind of batch passes for the other.
    let rays = encode_batch(&[ray(1)]);
    assert_eq!(decode_verdicts(&rays, &LIMITS), Err(WireError::Magic));
    assert_eq!(
        decode_batch(&encode_verdicts(&vs), &LIMITS),
        Err(WireError::Magic)
    );
}

#[test]
fn records_decoded_for_any_frame_then_range_checked_pass_as_a_frame_decode_does() {
    let any = BatchLimits::any_frame(1 << 16);
    let edits: [fn(&mut RayRecord); 4] = [
        |r| r.domain = 8,
        |r| r.pixel = 1000,
        |r| r.depth = 5,
        |_| {},
    ];
    for edit in edits {
        let mut rays: Vec<RayRecord> = (0..10).map(ray).collect();
        edit(&mut rays[4]);
        let bytes = encode_batch(&rays);
        let once =
            decode_batch(&bytes, &any).and_then(|r| check_ray_ranges(&r, &LIMITS).map(|()| r));
        assert_eq!(once, decode_batch(&bytes, &LIMITS));
    }
    let edits: [fn(&mut VerdictRecord); 3] = [|v| v.pixel = 1000, |v| v.material = 4, |_| {}];
    for edit in edits {
        let mut vs: Vec<VerdictRecord> = (0..10).map(verdict).collect();
        edit(&mut vs[5]);
        let bytes = encode_verdicts(&vs);
        let once = decode_verdicts(&bytes, &any)
            .and_then(|v| check_verdict_ranges(&v, &LIMITS).map(|()| v));
        assert_eq!(once, decode_verdicts(&bytes, &LIMITS));
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(5000))]

    #[test]
    fn garbage_verdicts_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..1024)) {
        let _ = decode_verdicts(&bytes, &LIMITS);
    }

    #[test]
    fn garbage_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..2048)) {
        let _ = decode_batch(&bytes, &LIMITS);
    }

    #[test]
    fn corrupted_batches_never_panic_and_accepted_ones_are_in_range(
        edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..6),
        cut in any::<usize>(),
    ) {
        let mut b = encode_batch(&(0..20).map(ray).collect::<Vec<_>>());
        for (at, v) in edits {
            let at = at % b.len();
            b[at] = v;
        }
        if cut % 4 == 0 {
            b.truncate(cut % b.len());
        }
        if let Ok(rays) = decode_batch(&b, &LIMITS) {
            for r in rays {
                prop_assert!(r.domain < LIMITS.domains && r.pixel < LIMITS.pixels && r.depth <= LIMITS.max_depth);
            }
        }
    }
}
