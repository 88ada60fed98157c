//! The TacBench run description (`tacbench/NAME.toml`): tasks and their data, encoders, label
//! budgets, seeds and baselines. Paths are relative to the config file. Unknown keys are
//! errors, and every error names the file and the key.

use std::path::{Path, PathBuf};

use serde::Deserialize;
use sparsh_ssl::recipe::Recipe;

use super::tasks::TaskKind;
use crate::Error;
use crate::io::read_toml;

/// One `[[task]]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TaskConfig {
    /// `force`, `slip`, `pose`, `texture` or `grasp`.
    pub kind: TaskKind,
    /// The labelled dataset: a `sparsh generate` directory or an official TacBench layout.
    pub data: PathBuf,
    /// The scene file that generates `data` when it is missing (optional).
    #[serde(default)]
    pub scene: Option<PathBuf>,
    /// Use every `frame_stride`-th frame of a sequence as a sample (default 1).
    #[serde(default = "one")]
    pub frame_stride: usize,
    /// Recompute the slip task's friction-cone label as ‖F_xy‖ > ratio · F_z from the force
    /// labels (default: the data's own `slip_cone`). A simulated gel of friction μ never
    /// carries more than ‖F_xy‖ = μ F_z, so the official ratio 1.6 is only reached with μ > 1.6.
    #[serde(default)]
    pub slip_cone_ratio: Option<f64>,
    /// Force range per axis (N) the force and ΔF heads' tanh / sigmoid are scaled by
    /// (default DIGIT's official [4, 4, 5]).
    #[serde(default = "digit_force_scale")]
    pub force_scale_n: [f64; 3],
    /// Validate on these training indenters (the labels' `indenter`, e.g. `["box"]`) instead of
    /// every fifth training sequence, so that epochs are chosen on a shape never trained on, as
    /// the held-out test shapes are (default: none).
    #[serde(default)]
    pub validation_shapes: Vec<String>,
    /// Probe and read-out seeds of this task (default `probe.seeds`).
    #[serde(default)]
    pub seeds: Option<usize>,
}

/// One `[[encoder]]`: pretrained weights and the recipe that trained them (architecture and
/// frame stacking).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderConfig {
    /// Name in tables and charts.
    pub name: String,
    /// The training recipe (`assets/ssl/*.toml`).
    pub recipe: PathBuf,
    /// The encoder weights (safetensors, official key names).
    pub weights: PathBuf,
}

/// One `[[random]]`: randomly initialised encoders of a recipe's architecture, each drawn as a
/// run of the recipe with seed `k` draws its own, for k in `0..draws`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RandomConfig {
    /// Name prefix in tables (`NAME-k` per draw).
    pub name: String,
    /// The recipe whose architecture and stacking the draws share.
    pub recipe: PathBuf,
    /// How many draws (at least 1; TacBench runs use at least 8).
    pub draws: usize,
}

/// `[baselines]`: the probe on raw input patches and the end-to-end model.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BaselineConfig {
    /// Recipe giving the architecture and stacking of both.
    pub recipe: PathBuf,
    /// Run the attentive probe on the raw input patches.
    #[serde(default = "yes")]
    pub pixel_probe: bool,
    /// Train the recipe's ViT from scratch with the probe head on each budget's labels.
    #[serde(default = "yes")]
    pub end_to_end: bool,
    /// Epochs of end-to-end training (default: the probe's).
    #[serde(default)]
    pub end_to_end_epochs: Option<usize>,
    /// Peak learning rate of end-to-end training (default 3e-4).
    #[serde(default = "e2e_lr")]
    pub end_to_end_lr: f64,
    /// Run the classical read-out: ridge regression on block means of the frames at
    /// `pixel_size` (`tacbench::pixels`).
    #[serde(default = "yes")]
    pub ridge: bool,
    /// Side of the ridge's blocks in pixels of `pixel_size` (default 8).
    #[serde(default = "ridge_block")]
    pub ridge_block: usize,
    /// Train the supervised ceiling: a small CNN on the frames at `pixel_size` and the task's
    /// labels (default off: minutes per task and budget on a CPU).
    #[serde(default)]
    pub ceiling: bool,
    /// Train the floor oracles: the ceiling's CNN (every epoch) and the ridge on the true
    /// indentation −u_z (needs `uz` among the dataset's fields; default off).
    #[serde(default)]
    pub oracle: bool,
    /// Train the classical GelSight read-out: the floor oracle's ridge on the indentation the
    /// frames show, by a slope lookup calibrated on the training frames' true indentation and
    /// integrated (needs `uz`, and `pixel_size` the contact grid turned to portrait; default
    /// off).
    #[serde(default)]
    pub photometric: bool,
    /// Divide the frames the ridge and the ceiling read by their sequence's light level (each
    /// channel by the mean of its sequence's background over the mean of every background, as
    /// the photometric read-out does), so that the per-sequence LED intensity the scenes draw
    /// does not scale what they read; their rows are then named `ridge-light` and
    /// `supervised-cnn-light` (default off: the official I − bg input).
    #[serde(default)]
    pub light_normalize: bool,
    /// `[height, width]` the ridge and the ceiling read the frames at (default 160×120).
    #[serde(default = "pixel_size")]
    pub pixel_size: [usize; 2],
    /// Most epochs of the ceiling (default 40); it stops earlier after `ceiling_patience`
    /// epochs without a better validation score (default 8).
    #[serde(default = "ceiling_epochs")]
    pub ceiling_epochs: usize,
    /// See `ceiling_epochs`.
    #[serde(default = "ceiling_patience")]
    pub ceiling_patience: usize,
    /// Peak learning rate of the ceiling (default 1e-3).
    #[serde(default = "probe_lr")]
    pub ceiling_lr: f64,
}

/// `[probe]`: training of the attentive probe.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProbeConfig {
    /// Epochs (the epoch scored on test is the best on validation).
    #[serde(default = "epochs")]
    pub epochs: usize,
    /// Batch size.
    #[serde(default = "batch")]
    pub batch_size: usize,
    /// Peak learning rate (AdamW, half-cosine decay to 0).
    #[serde(default = "probe_lr")]
    pub lr: f64,
    /// Probe seeds per (task, encoder, budget).
    #[serde(default = "one")]
    pub seeds: usize,
    /// A frozen probe stops after this many epochs without a better validation score (default
    /// 0: it runs every epoch). The learning rate still decays over `epochs`.
    #[serde(default)]
    pub patience: usize,
}

/// A TacBench run description.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BenchConfig {
    /// Seed of splits, probe draws and bootstrap.
    #[serde(default)]
    pub seed: u64,
    /// Label budgets: shares of the training sequences, each in (0, 1].
    #[serde(default = "budgets")]
    pub budgets: Vec<f64>,
    /// Bootstrap resamples of the test sequences for the 95 % intervals.
    #[serde(default = "bootstrap")]
    pub bootstrap: usize,
    /// Probe training.
    #[serde(default)]
    pub probe: ProbeConfig,
    /// The tasks.
    #[serde(default)]
    pub task: Vec<TaskConfig>,
    /// Pretrained encoders.
    #[serde(default)]
    pub encoder: Vec<EncoderConfig>,
    /// Random-draw baselines.
    #[serde(default)]
    pub random: Vec<RandomConfig>,
    /// Pixel-probe and end-to-end baselines.
    #[serde(default)]
    pub baselines: Option<BaselineConfig>,
    /// Where the config was read from (set by [`BenchConfig::load`]).
    #[serde(skip)]
    pub path: PathBuf,
}

impl Default for ProbeConfig {
    fn default() -> Self {
        Self {
            epochs: epochs(),
            batch_size: batch(),
            lr: probe_lr(),
            seeds: 1,
            patience: 0,
        }
    }
}

fn one() -> usize {
    1
}
fn yes() -> bool {
    true
}
fn digit_force_scale() -> [f64; 3] {
    [4.0, 4.0, 5.0]
}
fn ridge_block() -> usize {
    8
}
fn pixel_size() -> [usize; 2] {
    [160, 120]
}
fn ceiling_epochs() -> usize {
    40
}
fn ceiling_patience() -> usize {
    8
}
fn e2e_lr() -> f64 {
    3e-4
}
fn epochs() -> usize {
    20
}
fn batch() -> usize {
    32
}
fn probe_lr() -> f64 {
    1e-3
}
fn budgets() -> Vec<f64> {
    vec![1.0, 0.33, 0.1, 0.01]
}
fn bootstrap() -> usize {
    1000
}

impl BenchConfig {
    /// Reads and checks `path`; relative paths inside become relative to its directory.
    pub fn load(path: &Path) -> Result<Self, Error> {
        let mut cfg: BenchConfig = read_toml(path)?;
        cfg.path = path.to_path_buf();
        let base = path.parent().unwrap_or(Path::new("")).to_path_buf();
        let rel = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        };
        for t in &mut cfg.task {
            rel(&mut t.data);
            if let Some(s) = &mut t.scene {
                rel(s);
            }
        }
        for e in &mut cfg.encoder {
            rel(&mut e.recipe);
            rel(&mut e.weights);
        }
        for r in &mut cfg.random {
            rel(&mut r.recipe);
        }
        if let Some(b) = &mut cfg.baselines {
            rel(&mut b.recipe);
        }
        cfg.check()?;
        Ok(cfg)
    }

    fn check(&self) -> Result<(), Error> {
        let bad = |field: &str, msg: String| Err(Error::config(&self.path, field, msg));
        if self.budgets.is_empty() {
            return bad("budgets", "give at least one label budget".into());
        }
        for &b in &self.budgets {
            if !(b > 0.0 && b <= 1.0) {
                return bad(
                    "budgets",
                    format!(
                        "a label budget is a share of the training sequences in (0, 1], got {b}"
                    ),
                );
            }
        }
        for (i, b) in self.budgets.iter().enumerate() {
            if self.budgets[..i].contains(b) {
                return bad("budgets", format!("{b} is given twice"));
            }
        }
        if self.task.is_empty() {
            return bad("task", "no [[task]] given".into());
        }
        for (i, t) in self.task.iter().enumerate() {
            if self.task[..i].iter().any(|o| o.kind == t.kind) {
                return bad(
                    &format!("task[{i}].kind"),
                    format!(
                        "`{}` is given twice: one dataset per task and config (write another \
                         config for another dataset)",
                        t.kind.name()
                    ),
                );
            }
        }
        for (i, t) in self.task.iter().enumerate() {
            if t.frame_stride == 0 {
                return bad(
                    &format!("task[{i}].frame_stride"),
                    "must be at least 1".into(),
                );
            }
            if let Some(r) = t.slip_cone_ratio
                && !(r.is_finite() && r > 0.0)
            {
                return bad(
                    &format!("task[{i}].slip_cone_ratio"),
                    format!("must be positive, got {r}"),
                );
            }
            if t.seeds == Some(0) {
                return bad(&format!("task[{i}].seeds"), "must be at least 1".into());
            }
            if t.force_scale_n.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
                return bad(
                    &format!("task[{i}].force_scale_n"),
                    format!(
                        "every axis's range must be positive, got {:?}",
                        t.force_scale_n
                    ),
                );
            }
        }
        if self.probe.epochs == 0 || self.probe.batch_size == 0 || self.probe.seeds == 0 {
            return bad(
                "probe",
                "epochs, batch_size and seeds must be at least 1".into(),
            );
        }
        if !(self.probe.lr.is_finite() && self.probe.lr > 0.0) {
            return bad(
                "probe.lr",
                format!("must be positive, got {}", self.probe.lr),
            );
        }
        if let Some(b) = &self.baselines {
            if b.ridge_block == 0 {
                return bad("baselines.ridge_block", "must be at least 1 pixel".into());
            }
            if b.pixel_size.iter().any(|&v| v < 16) {
                return bad(
                    "baselines.pixel_size",
                    format!(
                        "[height, width] must each be at least 16 pixels, got {:?}",
                        b.pixel_size
                    ),
                );
            }
            if b.ceiling_epochs == 0 {
                return bad("baselines.ceiling_epochs", "must be at least 1".into());
            }
            if !(b.ceiling_lr.is_finite() && b.ceiling_lr > 0.0) {
                return bad(
                    "baselines.ceiling_lr",
                    format!("must be positive, got {}", b.ceiling_lr),
                );
            }
        }
        // names become file names and table rows: unique, plain, and none of the baselines'
        let mut names: std::collections::BTreeSet<String> = [
            "pixels",
            "end-to-end",
            "constant",
            "ridge",
            "ridge-light",
            "supervised-cnn",
            "supervised-cnn-light",
            "floor-cnn",
            "floor-ridge",
            "photometric-ridge",
        ]
        .map(String::from)
        .into();
        let plain = |n: &str| {
            !n.is_empty()
                && n.chars()
                    .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
                && !n.starts_with('.')
        };
        for (i, e) in self.encoder.iter().enumerate() {
            if !plain(&e.name) {
                return bad(
                    &format!("encoder[{i}].name"),
                    format!("`{}`: use letters, digits, `-`, `_` and `.` only", e.name),
                );
            }
            if !names.insert(e.name.clone()) {
                return bad(
                    &format!("encoder[{i}].name"),
                    format!(
                        "`{}` is taken (names are unique; pixels, end-to-end, ridge, supervised-cnn, floor-cnn, floor-ridge, photometric-ridge and constant are the baselines')",
                        e.name
                    ),
                );
            }
        }
        for (i, r) in self.random.iter().enumerate() {
            if r.draws == 0 {
                return bad(
                    &format!("random[{i}].draws"),
                    format!("`{}` draws no encoder", r.name),
                );
            }
            if !plain(&r.name) {
                return bad(
                    &format!("random[{i}].name"),
                    format!("`{}`: use letters, digits, `-`, `_` and `.` only", r.name),
                );
            }
            for name in std::iter::once(r.name.clone())
                .chain((0..r.draws).map(|k| format!("{}-{k}", r.name)))
            {
                if !names.insert(name.clone()) {
                    return bad(&format!("random[{i}].name"), format!("`{name}` is taken"));
                }
            }
        }
        if let Some(b) = &self.baselines
            && b.end_to_end_epochs == Some(0)
        {
            return bad("baselines.end_to_end_epochs", "must be at least 1".into());
        }
        if let Some(b) = &self.baselines
            && !(b.end_to_end_lr.is_finite() && b.end_to_end_lr > 0.0)
        {
            return bad(
                "baselines.end_to_end_lr",
                format!("must be positive, got {}", b.end_to_end_lr),
            );
        }
        if self.bootstrap == 0 {
            return bad("bootstrap", "must be at least 1".into());
        }
        Ok(())
    }

    /// Loads a recipe named by this config, naming the config key on failure.
    pub fn recipe(&self, path: &Path, field: &str) -> Result<Recipe, Error> {
        Recipe::load(path).map_err(|e| Error::config(&self.path, field, e))
    }
}
