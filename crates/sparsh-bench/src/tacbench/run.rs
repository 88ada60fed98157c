//! The benchmark loop: for each task × encoder × label budget × probe seed, fit the head with
//! the epoch chosen on validation, score it on the held-out test sequences, and record the
//! unit on disk so an interrupted run resumes where it stopped.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use burn::prelude::*;
use serde::{Deserialize, Serialize};
use sparsh_ssl::data::{AugmentConfig, HostBatch, Sampler, Stacking};
use sparsh_ssl::recipe::Recipe;
use sparsh_ssl::vit::{Vit, VitConfig};

use super::config::BenchConfig;
use super::pixels::{PixelInputs, fit_ceiling, fit_ridge};
use super::probe::{Fit, FitOptions, Split, Tokens, fit_end_to_end, fit_frozen};
use super::tasks::{Head, TaskKind, TaskSamples, extract, score};
use crate::encoders::{missing_weights, random_encoder};
use crate::io::write_atomic;
use crate::labels::LabelledData;
use crate::{Error, labels};

/// What an encoder row of the results is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, PartialOrd, Ord)]
#[serde(rename_all = "snake_case")]
pub enum EncoderKind {
    /// Pretrained weights.
    Pretrained,
    /// A randomly initialised encoder.
    Random,
    /// The attentive probe on the raw input patches.
    Pixels,
    /// The ViT trained from scratch with the head on the budget's labels.
    EndToEnd,
    /// The classical read-out: ridge regression on block means of the frames
    /// ([`super::pixels::fit_ridge`]).
    Ridge,
    /// The supervised ceiling: a CNN trained on the frames at their own resolution
    /// ([`super::pixels::fit_ceiling`]).
    Ceiling,
    /// The floor oracle: the ceiling's CNN on the true indentation ([`super::pixels`]).
    Oracle,
    /// The floor oracle's linear read-out: the ridge on the true indentation.
    OracleRidge,
    /// The classical GelSight read-out: the floor oracle's ridge on the indentation the frames
    /// show, by a calibrated slope lookup and integration ([`super::photometric`]).
    Photometric,
}

/// One finished (task, encoder, budget, seed): what the report is made from.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Unit {
    /// Task.
    pub task: TaskKind,
    /// Encoder name.
    pub encoder: String,
    /// What the encoder is.
    pub kind: EncoderKind,
    /// For random draws: the `[[random]]` group; for pretrained encoders: the group of the same
    /// architecture they are ranked in, if any.
    pub group: Option<String>,
    /// Label budget.
    pub budget: f64,
    /// Probe seed.
    pub seed: u64,
    /// Labelled training sequences and samples.
    pub train_sequences: usize,
    /// Labelled training samples.
    pub train_samples: usize,
    /// Epoch chosen on validation, and the validation curve.
    pub best_epoch: usize,
    /// Validation metric per epoch.
    pub val_curve: Vec<f64>,
    /// Predictions on the test rows (in the order of [`TaskRun::test`]).
    pub test_preds: Vec<Vec<f64>>,
    /// Predictions on the seen-shape test rows (in the order of [`TaskRun::seen`]).
    #[serde(default)]
    pub seen_preds: Vec<Vec<f64>>,
    /// Every metric of the task on the whole test split, and as `seen_<metric>` on the
    /// seen-shape test split when the task has one.
    pub metrics: BTreeMap<String, f64>,
    /// Fingerprint of the test samples (their sequences and frames) the predictions belong to.
    pub test_key: u64,
}

/// A task's data, samples and splits, shared by every encoder.
pub struct TaskRun {
    /// The samples.
    pub samples: TaskSamples,
    /// Test rows and their sequence of origin.
    pub test: Vec<usize>,
    /// Validation rows.
    pub val: Vec<usize>,
    /// Seen-shape test rows: held-out sequences of the training split's shapes, scored as a
    /// second test split (in distribution) where the data hold out shapes for testing; empty
    /// otherwise (the test split is then itself in distribution).
    pub seen: Vec<usize>,
    /// Training sequences (the pool budgets take shares of), in order.
    pub train_sequences: Vec<usize>,
    /// Every training-split row (for token statistics).
    pub pool: Vec<usize>,
    /// The data.
    pub data: Arc<LabelledData>,
}

impl TaskRun {
    /// Splits `samples` by sequence: the data's own test split when it has one (held-out
    /// indenter shapes), else every fifth sequence; of the rest every fifth is validation —
    /// or, with `validation_shapes`, every sequence of those indenters — and where the data
    /// hold out shapes another fifth is the seen-shape test split.
    pub fn new(
        data: Arc<LabelledData>,
        samples: TaskSamples,
        validation_shapes: &[String],
    ) -> Result<Self, String> {
        let seqs: Vec<usize> = {
            let mut s: Vec<usize> = samples.samples.iter().map(|s| s.sequence).collect();
            s.dedup();
            s
        };
        let marked = seqs.iter().any(|&s| data.labels[s].test == Some(true))
            && seqs.iter().any(|&s| data.labels[s].test == Some(false));
        let is_test = |k: usize, s: usize| {
            if marked {
                data.labels[s].test == Some(true)
            } else {
                k % 5 == 4
            }
        };
        let test_seqs: Vec<usize> = seqs
            .iter()
            .enumerate()
            .filter(|&(k, &s)| is_test(k, s))
            .map(|(_, &s)| s)
            .collect();
        let rest: Vec<usize> = seqs
            .iter()
            .enumerate()
            .filter(|&(k, &s)| !is_test(k, s))
            .map(|(_, &s)| s)
            .collect();
        let (val_seqs, seen_seqs): (Vec<usize>, Vec<usize>) = if validation_shapes.is_empty() {
            let val = rest.iter().copied().skip(4).step_by(5).collect();
            let seen = if marked {
                rest.iter().copied().skip(2).step_by(5).collect()
            } else {
                Vec::new()
            };
            (val, seen)
        } else {
            let shape_of = |s: usize| data.labels[s].indenter.as_deref();
            if let Some(&s) = rest.iter().find(|&&s| shape_of(s).is_none()) {
                return Err(format!(
                    "validation_shapes needs each sequence's indenter, and sequence {s} has none \
                     (labels.jsonl without `indenter`: regenerate the data)"
                ));
            }
            let trained: BTreeSet<&str> = rest.iter().filter_map(|&s| shape_of(s)).collect();
            if let Some(name) = validation_shapes
                .iter()
                .find(|n| !trained.contains(n.as_str()))
            {
                return Err(format!(
                    "validation_shapes: no training sequence has indenter {name:?} (training \
                     indenters: {})",
                    trained.into_iter().collect::<Vec<_>>().join(", ")
                ));
            }
            let (val, others): (Vec<usize>, Vec<usize>) = rest.iter().copied().partition(|&s| {
                validation_shapes
                    .iter()
                    .any(|n| shape_of(s) == Some(n.as_str()))
            });
            let seen = if marked {
                others.into_iter().skip(2).step_by(5).collect()
            } else {
                Vec::new()
            };
            (val, seen)
        };
        let train_sequences: Vec<usize> = rest
            .iter()
            .copied()
            .filter(|s| !val_seqs.contains(s) && !seen_seqs.contains(s))
            .collect();
        if test_seqs.is_empty() || val_seqs.is_empty() || train_sequences.is_empty() {
            return Err(format!(
                "the {} task has {} sequences with samples: too few for training, validation and \
                 test splits (at least 5 needed, and a held-out test split)",
                samples.kind.name(),
                seqs.len()
            ));
        }
        let rows_of = |set: &[usize]| -> Vec<usize> {
            (0..samples.samples.len())
                .filter(|&i| set.contains(&samples.samples[i].sequence))
                .collect()
        };
        Ok(Self {
            test: rows_of(&test_seqs),
            val: rows_of(&val_seqs),
            seen: rows_of(&seen_seqs),
            pool: rows_of(&train_sequences),
            train_sequences,
            samples,
            data,
        })
    }

    /// The training sequences of a label budget: an evenly spaced share `budget` of the
    /// training sequences (at least one), taken within each class for class tasks so that
    /// every class keeps at least one sequence.
    pub fn budget_sequences(&self, budget: f64) -> Vec<usize> {
        let pick = |seqs: &[usize]| -> Vec<usize> {
            let n = seqs.len();
            let m = ((budget * n as f64).round() as usize).clamp(1, n);
            (0..m).map(|i| seqs[i * n / m]).collect()
        };
        if self.samples.classes.is_empty() {
            return pick(&self.train_sequences);
        }
        let mut out = Vec::new();
        for c in 0..self.samples.classes.len() {
            let of: Vec<usize> = self
                .train_sequences
                .iter()
                .copied()
                .filter(|&s| self.samples.sequence_class[s] == Some(c))
                .collect();
            if !of.is_empty() {
                out.extend(pick(&of));
            }
        }
        out.sort_unstable();
        out
    }

    /// Training rows of a budget's sequences.
    pub fn rows(&self, sequences: &[usize]) -> Vec<usize> {
        self.pool
            .iter()
            .copied()
            .filter(|&i| sequences.contains(&self.samples.samples[i].sequence))
            .collect()
    }

    /// Fingerprint of the test samples of both test splits (FNV-1a over their sequence and
    /// frame indices): a recorded unit whose key differs was made on other data or splits.
    pub fn test_key(&self) -> u64 {
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        for &i in self.test.iter().chain(&self.seen) {
            let s = &self.samples.samples[i];
            for v in [s.sequence as u64, s.frame as u64] {
                for b in v.to_le_bytes() {
                    h = (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3);
                }
            }
        }
        h
    }

    /// Positions in `rows` (a test split) grouped by sequence, for the bootstrap.
    pub fn groups_of(&self, rows: &[usize]) -> Vec<Vec<usize>> {
        let mut groups: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
        for (k, &i) in rows.iter().enumerate() {
            groups
                .entry(self.samples.samples[i].sequence)
                .or_default()
                .push(k);
        }
        groups.into_values().collect()
    }
}

/// An encoder of the run.
pub struct EncoderEntry {
    /// Name.
    pub name: String,
    /// What it is.
    pub kind: EncoderKind,
    /// Random-draw group it belongs to or is ranked in.
    pub group: Option<String>,
    /// Its recipe (architecture, frame stacking, patch size).
    pub recipe: Recipe,
    /// Weights: `None` for the pixel probe and the end-to-end model (drawn per unit).
    pub vit: Option<Vit>,
}

/// Options of a run beyond its config.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Output directory.
    pub out: PathBuf,
    /// Continue a run in `out`, skipping finished units.
    pub resume: bool,
    /// Small settings for tests: 2 epochs, 2 random draws, budgets 1 and 0.1, at most 20
    /// sequences per task.
    pub quick: bool,
    /// Train nothing: report the units already recorded (tasks without any are left out).
    pub report_only: bool,
    /// Run only these tasks of the config (`None`: all); the others are skipped, so a run
    /// can be done a few tasks at a time and resumed with the rest.
    pub tasks: Option<Vec<TaskKind>>,
    /// Where the encoders run and the heads train (a device without autodiff; the CPU's
    /// `Device::flex()` by default). Every model is drawn on the CPU under its seed and moved.
    pub device: Device,
}

/// The encoders of a config: pretrained ones (loaded; a file of another architecture is a
/// one-line error), the random draws, the pixel probe and the end-to-end model.
pub fn encoders(
    cfg: &BenchConfig,
    random_draws_cap: Option<usize>,
) -> Result<Vec<EncoderEntry>, Error> {
    let mut out = Vec::new();
    let mut groups: Vec<(String, VitConfig, Stacking)> = Vec::new();
    for (i, r) in cfg.random.iter().enumerate() {
        let recipe = cfg.recipe(&r.recipe, &format!("random[{i}].recipe"))?;
        groups.push((r.name.clone(), recipe.encoder_config()?, recipe.stacking()));
        let draws = random_draws_cap.map_or(r.draws, |c| r.draws.min(c));
        for k in 0..draws {
            out.push(EncoderEntry {
                name: format!("{}-{k}", r.name),
                kind: EncoderKind::Random,
                group: Some(r.name.clone()),
                vit: Some(random_encoder(&recipe, k as u64)?),
                recipe: recipe.clone(),
            });
        }
    }
    let mut pretrained = Vec::new();
    for (i, e) in cfg.encoder.iter().enumerate() {
        let recipe = cfg.recipe(&e.recipe, &format!("encoder[{i}].recipe"))?;
        let (arch, stacking) = (recipe.encoder_config()?, recipe.stacking());
        let group = groups
            .iter()
            .find(|(_, a, s)| same_architecture(a, &arch) && *s == stacking)
            .map(|(n, _, _)| n.clone());
        if !e.weights.is_file() {
            return Err(Error::config(
                &cfg.path,
                format!("encoder[{i}].weights"),
                missing_weights(&e.weights, &e.recipe),
            ));
        }
        let vit = sparsh_ssl::weights::load_encoder(random_encoder(&recipe, 0)?, &e.weights, None)
            .map_err(|err| {
                Error::config(
                    &cfg.path,
                    format!("encoder[{i}].weights"),
                    format!(
                        "does not fit the architecture of {}: {err}",
                        e.recipe.display()
                    ),
                )
            })?;
        pretrained.push(EncoderEntry {
            name: e.name.clone(),
            kind: EncoderKind::Pretrained,
            group,
            recipe,
            vit: Some(vit),
        });
    }
    pretrained.extend(out);
    let mut out = pretrained;
    if let Some(b) = &cfg.baselines {
        let recipe = cfg.recipe(&b.recipe, "baselines.recipe")?;
        if b.pixel_probe {
            out.push(EncoderEntry {
                name: "pixels".into(),
                kind: EncoderKind::Pixels,
                group: None,
                recipe: recipe.clone(),
                vit: None,
            });
        }
        if b.end_to_end {
            out.push(EncoderEntry {
                name: "end-to-end".into(),
                kind: EncoderKind::EndToEnd,
                group: None,
                recipe: recipe.clone(),
                vit: None,
            });
        }
        let (ridge, ceiling) = if b.light_normalize {
            ("ridge-light", "supervised-cnn-light")
        } else {
            ("ridge", "supervised-cnn")
        };
        for (on, name, kind) in [
            (b.ridge, ridge, EncoderKind::Ridge),
            (b.ceiling, ceiling, EncoderKind::Ceiling),
            (b.oracle, "floor-cnn", EncoderKind::Oracle),
            (b.oracle, "floor-ridge", EncoderKind::OracleRidge),
            (b.photometric, "photometric-ridge", EncoderKind::Photometric),
        ] {
            if on {
                out.push(EncoderEntry {
                    name: name.into(),
                    kind,
                    group: None,
                    recipe: recipe.clone(),
                    vit: None,
                });
            }
        }
    }
    Ok(out)
}

/// Whether two encoder configurations build the same network (the same weights fit both).
fn same_architecture(a: &VitConfig, b: &VitConfig) -> bool {
    format!("{a:?}") == format!("{b:?}")
}

/// Where a unit is recorded.
fn unit_path(out: &Path, task: TaskKind, encoder: &str, budget: f64, seed: u64) -> PathBuf {
    out.join("units")
        .join(task.name())
        .join(encoder)
        .join(format!("budget{budget}_seed{seed}.json"))
}

/// Reads every recorded unit of a run directory.
pub fn read_units(out: &Path) -> Result<Vec<Unit>, Error> {
    let mut units = Vec::new();
    let root = out.join("units");
    if !root.is_dir() {
        return Ok(units);
    }
    let mut files = Vec::new();
    for task in std::fs::read_dir(&root).map_err(|e| Error::file(&root, e))? {
        let task = task.map_err(|e| Error::file(&root, e))?.path();
        for enc in std::fs::read_dir(&task).map_err(|e| Error::file(&task, e))? {
            let enc = enc.map_err(|e| Error::file(&task, e))?.path();
            for f in std::fs::read_dir(&enc).map_err(|e| Error::file(&enc, e))? {
                let f = f.map_err(|e| Error::file(&enc, e))?.path();
                if f.extension().is_some_and(|e| e == "json") {
                    files.push(f);
                }
            }
        }
    }
    files.sort();
    for f in files {
        units.push(read_unit(&f)?);
    }
    Ok(units)
}

/// Reads one unit record.
fn read_unit(path: &Path) -> Result<Unit, Error> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::file(path, e))?;
    serde_json::from_str(&text).map_err(|e| Error::file(path, e))
}

/// Called after each task with the task runs and every recorded unit so far.
pub type TaskDone<'a> = dyn FnMut(&BTreeMap<TaskKind, TaskRun>, &[Unit]) -> Result<(), Error> + 'a;

/// Progress of a run: called with one line per finished unit.
pub type Progress<'a> = dyn FnMut(&str) + 'a;

/// Runs every unit of `cfg` not yet recorded in `opts.out`, returning the task runs (for the
/// report) and every unit. `ensure_data` makes a task's dataset when it is missing (the CLI
/// generates it from the task's scene); `task_done` sees the runs and units so far after each
/// task (the CLI rewrites the report, so a long run shows its finished tasks).
pub fn run(
    cfg: &BenchConfig,
    opts: &RunOptions,
    ensure_data: &mut dyn FnMut(&crate::tacbench::config::TaskConfig) -> Result<(), Error>,
    progress: &mut Progress<'_>,
    task_done: &mut TaskDone<'_>,
) -> Result<(BTreeMap<TaskKind, TaskRun>, Vec<Unit>), Error> {
    let encoders = encoders(cfg, opts.quick.then_some(2))?;
    let budgets: Vec<f64> = if opts.quick {
        vec![1.0, 0.1]
    } else {
        cfg.budgets.clone()
    };
    let epochs = if opts.quick { 2 } else { cfg.probe.epochs };
    let reach = encoders
        .iter()
        .flat_map(|e| e.recipe.frame_offsets())
        .max()
        .unwrap_or(0);
    let mut sizes: Vec<[usize; 2]> = encoders.iter().map(|e| e.recipe.encoder.img_size).collect();
    sizes.dedup();
    if sizes.len() > 1 {
        return Err(Error::config(
            &cfg.path,
            "encoder",
            format!("every encoder must read one image size, got {sizes:?}"),
        ));
    }
    let size = sizes.first().copied().unwrap_or([96, 72]);
    let mut runs = BTreeMap::new();
    let mut loaded: BTreeMap<PathBuf, LabelledData> = BTreeMap::new();
    for (ti, task) in cfg.task.iter().enumerate() {
        let chosen = opts.tasks.as_ref().is_none_or(|t| t.contains(&task.kind));
        let recorded = opts.out.join("units").join(task.kind.name()).is_dir();
        if !chosen || (opts.report_only && !recorded) {
            continue;
        }
        ensure_data(task)?;
        if !loaded.contains_key(&task.data) {
            loaded.insert(task.data.clone(), labels::load(&task.data, size)?);
        }
        let mut data = loaded[&task.data].clone();
        if let Some(ratio) = task.slip_cone_ratio {
            for f in data.labels.iter_mut().flat_map(|s| s.frames.iter_mut()) {
                if let Some([x, y, z]) = f.force_n {
                    f.slip_cone = Some(x.hypot(y) > ratio * z);
                }
            }
        }
        let mut origin: Vec<usize> = (0..data.labels.len()).collect();
        if opts.quick {
            let keep = quick_sequences(&data, 20);
            data.dataset.sequences = keep
                .iter()
                .map(|&s| data.dataset.sequences[s].clone())
                .collect();
            data.labels = keep.iter().map(|&s| data.labels[s].clone()).collect();
            origin = keep;
        }
        let stride = if opts.quick {
            task.frame_stride * 2
        } else {
            task.frame_stride
        };
        let samples = extract(task.kind, &data.labels, reach, stride).map_err(|m| {
            Error::config(
                &cfg.path,
                format!("task[{ti}]"),
                format!("{}: {m}", task.data.display()),
            )
        })?;
        let data = Arc::new(data);
        let tr = TaskRun::new(data.clone(), samples, &task.validation_shapes).map_err(|m| {
            Error::config(
                &cfg.path,
                format!("task[{ti}]"),
                format!("{}: {m}", task.data.display()),
            )
        })?;
        let classes = tr.samples.classes.len();
        if let Some(b) = cfg.baselines.as_ref().filter(|b| b.oracle || b.photometric)
            && !opts.report_only
        {
            let [rows, cols] = PixelInputs::check_indentation(&task.data)?;
            if b.photometric && b.pixel_size != [cols, rows] {
                return Err(Error::file(
                    &task.data,
                    format!(
                        "baselines.pixel_size {:?} must be the contact grid ({rows} × {cols} \
                         cells) turned to portrait, [{cols}, {rows}], for photometric = true",
                        b.pixel_size
                    ),
                ));
            }
        }
        if let Some(b) = cfg.baselines.as_ref()
            && b.light_normalize
            && (b.ridge || b.ceiling)
            && !task.data.join("labels.jsonl").is_file()
        {
            return Err(Error::file(
                &task.data,
                "baselines.light_normalize needs each sequence's background (a generated \
                 dataset); this layout keeps none",
            ));
        }
        let seeds = if opts.quick {
            1
        } else {
            task.seeds.unwrap_or(cfg.probe.seeds) as u64
        };
        let mut pixels: Option<PixelInputs> = None;
        let mut indentation: Option<PixelInputs> = None;
        for enc in &encoders {
            let mut todo: Vec<(f64, u64)> = Vec::new();
            for b in &budgets {
                for s in 0..seeds {
                    let path = unit_path(&opts.out, task.kind, &enc.name, *b, s);
                    if !path.is_file() {
                        todo.push((*b, s));
                        continue;
                    }
                    let unit = read_unit(&path)?;
                    if unit.test_key != tr.test_key()
                        || unit.test_preds.len() != tr.test.len()
                        || unit.seen_preds.len() != tr.seen.len()
                    {
                        return Err(Error::file(
                            &path,
                            format!(
                                "made on other test samples than {} holds now (was the data \
                                 regenerated?): start a new run in another --out",
                                task.data.display()
                            ),
                        ));
                    }
                }
            }
            if todo.is_empty() || opts.report_only {
                continue;
            }
            let b = cfg.baselines.as_ref();
            let framed = matches!(
                enc.kind,
                EncoderKind::Ridge | EncoderKind::Ceiling | EncoderKind::Photometric
            );
            if framed && pixels.is_none() {
                let b = b.expect("pixel read-outs come from [baselines]");
                pixels = Some(PixelInputs::load(
                    &task.data,
                    &tr.samples.samples,
                    &origin,
                    b.pixel_size,
                    b.light_normalize,
                )?);
            }
            let oracle = matches!(
                enc.kind,
                EncoderKind::Oracle | EncoderKind::OracleRidge | EncoderKind::Photometric
            );
            if oracle && indentation.is_none() {
                indentation = Some(PixelInputs::load_indentation(
                    &task.data,
                    &tr.samples.samples,
                    &origin,
                )?);
            }
            let sampler = Sampler::new(Arc::new(data.dataset.clone()), enc.recipe.stacking())?;
            let index: BTreeMap<(usize, usize), usize> = sampler
                .samples
                .iter()
                .enumerate()
                .map(|(i, &st)| (st, i))
                .collect();
            let picks: Vec<usize> = tr
                .samples
                .samples
                .iter()
                .map(|s| {
                    index.get(&(s.sequence, s.frame)).copied().ok_or_else(|| {
                        Error::file(
                            &task.data,
                            format!(
                                "sequence {} has labels for frame {} but no such frame",
                                s.sequence, s.frame
                            ),
                        )
                    })
                })
                .collect::<Result<_, _>>()?;
            let images = |rows: &[usize]| -> HostBatch {
                let p: Vec<usize> = rows.iter().map(|&r| picks[r]).collect();
                sampler
                    .batch(&p, &AugmentConfig::none(), 0, 0)
                    .expect("TacBench's datasets are decoded when they load")
            };
            let mut tokens = match enc.kind {
                EncoderKind::Pretrained | EncoderKind::Random => Some(encode_all(
                    enc.vit.as_ref().expect("loaded"),
                    &images,
                    picks.len(),
                    &opts.device,
                )),
                EncoderKind::Pixels => Some(patch_tokens_all(
                    &images,
                    picks.len(),
                    enc.recipe.encoder.patch_size,
                )),
                EncoderKind::EndToEnd
                | EncoderKind::Ridge
                | EncoderKind::Ceiling
                | EncoderKind::Oracle
                | EncoderKind::OracleRidge
                | EncoderKind::Photometric => None,
            };
            if let Some(t) = &mut tokens {
                t.standardize(&tr.pool);
            }
            for (budget, seed) in todo {
                let seqs = tr.budget_sequences(budget);
                let train = tr.rows(&seqs);
                let split = Split {
                    train: train.clone(),
                    val: tr.val.clone(),
                    test: tr.test.clone(),
                    seen: tr.seen.clone(),
                };
                let train_refs: Vec<_> = train.iter().map(|&i| &tr.samples.samples[i]).collect();
                let head = Head::new(task.kind, classes, task.force_scale_n, &train_refs);
                let fit_seed = cfg.seed.wrapping_mul(1_000_003).wrapping_add(seed);
                let pixel_fit = |kind: EncoderKind| -> Result<Fit, Error> {
                    let b = b.expect("pixel read-outs come from [baselines]");
                    if kind == EncoderKind::Photometric {
                        let frames = pixels.as_ref().expect("loaded above");
                        let truth = indentation.as_ref().expect("loaded above");
                        let estimated = frames
                            .photometric(truth, &split.train)
                            .map_err(|e| Error::file(&task.data, e))?;
                        return Ok(fit_ridge(
                            &estimated,
                            b.ridge_block,
                            &tr.samples.samples,
                            &head,
                            classes,
                            &split,
                        ));
                    }
                    let p = if matches!(kind, EncoderKind::Oracle | EncoderKind::OracleRidge) {
                        indentation.as_ref()
                    } else {
                        pixels.as_ref()
                    }
                    .expect("loaded above");
                    if matches!(kind, EncoderKind::Ridge | EncoderKind::OracleRidge) {
                        return Ok(fit_ridge(
                            p,
                            b.ridge_block,
                            &tr.samples.samples,
                            &head,
                            classes,
                            &split,
                        ));
                    }
                    Ok(fit_ceiling(
                        p,
                        &tr.samples.samples,
                        &head,
                        classes,
                        &split,
                        FitOptions {
                            epochs: if opts.quick { 2 } else { b.ceiling_epochs },
                            batch_size: cfg.probe.batch_size,
                            lr: b.ceiling_lr,
                            seed: fit_seed,
                            // the oracle runs every epoch: an estimate of the floor from above
                            // gains from every one
                            patience: if kind == EncoderKind::Oracle {
                                0
                            } else {
                                b.ceiling_patience
                            },
                        },
                        &opts.device,
                    ))
                };
                let fit: Fit = match (&tokens, enc.kind) {
                    (
                        None,
                        EncoderKind::Ridge
                        | EncoderKind::Ceiling
                        | EncoderKind::Oracle
                        | EncoderKind::OracleRidge
                        | EncoderKind::Photometric,
                    ) => pixel_fit(enc.kind)?,
                    (Some(t), _) => fit_frozen(
                        t,
                        &tr.samples.samples,
                        &head,
                        classes,
                        &split,
                        FitOptions {
                            epochs,
                            batch_size: cfg.probe.batch_size,
                            lr: cfg.probe.lr,
                            seed: fit_seed,
                            patience: if opts.quick { 0 } else { cfg.probe.patience },
                        },
                        &opts.device,
                    ),
                    (None, _) => {
                        let b = cfg
                            .baselines
                            .as_ref()
                            .expect("end-to-end comes from [baselines]");
                        let e2e_epochs = if opts.quick {
                            2
                        } else {
                            b.end_to_end_epochs.unwrap_or(epochs)
                        };
                        fit_end_to_end(
                            random_encoder(&enc.recipe, 1000 + seed)?,
                            &images,
                            &tr.samples.samples,
                            &head,
                            classes,
                            &split,
                            FitOptions {
                                epochs: e2e_epochs,
                                batch_size: cfg.probe.batch_size,
                                lr: b.end_to_end_lr,
                                seed: fit_seed,
                                patience: 0,
                            },
                            &opts.device,
                        )
                    }
                };
                let mut preds = vec![Vec::new(); tr.samples.samples.len()];
                for (&i, p) in tr
                    .test
                    .iter()
                    .zip(&fit.test_preds)
                    .chain(tr.seen.iter().zip(&fit.seen_preds))
                {
                    preds[i] = p.clone();
                }
                let mut metrics = BTreeMap::new();
                for &m in task.kind.metrics() {
                    let on = |rows: &[usize]| score(m, rows, &preds, &tr.samples.samples);
                    metrics.insert(m.name().to_string(), on(&tr.test));
                    if !tr.seen.is_empty() {
                        metrics.insert(format!("seen_{}", m.name()), on(&tr.seen));
                    }
                }
                let unit = Unit {
                    task: task.kind,
                    encoder: enc.name.clone(),
                    kind: enc.kind,
                    group: enc.group.clone(),
                    budget,
                    seed,
                    train_sequences: seqs.len(),
                    train_samples: train.len(),
                    best_epoch: fit.best_epoch,
                    val_curve: fit.val_curve,
                    test_preds: fit.test_preds,
                    seen_preds: fit.seen_preds,
                    metrics,
                    test_key: tr.test_key(),
                };
                let path = unit_path(&opts.out, task.kind, &enc.name, budget, seed);
                let json = serde_json::to_vec(&unit).map_err(|e| Error::file(&path, e))?;
                write_atomic(&path, &json)?;
                let primary = task.kind.metrics()[0];
                progress(&format!(
                    "{} {} budget {budget} seed {seed}: {} {:.4} (epoch {}, {} training sequences)",
                    task.kind.name(),
                    enc.name,
                    primary.name(),
                    unit.metrics[primary.name()],
                    unit.best_epoch,
                    unit.train_sequences
                ));
            }
        }
        runs.insert(task.kind, tr);
        task_done(&runs, &read_units(&opts.out)?)?;
    }
    let units = read_units(&opts.out)?;
    Ok((runs, units))
}

/// At most `n` sequences spread over the data, keeping the held-out split represented.
fn quick_sequences(data: &LabelledData, n: usize) -> Vec<usize> {
    let total = data.labels.len();
    if total <= n {
        return (0..total).collect();
    }
    let (test, train): (Vec<usize>, Vec<usize>) =
        (0..total).partition(|&s| data.labels[s].test == Some(true));
    let take = |v: &[usize], m: usize| -> Vec<usize> {
        let m = m.min(v.len());
        (0..m).map(|i| v[i * v.len() / m]).collect()
    };
    let n_test = if test.is_empty() { 0 } else { (n / 4).max(1) };
    let mut keep = take(&train, n - n_test);
    keep.extend(take(&test, n_test));
    keep.sort_unstable();
    keep
}

/// The frozen encoder's normalized patch tokens for every sample, computed on `device`.
fn encode_all(
    vit: &Vit,
    images: &dyn Fn(&[usize]) -> HostBatch,
    n: usize,
    device: &Device,
) -> Tokens {
    let device = device.clone().inner();
    let enc = sparsh_ssl::device::on_device(vit.valid(), &device);
    let mut values = Vec::new();
    let mut dims = [0, 0, 0];
    let rows: Vec<usize> = (0..n).collect();
    for chunk in rows.chunks(64) {
        let b = images(chunk);
        let x = Tensor::<1>::from_floats(b.values.as_slice(), &device).reshape(b.shape);
        let out = enc.forward(x, None).patches;
        let [m, t, d] = out.dims();
        dims = [dims[0] + m, t, d];
        values.extend(
            out.into_data()
                .convert::<f32>()
                .try_into_vec::<f32>()
                .expect("f32 tokens"),
        );
    }
    Tokens { values, dims }
}

/// The raw input patches of every sample as tokens (see
/// [`sparsh_ssl::probe::patch_tokens`]).
fn patch_tokens_all(images: &dyn Fn(&[usize]) -> HostBatch, n: usize, patch: usize) -> Tokens {
    let mut values = Vec::new();
    let mut dims = [0, 0, 0];
    let rows: Vec<usize> = (0..n).collect();
    for chunk in rows.chunks(64) {
        let (v, [m, t, d]) = sparsh_ssl::probe::patch_tokens(&images(chunk), patch);
        values.extend(v);
        dims = [dims[0] + m, t, d];
    }
    Tokens { values, dims }
}
