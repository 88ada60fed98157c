//! Training recipes: one TOML file per run (`assets/ssl/*.toml`), unknown keys rejected.
//!
//! ```toml
//! objective = "mae"            # mae | dino | ijepa | vjepa
//! seed = 0
//! [encoder]                    # size preset, then overrides
//! size = "tiny"
//! img_size = [96, 72]          # [height, width], portrait 4:3
//! patch_size = 8
//! depth = 6
//! [mae]                        # or [dino] / [jepa]: the objective's settings
//! decoder_dim = 128
//! [optim]
//! steps = 1500
//! batch_size = 32
//! micro_batches = 2            # forward + backward of each half in parallel, same gradient
//! lr = 1.5e-4
//! [data]
//! frame_offsets = [0, 5]       # I_t ⊕ I_{t−5}
//! [log]
//! probe_every = 250
//! probe_epochs = 30            # attentive probe; 0: ridge read-out only
//! ```

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::Error;
use crate::data::{AugmentConfig, Stacking};
use crate::dino::{DinoConfig, TeacherNorm};
use crate::jepa::{JepaConfig, JepaLoss, TargetNorm};
use crate::mae::MaeConfig;
use crate::masks::{DinoViewConfig, IjepaMaskConfig, TubeMaskConfig, default_tube_masks};
use crate::vit::{VitConfig, size_preset};

/// The self-supervised objective.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ObjectiveKind {
    /// Masked autoencoder.
    Mae,
    /// DINO self-distillation.
    Dino,
    /// I-JEPA.
    Ijepa,
    /// V-JEPA.
    Vjepa,
}

/// `[encoder]`: a size preset with optional overrides.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EncoderSection {
    /// `tiny`, `small` or `base`.
    #[serde(default = "default_size")]
    pub size: String,
    /// `[height, width]`.
    pub img_size: [usize; 2],
    /// Patch side.
    pub patch_size: usize,
    /// Overrides the preset's width.
    pub embed_dim: Option<usize>,
    /// Overrides the preset's depth.
    pub depth: Option<usize>,
    /// Overrides the preset's heads.
    pub num_heads: Option<usize>,
    /// MLP ratio.
    #[serde(default = "default_mlp_ratio")]
    pub mlp_ratio: f64,
    /// Register tokens (DINO needs at least one).
    #[serde(default)]
    pub num_registers: usize,
    /// Layer scale's initial value (official `init_values`: 1, DINOv2 1e-5); unset, the blocks
    /// have none. Off in the CPU recipes.
    #[serde(default)]
    pub layer_scale: Option<f64>,
}

fn default_size() -> String {
    "tiny".into()
}
fn default_mlp_ratio() -> f64 {
    4.0
}

/// `[mae]`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MaeSection {
    /// Fraction masked.
    pub mask_ratio: f64,
    /// Decoder width.
    pub decoder_dim: usize,
    /// Decoder blocks.
    pub decoder_depth: usize,
    /// Decoder heads.
    pub decoder_heads: usize,
    /// Per-patch standardized pixel targets (MAE's `norm_pix_loss`; official Sparsh: off).
    pub norm_pix_loss: bool,
}

impl Default for MaeSection {
    fn default() -> Self {
        Self {
            mask_ratio: 0.75,
            decoder_dim: 512,
            decoder_depth: 8,
            decoder_heads: 16,
            norm_pix_loss: false,
        }
    }
}

/// `[dino]`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DinoSection {
    /// Head hidden width.
    pub head_hidden: usize,
    /// Head bottleneck.
    pub head_bottleneck: usize,
    /// Prototypes.
    pub num_prototypes: usize,
    /// Student temperature.
    pub student_temp: f64,
    /// Teacher temperature: start, end of the warm-up.
    pub teacher_temp: [f64; 2],
    /// Steps of the teacher temperature warm-up.
    pub teacher_temp_warmup_steps: usize,
    /// Centre momentum.
    pub center_momentum: f64,
    /// Batch normalization after the head's hidden layers (DINO's `use_bn_in_head`; official
    /// off).
    pub head_batch_norm: bool,
    /// Teacher EMA momentum: start, end (linear over the run; official fixed 0.998).
    pub ema: [f64; 2],
    /// Weight of DINOv2's KoLeo term on the student's `[cls]` features, summed over the global
    /// views (DINOv2: 0.1; official DINO: 0).
    pub koleo_weight: f64,
    /// Teacher targets: `"center"` (official running centre) or `"batch"` (each prototype's
    /// score standardized over the step's batch, see [`TeacherNorm`]).
    pub teacher_norm: TeacherNorm,
    /// Weight of DINOv2's iBOT masked-patch term (0 = off, official DINO); needs
    /// `views.mask_ratio > 0` and `teacher_norm = "batch"`.
    pub ibot_weight: f64,
    /// Views.
    pub views: DinoViewConfig,
}

impl DinoSection {
    /// Teacher temperature of step `step`: the official linear warm-up from `teacher_temp[0]`
    /// to `teacher_temp[1]` over `teacher_temp_warmup_steps`, then held (DINO, Caron et al.
    /// 2021, §3.1 and appendix; Sparsh `DINOModule.teacher_temp_schedule`).
    pub fn teacher_temp_at(&self, step: usize) -> f64 {
        let [start, end] = self.teacher_temp;
        start
            + (end - start) * (step as f64 / self.teacher_temp_warmup_steps.max(1) as f64).min(1.0)
    }
}

impl Default for DinoSection {
    fn default() -> Self {
        Self {
            head_hidden: 2048,
            head_bottleneck: 256,
            num_prototypes: 65536,
            student_temp: 0.1,
            teacher_temp: [0.04, 0.07],
            teacher_temp_warmup_steps: 1000,
            center_momentum: 0.9,
            head_batch_norm: false,
            ema: [0.998, 0.998],
            koleo_weight: 0.0,
            teacher_norm: TeacherNorm::Center,
            ibot_weight: 0.0,
            views: DinoViewConfig::default(),
        }
    }
}

/// `[jepa]` (I-JEPA and V-JEPA).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct JepaSection {
    /// Predictor width (official I-JEPA 192, V-JEPA 384).
    pub predictor_dim: usize,
    /// Predictor blocks (official I-JEPA 6, V-JEPA 12).
    pub predictor_depth: usize,
    /// Predictor heads.
    pub predictor_heads: usize,
    /// Target-encoder EMA momentum: start, end (official I-JEPA 0.996→1, V-JEPA 0.997→1).
    pub ema: [f64; 2],
    /// I-JEPA block masks.
    pub masks: IjepaMaskConfig,
    /// V-JEPA tube-mask generators.
    pub tube_masks: Vec<TubeMaskConfig>,
    /// V-JEPA tubelet length.
    pub tubelet_size: usize,
    /// Regression targets: `"layer"` (official) or `"layer_batch"` (then standardized per
    /// token and feature over the batch, see [`TargetNorm`]).
    pub target_norm: TargetNorm,
    /// Latent regression loss: `"l1"` or `"smooth_l1"`; unset, the objective's own (V-JEPA
    /// L1, I-JEPA smooth L1).
    pub loss: Option<JepaLoss>,
}

impl Default for JepaSection {
    fn default() -> Self {
        Self {
            predictor_dim: 192,
            predictor_depth: 6,
            predictor_heads: 6,
            ema: [0.996, 1.0],
            masks: IjepaMaskConfig::default(),
            tube_masks: default_tube_masks(),
            tubelet_size: 2,
            target_norm: TargetNorm::Layer,
            loss: None,
        }
    }
}

/// `[optim]`: AdamW with linear warm-up and cosine decay.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OptimSection {
    /// Total steps of the schedule.
    pub steps: usize,
    /// Samples per step.
    pub batch_size: usize,
    /// Equal micro-batches the step's batch is split into, each forward and backward on its
    /// own thread with the gradients averaged (the same gradient for the mean losses of MAE and
    /// the JEPAs; batch statistics — DINO's head batch norm, KoLeo and `teacher_norm = "batch"`,
    /// JEPA `target_norm = "layer_batch"` — then see one micro-batch at a time, as on one GPU
    /// of a multi-GPU run; DINO's centre is the mean over the parts, as for the whole batch).
    /// The split is fixed by the recipe, never by the thread count, so results do not depend
    /// on the number of threads.
    pub micro_batches: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// Final learning rate.
    pub min_lr: f64,
    /// Linear warm-up steps.
    pub warmup_steps: usize,
    /// AdamW weight decay (fixed; the official run ramps 0.04 → 0.4).
    pub weight_decay: f64,
}

impl Default for OptimSection {
    fn default() -> Self {
        Self {
            steps: 1000,
            batch_size: 32,
            micro_batches: 1,
            lr: 1e-4,
            min_lr: 1e-6,
            warmup_steps: 50,
            weight_decay: 0.04,
        }
    }
}

impl OptimSection {
    /// Learning rate of step `step` (from 0): the official `WarmupCosineScheduler` with
    /// `start_lr = 0`, as torch advances it (step `s` runs at count `k = s + 1`): `lr · k / W`
    /// while `k < W` (`W = warmup_steps`), then
    /// `min_lr + ½ (lr − min_lr) (1 + cos(π · min((k − W) / (steps − W), 1)))`, so the peak is
    /// reached once (at `k = W`) and the last step runs at `min_lr`.
    pub fn lr_at(&self, step: usize) -> f64 {
        let k = step + 1;
        if k < self.warmup_steps {
            return self.lr * k as f64 / self.warmup_steps as f64;
        }
        let span = self.steps.saturating_sub(self.warmup_steps).max(1);
        let t = ((k - self.warmup_steps) as f64 / span as f64).min(1.0);
        self.min_lr + 0.5 * (self.lr - self.min_lr) * (1.0 + (std::f64::consts::PI * t).cos())
    }
}

/// `[data]`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DataSection {
    /// Frames back in time stacked into one sample (`[0, 5]` images, `[0, 2, 4, 6]` V-JEPA);
    /// empty means the objective's official default.
    pub frame_offsets: Vec<usize>,
    /// Augmentation.
    pub augment: AugmentConfig,
    /// Batches assembled ahead of the trainer.
    pub prefetch: usize,
    /// MiB of decoded frames kept in memory; frames beyond it are read from disk (or from their
    /// pickle's encoded bytes) each time a batch needs them.
    pub cache_mb: usize,
}

impl Default for DataSection {
    fn default() -> Self {
        Self {
            frame_offsets: Vec::new(),
            augment: AugmentConfig::default(),
            prefetch: 3,
            cache_mb: crate::data::DEFAULT_CACHE_MB,
        }
    }
}

/// `[log]`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LogSection {
    /// Steps between checkpoints.
    pub checkpoint_every: usize,
    /// Steps between online force probes (0: never).
    pub probe_every: usize,
    /// Labelled samples used by the probe at most.
    pub probe_max_samples: usize,
    /// Training epochs of the attentive probe (0: the linear read-out only).
    pub probe_epochs: usize,
    /// Share of the probe's training samples it is fitted on (evenly spaced; the held-out
    /// sequences are all scored): TacBench's label budget, in (0, 1].
    pub probe_label_fraction: f64,
}

impl Default for LogSection {
    fn default() -> Self {
        Self {
            checkpoint_every: 100,
            probe_every: 250,
            probe_max_samples: 512,
            probe_epochs: 40,
            probe_label_fraction: 1.0,
        }
    }
}

/// A training recipe.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Recipe {
    /// The objective.
    pub objective: ObjectiveKind,
    /// Seed of every random choice.
    #[serde(default)]
    pub seed: u64,
    /// The encoder.
    pub encoder: EncoderSection,
    /// MAE settings.
    #[serde(default)]
    pub mae: MaeSection,
    /// DINO settings.
    #[serde(default)]
    pub dino: DinoSection,
    /// I-JEPA / V-JEPA settings.
    #[serde(default)]
    pub jepa: JepaSection,
    /// Optimizer.
    #[serde(default)]
    pub optim: OptimSection,
    /// Data.
    #[serde(default)]
    pub data: DataSection,
    /// Logging, checkpoints, probe.
    #[serde(default)]
    pub log: LogSection,
}

impl Recipe {
    /// Parses and validates a recipe file; errors name the file and the field.
    pub fn load(path: &Path) -> Result<Self, Error> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::file(path, e))?;
        Self::parse(&text).map_err(|e| Error::file(path, e))
    }

    /// Parses and validates recipe text.
    pub fn parse(text: &str) -> Result<Self, String> {
        let recipe: Recipe = toml::from_str(text).map_err(|e| {
            let msg = e.message().to_string();
            match e.span() {
                Some(span) => {
                    let line = text[..span.start].lines().count().max(1);
                    format!("line {line}: {msg}")
                }
                None => msg,
            }
        })?;
        recipe.validate().map_err(|e| e.to_string())?;
        Ok(recipe)
    }

    /// Frame offsets of one sample.
    pub fn frame_offsets(&self) -> Vec<usize> {
        if !self.data.frame_offsets.is_empty() {
            return self.data.frame_offsets.clone();
        }
        match self.objective {
            ObjectiveKind::Vjepa => vec![0, 2, 4, 6],
            _ => vec![0, 5],
        }
    }

    /// How frames are stacked into samples.
    pub fn stacking(&self) -> Stacking {
        match self.objective {
            ObjectiveKind::Vjepa => Stacking::Frames(self.frame_offsets()),
            _ => Stacking::Channels(self.frame_offsets()),
        }
    }

    /// The encoder configuration.
    pub fn encoder_config(&self) -> Result<VitConfig, Error> {
        let e = &self.encoder;
        let (dim, depth, heads) = size_preset(&e.size).ok_or_else(|| {
            Error::Config(format!(
                "encoder.size: `{}` is not one of tiny, small, base",
                e.size
            ))
        })?;
        let [frames, chans] = self.stacking().shape();
        let tubelet = if self.objective == ObjectiveKind::Vjepa {
            self.jepa.tubelet_size
        } else {
            1
        };
        let cfg = VitConfig::new(e.img_size, e.patch_size)
            .with_in_chans(chans)
            .with_num_frames(frames)
            .with_tubelet_size(tubelet)
            .with_embed_dim(e.embed_dim.unwrap_or(dim))
            .with_depth(e.depth.unwrap_or(depth))
            .with_num_heads(e.num_heads.unwrap_or(heads))
            .with_mlp_ratio(e.mlp_ratio)
            .with_num_registers(e.num_registers)
            .with_layer_scale(e.layer_scale);
        cfg.validate().map_err(|e| {
            Error::Config(format!(
                "encoder.{}",
                e.to_string().trim_start_matches("config: ")
            ))
        })?;
        Ok(cfg)
    }

    /// Checks the recipe as a whole.
    pub fn validate(&self) -> Result<(), Error> {
        let enc = self.encoder_config()?;
        let bad = |m: String| Err(Error::Config(m));
        if self.optim.steps == 0 || self.optim.batch_size == 0 {
            return bad("optim.steps and optim.batch_size must be positive".into());
        }
        let parts = self.optim.micro_batches;
        if parts == 0 || !self.optim.batch_size.is_multiple_of(parts) {
            return bad(format!(
                "optim.micro_batches must be a positive divisor of optim.batch_size {}, got {parts}",
                self.optim.batch_size
            ));
        }
        // batch statistics need at least two samples in each micro-batch
        let per_part = self.optim.batch_size / parts;
        if self.log.checkpoint_every == 0 {
            return bad("log.checkpoint_every must be positive".into());
        }
        let f = self.log.probe_label_fraction;
        if !(f > 0.0 && f <= 1.0) {
            return bad(format!(
                "log.probe_label_fraction must be in (0, 1], got {f}"
            ));
        }
        match self.objective {
            ObjectiveKind::Mae => {
                let r = self.mae.mask_ratio;
                if !(0.0..1.0).contains(&r) {
                    return bad(format!("mae.mask_ratio: {r} is not in [0, 1)"));
                }
                if !self
                    .mae
                    .decoder_dim
                    .is_multiple_of(self.mae.decoder_heads.max(1))
                    || !self.mae.decoder_dim.is_multiple_of(8)
                {
                    return bad(
                        "mae.decoder_dim must be a multiple of 8 and of mae.decoder_heads".into(),
                    );
                }
            }
            ObjectiveKind::Dino => {
                if enc.num_registers == 0 {
                    return bad(
                        "encoder.num_registers: DINO needs at least one register token (its [cls])"
                            .into(),
                    );
                }
                if self.dino.views.num_global < 2 {
                    return bad("dino.views.num_global must be at least 2".into());
                }
                let w = self.dino.koleo_weight;
                if !(w.is_finite() && w >= 0.0) || (w > 0.0 && per_part < 2) {
                    return bad(format!(
                        "dino.koleo_weight must be ≥ 0 (and needs ≥ 2 samples per micro-batch), got {w}"
                    ));
                }
                if self.dino.teacher_norm == TeacherNorm::Batch && per_part < 2 {
                    return bad(
                        "dino.teacher_norm = \"batch\" needs ≥ 2 samples per micro-batch".into(),
                    );
                }
                let r = self.dino.views.mask_ratio;
                if !(0.0..1.0).contains(&r) {
                    return bad(format!("dino.views.mask_ratio must be in [0, 1), got {r}"));
                }
                let w = self.dino.ibot_weight;
                if !(w.is_finite() && w >= 0.0)
                    || ((w > 0.0) != (r > 0.0))
                    || (w > 0.0 && self.dino.teacher_norm != TeacherNorm::Batch)
                {
                    return bad(format!(
                        "dino.ibot_weight must be ≥ 0, and above 0 exactly when \
                         dino.views.mask_ratio is (the masks only serve iBOT), with \
                         dino.teacher_norm = \"batch\"; got {w} and {r}"
                    ));
                }
            }
            ObjectiveKind::Ijepa | ObjectiveKind::Vjepa => {
                let j = &self.jepa;
                if !j.predictor_dim.is_multiple_of(j.predictor_heads.max(1))
                    || !j.predictor_dim.is_multiple_of(8)
                {
                    return bad(
                        "jepa.predictor_dim must be a multiple of 8 and of jepa.predictor_heads"
                            .into(),
                    );
                }
                if j.target_norm == TargetNorm::LayerBatch && per_part < 2 {
                    return bad(
                        "jepa.target_norm = \"layer_batch\" needs ≥ 2 samples per micro-batch"
                            .into(),
                    );
                }
                if self.objective == ObjectiveKind::Vjepa && j.tube_masks.is_empty() {
                    return bad("jepa.tube_masks must list at least one generator".into());
                }
                if self.objective == ObjectiveKind::Vjepa && enc.grid()[0] < 1 {
                    return bad("data.frame_offsets: V-JEPA needs at least one tubelet".into());
                }
            }
        }
        Ok(())
    }

    /// MAE configuration.
    pub fn mae_config(&self) -> Result<MaeConfig, Error> {
        Ok(MaeConfig::new(self.encoder_config()?)
            .with_mask_ratio(self.mae.mask_ratio)
            .with_decoder_dim(self.mae.decoder_dim)
            .with_decoder_depth(self.mae.decoder_depth)
            .with_decoder_heads(self.mae.decoder_heads)
            .with_norm_pix_loss(self.mae.norm_pix_loss))
    }

    /// DINO configuration.
    pub fn dino_config(&self) -> Result<DinoConfig, Error> {
        let d = &self.dino;
        Ok(DinoConfig::new(self.encoder_config()?)
            .with_head_hidden(d.head_hidden)
            .with_head_bottleneck(d.head_bottleneck)
            .with_num_prototypes(d.num_prototypes)
            .with_student_temp(d.student_temp)
            .with_center_momentum(d.center_momentum)
            .with_head_batch_norm(d.head_batch_norm)
            .with_koleo_weight(d.koleo_weight)
            .with_teacher_norm(d.teacher_norm)
            .with_ibot_weight(d.ibot_weight))
    }

    /// I-JEPA / V-JEPA configuration.
    pub fn jepa_config(&self) -> Result<JepaConfig, Error> {
        let j = &self.jepa;
        let loss = j.loss.unwrap_or(if self.objective == ObjectiveKind::Vjepa {
            JepaLoss::L1
        } else {
            JepaLoss::SmoothL1
        });
        Ok(JepaConfig::new(
            self.encoder_config()?,
            j.predictor_dim,
            j.predictor_depth,
            j.predictor_heads,
            loss,
        )
        .with_target_norm(j.target_norm))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const BASE: &str = "objective = \"mae\"\n[encoder]\nimg_size = [32, 24]\npatch_size = 8\n";

    #[test]
    fn parses_minimal_and_defaults_are_official() {
        let r = Recipe::parse(BASE).unwrap();
        assert_eq!(r.mae.mask_ratio, 0.75);
        assert_eq!(r.dino.num_prototypes, 65536);
        assert_eq!(r.jepa.masks.num_targets, 4);
        assert_eq!(r.frame_offsets(), vec![0, 5]);
        let enc = r.encoder_config().unwrap();
        assert_eq!((enc.in_chans, enc.embed_dim, enc.depth), (6, 192, 12));
        // the official portrait input stays expressible: 320×240, patch 16 → 300 tokens
        let off = Recipe::parse(
            "objective = \"mae\"\n[encoder]\nsize = \"base\"\nimg_size = [320, 240]\npatch_size = 16\n",
        )
        .unwrap();
        assert_eq!(off.encoder_config().unwrap().num_patches(), 300);
    }

    /// Layer scale is off unless the recipe sets its initial value, which must be positive.
    #[test]
    fn layer_scale_is_set_by_the_recipe() {
        let plain = Recipe::parse(BASE).unwrap().encoder_config().unwrap();
        assert_eq!(plain.layer_scale, None);
        let with = BASE.replace("patch_size = 8\n", "patch_size = 8\nlayer_scale = 1e-5\n");
        let cfg = Recipe::parse(&with).unwrap().encoder_config().unwrap();
        assert_eq!(cfg.layer_scale, Some(1e-5));
        let device = burn::prelude::Device::flex();
        let vit = crate::device::seeded_module(&device, 1, || cfg.init(&device));
        let gamma: Vec<f32> = vit.blocks[0]
            .ls2
            .as_ref()
            .unwrap()
            .val()
            .into_data()
            .try_to_vec::<f32>()
            .unwrap();
        assert!(gamma.iter().all(|&g| g == 1e-5f32), "{gamma:?}");
        let e = Recipe::parse(
            &BASE.replace("patch_size = 8\n", "patch_size = 8\nlayer_scale = -1.0\n"),
        )
        .unwrap_err();
        assert!(
            e.contains("encoder.layer_scale") && !e.contains('\n'),
            "{e}"
        );
    }

    #[test]
    fn unknown_keys_and_bad_shapes_are_one_line_errors() {
        let e = Recipe::parse(&format!("{BASE}bogus = 1\n")).unwrap_err();
        assert!(e.contains("bogus") && !e.contains('\n'), "{e}");
        let e = Recipe::parse(&format!("{BASE}[optim]\nlearning_rate = 1\n")).unwrap_err();
        assert!(e.contains("learning_rate"), "{e}");
        let e =
            Recipe::parse("objective = \"mae\"\n[encoder]\nimg_size = [30, 24]\npatch_size = 8\n")
                .unwrap_err();
        assert!(e.contains("img_size") && !e.contains('\n'), "{e}");
        let e = Recipe::parse(&BASE.replace("mae", "dino")).unwrap_err();
        assert!(e.contains("num_registers"), "{e}");
        let dino = BASE
            .replace("mae", "dino")
            .replace("patch_size = 8\n", "patch_size = 8\nnum_registers = 1\n");
        for ibot in [
            "ibot_weight = 1.0\nteacher_norm = \"batch\"\n",
            "ibot_weight = 1.0\n[dino.views]\nmask_ratio = 0.3\n",
            "teacher_norm = \"batch\"\n[dino.views]\nmask_ratio = 1.0\n",
            "teacher_norm = \"batch\"\n[dino.views]\nmask_ratio = 0.3\n",
        ] {
            let e = Recipe::parse(&format!("{dino}[dino]\n{ibot}")).unwrap_err();
            assert!(
                (e.contains("dino.ibot_weight") || e.contains("dino.views.mask_ratio"))
                    && !e.contains('\n'),
                "{e}"
            );
        }
        let ibot = "ibot_weight = 1.0\nteacher_norm = \"batch\"\n[dino.views]\nmask_ratio = 0.3\n";
        assert!(Recipe::parse(&format!("{dino}[dino]\n{ibot}")).is_ok());
        let e = Recipe::parse(&format!("{dino}[dino]\nkoleo_weight = -0.1\n")).unwrap_err();
        assert!(e.contains("dino.koleo_weight") && !e.contains('\n'), "{e}");
        for parts in [0, 5] {
            let e = Recipe::parse(&format!(
                "{BASE}[optim]\nbatch_size = 32\nmicro_batches = {parts}\n"
            ))
            .unwrap_err();
            assert!(
                e.contains("optim.micro_batches") && !e.contains('\n'),
                "{e}"
            );
        }
        let e = Recipe::parse(&BASE.replace("mae", "simclr")).unwrap_err();
        assert!(e.contains("simclr") || e.contains("variant"), "{e}");
    }

    #[test]
    fn jepa_loss_is_the_objective_s_own_unless_set() {
        let loss = |objective: &str, extra: &str| {
            Recipe::parse(&format!("{}{extra}", BASE.replace("mae", objective)))
                .and_then(|r| r.jepa_config().map_err(|e| e.to_string()))
                .map(|c| c.loss)
        };
        assert_eq!(loss("vjepa", ""), Ok(JepaLoss::L1));
        assert_eq!(loss("ijepa", ""), Ok(JepaLoss::SmoothL1));
        let set = "[jepa]\nloss = \"smooth_l1\"\n";
        assert_eq!(loss("vjepa", set), Ok(JepaLoss::SmoothL1));
        let e = loss("vjepa", "[jepa]\nloss = \"l2\"\n").unwrap_err();
        assert!(e.contains("l2") && !e.contains('\n'), "{e}");
    }

    #[test]
    fn schedule_warms_up_then_decays() {
        let o = OptimSection {
            steps: 100,
            warmup_steps: 10,
            lr: 1.0,
            min_lr: 0.0,
            ..Default::default()
        };
        assert!((o.lr_at(0) - 0.1).abs() < 1e-12);
        assert!((o.lr_at(9) - 1.0).abs() < 1e-12);
        // the peak is held for one step only
        assert!(o.lr_at(10) < 1.0);
        assert!((o.lr_at(54) - 0.5).abs() < 1e-12);
        assert!(o.lr_at(99).abs() < 1e-12);
        assert!(o.lr_at(150).abs() < 1e-12);
    }
}
