//! The domain file: one little-endian blob laid out so that loading is `mmap` plus a cast.
//!
//! ```text
//! header (104 bytes)  magic, version, domain id, counts, bounds, checksum, section offsets
//! nodes               BvhNode (256 bytes, 8-wide) each
//! blocks              TriangleBlock (192 bytes: four triangles as structure-of-arrays, with
//!                     their scene-wide ids and materials) each, in BVH leaf order
//! normals             NormalBlock (144 bytes: the blocks' corner shading normals) per block,
//!                     or none: a smooth surface's (an isosurface's gradient), else empty
//! ```
//! The blocks are the only copy of the domain's triangles: traversal tests them, a hit names
//! a block and lane, shading reads that lane back (`Bvh::triangle`), and tools that need the
//! mesh list it from them (`Bvh::triangles`). Every section starts on a 64-byte boundary. The
//! checksum is xxh3-64 of the whole file with the checksum field zeroed, so a flipped bit
//! anywhere, header included, is caught.

use std::ops::Range;
use std::path::{Path, PathBuf};

use bytemuck::{Pod, Zeroable};

use super::residence::{Held, Received, Residence};
use super::{SceneError, check_domain_checksum, domain_checksum, write_domain_file};
use crate::bvh::{self, BvhNode};
use crate::geometry::{Aabb, BLOCK, NormalBlock, PackedTriangle, TriangleBlock};

/// First bytes of every domain file.
pub const MAGIC: [u8; 8] = *b"RFDOMAIN";
/// Layout version. 6: a section of corner shading normals per block (none for flat meshes);
/// 5: the blocks are the only copy of the triangles (4 also stored the mesh and a packed array
/// of every triangle; 3 had 4-wide nodes and no blocks).
pub const VERSION: u32 = 6;
/// Number of sections after the header.
const SECTIONS: usize = 3;
const ALIGN: u64 = 64;

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct Header {
    magic: [u8; 8],
    version: u32,
    domain: u32,
    /// Distinct triangles in the blocks (padding lanes not counted).
    triangle_count: u64,
    node_count: u64,
    block_count: u64,
    /// Normal blocks: zero, or `block_count`.
    normal_count: u64,
    bounds: Aabb,
    checksum: u64,
    /// Offsets of nodes, blocks, normals.
    offsets: [u64; SECTIONS],
}

const HEADER_BYTES: usize = std::mem::size_of::<Header>();
const _: () = assert!(HEADER_BYTES == 104);

/// A triangle handed to the domain writer.
#[derive(Clone, Copy, Debug)]
pub struct SourceTriangle {
    /// Its corners.
    pub vertices: [[f32; 3]; 3],
    /// Scene-wide id.
    pub id: u64,
    /// Material index.
    pub material: u32,
    /// Shading normals at the corners (unit, or zero for none), for a smooth surface; `None`
    /// shades by the facet normal. A domain stores them if any of its triangles has them.
    pub normals: Option<[[f32; 3]; 3]>,
}

/// What the manifest needs to know about a written domain file.
#[derive(Clone, Debug, PartialEq)]
pub struct DomainSummary {
    /// File size.
    pub bytes: u64,
    /// Triangles referenced.
    pub triangles: u64,
    /// xxh3-64 after the header.
    pub checksum: u64,
}

fn align(x: u64) -> u64 {
    x.div_ceil(ALIGN) * ALIGN
}

/// Builds the BVH and writes domain `domain` to `path` (through a temporary name).
pub fn write_domain(
    path: &Path,
    domain: u32,
    bounds: Aabb,
    triangles: &[SourceTriangle],
) -> Result<DomainSummary, SceneError> {
    let mut packed: Vec<PackedTriangle> = triangles
        .iter()
        .map(|t| PackedTriangle::new(&t.vertices, t.id, t.material))
        .collect();
    let bvh::Built { nodes, blocks } = bvh::build(&mut packed);
    drop(packed);
    let normals = normal_blocks(triangles, &blocks);
    let checked = bvh::validate(&nodes, &blocks).and_then(|_| {
        let held = distinct_triangles(&blocks);
        if held == triangles.len() as u64 {
            Ok(())
        } else {
            // Two triangles with one id: a lane would read as padding and be lost to tools.
            Err(format!(
                "{} triangles were given but the blocks hold {held} distinct ids",
                triangles.len()
            ))
        }
    });
    if let Err(reason) = checked {
        return Err(SceneError::Domain {
            path: path.into(),
            reason,
        });
    }

    let sections: [&[u8]; SECTIONS] = [
        bytemuck::cast_slice(&nodes),
        bytemuck::cast_slice(&blocks),
        bytemuck::cast_slice(&normals),
    ];
    let mut body = Vec::new();
    let mut offsets = [0u64; SECTIONS];
    for (k, s) in sections.iter().enumerate() {
        let at = align(HEADER_BYTES as u64 + body.len() as u64);
        body.resize((at - HEADER_BYTES as u64) as usize, 0);
        offsets[k] = at;
        body.extend_from_slice(s);
    }
    let mut header = Header {
        magic: MAGIC,
        version: VERSION,
        domain,
        triangle_count: triangles.len() as u64,
        node_count: nodes.len() as u64,
        block_count: blocks.len() as u64,
        normal_count: normals.len() as u64,
        bounds,
        checksum: 0,
        offsets,
    };
    let checksum = domain_checksum(bytemuck::bytes_of(&header), &body);
    header.checksum = checksum;
    write_domain_file(path, bytemuck::bytes_of(&header), &body)?;
    Ok(DomainSummary {
        bytes: (HEADER_BYTES + body.len()) as u64,
        triangles: triangles.len() as u64,
        checksum,
    })
}

/// The corner normals of `blocks` (built from `triangles`), lane by lane as the blocks hold
/// the triangles: one per block if any triangle has normals, else none.
fn normal_blocks(triangles: &[SourceTriangle], blocks: &[TriangleBlock]) -> Vec<NormalBlock> {
    if triangles.iter().all(|t| t.normals.is_none()) {
        return Vec::new();
    }
    let by_id: std::collections::HashMap<u64, [[f32; 3]; 3]> = triangles
        .iter()
        .filter_map(|t| t.normals.map(|n| (t.id, n)))
        .collect();
    blocks
        .iter()
        .map(|b| {
            let mut out = NormalBlock::zeroed();
            for lane in 0..BLOCK {
                if let Some(n) = by_id.get(&b.id(lane)) {
                    for (vertex, normal) in n.iter().enumerate() {
                        for (axis, &c) in normal.iter().enumerate() {
                            out.n[vertex][axis][lane] = c;
                        }
                    }
                }
            }
            out
        })
        .collect()
}

/// A mapped, checked domain file: a mesh domain, or a volume brick (`scene::brick`), whose
/// mesh sections are then empty; a brick of a scene with surfaces in its volume carries its
/// surfaces' mesh domain beside it ([`DomainData::surfaces`]).
pub struct DomainData {
    map: Held,
    path: PathBuf,
    domain: u32,
    bounds: Aabb,
    triangles: u64,
    sections: [Range<usize>; SECTIONS],
    brick: Option<super::brick::BrickLayout>,
    surfaces: Option<Box<DomainData>>,
}

impl std::fmt::Debug for DomainData {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DomainData")
            .field("path", &self.path)
            .field("domain", &self.domain)
            .field("bytes", &self.map.len())
            .field("residence", &self.residence())
            .finish()
    }
}

impl DomainData {
    /// Maps `path` and checks its structure; with `verify_checksum` also hashes the whole file
    /// against the manifest's `expected_checksum`. `materials` bounds every material index.
    pub fn open(
        path: &Path,
        expected_checksum: u64,
        verify_checksum: bool,
        materials: u32,
    ) -> Result<DomainData, SceneError> {
        Self::open_as(path, expected_checksum, verify_checksum, materials, None)
    }

    /// [`DomainData::open`], held in memory the way `residence` says, or as the process
    /// chooses ([`Residence::selected`]) if `None`. The same bytes, so the same images, either
    /// way; tests and benchmarks compare the two.
    pub fn open_as(
        path: &Path,
        expected_checksum: u64,
        verify_checksum: bool,
        materials: u32,
        residence: Option<Residence>,
    ) -> Result<DomainData, SceneError> {
        let (file, len) = super::open_regular(path, u64::MAX, "domain file")?;
        let residence = residence.unwrap_or_else(|| Residence::selected(len));
        let map = Held::load(file, len, residence).map_err(|e| SceneError::io(path, e))?;
        Self::from_map(map, path, expected_checksum, verify_checksum, materials)
    }

    /// How this domain's bytes are held: copied into huge pages, or mapped from the file.
    pub fn residence(&self) -> Residence {
        self.map.residence()
    }

    /// A domain file's bytes that arrived from elsewhere (a peer that had it loaded), checked
    /// exactly as a file opened from storage is, checksum always included: the same bytes
    /// give the same domain, anything else is refused. `origin` names where they came from
    /// in errors (never opened as a path).
    pub fn from_received(
        received: Received,
        origin: &Path,
        expected_checksum: u64,
        materials: u32,
    ) -> Result<DomainData, SceneError> {
        let map = received
            .into_held()
            .map_err(|e| SceneError::io(origin, e))?;
        Self::from_map(map, origin, expected_checksum, true, materials)
    }

    /// The bytes of this domain's own file (not its surfaces'), as read from storage: what
    /// a peer serves.
    pub fn file_bytes(&self) -> &[u8] {
        &self.map
    }

    fn from_map(
        map: Held,
        path: &Path,
        expected_checksum: u64,
        verify_checksum: bool,
        materials: u32,
    ) -> Result<DomainData, SceneError> {
        let bad = |reason: String| SceneError::Domain {
            path: path.into(),
            reason,
        };
        if super::brick::is_brick(&map) {
            let layout =
                super::brick::parse(&map, expected_checksum, verify_checksum).map_err(bad)?;
            return Ok(DomainData {
                path: path.into(),
                domain: layout.header.domain,
                bounds: Aabb::EMPTY,
                triangles: 0,
                sections: Default::default(),
                brick: Some(layout),
                surfaces: None,
                map,
            });
        }
        let header = parse_header(&map).map_err(bad)?;
        let sizes = [
            (header.node_count, std::mem::size_of::<BvhNode>() as u64),
            (
                header.block_count,
                std::mem::size_of::<TriangleBlock>() as u64,
            ),
            (
                header.normal_count,
                std::mem::size_of::<NormalBlock>() as u64,
            ),
        ];
        if header.normal_count != 0 && header.normal_count != header.block_count {
            return Err(bad(format!(
                "{} normal blocks for {} triangle blocks (zero or one each)",
                header.normal_count, header.block_count
            )));
        }
        let mut sections: [Range<usize>; SECTIONS] = Default::default();
        for (k, (count, size)) in sizes.iter().enumerate() {
            let start = header.offsets[k];
            let end = count
                .checked_mul(*size)
                .and_then(|n| n.checked_add(start))
                .filter(|&e| e <= map.len() as u64 && start >= HEADER_BYTES as u64)
                .ok_or_else(|| {
                    bad(format!(
                        "section {k} lies outside the {} byte file (truncated or corrupt)",
                        map.len()
                    ))
                })?;
            if start % ALIGN != 0 {
                return Err(bad(format!("section {k} is not {ALIGN}-byte aligned")));
            }
            sections[k] = start as usize..end as usize;
        }
        // The checksum after the layout: a file cut short is reported as truncated.
        let mut unsealed = header;
        unsealed.checksum = 0;
        check_domain_checksum(
            header.checksum,
            expected_checksum,
            verify_checksum,
            bytemuck::bytes_of(&unsealed),
            &map[HEADER_BYTES..],
        )
        .map_err(bad)?;
        let data = DomainData {
            path: path.into(),
            domain: header.domain,
            bounds: header.bounds,
            triangles: header.triangle_count,
            sections,
            map,
            brick: None,
            surfaces: None,
        };
        bvh::validate(data.nodes(), data.blocks()).map_err(bad)?;
        if let Some(i) = data
            .normals()
            .iter()
            .flat_map(|b| b.n.iter().flatten().flatten())
            .position(|c| !c.is_finite() || c.abs() > 1.0 + 1e-3)
        {
            return Err(bad(format!(
                "shading normal component {i} is not a unit vector's"
            )));
        }
        for b in data.blocks() {
            if let Some(lane) = (0..BLOCK).find(|&l| b.material[l] >= materials) {
                return Err(bad(format!(
                    "triangle {} names material {} of {materials}",
                    b.id(lane),
                    b.material[lane]
                )));
            }
        }
        let held = distinct_triangles(data.blocks());
        if held != header.triangle_count {
            return Err(bad(format!(
                "the header counts {} triangles, the blocks hold {held}",
                header.triangle_count
            )));
        }
        Ok(data)
    }

    fn section<T: Pod>(&self, k: usize) -> &[T] {
        // Offsets were checked in `open`: aligned to 64 within a page-aligned map, sizes exact.
        bytemuck::cast_slice(&self.map[self.sections[k].clone()])
    }

    /// The volume brick, if this domain is one.
    pub fn brick(&self) -> Option<super::brick::Brick<'_>> {
        self.brick.as_ref().map(|b| b.view(&self.map))
    }

    /// The domain id recorded in the file.
    pub fn domain(&self) -> u32 {
        self.domain
    }

    /// The domain's box.
    pub fn bounds(&self) -> Aabb {
        self.bounds
    }

    /// Size of the mappings: the domain's file, and its surfaces' file if it has one.
    pub fn bytes(&self) -> u64 {
        self.map.len() as u64 + self.surfaces.as_ref().map_or(0, |s| s.bytes())
    }

    /// Triangles the domain holds (distinct ones; a brick only those of its surfaces).
    pub fn triangle_count(&self) -> u64 {
        self.triangles + self.surfaces.as_ref().map_or(0, |s| s.triangle_count())
    }

    /// A brick's surfaces: the mesh domain of the triangles inside its box, if the scene has
    /// surfaces in its volume.
    pub fn surfaces(&self) -> Option<&DomainData> {
        self.surfaces.as_deref()
    }

    /// Gives this brick the mesh domain `surfaces` of the triangles inside its box; refused
    /// (naming the surfaces' file) unless this is a brick and `surfaces` a mesh domain of the
    /// same id.
    pub fn attach_surfaces(&mut self, surfaces: DomainData) -> Result<(), SceneError> {
        let reason = if self.brick.is_none() {
            Some("surfaces belong to a volume brick, not to a mesh domain".to_string())
        } else if surfaces.brick.is_some() {
            Some("is a volume brick where a brick's surfaces belong".to_string())
        } else if surfaces.domain != self.domain {
            Some(format!(
                "holds the surfaces of domain {}, not of brick {}",
                surfaces.domain, self.domain
            ))
        } else {
            None
        };
        if let Some(reason) = reason {
            return Err(SceneError::Domain {
                path: surfaces.path.clone(),
                reason,
            });
        }
        self.surfaces = Some(Box::new(surfaces));
        Ok(())
    }

    /// BVH nodes.
    pub fn nodes(&self) -> &[BvhNode] {
        self.section(0)
    }

    /// BVH leaf blocks: the domain's triangles.
    pub fn blocks(&self) -> &[TriangleBlock] {
        self.section(1)
    }

    /// Corner shading normals, one per block, or none (a flat mesh).
    pub fn normals(&self) -> &[NormalBlock] {
        self.section(2)
    }

    /// The BVH, nodes and leaf blocks (and the blocks' shading normals), for traversal and
    /// for reading triangles back.
    pub fn bvh(&self) -> bvh::Bvh<'_> {
        // Checked by `bvh::validate` (and the normals' count) when the file was opened.
        bvh::Bvh::trusted(self.nodes(), self.blocks(), self.normals())
    }
}

/// Triangles the blocks hold: every lane that is not a repeat of the lane before it.
fn distinct_triangles(blocks: &[TriangleBlock]) -> u64 {
    blocks
        .iter()
        .map(|b| (0..BLOCK).filter(|&l| !b.is_repeat(l)).count() as u64)
        .sum()
}

/// Writes into `bytes` (a domain file's contents) the checksum they should carry, as the
/// writer would have: tests and fuzzers that change a file use it to reach the checks behind
/// the checksum, as an attacker who writes the file could. Shorter than a header: unchanged.
pub fn seal(bytes: &mut [u8]) {
    if bytes.len() < HEADER_BYTES {
        return;
    }
    let mut header: Header = bytemuck::pod_read_unaligned(&bytes[..HEADER_BYTES]);
    header.checksum = 0;
    header.checksum = domain_checksum(bytemuck::bytes_of(&header), &bytes[HEADER_BYTES..]);
    bytes[..HEADER_BYTES].copy_from_slice(bytemuck::bytes_of(&header));
}

fn parse_header(bytes: &[u8]) -> Result<Header, String> {
    // Magic and version first: a file of another version may have another header size.
    if bytes.len() >= 12 {
        if bytes[..8] != MAGIC {
            return Err("not a rayfarm domain file (bad magic)".into());
        }
        let version = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
        if version != VERSION {
            return Err(format!(
                "domain file format version {version}, this build reads version {VERSION}: \
                 re-run `rayfarm prepare` for this scene"
            ));
        }
    }
    let Some(raw) = bytes.get(..HEADER_BYTES) else {
        return Err(format!(
            "{} bytes is shorter than the {HEADER_BYTES} byte header (truncated)",
            bytes.len()
        ));
    };
    let header: Header = bytemuck::pod_read_unaligned(raw);
    Ok(header)
}

/// Reads a domain file from bytes in memory (tests and fuzzing use this).
pub fn parse_domain_bytes(bytes: &[u8], materials: u32) -> Result<DomainData, SceneError> {
    let map = Held::copy_of(bytes).map_err(|e| SceneError::io("<memory>", e))?;
    // The checksum is still verified against the contents; only the manifest is absent.
    let checksum = match super::brick::recorded_checksum(bytes) {
        Some(c) if super::brick::is_brick(bytes) => c,
        _ => parse_header(bytes).map(|h| h.checksum).unwrap_or(0),
    };
    DomainData::from_map(map, Path::new("<memory>"), checksum, true, materials)
}
