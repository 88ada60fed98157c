//! The ablation's report: `ablation.csv` (one row per variant and model, every score and its
//! interval), `ablation.md` (the table) and `ablation.png` / `.svg` (median centre and radius
//! errors as bars with their 95 % intervals).

use std::path::Path;

use plotters::prelude::*;

use super::{Row, RowKind};
use crate::Error;

const HEADER: [&str; 22] = [
    "variant",
    "model",
    "kind",
    "train_frames",
    "seeds",
    "mean_best_epoch",
    "centre_median_px",
    "centre_median_ci_low",
    "centre_median_ci_high",
    "centre_p90_px",
    "radius_median_px",
    "radius_p90_px",
    "radius_median_pct",
    "radius_median_pct_ci_low",
    "radius_median_pct_ci_high",
    "radius_p90_pct",
    "within_3px_5pct",
    "within_5px_10pct",
    "synthetic_val_centre_median_px",
    "synthetic_val_radius_median_pct",
    "seconds",
    "row",
];

/// Rows in report order: the references, then the synthetic rows as run, then the ceiling.
fn ordered(rows: &[Row]) -> Vec<&Row> {
    let rank = |r: &Row| match r.kind {
        RowKind::Constant => 0,
        RowKind::Classical => 1,
        RowKind::Synthetic => 2,
        RowKind::RealConstant => 3,
        RowKind::RealCeiling => 4,
        RowKind::MarksRefit => 5,
    };
    let mut v: Vec<&Row> = rows.iter().collect();
    v.sort_by_key(|r| rank(r));
    v
}

fn label(r: &Row) -> String {
    match r.kind {
        RowKind::Synthetic => format!("{}: {}", r.variant, r.model),
        RowKind::RealCeiling => "real frames (held out): cnn".into(),
        RowKind::RealConstant => format!("constant ({} real frames not scored)", r.train_frames),
        RowKind::MarksRefit => {
            "label noise: circles fitted by rendering each frame, against its mark".into()
        }
        k => format!("{} ({} frames)", k.name(), r.variant),
    }
}

/// Writes the CSV, the Markdown table and the chart into `out`.
pub fn write(out: &Path, rows: &[Row]) -> Result<(), Error> {
    let rows = ordered(rows);
    let csv_path = out.join("ablation.csv");
    let mut w = csv::Writer::from_writer(Vec::new());
    w.write_record(HEADER)
        .map_err(|e| Error::file(&csv_path, e))?;
    for (i, r) in rows.iter().enumerate() {
        let s = &r.scores;
        let f = |v: f64| format!("{v:.4}");
        w.write_record([
            r.variant.clone(),
            r.model.clone(),
            r.kind.name().into(),
            r.train_frames.to_string(),
            r.seeds.to_string(),
            format!("{:.1}", r.mean_best_epoch),
            f(s.centre_median_px),
            f(s.centre_median_ci[0]),
            f(s.centre_median_ci[1]),
            f(s.centre_p90_px),
            f(s.radius_median_px),
            f(s.radius_p90_px),
            f(s.radius_median_pct),
            f(s.radius_median_pct_ci[0]),
            f(s.radius_median_pct_ci[1]),
            f(s.radius_p90_pct),
            f(s.within_3px_5pct),
            f(s.within_5px_10pct),
            r.synthetic_val.map_or(String::new(), |v| f(v[0])),
            r.synthetic_val.map_or(String::new(), |v| f(v[1])),
            format!("{:.1}", r.seconds),
            i.to_string(),
        ])
        .map_err(|e| Error::file(&csv_path, e))?;
    }
    let bytes = w.into_inner().map_err(|e| Error::file(&csv_path, e))?;
    crate::io::write_atomic(&csv_path, &bytes)?;
    crate::io::write_atomic(&out.join("ablation.md"), markdown(&rows).as_bytes())?;
    chart(out, &rows)
}

/// The Markdown table.
pub fn markdown(rows: &[&Row]) -> String {
    let mut md = String::from(
        "| row | kind | train frames | seeds | centre median px [95 % CI] | centre p90 px | radius median px | radius median % [95 % CI] | radius p90 % | ≤ 3 px & 5 % | ≤ 5 px & 10 % | synthetic validation: centre px, radius % |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        let s = &r.scores;
        md.push_str(&format!(
            "| {} | {} | {} | {} | {:.1} [{:.1}, {:.1}] | {:.1} | {:.1} | {:.1} [{:.1}, {:.1}] | {:.1} | {:.0} % | {:.0} % | {} |\n",
            label(r),
            r.kind.name(),
            r.train_frames,
            r.seeds,
            s.centre_median_px,
            s.centre_median_ci[0],
            s.centre_median_ci[1],
            s.centre_p90_px,
            s.radius_median_px,
            s.radius_median_pct,
            s.radius_median_pct_ci[0],
            s.radius_median_pct_ci[1],
            s.radius_p90_pct,
            100.0 * s.within_3px_5pct,
            100.0 * s.within_5px_10pct,
            r.synthetic_val
                .map_or("—".into(), |[c, p]| format!("{c:.1}, {p:.1}")),
        ));
    }
    md
}

fn chart_err(e: impl std::fmt::Display) -> Error {
    Error::file("ablation chart", e)
}

fn colour(kind: RowKind) -> RGBColor {
    match kind {
        RowKind::Synthetic => RGBColor(40, 100, 180),
        RowKind::RealCeiling => RGBColor(40, 150, 70),
        RowKind::RealConstant => RGBColor(150, 200, 160),
        _ => RGBColor(140, 140, 140),
    }
}

const SANS: &str = "sans-serif";

/// `ablation.png` and `ablation.svg`.
fn chart(out: &Path, rows: &[&Row]) -> Result<(), Error> {
    crate::io::register_sans()?;
    let (w, h) = (1400u32, 140 + 34 * rows.len() as u32);
    let mut rgb = vec![0u8; (w * h * 3) as usize];
    draw(
        BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area(),
        rows,
    )?;
    let img = image::RgbImage::from_raw(w, h, rgb).ok_or_else(|| chart_err("buffer size"))?;
    let png = sparsh_data::encode_png(&img).map_err(chart_err)?;
    crate::io::write_atomic(&out.join("ablation.png"), &png)?;
    let mut svg = String::new();
    draw(
        SVGBackend::with_string(&mut svg, (w, h)).into_drawing_area(),
        rows,
    )?;
    crate::io::write_atomic(&out.join("ablation.svg"), svg.as_bytes())
}

fn draw<DB: DrawingBackend>(
    area: DrawingArea<DB, plotters::coord::Shift>,
    rows: &[&Row],
) -> Result<(), Error> {
    area.fill(&WHITE).map_err(chart_err)?;
    let (w, _) = area.dim_in_pixel();
    let (left, right) = area.split_horizontally(w * 3 / 5);
    type Metric = fn(&Row) -> (f64, [f64; 2]);
    let panels: [(DrawingArea<DB, _>, &str, Metric, bool); 2] = [
        (
            left,
            "median contact-centre error (px), 95 % CI",
            |r: &Row| (r.scores.centre_median_px, r.scores.centre_median_ci),
            true,
        ),
        (
            right,
            "median radius error (%), 95 % CI",
            |r: &Row| (r.scores.radius_median_pct, r.scores.radius_median_pct_ci),
            false,
        ),
    ];
    let n = rows.len();
    for (panel, title, metric, labels) in panels {
        // rows that miss by far more than the typical one (the constant predictor, models that
        // do not transfer) are cut at the axis, four times the median row, and labelled
        let mut values: Vec<f64> = rows
            .iter()
            .map(|r| metric(r).0)
            .filter(|v| v.is_finite())
            .collect();
        values.sort_by(f64::total_cmp);
        let typical = if values.is_empty() {
            1.0
        } else {
            crate::stats::quantile(&values, 0.5)
        };
        let x1 = rows
            .iter()
            .map(|r| {
                let (v, ci) = metric(r);
                v.max(ci[1])
            })
            .filter(|v| v.is_finite())
            .fold(1e-3f64, f64::max)
            .min(4.0 * typical.max(1e-3))
            * 1.05;
        let mut c = ChartBuilder::on(&panel)
            .caption(title, (SANS, 20))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(if labels { 420 } else { 10 })
            .build_cartesian_2d(0.0..x1, -0.5..(n as f64 - 0.5))
            .map_err(chart_err)?;
        let names: Vec<String> = rows.iter().map(|r| label(r)).collect();
        c.configure_mesh()
            .disable_y_mesh()
            .y_labels(n)
            .y_label_formatter(&|v| {
                let k = v.round();
                if labels && (v - k).abs() < 1e-6 && k >= 0.0 && (k as usize) < n {
                    names[n - 1 - k as usize].clone()
                } else {
                    String::new()
                }
            })
            .label_style((SANS, 14))
            .draw()
            .map_err(chart_err)?;
        for (i, r) in rows.iter().enumerate() {
            let y = (n - 1 - i) as f64;
            let (v, ci) = metric(r);
            if !v.is_finite() {
                continue;
            }
            let col = colour(r.kind);
            c.draw_series(std::iter::once(Rectangle::new(
                [(0.0, y - 0.35), (v.min(x1), y + 0.35)],
                col.mix(0.75).filled(),
            )))
            .map_err(chart_err)?;
            if v > x1 {
                c.draw_series(std::iter::once(Text::new(
                    format!("{v:.1} →"),
                    (0.8 * x1, y + 0.1),
                    (SANS, 15).into_font(),
                )))
                .map_err(chart_err)?;
                continue;
            }
            if ci[0].is_finite() && ci[1].is_finite() {
                c.draw_series(std::iter::once(PathElement::new(
                    vec![(ci[0], y), (ci[1], y)],
                    BLACK.stroke_width(2),
                )))
                .map_err(chart_err)?;
                for x in ci {
                    c.draw_series(std::iter::once(PathElement::new(
                        vec![(x, y - 0.15), (x, y + 0.15)],
                        BLACK.stroke_width(2),
                    )))
                    .map_err(chart_err)?;
                }
            }
        }
    }
    area.present().map_err(chart_err)
}
