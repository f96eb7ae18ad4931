//! What rayfarm's fuzz targets check, one function per target: each takes any bytes, feeds
//! them to the code that reads them from another process or from disk, and panics if a
//! property fails. libFuzzer runs them under coverage guidance (`fuzz/fuzz_targets`, with
//! `cargo fuzz`); `tests/corpus.rs` replays every committed corpus input through them on
//! every CI run, so what fuzzing found stays found.
//!
//! The properties, beyond "no panic, no crash": an accepted ray or verdict batch re-encodes
//! to the bytes it came from; an accepted domain file can be traced by every kernel this CPU
//! runs, and they agree to the bit; an accepted mesh has only finite vertices and in-range
//! indices; an accepted volume brick can be marched, giving a finite colour and an opacity
//! that is a fraction; an accepted transfer function re-parses to itself from its own TOML,
//! and its table's opacities are fractions and are zero wherever it calls a range
//! transparent; a refusal always says why.

use glam::Vec3;
use prost::Message;
use rayfarm_core::bvh::{Kernel, TraceRay, Traverser};
use rayfarm_core::cluster::tile_sums;
use rayfarm_core::mesh::parse_mesh;
use rayfarm_core::scene::domain_file::parse_domain_bytes;
use rayfarm_core::scene::{Camera, Manifest};
use rayfarm_core::wire::{self, BatchLimits};
use rayfarm_proto as proto;

/// What a frame of the fuzzed batches allows: small, so records out of range are common.
const LIMITS: BatchLimits = BatchLimits {
    domains: 8,
    pixels: 10_000,
    max_depth: 6,
    materials: 4,
    max_records: 4096,
};

/// The camera of the scene a fuzzed job names.
const SCENE_CAMERA: Camera = Camera {
    eye: [0.0, 0.0, 5.0],
    look_at: [0.0; 3],
    up: [0.0, 1.0, 0.0],
    fov_y_degrees: 40.0,
};

/// Pixels of a fuzzed tile result's tile.
const TILE_PIXELS: usize = 64 * 64;

/// Materials a fuzzed domain file may name.
const MATERIALS: u32 = 4;

/// Ray batches from peers (`core::wire`): accepted ones re-encode to the same bytes.
pub fn ray_batch(data: &[u8]) {
    match wire::decode_batch(data, &LIMITS) {
        Ok(rays) => assert_eq!(wire::encode_batch(&rays), data, "an accepted batch changed"),
        Err(e) => assert!(!e.to_string().is_empty()),
    }
}

/// Verdict batches from peers: accepted ones re-encode to the same bytes.
pub fn verdict_batch(data: &[u8]) {
    match wire::decode_verdicts(data, &LIMITS) {
        Ok(verdicts) => assert_eq!(
            wire::encode_verdicts(&verdicts),
            data,
            "an accepted verdict batch changed"
        ),
        Err(e) => assert!(!e.to_string().is_empty()),
    }
}

/// `scene.toml` as text: parsed or refused with a reason; an accepted manifest checks its
/// own domains' boxes (the tree is built from them) without panicking.
pub fn manifest(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    match Manifest::parse(text) {
        Ok(m) => {
            let _ = m.domain_tree();
        }
        Err(e) => assert!(!e.is_empty()),
    }
}

/// Mesh files in every format rayfarm reads (the first byte picks the format, the rest is
/// the file): accepted meshes have finite vertices and indices in range.
pub fn mesh(data: &[u8]) {
    let Some((&pick, bytes)) = data.split_first() else {
        return;
    };
    let name = ["in.ply", "in.obj", "in.stl"][usize::from(pick % 3)];
    match parse_mesh(name, bytes) {
        Ok(mesh) => {
            assert!(mesh.positions.iter().flatten().all(|c| c.is_finite()));
            let n = mesh.positions.len();
            assert!(mesh.triangles.iter().flatten().all(|&i| (i as usize) < n));
        }
        Err(e) => assert!(!e.to_string().is_empty()),
    }
}

/// Domain files: the checksum is fixed up first (an attacker who writes a scene can make it
/// match), so the structural checks behind it are reached. An accepted file is traced with
/// every kernel this CPU supports, from its corners toward its centre and back: no crash, and
/// every kernel finds the same hits to the bit.
pub fn domain_file(data: &[u8]) {
    let mut bytes = data.to_vec();
    rayfarm_core::scene::domain_file::seal(&mut bytes);
    let Ok(domain) = parse_domain_bytes(&bytes, MATERIALS) else {
        return;
    };
    let b = domain.bounds();
    let (lo, hi) = (Vec3::from(b.min), Vec3::from(b.max));
    if !(lo.is_finite() && hi.is_finite()) {
        return;
    }
    let centre = (lo + hi) * 0.5;
    let corners = (0..8).map(|i| {
        Vec3::new(
            if i & 1 == 0 { lo.x } else { hi.x },
            if i & 2 == 0 { lo.y } else { hi.y },
            if i & 4 == 0 { lo.z } else { hi.z },
        )
    });
    let rays: Vec<TraceRay> = corners
        .flat_map(|c| {
            [
                TraceRay::new(c, centre - c),
                TraceRay::new(centre, c - centre),
            ]
        })
        .collect();
    let kernels: Vec<Kernel> = Kernel::ALL.into_iter().filter(|k| k.supported()).collect();
    let trace = |k: Kernel| {
        let mut t = Traverser::with_kernel(k).expect("supported");
        rays.iter()
            .map(|r| {
                let hit = t.nearest_hit(domain.bvh(), r, 0.0, f32::INFINITY);
                let blocked = t.any_hit(domain.bvh(), r, 0.0, f32::INFINITY);
                // A hit's shading normals, if stored, are unit vectors (the reader checked
                // their components; a set lane is three non-zero normals).
                if let Some(normals) = hit.and_then(|h| domain.bvh().vertex_normals(&h)) {
                    assert!(normals.iter().all(|n| n.is_finite() && n.length() <= 2.0));
                }
                (hit.map(|h| (h.t.to_bits(), h.id)), blocked)
            })
            .collect::<Vec<_>>()
    };
    let first = trace(kernels[0]);
    for &k in &kernels[1..] {
        assert_eq!(trace(k), first, "{k:?} and {:?} disagree", kernels[0]);
    }
}

/// What the job API accepts: a SubmitJobRequest's spec is checked as the coordinator checks
/// it, and a refusal says why.
pub fn job_request(data: &[u8]) {
    let Ok(req) = proto::SubmitJobRequest::decode(data) else {
        return;
    };
    let Some(spec) = req.spec else {
        return;
    };
    if rayfarm_node::bounds::check_field("scene", &spec.scene).is_err() {
        return;
    }
    match rayfarm_node::job::frame_spec(&spec, &SCENE_CAMERA) {
        Ok(frame) => assert!(frame.width > 0 && frame.height > 0 && frame.spp > 0),
        Err(e) => assert!(!e.is_empty()),
    }
}

/// What a worker sends the coordinator: tile results' sums decode (in pixel order, within
/// the tile, and round-trip) or are refused.
pub fn worker_message(data: &[u8]) {
    let Ok(msg) = proto::WorkerMessage::decode(data) else {
        return;
    };
    if let Some(proto::worker_message::Body::TileResults(r)) = msg.body {
        for result in r.results {
            match tile_sums::decode(&result.sums, TILE_PIXELS) {
                Ok(sums) => {
                    assert!(sums.len() <= TILE_PIXELS);
                    assert!(
                        sums.windows(2).all(|w| w[0].0 < w[1].0),
                        "pixels out of order"
                    );
                    let again = tile_sums::decode(&tile_sums::encode(&sums), TILE_PIXELS);
                    assert_eq!(again.as_ref(), Ok(&sums), "accepted sums do not round-trip");
                }
                Err(e) => assert!(!e.to_string().is_empty()),
            }
        }
    }
}

/// What a peer sends: every batch of a bundle decodes as its tier says, or is refused.
pub fn peer_bundle(data: &[u8]) {
    let Ok(bundle) = proto::PeerBundle::decode(data) else {
        return;
    };
    let verdicts = bundle.tier() == proto::Tier::Results;
    for batch in &bundle.batches {
        if verdicts {
            verdict_batch(batch);
        } else {
            ray_batch(batch);
        }
    }
}

/// Volume bricks (`core::scene::brick`): the checksum is fixed up first, as for domain files, and
/// the bytes copied to a 64-byte aligned buffer, as a map would be. An accepted brick is
/// marched along rays from its corners through its centre with a density transfer function,
/// lit by a directional light: no panic, every segment's colour finite and non-negative, its
/// opacity and the ray's a fraction.
pub fn brick(data: &[u8]) {
    use rayfarm_core::ray::RayRecord;
    use rayfarm_core::render::dvr::{SampleCounts, VolumeView, composite};
    use rayfarm_core::scene::brick;
    use rayfarm_core::scene::{Light, VolumeSpec};
    use rayfarm_core::transfer::TransferFunction;

    // Aligned for the voxels' f32 (a map is page-aligned; sections are checked for 64-byte
    // offsets, not addresses).
    let mut words = vec![0u64; data.len().div_ceil(8)];
    let buffer: &mut [u8] = bytemuck::cast_slice_mut(&mut words);
    let bytes = &mut buffer[..data.len()];
    bytes.copy_from_slice(data);
    brick::seal(bytes);
    let bytes = &*bytes;
    // The manifest's checksum is the file's own (the manifest is another target's).
    let expected = brick::recorded_checksum(bytes).unwrap_or(0);
    let layout = match brick::parse(bytes, expected, false) {
        Ok(layout) => layout,
        Err(e) => {
            assert!(!e.is_empty(), "a refusal says why");
            return;
        }
    };
    let b = layout.view(bytes);
    let h = b.header;
    // Voxels the size of one world unit, voxel 0 at the origin.
    let spec = VolumeSpec {
        dims: h.volume_dims,
        origin: [0.0; 3],
        spacing: [1.0; 3],
        step: 0.5,
        shading: true,
        shadows: true,
        transfer: TransferFunction::preset("density").expect("preset"),
    };
    if spec.check().is_err() {
        return;
    }
    let lights = [Light::Directional {
        direction: [0.3, 0.9, 0.1],
        radiance: [1.0; 3],
    }];
    let view = VolumeView::new(&spec, &lights);
    let skip = view.transparent_blocks(&b);
    assert_eq!(skip.len(), b.ranges().len());
    let lo = Vec3::from(h.cells_lo.map(|c| c as f32));
    let hi = Vec3::from(h.cells_hi.map(|c| c as f32));
    let centre = (lo + hi) * 0.5;
    for i in 0..8 {
        let corner = Vec3::new(
            if i & 1 == 0 { lo.x } else { hi.x },
            if i & 2 == 0 { lo.y } else { hi.y },
            if i & 4 == 0 { lo.z } else { hi.z },
        );
        let dir = (centre - corner).normalize_or(Vec3::X);
        let length = (hi - lo).length();
        let mut ray: RayRecord = RayRecord {
            origin: corner.into(),
            dir: dir.into(),
            t_max: length,
            throughput: [1.0; 3],
            credit: 1,
            ..bytemuck::Zeroable::zeroed()
        };
        let lit = view.lights_for(&ray);
        let mut counts = SampleCounts::default();
        view.march(
            &b,
            &skip,
            (corner, dir),
            &lit,
            0.0,
            length,
            &mut counts,
            |segment| {
                let colour = segment.rgb.iter().chain(segment.direct.iter().flatten());
                assert!(
                    colour.clone().all(|c| c.is_finite() && *c >= 0.0),
                    "{segment:?}"
                );
                assert!((0.0..=1.0).contains(&segment.alpha), "{segment:?}");
                if composite(&mut ray, &segment) {
                    std::ops::ControlFlow::Break(())
                } else {
                    std::ops::ControlFlow::Continue(())
                }
            },
        );
        assert!(
            (0.0..=1.0).contains(&ray.volume_alpha),
            "{}",
            ray.volume_alpha
        );
    }
}

/// Transfer-function TOML (`core::transfer`): an accepted one passes its own check, parses
/// again to itself from the TOML it serialises to, and its table (for a half-voxel step)
/// holds opacities that are fractions, zero at every value of a range it calls transparent.
pub fn transfer_function(data: &[u8]) {
    use rayfarm_core::transfer::{TransferFunction, TransferTable};
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let tf = match TransferFunction::parse(text) {
        Ok(tf) => tf,
        Err(e) => {
            assert!(!e.is_empty(), "a refusal says why");
            return;
        }
    };
    tf.check()
        .expect("an accepted transfer function checks out");
    let toml = tf
        .to_toml()
        .expect("an accepted transfer function serialises");
    let again = TransferFunction::parse(&toml).expect("its own TOML parses");
    assert_eq!(again, tf, "TOML round trip");
    let table = TransferTable::new(&tf, 0.5);
    let lo = tf.points[0].value;
    let hi = tf.points[tf.points.len() - 1].value;
    let probe: Vec<f32> = (0..=64)
        .map(|i| lo + (hi - lo) * (i as f32 / 64.0))
        .chain([
            lo - 1.0,
            hi + 1.0,
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
        ])
        .collect();
    for &v in &probe {
        let [r, g, b, a] = table.lookup(v);
        assert!((0.0..=1.0).contains(&a), "opacity {a} at {v}");
        assert!(
            [r, g, b].iter().all(|c| (0.0..=1.0).contains(c)),
            "colour at {v}"
        );
    }
    for w in probe[..65].windows(2) {
        if table.transparent(w[0], w[1]) {
            for v in [w[0], (w[0] + w[1]) * 0.5, w[1]] {
                assert_eq!(table.lookup(v)[3], 0.0, "{v} in a transparent range");
            }
        }
    }
}

/// A refusal of a request: it says why, and never echoes an oversized field (bounds refuse
/// with a field's size only).
fn refused(status: &tonic::Status, fields: &[&str]) {
    let message = status.message();
    assert!(!message.is_empty(), "a refusal says why");
    for field in fields {
        if field.len() > rayfarm_node::bounds::MAX_FIELD_BYTES {
            assert!(
                !message.contains(field),
                "a refusal echoes an oversized field"
            );
        }
    }
}

/// A job id field as every job API call but ListJobs checks it before any work.
fn job_id(id: &str) {
    if let Err(e) = rayfarm_node::bounds::check_field("job_id", id) {
        refused(&e, &[id]);
    }
}

/// Every job API request (the first byte picks the call, the rest is its protobuf message),
/// checked as the coordinator checks it before any work: SubmitJob as [`job_request`];
/// ListJobs's page within bounds and an accepted page token one a response gives (it
/// re-encodes to itself); FetchResultStream's chunk within bounds; refusals say why and
/// never echo an oversized field.
pub fn job_api_request(data: &[u8]) {
    use rayfarm_node::requests;
    let Some((&pick, bytes)) = data.split_first() else {
        return;
    };
    match pick % 9 {
        0 => job_request(bytes),
        1 => {
            if let Ok(r) = proto::WatchJobRequest::decode(bytes) {
                job_id(&r.job_id);
            }
        }
        2 => {
            let Ok(r) = proto::ListJobsRequest::decode(bytes) else {
                return;
            };
            match requests::list_page(&r) {
                Ok(page) => {
                    assert!((1..=requests::MAX_PAGE).contains(&page.size));
                    match page.from_seq {
                        None => assert!(r.page_token.is_empty()),
                        Some(seq) => assert_eq!(
                            requests::page_token(seq),
                            r.page_token,
                            "an accepted page token is not one a response gives"
                        ),
                    }
                }
                Err(e) => refused(&e, &[&r.page_token]),
            }
        }
        3 => {
            if let Ok(r) = proto::CancelJobRequest::decode(bytes) {
                job_id(&r.job_id);
            }
        }
        4 => {
            if let Ok(r) = proto::FetchResultRequest::decode(bytes) {
                job_id(&r.job_id);
                // Any number names a format: unknown ones read as the default.
                let _ = r.format();
            }
        }
        5 => {
            let Ok(r) = proto::FetchResultStreamRequest::decode(bytes) else {
                return;
            };
            let _ = r.format();
            match requests::result_chunk(&r) {
                Ok(chunk) => assert!((1..=requests::MAX_RESULT_CHUNK).contains(&chunk)),
                Err(e) => refused(&e, &[&r.job_id]),
            }
        }
        6 => {
            if let Ok(r) = proto::FetchPreviewRequest::decode(bytes) {
                job_id(&r.job_id);
            }
        }
        7 => {
            // Any priority is taken; only the job id is checked.
            if let Ok(r) = proto::SetJobPriorityRequest::decode(bytes) {
                job_id(&r.job_id);
            }
        }
        _ => {
            // No fields to check: decoding (unknown fields skipped) is all the server does.
            let _ = proto::GetClusterStatusRequest::decode(bytes);
        }
    }
}

/// A peer's `FetchDomain` request (`DomainRequest`), checked as the serving worker checks it
/// before looking at its frame: an accepted one speaks this protocol, its fields are within
/// bounds and its chunk size within the server's; refusals say why and never echo an
/// oversized field.
pub fn domain_request(data: &[u8]) {
    use rayfarm_node::requests::{MAX_DOMAIN_CHUNK, MIN_DOMAIN_CHUNK, domain_request};
    let Ok(r) = proto::DomainRequest::decode(data) else {
        return;
    };
    match domain_request(&r) {
        Ok(chunk) => {
            assert_eq!(r.protocol_version, proto::PROTOCOL_VERSION);
            let bound = rayfarm_node::bounds::MAX_FIELD_BYTES;
            assert!(r.sender.len() <= bound && r.job_id.len() <= bound);
            assert!((MIN_DOMAIN_CHUNK..=MAX_DOMAIN_CHUNK).contains(&chunk));
        }
        Err(e) => refused(&e, &[&r.sender, &r.job_id]),
    }
}
