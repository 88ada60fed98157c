//! The report of a run: `results.csv` (one row per task, encoder, budget and metric), the
//! Markdown table `results.md`, and one label-budget chart per task (`budget_TASK.png` and
//! `.svg`: the task's first metric against the budget, one line per encoder, 95 % bootstrap
//! bands over test sequences; the random draws as their mean with their min–max band).

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use plotters::prelude::*;
use rayon::prelude::*;

use super::run::{EncoderKind, TaskRun, Unit};
use super::tasks::{Metric, Target, TaskKind, score};
use crate::Error;
use crate::io::{SANS, register_sans};
use crate::stats::{Spread, bootstrap_interval, rank};

/// One row of `results.csv`.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Row {
    /// Task.
    pub task: String,
    /// Encoder (a random group's summary row is `GROUP (K draws)`).
    pub encoder: String,
    /// `pretrained`, `random`, `random_draws`, `pixels`, `end_to_end`, `ridge`, `ceiling`,
    /// `floor` (the floor oracle) or `constant`.
    pub kind: String,
    /// Label budget (share of training sequences).
    pub budget: f64,
    /// Metric name.
    pub metric: String,
    /// Mean over probe seeds (over draws for a summary row).
    pub value: f64,
    /// Probe seeds averaged.
    pub seeds: usize,
    /// Standard deviation (n − 1) of the metric over those probe seeds, where there are several;
    /// for a summary row, the mean over the draws of each draw's.
    pub seeds_sd: Option<f64>,
    /// 95 % bootstrap interval over test sequences (empty for summary rows).
    pub ci_low: Option<f64>,
    /// Upper end of the interval.
    pub ci_high: Option<f64>,
    /// Summary rows: standard deviation, minimum and maximum over the draws.
    pub draws_sd: Option<f64>,
    /// Smallest draw.
    pub draws_min: Option<f64>,
    /// Largest draw.
    pub draws_max: Option<f64>,
    /// Pretrained rows: rank among the random draws of the same architecture (1 = best).
    pub rank: Option<usize>,
    /// Out of how many (the draws and the encoder).
    pub rank_of: Option<usize>,
    /// Labelled training sequences.
    pub train_sequences: usize,
    /// Labelled training samples.
    pub train_samples: usize,
    /// Test samples.
    pub test_samples: usize,
}

fn kind_name(k: EncoderKind) -> &'static str {
    match k {
        EncoderKind::Pretrained => "pretrained",
        EncoderKind::Random => "random",
        EncoderKind::Pixels => "pixels",
        EncoderKind::EndToEnd => "end_to_end",
        EncoderKind::Ridge | EncoderKind::Photometric => "ridge",
        EncoderKind::Ceiling => "ceiling",
        EncoderKind::Oracle | EncoderKind::OracleRidge => "floor",
    }
}

/// Predictions of the constant predictor fitted on `train` rows: the mean force, the majority
/// class of each head (what a model that learns nothing from the frames scores).
pub fn constant_predictions(tr: &TaskRun, train: &[usize]) -> Vec<Vec<f64>> {
    let samples = &tr.samples.samples;
    let majority = |f: &dyn Fn(&Target) -> usize, n: usize| -> f64 {
        let mut counts = vec![0usize; n];
        for &i in train {
            counts[f(&samples[i].target)] += 1;
        }
        (0..n)
            .max_by_key(|&c| (counts[c], usize::MAX - c))
            .unwrap_or(0) as f64
    };
    let pred: Vec<f64> = match tr.samples.kind {
        TaskKind::Force => {
            let mut m = vec![0.0; 3];
            for &i in train {
                if let Target::Force(f) = samples[i].target {
                    (0..3).for_each(|k| m[k] += f[k] / train.len() as f64);
                }
            }
            m
        }
        TaskKind::Slip => vec![
            majority(
                &|t| matches!(t, Target::Slip { cone: true, .. }) as usize,
                2,
            ),
            majority(
                &|t| match t {
                    Target::Slip { state, .. } => state.unwrap_or(0),
                    _ => 0,
                },
                3,
            ),
        ],
        TaskKind::Pose => (0..3)
            .map(|h| {
                let edges: &[f64] = if h == 2 {
                    &crate::tacbench::tasks::POSE_EDGES_DEG
                } else {
                    &crate::tacbench::tasks::POSE_EDGES_MM
                };
                majority(
                    &|t| match t {
                        Target::Pose(p) => crate::tacbench::tasks::bin_of(p[h], edges),
                        _ => 0,
                    },
                    11,
                )
            })
            .collect(),
        TaskKind::Texture | TaskKind::Grasp => vec![majority(
            &|t| match t {
                Target::Class(c) => *c,
                _ => 0,
            },
            tr.samples.classes.len().max(1),
        )],
    };
    vec![pred; samples.len()]
}

/// A unit's predictions on one test split.
type PredsOf = fn(&Unit) -> &[Vec<f64>];

/// Builds the rows of the report from the task runs and units.
pub fn rows(
    runs: &BTreeMap<TaskKind, TaskRun>,
    units: &[Unit],
    budgets: &[f64],
    draws: usize,
    seed: u64,
) -> Vec<Row> {
    let mut rows = Vec::new();
    for (&task, tr) in runs {
        let samples = &tr.samples.samples;
        let of_task: Vec<&Unit> = units.iter().filter(|u| u.task == task).collect();
        // (encoder, budget) → units over seeds
        let mut cells: BTreeMap<(String, u64), Vec<&Unit>> = BTreeMap::new();
        for u in &of_task {
            cells
                .entry((u.encoder.clone(), u.budget.to_bits()))
                .or_default()
                .push(u);
        }
        let mut computed: Vec<Row> = Vec::new();
        // the held-out-shape test split, then the seen-shape one (metrics `seen_…`)
        let splits: [(&str, &[usize], PredsOf); 2] = [
            ("", &tr.test, |u| &u.test_preds),
            ("seen_", &tr.seen, |u| &u.seen_preds),
        ];
        for (prefix, split, preds_of) in splits {
            if split.is_empty() {
                continue;
            }
            let groups = tr.groups_of(split);
            let groups = &groups;
            let full = |u: &Unit| -> Vec<Vec<f64>> {
                let mut p = vec![Vec::new(); samples.len()];
                for (&i, v) in split.iter().zip(preds_of(u)) {
                    p[i] = v.clone();
                }
                p
            };
            computed.par_extend(cells.par_iter().flat_map_iter(|((name, bits), us)| {
                let preds: Vec<Vec<Vec<f64>>> = us.iter().map(|u| full(u)).collect();
                let first = us[0];
                task.metrics()
                    .iter()
                    .map(move |&m| {
                        let metric = format!("{prefix}{}", m.name());
                        let (value, seeds_sd) = over_seeds(us, &metric);
                        let stat = |k: &[usize]| {
                            let rows: Vec<usize> = k.iter().map(|&j| split[j]).collect();
                            preds
                                .iter()
                                .map(|p| score(m, &rows, p, samples))
                                .sum::<f64>()
                                / preds.len() as f64
                        };
                        let (lo, hi) = bootstrap_interval(groups, draws, seed, stat);
                        Row {
                            task: task.name().into(),
                            encoder: name.clone(),
                            kind: kind_name(first.kind).into(),
                            budget: f64::from_bits(*bits),
                            metric,
                            value,
                            seeds: us.len(),
                            seeds_sd,
                            ci_low: Some(lo),
                            ci_high: Some(hi),
                            draws_sd: None,
                            draws_min: None,
                            draws_max: None,
                            rank: None,
                            rank_of: None,
                            train_sequences: first.train_sequences,
                            train_samples: first.train_samples,
                            test_samples: split.len(),
                        }
                    })
                    .collect::<Vec<_>>()
            }));
            // the constant predictor per budget
            for &budget in budgets {
                let seqs = tr.budget_sequences(budget);
                let train = tr.rows(&seqs);
                let preds = constant_predictions(tr, &train);
                for &m in task.metrics() {
                    let stat = |k: &[usize]| {
                        let rows: Vec<usize> = k.iter().map(|&j| split[j]).collect();
                        score(m, &rows, &preds, samples)
                    };
                    let (lo, hi) = bootstrap_interval(groups, draws, seed, stat);
                    rows.push(Row {
                        task: task.name().into(),
                        encoder: "constant".into(),
                        kind: "constant".into(),
                        budget,
                        metric: format!("{prefix}{}", m.name()),
                        value: score(m, split, &preds, samples),
                        seeds: 1,
                        seeds_sd: None,
                        ci_low: Some(lo),
                        ci_high: Some(hi),
                        draws_sd: None,
                        draws_min: None,
                        draws_max: None,
                        rank: None,
                        rank_of: None,
                        train_sequences: seqs.len(),
                        train_samples: train.len(),
                        test_samples: split.len(),
                    });
                }
            }
        }
        // random-draw summaries and ranks
        let group_of: BTreeMap<String, Option<String>> = of_task
            .iter()
            .map(|u| (u.encoder.clone(), u.group.clone()))
            .collect();
        let kind_of: BTreeMap<String, EncoderKind> = of_task
            .iter()
            .map(|u| (u.encoder.clone(), u.kind))
            .collect();
        let mut with_ranks = computed.clone();
        let groups_present: BTreeSet<String> = of_task
            .iter()
            .filter(|u| u.kind == EncoderKind::Random)
            .filter_map(|u| u.group.clone())
            .collect();
        let prefixes: &[&str] = if tr.seen.is_empty() {
            &[""]
        } else {
            &["", "seen_"]
        };
        let metric_names: Vec<(String, bool)> = prefixes
            .iter()
            .flat_map(|p| {
                task.metrics()
                    .iter()
                    .map(move |m| (format!("{p}{}", m.name()), m.higher_is_better()))
            })
            .collect();
        for g in &groups_present {
            for &budget in budgets {
                for (metric, higher_is_better) in &metric_names {
                    let draws_rows: Vec<&Row> = computed
                        .iter()
                        .filter(|r| {
                            r.budget == budget
                                && &r.metric == metric
                                && kind_of.get(&r.encoder) == Some(&EncoderKind::Random)
                                && group_of.get(&r.encoder).cloned().flatten().as_deref() == Some(g)
                        })
                        .collect();
                    if draws_rows.is_empty() {
                        continue;
                    }
                    let values: Vec<f64> = draws_rows.iter().map(|r| r.value).collect();
                    let s = Spread::of(&values);
                    rows.push(Row {
                        task: task.name().into(),
                        encoder: format!("{g} ({} draws)", values.len()),
                        kind: "random_draws".into(),
                        budget,
                        metric: metric.clone(),
                        value: s.mean,
                        seeds: draws_rows[0].seeds,
                        seeds_sd: mean_seed_sd(&draws_rows),
                        ci_low: None,
                        ci_high: None,
                        draws_sd: Some(s.sd),
                        draws_min: Some(s.min),
                        draws_max: Some(s.max),
                        rank: None,
                        rank_of: None,
                        train_sequences: draws_rows[0].train_sequences,
                        train_samples: draws_rows[0].train_samples,
                        test_samples: if metric.starts_with("seen_") {
                            tr.seen.len()
                        } else {
                            tr.test.len()
                        },
                    });
                    for r in with_ranks.iter_mut().filter(|r| {
                        r.budget == budget
                            && &r.metric == metric
                            && kind_of.get(&r.encoder) == Some(&EncoderKind::Pretrained)
                            && group_of.get(&r.encoder).cloned().flatten().as_deref() == Some(g)
                    }) {
                        r.rank = Some(rank(r.value, &values, *higher_is_better));
                        r.rank_of = Some(values.len() + 1);
                    }
                }
            }
        }
        rows.extend(with_ranks);
    }
    let order = |k: &str| match k {
        "pretrained" => 0,
        "random_draws" => 1,
        "pixels" => 2,
        "end_to_end" => 3,
        "floor" => 4,
        "ceiling" => 5,
        "ridge" => 6,
        "constant" => 7,
        _ => 8,
    };
    rows.sort_by(|a, b| {
        (&a.task, order(&a.kind), &a.encoder, &a.metric)
            .cmp(&(&b.task, order(&b.kind), &b.encoder, &b.metric))
            .then(b.budget.total_cmp(&a.budget))
    });
    rows
}

/// A cell's metric over its probe seeds' units: the mean, and the standard deviation (n − 1)
/// where there are several seeds.
fn over_seeds(units: &[&Unit], metric: &str) -> (f64, Option<f64>) {
    let values: Vec<f64> = units
        .iter()
        .map(|u| u.metrics.get(metric).copied().unwrap_or(f64::NAN))
        .collect();
    let s = Spread::of(&values);
    (s.mean, (values.len() > 1).then_some(s.sd))
}

/// The mean over random draws of each draw's spread over probe seeds (none with one seed).
fn mean_seed_sd(draws: &[&Row]) -> Option<f64> {
    let sds: Vec<f64> = draws.iter().filter_map(|r| r.seeds_sd).collect();
    (!sds.is_empty() && sds.len() == draws.len())
        .then(|| sds.iter().sum::<f64>() / sds.len() as f64)
}

/// Writes `results.csv` (RFC 4180, header row first), `results.md` and the charts into `out`.
pub fn write(out: &Path, rows: &[Row], budgets: &[f64]) -> Result<(), Error> {
    let mut w = csv::Writer::from_writer(Vec::new());
    for r in rows {
        w.serialize(r)
            .map_err(|e| Error::file(out.join("results.csv"), e))?;
    }
    let bytes = w
        .into_inner()
        .map_err(|e| Error::file(out.join("results.csv"), e))?;
    sparsh_data::write_atomic(&out.join("results.csv"), &bytes)
        .map_err(|e| Error::file(out.join("results.csv"), e))?;
    let md = markdown(rows, budgets);
    sparsh_data::write_atomic(&out.join("results.md"), md.as_bytes())
        .map_err(|e| Error::file(out.join("results.md"), e))?;
    register_sans()?;
    let tasks: BTreeSet<&str> = rows.iter().map(|r| r.task.as_str()).collect();
    for task in tasks {
        chart(out, task, rows)?;
    }
    Ok(())
}

/// The first metric of a task by name.
fn primary(task: &str) -> Metric {
    let kind: TaskKind = serde_json::from_value(serde_json::Value::String(task.into()))
        .expect("task names round-trip");
    kind.metrics()[0]
}

/// The Markdown tables: per task, its first metric per encoder and budget on the test split, and
/// on the seen-shape test split where the task has one.
pub fn markdown(rows: &[Row], budgets: &[f64]) -> String {
    let mut s = String::new();
    let tasks: Vec<&str> = {
        let mut t: Vec<&str> = rows.iter().map(|r| r.task.as_str()).collect();
        t.dedup();
        t
    };
    for task in tasks {
        let m = primary(task);
        let arrow = if m.higher_is_better() {
            "higher is better"
        } else {
            "lower is better"
        };
        for (metric, split) in [
            (m.name().to_string(), "held-out-shape test sequences"),
            (
                format!("seen_{}", m.name()),
                "seen-shape test sequences (in distribution)",
            ),
        ] {
            let mut names: Vec<(&str, &str)> = rows
                .iter()
                .filter(|r| r.task == task && r.metric == metric && r.kind != "random")
                .map(|r| (r.encoder.as_str(), r.kind.as_str()))
                .collect();
            names.dedup();
            if names.is_empty() {
                continue;
            }
            s += &format!(
                "\n**{task}** — {metric} ({arrow}); 95 % bootstrap interval over {split}; pretrained encoders ranked among the random draws of their architecture\n\n"
            );
            s += "| encoder |";
            for b in budgets {
                s += &format!(" budget {b} |");
            }
            s += "\n|---|";
            s += &"---|".repeat(budgets.len());
            s += "\n";
            for (name, kind) in names {
                s += &format!("| {name} |");
                for &b in budgets {
                    let cell = rows.iter().find(|r| {
                        r.task == task && r.metric == metric && r.encoder == name && r.budget == b
                    });
                    s += &match cell {
                        None => " – |".to_string(),
                        Some(r) if kind == "random_draws" => format!(
                            " {} ± {} [{}–{}]{} |",
                            fmt(r.value),
                            fmt(r.draws_sd.unwrap_or(0.0)),
                            fmt(r.draws_min.unwrap_or(f64::NAN)),
                            fmt(r.draws_max.unwrap_or(f64::NAN)),
                            seed_note(r)
                        ),
                        Some(r) => {
                            let rank = match (r.rank, r.rank_of) {
                                (Some(k), Some(n)) => format!(", rank {k}/{n}"),
                                _ => String::new(),
                            };
                            format!(
                                " {} [{}, {}]{rank}{} |",
                                fmt(r.value),
                                fmt(r.ci_low.unwrap_or(f64::NAN)),
                                fmt(r.ci_high.unwrap_or(f64::NAN)),
                                seed_note(r)
                            )
                        }
                    };
                }
                s += "\n";
            }
        }
    }
    s
}

/// `; N seeds, sd S` where a cell averages several probe seeds (for a summary row, each draw's
/// seeds and the draws' mean spread over them).
fn seed_note(r: &Row) -> String {
    match r.seeds_sd {
        Some(sd) if r.seeds > 1 => format!("; {} seeds, sd {}", r.seeds, fmt(sd)),
        _ => String::new(),
    }
}

/// Three significant digits, at most one decimal above 100.
fn fmt(v: f64) -> String {
    if !v.is_finite() {
        "–".into()
    } else if v.abs() >= 100.0 {
        format!("{v:.1}")
    } else if v.abs() >= 1.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.3}")
    }
}

fn color(i: usize) -> RGBColor {
    const PALETTE: [RGBColor; 12] = [
        RGBColor(0, 114, 178),
        RGBColor(213, 94, 0),
        RGBColor(0, 158, 115),
        RGBColor(204, 121, 167),
        RGBColor(230, 159, 0),
        RGBColor(86, 180, 233),
        RGBColor(120, 120, 120),
        RGBColor(0, 0, 0),
        RGBColor(160, 30, 60),
        RGBColor(110, 60, 170),
        RGBColor(150, 150, 40),
        RGBColor(60, 60, 140),
    ];
    PALETTE[i % PALETTE.len()]
}

/// One line of a chart: encoder name, row kind, and (budget, value, band low, band high).
type Line = (String, String, Vec<(f64, f64, f64, f64)>);

fn chart_err(e: impl std::fmt::Display) -> Error {
    Error::file("chart", e)
}

/// `budget_TASK.png` and `.svg`.
fn chart(out: &Path, task: &str, rows: &[Row]) -> Result<(), Error> {
    let m = primary(task);
    let lines: Vec<Line> = {
        let mut names: Vec<(String, String)> = rows
            .iter()
            .filter(|r| r.task == task && r.metric == m.name() && r.kind != "random")
            .map(|r| (r.encoder.clone(), r.kind.clone()))
            .collect();
        names.dedup();
        names
            .into_iter()
            .map(|(name, kind)| {
                let mut pts: Vec<(f64, f64, f64, f64)> = rows
                    .iter()
                    .filter(|r| r.task == task && r.metric == m.name() && r.encoder == name)
                    .map(|r| {
                        let (lo, hi) = if kind == "random_draws" {
                            (
                                r.draws_min.unwrap_or(r.value),
                                r.draws_max.unwrap_or(r.value),
                            )
                        } else {
                            (r.ci_low.unwrap_or(r.value), r.ci_high.unwrap_or(r.value))
                        };
                        (r.budget, r.value, lo, hi)
                    })
                    .collect();
                pts.sort_by(|a, b| a.0.total_cmp(&b.0));
                (name, kind, pts)
            })
            .collect()
    };
    let all = lines.iter().flat_map(|l| l.2.iter());
    let (mut y0, mut y1) = all.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
        (a.min(p.2).min(p.1), b.max(p.3).max(p.1))
    });
    if !(y0.is_finite() && y1.is_finite()) {
        return Ok(());
    }
    let pad = 0.05 * (y1 - y0).max(1e-9);
    (y0, y1) = (y0 - pad, y1 + pad);
    let (x0, x1) = lines
        .iter()
        .flat_map(|l| l.2.iter().map(|p| p.0))
        .fold((f64::INFINITY, 0.0f64), |(a, b), x| (a.min(x), b.max(x)));
    let (w, h) = (1000u32, 680u32);
    let mut rgb = vec![0u8; (w * h * 3) as usize];
    draw_chart(
        BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area(),
        task,
        m,
        &lines,
        (x0, x1, y0, y1),
    )?;
    let img = image::RgbImage::from_raw(w, h, rgb).ok_or_else(|| chart_err("buffer size"))?;
    let png = sparsh_data::encode_png(&img).map_err(chart_err)?;
    let stem = out.join(format!("budget_{task}"));
    sparsh_data::write_atomic(&stem.with_extension("png"), &png)
        .map_err(|e| Error::file(&stem, e))?;
    let mut svg = String::new();
    draw_chart(
        SVGBackend::with_string(&mut svg, (w, h)).into_drawing_area(),
        task,
        m,
        &lines,
        (x0, x1, y0, y1),
    )?;
    sparsh_data::write_atomic(&stem.with_extension("svg"), svg.as_bytes())
        .map_err(|e| Error::file(&stem, e))
}

fn draw_chart<DB: DrawingBackend>(
    area: DrawingArea<DB, plotters::coord::Shift>,
    task: &str,
    m: Metric,
    lines: &[Line],
    (x0, x1, y0, y1): (f64, f64, f64, f64),
) -> Result<(), Error> {
    area.fill(&WHITE).map_err(chart_err)?;
    let mut c = ChartBuilder::on(&area)
        .caption(
            format!("TacBench {task}: {} against label budget", m.name()),
            (SANS, 22),
        )
        .margin(14)
        .x_label_area_size(50)
        .y_label_area_size(80)
        .build_cartesian_2d(((x0 / 1.5)..(x1 * 1.5)).log_scale(), y0..y1)
        .map_err(chart_err)?;
    c.configure_mesh()
        .x_desc("label budget (share of training sequences)")
        .y_desc(m.name())
        .label_style((SANS, 15))
        .axis_desc_style((SANS, 17))
        .x_labels(6)
        .x_label_formatter(&|v| format!("{}", (v * 100.0).round() / 100.0))
        .draw()
        .map_err(chart_err)?;
    for (i, (name, kind, pts)) in lines.iter().enumerate() {
        let col = color(i);
        let mut band: Vec<(f64, f64)> = pts.iter().map(|p| (p.0, p.3)).collect();
        band.extend(pts.iter().rev().map(|p| (p.0, p.2)));
        c.draw_series(std::iter::once(Polygon::new(band, col.mix(0.15).filled())))
            .map_err(chart_err)?;
        let style = if kind == "constant" {
            col.stroke_width(1)
        } else {
            col.stroke_width(3)
        };
        c.draw_series(LineSeries::new(pts.iter().map(|p| (p.0, p.1)), style))
            .map_err(chart_err)?
            .label(if kind == "random_draws" {
                format!("{name}: mean, min–max band")
            } else {
                name.clone()
            })
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 24, y)], col.stroke_width(3)));
        c.draw_series(pts.iter().map(|p| Circle::new((p.0, p.1), 4, col.filled())))
            .map_err(chart_err)?;
    }
    c.configure_series_labels()
        .position(if m.higher_is_better() {
            SeriesLabelPosition::LowerRight
        } else {
            SeriesLabelPosition::UpperRight
        })
        .label_font((SANS, 15))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(chart_err)?;
    area.present().map_err(chart_err)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(seed: u64, rmse: f64) -> Unit {
        Unit {
            task: TaskKind::Force,
            encoder: "random-vit-0".into(),
            kind: EncoderKind::Random,
            group: Some("random-vit".into()),
            budget: 1.0,
            seed,
            train_sequences: 4,
            train_samples: 40,
            best_epoch: 3,
            val_curve: vec![1.0; 5],
            test_preds: Vec::new(),
            seen_preds: Vec::new(),
            metrics: BTreeMap::from([("rmse_mn".to_string(), rmse)]),
            test_key: 0,
        }
    }

    fn row(seeds: usize, value: f64, seeds_sd: Option<f64>) -> Row {
        Row {
            task: "force".into(),
            encoder: "random-vit-0".into(),
            kind: "random".into(),
            budget: 1.0,
            metric: "rmse_mn".into(),
            value,
            seeds,
            seeds_sd,
            ci_low: Some(value - 1.0),
            ci_high: Some(value + 1.0),
            draws_sd: None,
            draws_min: None,
            draws_max: None,
            rank: None,
            rank_of: None,
            train_sequences: 4,
            train_samples: 40,
            test_samples: 10,
        }
    }

    #[test]
    fn a_cell_over_probe_seeds_is_their_mean_and_sample_spread() {
        // 150, 170, 190 mN: mean 170, deviations ±20 and 0, sd √(800 / 2) = 20
        let us = [unit(0, 150.0), unit(1, 170.0), unit(2, 190.0)];
        let refs: Vec<&Unit> = us.iter().collect();
        let (mean, sd) = over_seeds(&refs, "rmse_mn");
        assert!((mean - 170.0).abs() < 1e-12);
        assert!((sd.unwrap() - 20.0).abs() < 1e-12);
        // one seed: no spread to report
        assert_eq!(over_seeds(&refs[..1], "rmse_mn"), (150.0, None));
        // a metric a unit lacks is NaN, not a silent mean of the others
        assert!(over_seeds(&refs, "seen_rmse_mn").0.is_nan());
    }

    #[test]
    fn draws_carry_their_mean_seed_spread_and_the_table_names_it() {
        let draws = [row(3, 170.0, Some(20.0)), row(3, 180.0, Some(10.0))];
        let refs: Vec<&Row> = draws.iter().collect();
        assert_eq!(mean_seed_sd(&refs), Some(15.0));
        // a draw without a spread (one seed) leaves the summary without one
        let mixed = [row(3, 170.0, Some(20.0)), row(1, 180.0, None)];
        assert_eq!(mean_seed_sd(&mixed.iter().collect::<Vec<_>>()), None);
        assert_eq!(seed_note(&draws[0]), "; 3 seeds, sd 20.00");
        assert_eq!(seed_note(&row(1, 170.0, None)), "");
        let mut shown = row(3, 170.0, Some(20.0));
        shown.kind = "pixels".into();
        shown.encoder = "pixels".into();
        let md = markdown(&[shown], &[1.0]);
        assert!(
            md.contains("| pixels | 170.0 [169.0, 171.0]; 3 seeds, sd 20.00 |"),
            "{md}"
        );
    }
}
