use super::*;
use bytemuck::Zeroable;

fn hit(t: f32) -> Verdict {
    Verdict::Hit(SurfaceHit {
        t,
        normal: [0.0, 1.0, 0.0],
        material: 0,
    })
}

fn ray(credit: u64) -> RayRecord {
    RayRecord {
        credit,
        pixel: 5,
        ..RayRecord::zeroed()
    }
}

fn copies(groups: &mut Groups, r: RayRecord, domains: &[u32]) -> Vec<RayRecord> {
    let mut out = Vec::new();
    groups.spread(r, domains.to_vec(), 3, &mut out);
    out
}

fn spread(groups: &mut Groups, r: RayRecord, domains: &[u32]) -> RayRecord {
    copies(groups, r, domains)[0]
}

fn settle(groups: &mut Groups, copy: &RayRecord, v: Verdict) -> Option<(RayRecord, Outcome)> {
    groups
        .settle(&VerdictRecord::new(copy, v), &mut Vec::new())
        .unwrap()
}

#[test]
fn copies_go_to_every_domain_without_credit() {
    let mut groups = Groups::default();
    let copies = copies(&mut groups, ray(7), &[4, 9, 2]);
    assert_eq!(
        copies.iter().map(|c| c.domain).collect::<Vec<_>>(),
        [4, 9, 2]
    );
    assert!(
        copies
            .iter()
            .all(|c| c.credit == 0 && c.group == copies[0].group)
    );
    assert!(copies.iter().all(|c| c.resolver == 3));
    assert_eq!(groups.waiting(), 1);
    assert_eq!(groups.oldest_waiting(), Some(0));
    let shadow = RayRecord {
        depth: 2,
        kind: crate::ray::RayKind::Shadow as u8,
        ..ray(1)
    };
    let copy = spread(&mut groups, shadow, &[1]);
    assert_eq!(groups.oldest_waiting(), Some(0));
    groups.retain(|r| r.depth > 0);
    assert_eq!(groups.oldest_waiting(), Some(3));
    groups
        .settle(&VerdictRecord::new(&copy, Verdict::Clear), &mut Vec::new())
        .unwrap();
    assert_eq!(groups.oldest_waiting(), None);
}

#[test]
fn the_nearest_domain_with_a_hit_wins_whatever_the_order_verdicts_arrive_in() {
    let mut groups = Groups::default();
    let c = copies(&mut groups, ray(7), &[1, 2, 3]);
    assert_eq!(settle(&mut groups, &c[2], hit(0.5)), None);
    assert_eq!(settle(&mut groups, &c[0], Verdict::Clear), None);
    let (r, outcome) = settle(&mut groups, &c[1], hit(9.0)).unwrap();
    assert_eq!(r.credit, 7, "the concluded ray keeps its credit");
    assert_eq!(
        outcome.nearest.map(|h| h.t),
        Some(9.0),
        "the second domain's hit"
    );
    assert!(!outcome.blocked);
    assert_eq!(groups.waiting(), 0);
}

#[test]
fn windows_go_out_one_after_another_until_one_ends_the_ray() {
    // One domain at a time: a hit in the second domain ends the ray there, the third is
    // never copied.
    let mut groups = Groups::new(Depth::Ahead(1));
    let first = copies(&mut groups, ray(7), &[5, 6, 7]);
    assert_eq!(first.iter().map(|c| c.domain).collect::<Vec<_>>(), [5]);
    let mut more = Vec::new();
    let settled = groups.settle(&VerdictRecord::new(&first[0], Verdict::Clear), &mut more);
    assert_eq!(settled, Ok(None));
    assert_eq!(more.iter().map(|c| c.domain).collect::<Vec<_>>(), [6]);
    assert!(
        more.iter()
            .all(|c| c.group == first[0].group && c.credit == 0)
    );
    let (r, outcome) = settle(&mut groups, &more[0], hit(2.0)).unwrap();
    assert_eq!((r.credit, outcome.nearest.map(|h| h.t)), (7, Some(2.0)));
    assert_eq!((groups.copies, groups.extensions), (2, 1));

    // Two at a time: a shadow ray blocked in the first window ends there, before its other
    // copy answers; one that goes through every window concludes clear after the last.
    let mut groups = Groups::new(Depth::Ahead(2));
    let shadow = RayRecord {
        kind: crate::ray::RayKind::Shadow as u8,
        ..ray(1)
    };
    let w = copies(&mut groups, shadow, &[1, 2, 3]);
    assert_eq!(w.len(), 2);
    let (_, outcome) = settle(&mut groups, &w[1], Verdict::Blocked).unwrap();
    assert_eq!((outcome.blocked, outcome.blocker), (true, Some(1)));
    assert_eq!(settle(&mut groups, &w[0], Verdict::Clear), None);
    assert_eq!(groups.waiting(), 0, "the last copy out frees the id");
    let w = copies(&mut groups, shadow, &[1, 2, 3]);
    let mut more = Vec::new();
    for c in &w {
        let v = VerdictRecord::new(c, Verdict::Clear);
        assert_eq!(groups.settle(&v, &mut more), Ok(None));
    }
    assert_eq!(more.iter().map(|c| c.domain).collect::<Vec<_>>(), [3]);
    let (_, outcome) = settle(&mut groups, &more[0], Verdict::Clear).unwrap();
    assert!(!outcome.blocked);
    assert_eq!(groups.waiting(), 0);
}

#[test]
fn one_blocking_copy_blocks_the_shadow_ray() {
    let mut groups = Groups::default();
    let c = copies(&mut groups, ray(1), &[1, 2]);
    settle(&mut groups, &c[1], Verdict::Blocked);
    let (_, outcome) = settle(&mut groups, &c[0], Verdict::Clear).unwrap();
    assert!(outcome.blocked);
    assert_eq!(outcome.blocker, Some(1), "at the second place");
}

#[test]
fn verdicts_survive_the_wire_form() {
    let copy = spread(&mut Groups::default(), ray(1), &[1]);
    for v in [
        Verdict::Clear,
        Verdict::Blocked,
        hit(2.5),
        segment(9, 0.25),
        Verdict::Light(SegmentLight {
            first: 9,
            light: 1,
            depth: 2.5,
            rgb: [0.1, 0.2, 0.3],
        }),
        Verdict::VolumeEnd(3),
    ] {
        assert_eq!(VerdictRecord::new(&copy, v).verdict(), v);
    }
    // A verdict on a stretch of the ray names the copy's domain, whatever it found there.
    for v in [Verdict::Clear, Verdict::Blocked, hit(2.5)] {
        assert_eq!(VerdictRecord::new(&copy, v).order, copy.domain);
    }
}

#[test]
fn a_verdict_naming_a_domain_no_copy_went_to_is_refused() {
    let mut groups = Groups::default();
    let c = copies(&mut groups, ray(7), &[4, 5]);
    for v in [Verdict::Clear, Verdict::Blocked, hit(1.0)] {
        let forged = VerdictRecord::new(&RayRecord { domain: 9, ..c[0] }, v);
        assert_eq!(
            groups.settle(&forged, &mut Vec::new()),
            Err(GroupError::Mismatch(c[0].group)),
            "{v:?}"
        );
    }
    // Nothing was counted: the real verdicts conclude the ray as before.
    assert_eq!(settle(&mut groups, &c[1], hit(3.0)), None);
    let (_, outcome) = settle(&mut groups, &c[0], Verdict::Clear).unwrap();
    assert_eq!(outcome.nearest.map(|h| h.t), Some(3.0));
}

fn segment(first: u32, alpha: f32) -> Verdict {
    Verdict::Segment(Segment::plain(first, [alpha * 0.5; 3], alpha))
}

#[test]
fn volume_segments_conclude_once_all_copies_closed_in_order_along_the_ray() {
    // Two bricks: the far one's segments (and its closing count) arrive first, the near
    // one's closing verdict before its segments.
    let mut groups = Groups::default();
    let copy = spread(&mut groups, ray(7), &[1, 2]);
    assert_eq!(settle(&mut groups, &copy, segment(40, 0.2)), None);
    assert_eq!(settle(&mut groups, &copy, segment(30, 0.1)), None);
    assert_eq!(settle(&mut groups, &copy, Verdict::VolumeEnd(2)), None);
    assert_eq!(settle(&mut groups, &copy, Verdict::VolumeEnd(2)), None);
    assert_eq!(settle(&mut groups, &copy, segment(12, 0.3)), None);
    let (r, outcome) = settle(&mut groups, &copy, segment(3, 0.4)).unwrap();
    assert_eq!(r.credit, 7);
    let firsts: Vec<u32> = outcome.segments.iter().map(|s| s.first).collect();
    assert_eq!(firsts, [3, 12, 30, 40]);
    assert_eq!(groups.waiting(), 0);

    // A copy that sends nothing closes with a count of zero; an empty copy off the path
    // closes with Clear.
    let c = copies(&mut groups, ray(1), &[1, 2]);
    assert_eq!(settle(&mut groups, &c[0], Verdict::VolumeEnd(0)), None);
    let (_, outcome) = settle(&mut groups, &c[1], Verdict::Clear).unwrap();
    assert!(outcome.segments.is_empty());
}

#[test]
fn a_hit_on_a_bricks_surfaces_comes_with_its_segments_and_the_nearest_wins() {
    // The near brick's hit arrives after its closing count, which counts it; the far
    // brick's hit is farther along the ray and loses.
    let mut groups = Groups::default();
    let c = copies(&mut groups, ray(7), &[1, 2]);
    let volume_hit = |t| {
        Verdict::VolumeHit(SurfaceHit {
            t,
            normal: [0.0, 0.0, 1.0],
            material: 0,
        })
    };
    assert_eq!(settle(&mut groups, &c[0], segment(3, 0.1)), None);
    assert_eq!(settle(&mut groups, &c[0], Verdict::VolumeEnd(2)), None);
    // The far brick's hit is nearer in distance than a real one would be: the place decides.
    assert_eq!(settle(&mut groups, &c[1], volume_hit(1.0)), None);
    assert_eq!(settle(&mut groups, &c[0], volume_hit(2.5)), None);
    let (_, outcome) = settle(&mut groups, &c[1], Verdict::VolumeEnd(1)).unwrap();
    assert_eq!(outcome.nearest.map(|h| h.t), Some(2.5));
    assert_eq!(outcome.segments.len(), 1);
    // Through the wire and back, a brick's hit stays one.
    let back = VerdictRecord::new(&c[0], volume_hit(2.5)).verdict();
    assert_eq!(back, volume_hit(2.5));
}

fn light(first: u32, light: u32) -> Verdict {
    Verdict::Light(SegmentLight {
        first,
        light,
        depth: first as f32,
        rgb: [0.25; 3],
    })
}

#[test]
fn segment_lights_are_counted_and_sorted_by_segment_then_light() {
    let mut groups = Groups::default();
    let copy = spread(&mut groups, ray(7), &[1, 2]);
    // The far brick: one segment lit by lights 1 and 0, in that order; then the near one,
    // its lights before its segment.
    assert_eq!(settle(&mut groups, &copy, segment(40, 0.2)), None);
    assert_eq!(settle(&mut groups, &copy, light(40, 1)), None);
    assert_eq!(settle(&mut groups, &copy, light(40, 0)), None);
    assert_eq!(settle(&mut groups, &copy, Verdict::VolumeEnd(3)), None);
    assert_eq!(settle(&mut groups, &copy, light(3, 2)), None);
    assert_eq!(settle(&mut groups, &copy, Verdict::VolumeEnd(2)), None);
    let (_, outcome) = settle(&mut groups, &copy, segment(3, 0.4)).unwrap();
    let lights: Vec<(u32, u32)> = outcome.lights.iter().map(|l| (l.first, l.light)).collect();
    assert_eq!(lights, [(3, 2), (40, 0), (40, 1)]);
    // A light beyond the count is one verdict too many.
    let copy = spread(&mut groups, ray(1), &[1]);
    settle(&mut groups, &copy, segment(1, 0.5));
    groups
        .settle(&VerdictRecord::new(&copy, light(1, 0)), &mut Vec::new())
        .unwrap();
    let end = VerdictRecord::new(&copy, Verdict::VolumeEnd(1));
    assert_eq!(
        groups.settle(&end, &mut Vec::new()),
        Err(GroupError::TooManySegments(copy.group))
    );
}

#[test]
fn segments_beyond_what_the_copies_announce_are_refused() {
    let mut groups = Groups::default();
    let copy = spread(&mut groups, ray(1), &[1]);
    settle(&mut groups, &copy, segment(1, 0.5));
    let extra = VerdictRecord::new(&copy, segment(2, 0.5));
    groups.settle(&extra, &mut Vec::new()).unwrap();
    let end = VerdictRecord::new(&copy, Verdict::VolumeEnd(1));
    assert_eq!(
        groups.settle(&end, &mut Vec::new()),
        Err(GroupError::TooManySegments(copy.group)),
        "two segments, one announced: the group is dropped"
    );
    assert_eq!(groups.waiting(), 0);
    let copy = spread(&mut groups, ray(1), &[1]);
    let huge = VerdictRecord::new(&copy, Verdict::VolumeEnd(MAX_SEGMENTS + 1));
    assert_eq!(
        groups.settle(&huge, &mut Vec::new()),
        Err(GroupError::TooManySegments(copy.group))
    );
}

#[test]
fn ids_are_reused_and_stale_verdicts_are_refused() {
    let mut groups = Groups::default();
    let a = spread(&mut groups, ray(1), &[1]);
    settle(&mut groups, &a, Verdict::Clear).unwrap();
    let stale = VerdictRecord::new(&a, Verdict::Clear);
    assert_eq!(
        groups.settle(&stale, &mut Vec::new()),
        Err(GroupError::Unknown(a.group))
    );
    let far = VerdictRecord { group: 99, ..stale };
    assert_eq!(
        groups.settle(&far, &mut Vec::new()),
        Err(GroupError::Unknown(99))
    );
    let b = spread(&mut groups, RayRecord { epoch: 1, ..ray(2) }, &[1, 2]);
    assert_eq!(a.group, b.group);
    assert_eq!(
        groups.settle(&stale, &mut Vec::new()),
        Err(GroupError::Mismatch(b.group))
    );
    groups.retain(|r| r.credit != 2);
    assert_eq!(groups.waiting(), 0);
    let late = VerdictRecord::new(&b, Verdict::Clear);
    assert_eq!(
        groups.settle(&late, &mut Vec::new()),
        Err(GroupError::Unknown(b.group))
    );
}

#[test]
fn a_hit_with_every_nearer_domain_clear_concludes_before_the_farther_copies_answer() {
    let mut groups = Groups::default();
    let c = copies(&mut groups, ray(7), &[4, 5, 6]);
    // The hit in the second domain decides nothing while the first has not answered.
    assert_eq!(settle(&mut groups, &c[1], hit(2.0)), None);
    let (r, outcome) = settle(&mut groups, &c[0], Verdict::Clear).unwrap();
    assert_eq!((r.credit, outcome.nearest.map(|h| h.t)), (7, Some(2.0)));
    assert_eq!(groups.early, 1);
    // The third copy is still out: its id is not reused, and its verdict is absorbed.
    let other = copies(&mut groups, RayRecord { pixel: 6, ..ray(1) }, &[4]);
    assert_ne!(other[0].group, c[0].group);
    assert_eq!(groups.waiting(), 2);
    assert_eq!(settle(&mut groups, &c[2], hit(1.0)), None);
    assert_eq!(groups.waiting(), 1);
    // The clear verdict names its copy's domain; a hit arriving first with the nearer clear
    // already in concludes at once.
    assert_eq!(VerdictRecord::new(&c[2], Verdict::Clear).order, 6);
    let c = copies(&mut groups, ray(3), &[4, 5, 6]);
    assert_eq!(settle(&mut groups, &c[0], Verdict::Clear), None);
    assert!(settle(&mut groups, &c[1], hit(2.0)).is_some());
}

#[test]
fn copies_of_a_concluded_ray_are_skipped_and_free_the_id_once_all_are_accounted_for() {
    let mut groups = Groups::default();
    let shadow = RayRecord {
        kind: crate::ray::RayKind::Shadow as u8,
        ..ray(1)
    };
    let c = copies(&mut groups, shadow, &[1, 2, 3]);
    assert!(!groups.skip(&c[0]), "the ray is still undecided");
    assert!(settle(&mut groups, &c[2], Verdict::Blocked).is_some());
    assert!(groups.skip(&c[0]));
    // A copy of another ray under the same id is not this ray's.
    let stranger = RayRecord { pixel: 9, ..c[1] };
    assert!(!groups.skip(&stranger));
    assert!(groups.skip(&c[1]));
    assert!(
        !groups.skip(&c[1]),
        "all copies accounted for: the id is free"
    );
    assert_eq!((groups.skipped, groups.waiting()), (2, 0));
    let late = VerdictRecord::new(&c[1], Verdict::Clear);
    assert_eq!(
        groups.settle(&late, &mut Vec::new()),
        Err(GroupError::Unknown(c[1].group))
    );
}

#[test]
fn volume_rays_wait_for_every_copy() {
    // A brick's closing verdict before the hit: segments may still be due, so no early end.
    let mut groups = Groups::default();
    let c = copies(&mut groups, ray(7), &[1, 2, 3]);
    assert_eq!(settle(&mut groups, &c[0], Verdict::VolumeEnd(0)), None);
    assert_eq!(settle(&mut groups, &c[1], hit(2.0)), None);
    let (_, outcome) = settle(&mut groups, &c[2], Verdict::Clear).unwrap();
    assert_eq!(outcome.nearest.map(|h| h.t), Some(2.0));
    assert_eq!(groups.early, 0);
}

#[test]
fn a_path_longer_than_the_record_holds_answers_as_a_short_one() {
    // 70 places: the path on the heap, the answers as flags (past 64 places).
    let domains: Vec<u32> = (0..70).map(|d| d * 3).collect();
    let mut groups = Groups::default();
    let copies = copies(&mut groups, ray(9), &domains);
    assert_eq!(copies.len(), 70);
    // A hit at place 2 decides nothing until places 0 and 1 are clear.
    assert!(settle(&mut groups, &copies[2], hit(1.0)).is_none());
    assert!(settle(&mut groups, &copies[1], Verdict::Clear).is_none());
    let (r, outcome) = settle(&mut groups, &copies[0], Verdict::Clear).unwrap();
    assert_eq!((r.credit, outcome.nearest.map(|h| h.t)), (9, Some(1.0)));
    // The 67 copies still out hold the id until they are skipped.
    assert!(copies[3..].iter().all(|c| groups.skip(c)));
    assert_eq!(groups.waiting(), 0);
}

#[test]
fn many_waiting_rays_each_keep_their_own_group() {
    // More rays than one chunk of slots holds, settled in the reverse order.
    let mut groups = Groups::default();
    let firsts: Vec<RayRecord> = (0..10_000u32)
        .map(|i| {
            let r = RayRecord {
                pixel: i,
                credit: u64::from(i) + 1,
                ..RayRecord::zeroed()
            };
            spread(&mut groups, r, &[i % 7])
        })
        .collect();
    assert_eq!(groups.waiting(), 10_000);
    for (i, copy) in firsts.iter().enumerate().rev() {
        let (r, _) = settle(&mut groups, copy, Verdict::Clear).unwrap();
        assert_eq!((r.pixel, r.credit), (i as u32, i as u64 + 1));
    }
    assert_eq!(groups.waiting(), 0);
}

#[test]
fn a_group_record_stays_small() {
    // Settling a verdict is one random access into the groups (README "Benchmarks"): a
    // group was 280 bytes and a path vector before this bound.
    assert!(std::mem::size_of::<Option<Group>>() <= 232);
}
