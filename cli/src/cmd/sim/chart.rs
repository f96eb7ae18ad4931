//! `rayfarm sim chart`: domain loads and simulated frame time against the worker count, a
//! line per schedule on log-log axes, drawn from the CSV files of `rayfarm sim --csv` (clean
//! runs only), so that runs made apart (one worker count at a time) go into one chart.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, anyhow, bail};
use clap::Args;
use plotters::coord::Shift;
use plotters::prelude::*;

use crate::bench::chart::{FAMILY, plot_error, write_side_by_side};

/// Size of the whole image, pixels.
const SIZE: (u32, u32) = (1200, 540);

/// Options of `rayfarm sim chart`.
#[derive(Args, Clone, Debug)]
pub struct ChartArgs {
    /// CSV files written by `rayfarm sim --csv`, separated by commas.
    #[arg(long, value_delimiter = ',', required = true)]
    pub csv: Vec<PathBuf>,
    /// The PNG to write.
    #[arg(long)]
    pub out: PathBuf,
    /// The chart's title.
    #[arg(
        long,
        default_value = "rayfarm sim: loads and frame time against workers"
    )]
    pub title: String,
}

/// One clean run read back: (workers, domain loads, virtual ms).
type Point = (f64, f64, f64);

/// `rayfarm sim chart`: reads the runs and writes the chart.
pub(super) fn run_chart(c: ChartArgs) -> anyhow::Result<()> {
    let mut series: BTreeMap<String, Vec<Point>> = BTreeMap::new();
    for path in &c.csv {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        for (schedule, point) in clean_runs(&text).with_context(|| path.display().to_string())? {
            series.entry(schedule).or_default().push(point);
        }
    }
    if series.is_empty() {
        bail!("no clean run with a frame time in the CSV files");
    }
    for points in series.values_mut() {
        points.sort_by(|a, b| a.0.total_cmp(&b.0));
    }
    write(&c.out, &c.title, &series)?;
    println!("wrote {}", c.out.display());
    Ok(())
}

/// The clean runs of a CSV text, by schedule.
fn clean_runs(text: &str) -> anyhow::Result<Vec<(String, Point)>> {
    let mut lines = text.lines();
    let header = split(lines.next().ok_or_else(|| anyhow!("empty CSV"))?);
    let col = |name: &str| {
        header
            .iter()
            .position(|h| h == name)
            .ok_or_else(|| anyhow!("no column {name}"))
    };
    let (workers, schedule, seed, ms, loads) = (
        col("workers")?,
        col("schedule")?,
        col("seed")?,
        col("virtual_ms")?,
        col("loads")?,
    );
    let mut out = Vec::new();
    for (n, line) in lines.enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let f = split(line);
        let field = |i: usize| {
            f.get(i)
                .map(String::as_str)
                .ok_or_else(|| anyhow!("line {}: too few fields", n + 2))
        };
        if field(seed)? != "clean" {
            continue;
        }
        let number = |i: usize| -> anyhow::Result<f64> {
            field(i)?
                .parse()
                .map_err(|e| anyhow!("line {}: {e}", n + 2))
        };
        let point = (number(workers)?, number(loads)?, number(ms)?);
        // A run that did not finish has no frame time.
        if point.2.is_finite() && point.0 > 0.0 {
            out.push((field(schedule)?.to_string(), point));
        }
    }
    Ok(out)
}

/// The fields of one CSV line; quoted fields may hold commas and doubled quotes.
fn split(line: &str) -> Vec<String> {
    let mut fields = vec![String::new()];
    let mut quoted = false;
    let mut chars = line.chars().peekable();
    while let Some(ch) = chars.next() {
        match (ch, quoted) {
            ('"', true) if chars.peek() == Some(&'"') => {
                chars.next();
                if let Some(f) = fields.last_mut() {
                    f.push('"');
                }
            }
            ('"', _) => quoted = !quoted,
            (',', false) => fields.push(String::new()),
            (ch, _) => {
                if let Some(f) = fields.last_mut() {
                    f.push(ch);
                }
            }
        }
    }
    fields
}

/// Draws the two panels and writes the PNG.
fn write(path: &Path, title: &str, series: &BTreeMap<String, Vec<Point>>) -> anyhow::Result<()> {
    write_side_by_side(path, SIZE, title, |left, right| {
        panel(left, "domain loads", series, |p| p.1)?;
        panel(right, "simulated frame time, ms", series, |p| p.2)
    })
}

/// One log-log panel: `value` of every run against its workers, a line per schedule.
fn panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    caption: &str,
    series: &BTreeMap<String, Vec<Point>>,
    value: impl Fn(&Point) -> f64,
) -> anyhow::Result<()> {
    let all = || series.values().flatten();
    let range = |f: &dyn Fn(&Point) -> f64| {
        let lo = all().map(f).filter(|v| *v > 0.0).fold(f64::MAX, f64::min);
        let hi = all().map(f).fold(0.0_f64, f64::max);
        // Log axes need positive bounds, with a margin around the points.
        let lo = if lo == f64::MAX { 1.0 } else { lo };
        (lo / 1.5, hi.max(lo) * 1.5)
    };
    let (w0, w1) = range(&|p| p.0);
    let (v0, v1) = range(&|p| value(p));
    let mut chart = ChartBuilder::on(area)
        .caption(caption, (FAMILY, 18).into_font())
        .margin(16)
        .x_label_area_size(36)
        .y_label_area_size(64)
        .build_cartesian_2d((w0..w1).log_scale(), (v0..v1).log_scale())
        .map_err(plot_error)?;
    chart
        .configure_mesh()
        .x_desc("workers")
        .x_label_formatter(&|v| format!("{v:.0}"))
        .y_label_formatter(&|v| format!("{v:.3}"))
        .label_style((FAMILY, 14).into_font())
        .draw()
        .map_err(plot_error)?;
    for (i, (schedule, points)) in series.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        let points: Vec<(f64, f64)> = points
            .iter()
            .map(|p| (p.0, value(p)))
            .filter(|p| p.1 > 0.0)
            .collect();
        chart
            .draw_series([PathElement::new(points.clone(), color.stroke_width(2))])
            .map_err(plot_error)?
            .label(schedule.clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
            });
        chart
            .draw_series(
                points
                    .into_iter()
                    .map(|p| Circle::new(p, 4, color.filled())),
            )
            .map_err(plot_error)?;
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font((FAMILY, 14).into_font())
        .position(SeriesLabelPosition::UpperLeft)
        .draw()
        .map_err(plot_error)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    const CSV: &str = "workers,schedule,seed,faults,virtual_ms,loads,bytes_loaded\n\
        64,image-plane,clean,\"none\",6381.2,19723,1\n\
        64,domain,clean,\"none\",142.6,2738,1\n\
        256,domain,clean,\"none\",80.5,3000,1\n\
        64,dynamic,7,\"kill 3, \"\"late\"\"\",99.0,10,1\n\
        256,image-plane,clean,\"none\",NaN,0,1\n";

    #[test]
    fn only_finished_clean_runs_are_read_and_quoted_commas_hold() {
        let runs = clean_runs(CSV).unwrap();
        let names: Vec<&str> = runs.iter().map(|(s, _)| s.as_str()).collect();
        assert_eq!(names, ["image-plane", "domain", "domain"]);
        assert_eq!(runs[2].1, (256.0, 3000.0, 80.5));
        assert_eq!(split("a,\"b, \"\"c\"\"\",d"), ["a", "b, \"c\"", "d"]);
    }

    #[test]
    fn the_chart_is_a_png_with_lines() {
        let mut series: BTreeMap<String, Vec<Point>> = BTreeMap::new();
        for (s, p) in clean_runs(CSV).unwrap() {
            series.entry(s).or_default().push(p);
        }
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("scale.png");
        write(&path, "test", &series).unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), SIZE);
        let coloured = img
            .pixels()
            .filter(|p| p.0.iter().max().unwrap() - p.0.iter().min().unwrap() > 80)
            .count();
        assert!(coloured > 200, "{coloured} coloured pixels");
    }
}
