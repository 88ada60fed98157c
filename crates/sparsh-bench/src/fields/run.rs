//! `sparsh fieldprobe train` and `sparsh fieldprobe eval`.
//!
//! Train: the self-supervised decoder on the given frozen encoder, and the references the config
//! asks for — the same decoder supervised by the ground-truth fields (the ceiling) and
//! self-supervised decoders on randomly initialised encoders of the same architecture (several
//! draws) — saved under `RUN/decoders/`, with `RUN/run.json`. Only the supervised ceiling reads
//! fields while training.
//!
//! Eval: every decoder, the classical baselines (background-difference intensity for normal,
//! Farnebäck optical flow for shear) and the markers where the sensor prints them, scored on the
//! held-out sequences against the EXR ground truth: means over sequences with 95 % bootstrap
//! intervals, `RUN/eval/fields.csv`, `fields.md` and the figure `fields_examples.png`; with
//! `--pack`, the predicted contact region against a real Taxim pack's contact circles.

use std::path::{Path, PathBuf};
use std::time::Instant;

use burn::module::Module;
use burn::prelude::*;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use sparsh_ssl::data::Stacking;
use sparsh_ssl::recipe::Recipe;
use sparsh_ssl::vit::Vit;

use super::ceiling::{CeilingRecord, CeilingSection, FieldCnn, predict_ceiling, train_ceiling};
use super::data::{FramePairs, GroundTruth, Pair, PairTruth, marker_flow};
use super::dpt::FieldDecoderConfig;
use super::figures::{Panel, write_field_grid};
use super::flow::{FarnebackParams, farneback_flow};
use super::geometry::InputGeometry;
use super::loss::LossWeights;
use super::metrics::{METRICS, best_threshold, higher_is_better, score_pair};
use super::train::{
    FieldModel, HookTokens, Prediction, Signal, Targets, TokenStats, TrainOptions, encode_hooks,
    encode_inputs, predict, train,
};
use crate::Error;
use crate::encoders::random_encoder;
use crate::io::write_atomic;
use crate::stats::{Spread, bootstrap_interval, rank};

/// `[decoder]` of a field-probe config.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DecoderSection {
    /// Reassembled feature channels (official: 128).
    pub channels: usize,
    /// Flow bound of the shear branch (input pixels).
    pub max_flow_px: f64,
    /// Feed the encoder's input `I_t ⊕ I_{t−k}` at full resolution to the heads as well
    /// ([`super::dpt::ImageSkip`]; not in the official decoder).
    pub image_skip: bool,
}

impl Default for DecoderSection {
    fn default() -> Self {
        Self {
            channels: 32,
            max_flow_px: 4.0,
            image_skip: false,
        }
    }
}

/// `[train]` of a field-probe config.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrainSection {
    /// Optimizer steps per decoder.
    pub steps: usize,
    /// Pairs per step.
    pub batch_size: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// The pairs the self-supervised shear loss reads: `"all"`, or `"markers"` — only those of
    /// gels that print markers, whose texture moves with the gel (on a markerless gel the
    /// shading moves with the indenter, and brightness constancy prefers its motion).
    pub shear_pairs: ShearPairs,
}

/// `train.shear_pairs` of a field-probe config.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ShearPairs {
    /// Every training pair.
    #[default]
    All,
    /// The pairs of marker gels.
    Markers,
}

impl Default for TrainSection {
    fn default() -> Self {
        Self {
            steps: 600,
            batch_size: 8,
            lr: 1e-3,
            shear_pairs: ShearPairs::All,
        }
    }
}

/// `[references]` of a field-probe config.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ReferenceSection {
    /// Train the supervised ceiling.
    pub supervised: bool,
    /// Self-supervised decoders on this many random encoders (recipe seeds 0, 1, …).
    pub random_draws: usize,
    /// Extra loss weight of the pixels in contact for the models trained on the fields (the
    /// supervised decoder and the U-Net ceiling): 0 is the plain mean squared error.
    pub contact_weight: f64,
}

impl Default for ReferenceSection {
    fn default() -> Self {
        Self {
            supervised: true,
            random_draws: 3,
            contact_weight: 0.0,
        }
    }
}

/// A field-probe config (`tacbench/fields_*.toml`); paths are relative to the file.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldProbeConfig {
    /// Seed of the decoders' draws and batch order.
    #[serde(default)]
    pub seed: u64,
    /// The encoder's training recipe: architecture, input size and frame stacking.
    pub recipe: PathBuf,
    /// Every `frame_stride`-th frame of a sequence is a sample.
    #[serde(default = "two")]
    pub frame_stride: usize,
    /// Bootstrap draws of the intervals.
    #[serde(default = "thousand")]
    pub bootstrap: usize,
    /// Every `seen_test_period`-th sequence of the training split is held out as the
    /// in-distribution test (shapes the models train on, sequences they never see), scored
    /// beside the held-out shapes; 0: no such split.
    #[serde(default)]
    pub seen_test_period: usize,
    /// Decoder size.
    #[serde(default)]
    pub decoder: DecoderSection,
    /// Training schedule.
    #[serde(default)]
    pub train: TrainSection,
    /// Loss weights.
    #[serde(default)]
    pub loss: LossWeights,
    /// References trained beside the decoder.
    #[serde(default)]
    pub references: ReferenceSection,
    /// The supervised U-Net at the input's resolution, which reads no encoder.
    #[serde(default)]
    pub ceiling: CeilingSection,
}

fn two() -> usize {
    2
}

fn thousand() -> usize {
    1000
}

impl FieldProbeConfig {
    /// Reads and checks a config; every error names the file and the key.
    pub fn load(path: &Path) -> Result<Self, Error> {
        let mut cfg: FieldProbeConfig = crate::io::read_toml(path)?;
        if cfg.recipe.is_relative() {
            cfg.recipe = path.parent().unwrap_or(Path::new("")).join(&cfg.recipe);
        }
        let bad = |field: &str, msg: &str| Err(Error::config(path, field, msg));
        if cfg.frame_stride == 0 {
            return bad("frame_stride", "must be at least 1");
        }
        if cfg.seen_test_period == 1 {
            return bad(
                "seen_test_period",
                "must be 0 (none) or at least 2 (1 would hold out every training sequence)",
            );
        }
        if cfg.train.steps == 0 || cfg.train.batch_size == 0 {
            return bad("train.steps / train.batch_size", "must be at least 1");
        }
        if !(cfg.train.lr.is_finite() && cfg.train.lr > 0.0) {
            return bad("train.lr", "must be a positive number");
        }
        if cfg.decoder.channels < 4 || !cfg.decoder.channels.is_multiple_of(2) {
            return bad("decoder.channels", "must be an even number ≥ 4");
        }
        if !(cfg.decoder.max_flow_px.is_finite() && cfg.decoder.max_flow_px > 0.0) {
            return bad("decoder.max_flow_px", "must be a positive number");
        }
        let w = cfg.references.contact_weight;
        if !(w.is_finite() && w >= 0.0) {
            return bad("references.contact_weight", "must be a finite number ≥ 0");
        }
        let c = &cfg.ceiling;
        if c.channels == 0 || c.steps == 0 || c.batch_size == 0 || c.validate_every == 0 {
            return bad(
                "ceiling.channels / steps / batch_size / validate_every",
                "must be at least 1",
            );
        }
        if c.validation_period < 2 {
            return bad(
                "ceiling.validation_period",
                "must be at least 2 (every n-th training sequence validates)",
            );
        }
        if !(c.lr.is_finite() && c.lr > 0.0) {
            return bad("ceiling.lr", "must be a positive number");
        }
        let l = &cfg.loss;
        if !(0.0..=1.0).contains(&l.ssim) {
            return bad("loss.ssim", "must lie in [0, 1]");
        }
        for (name, v) in [
            ("loss.normal_smoothness", l.normal_smoothness),
            ("loss.normal_sparsity", l.normal_sparsity),
            ("loss.shear_smoothness", l.shear_smoothness),
            ("loss.slope_gain", l.slope_gain),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(name, "must be a finite number ≥ 0");
            }
        }
        Ok(cfg)
    }

    /// The recipe, and the frame offset of its stacking (`I_t ⊕ I_{t−k}`).
    fn recipe(&self, path: &Path) -> Result<(Recipe, usize), Error> {
        let recipe = Recipe::load(&self.recipe).map_err(|e| Error::config(path, "recipe", e))?;
        match recipe.stacking() {
            Stacking::Channels(o) if o.len() == 2 && o[0] == 0 && o[1] > 0 => {
                let k = o[1];
                Ok((recipe, k))
            }
            other => Err(Error::config(
                path,
                "recipe",
                format!(
                    "{}: the field decoder reads image pairs I_t ⊕ I_(t−k); this recipe stacks \
                     {other:?}",
                    self.recipe.display()
                ),
            )),
        }
    }
}

/// One trained decoder of a run.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct DecoderRecord {
    /// Name in tables (`self-supervised`, `supervised`, `random-k`).
    pub name: String,
    /// The encoder: `None` for the given weights, `Some(k)` for the random draw of seed k.
    pub random_seed: Option<u64>,
    /// Trained on the ground truth.
    pub supervised: bool,
    /// Loss of the first and last steps.
    pub loss_first_last: [f64; 2],
    /// Wall time of encoding and training (s).
    pub seconds: f64,
    /// File under `RUN/decoders/`.
    pub file: String,
}

/// `RUN/run.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunRecord {
    /// The config as loaded (recipe path absolute).
    pub config: FieldProbeConfig,
    /// The config file.
    pub config_path: PathBuf,
    /// The encoder weights.
    pub encoder: PathBuf,
    /// Their sha256.
    pub encoder_sha256: String,
    /// The training data.
    pub data: PathBuf,
    /// Trained with `--quick`.
    pub quick: bool,
    /// Training pairs used.
    pub train_pairs: usize,
    /// The decoders.
    pub decoders: Vec<DecoderRecord>,
    /// The U-Net ceiling, when trained.
    #[serde(default)]
    pub ceiling: Option<CeilingRecord>,
}

fn absolute(p: &Path) -> PathBuf {
    std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf())
}

fn sha256_file(path: &Path) -> Result<String, Error> {
    let bytes = std::fs::read(path).map_err(|e| Error::file(path, e))?;
    Ok(format!("{:x}", Sha256::digest(&bytes)))
}

fn decoder_config(cfg: &FieldProbeConfig, recipe: &Recipe) -> Result<FieldDecoderConfig, Error> {
    let vit = recipe.encoder_config()?;
    let [_, gh, gw] = vit.grid();
    Ok(
        FieldDecoderConfig::new(vit.embed_dim, [gh, gw], vit.img_size)
            .with_channels(cfg.decoder.channels)
            .with_max_flow_px(cfg.decoder.max_flow_px)
            .with_image_skip(cfg.decoder.image_skip),
    )
}

fn load_pretrained(recipe: &Recipe, weights: &Path) -> Result<Vit, Error> {
    if !weights.is_file() {
        return Err(Error::file(weights, "no such encoder file"));
    }
    sparsh_ssl::weights::load_encoder(random_encoder(recipe, 0)?, weights, None).map_err(|e| {
        Error::file(
            weights,
            format!("does not fit the recipe's architecture: {e}"),
        )
    })
}

/// Loads the pairs a run uses (capped under `--quick`).
fn load_pairs(
    data: &Path,
    recipe: &Recipe,
    offset: usize,
    cfg: &FieldProbeConfig,
    quick: bool,
) -> Result<FramePairs, Error> {
    let size = recipe.encoder_config()?.img_size;
    let mut pairs = FramePairs::load(data, size, offset, cfg.frame_stride, cfg.seen_test_period)?;
    if quick {
        pairs.train.truncate(24);
        pairs.test.truncate(12);
        pairs.seen.truncate(12);
    }
    Ok(pairs)
}

/// The settings a trained model depends on, besides the encoder and the data: a
/// self-supervised decoder's (`Some(false)`), the supervised decoder's (`Some(true)`) or the
/// U-Net's (`None`).
fn settings(cfg: &FieldProbeConfig, model: Option<bool>) -> serde_json::Value {
    let common = (
        cfg.seed,
        absolute(&cfg.recipe),
        cfg.frame_stride,
        cfg.decoder.max_flow_px,
        cfg.seen_test_period,
    );
    match model {
        // the supervised decoder reads neither the self-supervised loss nor its pairs
        Some(true) => serde_json::json!([
            common,
            cfg.decoder,
            [cfg.train.steps, cfg.train.batch_size],
            cfg.train.lr,
            cfg.references.contact_weight
        ]),
        Some(false) => serde_json::json!([common, cfg.decoder, cfg.train, cfg.loss]),
        None => serde_json::json!([common, cfg.ceiling, cfg.references.contact_weight]),
    }
}

/// Saves `model` to `RUN/decoders/<name>.bpk` through a temporary file.
fn save_model<M: Module>(model: M, out: &Path, name: &str) -> Result<String, Error> {
    let file = format!("{name}.bpk");
    let path = out.join("decoders").join(&file);
    let tmp = out.join("decoders").join(format!("{name}.bpk.tmp-write"));
    model
        .save_file(&tmp)
        .map_err(|e| Error::file(&tmp, format!("{e:?}")))?;
    std::fs::rename(&tmp, &path).map_err(|e| Error::file(&path, e))?;
    Ok(file)
}

/// `sparsh fieldprobe train`: the encoders run and the decoders train on `device` (every model
/// drawn on the CPU under its seed and moved; the saved decoders load on any device). With
/// `resume`, a model already in `out` is kept when the earlier run's encoder, data and the
/// settings that model depends on are the same (so that a reference added to a config does
/// not retrain the rest).
#[allow(clippy::too_many_arguments)]
pub fn train_run(
    config_path: &Path,
    encoder: &Path,
    data: &Path,
    out: &Path,
    quick: bool,
    resume: bool,
    device: &Device,
    log: &dyn Fn(&str),
) -> Result<RunRecord, Error> {
    let cfg = FieldProbeConfig::load(config_path)?;
    let (recipe, offset) = cfg.recipe(config_path)?;
    let pretrained = load_pretrained(&recipe, encoder)?;
    let pairs = load_pairs(data, &recipe, offset, &cfg, quick)?;
    let dec_cfg = decoder_config(&cfg, &recipe)?;
    let encoder_sha256 = sha256_file(encoder)?;
    let steps = if quick { 3 } else { cfg.train.steps };
    let draws = if quick {
        cfg.references.random_draws.min(1)
    } else {
        cfg.references.random_draws
    };
    let earlier = if resume && out.join("run.json").is_file() {
        let run = read_run(out)?;
        let same = run.encoder_sha256 == encoder_sha256
            && run.data == absolute(data)
            && run.quick == quick
            && run.train_pairs == pairs.train.len();
        if !same {
            log("field probe: the earlier run read another encoder or data; training every model");
        }
        same.then_some(run)
    } else {
        None
    };
    let file_there = |file: &str| out.join("decoders").join(file).is_file();
    let unchanged = |run: &RunRecord, model| settings(&run.config, model) == settings(&cfg, model);
    let kept_decoder = |name: &str, supervised: bool| {
        earlier
            .as_ref()
            .filter(|run| unchanged(run, Some(supervised)))
            .and_then(|run| run.decoders.iter().find(|d| d.name == name))
            .filter(|d| file_there(&d.file))
            .cloned()
    };
    let kept_ceiling = || {
        earlier
            .as_ref()
            .filter(|run| unchanged(run, None))
            .and_then(|run| run.ceiling.clone())
            .filter(|c| file_there(&c.file))
    };
    let targets = if cfg.references.supervised || cfg.ceiling.cnn {
        let truth = GroundTruth::new(&pairs);
        let truths = pairs
            .train
            .iter()
            .map(|&p| truth.pair(p))
            .collect::<Result<Vec<_>, _>>()?;
        Some(Targets::new(&truths, cfg.references.contact_weight))
    } else {
        None
    };
    log(&format!(
        "field probe: {} training pairs of {} sequences, I_t ⊕ I_(t−{offset}), {steps} steps per decoder",
        pairs.train.len(),
        pairs
            .sequences
            .iter()
            .filter(|s| !s.test && !s.seen_test)
            .count()
    ));
    let mut plan: Vec<(String, Option<u64>, bool)> = vec![("self-supervised".into(), None, false)];
    if cfg.references.supervised {
        plan.push(("supervised".into(), None, true));
    }
    for k in 0..draws {
        plan.push((format!("random-{k}"), Some(k as u64), false));
    }
    std::fs::create_dir_all(out.join("decoders")).map_err(|e| Error::file(out, e))?;
    let mut pretrained_tokens: Option<HookTokens> = None;
    let mut records = Vec::new();
    for (name, random_seed, supervised) in plan {
        if let Some(record) = kept_decoder(&name, supervised) {
            log(&format!("  {name}: kept from the earlier run"));
            records.push(record);
            continue;
        }
        let t0 = Instant::now();
        let mut tokens = match random_seed {
            None => pretrained_tokens
                .get_or_insert_with(|| encode_hooks(&pretrained, &pairs, &pairs.train, device))
                .clone(),
            Some(k) => encode_hooks(&random_encoder(&recipe, k)?, &pairs, &pairs.train, device),
        };
        let stats = tokens.stats();
        tokens.standardize(&stats);
        let opts = TrainOptions {
            steps,
            batch_size: cfg.train.batch_size,
            lr: cfg.train.lr,
            seed: cfg.seed,
            weights: cfg.loss,
            shear_on_markers: cfg.train.shear_pairs == ShearPairs::Markers,
        };
        let every = (steps / 10).max(1);
        let signal = match (&targets, supervised) {
            (Some(t), true) => Signal::Fields(t),
            _ => Signal::Frames {
                data: &pairs,
                pairs: &pairs.train,
            },
        };
        let (model, curve) = train(&tokens, signal, &dec_cfg, opts, device, &|step, loss| {
            if step % every == 0 || step + 1 == steps {
                log(&format!(
                    "  {name}: step {}/{steps}, loss {loss:.5}",
                    step + 1
                ));
            }
        });
        let file = save_model(model, out, &name)?;
        let stats_path = out.join("decoders").join(format!("{name}.stats.json"));
        write_atomic(
            &stats_path,
            &serde_json::to_vec(&stats).expect("serializable"),
        )?;
        let seconds = t0.elapsed().as_secs_f64();
        log(&format!("  {name}: {seconds:.0} s"));
        records.push(DecoderRecord {
            name,
            random_seed,
            supervised,
            loss_first_last: [curve[0], *curve.last().expect("at least one step")],
            seconds,
            file,
        });
    }
    let ceiling = match (&targets, cfg.ceiling.cnn) {
        (Some(targets), true) => Some(match kept_ceiling() {
            Some(record) => {
                log(&format!("  {CEILING}: kept from the earlier run"));
                record
            }
            None => {
                let section = CeilingSection {
                    steps: if quick { 3 } else { cfg.ceiling.steps },
                    validate_every: if quick { 3 } else { cfg.ceiling.validate_every },
                    ..cfg.ceiling.clone()
                };
                let sequence: Vec<usize> = pairs.train.iter().map(|p| p.sequence).collect();
                let (model, mut record) = train_ceiling(
                    &|rows: &[usize]| pairs.pair_inputs(&pairs.train, rows),
                    pairs.size(),
                    &sequence,
                    targets,
                    &section,
                    cfg.decoder.max_flow_px,
                    cfg.seed,
                    device,
                    log,
                )
                .map_err(|e| Error::file(data, e))?;
                record.file = save_model(model, out, "ceiling-cnn")?;
                log(&format!(
                    "  {CEILING}: {:.0} s, step {} of {} kept",
                    record.seconds, record.best_step, section.steps
                ));
                record
            }
        }),
        _ => None,
    };
    let record = RunRecord {
        config: FieldProbeConfig {
            recipe: absolute(&cfg.recipe),
            ..cfg
        },
        config_path: absolute(config_path),
        encoder: absolute(encoder),
        encoder_sha256,
        data: absolute(data),
        quick,
        train_pairs: pairs.train.len(),
        decoders: records,
        ceiling,
    };
    let json = serde_json::to_vec_pretty(&record).expect("serializable");
    write_atomic(&out.join("run.json"), &json)?;
    Ok(record)
}

/// Name of the U-Net ceiling in tables.
pub const CEILING: &str = "ceiling CNN (input resolution)";

/// A decoder ready to predict: its name, encoder, model and token statistics.
type Trained = (String, Vit, FieldModel, TokenStats, bool);

/// Reads the token statistics a decoder was trained with.
fn read_stats(run: &Path, name: &str) -> Result<TokenStats, Error> {
    let path = run.join("decoders").join(format!("{name}.stats.json"));
    let text = std::fs::read_to_string(&path).map_err(|e| Error::file(&path, e))?;
    serde_json::from_str(&text).map_err(|e| Error::file(&path, e))
}

/// Reads `RUN/run.json`.
pub fn read_run(run: &Path) -> Result<RunRecord, Error> {
    let path = run.join("run.json");
    let text = std::fs::read_to_string(&path).map_err(|e| {
        Error::file(
            &path,
            format!("{e} (train the decoders first: sparsh fieldprobe train … --out RUN)"),
        )
    })?;
    serde_json::from_str(&text).map_err(|e| Error::file(&path, e))
}

/// Scores of one method over the test pairs.
#[derive(Debug, Clone)]
struct MethodScores {
    name: String,
    /// Per test pair, the metrics of [`METRICS`].
    per_pair: Vec<[Option<f64>; METRICS.len()]>,
}

/// One row of the results: a method's metric over a subset of test sequences.
#[derive(Debug, Clone, Serialize)]
pub struct ResultRow {
    /// Test frames it covers: `all` (the held-out shapes), `seen_shapes` (held-out sequences of
    /// the training shapes) or `markers` (the held-out shapes' GelSight 2017 sequences).
    pub subset: String,
    /// Method.
    pub method: String,
    /// Metric name ([`METRICS`]).
    pub metric: String,
    /// Mean over sequences of the per-sequence mean.
    pub mean: f64,
    /// 95 % bootstrap interval over sequences.
    pub ci_low: f64,
    /// Upper end.
    pub ci_high: f64,
    /// Sequences with a value.
    pub sequences: usize,
}

/// Per-sequence means of metric `k`, from `rows` (indices into the test pairs).
fn sequence_means(
    pairs: &[Pair],
    scores: &[[Option<f64>; METRICS.len()]],
    k: usize,
    rows: &[usize],
) -> Vec<(usize, f64)> {
    let mut by_seq: std::collections::BTreeMap<usize, (f64, usize)> = Default::default();
    for &i in rows {
        if let Some(v) = scores[i][k].filter(|v| v.is_finite()) {
            let e = by_seq.entry(pairs[i].sequence).or_default();
            e.0 += v;
            e.1 += 1;
        }
    }
    by_seq
        .into_iter()
        .map(|(s, (sum, n))| (s, sum / n as f64))
        .collect()
}

fn summarize(
    subset: &str,
    method: &MethodScores,
    pairs: &[Pair],
    rows: &[usize],
    draws: usize,
    seed: u64,
) -> Vec<ResultRow> {
    (0..METRICS.len())
        .filter_map(|k| {
            let means = sequence_means(pairs, &method.per_pair, k, rows);
            if means.is_empty() {
                return None;
            }
            let values: Vec<f64> = means.iter().map(|m| m.1).collect();
            let groups: Vec<Vec<usize>> = (0..values.len()).map(|i| vec![i]).collect();
            let mean = values.iter().sum::<f64>() / values.len() as f64;
            let (lo, hi) = bootstrap_interval(&groups, draws, seed, |r| {
                r.iter().map(|&i| values[i]).sum::<f64>() / r.len() as f64
            });
            Some(ResultRow {
                subset: subset.into(),
                method: method.name.clone(),
                metric: METRICS[k].into(),
                mean,
                ci_low: lo,
                ci_high: hi,
                sequences: values.len(),
            })
        })
        .collect()
}

/// The sign of a self-supervised normal map is free (its loss sees slopes only); the gel at
/// rest is a map's most common value and belongs at its low end. True when, over `maps` (the
/// training frames, no labels read), the median sits above the mean: the background is high and
/// the contacts dip below it.
fn background_above_contact(maps: &[Vec<f32>]) -> bool {
    let lean: f64 = maps
        .iter()
        .map(|m| {
            let mut v = m.clone();
            v.sort_by(f32::total_cmp);
            let median = v[v.len() / 2] as f64;
            let mean = v.iter().map(|&x| x as f64).sum::<f64>() / v.len() as f64;
            median - mean
        })
        .sum();
    lean > 0.0
}

/// `D → 1 − D`.
fn invert(map: &mut [f32]) {
    map.iter_mut().for_each(|v| *v = 1.0 - *v);
}

/// Normal map of the classical baseline: the background difference's magnitude
/// `‖I_t − bg‖` over the colour channels (the frames are stored as `½ + I − bg`).
fn intensity_map(frame: &[f32], n: usize) -> Vec<f32> {
    (0..n)
        .map(|i| {
            (0..3)
                .map(|c| (frame[c * n + i] - 0.5).powi(2))
                .sum::<f32>()
                .sqrt()
        })
        .collect()
}

fn gray(frame: &[f32], n: usize) -> Vec<f32> {
    (0..n)
        .map(|i| (frame[i] + frame[n + i] + frame[2 * n + i]) / 3.0)
        .collect()
}

/// Contact circle of a normal map: the pixels at or above `threshold`, their centroid and the
/// radius of a disc of their area (input pixels); `None` when no pixel qualifies.
fn contact_circle(map: &[f32], width: usize, threshold: f32) -> Option<([f64; 2], f64)> {
    let (mut n, mut sx, mut sy) = (0usize, 0.0, 0.0);
    for (i, &v) in map.iter().enumerate() {
        if v >= threshold {
            n += 1;
            sx += (i % width) as f64;
            sy += (i / width) as f64;
        }
    }
    (n > 0).then(|| {
        (
            [sx / n as f64, sy / n as f64],
            (n as f64 / std::f64::consts::PI).sqrt(),
        )
    })
}

/// What `eval` found.
#[derive(Debug, Clone)]
pub struct EvalSummary {
    /// Every result row.
    pub rows: Vec<ResultRow>,
    /// The Markdown report.
    pub markdown: String,
}

/// The row that reads the true fields (the scorer's ceiling).
pub const ORACLE: &str = "oracle (true fields)";

/// `sparsh fieldprobe objective`: the shear objective of the config's loss weights on the
/// training pairs of `data` in contact (reads the fields: a check of the loss, not a decoder).
pub fn objective_run(
    config_path: &Path,
    data: &Path,
) -> Result<Vec<super::objective::ObjectiveRow>, Error> {
    let cfg = FieldProbeConfig::load(config_path)?;
    let (recipe, offset) = cfg.recipe(config_path)?;
    let pairs = load_pairs(data, &recipe, offset, &cfg, false)?;
    super::objective::shear_objective(&pairs, &pairs.train, &cfg.loss)
}

/// `sparsh fieldprobe eval`: the encoders and decoders run on `device`.
pub fn eval_run(
    run: &Path,
    data: &Path,
    packs: &[PathBuf],
    device: &Device,
    log: &dyn Fn(&str),
) -> Result<EvalSummary, Error> {
    let record = read_run(run)?;
    let cfg = &record.config;
    let (recipe, offset) = cfg.recipe(&run.join("run.json"))?;
    let pairs = load_pairs(data, &recipe, offset, cfg, record.quick)?;
    let [h, w] = pairs.size();
    let n = h * w;
    let truth = GroundTruth::new(&pairs);
    log(&format!(
        "field probe eval: {} held-out pairs of {} sequences of held-out shapes, {} of {} sequences \
         of training shapes; thresholds from {} training pairs",
        pairs.test.len(),
        pairs.sequences.iter().filter(|s| s.test).count(),
        pairs.seen.len(),
        pairs.sequences.iter().filter(|s| s.seen_test).count(),
        pairs.train.len()
    ));
    // Scored: the held-out shapes' pairs, then the held-out sequences of training shapes.
    let scored: Vec<Pair> = pairs.test.iter().chain(&pairs.seen).copied().collect();
    let test_truth = scored
        .iter()
        .map(|&p| truth.pair(p))
        .collect::<Result<Vec<_>, _>>()?;
    let train_truth = pairs
        .train
        .iter()
        .map(|&p| truth.pair(p))
        .collect::<Result<Vec<_>, _>>()?;
    let in_contact: Vec<usize> = (0..train_truth.len())
        .filter(|&i| train_truth[i].in_contact())
        .collect();
    let threshold_for = |train_maps: &[Vec<f32>]| {
        let maps: Vec<&[f32]> = in_contact
            .iter()
            .map(|&i| train_maps[i].as_slice())
            .collect();
        let masks: Vec<&[bool]> = in_contact
            .iter()
            .map(|&i| train_truth[i].contact.as_slice())
            .collect();
        best_threshold(&maps, &masks)
    };
    let score_all = |normals: Option<&[Vec<f32>]>, flows: Option<&[Vec<[f32; 2]>]>, thr: f32| {
        (0..scored.len())
            .map(|i| {
                score_pair(
                    normals.map(|m| m[i].as_slice()),
                    flows.map(|f| f[i].as_slice()),
                    &test_truth[i],
                    w,
                    thr,
                )
            })
            .collect::<Vec<_>>()
    };
    let pretrained = load_pretrained(&recipe, &record.encoder)?;
    let dec_cfg = decoder_config(cfg, &recipe)?;
    let mut methods: Vec<MethodScores> = Vec::new();
    let mut examples: Vec<(String, Vec<Prediction>)> = Vec::new();
    let mut thresholds: Vec<(String, f32)> = Vec::new();
    let mut orientation: Vec<String> = Vec::new();
    let mut models: Vec<Trained> = Vec::new();
    for d in &record.decoders {
        let vit = match d.random_seed {
            None => pretrained.valid(),
            Some(k) => random_encoder(&recipe, k)?.valid(),
        };
        let vit = sparsh_ssl::device::on_device(vit, device);
        let path = run.join("decoders").join(&d.file);
        let model = FieldModel {
            decoder: dec_cfg.init(&Device::flex()),
            shading: super::loss::Shading::new(&Device::flex()),
        }
        .try_load_file(&path)
        .map_err(|e| Error::file(&path, format!("{e:?}")))?;
        let model = sparsh_ssl::device::on_device(model, device);
        let stats = read_stats(run, &d.name)?;
        let t0 = Instant::now();
        let tokens_of = |list: &[Pair]| {
            let mut t = encode_hooks(&vit, &pairs, list, device);
            t.standardize(&stats);
            t
        };
        let train_pred = predict(&model, &tokens_of(&pairs.train));
        let mut test_pred = predict(&model, &tokens_of(&scored));
        let mut train_maps: Vec<Vec<f32>> = train_pred.into_iter().map(|p| p.normal).collect();
        let flipped = background_above_contact(&train_maps);
        if flipped {
            train_maps.iter_mut().for_each(|m| invert(m));
            test_pred.iter_mut().for_each(|p| invert(&mut p.normal));
            orientation.push(d.name.clone());
        }
        let thr = threshold_for(&train_maps);
        let normals: Vec<Vec<f32>> = test_pred.iter().map(|p| p.normal.clone()).collect();
        let flows: Vec<Vec<[f32; 2]>> = test_pred.iter().map(|p| p.flow.clone()).collect();
        methods.push(MethodScores {
            name: d.name.clone(),
            per_pair: score_all(Some(&normals), Some(&flows), thr),
        });
        log(&format!(
            "  {}: scored in {:.0} s (contact threshold {thr:.3})",
            d.name,
            t0.elapsed().as_secs_f64()
        ));
        thresholds.push((d.name.clone(), thr));
        examples.push((d.name.clone(), test_pred));
        models.push((d.name.clone(), vit, model, stats, flipped));
    }
    let mut ceiling = None;
    if let Some(c) = &record.ceiling {
        let t0 = Instant::now();
        let path = run.join("decoders").join(&c.file);
        let model = FieldCnn::new(
            cfg.ceiling.channels,
            cfg.decoder.max_flow_px,
            &Device::flex(),
        )
        .try_load_file(&path)
        .map_err(|e| Error::file(&path, format!("{e:?}")))?;
        let model = sparsh_ssl::device::on_device(model, device);
        let predict = |list: &[Pair]| {
            let input = |rows: &[usize]| pairs.pair_inputs(list, rows);
            predict_ceiling(&model, &input, [h, w], list.len())
        };
        let train_maps: Vec<Vec<f32>> = predict(&pairs.train)
            .into_iter()
            .map(|p| p.normal)
            .collect();
        let test_pred = predict(&scored);
        let thr = threshold_for(&train_maps);
        let normals: Vec<Vec<f32>> = test_pred.iter().map(|p| p.normal.clone()).collect();
        let flows: Vec<Vec<[f32; 2]>> = test_pred.iter().map(|p| p.flow.clone()).collect();
        methods.push(MethodScores {
            name: CEILING.into(),
            per_pair: score_all(Some(&normals), Some(&flows), thr),
        });
        log(&format!(
            "  {CEILING}: scored in {:.0} s (contact threshold {thr:.3})",
            t0.elapsed().as_secs_f64()
        ));
        thresholds.push((CEILING.into(), thr));
        examples.push((CEILING.into(), test_pred));
        ceiling = Some(model);
    }
    // classical baselines
    let t0 = Instant::now();
    let intensity = |list: &[Pair]| -> Vec<Vec<f32>> {
        list.iter()
            .map(|&p| intensity_map(pairs.frames(p).0, n))
            .collect()
    };
    let train_intensity = intensity(&pairs.train);
    let intensity_thr = threshold_for(&train_intensity);
    let test_intensity = intensity(&scored);
    let params = FarnebackParams::default();
    let farneback: Vec<Vec<[f32; 2]>> = scored
        .iter()
        .map(|&p| {
            let (now, before) = pairs.frames(p);
            farneback_flow(&gray(before, n), &gray(now, n), h, w, &params)
                .map_err(|e| Error::file(run, e))
        })
        .collect::<Result<_, _>>()?;
    let zero_flow = vec![vec![[0.0f32; 2]; n]; scored.len()];
    methods.push(MethodScores {
        name: "zero flow".into(),
        per_pair: score_all(None, Some(&zero_flow), 0.5),
    });
    methods.push(MethodScores {
        name: "classical".into(),
        per_pair: score_all(Some(&test_intensity), Some(&farneback), intensity_thr),
    });
    thresholds.push(("classical".into(), intensity_thr));
    log(&format!(
        "  classical (intensity, Farnebäck): {:.0} s",
        t0.elapsed().as_secs_f64()
    ));
    // The scorer's own ceiling: the true pressure as the normal map (its contact threshold
    // chosen on the training pairs like every other row's) and the true flow, so r(p) and ρ(p)
    // are 1 and the flow errors 0 by construction, and the contact IoU shows what thresholding
    // a perfect map at the input's resolution costs.
    let true_pressure = |truth: &[PairTruth]| -> Vec<Vec<f32>> {
        truth.iter().map(|t| t.pressure_kpa.clone()).collect()
    };
    let oracle_thr = threshold_for(&true_pressure(&train_truth[..]));
    let true_flow: Vec<Vec<[f32; 2]>> = test_truth.iter().map(|t| t.flow_px.clone()).collect();
    methods.push(MethodScores {
        name: ORACLE.into(),
        per_pair: score_all(
            Some(&true_pressure(&test_truth[..])),
            Some(&true_flow),
            oracle_thr,
        ),
    });
    thresholds.push((ORACLE.into(), oracle_thr));
    // markers, where printed
    let marker_rows: Vec<usize> = (0..pairs.test.len())
        .filter(|&i| pairs.sequences[pairs.test[i].sequence].has_markers())
        .collect();
    if !marker_rows.is_empty() {
        let flows: Vec<Vec<[f32; 2]>> = scored
            .iter()
            .map(|&p| marker_flow(&pairs, p).unwrap_or_else(|| vec![[0.0; 2]; n]))
            .collect();
        methods.push(MethodScores {
            name: "markers".into(),
            per_pair: score_all(None, Some(&flows), 0.5),
        });
    }
    // rows
    let all_rows: Vec<usize> = (0..pairs.test.len()).collect();
    let seen_rows: Vec<usize> = (pairs.test.len()..scored.len()).collect();
    let mut rows = Vec::new();
    for m in &methods {
        if m.name != "markers" {
            rows.extend(summarize(
                "all",
                m,
                &scored,
                &all_rows,
                cfg.bootstrap,
                cfg.seed,
            ));
        }
        if !seen_rows.is_empty() && m.name != "markers" {
            rows.extend(summarize(
                "seen_shapes",
                m,
                &scored,
                &seen_rows,
                cfg.bootstrap,
                cfg.seed,
            ));
        }
        if !marker_rows.is_empty() {
            rows.extend(summarize(
                "markers",
                m,
                &scored,
                &marker_rows,
                cfg.bootstrap,
                cfg.seed,
            ));
        }
    }
    let out = run.join("eval");
    std::fs::create_dir_all(&out).map_err(|e| Error::file(&out, e))?;
    write_csv(&out.join("fields.csv"), &rows)?;
    let mut markdown = markdown_tables(&rows, &record);
    markdown.push_str(&format!(
        "\nContact thresholds (chosen on {} training pairs in contact): {}\n",
        in_contact.len(),
        thresholds
            .iter()
            .map(|(m, t)| format!("{m} {t:.3}"))
            .collect::<Vec<_>>()
            .join(", ")
    ));
    if !orientation.is_empty() {
        markdown.push_str(&format!(
            "\nNormal maps read as 1 − D (their background sat above their contacts on the \
             training frames): {}\n",
            orientation.join(", ")
        ));
    }
    // figure
    let figure = out.join("fields_examples.png");
    write_examples(
        &figure,
        &pairs,
        &test_truth,
        &examples,
        &test_intensity,
        &farneback,
    )?;
    markdown.push_str(&format!("\nFigure: {}\n", figure.display()));
    // real packs
    for pack in packs {
        markdown.push_str(&pack_report(
            pack,
            &models,
            ceiling.as_ref(),
            &thresholds,
            intensity_thr,
            [h, w],
            device,
        )?);
    }
    write_atomic(&out.join("fields.md"), markdown.as_bytes())?;
    Ok(EvalSummary { rows, markdown })
}

fn write_csv(path: &Path, rows: &[ResultRow]) -> Result<(), Error> {
    let mut w = csv::Writer::from_writer(Vec::new());
    for r in rows {
        w.serialize(r).map_err(|e| Error::file(path, e))?;
    }
    let bytes = w.into_inner().map_err(|e| Error::file(path, e))?;
    write_atomic(path, &bytes)
}

/// Column headings of the tables, in [`METRICS`] order.
const HEADINGS: [&str; METRICS.len()] = [
    "r(p)",
    "ρ(p)",
    "r(−u_z)",
    "ρ(−u_z)",
    "contact IoU",
    "EPE contact (px)",
    "EPE all (px)",
    "AE contact (°)",
    "AE all (°)",
    "r(‖F‖, ‖q‖)",
    "r(p) near contact",
    "flow spread (px)",
];

fn markdown_tables(rows: &[ResultRow], record: &RunRecord) -> String {
    let mut md = String::new();
    let randoms: Vec<String> = record
        .decoders
        .iter()
        .filter(|d| d.random_seed.is_some())
        .map(|d| d.name.clone())
        .collect();
    for subset in ["all", "seen_shapes", "markers"] {
        let in_subset: Vec<&ResultRow> = rows.iter().filter(|r| r.subset == subset).collect();
        if in_subset.is_empty() {
            continue;
        }
        let mut methods: Vec<String> = Vec::new();
        for r in &in_subset {
            if !methods.contains(&r.method) {
                methods.push(r.method.clone());
            }
        }
        let title = match subset {
            "all" => "All held-out sequences (shapes never trained on)",
            "seen_shapes" => {
                "Held-out sequences of the training shapes (in distribution; no model trained or \
                 stopped on them)"
            }
            _ => "Held-out sequences of the sensor with markers",
        };
        md.push_str(&format!(
            "\n{title} (means over sequences, 95 % bootstrap interval)\n\n| method | {} |\n|---|{}\n",
            HEADINGS.join(" | "),
            "---|".repeat(HEADINGS.len())
        ));
        let get = |m: &str, k: usize| {
            in_subset
                .iter()
                .find(|r| r.method == m && r.metric == METRICS[k])
        };
        for m in &methods {
            let cells: Vec<String> = (0..METRICS.len())
                .map(|k| match get(m, k) {
                    Some(r) => format!("{:.3} [{:.3}, {:.3}]", r.mean, r.ci_low, r.ci_high),
                    None => "—".into(),
                })
                .collect();
            md.push_str(&format!("| {m} | {} |\n", cells.join(" | ")));
        }
        if !randoms.is_empty() && methods.iter().any(|m| m == "self-supervised") {
            let cells: Vec<String> = (0..METRICS.len())
                .map(|k| {
                    let draws: Vec<f64> = randoms
                        .iter()
                        .filter_map(|r| get(r, k).map(|x| x.mean))
                        .collect();
                    match (get("self-supervised", k), draws.is_empty()) {
                        (Some(s), false) => {
                            let sp = Spread::of(&draws);
                            format!(
                                "{:.3} ± {:.3}; rank {}/{}",
                                sp.mean,
                                sp.sd,
                                rank(s.mean, &draws, higher_is_better(k)),
                                draws.len() + 1
                            )
                        }
                        _ => "—".into(),
                    }
                })
                .collect();
            md.push_str(&format!(
                "| random draws: mean ± sd; self-supervised's rank | {} |\n",
                cells.join(" | ")
            ));
        }
    }
    md
}

/// The example figure: for a press, a slide and a twist (the held-out pair with the largest
/// ground-truth motion in contact among sequences of that motion), ground truth beside the
/// decoders and the classical baseline.
fn write_examples(
    path: &Path,
    pairs: &FramePairs,
    truths: &[PairTruth],
    decoders: &[(String, Vec<Prediction>)],
    intensity: &[Vec<f32>],
    farneback: &[Vec<[f32; 2]>],
) -> Result<(), Error> {
    let [h, w] = pairs.size();
    let motion = |i: usize| -> f64 {
        let t = &truths[i];
        t.flow_px
            .iter()
            .zip(&t.contact)
            .filter(|(_, c)| **c)
            .map(|(f, _)| (f[0] as f64).hypot(f[1] as f64))
            .sum::<f64>()
            + t.contact.iter().filter(|c| **c).count() as f64 * 1e-3
    };
    let mut row_labels = Vec::new();
    let mut rows = Vec::new();
    for kind in ["press", "slide", "twist"] {
        let best = (0..pairs.test.len())
            .filter(|&i| {
                let fam = &pairs.sequences[pairs.test[i].sequence].family;
                fam.ends_with(kind) && truths[i].in_contact()
            })
            .max_by(|&a, &b| motion(a).total_cmp(&motion(b)));
        let Some(i) = best else { continue };
        let fam = &pairs.sequences[pairs.test[i].sequence].family;
        row_labels.push(format!("{fam}, frame {}", pairs.test[i].t));
        let panel = |title: &str, normal: &[f32], flow: &[[f32; 2]]| Panel {
            title: title.into(),
            height: h,
            width: w,
            normal: normal.to_vec(),
            shear_px: Some(flow.to_vec()),
        };
        let mut row = vec![panel(
            "ground truth (p, Δu)",
            &truths[i].pressure_kpa,
            &truths[i].flow_px,
        )];
        for (name, preds) in decoders.iter().filter(|(n, _)| {
            ["self-supervised", "supervised", "random-0", CEILING].contains(&n.as_str())
        }) {
            let title = if name == CEILING { "ceiling CNN" } else { name };
            row.push(panel(title, &preds[i].normal, &preds[i].flow));
        }
        row.push(panel("classical", &intensity[i], &farneback[i]));
        rows.push(row);
    }
    if rows.is_empty() {
        return Ok(());
    }
    write_field_grid(path, &row_labels, &rows).map_err(|e| Error::file(path, e))
}

/// The contact region of each decoder's normal map (and of the background difference) on a
/// real Taxim pack's frames against the pack's contact circles, as a Markdown table.
fn pack_report(
    pack_path: &Path,
    models: &[Trained],
    ceiling: Option<&FieldCnn>,
    thresholds: &[(String, f32)],
    intensity_thr: f32,
    size: [usize; 2],
    device: &Device,
) -> Result<String, Error> {
    let pack = sparsh_optics::pack::CalibrationPack::read(pack_path)
        .map_err(|e| Error::file(pack_path, format!("{}: {}", e.field, e.message)))?;
    let (fw, fh) = pack.background.dimensions();
    let g = InputGeometry::new(fw as usize, fh as usize, size);
    let bg = &pack.background;
    let pre =
        |img| sparsh_ssl::data::preprocess(img, bg, size).map_err(|e| Error::file(pack_path, e));
    let rest = pre(bg)?;
    let frames = pack.frames.iter().map(pre).collect::<Result<Vec<_>, _>>()?;
    let [h, w] = size;
    let n = h * w;
    // one pair per frame: the contact frame against the no-contact frame
    let input = |vit: &Vit| {
        encode_inputs(vit, size, frames.len(), device, |rows| {
            frames[rows]
                .iter()
                .flat_map(|f| f.iter().chain(rest.iter()).copied())
                .collect()
        })
    };
    let score = |maps: &[Vec<f32>], thr: f32| -> (f64, f64, usize) {
        let mut centre = Vec::new();
        let mut radius = Vec::new();
        let mut missed = 0;
        for (k, m) in maps.iter().enumerate() {
            match contact_circle(m, w, thr) {
                Some((c, r)) => {
                    let c = g.point_to_frame(c);
                    let r = r / g.pixels_per_frame_pixel();
                    let t = pack.centers_px[k];
                    centre.push((c[0] - t[0]).hypot(c[1] - t[1]));
                    radius.push(100.0 * (r - pack.radii_px[k]).abs() / pack.radii_px[k]);
                }
                None => missed += 1,
            }
        }
        let median = |mut v: Vec<f64>| {
            if v.is_empty() {
                return f64::NAN;
            }
            v.sort_by(f64::total_cmp);
            crate::stats::quantile(&v, 0.5)
        };
        (median(centre), median(radius), missed)
    };
    let mut md = format!(
        "\nReal frames: {} ({} frames, {}×{}): median contact-centre error (frame px) and \
         radius error (%) of the thresholded normal map against the pack's circles\n\n\
         | method | centre error (px) | radius error (%) | frames without a region |\n|---|---|---|---|\n",
        pack_path.display(),
        frames.len(),
        fw,
        fh
    );
    for (name, vit, model, stats, flipped) in models {
        let thr = thresholds
            .iter()
            .find(|(m, _)| m == name)
            .map_or(0.5, |t| t.1);
        let mut tokens = input(vit);
        tokens.standardize(stats);
        let mut maps: Vec<Vec<f32>> = predict(model, &tokens)
            .into_iter()
            .map(|p| p.normal)
            .collect();
        if *flipped {
            maps.iter_mut().for_each(|m| invert(m));
        }
        let (c, r, missed) = score(&maps, thr);
        md.push_str(&format!("| {name} | {c:.1} | {r:.1} | {missed} |\n"));
    }
    if let Some(cnn) = ceiling {
        let thr = thresholds
            .iter()
            .find(|(m, _)| m == CEILING)
            .map_or(0.5, |t| t.1);
        let pair = |rows: &[usize]| -> Vec<f32> {
            rows.iter()
                .flat_map(|&i| frames[i].iter().chain(rest.iter()).copied())
                .collect()
        };
        let maps: Vec<Vec<f32>> = predict_ceiling(cnn, &pair, size, frames.len())
            .into_iter()
            .map(|p| p.normal)
            .collect();
        let (c, r, missed) = score(&maps, thr);
        md.push_str(&format!("| {CEILING} | {c:.1} | {r:.1} | {missed} |\n"));
    }
    let maps: Vec<Vec<f32>> = frames.iter().map(|f| intensity_map(f, n)).collect();
    let (c, r, missed) = score(&maps, intensity_thr);
    md.push_str(&format!("| classical | {c:.1} | {r:.1} | {missed} |\n"));
    Ok(md)
}
