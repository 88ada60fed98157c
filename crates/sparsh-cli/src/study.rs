//! `sparsh study`: speed against accuracy of the contact solver rungs, their stability map and
//! the table `solver = "auto"` reads (`sparsh_contact::study`), with charts drawn by plotters in
//! DejaVu Sans (bundled in `assets/fonts`, so no system font is needed).

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result, anyhow, bail};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::FontStyle;
use sparsh_contact::study::{
    Outcome, SWEEPS, StabilityPoint, Study, StudyOptions, StudyPoint, TABLE_SWEEPS, run_study,
    update_table,
};
use sparsh_scene::auto::SolverTable;
use sparsh_scene::{RungLimits, SolverKind};

const FONT: &[u8] = include_bytes!("../../../assets/fonts/DejaVuSans.ttf");
const SANS: &str = "sans-serif";

/// Runs the study on one thread (the stability points on `jobs` threads, one each), writes
/// `study.csv`, `stability.csv`, `solver_table.csv` and the charts (PNG and SVG) into `out`,
/// and the table also to `table` when given. With
/// `sweeps`, only those stability sweeps: their rows replace theirs in `out/stability.csv` (the
/// other sweeps' rows kept, a new file if there is none) and, given `table`, in the solver table
/// there; the charts are a whole study's.
pub fn study(
    out: &Path,
    quick: bool,
    table: Option<&Path>,
    sweeps: Vec<String>,
    jobs: usize,
) -> Result<()> {
    if jobs == 0 {
        bail!("--jobs: must be at least 1");
    }
    if let Some(unknown) = sweeps.iter().find(|s| !SWEEPS.contains(&s.as_str())) {
        bail!(
            "--sweep: no sweep named {unknown:?} (the sweeps: {})",
            SWEEPS.join(", ")
        );
    }
    let partial = !sweeps.is_empty();
    // A study of some sweeps updates an existing table: read it before the hours of solving.
    let earlier = match table {
        Some(path) if partial => {
            if let Some(rowless) = sweeps.iter().find(|s| !TABLE_SWEEPS.contains(&s.as_str())) {
                bail!(
                    "--table: the {rowless} sweep has no rows in the solver table (those that \
                     do: {})",
                    TABLE_SWEEPS.join(", ")
                );
            }
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("{}: cannot read the solver table", path.display()))?;
            let parsed = SolverTable::parse(&text)
                .map_err(|e| anyhow!("{}: not a solver table: {e}", path.display()))?;
            Some(parsed)
        }
        _ => None,
    };
    let options = StudyOptions {
        sweeps,
        jobs,
        ..if quick {
            StudyOptions::quick()
        } else {
            StudyOptions::full()
        }
    };
    std::fs::create_dir_all(out).with_context(|| format!("{}: cannot create", out.display()))?;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .context("cannot start the study's thread pool")?;
    let start = Instant::now();
    let study = pool.install(|| run_study(&options, &mut |line| eprintln!("{line}")));
    let seconds = start.elapsed().as_secs_f64();

    if partial {
        let stability = out.join("stability.csv");
        let kept = match std::fs::read_to_string(&stability) {
            Ok(text) => text
                .lines()
                .skip(1)
                .filter(|l| {
                    !study
                        .options
                        .sweeps
                        .iter()
                        .any(|s| l.starts_with(&format!("{s},")))
                })
                .map(|l| format!("{l}\n"))
                .collect::<String>(),
            Err(_) => String::new(),
        };
        let fresh = study.stability_csv();
        let (header, rows) = fresh.split_once('\n').unwrap_or((&fresh, ""));
        write_atomic(&stability, format!("{header}\n{kept}{rows}").as_bytes())?;
        if let (Some(path), Some(earlier)) = (table, earlier) {
            let updated = update_table(&earlier, &study);
            let sidecar = path.with_extension("json");
            let mut provenance: serde_json::Value = std::fs::read_to_string(&sidecar)
                .ok()
                .and_then(|t| serde_json::from_str(&t).ok())
                .filter(serde_json::Value::is_object)
                .unwrap_or_else(|| serde_json::json!({}));
            let update = serde_json::json!({
                "sweeps": study.options.sweeps,
                "written_by": format!(
                    "sparsh {} study{} --sweep {}",
                    env!("CARGO_PKG_VERSION"),
                    if quick { " --quick" } else { "" },
                    study.options.sweeps.join(",")
                ),
                "unix_time_s": unix_time_s(),
            });
            match provenance.get_mut("updated").and_then(|u| u.as_array_mut()) {
                Some(list) => list.push(update),
                None => provenance["updated"] = serde_json::json!([update]),
            }
            write_atomic(path, updated.to_csv().as_bytes())?;
            write_atomic(&sidecar, provenance.to_string().as_bytes())?;
            eprintln!(
                "{}: the rows of {} replaced",
                path.display(),
                study.options.sweeps.join(", ")
            );
        }
        eprintln!(
            "{} sweep points in {seconds:.0} s; {} written",
            study.stability.len() / SolverKind::ALL.len(),
            stability.display()
        );
        return Ok(());
    }
    write_atomic(&out.join("stability.csv"), study.stability_csv().as_bytes())?;
    write_atomic(&out.join("study.csv"), study.points_csv().as_bytes())?;
    let table_csv = study.table.to_csv();
    // provenance beside the data, not inside it, so default CSV readers take the file as it is
    let provenance = serde_json::json!({
        "written_by": format!("sparsh {} study{}", env!("CARGO_PKG_VERSION"), if quick { " --quick" } else { "" }),
        "unix_time_s": unix_time_s(),
        "threads": 1,
        "what": sparsh_scene::auto::SolverTable::DESCRIPTION,
    })
    .to_string();
    for csv in std::iter::once(out.join("solver_table.csv")).chain(table.map(Path::to_path_buf)) {
        write_atomic(&csv, table_csv.as_bytes())?;
        write_atomic(&csv.with_extension("json"), provenance.as_bytes())?;
    }

    plotters::style::register_font(SANS, FontStyle::Normal, FONT)
        .map_err(|_| anyhow!("assets/fonts/DejaVuSans.ttf is not a usable font"))?;
    let half_space = |p: &StudyPoint| !p.scene.starts_with("bonded_layer");
    render(
        &out.join("error_vs_time"),
        (1100, 760),
        &ErrorVsTime {
            study: &study,
            keep: &half_space,
            title: "Force error against time per frame: Hertz, flat punch, cone, Cattaneo–Mindlin",
        },
    )?;
    render(
        &out.join("error_vs_time_layers"),
        (1100, 760),
        &ErrorVsTime {
            study: &study,
            keep: &|p: &StudyPoint| !half_space(p),
            title: "Force error against time per frame: sphere on bonded layers, a/h = 0.01 … 1",
        },
    )?;
    for rung in SolverKind::ALL {
        render(
            &out.join(format!("stability_{}", rung.name())),
            (1300, 860),
            &StabilityMap {
                study: &study,
                rung,
            },
        )?;
    }

    println!(
        "study: {} accuracy points, {} stability points in {seconds:.1} s (one thread) → {}",
        study.points.len(),
        study.stability.len(),
        out.display()
    );
    for rung in SolverKind::ALL {
        let count = |o: Outcome| {
            study
                .stability
                .iter()
                .filter(|p| p.rung == rung && p.measurement.outcome == o)
                .count()
        };
        let counts: Vec<String> = Outcome::ALL
            .iter()
            .map(|&o| format!("{} {}", o.name(), count(o)))
            .collect();
        println!("stability {:<9}: {}", rung.name(), counts.join(", "));
    }
    Ok(())
}

/// Writes through a temporary file beside `path`, then renames.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    sparsh_data::write_atomic(path, bytes)
        .with_context(|| format!("{}: cannot write", path.display()))
}

/// Something drawn on any plotters backend.
trait Chart {
    fn draw<DB: DrawingBackend>(&self, area: &DrawingArea<DB, Shift>) -> Result<()>;
}

fn chart_err(e: impl std::fmt::Display) -> anyhow::Error {
    anyhow!("chart: {e}")
}

/// Draws `chart` to `stem.png` and `stem.svg`.
fn render(stem: &Path, (w, h): (u32, u32), chart: &impl Chart) -> Result<()> {
    let mut rgb = vec![0u8; (w * h * 3) as usize];
    {
        let area = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        chart.draw(&area)?;
        area.present().map_err(chart_err)?;
    }
    let image = image::RgbImage::from_raw(w, h, rgb).context("chart: buffer size")?;
    let png = sparsh_data::encode_png(&image).map_err(chart_err)?;
    write_atomic(&stem.with_extension("png"), &png)?;
    let mut svg = String::new();
    {
        let area = SVGBackend::with_string(&mut svg, (w, h)).into_drawing_area();
        chart.draw(&area)?;
        area.present().map_err(chart_err)?;
    }
    write_atomic(&stem.with_extension("svg"), svg.as_bytes())
}

fn rung_color(rung: SolverKind) -> RGBColor {
    match rung {
        SolverKind::Geometric => RGBColor(86, 180, 233),
        SolverKind::Halfspace => RGBColor(230, 159, 0),
        SolverKind::Layered => RGBColor(0, 114, 178),
        SolverKind::Fem => RGBColor(204, 121, 167),
    }
}

/// Errors are drawn from here up on the log axis (a point exactly on the answer).
const ERROR_FLOOR: f64 = 1e-6;

/// A point of a rung's line: (mean ms per frame, worst |relative force error|, a/cell).
type LinePoint = (f64, f64, f64);

/// Worst |relative force error| over the kept scenes against mean time per frame, per rung and
/// resolution; faint markers for each scene; the Pareto front over the rung lines.
struct ErrorVsTime<'a> {
    study: &'a Study,
    keep: &'a dyn Fn(&StudyPoint) -> bool,
    title: &'a str,
}

impl ErrorVsTime<'_> {
    /// Per rung: (mean ms per frame, worst error, a/cell) at each resolution where every kept
    /// scene was solved.
    fn lines(&self) -> Vec<(SolverKind, Vec<LinePoint>)> {
        SolverKind::ALL
            .iter()
            .map(|&rung| {
                let line = self
                    .study
                    .options
                    .contact_cells
                    .iter()
                    .filter_map(|&cells| {
                        let at: Vec<&StudyPoint> = self
                            .study
                            .points
                            .iter()
                            .filter(|p| p.rung == rung && p.a_over_cell == cells && (self.keep)(p))
                            .collect();
                        let errors: Vec<f64> =
                            at.iter().filter_map(|p| p.measurement.rel_error).collect();
                        if errors.is_empty() || errors.len() < at.len() {
                            return None;
                        }
                        let ms = at.iter().map(|p| p.measurement.ms_per_frame).sum::<f64>()
                            / at.len() as f64;
                        let worst = errors.iter().fold(0.0f64, |m, e| m.max(e.abs()));
                        Some((ms, worst.max(ERROR_FLOOR), cells))
                    })
                    .collect();
                (rung, line)
            })
            .collect()
    }
}

/// The points no other point beats in both time and error, by increasing time.
fn pareto_front(points: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let mut sorted = points.to_vec();
    sorted.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    let mut front: Vec<(f64, f64)> = Vec::new();
    for p in sorted {
        if front.last().is_none_or(|last| p.1 < last.1) {
            front.push(p);
        }
    }
    front
}

impl Chart for ErrorVsTime<'_> {
    fn draw<DB: DrawingBackend>(&self, area: &DrawingArea<DB, Shift>) -> Result<()> {
        area.fill(&WHITE).map_err(chart_err)?;
        let lines = self.lines();
        let scene_points: Vec<(SolverKind, f64, f64)> = self
            .study
            .points
            .iter()
            .filter(|p| (self.keep)(p))
            .filter_map(|p| {
                p.measurement
                    .rel_error
                    .map(|e| (p.rung, p.measurement.ms_per_frame, e.abs().max(ERROR_FLOOR)))
            })
            .collect();
        let xs = scene_points.iter().map(|p| p.1);
        let ys = scene_points.iter().map(|p| p.2);
        let (x0, x1) = xs.fold((f64::INFINITY, 0.0f64), |(a, b), x| (a.min(x), b.max(x)));
        let (y0, y1) = ys.fold((f64::INFINITY, 0.0f64), |(a, b), y| (a.min(y), b.max(y)));
        if !(x0.is_finite() && y0.is_finite()) {
            return Err(anyhow!("chart: no solved point to draw"));
        }
        let mut chart = ChartBuilder::on(area)
            .caption(self.title, (SANS, 22))
            .margin(14)
            .x_label_area_size(50)
            .y_label_area_size(80)
            .build_cartesian_2d(
                ((x0 / 2.0).max(1e-3)..x1 * 2.0).log_scale(),
                (y0 / 3.0..y1 * 3.0).log_scale(),
            )
            .map_err(chart_err)?;
        chart
            .configure_mesh()
            .x_desc("time per frame (ms, one thread)")
            .y_desc("|relative force error| (worst over scenes)")
            .label_style((SANS, 15))
            .axis_desc_style((SANS, 17))
            .x_label_formatter(&|v| format!("{v}"))
            .y_label_formatter(&|v| format!("{v:.0e}"))
            .draw()
            .map_err(chart_err)?;
        chart
            .draw_series(
                scene_points.iter().map(|&(rung, x, y)| {
                    Circle::new((x, y), 3, rung_color(rung).mix(0.35).filled())
                }),
            )
            .map_err(chart_err)?;
        for (rung, line) in &lines {
            let color = rung_color(*rung);
            let xy: Vec<(f64, f64)> = line.iter().map(|p| (p.0, p.1)).collect();
            chart
                .draw_series(LineSeries::new(xy.clone(), color.stroke_width(3)))
                .map_err(chart_err)?
                .label(rung.name())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 24, y)], color.stroke_width(3))
                });
            chart
                .draw_series(xy.iter().map(|&p| Circle::new(p, 6, color.filled())))
                .map_err(chart_err)?;
            chart
                .draw_series(line.iter().map(|&(x, y, cells)| {
                    EmptyElement::at((x, y))
                        + Text::new(
                            format!("{cells}"),
                            (7, -20),
                            (SANS, 15).into_font().color(&BLACK),
                        )
                }))
                .map_err(chart_err)?;
        }
        let all: Vec<(f64, f64)> = lines
            .iter()
            .flat_map(|(_, l)| l.iter().map(|p| (p.0, p.1)))
            .collect();
        let front = pareto_front(&all);
        chart
            .draw_series(LineSeries::new(
                front.clone(),
                BLACK.mix(0.6).stroke_width(1),
            ))
            .map_err(chart_err)?
            .label("Pareto front")
            .legend(|(x, y)| {
                EmptyElement::at((x + 12, y)) + Circle::new((0, 0), 8, BLACK.stroke_width(2))
            });
        chart
            .draw_series(
                front
                    .iter()
                    .map(|&p| Circle::new(p, 10, BLACK.stroke_width(2))),
            )
            .map_err(chart_err)?;
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .label_font((SANS, 16))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()
            .map_err(chart_err)?;
        area.draw(&Text::new(
            "labels: contact radius in grid cells; faint dots: single scenes",
            (100, 40),
            (SANS, 14).into_font().color(&BLACK.mix(0.7)),
        ))
        .map_err(chart_err)?;
        Ok(())
    }
}

fn outcome_color(o: Outcome) -> RGBColor {
    match o {
        Outcome::Ok => RGBColor(120, 198, 121),
        Outcome::OverTolerance => RGBColor(253, 174, 97),
        Outcome::NotConverged => RGBColor(215, 48, 39),
        Outcome::OutOfValidity => RGBColor(171, 171, 171),
        Outcome::NonFinite => RGBColor(40, 40, 40),
        Outcome::Panic => RGBColor(197, 27, 125),
    }
}

/// One rung's stability map: a row per swept parameter (the depth sweep a row per friction
/// coefficient), a cell per value, coloured by outcome and labelled with the value and the force
/// error.
struct StabilityMap<'a> {
    study: &'a Study,
    rung: SolverKind,
}

impl Chart for StabilityMap<'_> {
    fn draw<DB: DrawingBackend>(&self, area: &DrawingArea<DB, Shift>) -> Result<()> {
        area.fill(&WHITE).map_err(chart_err)?;
        let points: Vec<_> = self
            .study
            .stability
            .iter()
            .filter(|p| p.rung == self.rung)
            .collect();
        let row_of = |p: &StabilityPoint| {
            if p.sweep == "depth_over_thickness" {
                format!("depth/thickness, μ {}", p.friction)
            } else if p.sweep == "press_slide" {
                format!("press and slide, μ {}", p.friction)
            } else {
                p.sweep.replace('_', " ")
            }
        };
        let mut sweeps: Vec<String> = Vec::new();
        for p in &points {
            if !sweeps.contains(&row_of(p)) {
                sweeps.push(row_of(p));
            }
        }
        let columns = sweeps
            .iter()
            .map(|s| points.iter().filter(|p| row_of(p) == *s).count())
            .max()
            .unwrap_or(1);
        let (w, h) = area.dim_in_pixel();
        let (left, top, bottom) = (190i32, 60i32, 60i32);
        let cell_w = (w as i32 - left - 20) / columns as i32;
        let cell_h = (h as i32 - top - bottom) / sweeps.len().max(1) as i32;
        let tolerance = 100.0 * self.study.options.tolerance;
        area.draw(&Text::new(
            format!(
                "Stability map, {} rung: force error against the reference (pass: within ±{tolerance} %)",
                self.rung.name()
            ),
            (20, 18),
            (SANS, 21).into_font().color(&BLACK),
        ))
        .map_err(chart_err)?;
        let font = |size| (SANS, size).into_font().color(&BLACK);
        for (row, sweep) in sweeps.iter().enumerate() {
            let y = top + row as i32 * cell_h;
            area.draw(&Text::new(
                sweep.clone(),
                (12, y + cell_h / 2 - 8),
                font(16),
            ))
            .map_err(chart_err)?;
            for (col, p) in points.iter().filter(|p| row_of(p) == *sweep).enumerate() {
                let x = left + col as i32 * cell_w;
                let m = &p.measurement;
                area.draw(&Rectangle::new(
                    [(x + 2, y + 2), (x + cell_w - 2, y + cell_h - 2)],
                    outcome_color(m.outcome).filled(),
                ))
                .map_err(chart_err)?;
                let detail = match (m.outcome, m.rel_error) {
                    (Outcome::Ok | Outcome::OverTolerance, Some(e)) => {
                        format!("{:+.2} %", 100.0 * e)
                    }
                    (o, _) => o.name().replace('_', " "),
                };
                // The row names the friction; the cell, the depth.
                let value = p.label.split(',').next().unwrap_or(&p.label);
                area.draw(&Text::new(value.to_string(), (x + 8, y + 8), font(15)))
                    .map_err(chart_err)?;
                area.draw(&Text::new(detail, (x + 8, y + cell_h / 2 + 2), font(15)))
                    .map_err(chart_err)?;
            }
        }
        let mut x = left;
        let y = h as i32 - bottom + 20;
        for o in Outcome::ALL {
            area.draw(&Rectangle::new(
                [(x, y), (x + 18, y + 18)],
                outcome_color(o).filled(),
            ))
            .map_err(chart_err)?;
            area.draw(&Text::new(
                o.name().replace('_', " "),
                (x + 24, y + 1),
                font(15),
            ))
            .map_err(chart_err)?;
            x += 170;
        }
        Ok(())
    }
}

fn unix_time_s() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// `sparsh limits`: each rung's validity limits at `tolerance`, per friction coefficient of the
/// depth sweep, as a Markdown table on stdout.
pub fn limits(tolerance: f64) -> Result<()> {
    if !(tolerance > 0.0 && tolerance < 1.0) {
        bail!("--tolerance: must be a relative force error in (0, 1), got {tolerance}");
    }
    let table = SolverTable::builtin();
    let mut frictions = table.swept_frictions();
    if frictions.is_empty() {
        frictions.push(0.0);
    }
    println!(
        "| rung | friction μ up to | a/h up to | δ/h up to | δ/h up to, sliding | best studied error |"
    );
    println!("|---|---|---|---|---|---|");
    let depth = |d: f64| {
        if d.is_finite() {
            format!("{d}")
        } else {
            "not swept".into()
        }
    };
    for rung in SolverKind::ALL {
        for (k, &friction) in frictions.iter().enumerate() {
            let limits = RungLimits::of(table, rung, tolerance, friction);
            let (a_over_h, depth, sliding) = match limits.max_a_over_h {
                Some(a) => (
                    format!("{a}"),
                    depth(limits.max_depth_over_h),
                    depth(limits.max_sliding_depth_over_h),
                ),
                None => ("nowhere".into(), "nowhere".into(), "nowhere".into()),
            };
            // Past the largest swept friction a press sticks wholly: its limits hold.
            let mu = if k + 1 == frictions.len() {
                "any".to_string()
            } else {
                format!("{friction}")
            };
            println!(
                "| {} | {mu} | {a_over_h} | {depth} | {sliding} | {:.2} % |",
                rung.name(),
                100.0 * limits.best_rel_error
            );
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::pareto_front;

    #[test]
    fn pareto_front_keeps_only_undominated_points() {
        let points = [(1.0, 0.5), (2.0, 0.6), (3.0, 0.1), (0.5, 0.9), (4.0, 0.1)];
        assert_eq!(
            pareto_front(&points),
            vec![(0.5, 0.9), (1.0, 0.5), (3.0, 0.1)]
        );
    }
}
