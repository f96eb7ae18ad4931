//! The manifest cap: every manifest prepare can write is read, and the cap follows from the
//! domain limit and the longest text one domain can add.

use super::*;
use crate::colour_map::ColourMap;
use crate::scene::partition::KdNode;
use crate::transfer::{ControlPoint, MAX_POINTS, TransferFunction};

/// An `f32` whose text is 3 bytes (`1.5`). No `f32`'s text is shorter (`0.0` is the
/// shortest), so a text with F floats is at most F x ([`MAX_F32_TEXT`] - 3) bytes longer with
/// other floats in it, whatever floats it has.
const SHORT: f32 = 1.5;

fn short3() -> [f32; 3] {
    [SHORT; 3]
}

/// A name of `len` bytes TOML writes as it is.
fn name(len: usize) -> String {
    "d".repeat(len)
}

/// A volume manifest of `domains` domains at their longest: names of [`MAX_FILE_NAME`] bytes,
/// 16-digit checksums, the largest integers, a value range and a surfaces file per brick, and
/// the longest head prepare writes (263 materials, 16 lights, a transfer function of
/// [`MAX_POINTS`] points, a name of 1 KiB). Floats are [`SHORT`]; [`floats`] counts them.
fn longest(domains: u32) -> Manifest {
    let bounds = Aabb {
        min: short3(),
        max: short3(),
    };
    // A chain: split 2i has leaf i below (node 2i + 1) and the next split above (2i + 2);
    // the last leaf ends it.
    let mut kd_nodes = Vec::new();
    for d in 0..domains - 1 {
        let at = 2 * d;
        kd_nodes.push(KdNode::Split {
            axis: 2,
            position: SHORT,
            below: at + 1,
            above: at + 2,
        });
        kd_nodes.push(KdNode::Leaf { domain: d });
    }
    kd_nodes.push(KdNode::Leaf {
        domain: domains - 1,
    });
    let entry = |_| DomainEntry {
        file: name(MAX_FILE_NAME),
        bounds,
        bytes: u64::MAX,
        triangles: u64::MAX,
        checksum: "f".repeat(MAX_CHECKSUM),
        values: Some([SHORT; 2]),
        surfaces: Some(SurfaceFile {
            file: name(MAX_FILE_NAME),
            checksum: "f".repeat(MAX_CHECKSUM),
        }),
    };
    let mut materials: Vec<Material> = (0..256)
        .map(|_| Material::Diffuse { albedo: short3() })
        .collect();
    materials.extend((0..6).map(|_| Material::Glossy {
        albedo: short3(),
        specular: SHORT,
        roughness: SHORT,
    }));
    materials.push(Material::Mapped {
        map: ColourMap::Terrain,
        axis: 2,
        range: [SHORT, SHORT + 1.0],
    });
    let lights = (0..16)
        .map(|_| Light::Quad {
            corner: short3(),
            edge_u: short3(),
            edge_v: short3(),
            emission: short3(),
        })
        .collect();
    // Values strictly increase; colours and opacities lie in [0, 1].
    let points = (0..MAX_POINTS)
        .map(|i| ControlPoint {
            value: i as f32,
            colour: [0.5; 3],
            opacity: 0.5,
        })
        .collect();
    Manifest {
        format: FORMAT_VERSION,
        name: name(1024),
        bounds,
        triangles: u64::MAX,
        ray_epsilon: SHORT,
        camera: Camera {
            eye: short3(),
            look_at: [SHORT, SHORT, SHORT + 1.0],
            up: [0.0, 1.0, 0.0],
            fov_y_degrees: SHORT,
        },
        sky: Sky {
            horizon: short3(),
            zenith: short3(),
        },
        materials,
        lights,
        kd_nodes,
        domains: (0..domains).map(entry).collect(),
        volume: Some(VolumeSpec {
            dims: [u32::MAX; 3],
            origin: short3(),
            spacing: short3(),
            step: SHORT,
            shading: true,
            shadows: true,
            transfer: TransferFunction { points },
        }),
    }
}

/// Floats in the manifest's text: those of one domain (entry and its two nodes) times
/// `domains`, plus the head's.
fn floats(m: &Manifest) -> (u64, u64) {
    let per_domain = 6 + 2 + 1;
    let v = m.volume.as_ref().expect("volume");
    let head = 6 // bounds
        + 1 // ray_epsilon
        + 10 // camera
        + 6 // sky
        + m.materials.iter().map(|m| match m {
            Material::Diffuse { .. } | Material::Mirror { .. } => 3,
            Material::Glossy { .. } => 5,
            Material::Mapped { .. } => 2,
        }).sum::<u64>()
        + 12 * m.lights.len() as u64
        + 3 + 3 + 1 + 5 * v.transfer.points.len() as u64;
    (per_domain, head)
}

fn text(m: &Manifest) -> u64 {
    toml::to_string_pretty(m).expect("serialises").len() as u64
}

#[test]
fn the_longest_manifest_prepare_can_write_fits_the_cap() {
    let slack = (MAX_F32_TEXT - 3) as u64;
    let sizes: Vec<u64> = (1..=3).map(|n| text(&longest(n))).collect();
    for n in 1..=3 {
        Manifest::parse(&toml::to_string_pretty(&longest(n)).unwrap())
            .unwrap_or_else(|e| panic!("{n} domains at their longest are legal: {e}"));
    }
    // Each domain adds the same text: an entry, a leaf and a split.
    let step = sizes[1] - sizes[0];
    assert_eq!(sizes[2] - sizes[1], step, "{sizes:?}");
    let (per_domain_floats, head_floats) = floats(&longest(1));
    let per_domain = step + per_domain_floats * slack;
    // One domain has no split: its text is the head's plus a domain's less a split's.
    let head = sizes[0] + head_floats * slack;
    assert!(
        per_domain <= MAX_DOMAIN_TEXT_BYTES,
        "a domain takes up to {per_domain} bytes"
    );
    assert!(
        head <= MAX_MANIFEST_HEAD_BYTES,
        "the head takes up to {head} bytes"
    );
    assert!(
        MAX_DOMAINS as u64 * per_domain + head <= MAX_MANIFEST_BYTES,
        "every manifest of up to {MAX_DOMAINS} domains fits the cap"
    );
    const { assert!(crate::prepare::brick_scene::MAX_BRICKS <= MAX_DOMAINS) };
    // The cap is not far above what it must hold.
    const { assert!(MAX_MANIFEST_BYTES < 64 << 20) };
}

#[test]
fn no_f32_is_longer_than_its_bound() {
    #[derive(serde::Serialize)]
    struct F {
        x: f32,
    }
    // `x = ` and a newline around the number.
    let len = |x: f32| toml::to_string(&F { x }).expect("serialises").len() - 5;
    let mut longest = 0;
    // Every exponent with mantissas spread over their range, both signs, and a stride
    // through all bit patterns.
    let patterns = (0..=255u32)
        .flat_map(|e| (0..1024u32).map(move |m| (e << 23) | (m * 8191 + m % 7)))
        .chain((0..u32::MAX / 8191).map(|i| i * 8191));
    for bits in patterns {
        for x in [
            f32::from_bits(bits & 0x7fff_ffff),
            -f32::from_bits(bits & 0x7fff_ffff),
        ] {
            if x.is_finite() {
                longest = longest.max(len(x));
            }
        }
    }
    assert!(longest <= MAX_F32_TEXT, "{longest}");
    assert!(len(-1.1754942e-38) >= 48, "the bound is not loose");
}

#[test]
fn a_manifest_over_the_domain_limit_or_with_odd_names_is_refused() {
    let ok = longest(2);
    let mut m = ok.clone();
    m.domains[0].file = name(MAX_FILE_NAME + 1);
    assert!(m.check().unwrap_err().contains("plain name"));
    let mut m = ok.clone();
    m.domains[1].surfaces.as_mut().unwrap().file = "a\"b".into();
    assert!(m.check().unwrap_err().contains("plain name"));
    let mut m = ok.clone();
    m.domains[0].checksum = "0".repeat(17);
    assert!(m.check().unwrap_err().contains("hex digits"));
    let mut m = ok.clone();
    m.kd_nodes.push(KdNode::Leaf { domain: 0 });
    assert!(m.check().unwrap_err().contains("2n - 1"));
    let mut m = ok;
    let extra = m.domains[0].clone();
    m.domains.resize(MAX_DOMAINS as usize + 1, extra);
    assert!(m.check().unwrap_err().contains("more than the"));
}

#[test]
fn a_manifest_of_the_most_domains_is_written_and_read_back() {
    // Over the old 4 MiB cap from about 12,000 domains (prepare's 32,768-domain nbody scene
    // wrote 11.7 MB and failed its own check).
    let dir = tempfile::tempdir().expect("tempdir");
    let m = longest(MAX_DOMAINS);
    m.save(dir.path()).expect("saved");
    let bytes = std::fs::metadata(dir.path().join(crate::scene::MANIFEST_FILE))
        .expect("written")
        .len();
    assert!(bytes > 4 << 20, "{bytes}");
    assert_eq!(Manifest::load(dir.path()).expect("read back"), m);
}
