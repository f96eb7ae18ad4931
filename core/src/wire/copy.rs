//! The short ray layout: a record with no light, credit or volume colour to carry (a
//! speculative copy: its group keeps the ray's weight and credit, and a copy composites a
//! volume from nothing, `render::speculation`) travels as the 64 bytes tracing it reads
//! rather than the full 104. The sender picks the layout per batch, losslessly: a batch
//! goes short only when every record's dropped fields are zero.

use bytemuck::{Pod, Zeroable};

use crate::ray::RayRecord;

/// A ray record without its throughput, credit and volume colour and opacity (all zero).
/// 64 bytes, no padding holes.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub(super) struct CopyRecord {
    origin: [f32; 3],
    t_min: f32,
    dir: [f32; 3],
    t_max: f32,
    pixel: u32,
    sample: u32,
    depth: u16,
    kind: u8,
    _pad: u8,
    domain: u32,
    tile: u32,
    epoch: u32,
    group: u32,
    resolver: u32,
}

const _: () = assert!(std::mem::size_of::<CopyRecord>() == 64);

impl CopyRecord {
    /// The short form of `r`, if it has nothing in the fields it drops.
    pub(super) fn of(r: &RayRecord) -> Option<CopyRecord> {
        // Compared by bits: a negative zero is not zero here, so the round trip is exact.
        let zero = |x: &f32| x.to_bits() == 0;
        let bare = r.credit == 0
            && r._pad2 == 0
            && r.throughput.iter().chain(&r.volume_rgb).all(zero)
            && zero(&r.volume_alpha);
        bare.then_some(CopyRecord {
            origin: r.origin,
            t_min: r.t_min,
            dir: r.dir,
            t_max: r.t_max,
            pixel: r.pixel,
            sample: r.sample,
            depth: r.depth,
            kind: r.kind,
            _pad: r._pad,
            domain: r.domain,
            tile: r.tile,
            epoch: r.epoch,
            group: r.group,
            resolver: r.resolver,
        })
    }

    /// The full record, its dropped fields zero.
    pub(super) fn ray(&self) -> RayRecord {
        RayRecord {
            origin: self.origin,
            t_min: self.t_min,
            dir: self.dir,
            t_max: self.t_max,
            pixel: self.pixel,
            sample: self.sample,
            depth: self.depth,
            kind: self.kind,
            _pad: self._pad,
            domain: self.domain,
            tile: self.tile,
            epoch: self.epoch,
            group: self.group,
            resolver: self.resolver,
            ..Zeroable::zeroed()
        }
    }
}
