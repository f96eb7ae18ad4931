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
    // A clear verdict has no hit fields on the wire: they come back zero.
    let mut cleared = vs.clone();
    cleared[5].kind = VerdictRecord::CLEAR;
    let back = decode_verdicts(&encode_verdicts(&cleared), &LIMITS).unwrap();
    assert_eq!(
        (back[5].t, back[5].normal, back[5].material),
        (0.0, [0.0; 3], 0)
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
    // So does an occluder's or a hit's.
    assert_eq!(
        refused(|v| {
            (v.kind, v.order, v.t, v.normal, v.material) =
                (VerdictRecord::BLOCKED, 8, 0.0, [0.0; 3], 0);
        }),
        reason("domain out of range")
    );
    for kind in [VerdictRecord::HIT, VerdictRecord::VOLUME_HIT] {
        let mut far = vs.clone();
        (far[5].kind, far[5].order, far[5].t) = (kind, 8, 1.0);
        assert_eq!(
            decode_verdicts(&encode_verdicts(&far), &LIMITS).unwrap_err(),
            reason("domain out of range")
        );
    }
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
        v.material = super::MAX_SEGMENTS + 1;
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

/// A copy: no light, credit or volume colour (`render::speculation` makes them so).
fn copy(i: u32) -> RayRecord {
    RayRecord {
        throughput: [0.0; 3],
        credit: 0,
        group: i * 3,
        resolver: i % 4,
        ..ray(i)
    }
}

#[test]
fn copies_travel_short_and_mixed_batches_full() {
    let copies: Vec<RayRecord> = (0..50).map(copy).collect();
    let short = encode_batch(&copies);
    assert_eq!(short[..4], COPY_MAGIC);
    assert_eq!(short.len(), HEADER_BYTES + 50 * 64);
    assert_eq!(ray_count(&short), 50);
    assert_eq!(decode_batch(&short, &LIMITS).unwrap(), copies);
    assert_eq!(check_batch(&short, &LIMITS), Ok(50));
    // One record with light makes the whole batch full, and it round-trips as it was.
    let mut mixed = copies.clone();
    mixed[9] = ray(9);
    let full = encode_batch(&mixed);
    assert_eq!(full[..4], MAGIC);
    assert_eq!(full.len(), HEADER_BYTES + 50 * 104);
    assert_eq!(decode_batch(&full, &LIMITS).unwrap(), mixed);
    // A negative zero is not zero: the short layout would lose its sign.
    let mut signed = copies.clone();
    signed[3].volume_alpha = -0.0;
    assert_eq!(encode_batch(&signed)[..4], MAGIC);
    // Bare records sent in the full layout are refused: one encoding per batch.
    let mut forced = encode_batch(&mixed);
    let at = HEADER_BYTES + 9 * 104;
    forced[at..at + 104].copy_from_slice(bytemuck::bytes_of(&copy(9)));
    assert_eq!(decode_batch(&forced, &LIMITS), Err(WireError::Layout));
    // A short record is checked like a full one.
    let mut bad = copies.clone();
    bad[7].domain = 8;
    assert_eq!(
        decode_batch(&encode_batch(&bad), &LIMITS),
        Err(WireError::Record {
            index: 7,
            reason: "domain out of range"
        })
    );
}

#[test]
fn verdicts_take_a_kind_byte_varints_and_hit_fields_only_with_a_hit() {
    let clear = VerdictRecord {
        kind: VerdictRecord::CLEAR,
        group: 70_000,
        tile: 12,
        epoch: 0,
        pixel: 65_000,
        sample: 3,
        order: 40,
        ..bytemuck::Zeroable::zeroed()
    };
    let hit = VerdictRecord {
        kind: VerdictRecord::HIT,
        t: 2.5,
        normal: [0.0, 1.0, 0.0],
        material: 3,
        order: 2,
        ..clear
    };
    let limits = BatchLimits {
        domains: 48,
        pixels: 65_536,
        ..LIMITS
    };
    // Kind, group (3 bytes), tile, epoch, pixel (3), sample, order: 11 bytes.
    assert_eq!(encode_verdicts(&[clear]).len(), HEADER_BYTES + 11);
    // A hit adds its distance and normal (16 bytes) and its material.
    assert_eq!(encode_verdicts(&[hit]).len(), HEADER_BYTES + 11 + 17);
    let both = encode_verdicts(&[clear, hit, clear]);
    assert_eq!(
        decode_verdicts(&both, &limits).unwrap(),
        vec![clear, hit, clear]
    );
    assert_eq!(check_verdicts(&both, &limits), Ok(3));
    // Bytes past the stated count, a count past the bytes, and truncation are refused.
    let mut longer = both.clone();
    longer.push(0);
    assert_eq!(
        decode_verdicts(&longer, &limits),
        Err(WireError::Length(longer.len()))
    );
    let mut lying = both.clone();
    lying[8..12].copy_from_slice(&4u32.to_le_bytes());
    assert_eq!(
        decode_verdicts(&lying, &limits),
        Err(WireError::Length(lying.len()))
    );
    let cut = &both[..both.len() - 1];
    assert_eq!(
        decode_verdicts(cut, &limits),
        Err(WireError::Length(cut.len()))
    );
    let mut huge = both.clone();
    huge[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(matches!(
        decode_verdicts(&huge, &limits),
        Err(WireError::TooMany { .. })
    ));
    // A varint in a longer form than it needs would make two encodings of one batch.
    let mut long_form = encode_verdicts(&[VerdictRecord { tile: 0, ..clear }]);
    let tile_at = HEADER_BYTES + 1 + 3;
    assert_eq!(long_form[tile_at], 0);
    long_form[tile_at] = 0x80;
    long_form.insert(tile_at + 1, 0);
    assert_eq!(
        decode_verdicts(&long_form, &limits),
        Err(WireError::Record {
            index: 0,
            reason: "varint not in its shortest form or above 32 bits"
        })
    );
    // An unknown kind cannot be read past: the batch stops there.
    let mut unknown = encode_verdicts(&[clear]);
    unknown[HEADER_BYTES] = 9;
    assert_eq!(
        decode_verdicts(&unknown, &limits),
        Err(WireError::Record {
            index: 0,
            reason: "unknown verdict kind"
        })
    );
}
