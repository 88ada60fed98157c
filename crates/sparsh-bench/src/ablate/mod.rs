//! Sim-to-real ablation: which part of the simulator makes a model trained on synthetic touches
//! work on real ones. For each variant of a base dataset scene (contact rung, optics model,
//! shadows, noise, randomisation, mechanics stride, training-set size) the frames are generated,
//! models are trained on them alone — a small CNN, and the attentive probe on frozen Sparsh
//! encoders (pretrained and random) — and scored on real frames of a Taxim pack at predicting
//! the contact circle. Three references share the table: the constant predictor (the synthetic
//! training circles' mean), a classical detector tuned on synthetic frames only, and the CNN
//! trained on the real frames themselves (each scored frame held out: the ceiling).
//!
//! - [`config`]: the ablation file and the scene overrides.
//! - [`data`]: frames, circles and their geometry.
//! - [`models`]: the CNN, the regressor trainer.
//! - [`classical`]: the threshold-and-fit detector.
//! - [`metrics`]: errors, scores and bootstrap intervals.
//! - [`report`]: `ablation.csv`, the Markdown table and the chart.

pub mod classical;
pub mod config;
pub mod data;
pub mod metrics;
pub mod models;
pub mod report;

use std::path::Path;
use std::time::Instant;

use burn::prelude::*;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sparsh_optics::Calibration;
use sparsh_optics::pack::CalibrationPack;
use sparsh_optics::sim2real::{
    BallSetup, FrameRefit, pack_renderer, refit_frame, summarize_refits,
};
use sparsh_ssl::data::Stacking;
use sparsh_ssl::device::seeded_module;
use sparsh_ssl::probe::{AttentiveProbe, AttentiveProbeConfig};
use sparsh_ssl::recipe::Recipe;
use sparsh_ssl::vit::Vit;

use crate::Error;
use crate::tacbench::probe::RowStats;
use config::{AblationConfig, VariantConfig, slug};
use data::{Circle, CircleFrames, PackGeometry};
use metrics::{FrameError, Scores};
use models::{CircleCnn, Fitted, Forward, TrainOptions};

/// What a row is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RowKind {
    /// A model trained on a variant's synthetic frames.
    Synthetic,
    /// The synthetic training circles' mean, predicted for every frame.
    Constant,
    /// The classical detector tuned on synthetic frames.
    Classical,
    /// The mean circle of the pack's frames that are not scored.
    RealConstant,
    /// The CNN trained on the pack's other frames.
    RealCeiling,
    /// The circles the calibrated optics fit to each scored frame by rendering, scored against
    /// the marks: the marks' own noise.
    MarksRefit,
}

impl RowKind {
    /// Name in tables.
    pub fn name(self) -> &'static str {
        match self {
            RowKind::Synthetic => "synthetic",
            RowKind::Constant => "constant",
            RowKind::Classical => "classical",
            RowKind::RealConstant => "real constant",
            RowKind::RealCeiling => "real ceiling",
            RowKind::MarksRefit => "label noise",
        }
    }
}

/// One row of `ablation.csv`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Row {
    /// Variant name (the base variant for the references made from its frames; `real frames`
    /// for the ceiling).
    pub variant: String,
    /// `cnn`, `probe (pretrained)`, `probe (random)`, `constant`, `classical`.
    pub model: String,
    /// What the row is.
    pub kind: RowKind,
    /// Frames the model learned from (synthetic training split, or real frames per fold).
    pub train_frames: usize,
    /// Training seeds pooled (1 for what trains nothing).
    pub seeds: usize,
    /// Mean chosen epoch over seeds (0 for what trains nothing).
    pub mean_best_epoch: f64,
    /// Scores on the real test frames.
    pub scores: Scores,
    /// Median centre error (px) and radius error (%) on the synthetic validation sequences,
    /// pooled over seeds (none for the ceiling): the sim-to-real gap is the distance to
    /// `scores`.
    pub synthetic_val: Option<[f64; 2]>,
    /// Wall-clock seconds of the row (its training and scoring).
    pub seconds: f64,
}

/// How to run.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Keep the variants already recorded in the output.
    pub resume: bool,
    /// Small settings for tests: 24 sequences per variant, 2 epochs, one seed, 2 folds.
    pub quick: bool,
    /// Where the CNNs and the probes train and the frozen encoder runs (models are drawn on
    /// the CPU under their seed and moved).
    pub device: Device,
}

impl Default for RunOptions {
    fn default() -> Self {
        RunOptions {
            resume: false,
            quick: false,
            device: Device::flex(),
        }
    }
}

/// The settings actually used (the config's, or the quick ones), and the device.
#[derive(Debug, Clone)]
struct Effective {
    seeds: usize,
    bootstrap: usize,
    sequences: Option<usize>,
    folds: usize,
    cnn: TrainOptions,
    probe: Option<TrainOptions>,
    real: TrainOptions,
    device: Device,
}

fn quick_train(t: TrainOptions) -> TrainOptions {
    TrainOptions {
        epochs: t.epochs.min(2),
        ..t
    }
}

/// Runs the ablation `config` into `out`: per variant `variants/SLUG/` (its scene, its rows and,
/// with `keep_data`, its dataset), then `ablation.csv`, `ablation.md`, `ablation.png` and `.svg`.
pub fn run(
    config: &AblationConfig,
    out: &Path,
    opts: RunOptions,
    observer: &dyn sparsh_gen::Observer,
    log: &dyn Fn(&str),
) -> Result<Vec<Row>, Error> {
    let copy = out.join("ablation.toml");
    match std::fs::read_to_string(&copy) {
        Ok(_) if !opts.resume => {
            return Err(Error::file(
                out,
                "holds an ablation run already (add --resume to continue it, or choose another --out)",
            ));
        }
        Ok(text) if text != config.source => {
            return Err(Error::file(
                &copy,
                format!(
                    "differs from {}: --resume continues the same ablation only",
                    config.path.display()
                ),
            ));
        }
        _ => {}
    }
    // every variant's overrides are checked before anything runs
    for v in &config.variants {
        config::variant_scene(config, v, None)?;
    }
    let eff = Effective {
        seeds: if opts.quick { 1 } else { config.seeds },
        bootstrap: if opts.quick { 100 } else { config.bootstrap },
        sequences: opts.quick.then_some(24),
        folds: if opts.quick { 2 } else { config.real.folds },
        cnn: if opts.quick {
            quick_train(config.cnn)
        } else {
            config.cnn
        },
        probe: config.probe.as_ref().map(|p| {
            if opts.quick {
                quick_train(p.train)
            } else {
                p.train
            }
        }),
        real: if opts.quick {
            quick_train(config.real.train)
        } else {
            config.real.train
        },
        device: opts.device.clone(),
    };
    let pack = CalibrationPack::read(&config.pack)
        .map_err(|e| Error::file(&config.pack, format!("{}: {}", e.field, e.message)))?;
    let (w, h) = pack.size_px();
    let geometry = PackGeometry {
        width_px: w,
        height_px: h,
        mm_per_px: config.pack_mm_per_px,
    };
    let test = config.test_frames.indices(pack.frames.len());
    if test.is_empty() {
        return Err(Error::config(
            &config.path,
            "test_frames",
            "selects no frame of the pack",
        ));
    }
    let encoder = match &config.probe {
        Some(p) if config.variants.iter().any(|v| v.probe) => Some(ProbeEncoder::load(config, p)?),
        _ => None,
    };
    let marks = config
        .real
        .marks_calibration
        .as_ref()
        .map(|calib| {
            let bad = |e: String| {
                Error::config(
                    &config.path,
                    "real.marks_calibration",
                    format!("{}: {e}", calib.display()),
                )
            };
            let calibration = Calibration::load(calib).map_err(bad)?;
            let setup = BallSetup::recorded(&calibration).map_err(bad)?;
            Ok::<_, Error>((calibration, setup))
        })
        .transpose()?;
    let mut real_inputs = Vec::new();
    let real = data::real(&config.pack, &pack, &test, config.input_size, |f, bg| {
        if let Some(e) = &encoder {
            real_inputs.extend(e.input(&config.pack, f, bg)?);
        }
        Ok(())
    })?;
    log(&format!(
        "{}: {} test frames ({:?}) of {}",
        config.path.display(),
        test.len(),
        config.test_frames,
        config.pack.display()
    ));
    // The run's record is written once the config has been checked whole (pack, test frames,
    // probe weights): a config that fails leaves nothing that --resume would have to continue.
    crate::io::write_atomic(&copy, config.source.as_bytes())?;
    let mut rows = Vec::new();
    for (i, variant) in config.variants.iter().enumerate() {
        let dir = out.join("variants").join(slug(&variant.name));
        let record = dir.join("rows.json");
        if opts.resume && record.is_file() {
            let done: Vec<Row> = read_record(&record)?;
            log(&format!("{}: recorded, kept", variant.name));
            rows.extend(done);
            continue;
        }
        let variant_rows = run_variant(
            config,
            variant,
            i == 0,
            &dir,
            &eff,
            geometry,
            (&real, &real_inputs),
            encoder.as_ref(),
            observer,
            log,
        )?;
        write_record(&record, &variant_rows)?;
        rows.extend(variant_rows);
        report::write(out, &rows)?;
    }
    let record = out.join("real").join("rows.json");
    let ceiling = if opts.resume && record.is_file() {
        read_record(&record)?
    } else {
        let (row, predictions) = real_ceiling(config, &pack, &test, &real, &eff, log)?;
        write_predictions(
            &out.join("real").join("predictions.csv"),
            &real,
            &predictions,
        )?;
        if let (Some(enc), Some(popts)) = (encoder.as_ref(), eff.probe) {
            real_probe_ceiling(
                config,
                &pack,
                &test,
                (&real, &real_inputs),
                enc,
                popts,
                &eff,
                log,
            )?;
        }
        write_record(&record, &row)?;
        row
    };
    rows.push(real_constant(&pack, &test, &real, &eff));
    rows.push(ceiling);
    if let Some((calibration, setup)) = &marks {
        let record = out.join("real").join("marks.json");
        let row = if opts.resume && record.is_file() {
            read_record(&record)?
        } else {
            let (row, fitted) = marks_refit(
                (calibration, *setup),
                (&config.pack, &pack),
                &test,
                &real,
                &eff,
                log,
            )?;
            write_predictions(
                &out.join("real").join("marks_predictions.csv"),
                &real,
                &[("calibrated optics fit".into(), 0, fitted)],
            )?;
            write_record(&record, &row)?;
            row
        };
        rows.push(row);
    }
    report::write(out, &rows)?;
    Ok(rows)
}

/// A record `--resume` keeps (a variant's rows, the ceiling's, the marks' noise).
fn read_record<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, Error> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::file(path, e))?;
    serde_json::from_str(&text).map_err(|e| Error::file(path, e))
}

/// Writes a record [`read_record`] reads back, atomically.
fn write_record<T: Serialize>(path: &Path, value: &T) -> Result<(), Error> {
    let json = serde_json::to_vec_pretty(value).map_err(|e| Error::file(path, e))?;
    crate::io::write_atomic(path, &json)
}

/// The frozen encoder of the probe rows: its recipe, input size and pretrained weights.
struct ProbeEncoder {
    recipe: Recipe,
    size: [usize; 2],
    pretrained: Option<Vit>,
}

impl ProbeEncoder {
    fn load(config: &AblationConfig, p: &config::ProbeConfig) -> Result<Self, Error> {
        let recipe =
            Recipe::load(&p.recipe).map_err(|e| Error::config(&config.path, "probe.recipe", e))?;
        if !matches!(recipe.stacking(), Stacking::Channels(ref o) if o.len() == 2) {
            return Err(Error::config(
                &config.path,
                "probe.recipe",
                "the probe reads two frames stacked on channels (frame and no-contact frame); \
                 this recipe stacks otherwise",
            ));
        }
        let pretrained = match &p.weights {
            None => None,
            Some(w) if !w.is_file() => {
                return Err(Error::config(
                    &config.path,
                    "probe.weights",
                    crate::encoders::missing_weights(w, &p.recipe),
                ));
            }
            Some(w) => Some(
                sparsh_ssl::weights::load_encoder(
                    crate::encoders::random_encoder(&recipe, 0)?,
                    w,
                    None,
                )
                .map_err(|e| {
                    Error::config(
                        &config.path,
                        "probe.weights",
                        format!("does not fit the recipe's architecture: {e}"),
                    )
                })?,
            ),
        };
        let size = recipe.encoder.img_size;
        Ok(ProbeEncoder {
            recipe,
            size,
            pretrained,
        })
    }

    /// The encoder input of a frame: its official preprocessing against the background,
    /// stacked on the background's own (the no-contact pair).
    fn input(
        &self,
        path: &Path,
        frame: &image::RgbImage,
        bg: &image::RgbImage,
    ) -> Result<Vec<f32>, Error> {
        let pre = |img| {
            sparsh_ssl::data::preprocess(img, bg, self.size).map_err(|e| Error::file(path, e))
        };
        let mut x = pre(frame)?;
        x.extend(pre(bg)?);
        Ok(x)
    }

    /// Patch tokens of the stacked inputs, `[n, tokens, dim]`, computed on `device`.
    fn encode(&self, vit: &Vit, inputs: &[f32], device: &Device) -> (Vec<f32>, [usize; 3]) {
        let device = device.clone().inner();
        let vit = sparsh_ssl::device::on_device(vit.clone().valid(), &device);
        let [h, w] = self.size;
        let per = 6 * h * w;
        let n = inputs.len() / per;
        let (mut values, mut dims) = (Vec::new(), [0, 0, 0]);
        for chunk in inputs.chunks(32 * per) {
            let m = chunk.len() / per;
            let x = Tensor::<1>::from_floats(chunk, &device).reshape([m, 1, 6, h, w]);
            let t = vit.forward(x, None).patches;
            let [_, k, d] = t.dims();
            dims = [n, k, d];
            values.extend(
                t.into_data()
                    .convert::<f32>()
                    .try_into_vec::<f32>()
                    .expect("f32 tokens"),
            );
        }
        (values, dims)
    }
}

/// Splits the synthetic frames by sequence: every `k`-th sequence (k = 1 / share) validates.
fn split_by_group(frames: &CircleFrames, share: f64) -> (Vec<usize>, Vec<usize>) {
    let mut groups: Vec<usize> = frames.groups.clone();
    groups.sort_unstable();
    groups.dedup();
    let every = if share > 0.0 {
        (1.0 / share).round().max(2.0) as usize
    } else {
        usize::MAX
    };
    let val_groups: Vec<usize> = groups
        .iter()
        .enumerate()
        .filter(|(i, _)| i % every == every - 1)
        .map(|(_, &g)| g)
        .collect();
    (0..frames.len()).partition(|&k| !val_groups.contains(&frames.groups[k]))
}

fn errors_of(preds: &[Circle], truth: &[Circle]) -> Vec<FrameError> {
    preds
        .iter()
        .zip(truth)
        .map(|(&p, &t)| FrameError::of(p, t))
        .collect()
}

/// A CNN forward pass over rows of `frames`.
fn cnn_forward(
    frames: &CircleFrames,
) -> impl Fn(&CircleCnn, &[usize], &Device) -> Tensor<2> + Sync + '_ {
    move |m: &CircleCnn, rows: &[usize], device: &Device| {
        let [h, w] = frames.size;
        let x: Vec<f32> = rows
            .iter()
            .flat_map(|&k| frames.image(k).iter().copied())
            .collect();
        m.forward(Tensor::<1>::from_floats(x.as_slice(), device).reshape([rows.len(), 3, h, w]))
    }
}

/// Trains the CNN on `train` of `frames` (validating on `val`) on `device` and predicts `test`.
#[allow(clippy::too_many_arguments)]
fn cnn_seed(
    frames: &CircleFrames,
    train: &[(usize, Circle)],
    val: &[(usize, Circle)],
    test: &CircleFrames,
    size: [usize; 2],
    opts: TrainOptions,
    seed: u64,
    device: &Device,
) -> (Vec<Circle>, Fitted<CircleCnn>) {
    let cpu = Device::flex().autodiff();
    let model = seeded_module(&cpu, seed, || CircleCnn::new(&cpu));
    let fitted: Fitted<CircleCnn> = models::fit(
        model,
        size,
        &cnn_forward(frames),
        train,
        val,
        opts,
        seed,
        device,
    );
    let rows: Vec<usize> = (0..test.len()).collect();
    (fitted.predict(&cnn_forward(test), &rows), fitted)
}

/// Median centre error (px) and radius error (%) of predictions against circles.
fn medians(preds: &[Circle], truth: &[Circle]) -> Option<[f64; 2]> {
    if preds.is_empty() {
        return None;
    }
    let e = errors_of(preds, truth);
    let s = metrics::score(&[e], 0, 0);
    Some([s.centre_median_px, s.radius_median_pct])
}

#[allow(clippy::too_many_arguments)]
fn run_variant(
    config: &AblationConfig,
    variant: &VariantConfig,
    first: bool,
    dir: &Path,
    eff: &Effective,
    geometry: PackGeometry,
    (real, real_inputs): (&CircleFrames, &[f32]),
    encoder: Option<&ProbeEncoder>,
    observer: &dyn sparsh_gen::Observer,
    log: &dyn Fn(&str),
) -> Result<Vec<Row>, Error> {
    let start = Instant::now();
    let scene = config::variant_scene(config, variant, eff.sequences)?;
    let scene_path = dir.join("scene.toml");
    crate::io::write_atomic(&scene_path, scene.as_bytes())?;
    let data_dir = dir.join("data");
    // a complete dataset is kept as it is; an interrupted one is resumed
    if !data_dir.join("manifest.json").is_file() {
        let options = sparsh_gen::GenerateOptions {
            resume: data_dir.exists(),
            ..Default::default()
        };
        sparsh_gen::generate(&scene_path, &data_dir, options, None, observer)
            .map_err(|e| Error::file(&scene_path, format!("{e:#}")))?;
    }
    let probe_on = variant.probe.then_some(encoder).flatten();
    let mut inputs = Vec::new();
    let frames = data::synthetic(&data_dir, geometry, config.input_size, |f, bg| {
        if let Some(e) = probe_on {
            inputs.extend(e.input(&data_dir, f, bg)?);
        }
        Ok(())
    })?;
    let (train, val) = split_by_group(&frames, config.validation_share);
    let pairs = |rows: &[usize]| -> Vec<(usize, Circle)> {
        rows.iter().map(|&k| (k, frames.circles[k])).collect()
    };
    let (train_pairs, val_pairs) = (pairs(&train), pairs(&val));
    log(&format!(
        "{}: {} synthetic frames in contact ({} train, {} validation) in {:.0} s",
        variant.name,
        frames.len(),
        train.len(),
        val.len(),
        start.elapsed().as_secs_f64()
    ));
    let mut rows = Vec::new();
    let mut predictions: Vec<SeedPredictions> = Vec::new();
    let pack_size = [geometry.width_px, geometry.height_px];
    let val_circles: Vec<Circle> = val.iter().map(|&k| frames.circles[k]).collect();
    let row = |model: &str,
               kind,
               seeds,
               epochs: &[usize],
               errors: &[Vec<FrameError>],
               val_preds: &[Circle],
               t: Instant| Row {
        variant: variant.name.clone(),
        model: model.into(),
        kind,
        train_frames: train.len(),
        seeds,
        mean_best_epoch: epochs.iter().sum::<usize>() as f64 / epochs.len().max(1) as f64,
        scores: metrics::score(errors, eff.bootstrap, 7),
        synthetic_val: medians(val_preds, &val_circles.repeat(seeds)),
        seconds: t.elapsed().as_secs_f64(),
    };
    if first {
        let t = Instant::now();
        let train_circles: Vec<Circle> = train.iter().map(|&k| frames.circles[k]).collect();
        let mean = models::CircleScale::of(&train_circles, pack_size).mean();
        let constant = errors_of(&vec![mean; real.len()], &real.circles);
        predictions.push(("constant".into(), 0, vec![mean; real.len()]));
        rows.push(row(
            "constant",
            RowKind::Constant,
            1,
            &[],
            &[constant],
            &vec![mean; val.len()],
            t,
        ));
        let t = Instant::now();
        let train_frames = frames.select(&train);
        let detector = classical::Detector::tune(&train_frames, geometry.width_px);
        let preds: Vec<Circle> = (0..real.len())
            .map(|k| detector.detect(real, k, geometry.width_px).unwrap_or(mean))
            .collect();
        let val_preds: Vec<Circle> = val
            .iter()
            .map(|&k| {
                detector
                    .detect(&frames, k, geometry.width_px)
                    .unwrap_or(mean)
            })
            .collect();
        log(&format!(
            "classical detector tuned on {} synthetic frames: blur {} px, threshold {}, radius × {:.3}",
            train.len(),
            detector.blur_px,
            detector.threshold,
            detector.radius_scale
        ));
        rows.push(row(
            "classical",
            RowKind::Classical,
            1,
            &[],
            &[errors_of(&preds, &real.circles)],
            &val_preds,
            t,
        ));
        predictions.push(("classical".into(), 0, preds));
    }
    // a learned row: every seed's real predictions, chosen epoch and validation predictions
    let mut learned =
        |name: &str, train_seed: &dyn Fn(u64) -> Result<Seeded, Error>| -> Result<(), Error> {
            let t = Instant::now();
            let (mut errors, mut epochs, mut val_preds) = (Vec::new(), Vec::new(), Vec::new());
            for seed in 0..eff.seeds as u64 {
                let (preds, epoch, val) = train_seed(seed)?;
                errors.push(errors_of(&preds, &real.circles));
                predictions.push((name.into(), seed as usize, preds));
                epochs.push(epoch);
                val_preds.extend(val);
            }
            let r = row(
                name,
                RowKind::Synthetic,
                eff.seeds,
                &epochs,
                &errors,
                &val_preds,
                t,
            );
            log(&summary(&r));
            rows.push(r);
            Ok(())
        };
    learned("cnn", &|seed| {
        let (preds, fitted) = cnn_seed(
            &frames,
            &train_pairs,
            &val_pairs,
            real,
            pack_size,
            eff.cnn,
            seed,
            &eff.device,
        );
        Ok((preds, fitted.best_epoch, fitted.val_preds))
    })?;
    if let (Some(enc), Some(popts)) = (probe_on, eff.probe) {
        // Tokens standardized with the synthetic training frames' statistics; the real ones also
        // with their own (no labels), to tell a shift of the tokens' scale from a loss of the
        // contact in them (logged, not a row).
        let tokens_of = |vit: &Vit| {
            let (mut syn, dims) = enc.encode(vit, &inputs, &eff.device);
            let (mut rea, _) = enc.encode(vit, real_inputs, &eff.device);
            let row = dims[1] * dims[2];
            let real_rows: Vec<usize> = (0..rea.len() / row).collect();
            let mut own = rea.clone();
            RowStats::of(&own, row, &real_rows).apply(&mut own);
            let stats = RowStats::of(&syn, row, &train);
            stats.apply(&mut syn);
            stats.apply(&mut rea);
            let (zv, zr) = (z_spread(&syn, row, &val), z_spread(&rea, row, &real_rows));
            log(&format!(
                "{}: standardized tokens, RMS / 99th percentile of |z|: synthetic validation {:.2} / {:.2}, real {:.2} / {:.2}",
                variant.name, zv[0], zv[1], zr[0], zr[1]
            ));
            ((syn, rea, dims), own)
        };
        let probe = |(tokens, own): &(PairedTokens, Vec<f32>), name: &str, seed: u64| {
            let (preds, fitted) = probe_seed(
                tokens,
                &train_pairs,
                &val_pairs,
                pack_size,
                popts,
                seed,
                &eff.device,
            );
            let [_, t, d] = tokens.2;
            let rows: Vec<usize> = (0..real.len()).collect();
            let own_preds = fitted.predict(&token_forward(own, t, d), &rows);
            let spread = |c: &[Circle]| {
                let n = c.len().max(1) as f64;
                let (mx, my) = (
                    c.iter().map(|c| c.cx_px).sum::<f64>() / n,
                    c.iter().map(|c| c.cy_px).sum::<f64>() / n,
                );
                let s = (c
                    .iter()
                    .map(|c| (c.cx_px - mx).powi(2) + (c.cy_px - my).powi(2))
                    .sum::<f64>()
                    / n)
                    .sqrt();
                format!("mean ({mx:.0}, {my:.0}) px, spread {s:.1} px")
            };
            // Pearson r of predicted and marked centres along x and y: does the probe follow the
            // contact on real frames at all?
            let follows = |axis: fn(&Circle) -> f64| {
                let (p, m): (Vec<f32>, Vec<f32>) = preds
                    .iter()
                    .zip(&real.circles)
                    .map(|(p, m)| (axis(p) as f32, axis(m) as f32))
                    .unzip();
                crate::fields::metrics::pearson(&p, &m).unwrap_or(f64::NAN)
            };
            let [own_centre, own_radius] =
                medians(&own_preds, &real.circles).unwrap_or([f64::NAN; 2]);
            log(&format!(
                "{}: {name} seed {seed}: real predictions {}, r with the marked centres x {:.2}, y {:.2} (marked circles {}); tokens standardized on the real frames themselves: centre {own_centre:.1} px, radius {own_radius:.1} % (medians)",
                variant.name,
                spread(&preds),
                follows(|c| c.cx_px),
                follows(|c| c.cy_px),
                spread(&real.circles),
            ));
            Ok((preds, fitted.best_epoch, fitted.val_preds))
        };
        if let Some(vit) = &enc.pretrained {
            let once = tokens_of(vit);
            learned("probe (pretrained)", &|seed| {
                probe(&once, "probe (pretrained)", seed)
            })?;
        }
        learned("probe (random)", &|seed| {
            probe(
                &tokens_of(&crate::encoders::random_encoder(&enc.recipe, seed)?),
                "probe (random)",
                seed,
            )
        })?;
    }
    write_predictions(&dir.join("predictions.csv"), real, &predictions)?;
    if !config.keep_data {
        std::fs::remove_dir_all(&data_dir).map_err(|e| Error::file(&data_dir, e))?;
    }
    Ok(rows)
}

/// RMS and 99th percentile of |z| over the rows `rows` of standardized tokens (rows of `row`
/// values): how far tokens sit from the synthetic training frames' statistics, which the probe
/// was fitted inside.
fn z_spread(tokens: &[f32], row: usize, rows: &[usize]) -> [f64; 2] {
    let mut z: Vec<f64> = rows
        .iter()
        .flat_map(|&i| {
            tokens[i * row..(i + 1) * row]
                .iter()
                .map(|v| f64::from(v.abs()))
        })
        .collect();
    if z.is_empty() {
        return [f64::NAN; 2];
    }
    let rms = (z.iter().map(|v| v * v).sum::<f64>() / z.len() as f64).sqrt();
    let k = ((z.len() - 1) as f64 * 0.99).round() as usize;
    let (_, p99, _) = z.select_nth_unstable_by(k, f64::total_cmp);
    [rms, *p99]
}

/// The probe's forward pass over rows of `[n, t, d]` tokens.
fn token_forward(
    tokens: &[f32],
    t: usize,
    d: usize,
) -> impl Fn(&AttentiveProbe, &[usize], &Device) -> Tensor<2> + Sync + '_ {
    move |m: &AttentiveProbe, rows: &[usize], device: &Device| {
        let x: Vec<f32> = rows
            .iter()
            .flat_map(|&i| tokens[i * t * d..(i + 1) * t * d].iter().copied())
            .collect();
        m.forward(Tensor::<1>::from_floats(x.as_slice(), device).reshape([rows.len(), t, d]))
    }
}

/// One training seed's real predictions, chosen epoch and validation predictions.
type Seeded = (Vec<Circle>, usize, Vec<Circle>);

/// Standardized tokens of the synthetic frames and of the real ones, and their `[n, t, d]`
/// (n of the synthetic set).
type PairedTokens = (Vec<f32>, Vec<f32>, [usize; 3]);

/// Trains the attentive probe on standardized synthetic tokens on `device` and predicts the
/// real ones.
fn probe_seed(
    (syn, real, dims): &PairedTokens,
    train: &[(usize, Circle)],
    val: &[(usize, Circle)],
    size: [usize; 2],
    opts: TrainOptions,
    seed: u64,
    on: &Device,
) -> (Vec<Circle>, Fitted<AttentiveProbe>) {
    let [_, t, d] = *dims;
    let syn_forward = token_forward(syn, t, d);
    let device = Device::flex().autodiff();
    let heads = if d.is_multiple_of(64) { d / 64 } else { 1 };
    let probe = seeded_module(&device, seed, || {
        AttentiveProbeConfig::new(d, heads)
            .with_outputs(3)
            .init(&device)
    });
    let fitted = models::fit(
        probe,
        size,
        &syn_forward as &Forward<'_, AttentiveProbe>,
        train,
        val,
        opts,
        seed,
        on,
    );
    let real_forward = token_forward(real, t, d);
    let rows: Vec<usize> = (0..real.len() / (t * d)).collect();
    (fitted.predict(&real_forward, &rows), fitted)
}

/// One log line of a row.
fn summary(r: &Row) -> String {
    let val = r.synthetic_val.map_or(String::new(), |[c, p]| {
        format!("; synthetic validation {c:.1} px, {p:.1} %")
    });
    format!(
        "{}: {}: real centre {:.1} px, radius {:.1} % (medians){val}; {:.0} s",
        r.variant, r.model, r.scores.centre_median_px, r.scores.radius_median_pct, r.seconds
    )
}

/// One model's real predictions for one training seed, in the order of the scored frames.
type SeedPredictions = (String, usize, Vec<Circle>);

/// Writes every recorded model's real predictions as CSV: `model,seed,frame,cx_px,cy_px,r_px`
/// (pack pixels; `frame` is the pack's index), one row per seed and scored frame.
fn write_predictions(
    path: &Path,
    real: &CircleFrames,
    predictions: &[SeedPredictions],
) -> Result<(), Error> {
    let mut w = csv::Writer::from_writer(Vec::new());
    let bad = |e: csv::Error| Error::file(path, e);
    w.write_record(["model", "seed", "frame", "cx_px", "cy_px", "r_px"])
        .map_err(bad)?;
    for (model, seed, preds) in predictions {
        for (p, frame) in preds.iter().zip(&real.groups) {
            w.write_record([
                model.clone(),
                seed.to_string(),
                frame.to_string(),
                format!("{:.6}", p.cx_px),
                format!("{:.6}", p.cy_px),
                format!("{:.6}", p.r_px),
            ])
            .map_err(bad)?;
        }
    }
    let bytes = w.into_inner().map_err(|e| Error::file(path, e))?;
    crate::io::write_atomic(path, &bytes)
}

/// The marks' own noise: each scored frame's circle fitted by rendering it with `calibration`
/// (under `setup`, the ball, pitch and mechanics its `map.json` records), from its mark
/// ([`sparsh_optics::sim2real::refit_frame`]), the fitted circles scored as predictions of the
/// marks. The fit's own error, on frames rendered at the fitted circles with noise of its
/// residual, is logged.
fn marks_refit(
    (calibration, setup): (&Calibration, BallSetup),
    (pack_path, pack): (&Path, &CalibrationPack),
    test: &[usize],
    real: &CircleFrames,
    eff: &Effective,
    log: &dyn Fn(&str),
) -> Result<(Row, Vec<Circle>), Error> {
    let start = Instant::now();
    let renderer = pack_renderer(calibration, pack, setup, None);
    let refits: Vec<FrameRefit> = test
        .par_iter()
        .map(|&k| {
            refit_frame(&renderer, pack, k, setup)
                .map_err(|e| Error::file(pack_path, format!("frame {k}: label noise: {e}")))
        })
        .collect::<Result<_, _>>()?;
    let fitted: Vec<Circle> = refits.iter().map(|r| r.fit.fitted.into()).collect();
    let errors = errors_of(&fitted, &real.circles);
    let summary = summarize_refits(&refits);
    log(&format!(
        "label noise: fitted circles against the marks: centre {:.2} px (about the mean offset \
         ({:+.2}, {:+.2}) px: {:.2}), radius {:.2} % (medians); the fit on renders at its \
         circles with noise of its residual: {:.2} px, {:.2} %",
        summary.centre_median_px,
        summary.centre_mean_offset_px[0],
        summary.centre_mean_offset_px[1],
        summary.centre_median_about_offset_px,
        summary.radius_median_pct,
        summary.check_centre_median_px,
        summary.check_radius_median_pct
    ));
    let row = Row {
        variant: "real frames".into(),
        model: "calibrated optics fit".into(),
        kind: RowKind::MarksRefit,
        train_frames: 0,
        seeds: 1,
        mean_best_epoch: 0.0,
        scores: metrics::score(&[errors], eff.bootstrap, 7),
        synthetic_val: None,
        seconds: start.elapsed().as_secs_f64(),
    };
    Ok((row, fitted))
}

/// What is trivial on the pack: the mean circle of its frames that are not scored (the even
/// ones when the odd are), predicted for every scored frame.
fn real_constant(
    pack: &CalibrationPack,
    test: &[usize],
    real: &CircleFrames,
    eff: &Effective,
) -> Row {
    let start = Instant::now();
    let (w, h) = pack.size_px();
    let others: Vec<Circle> = (0..pack.frames.len())
        .filter(|k| !test.contains(k))
        .map(|k| pack.marked_circle(k).into())
        .collect();
    let mean = models::CircleScale::of(&others, [w, h]).mean();
    let errors = errors_of(&vec![mean; real.len()], &real.circles);
    Row {
        variant: "real frames".into(),
        model: "constant".into(),
        kind: RowKind::RealConstant,
        train_frames: others.len(),
        seeds: 1,
        mean_best_epoch: 0.0,
        scores: metrics::score(&[errors], eff.bootstrap, 7),
        synthetic_val: None,
        seconds: start.elapsed().as_secs_f64(),
    }
}

/// A frame mirrored: `flip` bit 0 mirrors columns, bit 1 rows (the circle follows).
fn mirrored(frames: &CircleFrames, k: usize, flip: usize, pack: [usize; 2]) -> (Vec<f32>, Circle) {
    let [h, w] = frames.size;
    let img = frames.image(k);
    let mut out = vec![0.0f32; img.len()];
    for c in 0..3 {
        for y in 0..h {
            for x in 0..w {
                let sx = if flip & 1 == 1 { w - 1 - x } else { x };
                let sy = if flip & 2 == 2 { h - 1 - y } else { y };
                out[(c * h + y) * w + x] = img[(c * h + sy) * w + sx];
            }
        }
    }
    (out, mirrored_circle(frames.circles[k], flip, pack))
}

/// A circle in a `pack`-sized image mirrored as [`mirrored`] mirrors the image.
fn mirrored_circle(mut circle: Circle, flip: usize, pack: [usize; 2]) -> Circle {
    if flip & 1 == 1 {
        circle.cx_px = pack[0] as f64 - 1.0 - circle.cx_px;
    }
    if flip & 2 == 2 {
        circle.cy_px = pack[1] as f64 - 1.0 - circle.cy_px;
    }
    circle
}

/// One fold of the ceilings: the scored frames' positions held out (every `folds`-th from
/// `fold`) and the training rows, those whose pack frame (`groups`) is not held out.
fn fold_split(
    test: &[usize],
    groups: &[usize],
    folds: usize,
    fold: usize,
) -> (Vec<usize>, Vec<usize>) {
    let held: Vec<usize> = (0..test.len()).filter(|i| i % folds == fold).collect();
    let held_frames: Vec<usize> = held.iter().map(|&i| test[i]).collect();
    let train = (0..groups.len())
        .filter(|&r| !held_frames.contains(&groups[r]))
        .collect();
    (held, train)
}

/// The ceiling: for each fold of the test frames, the CNN trained on every other frame of the
/// pack and its mirror images (no validation split: the last epoch is kept).
fn real_ceiling(
    config: &AblationConfig,
    pack: &CalibrationPack,
    test: &[usize],
    real: &CircleFrames,
    eff: &Effective,
    log: &dyn Fn(&str),
) -> Result<(Row, Vec<SeedPredictions>), Error> {
    let start = Instant::now();
    let all: Vec<usize> = (0..pack.frames.len()).collect();
    let frames = data::real(&config.pack, pack, &all, config.input_size, |_, _| Ok(()))?;
    let (w, h) = pack.size_px();
    let mut augmented = CircleFrames {
        size: frames.size,
        ..Default::default()
    };
    for k in 0..frames.len() {
        for flip in 0..4 {
            let (img, circle) = mirrored(&frames, k, flip, [w, h]);
            augmented.images.extend(img);
            augmented.circles.push(circle);
            augmented.groups.push(k);
        }
    }
    let mut errors = vec![Vec::with_capacity(test.len()); eff.seeds];
    let mut epochs = Vec::new();
    let mut train_frames = 0;
    let mut predictions = Vec::new();
    for (seed, errs) in errors.iter_mut().enumerate() {
        let mut preds = vec![None; test.len()];
        for fold in 0..eff.folds {
            let (held, rows) = fold_split(test, &augmented.groups, eff.folds, fold);
            let train: Vec<(usize, Circle)> = rows
                .into_iter()
                .map(|r| (r, augmented.circles[r]))
                .collect();
            train_frames = train.len() / 4;
            let fold_test = real.select(&held);
            let (p, fitted) = cnn_seed(
                &augmented,
                &train,
                &[],
                &fold_test,
                [w, h],
                eff.real,
                (seed * eff.folds + fold) as u64,
                &eff.device,
            );
            epochs.push(fitted.best_epoch);
            for (&i, c) in held.iter().zip(p) {
                preds[i] = Some(c);
            }
        }
        let preds: Vec<Circle> = preds
            .into_iter()
            .map(|p| p.expect("every fold ran"))
            .collect();
        *errs = errors_of(&preds, &real.circles);
        predictions.push(("cnn".to_string(), seed, preds));
    }
    let row = Row {
        variant: "real frames".into(),
        model: "cnn".into(),
        kind: RowKind::RealCeiling,
        train_frames,
        seeds: eff.seeds,
        mean_best_epoch: epochs.iter().sum::<usize>() as f64 / epochs.len().max(1) as f64,
        scores: metrics::score(&errors, eff.bootstrap, 7),
        synthetic_val: None,
        seconds: start.elapsed().as_secs_f64(),
    };
    log(&format!(
        "real ceiling ({} folds): centre {:.1} px, radius {:.1} % (medians) in {:.0} s",
        eff.folds, row.scores.centre_median_px, row.scores.radius_median_pct, row.seconds
    ));
    Ok((row, predictions))
}

/// The probe's ceiling, a diagnosis logged beside the CNN's (not a row): the attentive probe on
/// the frozen encoder's tokens of the pack's own frames and their mirror images, trained per
/// fold of the scored frames as [`real_ceiling`] trains the CNN, the tokens standardized on each
/// fold's training frames. Where it reads real contacts well, the frozen tokens carry them and
/// the synthetic-trained probe's miss is the domain's; where it does not, the tokens do not.
#[allow(clippy::too_many_arguments)]
fn real_probe_ceiling(
    config: &AblationConfig,
    pack: &CalibrationPack,
    test: &[usize],
    (real, real_inputs): (&CircleFrames, &[f32]),
    enc: &ProbeEncoder,
    opts: TrainOptions,
    eff: &Effective,
    log: &dyn Fn(&str),
) -> Result<(), Error> {
    let start = Instant::now();
    let (w, h) = pack.size_px();
    let (mut inputs, mut circles, mut groups) = (Vec::new(), Vec::new(), Vec::new());
    for k in 0..pack.frames.len() {
        for flip in 0..4 {
            let turn = |img: &image::RgbImage| {
                let img = if flip & 1 == 1 {
                    image::imageops::flip_horizontal(img)
                } else {
                    img.clone()
                };
                if flip & 2 == 2 {
                    image::imageops::flip_vertical(&img)
                } else {
                    img
                }
            };
            inputs.extend(enc.input(
                &config.pack,
                &turn(&pack.frames[k]),
                &turn(&pack.background),
            )?);
            circles.push(mirrored_circle(pack.marked_circle(k).into(), flip, [w, h]));
            groups.push(k);
        }
    }
    let mut encoders = Vec::new();
    if let Some(vit) = &enc.pretrained {
        encoders.push(("pretrained", vit.clone()));
    }
    encoders.push(("random", crate::encoders::random_encoder(&enc.recipe, 0)?));
    for (name, vit) in encoders {
        let (own, dims) = enc.encode(&vit, &inputs, &eff.device);
        let (scored, _) = enc.encode(&vit, real_inputs, &eff.device);
        let row = dims[1] * dims[2];
        let mut errors = Vec::new();
        for seed in 0..eff.seeds {
            let mut preds = vec![None; test.len()];
            for fold in 0..eff.folds {
                let (held, train) = fold_split(test, &groups, eff.folds, fold);
                let stats = RowStats::of(&own, row, &train);
                let (mut own_std, mut scored_std) = (own.clone(), scored.clone());
                stats.apply(&mut own_std);
                stats.apply(&mut scored_std);
                let pairs: Vec<(usize, Circle)> = train.iter().map(|&r| (r, circles[r])).collect();
                let (p, _) = probe_seed(
                    &(own_std, scored_std, dims),
                    &pairs,
                    &[],
                    [w, h],
                    opts,
                    (seed * eff.folds + fold) as u64,
                    &eff.device,
                );
                for &i in &held {
                    preds[i] = Some(p[i]);
                }
            }
            let preds: Vec<Circle> = preds
                .into_iter()
                .map(|p| p.expect("every fold ran"))
                .collect();
            errors.push(errors_of(&preds, &real.circles));
        }
        let s = metrics::score(&errors, 0, 0);
        log(&format!(
            "real frames (held out): probe ({name}) on the frozen tokens ({} folds, {} seeds): centre {:.1} px, radius {:.1} % (medians) in {:.0} s",
            eff.folds,
            eff.seeds,
            s.centre_median_px,
            s.radius_median_pct,
            start.elapsed().as_secs_f64()
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mirroring_moves_the_circle_with_the_image() {
        let mut f = CircleFrames {
            size: [2, 4],
            ..Default::default()
        };
        let mut img = vec![0.0f32; 3 * 8];
        img[1] = 5.0; // channel 0, row 0, column 1
        f.images = img;
        f.circles.push(Circle {
            cx_px: 10.0,
            cy_px: 3.0,
            r_px: 4.0,
        });
        f.groups.push(0);
        let (m, c) = mirrored(&f, 0, 3, [40, 20]);
        assert_eq!(m[4 + 2], 5.0); // row 1, column 2
        assert_eq!((c.cx_px, c.cy_px, c.r_px), (29.0, 16.0, 4.0));
    }

    #[test]
    fn the_validation_split_takes_whole_sequences() {
        let f = CircleFrames {
            size: [1, 1],
            images: vec![0.0; 3 * 40],
            circles: vec![
                Circle {
                    cx_px: 0.0,
                    cy_px: 0.0,
                    r_px: 1.0
                };
                40
            ],
            groups: (0..40).map(|k| k / 2).collect(),
        };
        let (train, val) = split_by_group(&f, 0.1);
        assert_eq!(val, vec![18, 19, 38, 39]);
        assert_eq!(train.len(), 36);
    }
}
