//! The bench chart: two bar panels side by side, median wall time (with a min-max whisker)
//! and median domain loads per schedule, as a PNG.
//!
//! Drawn with `plotters` into an RGB buffer and encoded by `image` (the PNG encoder the
//! workspace already has), and written with a font embedded in the binary (Ubuntu Light, from
//! `epaint_default_fonts`) through `ab_glyph`: no system fonts, fontconfig or FreeType, so the
//! chart looks the same on a bare server or in a container.

use std::path::Path;
use std::sync::OnceLock;

use anyhow::{Context, anyhow};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use super::ScheduleSummary;

/// Size of the whole image, pixels.
const SIZE: (u32, u32) = (1200, 520);

/// The family name the embedded font is registered under.
pub(crate) const FAMILY: &str = "sans-serif";

/// Registers the embedded font with plotters once per process.
pub(crate) fn register_font() -> anyhow::Result<()> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| {
        plotters::style::register_font(
            FAMILY,
            FontStyle::Normal,
            epaint_default_fonts::UBUNTU_LIGHT,
        )
        .is_ok()
    });
    ok.then_some(())
        .ok_or_else(|| anyhow!("the embedded chart font could not be read"))
}

/// Two panels side by side under `title`, in an image of `size` pixels, drawn by `draw`
/// (left, right) and written to `path` as PNG: the frame both the bench chart and
/// `rayfarm sim chart` draw into.
pub(crate) fn write_side_by_side(
    path: &Path,
    size: (u32, u32),
    title: &str,
    draw: impl for<'b> FnOnce(
        &DrawingArea<BitMapBackend<'b>, Shift>,
        &DrawingArea<BitMapBackend<'b>, Shift>,
    ) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    register_font()?;
    let mut rgb = vec![0u8; size.0 as usize * size.1 as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, size).into_drawing_area();
        root.fill(&WHITE).map_err(plot_error)?;
        let root = root
            .titled(title, (FAMILY, 22).into_font())
            .map_err(plot_error)?;
        let (left, right) = root.split_horizontally(size.0 / 2);
        draw(&left, &right)?;
        root.present().map_err(plot_error)?;
    }
    image::save_buffer_with_format(
        path,
        &rgb,
        size.0,
        size.1,
        image::ColorType::Rgb8,
        image::ImageFormat::Png,
    )
    .with_context(|| format!("writing the chart {}", path.display()))
}

/// Draws the chart of `summaries` under `title` and writes it to `path` as PNG.
pub fn write_chart(path: &Path, title: &str, summaries: &[ScheduleSummary]) -> anyhow::Result<()> {
    write_side_by_side(path, SIZE, title, |left, right| {
        let names: Vec<String> = summaries.iter().map(|s| s.schedule.clone()).collect();
        let times: Vec<Option<Bar>> = summaries
            .iter()
            .map(|s| {
                s.measured.as_ref().map(|m| Bar {
                    value: m.wall.median,
                    whisker: Some((m.wall.min, m.wall.max)),
                    label: format!("{:.2} s", m.wall.median),
                })
            })
            .collect();
        let loads: Vec<Option<Bar>> = summaries
            .iter()
            .map(|s| {
                s.measured.as_ref().map(|m| Bar {
                    value: m.domain_loads,
                    whisker: None,
                    label: super::report::count(m.domain_loads),
                })
            })
            .collect();
        panel(
            left,
            "median wall time, s (whisker: min-max)",
            &names,
            &times,
            &BLUE,
            &|v| format!("{v:.2}"),
        )?;
        panel(right, "median domain loads", &names, &loads, &RED, &|v| {
            super::report::count(v.round())
        })
    })
}

/// One bar: its height, an optional whisker (low, high) and the text above it.
struct Bar {
    value: f64,
    whisker: Option<(f64, f64)>,
    label: String,
}

/// One bar panel: a bar per schedule, "failed" where a schedule has no successful run.
fn panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    caption: &str,
    names: &[String],
    bars: &[Option<Bar>],
    color: &RGBColor,
    y_label: &dyn Fn(&f64) -> String,
) -> anyhow::Result<()> {
    let n = u32::try_from(names.len().max(1)).context("too many schedules to chart")?;
    let top = bars
        .iter()
        .flatten()
        .map(|b| b.whisker.map_or(b.value, |(_, hi)| hi.max(b.value)))
        .fold(0.0_f64, f64::max);
    let top = if top > 0.0 { top * 1.15 } else { 1.0 };
    let mut chart = ChartBuilder::on(area)
        .caption(caption, (FAMILY, 18).into_font())
        .margin(16)
        .x_label_area_size(32)
        .y_label_area_size(56)
        // An integer range is closed: 0..n-1 gives n segments.
        .build_cartesian_2d((0..n - 1).into_segmented(), 0.0..top)
        .map_err(plot_error)?;
    let label_of = |v: &SegmentValue<u32>| match v {
        SegmentValue::CenterOf(i) => names.get(*i as usize).cloned().unwrap_or_default(),
        _ => String::new(),
    };
    chart
        .configure_mesh()
        .disable_x_mesh()
        .x_labels(names.len() + 1)
        .x_label_formatter(&label_of)
        .y_label_formatter(y_label)
        .light_line_style(WHITE)
        .label_style((FAMILY, 15).into_font())
        .draw()
        .map_err(plot_error)?;
    let text = |size: i32| {
        (FAMILY, size)
            .into_font()
            .into_text_style(area)
            .pos(Pos::new(HPos::Center, VPos::Bottom))
    };
    for (i, bar) in (0..n).zip(bars) {
        let Some(bar) = bar else {
            chart
                .draw_series([Text::new(
                    "failed".to_string(),
                    (SegmentValue::CenterOf(i), top * 0.05),
                    text(16).color(&RED),
                )])
                .map_err(plot_error)?;
            continue;
        };
        let mut rect = Rectangle::new(
            [
                (SegmentValue::Exact(i), 0.0),
                (SegmentValue::Exact(i + 1), bar.value),
            ],
            color.mix(0.75).filled(),
        );
        rect.set_margin(0, 0, 18, 18);
        chart.draw_series([rect]).map_err(plot_error)?;
        let mut label_at = bar.value;
        if let Some((lo, hi)) = bar.whisker {
            chart
                .draw_series([PathElement::new(
                    vec![
                        (SegmentValue::CenterOf(i), lo),
                        (SegmentValue::CenterOf(i), hi),
                    ],
                    BLACK.stroke_width(2),
                )])
                .map_err(plot_error)?;
            label_at = label_at.max(hi);
        }
        chart
            .draw_series([Text::new(
                bar.label.clone(),
                (SegmentValue::CenterOf(i), label_at + top * 0.01),
                text(15),
            )])
            .map_err(plot_error)?;
    }
    Ok(())
}

/// A plotters error (generic over the backend) as an anyhow error.
pub(crate) fn plot_error(e: impl std::fmt::Display) -> anyhow::Error {
    anyhow!("drawing the chart: {e}")
}

#[cfg(test)]
mod tests {
    use super::super::summarize;
    use super::super::tests::{outcome, stats};
    use super::*;

    #[test]
    fn the_chart_is_a_png_with_bars_and_text() {
        let runs = vec![
            outcome(1, "dynamic", Ok(stats(2.0, 4, 1.0, 0.0, "h"))),
            outcome(2, "domain", Ok(stats(4.0, 40, 1.5, 0.5, "h"))),
            outcome(3, "image-plane", Err("UNIMPLEMENTED".into())),
        ];
        let names: Vec<String> = ["dynamic", "image-plane", "domain"]
            .map(String::from)
            .into();
        let summaries = summarize(&names, &runs);
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("chart.png");
        write_chart(&path, "scene x, 2 workers, 1 MiB cache each", &summaries).unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), SIZE);
        let pixels: Vec<&image::Rgb<u8>> = img.pixels().collect();
        // Blue-ish and red-ish bars, and dark text (the embedded font drew something).
        assert!(pixels.iter().any(|p| p[2] > 150 && p[0] < 120));
        assert!(pixels.iter().any(|p| p[0] > 150 && p[2] < 120));
        let dark = pixels
            .iter()
            .filter(|p| p[0] < 60 && p[1] < 60 && p[2] < 60)
            .count();
        assert!(dark > 1000, "{dark} dark pixels");
    }
}
