//! Fixed-point pixel sums of one tile as they travel from a worker to the coordinator:
//! `(pixel, r, g, b)` as four little-endian 64-bit integers per pixel.

/// Bytes per encoded pixel.
pub const PIXEL_BYTES: usize = 32;

/// Encodes `(pixel, [r, g, b])` sums.
pub fn encode(sums: impl IntoIterator<Item = (u32, [i64; 3])>) -> Vec<u8> {
    let mut out = Vec::new();
    for (pixel, rgb) in sums {
        out.extend_from_slice(&u64::from(pixel).to_le_bytes());
        for c in rgb {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    out
}

/// Why encoded sums were refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SumsError {
    /// The length is not a whole number of pixels.
    #[error("tile sums of {0} bytes are not a whole number of {PIXEL_BYTES}-byte pixels")]
    Length(usize),
    /// A pixel index does not fit 32 bits.
    #[error("pixel index {0} is out of range")]
    Pixel(u64),
}

/// Decodes sums written by [`encode`]; the ledger checks that pixels belong to the tile.
pub fn decode(bytes: &[u8]) -> Result<Vec<(u32, [i64; 3])>, SumsError> {
    if !bytes.len().is_multiple_of(PIXEL_BYTES) {
        return Err(SumsError::Length(bytes.len()));
    }
    bytes
        .chunks_exact(PIXEL_BYTES)
        .map(|c| {
            let word = |i: usize| {
                let mut w = [0u8; 8];
                w.copy_from_slice(&c[i * 8..i * 8 + 8]);
                w
            };
            let pixel = u64::from_le_bytes(word(0));
            let pixel = u32::try_from(pixel).map_err(|_| SumsError::Pixel(pixel))?;
            let rgb = [1, 2, 3].map(|i| i64::from_le_bytes(word(i)));
            Ok((pixel, rgb))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sums_round_trip_and_bad_lengths_are_refused() {
        let sums = vec![(7, [1, -2, i64::MAX]), (u32::MAX, [0, 0, 5])];
        assert_eq!(decode(&encode(sums.clone())).unwrap(), sums);
        assert_eq!(decode(&[0; 33]), Err(SumsError::Length(33)));
        let mut big = encode([(1, [0; 3])]);
        big[4] = 1;
        assert!(matches!(decode(&big), Err(SumsError::Pixel(_))));
    }
}
