//! Batches on the wire: a 16-byte header, then records as little-endian bytes, carried in one
//! protobuf `bytes` field (never one protobuf message per ray). Ray batches carry rays as
//! fixed-size raw records, in the full layout or, when no record has light, credit or volume
//! colour to carry (speculative copies), the short one (`copy`); verdict batches carry what
//! speculative copies found back to their rays' groups, each verdict as a kind byte and
//! varints (`varint`), its hit fields only when it has a hit: most verdicts say "clear" and
//! take about a quarter of a fixed record. Decoding checks every record, because the bytes
//! come from another process that may be broken or hostile.

mod copy;
mod varint;

use crate::ray::{RayKind, RayRecord};
use copy::CopyRecord;

#[cfg(not(target_endian = "little"))]
compile_error!(
    "ray batches are raw little-endian records; big-endian hosts need a byte-swapping codec"
);

/// First bytes of every ray batch.
pub const MAGIC: [u8; 4] = *b"RFRB";
/// First bytes of every ray batch in the short layout (records with no light, credit or
/// volume colour: speculative copies).
pub const COPY_MAGIC: [u8; 4] = *b"RFCB";
/// First bytes of every verdict batch.
pub const VERDICT_MAGIC: [u8; 4] = *b"RFVB";
/// Layout version of ray batches, full and short. 3: rays carry their volume colour and
/// opacity (104-byte records; 2 had 88).
pub const VERSION: u16 = 3;
/// Layout version of verdict batches. 4: variable-length records (3 had 48 bytes each).
pub const VERDICT_VERSION: u16 = 4;
/// Bytes before the first record.
pub const HEADER_BYTES: usize = 16;
/// Most lights a volume segment's verdict may name ([`VerdictRecord::LIGHT`]): a shadowed
/// segment carries one colour per light, and a volume is lit by at most this many of the
/// manifest's lights (the renderer's `render::volume_light::MAX_LIGHTS` is this bound). Kept
/// here, with the records it bounds, so checking a batch needs nothing of the renderer.
pub const MAX_SEGMENT_LIGHTS: usize = 4;
/// Most segments one ray may collect from all its copies, the most a closing volume verdict
/// may count: a bound on what a peer can make a group hold (far above a ray's crossings of
/// block faces in any volume a brick can hold).
pub const MAX_SEGMENTS: u32 = 1 << 16;
const RECORD_BYTES: usize = std::mem::size_of::<RayRecord>();
const COPY_BYTES: usize = std::mem::size_of::<CopyRecord>();
/// The in-memory verdict's size (its wire form is shorter, see [`encode_verdicts`]).
const VERDICT_BYTES: usize = std::mem::size_of::<VerdictRecord>();

/// What a speculative copy found, on its way back to the ray's group
/// (`render::speculation`). 48 bytes in memory, no padding holes; on the wire a kind byte,
/// varints, and the hit fields only for the kinds that have them ([`encode_verdicts`]).
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
    /// Clear, an occluder or a hit: the copy's domain (a hit's distance, the surface's normal
    /// and material follow, `SurfaceHit`); a volume segment or its light: the segment's
    /// first sample; zero otherwise.
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
    /// A ray batch in the full layout whose records all fit the short one: the sender must
    /// send it short, so that an accepted batch has exactly one encoding.
    #[error("ray batch in the full layout holds only records of the short layout")]
    Layout,
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

/// Encodes rays as one batch: in the short layout if no record has light, credit or volume
/// colour to carry (see `copy`), else in the full one.
pub fn encode_batch(rays: &[RayRecord]) -> Vec<u8> {
    if !rays.iter().all(|r| CopyRecord::of(r).is_some()) {
        return encode(MAGIC, VERSION, rays);
    }
    let mut out = header(COPY_MAGIC, VERSION, rays.len(), COPY_BYTES * rays.len());
    for copy in rays.iter().filter_map(CopyRecord::of) {
        out.extend_from_slice(bytemuck::bytes_of(&copy));
    }
    out
}

/// The rays a batch this process encoded carries (0 for a verdict batch or anything else):
/// a count for the metrics, from the length alone, with no check.
pub fn ray_count(bytes: &[u8]) -> u64 {
    let record = match bytes.get(..4) {
        Some(m) if m == MAGIC => RECORD_BYTES,
        Some(m) if m == COPY_MAGIC => COPY_BYTES,
        _ => return 0,
    };
    (bytes.len().saturating_sub(HEADER_BYTES) / record) as u64
}

/// Decodes and checks a batch.
pub fn decode_batch(bytes: &[u8], limits: &BatchLimits) -> Result<Vec<RayRecord>, WireError> {
    if bytes.get(..4) == Some(&COPY_MAGIC[..]) {
        check_header(bytes, COPY_MAGIC, VERSION, COPY_BYTES, limits.max_records)?;
        let mut rays = Vec::with_capacity((bytes.len() - HEADER_BYTES) / COPY_BYTES);
        for (index, raw) in bytes[HEADER_BYTES..].chunks_exact(COPY_BYTES).enumerate() {
            let r = bytemuck::pod_read_unaligned::<CopyRecord>(raw).ray();
            check_record(&r, limits).map_err(|reason| WireError::Record { index, reason })?;
            rays.push(r);
        }
        return Ok(rays);
    }
    check_batch(bytes, limits)?;
    // The payload is not aligned for RayRecord; copying also detaches it from the message.
    Ok(bytemuck::pod_collect_to_vec(&bytes[HEADER_BYTES..]))
}

/// Checks a batch without copying it; returns its number of records.
pub fn check_batch(bytes: &[u8], limits: &BatchLimits) -> Result<usize, WireError> {
    if bytes.get(..4) == Some(&COPY_MAGIC[..]) {
        return decode_batch(bytes, limits).map(|rays| rays.len());
    }
    let held = check_header(bytes, MAGIC, VERSION, RECORD_BYTES, limits.max_records)?;
    let mut short = true;
    for (index, raw) in bytes[HEADER_BYTES..].chunks_exact(RECORD_BYTES).enumerate() {
        let r: RayRecord = bytemuck::pod_read_unaligned(raw);
        check_record(&r, limits).map_err(|reason| WireError::Record { index, reason })?;
        short &= CopyRecord::of(&r).is_some();
    }
    if short {
        return Err(WireError::Layout);
    }
    Ok(held)
}

/// Checks the header and length of a batch of `record_bytes`-byte records; returns their
/// number.
fn check_header(
    bytes: &[u8],
    magic: [u8; 4],
    version: u16,
    record_bytes: usize,
    max_records: usize,
) -> Result<usize, WireError> {
    let said = check_prefix(bytes, magic, version)?;
    let len = bytes.len();
    if len < HEADER_BYTES || !(len - HEADER_BYTES).is_multiple_of(record_bytes) {
        return Err(WireError::Length(len));
    }
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

/// Checks a batch's header (magic, version, reserved bytes); returns the count it states.
fn check_prefix(bytes: &[u8], magic: [u8; 4], version: u16) -> Result<u32, WireError> {
    let len = bytes.len();
    // Identity before size, so that garbage is called garbage rather than a truncated batch.
    match bytes.get(0..4) {
        Some(m) if m != magic => return Err(WireError::Magic),
        Some(_) => {}
        None => return Err(WireError::Length(len)),
    }
    if let Some(&[lo, hi]) = bytes.get(4..6) {
        let found = u16::from_le_bytes([lo, hi]);
        if found != version {
            return Err(WireError::Version(found));
        }
    }
    if len < HEADER_BYTES {
        return Err(WireError::Length(len));
    }
    // Zero, as in records, so that an accepted batch has exactly one encoding.
    if bytes[6..8] != [0; 2] || bytes[12..16] != [0; 4] {
        return Err(WireError::Reserved);
    }
    Ok(u32::from_le_bytes([
        bytes[8], bytes[9], bytes[10], bytes[11],
    ]))
}

fn header(magic: [u8; 4], version: u16, count: usize, capacity: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER_BYTES + capacity);
    out.extend_from_slice(&magic);
    out.extend_from_slice(&version.to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes());
    out.extend_from_slice(&(count as u32).to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes());
    out
}

fn encode<T: bytemuck::Pod>(magic: [u8; 4], version: u16, records: &[T]) -> Vec<u8> {
    let mut out = header(
        magic,
        version,
        records.len(),
        std::mem::size_of_val(records),
    );
    out.extend_from_slice(bytemuck::cast_slice(records));
    out
}

/// Whether a verdict of this kind carries a hit's or a segment's fields (`t`, `normal`,
/// `material`) on the wire; a closing volume verdict carries its count (`material`) alone,
/// clear and blocked verdicts none.
fn has_hit_fields(kind: u8) -> bool {
    matches!(
        kind,
        VerdictRecord::HIT
            | VerdictRecord::VOLUME_HIT
            | VerdictRecord::SEGMENT
            | VerdictRecord::LIGHT
    )
}

/// Encodes verdicts as one batch (the bundler's results tier carries them). Each is its
/// kind byte, then `group`, `tile`, `epoch`, `pixel`, `sample` and `order` as varints, then
/// for hits, segments and lights `t` and `normal` as raw floats and `material` as a varint,
/// for a closing volume verdict `material` alone. The fields a kind does not carry must be
/// zero (the kernel makes them so; [`decode_verdicts`] gives them back as zero).
pub fn encode_verdicts(verdicts: &[VerdictRecord]) -> Vec<u8> {
    // Clear verdicts, the most common, take about 12 bytes.
    let mut out = header(
        VERDICT_MAGIC,
        VERDICT_VERSION,
        verdicts.len(),
        12 * verdicts.len(),
    );
    for v in verdicts {
        out.push(v.kind);
        for field in [v.group, v.tile, v.epoch, v.pixel, v.sample, v.order] {
            varint::put(&mut out, field);
        }
        if has_hit_fields(v.kind) {
            out.extend_from_slice(&v.t.to_le_bytes());
            for n in v.normal {
                out.extend_from_slice(&n.to_le_bytes());
            }
            varint::put(&mut out, v.material);
        } else if v.kind == VerdictRecord::VOLUME_END {
            varint::put(&mut out, v.material);
        }
    }
    out
}

/// Reads one verdict of the variable layout from the front of `bytes`.
fn take_verdict(bytes: &mut &[u8], index: usize, len: usize) -> Result<VerdictRecord, WireError> {
    let bad = |e| match e {
        varint::VarintError::Truncated => WireError::Length(len),
        varint::VarintError::NotCanonical => WireError::Record {
            index,
            reason: "varint not in its shortest form or above 32 bits",
        },
    };
    let (&kind, rest) = bytes.split_first().ok_or(WireError::Length(len))?;
    *bytes = rest;
    if kind > VerdictRecord::VOLUME_HIT {
        return Err(WireError::Record {
            index,
            reason: "unknown verdict kind",
        });
    }
    let mut v = VerdictRecord {
        kind,
        ..bytemuck::Zeroable::zeroed()
    };
    for field in [
        &mut v.group,
        &mut v.tile,
        &mut v.epoch,
        &mut v.pixel,
        &mut v.sample,
        &mut v.order,
    ] {
        *field = varint::take(bytes).map_err(bad)?;
    }
    if has_hit_fields(kind) {
        let mut float = || -> Result<f32, WireError> {
            let (raw, rest) = bytes
                .split_first_chunk::<4>()
                .ok_or(WireError::Length(len))?;
            *bytes = rest;
            Ok(f32::from_le_bytes(*raw))
        };
        v.t = float()?;
        v.normal = [float()?, float()?, float()?];
        v.material = varint::take(bytes).map_err(bad)?;
    } else if kind == VerdictRecord::VOLUME_END {
        v.material = varint::take(bytes).map_err(bad)?;
    }
    Ok(v)
}

/// Decodes and checks a batch of verdicts.
pub fn decode_verdicts(
    bytes: &[u8],
    limits: &BatchLimits,
) -> Result<Vec<VerdictRecord>, WireError> {
    let said = check_prefix(bytes, VERDICT_MAGIC, VERDICT_VERSION)? as usize;
    if said > limits.max_records {
        return Err(WireError::TooMany {
            held: said,
            limit: limits.max_records,
        });
    }
    let len = bytes.len();
    let mut rest = &bytes[HEADER_BYTES..];
    // Every record takes at least seven bytes: no count can make this allocate more than
    // the batch's own size.
    let mut verdicts = Vec::with_capacity(said.min(rest.len() / 7));
    for index in 0..said {
        let v = take_verdict(&mut rest, index, len)?;
        check_verdict(&v, limits).map_err(|reason| WireError::Record { index, reason })?;
        verdicts.push(v);
    }
    if !rest.is_empty() {
        return Err(WireError::Length(len));
    }
    Ok(verdicts)
}

/// Checks a batch of verdicts; returns its number of records.
pub fn check_verdicts(bytes: &[u8], limits: &BatchLimits) -> Result<usize, WireError> {
    decode_verdicts(bytes, limits).map(|v| v.len())
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
        // An occluder's verdict names its copy's domain (`order`) alone.
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
            if v.material as usize >= MAX_SEGMENT_LIGHTS {
                return Err("volume segment light index out of range");
            }
        }
        VerdictRecord::VOLUME_END => {
            if v.order != 0 || v.t != 0.0 || v.normal != [0.0; 3] {
                return Err("a closing volume verdict carries segment fields");
            }
            if v.material > MAX_SEGMENTS {
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
    let names_domain = matches!(
        v.kind,
        VerdictRecord::CLEAR
            | VerdictRecord::BLOCKED
            | VerdictRecord::HIT
            | VerdictRecord::VOLUME_HIT
    );
    if names_domain && v.order >= l.domains {
        return Err("domain out of range");
    }
    Ok(())
}

#[cfg(test)]
mod tests;
