//! Fuzzing the scene manifest parser: garbage, and a valid manifest broken by byte edits,
//! truncation, line splices and awkward values put in place of its numbers and names (so
//! inputs parse as TOML and reach the checks). Properties: no panic, memory in proportion to
//! the text, every accepted manifest is self-consistent and round-trips, and every error has a
//! message. Also: a manifest that lies about a domain's size, triangle count or checksum is
//! refused when the domain is opened, naming the file and the lie.
//!
//! `PROPTEST_CASES=N cargo test --release -p rayfarm-common --test manifest_fuzz -- --nocapture`

mod fuzz_support;

use std::sync::OnceLock;

use proptest::prelude::*;
use rayfarm_core::geometry::Aabb;
use rayfarm_core::scene::domain_file::SourceTriangle;
use rayfarm_core::scene::{
    Camera, DomainEntry, KdNode, Light, Manifest, Material, SceneError, Sky, write_domain,
};

const DEFAULT_CASES: u32 = 2000;

/// A two-domain scene written to a temporary directory, and its manifest's text.
struct Scene {
    dir: tempfile::TempDir,
    manifest: Manifest,
    text: String,
}

fn scene() -> &'static Scene {
    static SCENE: OnceLock<Scene> = OnceLock::new();
    SCENE.get_or_init(write_scene)
}

fn write_scene() -> Scene {
    let dir = tempfile::tempdir().unwrap();
    let bounds = Aabb {
        min: [0.0; 3],
        max: [2.0, 1.0, 1.0],
    };
    let halves = [
        Aabb {
            min: [0.0; 3],
            max: [1.0, 1.0, 1.0],
        },
        Aabb {
            min: [1.0, 0.0, 0.0],
            max: [2.0, 1.0, 1.0],
        },
    ];
    let mut domains = Vec::new();
    for (d, b) in halves.iter().enumerate() {
        let tris: Vec<SourceTriangle> = (0..20 + 10 * d as u64)
            .map(|i| {
                let x = b.min[0] + 0.04 * i as f32;
                SourceTriangle {
                    vertices: [[x, 0.1, 0.1], [x + 0.03, 0.9, 0.1], [x, 0.1, 0.9]],
                    id: 100 * d as u64 + i,
                    material: (i % 3) as u32,
                    normals: None,
                }
            })
            .collect();
        let file = format!("d{d}.rfd");
        let summary = write_domain(&dir.path().join(&file), d as u32, *b, &tris).unwrap();
        domains.push(DomainEntry {
            file,
            bounds: *b,
            bytes: summary.bytes,
            triangles: summary.triangles,
            checksum: format!("{:016x}", summary.checksum),
            values: None,
            surfaces: None,
        });
    }
    let manifest = Manifest {
        format: rayfarm_core::scene::manifest::FORMAT_VERSION,
        name: "fuzz".into(),
        bounds,
        triangles: 50,
        ray_epsilon: 1e-4,
        camera: Camera {
            eye: [1.0, 0.5, -3.0],
            look_at: [1.0, 0.5, 0.5],
            up: [0.0, 1.0, 0.0],
            fov_y_degrees: 40.0,
        },
        sky: Sky {
            horizon: [0.5, 0.6, 0.7],
            zenith: [0.1, 0.2, 0.4],
        },
        materials: vec![
            Material::Diffuse {
                albedo: [0.7, 0.7, 0.7],
            },
            Material::Mirror {
                tint: [0.9, 0.9, 0.9],
            },
            Material::Glossy {
                albedo: [0.2, 0.3, 0.4],
                specular: 0.5,
                roughness: 0.1,
            },
        ],
        lights: vec![
            Light::Directional {
                direction: [0.3, 1.0, -0.2],
                radiance: [2.0, 2.0, 2.0],
            },
            Light::Quad {
                corner: [0.5, 2.0, 0.5],
                edge_u: [1.0, 0.0, 0.0],
                edge_v: [0.0, 0.0, 1.0],
                emission: [5.0, 5.0, 5.0],
            },
        ],
        kd_nodes: vec![
            KdNode::Split {
                axis: 0,
                position: 1.0,
                below: 1,
                above: 2,
            },
            KdNode::Leaf { domain: 0 },
            KdNode::Leaf { domain: 1 },
        ],
        domains,
        volume: None,
    };
    manifest.save(dir.path()).unwrap();
    let text = std::fs::read_to_string(dir.path().join("scene.toml")).unwrap();
    Scene {
        dir,
        manifest,
        text,
    }
}

/// Values that TOML accepts but a manifest may not, or that sit at the edges of a type.
const AWKWARD: [&str; 24] = [
    "nan",
    "inf",
    "-inf",
    "-1",
    "0",
    "1",
    "2",
    "3",
    "180.0",
    "1e39",
    "-0.0",
    "4294967295",
    "4294967296",
    "18446744073709551615",
    "9223372036854775807",
    "\"\"",
    "\"../scene.toml\"",
    "\"a/b\"",
    "\"zz\"",
    "\"ffffffffffffffffff\"",
    "\"leaf\"",
    "\"split\"",
    "[]",
    "[1.0, 2.0]",
];

/// The properties every input must satisfy.
fn check_any(text: &str) -> Result<(), TestCaseError> {
    let (parsed, peak) = fuzz_support::peak_bytes(|| Manifest::parse(text));
    prop_assert!(
        peak <= 64 * text.len() + (256 << 10),
        "{peak} bytes for {} bytes of text",
        text.len()
    );
    match parsed {
        Ok(m) => {
            // What the checks promise the renderer.
            prop_assert!(!m.domains.is_empty() && !m.materials.is_empty());
            prop_assert!(m.camera.check().is_ok());
            prop_assert!(m.ray_epsilon.is_finite() && m.ray_epsilon >= 0.0);
            for d in &m.domains {
                prop_assert!(!d.file.is_empty() && !d.file.contains('/') && !d.file.contains(".."));
                prop_assert!(u64::from_str_radix(&d.checksum, 16).is_ok());
            }
            let boxes = m.domain_tree().domain_boxes(m.domains.len());
            prop_assert_eq!(boxes.len(), m.domains.len());
            let again = toml::to_string_pretty(&m).unwrap();
            prop_assert_eq!(Manifest::parse(&again), Ok(m));
        }
        Err(e) => prop_assert!(!e.is_empty()),
    }
    Ok(())
}

#[test]
fn the_valid_manifest_parses_and_round_trips() {
    let s = scene();
    assert_eq!(Manifest::parse(&s.text), Ok(s.manifest.clone()));
    assert_eq!(Manifest::load(s.dir.path()).unwrap(), s.manifest);
    s.manifest.check_domains(s.dir.path(), true).unwrap();
}

#[test]
fn garbage() {
    fuzz_support::check(
        file!(),
        "manifest garbage",
        DEFAULT_CASES,
        prop::collection::vec(any::<u8>(), 0..2048),
        |bytes| check_any(&String::from_utf8_lossy(&bytes)),
    );
}

#[test]
fn byte_edits_and_truncation() {
    let edit = (
        any::<usize>(),
        prop::sample::select(b"0123456789 \n\"[]{}=.,-_x#".to_vec()),
    );
    let input = (
        prop::collection::vec(edit, 0..6),
        any::<usize>(),
        any::<bool>(),
    );
    fuzz_support::check(
        file!(),
        "manifest byte edits",
        DEFAULT_CASES,
        input,
        |(edits, cut, do_cut)| {
            let mut bytes = scene().text.clone().into_bytes();
            for (at, v) in edits {
                let at = at % bytes.len();
                bytes[at] = v;
            }
            if do_cut {
                bytes.truncate(cut % (bytes.len() + 1));
            }
            check_any(&String::from_utf8_lossy(&bytes))
        },
    );
}

#[test]
fn line_splices() {
    let op = (any::<usize>(), any::<usize>(), 0u8..3);
    fuzz_support::check(
        file!(),
        "manifest line splices",
        DEFAULT_CASES,
        prop::collection::vec(op, 1..6),
        |ops| {
            let mut lines: Vec<&str> = scene().text.lines().collect();
            for (i, j, kind) in ops {
                if lines.is_empty() {
                    break;
                }
                let (i, j) = (i % lines.len(), j % lines.len());
                match kind {
                    0 => lines.swap(i, j),
                    1 => {
                        lines.remove(i);
                    }
                    _ => {
                        let l = lines[i];
                        lines.insert(j, l);
                    }
                }
            }
            check_any(&lines.join("\n"))
        },
    );
}

/// Replaces the value of random `key = value` lines with awkward ones; the text stays TOML, so
/// this reaches the manifest's own checks (and serde's type checks) rather than the lexer.
#[test]
fn awkward_values() {
    let op = (any::<usize>(), prop::sample::select(AWKWARD.to_vec()));
    fuzz_support::check(
        file!(),
        "manifest awkward values",
        DEFAULT_CASES,
        prop::collection::vec(op, 1..4),
        |ops| {
            let mut lines: Vec<String> = scene().text.lines().map(str::to_owned).collect();
            let assignments: Vec<usize> = (0..lines.len())
                .filter(|&i| lines[i].contains(" = "))
                .collect();
            for (i, value) in ops {
                let at = assignments[i % assignments.len()];
                let key = lines[at].split(" = ").next().unwrap_or_default().to_owned();
                lines[at] = format!("{key} = {value}");
            }
            check_any(&lines.join("\n"))
        },
    );
}

/// How a lie changes a domain's entry.
type Lie = fn(&mut DomainEntry);

/// Each lie is caught when the domain is opened, and the message names the file and the lie.
#[test]
fn a_manifest_lying_about_a_domain_is_refused_when_it_is_opened() {
    let s = scene();
    let dir = s.dir.path();
    let lies: [(&str, Lie); 5] = [
        ("bytes", |d| d.bytes += 64),
        ("triangles", |d| d.triangles += 1),
        ("triangles", |d| d.triangles = u64::MAX),
        ("checksum", |d| d.checksum = "0123456789abcdef".into()),
        ("d1.rfd", |d| d.file = "d1.rfd".into()),
    ];
    for (what, lie) in lies {
        let mut m = s.manifest.clone();
        lie(&mut m.domains[0]);
        let err = m.open_domain(dir, 0, true).unwrap_err();
        assert!(matches!(err, SceneError::Domain { .. }), "{what}: {err:?}");
        let msg = err.to_string();
        assert!(msg.contains("bad domain file"), "{what}: {msg}");
        assert!(
            msg.contains(what) || msg.contains("holds domain"),
            "{what}: {msg}"
        );
        // The other domain is unaffected.
        m.open_domain(dir, 1, true).unwrap();
    }
    let mut m = s.manifest.clone();
    m.domains[1].file = "missing.rfd".into();
    let err = m.open_domain(dir, 1, false).unwrap_err();
    assert!(matches!(err, SceneError::Io { .. }) && err.to_string().contains("missing.rfd"));
}

/// Random lies about a domain's size and triangle count: accepted only if they are the truth.
#[test]
fn random_lies_about_sizes() {
    let input = (0usize..2, any::<u64>(), any::<u64>(), 0u8..4);
    fuzz_support::check(
        file!(),
        "manifest size lies",
        DEFAULT_CASES / 4,
        input,
        |(d, bytes, tris, which)| {
            let s = scene();
            let mut m = s.manifest.clone();
            let truth = m.domains[d].clone();
            let small = |x: u64, t: u64| {
                if x.is_multiple_of(2) {
                    t.wrapping_add(x % 7).wrapping_sub(3)
                } else {
                    x
                }
            };
            if which & 1 != 0 {
                m.domains[d].bytes = small(bytes, truth.bytes);
            }
            if which & 2 != 0 {
                m.domains[d].triangles = small(tris, truth.triangles);
            }
            let honest = m.domains[d] == truth;
            let opened = m.open_domain(s.dir.path(), d as u32, false);
            prop_assert_eq!(opened.is_ok(), honest, "{:?}", opened.err());
            Ok(())
        },
    );
}

/// Values TOML reads but a renderer cannot use are refused by the checks, not later.
#[test]
fn non_finite_materials_and_sky_are_refused() {
    let text = &scene().text;
    for (from, to) in [
        ("horizon = [\n    0.5,", "horizon = [\n    nan,"),
        ("specular = 0.5", "specular = inf"),
        ("roughness = 0.1", "roughness = nan"),
    ] {
        assert!(text.contains(from), "{from} not in\n{text}");
        let err = Manifest::parse(&text.replacen(from, to, 1)).unwrap_err();
        assert!(err.contains("non-finite"), "{err}");
    }
}
