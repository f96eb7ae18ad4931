//! Transfer functions for direct volume rendering: a colour map and an opacity curve over the
//! volume's scalar values, as control points with linear interpolation between them. Presets
//! for CT (bone, skin) and for the generator's density field, and a TOML file format:
//!
//! ```toml
//! # opacity is per voxel length; colours are linear RGB in [0, 1]
//! [[point]]
//! value = 150.0
//! colour = [0.9, 0.8, 0.7]
//! opacity = 0.0
//! [[point]]
//! value = 700.0
//! colour = [1.0, 1.0, 0.95]
//! opacity = 0.6
//! ```
//! Values must increase strictly from point to point. The kernel does not evaluate the curve
//! per sample: [`TransferTable`] tabulates it once for the ray step, with the opacity already
//! corrected for that step, so every process that builds the table from the same points gets
//! the same bits.

use serde::{Deserialize, Serialize};

/// One control point of a transfer function.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControlPoint {
    /// Scalar value of the volume.
    pub value: f32,
    /// Linear RGB colour in [0, 1].
    pub colour: [f32; 3],
    /// Opacity of one voxel length of material of this value, in [0, 1].
    pub opacity: f32,
}

/// A colour map and an opacity curve: control points by increasing value.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransferFunction {
    /// The points, values strictly increasing.
    #[serde(rename = "point")]
    pub points: Vec<ControlPoint>,
}

/// Largest transfer-function file read.
pub const MAX_TRANSFER_BYTES: u64 = 1 << 20;
/// Most control points accepted.
pub const MAX_POINTS: usize = 4096;

/// Names of the built-in transfer functions.
pub const PRESETS: [&str; 3] = ["ct-bone", "ct-skin", "density"];

fn point(value: f32, colour: [f32; 3], opacity: f32) -> ControlPoint {
    ControlPoint {
        value,
        colour,
        opacity,
    }
}

impl TransferFunction {
    /// A built-in transfer function by name (see [`PRESETS`]): `ct-bone` shows bone in
    /// Hounsfield units (soft tissue transparent), `ct-skin` the skin faintly over the bone,
    /// `density` a hot colour map for the generator's particle density.
    pub fn preset(name: &str) -> Option<TransferFunction> {
        let points = match name {
            "ct-bone" => vec![
                point(-1024.0, [0.0, 0.0, 0.0], 0.0),
                point(150.0, [0.55, 0.25, 0.15], 0.0),
                point(300.0, [0.9, 0.75, 0.55], 0.15),
                point(700.0, [1.0, 0.95, 0.85], 0.6),
                point(3000.0, [1.0, 1.0, 1.0], 0.8),
            ],
            "ct-skin" => vec![
                point(-1024.0, [0.0, 0.0, 0.0], 0.0),
                point(-600.0, [0.8, 0.5, 0.4], 0.0),
                point(-300.0, [0.9, 0.6, 0.5], 0.04),
                point(50.0, [0.9, 0.65, 0.55], 0.04),
                point(200.0, [0.9, 0.8, 0.7], 0.0),
                point(300.0, [0.95, 0.9, 0.8], 0.2),
                point(1200.0, [1.0, 1.0, 0.95], 0.7),
                point(3000.0, [1.0, 1.0, 1.0], 0.8),
            ],
            "density" => vec![
                point(0.0, [0.0, 0.0, 0.0], 0.0),
                point(0.5, [0.3, 0.05, 0.4], 0.0),
                point(1.0, [0.8, 0.15, 0.2], 0.05),
                point(2.0, [1.0, 0.55, 0.1], 0.2),
                point(4.0, [1.0, 0.9, 0.5], 0.5),
                point(8.0, [1.0, 1.0, 1.0], 0.9),
            ],
            _ => return None,
        };
        Some(TransferFunction { points })
    }

    /// Parses and checks transfer-function TOML. Errors give the point and what is wrong.
    pub fn parse(text: &str) -> Result<TransferFunction, String> {
        let tf: TransferFunction = toml::from_str(text).map_err(|e| {
            let mut e = e;
            e.set_input(None);
            e.to_string().trim_end().replace('\n', " ")
        })?;
        tf.check()?;
        Ok(tf)
    }

    /// A preset by name, else the TOML file at `spec`; errors name the file.
    pub fn load(spec: &str) -> Result<TransferFunction, String> {
        if let Some(tf) = Self::preset(spec) {
            return Ok(tf);
        }
        use std::io::Read;
        let path = std::path::Path::new(spec);
        let file = std::fs::File::open(path).map_err(|e| {
            format!(
                "{spec}: {e} (not a file, nor one of the presets {})",
                PRESETS.join(", ")
            )
        })?;
        let mut raw = Vec::new();
        file.take(MAX_TRANSFER_BYTES + 1)
            .read_to_end(&mut raw)
            .map_err(|e| format!("{spec}: {e}"))?;
        if raw.len() as u64 > MAX_TRANSFER_BYTES {
            return Err(format!(
                "{spec}: larger than the {MAX_TRANSFER_BYTES} bytes a transfer function may have"
            ));
        }
        let text = String::from_utf8(raw).map_err(|_| format!("{spec}: not UTF-8 text"))?;
        Self::parse(&text).map_err(|e| format!("{spec}: bad transfer function: {e}"))
    }

    /// Checks the points: at least two, at most [`MAX_POINTS`], finite, colours and opacities
    /// in [0, 1], values strictly increasing.
    pub fn check(&self) -> Result<(), String> {
        if self.points.len() < 2 || self.points.len() > MAX_POINTS {
            return Err(format!(
                "{} points: a transfer function needs 2 to {MAX_POINTS}",
                self.points.len()
            ));
        }
        for (i, p) in self.points.iter().enumerate() {
            if !p.value.is_finite() {
                return Err(format!("point {i}: value is not finite"));
            }
            let unit = |x: f32| (0.0..=1.0).contains(&x);
            if !p.colour.iter().all(|&c| unit(c)) || !unit(p.opacity) {
                return Err(format!("point {i}: colour and opacity must lie in [0, 1]"));
            }
            if i > 0 && p.value <= self.points[i - 1].value {
                return Err(format!(
                    "point {i}: value {} does not increase on point {}'s {} (values must be \
                     strictly increasing)",
                    p.value,
                    i - 1,
                    self.points[i - 1].value
                ));
            }
        }
        Ok(())
    }

    /// The TOML file format of this transfer function (what [`TransferFunction::parse`] reads).
    pub fn to_toml(&self) -> Result<String, String> {
        toml::to_string(self).map_err(|e| e.to_string())
    }

    /// Colour and opacity at `v`, clamped to the end points.
    pub fn eval(&self, v: f32) -> ([f32; 3], f32) {
        let pts = &self.points;
        let i = pts.partition_point(|p| p.value <= v);
        if i == 0 {
            return (pts[0].colour, pts[0].opacity);
        }
        if i == pts.len() {
            let p = pts[i - 1];
            return (p.colour, p.opacity);
        }
        let (a, b) = (pts[i - 1], pts[i]);
        let f = (v - a.value) / (b.value - a.value);
        let mix = |x: f32, y: f32| x + (y - x) * f;
        (
            [
                mix(a.colour[0], b.colour[0]),
                mix(a.colour[1], b.colour[1]),
                mix(a.colour[2], b.colour[2]),
            ],
            mix(a.opacity, b.opacity),
        )
    }
}

/// Entries of a [`TransferTable`].
pub const TABLE_ENTRIES: usize = 4096;

/// A transfer function tabulated for one ray step: per entry the opacity of one step (corrected
/// from per-voxel-length opacity: `1 - (1 - a)^(step / voxel)`) and the colour premultiplied
/// by it; and which entries are transparent, for empty-space skipping.
#[derive(Clone, Debug)]
pub struct TransferTable {
    lo: f32,
    scale: f32,
    entries: Vec<[f32; 4]>,
    /// `opaque_before[i]`: entries below `i` with a non-zero opacity.
    opaque_before: Vec<u32>,
}

impl TransferTable {
    /// Tabulates `tf` for steps of `step_over_voxel` voxel lengths.
    pub fn new(tf: &TransferFunction, step_over_voxel: f32) -> TransferTable {
        let lo = tf.points[0].value;
        let hi = tf.points[tf.points.len() - 1].value;
        let scale = (TABLE_ENTRIES - 1) as f32 / (hi - lo);
        let mut entries = Vec::with_capacity(TABLE_ENTRIES);
        let mut opaque_before = Vec::with_capacity(TABLE_ENTRIES + 1);
        opaque_before.push(0);
        for i in 0..TABLE_ENTRIES {
            let v = lo + (hi - lo) * (i as f32 / (TABLE_ENTRIES - 1) as f32);
            let (c, a) = tf.eval(v);
            // In f64 and rounded once, so the table does not depend on a libm's f32 powf.
            let a = (1.0 - (1.0 - f64::from(a)).powf(f64::from(step_over_voxel))) as f32;
            let a = a.clamp(0.0, 1.0);
            entries.push([c[0] * a, c[1] * a, c[2] * a, a]);
            let last = *opaque_before.last().unwrap_or(&0);
            opaque_before.push(last + u32::from(a > 0.0));
        }
        TransferTable {
            lo,
            scale,
            entries,
            opaque_before,
        }
    }

    /// The entry index of value `v` (clamped to the table).
    #[inline]
    pub fn index(&self, v: f32) -> usize {
        let x = (v - self.lo) * self.scale + 0.5;
        // `as` saturates: NaN and negatives go to 0, the rest is clamped below.
        (x as usize).min(TABLE_ENTRIES - 1)
    }

    /// Premultiplied colour and opacity of one step through material of value `v`.
    #[inline]
    pub fn lookup(&self, v: f32) -> [f32; 4] {
        self.entries[self.index(v)]
    }

    /// Whether every value in `[min, max]` is transparent (with a margin of one entry on each
    /// side for a value rounded just outside its voxels' range).
    pub fn transparent(&self, min: f32, max: f32) -> bool {
        let a = self.index(min).saturating_sub(1);
        let b = (self.index(max) + 2).min(TABLE_ENTRIES);
        self.opaque_before[b] == self.opaque_before[a]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_check_out() {
        for name in PRESETS {
            TransferFunction::preset(name).unwrap().check().unwrap();
        }
        assert!(TransferFunction::preset("nope").is_none());
    }

    #[test]
    fn parses_toml_and_refuses_non_monotone_values() {
        let good = "[[point]]\nvalue = 0.0\ncolour = [0, 0, 0]\nopacity = 0\n\
                    [[point]]\nvalue = 1.0\ncolour = [1, 1, 1]\nopacity = 1\n";
        let tf = TransferFunction::parse(good).unwrap();
        assert_eq!(tf.eval(0.5), ([0.5; 3], 0.5));
        let bad = good.replace("value = 1.0", "value = 0.0");
        let e = TransferFunction::parse(&bad).unwrap_err();
        assert!(
            e.contains("point 1") && e.contains("strictly increasing"),
            "{e}"
        );
        let e = TransferFunction::parse("[[point]]\nvalue = 1\n").unwrap_err();
        assert!(e.contains("missing field"), "{e}");
        let e = TransferFunction::parse(&good.replace("opacity = 1", "opacity = 2")).unwrap_err();
        assert!(e.contains("[0, 1]"), "{e}");
        let e = TransferFunction::parse(&good.replace("value = 1.0", "value = nan")).unwrap_err();
        assert!(e.contains("not finite"), "{e}");
    }

    #[test]
    fn load_names_the_file() {
        let e = TransferFunction::load("/nonexistent/tf.toml").unwrap_err();
        assert!(e.contains("/nonexistent/tf.toml"), "{e}");
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("tf.toml");
        std::fs::write(&p, "not = [toml").unwrap();
        let e = TransferFunction::load(p.to_str().unwrap()).unwrap_err();
        assert!(
            e.contains("tf.toml") && e.contains("bad transfer function"),
            "{e}"
        );
    }

    #[test]
    fn table_marks_transparent_ranges() {
        let tf = TransferFunction::preset("ct-bone").unwrap();
        let t = TransferTable::new(&tf, 0.5);
        assert!(t.transparent(-1000.0, 100.0));
        assert!(!t.transparent(-1000.0, 500.0));
        assert!(!t.transparent(600.0, 700.0));
        assert_eq!(t.lookup(-2000.0)[3], 0.0);
        // Opacity of half a voxel is less than that of a whole one.
        let one = TransferTable::new(&tf, 1.0);
        assert!(t.lookup(700.0)[3] < one.lookup(700.0)[3]);
    }
}
