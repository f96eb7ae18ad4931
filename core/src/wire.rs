//! Batches on the wire: a 16-byte header, then fixed-size records as raw little-endian bytes,
//! carried in one protobuf `bytes` field (never one protobuf message per ray). Ray batches
//! carry rays; verdict batches carry what speculative copies found back to their rays' groups.
//! Decoding checks every record, because the bytes come from another process that may be
//! broken or hostile.

use crate::ray::{RayKind, RayRecord};

#[cfg(not(target_endian = "little"))]
compile_error!(
    "ray batches are raw little-endian records; big-endian hosts need a byte-swapping codec"
);

/// First bytes of every ray batch.
pub const MAGIC: [u8; 4] = *b"RFRB";
/// First bytes of every verdict batch.
pub const VERDICT_MAGIC: [u8; 4] = *b"RFVB";
/// Layout version of both kinds of batch. 3: rays carry their volume colour and opacity
/// (104-byte records; 2 had 88).
pub const VERSION: u16 = 3;
/// Bytes before the first record.
pub const HEADER_BYTES: usize = 16;
const RECORD_BYTES: usize = std::mem::size_of::<RayRecord>();
const VERDICT_BYTES: usize = std::mem::size_of::<VerdictRecord>();

/// What a speculative copy found, on its way back to the ray's group
/// (`render::speculation`). 48 bytes, no padding holes.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct VerdictRecord {
    /// The group at the receiving worker.
    pub group: u32,
    /// The copy's tile, epoch, pixel and sample: the group checks they are its ray's, so a
    /// stale verdict never settles a group that reused the id.
    pub tile: u32,
    pub epoch: u32,
    pub pixel: u32,
    pub sample: u32,
    /// `CLEAR`, `BLOCKED`, `HIT` or a volume kind (`render::speculation`).
    pub kind: u8,
    /// Zero.
    pub _pad: [u8; 3],
    /// A hit: the domain's place along the ray, the distance, the surface's normal and
    /// material (`SurfaceHit`); an occluder: the domain's place alone; zero otherwise.
    pub order: u32,
    pub t: f32,
    pub normal: [f32; 3],
    pub material: u32,
}

const _: () = assert!(VERDICT_BYTES == 48);

/// What a batch's records must satisfy to be accepted.
#[derive(Clone, Copy, Debug)]
pub struct BatchLimits {
    /// Domains in the scene: every record's domain must be below.
    pub domains: u32,
    /// Pixels in the frame: every record's pixel must be below.
    pub pixels: u32,
    /// Largest bounce count.
    pub max_depth: u16,
    /// Materials in the scene: every hit's material must be below.
    pub materials: u32,
    /// Largest number of records in one batch.
    pub max_records: usize,
}

/// Why a batch was refused.
#[derive(Clone, Debug, thiserror::Error, PartialEq)]
pub enum WireError {
    /// Shorter than the header, or not a whole number of records.
    #[error("batch of {0} bytes is truncated or not a whole number of records")]
    Length(usize),
    /// Wrong magic.
    #[error("not a ray or verdict batch, or not the one expected (bad magic)")]
    Magic,
    /// A version this build does not read.
    #[error("batch version {0} is not the supported {VERSION}")]
    Version(u16),
    /// Header bytes this version leaves unused are not zero.
    #[error("batch header has non-zero reserved bytes")]
    Reserved,
    /// The header's count disagrees with the records present.
    #[error("batch says {said} records, holds {held}")]
    Count {
        /// Count in the header.
        said: u32,
        /// Records present.
        held: usize,
    },
    /// More records than a batch may hold.
    #[error("batch holds {held} records, more than the limit of {limit}")]
    TooMany {
        /// Records present.
        held: usize,
        /// Largest accepted.
        limit: usize,
    },
    /// A record is out of range.
    #[error("record {index}: {reason}")]
    Record {
        /// Position in the batch.
        index: usize,
        /// What is wrong.
        reason: &'static str,
    },
}

impl BatchLimits {
    /// Limits that hold whatever the frame, for checking a batch before its frame is known:
    /// the frame-dependent ranges (domain, pixel, depth) are left open.
    pub fn any_frame(max_records: usize) -> Self {
        BatchLimits {
            domains: u32::MAX,
            pixels: u32::MAX,
            max_depth: u16::MAX,
            materials: u32::MAX,
            max_records,
        }
    }
}

/// Encodes rays as one batch.
pub fn encode_batch(rays: &[RayRecord]) -> Vec<u8> {
    encode(MAGIC, rays)
}

/// The rays a batch this process encoded carries (0 for a verdict batch or anything else):
/// a count for the metrics, from the length alone, with no check.
pub fn ray_count(bytes: &[u8]) -> u64 {
    if bytes.len() < HEADER_BYTES || bytes[..4] != MAGIC {
        return 0;
    }
    ((bytes.len() - HEADER_BYTES) / RECORD_BYTES) as u64
}

/// Decodes and checks a batch.
pub fn decode_batch(bytes: &[u8], limits: &BatchLimits) -> Result<Vec<RayRecord>, WireError> {
    check_batch(bytes, limits)?;
    // The payload is not aligned for RayRecord; copying also detaches it from the message.
    Ok(bytemuck::pod_collect_to_vec(&bytes[HEADER_BYTES..]))
}

/// Checks a batch without copying it; returns its number of records.
pub fn check_batch(bytes: &[u8], limits: &BatchLimits) -> Result<usize, WireError> {
    let held = check_header(bytes, MAGIC, RECORD_BYTES, limits.max_records)?;
    for (index, raw) in bytes[HEADER_BYTES..].chunks_exact(RECORD_BYTES).enumerate() {
        let r: RayRecord = bytemuck::pod_read_unaligned(raw);
        check_record(&r, limits).map_err(|reason| WireError::Record { index, reason })?;
    }
    Ok(held)
}

/// Checks the header and length of a batch of `record_bytes`-byte records; returns their
/// number.
fn check_header(
    bytes: &[u8],
    magic: [u8; 4],
    record_bytes: usize,
    max_records: usize,
) -> Result<usize, WireError> {
    let len = bytes.len();
    // Identity before size, so that garbage is called garbage rather than a truncated batch.
    match bytes.get(0..4) {
        Some(m) if m != magic => return Err(WireError::Magic),
        Some(_) => {}
        None => return Err(WireError::Length(len)),
    }
    if let Some(&[lo, hi]) = bytes.get(4..6) {
        let version = u16::from_le_bytes([lo, hi]);
        if version != VERSION {
            return Err(WireError::Version(version));
        }
    }
    if len < HEADER_BYTES || !(len - HEADER_BYTES).is_multiple_of(record_bytes) {
        return Err(WireError::Length(len));
    }
    // Zero, as in records, so that an accepted batch has exactly one encoding.
    if bytes[6..8] != [0; 2] || bytes[12..16] != [0; 4] {
        return Err(WireError::Reserved);
    }
    let said = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
    let held = (len - HEADER_BYTES) / record_bytes;
    if held > max_records {
        return Err(WireError::TooMany {
            held,
            limit: max_records,
        });
    }
    if said as usize != held {
        return Err(WireError::Count { said, held });
    }
    Ok(held)
}

fn encode<T: bytemuck::Pod>(magic: [u8; 4], records: &[T]) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER_BYTES + std::mem::size_of_val(records));
    out.extend_from_slice(&magic);
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes());
    out.extend_from_slice(&(records.len() as u32).to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes());
    out.extend_from_slice(bytemuck::cast_slice(records));
    out
}

/// Encodes verdicts as one batch (the bundler's results tier carries them).
pub fn encode_verdicts(verdicts: &[VerdictRecord]) -> Vec<u8> {
    encode(VERDICT_MAGIC, verdicts)
}

/// Decodes and checks a batch of verdicts.
pub fn decode_verdicts(
    bytes: &[u8],
    limits: &BatchLimits,
) -> Result<Vec<VerdictRecord>, WireError> {
    check_verdicts(bytes, limits)?;
    Ok(bytemuck::pod_collect_to_vec(&bytes[HEADER_BYTES..]))
}

/// Checks a batch of verdicts without copying it; returns its number of records.
pub fn check_verdicts(bytes: &[u8], limits: &BatchLimits) -> Result<usize, WireError> {
    let held = check_header(bytes, VERDICT_MAGIC, VERDICT_BYTES, limits.max_records)?;
    for (index, raw) in bytes[HEADER_BYTES..]
        .chunks_exact(VERDICT_BYTES)
        .enumerate()
    {
        let v: VerdictRecord = bytemuck::pod_read_unaligned(raw);
        check_verdict(&v, limits).map_err(|reason| WireError::Record { index, reason })?;
    }
    Ok(held)
}

fn check_verdict(v: &VerdictRecord, l: &BatchLimits) -> Result<(), &'static str> {
    if v._pad != [0; 3] {
        return Err("padding is not zero");
    }
    match v.kind {
        // A clear verdict names its copy's domain (`order`, checked against the frame's).
        VerdictRecord::CLEAR => {
            if v.t != 0.0 || v.normal != [0.0; 3] || v.material != 0 {
                return Err("a verdict without a hit carries hit fields");
            }
        }
        // An occluder's verdict names the domain's place along the ray (`order`) alone.
        VerdictRecord::BLOCKED => {
            if v.t != 0.0 || v.normal != [0.0; 3] || v.material != 0 {
                return Err("a verdict without a hit carries hit fields");
            }
        }
        VerdictRecord::HIT | VerdictRecord::VOLUME_HIT => {
            let finite = v.t.is_finite() && v.normal.iter().all(|x| x.is_finite());
            if !(finite && v.t >= 0.0) {
                return Err("non-finite or negative hit");
            }
        }
        VerdictRecord::SEGMENT => {
            // Premultiplied colour is non-negative and opacity a fraction, as in a ray record.
            let colour = v.normal.iter().all(|c| c.is_finite() && *c >= 0.0);
            if !(colour && (0.0..=1.0).contains(&v.t)) || v.material != 0 {
                return Err("volume segment colour or opacity out of range");
            }
        }
        VerdictRecord::LIGHT => {
            // Reflected light is premultiplied colour; the depth a distance along the ray.
            let colour = v.normal.iter().all(|c| c.is_finite() && *c >= 0.0);
            if !(colour && v.t.is_finite() && v.t >= 0.0) {
                return Err("volume segment light or depth out of range");
            }
            if v.material as usize >= crate::render::volume_light::MAX_LIGHTS {
                return Err("volume segment light index out of range");
            }
        }
        VerdictRecord::VOLUME_END => {
            if v.order != 0 || v.t != 0.0 || v.normal != [0.0; 3] {
                return Err("a closing volume verdict carries segment fields");
            }
            if v.material > crate::render::speculation::MAX_SEGMENTS {
                return Err("a closing volume verdict counts too many segments");
            }
        }
        _ => return Err("unknown verdict kind"),
    }
    check_verdict_range(v, l)
}

fn check_record(r: &RayRecord, l: &BatchLimits) -> Result<(), &'static str> {
    let finite = |v: &[f32; 3]| v.iter().all(|x| x.is_finite());
    if r.kind != RayKind::Radiance as u8 && r.kind != RayKind::Shadow as u8 {
        return Err("unknown kind");
    }
    if r._pad != 0 || r._pad2 != 0 {
        return Err("padding is not zero");
    }
    if !finite(&r.origin) || !finite(&r.dir) || !finite(&r.throughput) {
        return Err("non-finite origin, direction or throughput");
    }
    if r.dir == [0.0; 3] {
        return Err("zero direction");
    }
    // Composited premultiplied colour is non-negative and opacity a fraction: a record outside
    // that could only make a pixel no render makes.
    let unit = |x: f32| (0.0..=1.0).contains(&x);
    if !(finite(&r.volume_rgb) && r.volume_rgb.iter().all(|&c| c >= 0.0) && unit(r.volume_alpha)) {
        return Err("volume colour or opacity out of range");
    }
    if !(r.t_min >= 0.0 && r.t_min.is_finite() && r.t_max >= r.t_min) {
        return Err("bad interval");
    }
    check_ray_range(r, l)
}

/// The frame-dependent part of a ray record's check.
fn check_ray_range(r: &RayRecord, l: &BatchLimits) -> Result<(), &'static str> {
    if r.domain >= l.domains {
        return Err("domain out of range");
    }
    if r.pixel >= l.pixels {
        return Err("pixel out of range");
    }
    if r.depth > l.max_depth {
        return Err("depth above the frame's maximum");
    }
    Ok(())
}

/// Checks rays decoded under [`BatchLimits::any_frame`] against a frame's ranges (domain,
/// pixel, depth): the rest of each record was checked when it was decoded, so a batch is
/// read once and checked once.
pub fn check_ray_ranges(rays: &[RayRecord], limits: &BatchLimits) -> Result<(), WireError> {
    for (index, r) in rays.iter().enumerate() {
        check_ray_range(r, limits).map_err(|reason| WireError::Record { index, reason })?;
    }
    Ok(())
}

/// Checks verdicts decoded under [`BatchLimits::any_frame`] against a frame's ranges (pixel,
/// a hit's material), as [`check_ray_ranges`] does for rays.
pub fn check_verdict_ranges(
    verdicts: &[VerdictRecord],
    limits: &BatchLimits,
) -> Result<(), WireError> {
    for (index, v) in verdicts.iter().enumerate() {
        check_verdict_range(v, limits).map_err(|reason| WireError::Record { index, reason })?;
    }
    Ok(())
}

/// The frame-dependent part of a verdict's check.
fn check_verdict_range(v: &VerdictRecord, l: &BatchLimits) -> Result<(), &'static str> {
    if v.pixel >= l.pixels {
        return Err("pixel out of range");
    }
    if matches!(v.kind, VerdictRecord::HIT | VerdictRecord::VOLUME_HIT) && v.material >= l.materials
    {
        return Err("material out of range");
    }
    if v.kind == VerdictRecord::CLEAR && v.order >= l.domains {
        return Err("domain out of range");
    }
    Ok(())
}

#[cfg(test)]
mod tests;
