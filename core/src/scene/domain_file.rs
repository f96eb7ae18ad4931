//! The domain file: one little-endian blob laid out so that loading is `mmap` plus a cast.
//!
//! ```text
//! header (128 bytes)  magic, version, domain id, counts, bounds, checksum, section offsets
//! vertices            [f32; 3] per vertex        (the domain's mesh, for tools and rebuilds)
//! indices             [u32; 3] per triangle
//! materials           u32 per triangle
//! ids                 u64 per triangle           (scene-wide triangle id)
//! nodes               BvhNode (256 bytes, 8-wide) each
//! blocks              TriangleBlock (192 bytes: four triangles as structure-of-arrays) each
//! packed              PackedTriangle (48 bytes) each, in BVH leaf order
//! ```
//! Every section starts on a 64-byte boundary. The checksum is xxh3-64 of the whole file with
//! the checksum field zeroed, so a flipped bit anywhere, header included, is caught.

use std::collections::HashMap;
use std::ops::Range;
use std::path::{Path, PathBuf};

use bytemuck::{Pod, Zeroable};
use memmap2::Mmap;

use super::{SceneError, check_domain_checksum, domain_checksum, write_domain_file};
use crate::bvh::{self, BvhNode};
use crate::geometry::{Aabb, PackedTriangle, TriangleBlock};

/// First bytes of every domain file.
pub const MAGIC: [u8; 8] = *b"RFDOMAIN";
/// Layout version. 4: 8-wide nodes and triangle blocks (3 had 4-wide nodes and no blocks).
pub const VERSION: u32 = 4;
/// Number of sections after the header.
const SECTIONS: usize = 7;
const ALIGN: u64 = 64;

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct Header {
    magic: [u8; 8],
    version: u32,
    domain: u32,
    vertex_count: u64,
    triangle_count: u64,
    node_count: u64,
    block_count: u64,
    packed_count: u64,
    bounds: Aabb,
    checksum: u64,
    /// Offsets of vertices, indices, materials, ids, nodes, blocks, packed.
    offsets: [u64; SECTIONS],
}

const HEADER_BYTES: usize = std::mem::size_of::<Header>();
const _: () = assert!(HEADER_BYTES == 144);

/// A triangle handed to the domain writer.
#[derive(Clone, Copy, Debug)]
pub struct SourceTriangle {
    /// Its corners.
    pub vertices: [[f32; 3]; 3],
    /// Scene-wide id.
    pub id: u64,
    /// Material index.
    pub material: u32,
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
    let mut vertices: Vec<[f32; 3]> = Vec::new();
    let mut index_of: HashMap<[u32; 3], u32> = HashMap::new();
    let mut indices = Vec::with_capacity(triangles.len());
    for t in triangles {
        indices.push(t.vertices.map(|v| {
            *index_of.entry(v.map(f32::to_bits)).or_insert_with(|| {
                vertices.push(v);
                vertices.len() as u32 - 1
            })
        }));
    }
    drop(index_of);
    let materials: Vec<u32> = triangles.iter().map(|t| t.material).collect();
    let ids: Vec<u64> = triangles.iter().map(|t| t.id).collect();
    let mut packed: Vec<PackedTriangle> = triangles
        .iter()
        .map(|t| PackedTriangle::new(&t.vertices, t.id, t.material))
        .collect();
    let bvh::Built { nodes, blocks } = bvh::build(&mut packed);
    if let Err(reason) = bvh::validate(&nodes, &blocks, packed.len()) {
        return Err(SceneError::Domain {
            path: path.into(),
            reason,
        });
    }

    let sections: [&[u8]; SECTIONS] = [
        bytemuck::cast_slice(&vertices),
        bytemuck::cast_slice(&indices),
        bytemuck::cast_slice(&materials),
        bytemuck::cast_slice(&ids),
        bytemuck::cast_slice(&nodes),
        bytemuck::cast_slice(&blocks),
        bytemuck::cast_slice(&packed),
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
        vertex_count: vertices.len() as u64,
        triangle_count: triangles.len() as u64,
        node_count: nodes.len() as u64,
        block_count: blocks.len() as u64,
        packed_count: packed.len() as u64,
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

/// A mapped, checked domain file: a mesh domain, or a volume brick (`crate::brick`), whose
/// mesh sections are then empty.
pub struct DomainData {
    map: Mmap,
    path: PathBuf,
    domain: u32,
    bounds: Aabb,
    sections: [Range<usize>; SECTIONS],
    brick: Option<crate::brick::BrickLayout>,
}

impl std::fmt::Debug for DomainData {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DomainData")
            .field("path", &self.path)
            .field("domain", &self.domain)
            .field("bytes", &self.map.len())
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
        let (file, _) = super::open_regular(path, u64::MAX, "domain file")?;
        // SAFETY: domain files are written once, then renamed into place and never modified;
        // a file changed under us is a broken deployment, and every value read is bounds-checked.
        let map = unsafe { Mmap::map(&file) }.map_err(|e| SceneError::io(path, e))?;
        Self::from_map(map, path, expected_checksum, verify_checksum, materials)
    }

    fn from_map(
        map: Mmap,
        path: &Path,
        expected_checksum: u64,
        verify_checksum: bool,
        materials: u32,
    ) -> Result<DomainData, SceneError> {
        let bad = |reason: String| SceneError::Domain {
            path: path.into(),
            reason,
        };
        if crate::brick::is_brick(&map) {
            let layout =
                crate::brick::parse(&map, expected_checksum, verify_checksum).map_err(bad)?;
            return Ok(DomainData {
                path: path.into(),
                domain: layout.header.domain,
                bounds: Aabb::EMPTY,
                sections: Default::default(),
                brick: Some(layout),
                map,
            });
        }
        let header = parse_header(&map).map_err(bad)?;
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
        let sizes = [
            (header.vertex_count, 12u64),
            (header.triangle_count, 12),
            (header.triangle_count, 4),
            (header.triangle_count, 8),
            (header.node_count, std::mem::size_of::<BvhNode>() as u64),
            (
                header.block_count,
                std::mem::size_of::<TriangleBlock>() as u64,
            ),
            (
                header.packed_count,
                std::mem::size_of::<PackedTriangle>() as u64,
            ),
        ];
        let mut sections: [Range<usize>; SECTIONS] = Default::default();
        for (k, (count, size)) in sizes.iter().enumerate() {
            let start = header.offsets[k];
            let end = count
                .checked_mul(*size)
                .and_then(|n| n.checked_add(start))
                .filter(|&e| e <= map.len() as u64 && start >= HEADER_BYTES as u64)
                .ok_or_else(|| {
                    bad(format!(
                        "section {k} lies outside the {} byte file",
                        map.len()
                    ))
                })?;
            if start % ALIGN != 0 {
                return Err(bad(format!("section {k} is not {ALIGN}-byte aligned")));
            }
            sections[k] = start as usize..end as usize;
        }
        let data = DomainData {
            path: path.into(),
            domain: header.domain,
            bounds: header.bounds,
            sections,
            map,
            brick: None,
        };
        bvh::validate(data.nodes(), data.blocks(), data.packed().len()).map_err(bad)?;
        if let Some(t) = data.packed().iter().find(|t| t.material >= materials) {
            return Err(bad(format!(
                "triangle {} names material {} of {materials}",
                t.id(),
                t.material
            )));
        }
        Ok(data)
    }

    fn section<T: Pod>(&self, k: usize) -> &[T] {
        // Offsets were checked in `open`: aligned to 64 within a page-aligned map, sizes exact.
        bytemuck::cast_slice(&self.map[self.sections[k].clone()])
    }

    /// The volume brick, if this domain is one.
    pub fn brick(&self) -> Option<crate::brick::Brick<'_>> {
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

    /// Size of the mapping.
    pub fn bytes(&self) -> u64 {
        self.map.len() as u64
    }

    /// Mesh vertices.
    pub fn vertices(&self) -> &[[f32; 3]] {
        self.section(0)
    }

    /// Mesh triangles as vertex indices.
    pub fn indices(&self) -> &[[u32; 3]] {
        self.section(1)
    }

    /// Material per mesh triangle.
    pub fn materials(&self) -> &[u32] {
        self.section(2)
    }

    /// Scene-wide id per mesh triangle.
    pub fn ids(&self) -> &[u64] {
        self.section(3)
    }

    /// BVH nodes.
    pub fn nodes(&self) -> &[BvhNode] {
        self.section(4)
    }

    /// BVH leaf blocks.
    pub fn blocks(&self) -> &[TriangleBlock] {
        self.section(5)
    }

    /// The BVH, nodes and leaf blocks, for traversal.
    pub fn bvh(&self) -> bvh::Bvh<'_> {
        // Checked by `bvh::validate` when the file was opened.
        bvh::Bvh::trusted(self.nodes(), self.blocks())
    }

    /// Triangles in BVH leaf order.
    pub fn packed(&self) -> &[PackedTriangle] {
        self.section(6)
    }
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
    let mut map = memmap2::MmapMut::map_anon(bytes.len().max(1))
        .map_err(|e| SceneError::io("<memory>", e))?;
    map[..bytes.len()].copy_from_slice(bytes);
    let map = map
        .make_read_only()
        .map_err(|e| SceneError::io("<memory>", e))?;
    // The checksum is still verified against the contents; only the manifest is absent.
    let checksum = match crate::brick::recorded_checksum(bytes) {
        Some(c) if crate::brick::is_brick(bytes) => c,
        _ => parse_header(bytes).map(|h| h.checksum).unwrap_or(0),
    };
    DomainData::from_map(map, Path::new("<memory>"), checksum, true, materials)
}
