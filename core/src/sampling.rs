//! Deterministic random numbers: each one is a hash of where it is used, so every process that
//! traces a ray draws the same numbers for it, in any order.

/// What a random number is for; part of the hash so that different decisions at the same
/// vertex of a path are independent.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u32)]
pub enum Purpose {
    /// Sub-pixel position of a camera ray, x.
    PixelX = 0,
    /// Sub-pixel position of a camera ray, y.
    PixelY = 1,
    /// Bounce direction, first dimension.
    BounceU = 2,
    /// Bounce direction, second dimension.
    BounceV = 3,
    /// Choice between the lobes of a layered material.
    Lobe = 4,
    /// Roughness perturbation of a glossy reflection.
    GlossU = 5,
    /// Roughness perturbation of a glossy reflection, second dimension.
    GlossV = 6,
    /// Point on a light; the light's index is added to the hash separately.
    LightU = 7,
    /// Point on a light, second dimension.
    LightV = 8,
}

/// The splitmix64 finaliser: a bijection of 64-bit words with full avalanche. Sampling's
/// hashes are built on it; seeded generators elsewhere (tests, benchmarks) draw from it too.
#[inline(always)]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// A uniform number in `[0, 1)` from (pixel, sample, depth, purpose, index).
#[inline(always)]
pub fn uniform(pixel: u32, sample: u32, depth: u32, purpose: Purpose, index: u32) -> f32 {
    let a = mix64(((pixel as u64) << 32) | sample as u64);
    let b = mix64(a ^ (((depth as u64) << 40) | ((purpose as u64) << 32) | index as u64));
    // 24 high bits give every representable float step in [0, 1).
    (b >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_is_in_unit_interval_and_roughly_uniform() {
        let n = 100_000;
        let mut sum = 0.0f64;
        for i in 0..n {
            let u = uniform(i, 3, 1, Purpose::BounceU, 0);
            assert!((0.0..1.0).contains(&u));
            sum += u as f64;
        }
        let mean = sum / n as f64;
        assert!((mean - 0.5).abs() < 0.01, "mean {mean}");
    }

    #[test]
    fn purposes_and_depths_decorrelate() {
        let a = uniform(7, 1, 0, Purpose::BounceU, 0);
        assert_ne!(a, uniform(7, 1, 0, Purpose::BounceV, 0));
        assert_ne!(a, uniform(7, 1, 1, Purpose::BounceU, 0));
        assert_ne!(a, uniform(7, 2, 0, Purpose::BounceU, 0));
        assert_eq!(a, uniform(7, 1, 0, Purpose::BounceU, 0));
    }
}
