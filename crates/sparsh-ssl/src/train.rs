//! The pretraining loop: AdamW with warm-up + cosine, one objective per run, a CSV log of loss,
//! learning rate and the online force probe, atomic checkpoints and exact resume.
//!
//! A run directory holds `recipe.toml` (the recipe it was started with), `log.csv`
//! (`step,loss,lr,probe_rmse_mn,probe_linear_mn,probe_baseline_mn,probe_feature_std,probe_feature_rank,wait_s,step_s`), `checkpoint/`
//! (`model.bpk`, `optim.bpk`, `state.json`, `encoder.safetensors`) and `encoder.safetensors`, the
//! encoder where the last invocation stopped (the end of the schedule, or `--max-steps`). A checkpoint is written to `checkpoint.tmp/` and renamed into place, so
//! an interrupted write never leaves a half checkpoint. Every random draw of step `s` comes from
//! `(seed, s)`, so `--resume` continues with the very batches, masks and views an uninterrupted
//! run would have used.

use std::io::Write;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::{AdamWConfig, GradientsParams};
use burn::prelude::*;
use rayon::prelude::*;

use crate::Error;
use crate::data::{Dataset, HostBatch, Sampler};
use crate::device::{Devices, seeded_module};
use crate::dino::Dino;
use crate::ema::momentum_at;
use crate::jepa::Jepa;
use crate::mae::Mae;
use crate::masks::{DinoViews, JepaMasks, MaeMask, dino_views, ijepa_masks, mae_mask, tube_masks};
use crate::probe::{ProbeScore, ProbeSet};
use crate::recipe::{ObjectiveKind, Recipe};
use crate::rng::Rng;
use crate::vit::Vit;
use crate::weights::write_atomic;

/// A model under training, one variant per objective.
// One value per run: boxing the larger variants would buy nothing.
#[allow(clippy::large_enum_variant)]
#[derive(Module, Debug)]
pub enum Trainee {
    /// MAE.
    Mae(Mae),
    /// DINO.
    Dino(Dino),
    /// I-JEPA or V-JEPA.
    Jepa(Jepa),
}

/// What one training step reports.
#[derive(Debug, Clone, Copy)]
pub struct StepReport {
    /// Steps completed.
    pub step: usize,
    /// Total steps of the run.
    pub total: usize,
    /// Loss of this step.
    pub loss: f64,
    /// Learning rate of this step.
    pub lr: f64,
    /// Seconds the trainer waited for the batch.
    pub wait_s: f64,
    /// Seconds of the whole step.
    pub step_s: f64,
    /// Probe score, when the probe ran before this step.
    pub probe: Option<ProbeScore>,
}

impl Trainee {
    /// A freshly initialized model for `recipe` on `device` (an autodiff device), drawn on the
    /// CPU under the recipe's seed and then moved, so every device starts from the same weights.
    pub fn init(recipe: &Recipe, device: &Device) -> Result<Self, Error> {
        let cpu = Device::flex().autodiff();
        Ok(crate::device::on_device(
            Self::init_on(recipe, &cpu)?,
            device,
        ))
    }

    fn init_on(recipe: &Recipe, device: &Device) -> Result<Self, Error> {
        let (mae, dino, jepa) = match recipe.objective {
            ObjectiveKind::Mae => (Some(recipe.mae_config()?), None, None),
            ObjectiveKind::Dino => (None, Some(recipe.dino_config()?), None),
            ObjectiveKind::Ijepa | ObjectiveKind::Vjepa => {
                (None, None, Some(recipe.jepa_config()?))
            }
        };
        Ok(seeded_module(device, recipe.seed, || {
            if let Some(c) = mae {
                Trainee::Mae(c.init(device))
            } else if let Some(c) = dino {
                Trainee::Dino(c.init(device))
            } else {
                Trainee::Jepa(jepa.expect("one objective").init(device))
            }
        }))
    }

    /// The encoder being pretrained.
    pub fn encoder(&self) -> &Vit {
        match self {
            Trainee::Mae(m) => &m.encoder,
            Trainee::Dino(m) => &m.encoder,
            Trainee::Jepa(m) => &m.encoder,
        }
    }

    /// The masks or views of step `step` for a batch of `b`, drawn from `(seed, step)`.
    pub fn draw(&self, recipe: &Recipe, b: usize, step: usize) -> StepDraw {
        let mut rng = Rng::for_step(recipe.seed, step as u64, 1);
        let enc = recipe.encoder_config().expect("validated recipe");
        let [gt, gh, gw] = enc.grid();
        match self {
            Trainee::Mae(_) => StepDraw::Mae(mae_mask(
                &mut rng,
                b,
                enc.num_patches(),
                recipe.mae.mask_ratio,
            )),
            Trainee::Dino(_) => {
                let views = dino_views(&mut rng, b, gh * gt, gw, &recipe.dino.views);
                StepDraw::Dino {
                    views,
                    teacher_temp: recipe.dino.teacher_temp_at(step),
                }
            }
            Trainee::Jepa(_) => StepDraw::Jepa(if recipe.objective == ObjectiveKind::Vjepa {
                recipe
                    .jepa
                    .tube_masks
                    .iter()
                    .map(|c| tube_masks(&mut rng, b, [gt, gh, gw], c))
                    .collect()
            } else {
                vec![ijepa_masks(&mut rng, b, gh, gw, &recipe.jepa.masks)]
            }),
        }
    }

    /// Loss of step `step` on the whole batch `x`, with masks / views drawn from
    /// `(seed, step)`; for DINO also the teacher mean for the centre update.
    pub fn loss(
        &self,
        recipe: &Recipe,
        x: Tensor<5>,
        step: usize,
    ) -> (Tensor<1>, Option<Tensor<2>>) {
        let b = x.dims()[0];
        self.draw_loss(x, &self.draw(recipe, b, step), 0..b)
    }

    /// Updates after the optimizer step of `step`: teacher / target EMA, DINO centre.
    pub fn after_step(self, recipe: &Recipe, step: usize, aux: Option<Tensor<2>>) -> Self {
        let total = recipe.optim.steps;
        match self {
            Trainee::Mae(m) => Trainee::Mae(m),
            Trainee::Dino(m) => {
                let [a, b] = recipe.dino.ema;
                let mean = aux.expect("DINO reports its teacher mean");
                Trainee::Dino(m.after_step(momentum_at(a, b, step, total), mean))
            }
            Trainee::Jepa(m) => {
                let [a, b] = recipe.jepa.ema;
                Trainee::Jepa(m.after_step(momentum_at(a, b, step, total)))
            }
        }
    }

    /// Gradients of step `step`'s loss on `x`, taken over `optim.micro_batches` micro-batches on
    /// each of `devices` ([`micro_batch_gradients`]): the gradients, the loss value and, for
    /// DINO, the teacher mean for the centre update, all on the first device.
    pub fn gradients(
        &self,
        recipe: &Recipe,
        x: Tensor<5>,
        step: usize,
        devices: &[Device],
    ) -> (GradientsParams, f64, Option<Tensor<2>>) {
        let b = x.dims()[0];
        let draw = self.draw(recipe, b, step);
        micro_batch_gradients(self, x, devices, recipe.optim.micro_batches, |m, x, r| {
            m.draw_loss(x, &draw, r)
        })
    }

    /// Loss on `x`, the batch rows `rows` of a step whose masks / views are `draw`, and, for
    /// DINO, the teacher mean.
    fn draw_loss(
        &self,
        x: Tensor<5>,
        draw: &StepDraw,
        rows: Range<usize>,
    ) -> (Tensor<1>, Option<Tensor<2>>) {
        match (self, draw) {
            (Trainee::Mae(m), StepDraw::Mae(mask)) => (m.loss(x, &mask.rows(rows)), None),
            (
                Trainee::Dino(m),
                StepDraw::Dino {
                    views,
                    teacher_temp,
                },
            ) => {
                let (loss, mean) = m.loss(x, &views.rows(rows), *teacher_temp);
                (loss, Some(mean))
            }
            (Trainee::Jepa(m), StepDraw::Jepa(sets)) => {
                let sets: Vec<JepaMasks> = sets.iter().map(|s| s.rows(rows.clone())).collect();
                (m.loss(x, &sets), None)
            }
            _ => unreachable!("a step's draw comes from the same objective"),
        }
    }

    /// One full training step on a host batch: loss, backward (per micro-batch and device),
    /// AdamW, EMA. `devices` are autodiff devices, the model lives on the first; with several the
    /// step is data-parallel ([`micro_batch_gradients`]). Returns the loss (mean over the
    /// micro-batches).
    pub fn train_step(
        self,
        recipe: &Recipe,
        optim: &mut burn::optim::ModuleOptimizer,
        batch: &HostBatch,
        devices: &[Device],
    ) -> (Self, f64) {
        let x = Tensor::<1>::from_floats(batch.values.as_slice(), &devices[0]).reshape(batch.shape);
        let (grads, value, aux) = self.gradients(recipe, x, batch.step, devices);
        let next = optim.step(recipe.optim.lr_at(batch.step), self, grads);
        (next.after_step(recipe, batch.step, aux), value)
    }

    fn save(&self, path: &Path) -> Result<(), Error> {
        let r = match self {
            Trainee::Mae(m) => m.clone().save_file(path),
            Trainee::Dino(m) => m.clone().save_file(path),
            Trainee::Jepa(m) => m.clone().save_file(path),
        };
        r.map_err(|e| Error::file(path, e))
    }

    fn load(self, path: &Path) -> Result<Self, Error> {
        let err = |e: burn::store::RecordError| {
            Error::file(
                path,
                format!("{e} (truncated file or another architecture?)"),
            )
        };
        Ok(match self {
            Trainee::Mae(m) => Trainee::Mae(m.try_load_file(path).map_err(err)?),
            Trainee::Dino(m) => Trainee::Dino(m.try_load_file(path).map_err(err)?),
            Trainee::Jepa(m) => Trainee::Jepa(m.try_load_file(path).map_err(err)?),
        })
    }
}

/// The masks or views of one step, drawn for the whole batch.
#[derive(Debug, Clone)]
pub enum StepDraw {
    /// MAE random masking.
    Mae(MaeMask),
    /// DINO views and the teacher temperature of the step.
    Dino {
        /// Token-crop views.
        views: DinoViews,
        /// Teacher softmax temperature.
        teacher_temp: f64,
    },
    /// JEPA context and target sets (one per I-JEPA step, one per tube-mask kind in V-JEPA).
    Jepa(Vec<JepaMasks>),
}

/// Sums one parameter's gradient over the micro-batches and divides by their count.
struct AverageGradients<'a> {
    parts: &'a mut [GradientsParams],
    out: GradientsParams,
}

impl ModuleVisitor for AverageGradients<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let n = self.parts.len() as f64;
        // in micro-batch order, so the sum does not depend on which thread finished first
        let sum = self
            .parts
            .iter_mut()
            .filter_map(|g| g.remove::<D>(param.id))
            .reduce(|acc, g| acc + g);
        if let Some(sum) = sum {
            self.out.register(param.id, sum.div_scalar(n));
        }
    }
}

/// Gradients of `loss` averaged over `parts` equal micro-batches of `x` on each of `devices`
/// (rows split in order: device 0 takes the first `parts` micro-batches, device 1 the next…),
/// with the mean loss value and the mean of the auxiliary output (DINO's teacher mean), all on
/// the device of `x` — the first device, where the model lives.
///
/// Each micro-batch runs forward and backward on its own copy of the parameters
/// ([`Module::fork`] onto its device: fresh autodiff leaves, so the graphs stay independent) in
/// parallel on the rayon pool; burn's CPU backend runs element-wise ops on the calling thread, so
/// this is what puts the second core to work outside the matrix products. With several devices
/// this is data-parallel training: the fork broadcasts the parameters, and every part's
/// gradients are moved to the first device ([`GradientsParams::to_device`]) and averaged there in
/// part order (the all-reduce), so the step does not depend on which device finished first. For a
/// loss that is a mean over samples with equal counts per sample (MAE, I-JEPA, V-JEPA) the average
/// is the whole-batch gradient. One device and `parts = 1` is the plain whole-batch step.
pub fn micro_batch_gradients<M, F>(
    model: &M,
    x: Tensor<5>,
    devices: &[Device],
    parts: usize,
    loss: F,
) -> (GradientsParams, f64, Option<Tensor<2>>)
where
    M: Module + Sync,
    F: Fn(&M, Tensor<5>, Range<usize>) -> (Tensor<1>, Option<Tensor<2>>) + Sync,
{
    let b = x.dims()[0];
    let parts_per_device = parts.max(1);
    let parts = parts_per_device * devices.len().max(1);
    if parts == 1 {
        let (l, aux) = loss(model, x, 0..b);
        let value = l.clone().into_scalar::<f32>() as f64;
        return (GradientsParams::from_grads(l.backward(), model), value, aux);
    }
    assert!(
        b.is_multiple_of(parts),
        "micro-batches × devices must split the batch evenly"
    );
    let main = x.device();
    let size = b / parts;
    let results: Vec<(GradientsParams, f64, Option<Tensor<2>>)> = (0..parts)
        .into_par_iter()
        .map(|i| {
            let device = devices.get(i / parts_per_device).unwrap_or(&main);
            let rows = i * size..(i + 1) * size;
            let part = model.clone().fork(device);
            let xs = x.clone().slice(rows.clone()).to_device(device);
            let (l, aux) = loss(&part, xs, rows);
            let value = l.clone().into_scalar::<f32>() as f64;
            let grads = GradientsParams::from_grads(l.backward(), &part);
            let grads = if *device == main {
                grads
            } else {
                grads.to_device(&main, &part)
            };
            (grads, value, aux.map(|a| a.to_device(&main)))
        })
        .collect();
    let mut grads = Vec::with_capacity(parts);
    let mut value = 0.0;
    let mut auxes = Vec::with_capacity(parts);
    for (g, v, a) in results {
        grads.push(g);
        value += v;
        auxes.push(a);
    }
    // every part reports an auxiliary output or none does (it comes from the same objective)
    let aux = auxes
        .into_iter()
        .collect::<Option<Vec<_>>>()
        .and_then(|a| a.into_iter().reduce(|acc, t| acc + t));
    let mut avg = AverageGradients {
        parts: &mut grads,
        out: GradientsParams::new(),
    };
    model.visit(&mut avg);
    let n = parts as f64;
    (avg.out, value / n, aux.map(|s| s.div_scalar(n)))
}

/// The force-probe set of `recipe` drawn from the labelled datasets `data`; an error naming the
/// first dataset when they carry too few force labels.
fn probe_set(recipe: &Recipe, data: &[PathBuf]) -> Result<ProbeSet, Error> {
    let sampler = Sampler::new(Arc::new(load_data(recipe, data)?), recipe.stacking())?
        .with_cache_mb(recipe.data.cache_mb);
    let first = data.first().map_or(Path::new("."), PathBuf::as_path);
    ProbeSet::new(
        &sampler,
        recipe.log.probe_max_samples,
        recipe.optim.batch_size,
        recipe.log.probe_label_fraction,
    )?
    .ok_or_else(|| {
        Error::file(
            first,
            "no force probe: it needs force labels on at least 10 frames of several sequences \
             (and [log] probe_max_samples ≥ 10, a probe_label_fraction that keeps a sample)",
        )
    })
}

/// Scores the force probes of `recipe` on `data` for the recipe's randomly initialised encoder
/// and, when given, the encoder weights in `encoder` (safetensors, official key names), once per
/// probe seed in `seeds`: `(random init, loaded)` per seed, computed on `device`. Errors when the
/// data carry no force labels.
pub fn probe_encoders(
    recipe: &Recipe,
    data: &[PathBuf],
    encoder: Option<&Path>,
    seeds: &[u64],
    device: &Device,
) -> Result<Vec<(ProbeScore, Option<ProbeScore>)>, Error> {
    probe_encoders_with_progress(recipe, data, encoder, seeds, device, &|| {})
}

/// [`probe_encoders`], calling `fitted` after each probe fit (one per seed and encoder).
pub fn probe_encoders_with_progress(
    recipe: &Recipe,
    data: &[PathBuf],
    encoder: Option<&Path>,
    seeds: &[u64],
    device: &Device,
    fitted: &dyn Fn(),
) -> Result<Vec<(ProbeScore, Option<ProbeScore>)>, Error> {
    recipe.validate()?;
    let set = probe_set(recipe, data)?;
    // initialised as a run initialises it, on the autodiff device
    let device = device.clone().autodiff();
    let random = Trainee::init(recipe, &device)?.encoder().clone();
    let loaded = match encoder {
        Some(path) => Some(crate::weights::load_encoder(random.clone(), path, None)?),
        None => None,
    };
    let epochs = recipe.log.probe_epochs;
    let score = |encoder: &Vit, seed: u64| {
        let s = set.score(encoder, epochs, seed);
        fitted();
        s
    };
    Ok(seeds
        .iter()
        .map(|&seed| {
            (
                score(&random, seed),
                loaded.as_ref().map(|e| score(e, seed)),
            )
        })
        .collect())
}

/// The force probes of `recipe` on `data` for randomly initialised encoders, each drawn as a run
/// of the recipe with that seed draws its own, once per probe seed in `probe_seeds`: one row per
/// seed in `encoder_seeds`. Their spread is the yardstick for a pretrained encoder: two draws of
/// the same architecture can read force tens of mN apart, so one random encoder is a noisy
/// baseline. Computed on `device`. Errors when the data carry no force labels.
pub fn probe_random_encoders(
    recipe: &Recipe,
    data: &[PathBuf],
    encoder_seeds: &[u64],
    probe_seeds: &[u64],
    device: &Device,
) -> Result<Vec<Vec<ProbeScore>>, Error> {
    probe_random_encoders_with_progress(recipe, data, encoder_seeds, probe_seeds, device, &|| {})
}

/// [`probe_random_encoders`], calling `fitted` after each probe fit.
pub fn probe_random_encoders_with_progress(
    recipe: &Recipe,
    data: &[PathBuf],
    encoder_seeds: &[u64],
    probe_seeds: &[u64],
    device: &Device,
    fitted: &dyn Fn(),
) -> Result<Vec<Vec<ProbeScore>>, Error> {
    recipe.validate()?;
    let set = probe_set(recipe, data)?;
    let device = device.clone().autodiff();
    encoder_seeds
        .iter()
        .map(|&seed| {
            let drawn = Recipe {
                seed,
                ..recipe.clone()
            };
            let encoder = Trainee::init(&drawn, &device)?.encoder().clone();
            Ok(probe_seeds
                .iter()
                .map(|&p| {
                    let s = set.score(&encoder, recipe.log.probe_epochs, p);
                    fitted();
                    s
                })
                .collect())
        })
        .collect()
}

/// The attentive force probe of `recipe` on the raw input patches of `data` (no encoder), once
/// per probe seed in `seeds`: RMSE in mN. Computed on `device`.
pub fn probe_patches(
    recipe: &Recipe,
    data: &[PathBuf],
    seeds: &[u64],
    device: &Device,
) -> Result<Vec<f64>, Error> {
    probe_patches_with_progress(recipe, data, seeds, device, &|| {})
}

/// [`probe_patches`], calling `fitted` after each probe fit.
pub fn probe_patches_with_progress(
    recipe: &Recipe,
    data: &[PathBuf],
    seeds: &[u64],
    device: &Device,
    fitted: &dyn Fn(),
) -> Result<Vec<f64>, Error> {
    recipe.validate()?;
    if recipe.log.probe_epochs == 0 {
        return Err(Error::Config(
            "the raw-patch probe is an attentive probe: set log.probe_epochs above 0".into(),
        ));
    }
    let set = probe_set(recipe, data)?;
    Ok(seeds
        .iter()
        .map(|&seed| {
            let s = set.score_patches(
                recipe.encoder.patch_size,
                recipe.log.probe_epochs,
                seed,
                device,
            );
            fitted();
            s
        })
        .collect())
}

/// The AdamW optimizer of a recipe.
pub fn optimizer(recipe: &Recipe) -> burn::optim::ModuleOptimizer {
    AdamWConfig::new()
        .with_weight_decay(recipe.optim.weight_decay as f32)
        .with_epsilon(1e-8)
        .init()
}

/// Options of one run beyond its recipe.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Datasets: directories (generated or Sparsh pickles) or Taxim packs.
    pub data: Vec<PathBuf>,
    /// Labelled datasets of the online force probe; empty: the probe reads `data`.
    pub probe_data: Vec<PathBuf>,
    /// Run directory.
    pub out: PathBuf,
    /// Continue the run in `out` from its checkpoint.
    pub resume: bool,
    /// Stop after this many steps in total (the schedule still spans `optim.steps`).
    pub max_steps: Option<usize>,
    /// Where the run computes; several devices split every batch (data-parallel).
    pub devices: Devices,
}

#[derive(serde::Serialize, serde::Deserialize)]
struct State {
    step: usize,
    objective: ObjectiveKind,
}

/// Summary of a finished (or stopped) run.
#[derive(Debug, Clone)]
pub struct RunSummary {
    /// Steps completed in total.
    pub steps: usize,
    /// Steps run by this invocation.
    pub ran: usize,
    /// Loss of the last step.
    pub last_loss: f64,
    /// Probe on the initial (random) encoder, if the data have force labels.
    pub probe_initial: Option<ProbeScore>,
    /// Probe on the final encoder.
    pub probe_final: Option<ProbeScore>,
    /// Mean seconds per step of this invocation.
    pub mean_step_s: f64,
    /// Mean seconds per step spent waiting for data.
    pub mean_wait_s: f64,
}

/// Loads and concatenates the datasets of a run.
pub fn load_data(recipe: &Recipe, dirs: &[PathBuf]) -> Result<Dataset, Error> {
    let size = recipe.encoder.img_size;
    let mut all = Dataset {
        sequences: Vec::new(),
        size,
    };
    if dirs.is_empty() {
        return Err(Error::Data("no --data directory given".into()));
    }
    for d in dirs {
        all.sequences.extend(Dataset::load(d, size)?.sequences);
    }
    Ok(all)
}

fn csv_header() -> &'static str {
    "step,loss,lr,probe_rmse_mn,probe_linear_mn,probe_baseline_mn,probe_feature_std,probe_feature_rank,wait_s,step_s\n"
}

fn csv_row(r: &StepReport, probe_only: bool) -> String {
    let (p, l, b, f, k) = r.probe.map_or(Default::default(), |p| {
        (
            format!("{:.3}", p.rmse_mn),
            format!("{:.3}", p.linear_mn),
            format!("{:.3}", p.baseline_mn),
            format!("{:.5}", p.feature_std),
            format!("{:.2}", p.feature_rank),
        )
    });
    if probe_only {
        format!("{},,,{p},{l},{b},{f},{k},,\n", r.step)
    } else {
        format!(
            "{},{:.6},{:.6e},{p},{l},{b},{f},{k},{:.4},{:.4}\n",
            r.step, r.loss, r.lr, r.wait_s, r.step_s
        )
    }
}

/// Keeps the log rows of steps before `step` (a resumed run rewrites the rest).
fn truncate_log(path: &Path, step: usize) -> Result<String, Error> {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    if let Some(header) = text.lines().next()
        && format!("{header}\n") != csv_header()
    {
        return Err(Error::file(
            path,
            "has other columns than this version writes; resume it with the version that \
             started it, or start a new run",
        ));
    }
    let mut out = String::from(csv_header());
    for line in text.lines().skip(1) {
        let s: usize = line
            .split(',')
            .next()
            .and_then(|v| v.parse().ok())
            .unwrap_or(usize::MAX);
        let probe_only = line.split(',').nth(1) == Some("");
        if s < step || (s == step && probe_only) {
            out.push_str(line);
            out.push('\n');
        }
    }
    Ok(out)
}

/// Runs (or resumes) a pretraining run; `on_step` sees every step's report.
pub fn run(
    recipe: &Recipe,
    opts: &RunOptions,
    on_step: &mut dyn FnMut(&StepReport),
) -> Result<RunSummary, Error> {
    recipe.validate()?;
    let parts = recipe.optim.micro_batches * opts.devices.devices.len();
    if !recipe.optim.batch_size.is_multiple_of(parts) {
        return Err(Error::Config(format!(
            "optim.batch_size {} does not split into {} micro-batches on each of {} devices",
            recipe.optim.batch_size,
            recipe.optim.micro_batches,
            opts.devices.devices.len()
        )));
    }
    let devices: Vec<Device> = opts
        .devices
        .devices
        .iter()
        .map(|d| d.clone().autodiff())
        .collect();
    let device = devices[0].clone();
    let ckpt = opts.out.join("checkpoint");
    if !opts.resume && ckpt.exists() {
        return Err(Error::file(
            &opts.out,
            "already holds a run; pass --resume or choose another --out",
        ));
    }
    if opts.resume && !ckpt.exists() {
        // an interrupted checkpoint swap: the new one is complete in `.tmp`, or the old one is
        // still in `.old`
        for side in ["checkpoint.tmp", "checkpoint.old"] {
            let cand = opts.out.join(side);
            if cand.join("state.json").is_file() && cand.join("encoder.safetensors").is_file() {
                std::fs::rename(&cand, &ckpt).map_err(|e| Error::file(&cand, e))?;
                break;
            }
        }
    }
    if opts.resume && !ckpt.join("state.json").is_file() {
        return Err(Error::file(&ckpt, "no checkpoint to resume from"));
    }
    std::fs::create_dir_all(&opts.out).map_err(|e| Error::file(&opts.out, e))?;
    let data = Arc::new(load_data(recipe, &opts.data)?);
    let sampler = Sampler::new(data, recipe.stacking())?.with_cache_mb(recipe.data.cache_mb);
    let probe_set = if recipe.log.probe_every == 0 {
        None
    } else if opts.probe_data.is_empty() {
        ProbeSet::new(
            &sampler,
            recipe.log.probe_max_samples,
            recipe.optim.batch_size,
            recipe.log.probe_label_fraction,
        )?
    } else {
        Some(probe_set(recipe, &opts.probe_data)?)
    };

    let mut model = Trainee::init(recipe, &device)?;
    let mut optim = optimizer(recipe);
    let mut start = 0;
    let log_path = opts.out.join("log.csv");
    let mut log_text = String::from(csv_header());
    if opts.resume {
        let state_path = ckpt.join("state.json");
        let text = std::fs::read_to_string(&state_path).map_err(|e| Error::file(&state_path, e))?;
        let state: State = serde_json::from_str(&text).map_err(|e| Error::file(&state_path, e))?;
        if state.objective != recipe.objective {
            return Err(Error::file(
                &state_path,
                format!(
                    "checkpoint is {:?}, the recipe is {:?}",
                    state.objective, recipe.objective
                ),
            ));
        }
        model = model.load(&ckpt.join("model.bpk"))?;
        let op = ckpt.join("optim.bpk");
        optim = optim
            .load(&op)
            .map_err(|e| Error::file(&op, format!("{e} (truncated file?)")))?;
        start = state.step;
        log_text = truncate_log(&log_path, start)?;
    } else {
        let text = toml::to_string(recipe).map_err(|e| Error::Config(e.to_string()))?;
        write_atomic(&opts.out.join("recipe.toml"), text.as_bytes())?;
    }
    let total = recipe.optim.steps;
    let end = opts.max_steps.map_or(total, |m| m.min(total));
    let mut log = std::fs::File::create(&log_path).map_err(|e| Error::file(&log_path, e))?;
    log.write_all(log_text.as_bytes())
        .map_err(|e| Error::file(&log_path, e))?;

    let rx = sampler.prefetch(
        recipe.data.augment.clone(),
        recipe.seed,
        recipe.optim.batch_size,
        start,
        end,
        recipe.data.prefetch,
    );
    let probe_at =
        |step: usize| recipe.log.probe_every > 0 && step.is_multiple_of(recipe.log.probe_every);
    let mut summary = RunSummary {
        steps: start,
        ran: end.saturating_sub(start),
        last_loss: f64::NAN,
        probe_initial: None,
        probe_final: None,
        mean_step_s: 0.0,
        mean_wait_s: 0.0,
    };
    let (mut sum_step, mut sum_wait) = (0.0, 0.0);
    for step in start..end {
        let probe = match &probe_set {
            Some(p) if probe_at(step) => {
                Some(p.score(model.encoder(), recipe.log.probe_epochs, recipe.seed))
            }
            _ => None,
        };
        if step == 0 {
            summary.probe_initial = probe;
        }
        // a step's time is its training step's, not the probe's before it
        let t0 = Instant::now();
        let tw = Instant::now();
        let batch = rx
            .recv()
            .map_err(|_| Error::Data("the batch loader stopped".into()))??;
        let wait_s = tw.elapsed().as_secs_f64();
        let (next, loss) = model.train_step(recipe, &mut optim, &batch, &devices);
        model = next;
        if !loss.is_finite() {
            return Err(Error::Data(format!("loss is {loss} at step {step}")));
        }
        let report = StepReport {
            step,
            total,
            loss,
            lr: recipe.optim.lr_at(step),
            wait_s,
            step_s: t0.elapsed().as_secs_f64(),
            probe,
        };
        if probe.is_some() {
            log.write_all(csv_row(&report, true).as_bytes())
                .map_err(|e| Error::file(&log_path, e))?;
        }
        log.write_all(csv_row(&report, false).as_bytes())
            .map_err(|e| Error::file(&log_path, e))?;
        on_step(&report);
        sum_step += report.step_s;
        sum_wait += wait_s;
        summary.steps = step + 1;
        summary.last_loss = loss;
        if (step + 1) % recipe.log.checkpoint_every == 0 || step + 1 == end {
            log.flush().map_err(|e| Error::file(&log_path, e))?;
            checkpoint(&model, &optim, recipe, step + 1, &opts.out)?;
        }
    }
    let ran = end.saturating_sub(start).max(1) as f64;
    summary.mean_step_s = sum_step / ran;
    summary.mean_wait_s = sum_wait / ran;
    if end == total
        && end > start
        && let Some(p) = &probe_set
    {
        let score = p.score(model.encoder(), recipe.log.probe_epochs, recipe.seed);
        summary.probe_final = Some(score);
        let report = StepReport {
            step: total,
            total,
            loss: f64::NAN,
            lr: 0.0,
            wait_s: 0.0,
            step_s: 0.0,
            probe: Some(score),
        };
        log.write_all(csv_row(&report, true).as_bytes())
            .map_err(|e| Error::file(&log_path, e))?;
        on_step(&report);
    }
    if end > start {
        crate::weights::save_encoder(model.encoder(), &opts.out.join("encoder.safetensors"))?;
    }
    log.flush().map_err(|e| Error::file(&log_path, e))?;
    Ok(summary)
}

fn checkpoint(
    model: &Trainee,
    optim: &burn::optim::ModuleOptimizer,
    recipe: &Recipe,
    step: usize,
    out: &Path,
) -> Result<(), Error> {
    let tmp = out.join("checkpoint.tmp");
    let dst = out.join("checkpoint");
    let old = out.join("checkpoint.old");
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(|e| Error::file(&tmp, e))?;
    }
    std::fs::create_dir_all(&tmp).map_err(|e| Error::file(&tmp, e))?;
    model.save(&tmp.join("model.bpk"))?;
    let op = tmp.join("optim.bpk");
    optim.save(&op).map_err(|e| Error::file(&op, e))?;
    crate::weights::save_encoder(model.encoder(), &tmp.join("encoder.safetensors"))?;
    let state = State {
        step,
        objective: recipe.objective,
    };
    let json = serde_json::to_string(&state).map_err(|e| Error::Data(e.to_string()))?;
    std::fs::write(tmp.join("state.json"), json).map_err(|e| Error::file(&tmp, e))?;
    if old.exists() {
        std::fs::remove_dir_all(&old).map_err(|e| Error::file(&old, e))?;
    }
    if dst.exists() {
        std::fs::rename(&dst, &old).map_err(|e| Error::file(&dst, e))?;
    }
    std::fs::rename(&tmp, &dst).map_err(|e| Error::file(&dst, e))?;
    if old.exists() {
        std::fs::remove_dir_all(&old).map_err(|e| Error::file(&old, e))?;
    }
    Ok(())
}
