//! Unsigned LEB128 integers for the variable-length verdict layout: seven bits a byte, low
//! bits first, the top bit set on every byte but the last. Group ids, tiles, pixels and
//! domains are small numbers in 32-bit fields, so most take one to three bytes.
//!
//! Decoding accepts only the shortest form of each value (no trailing zero byte, nothing
//! above `u32::MAX`), so that an accepted batch has exactly one encoding, as with the fixed
//! layouts.

/// Most bytes a `u32` takes.
const MAX_BYTES: usize = 5;

/// Appends `value` to `out`.
pub(super) fn put(out: &mut Vec<u8>, mut value: u32) {
    while value >= 0x80 {
        out.push((value as u8 & 0x7f) | 0x80);
        value >>= 7;
    }
    out.push(value as u8);
}

/// Why a varint could not be read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum VarintError {
    /// The bytes ended inside it.
    Truncated,
    /// A longer form than the value needs, or a value above `u32::MAX`.
    NotCanonical,
}

/// Reads one value from the front of `bytes`, advancing it.
pub(super) fn take(bytes: &mut &[u8]) -> Result<u32, VarintError> {
    let mut value: u64 = 0;
    for i in 0..MAX_BYTES {
        let Some((&b, rest)) = bytes.split_first() else {
            return Err(VarintError::Truncated);
        };
        *bytes = rest;
        value |= u64::from(b & 0x7f) << (7 * i);
        if b & 0x80 == 0 {
            // A last byte of zero after others adds nothing: a longer form than needed.
            if i > 0 && b == 0 {
                return Err(VarintError::NotCanonical);
            }
            return u32::try_from(value).map_err(|_| VarintError::NotCanonical);
        }
    }
    Err(VarintError::NotCanonical)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_round_trip_in_their_shortest_form() {
        for v in [0, 1, 127, 128, 300, 16_383, 16_384, 1 << 21, u32::MAX] {
            let mut out = Vec::new();
            put(&mut out, v);
            let len = (32 - v.leading_zeros()).div_ceil(7).max(1) as usize;
            assert_eq!(out.len(), len, "{v}");
            let mut s = out.as_slice();
            assert_eq!(take(&mut s), Ok(v));
            assert!(s.is_empty());
        }
    }

    #[test]
    fn longer_forms_overflow_and_truncation_are_refused() {
        assert_eq!(take(&mut &[0x80, 0x00][..]), Err(VarintError::NotCanonical));
        assert_eq!(
            take(&mut &[0xff, 0xff, 0xff, 0xff, 0x1f][..]),
            Err(VarintError::NotCanonical)
        );
        assert_eq!(
            take(&mut &[0x80, 0x80, 0x80, 0x80, 0x80, 0x01][..]),
            Err(VarintError::NotCanonical)
        );
        assert_eq!(take(&mut &[0x80][..]), Err(VarintError::Truncated));
        assert_eq!(take(&mut &[][..]), Err(VarintError::Truncated));
    }
}
