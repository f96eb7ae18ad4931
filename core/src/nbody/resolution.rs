//! How fine a grid over the field gives a wanted number of triangles: coarse marches
//! extrapolated, with a `log2` and `exp2` of our own so every machine picks the same grid.

use super::{NbodyField, SampledField};
use crate::isosurface::{Grid, march};

/// Points per axis of a cube grid over `[0, 1]^3` whose marching at `iso`
/// should yield roughly `target_triangles` triangles.
///
/// Marches coarse grids of 32³ and 64³ cells and extrapolates from their
/// triangle counts. A smooth surface's count grows with the square of the
/// resolution, but finer grids also resolve small blobs and wrinkles the
/// coarse ones miss; the growth between the two coarse grids measures that,
/// and the extrapolation uses it. Deterministic, like the field itself.
pub fn resolution_for_triangles(field: &NbodyField, iso: f32, target_triangles: u64) -> u32 {
    const COARSE: u32 = 64;
    let fine = count_triangles(field, iso, COARSE + 1) as f64;
    let coarse = count_triangles(field, iso, COARSE / 2 + 1) as f64;
    if fine == 0.0 || coarse == 0.0 {
        return COARSE + 1;
    }
    // Growth exponent between 32 and 64 cells, kept near the smooth-surface 2.
    let exponent = log2(fine / coarse).clamp(1.5, 3.0);
    let scale = exp2(log2(target_triangles.max(1) as f64 / fine) / exponent);
    let cells = (f64::from(COARSE) * scale).round();
    (cells as u32).saturating_add(1).clamp(2, 1 << 16)
}

/// How many triangles marching the field at `iso` on an `n`-point cube grid gives.
pub(super) fn count_triangles(field: &NbodyField, iso: f32, n: u32) -> u64 {
    let sampled = SampledField {
        field,
        grid: Grid::unit_cube(n),
    };
    let mut count = 0;
    march(
        &sampled.grid,
        &sampled,
        iso,
        sampled.grid.all_cells(),
        |_| count += 1,
    );
    count
}

/// Base-2 logarithm of a positive finite `x` from its exponent bits and an
/// atanh series, so the result does not depend on the platform's libm.
pub(super) fn log2(x: f64) -> f64 {
    debug_assert!(x > 0.0 && x.is_finite());
    let bits = x.to_bits();
    let exponent = ((bits >> 52) & 0x7ff) as i64 - 1023;
    let mantissa = f64::from_bits((bits & ((1 << 52) - 1)) | (1023 << 52));
    // ln(m) = 2·atanh(z), z = (m-1)/(m+1) ≤ 1/3: 30 terms are ample.
    let z = (mantissa - 1.0) / (mantissa + 1.0);
    let (mut term, mut series) = (z, 0.0);
    for k in 0..30 {
        series += term / f64::from(2 * k + 1);
        term *= z * z;
    }
    exponent as f64 + 2.0 * series / std::f64::consts::LN_2
}

/// 2^y for moderate `y`, by repeated squaring for the integer part and a
/// Taylor series for the fraction (same reason as [`log2`]).
pub(super) fn exp2(y: f64) -> f64 {
    let whole = y.floor();
    let frac_ln = (y - whole) * std::f64::consts::LN_2;
    let (mut term, mut series) = (1.0, 0.0);
    for k in 1..30 {
        series += term;
        term *= frac_ln / f64::from(k);
    }
    let mut power = 1.0;
    for _ in 0..(whole.abs().min(1023.0) as u32) {
        power *= 2.0;
    }
    if whole < 0.0 {
        series / power
    } else {
        series * power
    }
}
