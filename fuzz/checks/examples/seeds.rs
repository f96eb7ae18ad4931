//! Writes the seed corpora of the fuzz targets into `fuzz/corpus/<target>/`: a few valid
//! inputs of each kind (real ray and verdict batches, a real scene's manifest and domain
//! files, meshes in every format, job requests, worker messages, peer bundles, a volume
//! scene's bricks, the preset transfer functions, volume verdicts), from which
//! libFuzzer's mutations start. `cargo run --release -p rayfarm-fuzz --example seeds`.

use std::path::{Path, PathBuf};

use prost::Message;
use rayfarm_core::cluster::tile_sums;
use rayfarm_core::geometry::Aabb;
use rayfarm_core::mesh::{
    TriangleMesh, write_obj, write_ply_ascii, write_ply_binary, write_stl_ascii, write_stl_binary,
};
use rayfarm_core::prepare::brick_scene::VolumeLook;
use rayfarm_core::prepare::generate::{NbodyOptions, prepare_nbody, prepare_nbody_volume};
use rayfarm_core::ray::RayRecord;
use rayfarm_core::scene::domain_file::{SourceTriangle, write_domain};
use rayfarm_core::transfer::{PRESETS, TransferFunction};
use rayfarm_core::wire::{self, VerdictRecord};
use rayfarm_proto as proto;

fn corpus(target: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../corpus")
        .join(target);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn seed(target: &str, name: &str, bytes: &[u8]) {
    std::fs::write(corpus(target).join(name), bytes).unwrap();
}

fn ray(i: u32) -> RayRecord {
    RayRecord {
        origin: [i as f32, 0.5, -2.0],
        t_min: 0.0,
        dir: [0.0, 0.0, 1.0],
        t_max: f32::INFINITY,
        throughput: [1.0, 0.5, 0.25],
        pixel: i * 7,
        sample: i,
        depth: (i % 3) as u16,
        kind: (i % 2) as u8,
        domain: i % 8,
        tile: i / 4,
        epoch: 1,
        credit: 1 << 20,
        ..bytemuck::Zeroable::zeroed()
    }
}

fn verdict(i: u32) -> VerdictRecord {
    let mut v: VerdictRecord = bytemuck::Zeroable::zeroed();
    v.group = i;
    v.tile = i / 4;
    v.epoch = 1;
    v.pixel = i * 3;
    v.sample = i;
    v.kind = [
        VerdictRecord::CLEAR,
        VerdictRecord::BLOCKED,
        VerdictRecord::HIT,
    ][i as usize % 3];
    if v.kind == VerdictRecord::HIT {
        v.order = 2;
        v.t = 1.5;
        v.normal = [0.0, 1.0, 0.0];
        v.material = 1;
    }
    v
}

fn volume_verdicts() -> Vec<VerdictRecord> {
    let mut segment = verdict(0);
    (segment.kind, segment.order, segment.t, segment.normal) =
        (VerdictRecord::SEGMENT, 12, 0.4, [0.1, 0.2, 0.05]);
    let mut light = verdict(0);
    (
        light.kind,
        light.order,
        light.t,
        light.normal,
        light.material,
    ) = (VerdictRecord::LIGHT, 12, 7.5, [0.3, 0.2, 0.1], 1);
    let mut end = verdict(0);
    (end.kind, end.material) = (VerdictRecord::VOLUME_END, 2);
    vec![segment, light, end]
}

fn main() {
    let rays: Vec<RayRecord> = (0..5).map(ray).collect();
    seed("ray_batch", "five", &wire::encode_batch(&rays));
    seed("ray_batch", "empty", &wire::encode_batch(&[]));
    let verdicts: Vec<VerdictRecord> = (0..6).map(verdict).collect();
    seed("verdict_batch", "six", &wire::encode_verdicts(&verdicts));

    // A real scene: its manifest and its domain files.
    let scene = tempdir();
    let options = NbodyOptions {
        name: "seed".into(),
        triangles: 1000,
        seed: 1,
        domains: 2,
        max_memory: None,
        force: true,
    };
    let manifest = prepare_nbody(&scene, &options).unwrap();
    seed(
        "manifest",
        "nbody",
        &std::fs::read(scene.join("scene.toml")).unwrap(),
    );
    for d in &manifest.domains {
        let bytes = std::fs::read(scene.join(&d.file)).unwrap();
        seed("domain_file", &d.file, &bytes);
    }
    // Small domains whose every field a mutation reaches quickly: one block with padding
    // lanes, one node of seven one-block leaves, and no triangles at all. (The committed
    // corpus also holds hand-made lies of `seven_triangles`: counts, offsets, children,
    // leaf sizes, a material; and one file of format 4, refused by its version.)
    for (name, count) in [("one_triangle", 1u64), ("seven_triangles", 7), ("empty", 0)] {
        let tris: Vec<SourceTriangle> = (0..count)
            .map(|i| {
                let x = i as f32;
                SourceTriangle {
                    vertices: [[x, 0.0, 0.0], [x + 1.0, 0.0, 0.0], [x, 1.0, 0.5]],
                    id: 10 + i,
                    material: (i % 2) as u32,
                    // Smooth normals on some: files with the normals section (format 6).
                    normals: (i % 2 == 0).then_some([
                        [0.0, 0.0, 1.0],
                        [0.0, 0.6, 0.8],
                        [0.6, 0.0, 0.8],
                    ]),
                }
            })
            .collect();
        let path = scene.join(format!("{name}.rfd"));
        let bounds = Aabb {
            min: [-1.0; 3],
            max: [8.0; 3],
        };
        write_domain(&path, 0, bounds, &tris).unwrap();
        seed("domain_file", name, &std::fs::read(&path).unwrap());
    }

    let mesh = TriangleMesh {
        positions: vec![
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.0, 0.0, 1.0],
        ],
        triangles: vec![[0, 1, 2], [0, 2, 3], [0, 3, 1]],
    };
    let mut formats: Vec<(&str, u8, Vec<u8>)> = Vec::new();
    let mut b = Vec::new();
    write_ply_ascii(&mesh, &mut b).unwrap();
    formats.push(("ply_ascii", 0, b));
    let mut b = Vec::new();
    write_ply_binary(&mesh, &mut b).unwrap();
    formats.push(("ply_binary", 0, b));
    let mut b = Vec::new();
    write_obj(&mesh, &mut b).unwrap();
    formats.push(("obj", 1, b));
    let mut b = Vec::new();
    write_stl_ascii(&mesh, &mut b).unwrap();
    formats.push(("stl_ascii", 2, b));
    let mut b = Vec::new();
    write_stl_binary(&mesh, &mut b).unwrap();
    formats.push(("stl_binary", 2, b));
    for (name, pick, bytes) in formats {
        let mut input = vec![pick];
        input.extend_from_slice(&bytes);
        seed("mesh", name, &input);
    }

    let spec = proto::JobSpec {
        scene: "seed".into(),
        width: 64,
        height: 48,
        spp: 2,
        max_depth: 3,
        camera: Some(proto::Camera {
            eye: vec![0.0, 0.0, 5.0],
            look_at: vec![0.0; 3],
            up: vec![0.0, 1.0, 0.0],
            fov_y_degrees: 30.0,
        }),
        ..Default::default()
    };
    let req = proto::SubmitJobRequest { spec: Some(spec) };
    seed("job_request", "small", &req.encode_to_vec());
    // Every job API call, its pick byte first (`rayfarm_fuzz::job_api_request`).
    let job_id = || "job-0001".to_string();
    let api: [(&str, Vec<u8>); 9] = [
        ("submit", req.encode_to_vec()),
        (
            "watch",
            proto::WatchJobRequest { job_id: job_id() }.encode_to_vec(),
        ),
        (
            "list",
            proto::ListJobsRequest {
                page_size: 20,
                page_token: "42".into(),
            }
            .encode_to_vec(),
        ),
        (
            "cancel",
            proto::CancelJobRequest { job_id: job_id() }.encode_to_vec(),
        ),
        (
            "fetch",
            proto::FetchResultRequest {
                job_id: job_id(),
                format: proto::ImageFormat::Png as i32,
            }
            .encode_to_vec(),
        ),
        (
            "fetch_stream",
            proto::FetchResultStreamRequest {
                job_id: job_id(),
                format: proto::ImageFormat::Png as i32,
                offset: 4096,
                chunk_bytes: 65536,
            }
            .encode_to_vec(),
        ),
        (
            "preview",
            proto::FetchPreviewRequest { job_id: job_id() }.encode_to_vec(),
        ),
        (
            "priority",
            proto::SetJobPriorityRequest {
                job_id: job_id(),
                priority: -3,
            }
            .encode_to_vec(),
        ),
        ("status", proto::GetClusterStatusRequest {}.encode_to_vec()),
    ];
    for (pick, (name, bytes)) in api.into_iter().enumerate() {
        let mut input = vec![pick as u8];
        input.extend_from_slice(&bytes);
        seed("job_api_request", name, &input);
    }
    let domain = proto::DomainRequest {
        protocol_version: proto::PROTOCOL_VERSION,
        sender: "worker-1".into(),
        job_id: job_id(),
        domain: 3,
        max_chunk_bytes: 1 << 20,
    };
    seed("domain_request", "current", &domain.encode_to_vec());
    let old = proto::DomainRequest {
        protocol_version: proto::PROTOCOL_VERSION - 1,
        max_chunk_bytes: 0,
        ..domain
    };
    seed("domain_request", "old_protocol", &old.encode_to_vec());

    let sums = tile_sums::encode(&[(0, [1, 2, 3]), (1, [0, 0, 0]), (5, [1 << 40, 7, -1])]);
    let results = proto::TileResults {
        job_id: "job-1".into(),
        results: vec![proto::TileResult {
            tile: 0,
            epoch: 1,
            credit: 3 << 20,
            sums,
        }],
        segments_traced: 12,
    };
    let msg = proto::WorkerMessage {
        body: Some(proto::worker_message::Body::TileResults(results)),
    };
    seed("worker_message", "tile_results", &msg.encode_to_vec());

    for (name, tier, batch) in [
        ("rays", proto::Tier::Migrated, wire::encode_batch(&rays)),
        (
            "verdicts",
            proto::Tier::Results,
            wire::encode_verdicts(&verdicts),
        ),
        (
            "volume_verdicts",
            proto::Tier::Results,
            wire::encode_verdicts(&volume_verdicts()),
        ),
    ] {
        let bundle = proto::PeerBundle {
            protocol_version: proto::PROTOCOL_VERSION,
            sender: "127.0.0.1:7001".into(),
            job_id: "job-1".into(),
            tier: tier as i32,
            sequence: 4,
            batches: vec![batch.into()],
        };
        seed("peer_bundle", name, &bundle.encode_to_vec());
    }
    // Volume verdicts: a shadowed segment, its light and the copy's closing count.
    let volume: Vec<VerdictRecord> = volume_verdicts();
    seed("verdict_batch", "volume", &wire::encode_verdicts(&volume));

    // A real volume scene's bricks (lit, with shadows) and transfer functions.
    let bricks = scene.join("bricks");
    let look = VolumeLook {
        transfer: TransferFunction::preset("density").unwrap(),
        shading: true,
        shadows: true,
        iso_surface: None,
    };
    let m = prepare_nbody_volume(&bricks, &options, 16, look).unwrap();
    for d in &m.domains {
        let bytes = std::fs::read(bricks.join(&d.file)).unwrap();
        seed("brick", &d.file, &bytes);
    }
    for name in PRESETS {
        let tf = TransferFunction::preset(name).unwrap();
        seed("transfer_function", name, tf.to_toml().unwrap().as_bytes());
    }
    std::fs::remove_dir_all(&scene).unwrap();
    println!("seed corpora written under fuzz/corpus/");
}

/// A fresh directory for the scene (no tempfile dependency for one directory).
fn tempdir() -> PathBuf {
    let dir = std::env::temp_dir().join(format!("rayfarm-fuzz-seeds-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}
