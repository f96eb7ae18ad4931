//! Fixed-point pixel sums of one tile as they travel from a worker to the coordinator.
//!
//! A tile's result names every pixel one of its retiring rays belonged to (zero sums
//! included: the coordinator bounds a result's credit by the primary rays of the pixels it
//! names), so at one sample per pixel nearly every pixel of the frame crosses the wire once.
//! Fixed 32-byte `(pixel, r, g, b)` records made a 16384x16384 frame ship 8.6 GB; this form
//! spends a few bytes per pixel instead:
//!
//! - runs of consecutive pixel indices, each a LEB128 `gap` (pixels skipped since the end of
//!   the previous run, or the first pixel's index) and a LEB128 `len` (at least 1);
//! - after each run's header, its pixels' sums: per channel the zigzag LEB128 of the
//!   (wrapping) difference from the same channel of the pixel encoded before it (0 before the
//!   first), since neighbouring pixels of an image differ little.
//!
//! Pixels come out strictly increasing, so a result cannot name a pixel twice and never holds
//! more pixels than its tile: the decoder stops at a caller's bound before allocating more.
//! Bytes a pixel measured by the tests below (a 64x64 tile): smooth sky-like sums 4.1, no
//! light 3.0, every 7th pixel with unrelated sums 14.0; the fixed records took 32 for each
//! named pixel, and a dense array of the tile's sums would take 24 for every pixel of it.

/// Bytes per pixel of the earlier fixed `(pixel, r, g, b)` records, for comparison.
pub const FIXED_RECORD_BYTES: usize = 32;

/// Encodes `(pixel, [r, g, b])` sums; `sums` must be in strictly increasing pixel order (as
/// the worker sorts them), anything else is a bug of the caller.
///
/// # Panics
/// If the pixels are not strictly increasing.
pub fn encode(sums: &[(u32, [i64; 3])]) -> Vec<u8> {
    let mut out = Vec::with_capacity(sums.len() * 6);
    let mut prev = [0i64; 3];
    let mut next_pixel = 0u64;
    let mut i = 0;
    while i < sums.len() {
        let start = sums[i].0;
        let mut end = i + 1;
        while end < sums.len() && u64::from(sums[end].0) == u64::from(sums[end - 1].0) + 1 {
            end += 1;
        }
        assert!(
            u64::from(start) >= next_pixel,
            "tile sums must be in strictly increasing pixel order"
        );
        put_varint(&mut out, u64::from(start) - next_pixel);
        put_varint(&mut out, (end - i) as u64);
        for (_, rgb) in &sums[i..end] {
            for (p, &c) in prev.iter_mut().zip(rgb) {
                put_varint(&mut out, zigzag(c.wrapping_sub(*p)));
                *p = c;
            }
        }
        next_pixel = u64::from(sums[end - 1].0) + 1;
        i = end;
    }
    out
}

/// Why encoded sums were refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SumsError {
    /// The bytes end inside a number.
    #[error("tile sums end inside a number at byte {0}")]
    Truncated(usize),
    /// A number is longer than 64 bits.
    #[error("tile sums hold an over-long number at byte {0}")]
    Overlong(usize),
    /// A run of no pixels.
    #[error("tile sums hold an empty run at byte {0}")]
    EmptyRun(usize),
    /// A pixel index does not fit 32 bits.
    #[error("pixel index {0} is out of range")]
    Pixel(u64),
    /// More pixels than the tile has.
    #[error("tile sums name more than the tile's {0} pixels")]
    TooMany(usize),
}

/// Decodes sums written by [`encode`], refusing more than `max_pixels` pixels (the tile's
/// count) before holding them; the ledger checks that the pixels belong to the tile.
pub fn decode(bytes: &[u8], max_pixels: usize) -> Result<Vec<(u32, [i64; 3])>, SumsError> {
    let mut r = Reader { bytes, at: 0 };
    let mut out = Vec::new();
    let mut prev = [0i64; 3];
    let mut next_pixel = 0u64;
    while r.at < bytes.len() {
        let gap = r.varint()?;
        let at = r.at;
        let len = r.varint()?;
        if len == 0 {
            return Err(SumsError::EmptyRun(at));
        }
        if len > (max_pixels - out.len()) as u64 {
            return Err(SumsError::TooMany(max_pixels));
        }
        let start = next_pixel.saturating_add(gap);
        let last = start.saturating_add(len - 1);
        if last > u64::from(u32::MAX) {
            return Err(SumsError::Pixel(last));
        }
        for pixel in start..=last {
            for p in &mut prev {
                *p = p.wrapping_add(unzigzag(r.varint()?));
            }
            out.push((pixel as u32, prev));
        }
        next_pixel = last + 1;
    }
    Ok(out)
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    fn varint(&mut self) -> Result<u64, SumsError> {
        let start = self.at;
        let mut value = 0u64;
        for shift in (0..64).step_by(7) {
            let &b = self.bytes.get(self.at).ok_or(SumsError::Truncated(start))?;
            self.at += 1;
            let bits = u64::from(b & 0x7f);
            // The tenth byte may carry only the top bit.
            if shift == 63 && bits > 1 {
                return Err(SumsError::Overlong(start));
            }
            value |= bits << shift;
            if b & 0x80 == 0 {
                return Ok(value);
            }
        }
        Err(SumsError::Overlong(start))
    }
}

fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push(v as u8 | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

fn unzigzag(v: u64) -> i64 {
    (v >> 1) as i64 ^ -((v & 1) as i64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tile::TileGrid;

    #[test]
    fn sums_round_trip_at_the_extremes() {
        let sums = vec![
            (0, [0, 0, 0]),
            (1, [i64::MAX, i64::MIN, -1]),
            (7, [1, -2, i64::MAX]),
            (8, [i64::MIN, 0, 5]),
            (u32::MAX - 1, [3, 3, 3]),
            (u32::MAX, [0, 0, 5]),
        ];
        assert_eq!(decode(&encode(&sums), 6).unwrap(), sums);
        assert_eq!(decode(&encode(&[]), 0).unwrap(), []);
    }

    #[test]
    fn malformed_sums_are_refused() {
        let sums = encode(&[(5, [1, 2, 3]), (6, [1, 2, 3]), (9, [0; 3])]);
        let whole = decode(&sums, 3).unwrap();
        for cut in 1..sums.len() {
            // Cut between runs, the rest is a shorter valid result; anywhere else, refused.
            match decode(&sums[..cut], 3) {
                Ok(fewer) => assert!(whole.starts_with(&fewer) && fewer.len() < 3, "{cut}"),
                Err(e) => assert!(matches!(e, SumsError::Truncated(_)), "{cut}: {e}"),
            }
        }
        assert_eq!(decode(&sums, 2), Err(SumsError::TooMany(2)));
        // A run claiming four billion pixels is refused before anything is held.
        let mut huge = Vec::new();
        put_varint(&mut huge, 0);
        put_varint(&mut huge, u64::from(u32::MAX));
        assert_eq!(decode(&huge, 4096), Err(SumsError::TooMany(4096)));
        assert_eq!(decode(&[0, 0], 1), Err(SumsError::EmptyRun(1)));
        assert_eq!(decode(&[0x80; 11], 1), Err(SumsError::Overlong(0)));
        let mut past = Vec::new();
        put_varint(&mut past, u64::from(u32::MAX));
        put_varint(&mut past, 2);
        past.extend([0; 6]);
        assert_eq!(decode(&past, 2), Err(SumsError::Pixel(1 << 32)));
    }

    #[test]
    fn a_tile_takes_a_few_bytes_a_pixel() {
        // Tile 5 of a 4096-wide frame: 64 rows of 64 pixels, strided.
        let grid = TileGrid::new(4096, 4096, 64).expect("grid");
        let pixels: Vec<u32> = grid.pixels(5).collect();
        let mut sorted = pixels.clone();
        sorted.sort_unstable();
        let size = |sums: &[(u32, [i64; 3])]| {
            let bytes = encode(sums);
            assert_eq!(decode(&bytes, pixels.len()).unwrap(), sums);
            bytes.len() as f64 / sums.len() as f64
        };
        // A sky: smooth sums near 0.7 in 2^24 fixed point.
        let sky: Vec<_> = sorted
            .iter()
            .map(|&p| {
                let (x, y) = (i64::from(p % 4096), i64::from(p / 4096));
                (p, [11_000_000 + 700 * x, 11_500_000 + 300 * y, 12_000_000])
            })
            .collect();
        let dark: Vec<_> = sorted.iter().map(|&p| (p, [0; 3])).collect();
        // Every 7th pixel, with unrelated sums.
        let scattered: Vec<_> = sorted
            .iter()
            .step_by(7)
            .map(|&p| {
                let v = i64::from(p.wrapping_mul(2_654_435_761) >> 8);
                (p, [v, v / 3, v / 5])
            })
            .collect();
        let (sky, dark, scattered) = (size(&sky), size(&dark), size(&scattered));
        assert!(
            sky < 4.1 && dark < 3.1 && scattered < 14.1,
            "{sky} {dark} {scattered}"
        );
    }
}
