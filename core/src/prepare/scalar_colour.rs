//! Colouring a surface by a scalar known at its vertices (the volume's gradient magnitude, or
//! a second volume's value) through a lookup table, as VTK's and ParaView's lookup tables do:
//! [`LUT_ENTRIES`] diffuse materials sampled evenly from a colour map, and each triangle the
//! entry of its corners' mean value, placed between the lowest and the highest mean.
//!
//! A triangle's colour is its material, stored with it in every domain that references it,
//! so each schedule, domain cut and speculative copy reads the same colour from the triangle
//! alone. The colour is flat across a triangle; a marching-cubes triangle is smaller than a
//! voxel, so the steps are a voxel's and the table's (1/256 of the range), not a region's.

use crate::colour_map::ColourMap;
use crate::scene::Material;

/// Entries of the lookup table: colours the range of values is divided into.
pub const LUT_ENTRIES: usize = 256;

/// The lookup table's materials: `map` at [`LUT_ENTRIES`] evenly spaced values from 0 to 1.
pub fn lookup_table(map: ColourMap) -> Vec<Material> {
    let last = (LUT_ENTRIES - 1) as f32;
    (0..LUT_ENTRIES)
        .map(|k| Material::Diffuse {
            albedo: map.at(k as f32 / last),
        })
        .collect()
}

/// Each triangle's entry of the table, from its corners' values (`value_at` of each corner):
/// their mean placed between the lowest and the highest mean over all triangles (a
/// non-finite mean takes the first entry); and that range, for the log.
pub fn entries(
    triangles: &[[[f32; 3]; 3]],
    value_at: impl Fn([f32; 3]) -> f32,
) -> (Vec<u32>, [f32; 2]) {
    let means: Vec<f32> = triangles
        .iter()
        .map(|t| t.iter().map(|&v| value_at(v)).sum::<f32>() / 3.0)
        .collect();
    let (low, high) = means
        .iter()
        .filter(|m| m.is_finite())
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &m| {
            (lo.min(m), hi.max(m))
        });
    let range = if low < high {
        [low, high]
    } else if low.is_finite() {
        // One value everywhere: every triangle takes the first entry.
        [low, low + 1.0]
    } else {
        [0.0, 1.0]
    };
    let last = (LUT_ENTRIES - 1) as f32;
    let index = |m: f32| {
        let x = (m - range[0]) / (range[1] - range[0]) * last;
        // NaN casts to 0; the clamp keeps rounding inside the table.
        (x.round().clamp(0.0, last)) as u32
    };
    (means.into_iter().map(index).collect(), range)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_lowest_and_highest_means_take_the_table_ends() {
        let tri = |x: f32| [[x, 0.0, 0.0], [x, 1.0, 0.0], [x, 0.0, 1.0]];
        let tris = [tri(2.0), tri(4.0), tri(2.5), tri(f32::NAN)];
        // The value at a corner is its x plus its y: a triangle's mean is x + 1/3.
        let (picked, range) = entries(&tris, |v| v[0] + v[1]);
        assert_eq!(picked, [0, 255, 64, 0]);
        assert!((range[0] - (2.0 + 1.0 / 3.0)).abs() < 1e-6);
        assert!((range[1] - (4.0 + 1.0 / 3.0)).abs() < 1e-6);
        // One value everywhere: the first entry.
        let (flat, _) = entries(&[tri(1.0), tri(1.0)], |_| 5.0);
        assert_eq!(flat, [0, 0]);
        let table = lookup_table(ColourMap::Viridis);
        assert_eq!(table.len(), LUT_ENTRIES);
        assert_eq!(
            table[0],
            Material::Diffuse {
                albedo: ColourMap::Viridis.at(0.0)
            }
        );
        assert_eq!(
            table[255],
            Material::Diffuse {
                albedo: ColourMap::Viridis.at(1.0)
            }
        );
    }
}
