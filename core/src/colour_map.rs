//! Colour maps for surfaces: a surface's reflectance read from a map at the height of the
//! point shaded (`Material::Mapped`), instead of one colour per material or per region.

use serde::{Deserialize, Serialize};

/// A built-in colour map: reflectances at evenly spaced stops from 0 to 1, linear between.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ColourMap {
    /// Ivory shading to a warm brown: bone, darker low down.
    Bone,
    /// Blue low through green and tan to white high: a terrain's.
    Terrain,
    /// Perceptually even, dark violet through teal to yellow (after matplotlib's viridis).
    Viridis,
    /// Diverging blue to grey to red (after Moreland's cool-warm).
    CoolWarm,
}

/// Names of the presets, for errors and help.
pub const NAMES: [&str; 4] = ["bone", "terrain", "viridis", "cool-warm"];

impl ColourMap {
    /// The preset called `name`.
    pub fn parse(name: &str) -> Result<ColourMap, String> {
        Ok(match name {
            "bone" => ColourMap::Bone,
            "terrain" => ColourMap::Terrain,
            "viridis" => ColourMap::Viridis,
            "cool-warm" => ColourMap::CoolWarm,
            _ => {
                return Err(format!(
                    "unknown colour map {name:?} (presets: {})",
                    NAMES.join(", ")
                ));
            }
        })
    }

    fn stops(self) -> &'static [[f32; 3]] {
        match self {
            ColourMap::Bone => &[
                [0.42, 0.30, 0.20],
                [0.70, 0.58, 0.44],
                [0.86, 0.80, 0.68],
                [0.93, 0.90, 0.83],
            ],
            ColourMap::Terrain => &[
                [0.20, 0.30, 0.60],
                [0.25, 0.60, 0.45],
                [0.55, 0.72, 0.35],
                [0.70, 0.60, 0.42],
                [0.92, 0.92, 0.90],
            ],
            ColourMap::Viridis => &[
                [0.267, 0.005, 0.329],
                [0.229, 0.322, 0.546],
                [0.128, 0.567, 0.551],
                [0.369, 0.789, 0.383],
                [0.993, 0.906, 0.144],
            ],
            ColourMap::CoolWarm => &[
                [0.230, 0.299, 0.754],
                [0.552, 0.690, 0.996],
                [0.866, 0.866, 0.866],
                [0.956, 0.604, 0.486],
                [0.706, 0.016, 0.150],
            ],
        }
    }

    /// The reflectance at `x`, clamped into `[0, 1]` (NaN reads as 0).
    pub fn at(self, x: f32) -> [f32; 3] {
        let stops = self.stops();
        let last = (stops.len() - 1) as f32;
        let x = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) } * last;
        let i = (x.floor() as usize).min(stops.len() - 2);
        let f = x - i as f32;
        let (a, b) = (stops[i], stops[i + 1]);
        [0, 1, 2].map(|c| a[c] + f * (b[c] - a[c]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ends_are_the_first_and_last_stops_and_names_parse() {
        for name in NAMES {
            let map = ColourMap::parse(name).unwrap();
            let stops = map.stops();
            assert_eq!(map.at(0.0), stops[0]);
            assert_eq!(map.at(-3.0), stops[0]);
            assert_eq!(map.at(f32::NAN), stops[0]);
            let end = map.at(1.0);
            let want = stops[stops.len() - 1];
            assert!((0..3).all(|c| (end[c] - want[c]).abs() < 1e-6));
            assert_eq!(map.at(7.0), end);
            assert!((0..=100).all(|k| {
                map.at(k as f32 / 100.0)
                    .iter()
                    .all(|c| (0.0..=1.0).contains(c))
            }));
        }
        assert!(ColourMap::parse("rainbow").unwrap_err().contains("viridis"));
    }
}
