//! Volume bricks: a volume domain's file, laid out like a mesh domain file so that loading is
//! `mmap` plus a cast (`scene::domain_file` maps both kinds and tells them by their magic).
//!
//! ```text
//! header (128 bytes)  magic, version, domain id, the volume's dims, the stored voxel box,
//!                     the owned cell box, the sub-block grid, the value range, checksum,
//!                     section offsets
//! voxels              f32 per stored voxel, x fastest, then y, then z
//! ranges              [min, max] f32 per sub-block of owned cells, x fastest
//! ```
//! A brick owns the cells `cells_lo..cells_hi` of the volume (cell `i` lies between voxels `i`
//! and `i + 1`) and stores their voxels plus [`GHOST`] voxels on every side (fewer at the
//! volume's faces): trilinear interpolation anywhere in its box, with a cell of rounding slack
//! and a central-difference gradient, reads only voxels it holds, so the value at a point is
//! the same bits whichever brick computes it. Each sub-block of `block` cells keeps the range
//! of its cells' voxels, so that the kernel can skip sub-blocks the transfer function makes
//! transparent. Every section starts on a 64-byte boundary; the checksum is xxh3-64 of the file
//! with its checksum field zero.

use std::ops::Range;
use std::path::Path;

use bytemuck::{Pod, Zeroable};

use super::{SceneError, check_domain_checksum, domain_checksum, write_domain_file};
use crate::isosurface::Lattice;

/// First bytes of every brick file.
pub const MAGIC: [u8; 8] = *b"RFBRICK\0";
/// Layout version.
pub const VERSION: u32 = 1;
/// Voxels stored beyond the owned cells on every side (where the volume has them): one for
/// the far corner of a cell, one of rounding slack, one for the gradient's central difference.
pub const GHOST: u32 = 3;
/// Edge of a sub-block in cells.
pub const BLOCK: u32 = 8;
const ALIGN: u64 = 64;

/// The brick header.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct BrickHeader {
    magic: [u8; 8],
    version: u32,
    /// Domain id.
    pub domain: u32,
    /// Voxels of the whole volume along x, y, z.
    pub volume_dims: [u32; 3],
    /// Global index of the first stored voxel.
    pub stored_lo: [u32; 3],
    /// Stored voxels along x, y, z.
    pub stored_dims: [u32; 3],
    /// First owned cell.
    pub cells_lo: [u32; 3],
    /// One past the last owned cell.
    pub cells_hi: [u32; 3],
    /// Sub-block edge in cells.
    pub block: u32,
    /// Sub-blocks along x, y, z.
    pub blocks: [u32; 3],
    /// Smallest voxel value of the owned cells and one cell around them.
    pub value_min: f32,
    /// Largest such value.
    pub value_max: f32,
    _pad: u32,
    checksum: u64,
    voxels_offset: u64,
    ranges_offset: u64,
}

const HEADER_BYTES: usize = std::mem::size_of::<BrickHeader>();
const _: () = assert!(HEADER_BYTES == 128);

/// What the manifest records of a written brick.
#[derive(Clone, Debug, PartialEq)]
pub struct BrickSummary {
    /// File size.
    pub bytes: u64,
    /// Checksum.
    pub checksum: u64,
    /// Value range of the owned cells' voxels and one cell around them.
    pub values: [f32; 2],
}

/// Where a mapped brick's sections are (checked when it was opened).
#[derive(Clone, Debug)]
pub struct BrickLayout {
    /// The header.
    pub header: BrickHeader,
    voxels: Range<usize>,
    ranges: Range<usize>,
}

/// A mapped brick: its header, voxels and sub-block ranges.
#[derive(Clone, Copy, Debug)]
pub struct Brick<'a> {
    /// The header.
    pub header: &'a BrickHeader,
    voxels: &'a [f32],
    ranges: &'a [[f32; 2]],
}

fn align(x: u64) -> u64 {
    x.div_ceil(ALIGN) * ALIGN
}

fn count(d: [u32; 3]) -> u64 {
    d.iter().map(|&x| u64::from(x)).product()
}

/// Writes the brick owning cells `cells_lo..cells_hi` of `volume` (`volume_dims` voxels) to
/// `path` through a temporary name. Values are read from `volume` voxel by voxel, so a volume
/// larger than memory is read one brick at a time; a non-finite value is refused, naming it.
pub fn write_brick(
    path: &Path,
    domain: u32,
    volume: &impl Lattice,
    volume_dims: [u32; 3],
    cells_lo: [u32; 3],
    cells_hi: [u32; 3],
) -> Result<BrickSummary, SceneError> {
    let bad = |reason: String| SceneError::Domain {
        path: path.into(),
        reason,
    };
    let mut stored_lo = [0u32; 3];
    let mut stored_dims = [0u32; 3];
    let mut blocks = [0u32; 3];
    for a in 0..3 {
        if !(cells_lo[a] < cells_hi[a] && cells_hi[a] < volume_dims[a]) {
            return Err(bad(format!(
                "axis {a}: cells {cells_lo:?}..{cells_hi:?} are not inside the volume"
            )));
        }
        stored_lo[a] = cells_lo[a].saturating_sub(GHOST);
        let hi = (cells_hi[a] + 1 + GHOST).min(volume_dims[a]);
        stored_dims[a] = hi - stored_lo[a];
        blocks[a] = (cells_hi[a] - cells_lo[a]).div_ceil(BLOCK);
    }
    let [sx, sy, _] = stored_dims;
    let mut voxels = Vec::with_capacity(count(stored_dims) as usize);
    for k in 0..stored_dims[2] {
        for j in 0..stored_dims[1] {
            for i in 0..stored_dims[0] {
                let g = [stored_lo[0] + i, stored_lo[1] + j, stored_lo[2] + k];
                let v = volume.value(g[0], g[1], g[2]);
                if !v.is_finite() {
                    return Err(bad(format!(
                        "voxel {g:?} of the volume is not finite ({v})"
                    )));
                }
                voxels.push(v);
            }
        }
    }
    let at = |g: [u32; 3]| {
        let l = [
            g[0] - stored_lo[0],
            g[1] - stored_lo[1],
            g[2] - stored_lo[2],
        ];
        voxels[l[0] as usize + sx as usize * (l[1] as usize + sy as usize * l[2] as usize)]
    };
    // The range of the voxels of cells `lo..hi` (voxels `lo..=hi`), clamped to those stored.
    let range_of = |lo: [u32; 3], hi: [u32; 3]| {
        let (mut min, mut max) = (f32::INFINITY, f32::NEG_INFINITY);
        let last = |a: usize| stored_lo[a] + stored_dims[a] - 1;
        for k in lo[2].max(stored_lo[2])..=hi[2].min(last(2)) {
            for j in lo[1].max(stored_lo[1])..=hi[1].min(last(1)) {
                for i in lo[0].max(stored_lo[0])..=hi[0].min(last(0)) {
                    let v = at([i, j, k]);
                    min = min.min(v);
                    max = max.max(v);
                }
            }
        }
        [min, max]
    };
    let mut ranges = Vec::with_capacity(count(blocks) as usize);
    for bk in 0..blocks[2] {
        for bj in 0..blocks[1] {
            for bi in 0..blocks[0] {
                let b = [bi, bj, bk];
                let lo: [u32; 3] = std::array::from_fn(|a| cells_lo[a] + b[a] * BLOCK);
                let hi: [u32; 3] = std::array::from_fn(|a| (lo[a] + BLOCK).min(cells_hi[a]));
                ranges.push(range_of(lo, hi));
            }
        }
    }
    // One cell of slack around the owned cells: a sample on the brick's face may round into
    // its neighbour's cell.
    let values = range_of(
        cells_lo.map(|c| c.saturating_sub(1)),
        cells_hi.map(|c| c + 1),
    );

    let voxels_offset = align(HEADER_BYTES as u64);
    let ranges_offset = align(voxels_offset + 4 * voxels.len() as u64);
    let mut header = BrickHeader {
        magic: MAGIC,
        version: VERSION,
        domain,
        volume_dims,
        stored_lo,
        stored_dims,
        cells_lo,
        cells_hi,
        block: BLOCK,
        blocks,
        value_min: values[0],
        value_max: values[1],
        _pad: 0,
        checksum: 0,
        voxels_offset,
        ranges_offset,
    };
    let mut body = vec![0u8; (voxels_offset as usize) - HEADER_BYTES];
    body.extend_from_slice(bytemuck::cast_slice(&voxels));
    body.resize(ranges_offset as usize - HEADER_BYTES, 0);
    body.extend_from_slice(bytemuck::cast_slice(&ranges));
    header.checksum = domain_checksum(bytemuck::bytes_of(&header), &body);
    write_domain_file(path, bytemuck::bytes_of(&header), &body)?;
    Ok(BrickSummary {
        bytes: (HEADER_BYTES + body.len()) as u64,
        checksum: header.checksum,
        values,
    })
}

/// Whether `bytes` begin like a brick file.
pub fn is_brick(bytes: &[u8]) -> bool {
    bytes.starts_with(&MAGIC)
}

/// The checksum recorded in a brick's header, if it has one.
pub fn recorded_checksum(bytes: &[u8]) -> Option<u64> {
    let raw = bytes.get(..HEADER_BYTES)?;
    Some(bytemuck::pod_read_unaligned::<BrickHeader>(raw).checksum)
}

/// Writes into `bytes` (a brick file) the checksum it should carry, as the writer would:
/// tests and fuzzers that change a brick use it to reach the checks behind the checksum.
pub fn seal(bytes: &mut [u8]) {
    if bytes.len() < HEADER_BYTES {
        return;
    }
    let mut h: BrickHeader = bytemuck::pod_read_unaligned(&bytes[..HEADER_BYTES]);
    h.checksum = 0;
    h.checksum = domain_checksum(bytemuck::bytes_of(&h), &bytes[HEADER_BYTES..]);
    bytes[..HEADER_BYTES].copy_from_slice(bytemuck::bytes_of(&h));
}

/// Checks a brick file's bytes (a page-aligned map): header, sizes, offsets and, with
/// `verify_checksum`, the checksum against `expected_checksum`. Returns where its sections are.
pub fn parse(
    bytes: &[u8],
    expected_checksum: u64,
    verify_checksum: bool,
) -> Result<BrickLayout, String> {
    if bytes.len() >= 12 {
        let version = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
        if version != VERSION {
            return Err(format!(
                "brick format version {version}, this build reads version {VERSION}: re-run \
                 `rayfarm prepare` for this scene"
            ));
        }
    }
    let raw = bytes.get(..HEADER_BYTES).ok_or_else(|| {
        format!(
            "{} bytes is shorter than the {HEADER_BYTES} byte brick header (truncated)",
            bytes.len()
        )
    })?;
    let h: BrickHeader = bytemuck::pod_read_unaligned(raw);
    if h.magic != MAGIC {
        return Err("not a rayfarm brick file (bad magic)".into());
    }
    let mut unsealed = h;
    unsealed.checksum = 0;
    check_domain_checksum(
        h.checksum,
        expected_checksum,
        verify_checksum,
        bytemuck::bytes_of(&unsealed),
        &bytes[HEADER_BYTES..],
    )?;
    if h._pad != 0 {
        return Err("reserved header bytes are not zero".into());
    }
    for a in 0..3 {
        let v = h.volume_dims[a];
        let ok = h.cells_lo[a] < h.cells_hi[a]
            && h.cells_hi[a] < v
            && h.stored_lo[a] == h.cells_lo[a].saturating_sub(GHOST)
            && u64::from(h.stored_lo[a]) + u64::from(h.stored_dims[a])
                == u64::from((h.cells_hi[a] + 1).saturating_add(GHOST).min(v))
            && h.block == BLOCK
            && h.blocks[a] == (h.cells_hi[a] - h.cells_lo[a]).div_ceil(BLOCK);
        if !ok {
            return Err(format!(
                "axis {a}: the stored box, owned cells and sub-blocks do not fit the volume"
            ));
        }
    }
    if !(h.value_min.is_finite() && h.value_max.is_finite() && h.value_min <= h.value_max) {
        return Err("value range is not finite or not ordered".into());
    }
    let section = |offset: u64, items: u64, size: u64, what: &str| {
        let end = items
            .checked_mul(size)
            .and_then(|n| n.checked_add(offset))
            .filter(|&e| e <= bytes.len() as u64 && offset >= HEADER_BYTES as u64)
            .ok_or_else(|| format!("{what} lie outside the {} byte file", bytes.len()))?;
        if !offset.is_multiple_of(ALIGN) {
            return Err(format!("{what} are not {ALIGN}-byte aligned"));
        }
        Ok(offset as usize..end as usize)
    };
    let voxels = section(h.voxels_offset, count(h.stored_dims), 4, "voxels")?;
    let ranges = section(h.ranges_offset, count(h.blocks), 8, "sub-block ranges")?;
    let layout = BrickLayout {
        header: h,
        voxels,
        ranges,
    };
    let brick = layout.view(bytes);
    if !brick.voxels.iter().all(|v| v.is_finite()) {
        return Err("a voxel is not finite".into());
    }
    if !brick
        .ranges
        .iter()
        .all(|r| r[0].is_finite() && r[1].is_finite() && r[0] <= r[1])
    {
        return Err("a sub-block range is not finite or not ordered".into());
    }
    Ok(layout)
}

impl BrickLayout {
    /// The brick in `bytes`, the map this layout was parsed from (64-byte aligned sections).
    pub fn view<'a>(&'a self, bytes: &'a [u8]) -> Brick<'a> {
        Brick {
            header: &self.header,
            voxels: bytemuck::cast_slice(&bytes[self.voxels.clone()]),
            ranges: bytemuck::cast_slice(&bytes[self.ranges.clone()]),
        }
    }
}

impl Brick<'_> {
    /// The voxel at global index `g`, clamped into the stored box (a point more than a cell
    /// outside the brick's box never reaches here: its domain would be another).
    #[inline]
    pub fn voxel(&self, g: [u32; 3]) -> f32 {
        let h = self.header;
        let l: [usize; 3] = std::array::from_fn(|a| {
            (g[a].saturating_sub(h.stored_lo[a])).min(h.stored_dims[a] - 1) as usize
        });
        let (sx, sy) = (h.stored_dims[0] as usize, h.stored_dims[1] as usize);
        self.voxels[l[0] + sx * (l[1] + sy * l[2])]
    }

    /// The sub-block holding owned cell `c`, or `None` for a cell the brick does not own.
    #[inline]
    pub fn block_of(&self, c: [u32; 3]) -> Option<usize> {
        let h = self.header;
        let mut b = [0usize; 3];
        for a in 0..3 {
            if c[a] < h.cells_lo[a] || c[a] >= h.cells_hi[a] {
                return None;
            }
            b[a] = ((c[a] - h.cells_lo[a]) / h.block) as usize;
        }
        let (bx, by) = (h.blocks[0] as usize, h.blocks[1] as usize);
        Some(b[0] + bx * (b[1] + by * b[2]))
    }

    /// Value range of every sub-block, x fastest.
    pub fn ranges(&self) -> &[[f32; 2]] {
        self.ranges
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Ramp;
    impl Lattice for Ramp {
        fn value(&self, i: u32, j: u32, k: u32) -> f32 {
            (i + 10 * j + 100 * k) as f32
        }
    }

    #[test]
    fn writes_and_reads_back_with_ghosts_and_ranges() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("b.rfb");
        let s = write_brick(&p, 3, &Ramp, [20, 20, 20], [8, 0, 4], [18, 19, 12]).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        // Vec<u8> is not 64-byte aligned in general: copy into an aligned buffer.
        let mut aligned = vec![0u64; bytes.len().div_ceil(8)];
        bytemuck::cast_slice_mut::<u64, u8>(&mut aligned)[..bytes.len()].copy_from_slice(&bytes);
        let bytes = &bytemuck::cast_slice::<u64, u8>(&aligned)[..bytes.len()];
        let layout = parse(bytes, s.checksum, true).unwrap();
        let b = layout.view(bytes);
        assert_eq!(b.header.domain, 3);
        assert_eq!(b.header.stored_lo, [5, 0, 1]);
        assert_eq!(b.header.stored_dims, [15, 20, 15]);
        assert_eq!(b.voxel([6, 7, 9]), Ramp.value(6, 7, 9));
        assert_eq!(b.voxel([19, 19, 15]), Ramp.value(19, 19, 15));
        assert_eq!(b.block_of([7, 0, 4]), None);
        assert_eq!(b.block_of([8, 0, 4]), Some(0));
        assert_eq!(b.block_of([16, 8, 4]), Some(1 + 2));
        assert_eq!(b.ranges()[0], [Ramp.value(8, 0, 4), Ramp.value(16, 8, 12)]);
        assert_eq!(s.values, [Ramp.value(7, 0, 3), Ramp.value(19, 19, 13)]);
        // A flipped voxel bit is caught by the checksum, a wrong manifest checksum without it.
        let mut broken = bytes.to_vec();
        broken[200] ^= 1;
        let e = parse(&broken, s.checksum, true).unwrap_err();
        assert!(e.contains("corrupt"), "{e}");
        let e = parse(bytes, s.checksum ^ 1, false).unwrap_err();
        assert!(e.contains("differs from the manifest"), "{e}");
        let e = parse(&bytes[..100], s.checksum, true).unwrap_err();
        assert!(e.contains("truncated"), "{e}");
    }

    #[test]
    fn refuses_non_finite_voxels_naming_them() {
        struct Nan;
        impl Lattice for Nan {
            fn value(&self, i: u32, _: u32, _: u32) -> f32 {
                if i == 2 { f32::NAN } else { 0.0 }
            }
        }
        let dir = tempfile::tempdir().unwrap();
        let e = write_brick(&dir.path().join("b"), 0, &Nan, [4, 4, 4], [0; 3], [3; 3])
            .unwrap_err()
            .to_string();
        assert!(e.contains("[2, 0, 0]") && e.contains("not finite"), "{e}");
    }
}
