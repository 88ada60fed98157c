//! Training-step throughput and cross-device parity, for `sparsh bench-train` and
//! `cargo bench --bench train_step`.
//!
//! - [`ReferenceStep`]: the reference step of `benches/torch_step.py` (a ViT, a linear pixel
//!   head, MSE against the patchified input, Adam at lr 1e-4), at any input, patch and batch, so
//!   that burn and PyTorch time the same arithmetic on the same card. FLOPs are counted as
//!   2·M·N·K for every matrix product of the forward pass (the patch embedding, q/k/v, qkᵀ,
//!   attention · v, the output projection, the two MLP layers, the head; element-wise ops, norms
//!   and softmax not counted) and three times that for a training step (forward, and the two
//!   products of each backward), PyTorch's and burn's alike.
//! - [`time_recipe`]: seconds per training step of a recipe (the trainer's `train_step`).
//! - [`step_parity`]: one training step of a recipe on two devices from the same weights and
//!   batch, compared: loss, every gradient, every updated weight.
//!
//! Every timed step ends by reading its loss back to the host, so a GPU's queue is drained
//! inside the step it belongs to.

use std::time::Instant;

use burn::module::{Module, ModuleVisitor, Param};
use burn::nn::{Linear, LinearConfig};
use burn::optim::{AdamConfig, GradientsParams};
use burn::prelude::*;

use crate::Error;
use crate::data::HostBatch;
use crate::recipe::Recipe;
use crate::rng::Rng;
use crate::train::{Trainee, micro_batch_gradients, optimizer};
use crate::vit::{Vit, VitConfig, patchify};

/// The reference step's ViT sizes `[width, blocks, heads]` (MLP ratio 4), as
/// `benches/torch_step.py` names them: its `tiny` has 6 blocks, half the official ViT-tiny's.
pub const REFERENCE_SIZES: [(&str, [usize; 3]); 3] = [
    ("tiny", [192, 6, 3]),
    ("small", [384, 12, 6]),
    ("base", [768, 12, 12]),
];

/// Channels of the reference input (I_t ⊕ I_{t−5}, as the image encoders take).
pub const REFERENCE_CHANNELS: usize = 6;

/// One shape of the reference step.
#[derive(Debug, Clone, PartialEq)]
pub struct ReferenceStep {
    /// `[width, blocks, heads]` of the ViT.
    pub vit: [usize; 3],
    /// Input `[height, width]` in pixels.
    pub img_size: [usize; 2],
    /// Patch side in pixels.
    pub patch: usize,
    /// Images per step.
    pub batch: usize,
}

#[derive(Module, Debug)]
struct Reference {
    vit: Vit,
    head: Linear,
}

/// Median seconds per step of timed steps, and the images per step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepTime {
    /// Median wall seconds per step.
    pub seconds: f64,
    /// Images per step.
    pub batch: usize,
}

impl StepTime {
    /// Images per second.
    pub fn images_per_second(&self) -> f64 {
        self.batch as f64 / self.seconds
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

impl ReferenceStep {
    /// The named size of [`REFERENCE_SIZES`] at `img_size`, `patch` and `batch`; a one-line
    /// error for another name or an input the patch does not tile.
    pub fn new(
        size: &str,
        img_size: [usize; 2],
        patch: usize,
        batch: usize,
    ) -> Result<Self, Error> {
        let vit = REFERENCE_SIZES
            .iter()
            .find(|(n, _)| *n == size)
            .map(|(_, v)| *v)
            .ok_or_else(|| {
                Error::Config(format!(
                    "reference size '{size}': expected tiny, small or base"
                ))
            })?;
        let step = Self {
            vit,
            img_size,
            patch,
            batch,
        };
        step.config().validate()?;
        if batch == 0 {
            return Err(Error::Config("reference batch: must be at least 1".into()));
        }
        Ok(step)
    }

    fn config(&self) -> VitConfig {
        let [width, depth, heads] = self.vit;
        VitConfig::new(self.img_size, self.patch)
            .with_in_chans(REFERENCE_CHANNELS)
            .with_embed_dim(width)
            .with_depth(depth)
            .with_num_heads(heads)
    }

    /// Tokens per image.
    pub fn tokens(&self) -> usize {
        (self.img_size[0] / self.patch) * (self.img_size[1] / self.patch)
    }

    /// FLOPs of one training step (module comment): per token the patch embedding and the head
    /// (2 · 2·P·D, P values per patch) and per block q/k/v, projection and MLP (24 D²) and
    /// attention (4 N D); times the batch's tokens; times 3.
    pub fn flops(&self) -> f64 {
        let [width, depth, _] = self.vit;
        let d = width as f64;
        let n = self.tokens() as f64;
        let patch_values = (REFERENCE_CHANNELS * self.patch * self.patch) as f64;
        let per_token = 4.0 * patch_values * d + depth as f64 * (24.0 * d * d + 4.0 * n * d);
        3.0 * per_token * n * self.batch as f64
    }

    /// Median seconds per step of `timed` steps after `warmup` on `device` (an autodiff device),
    /// the batch split into `parts` micro-batches ([`micro_batch_gradients`], the trainer's path;
    /// 1 = the plain whole-batch step). `on_step` hears each step's wall seconds.
    pub fn time(
        &self,
        device: &Device,
        parts: usize,
        (warmup, timed): (usize, usize),
        mut on_step: impl FnMut(usize, f64),
    ) -> StepTime {
        let cfg = self.config();
        let mut model = Reference {
            vit: cfg.init(device),
            head: LinearConfig::new(self.vit[0], cfg.patch_dim()).init(device),
        };
        let mut optim = AdamConfig::new().init();
        let [h, w] = self.img_size;
        let x = Tensor::<5>::random(
            [self.batch, 1, REFERENCE_CHANNELS, h, w],
            burn::tensor::Distribution::Default,
            device,
        );
        let target = patchify(x.clone(), self.patch, 1);
        let mut times = Vec::new();
        for i in 0..warmup + timed.max(1) {
            let t0 = Instant::now();
            let (grads, _loss, _) = micro_batch_gradients(
                &model,
                x.clone(),
                std::slice::from_ref(device),
                parts,
                |m: &Reference, x, rows| {
                    let pred = m.head.forward(m.vit.forward(x, None).patches);
                    let loss = (pred - target.clone().slice(rows)).powi_scalar(2).mean();
                    (loss, None)
                },
            );
            model = optim.step(1e-4, model, grads);
            // the updated weights read back: the step's last kernels have run
            let _ = model.head.bias.as_ref().map(|b| b.val().into_data());
            let seconds = t0.elapsed().as_secs_f64();
            on_step(i, seconds);
            if i >= warmup {
                times.push(seconds);
            }
        }
        StepTime {
            seconds: median(times),
            batch: self.batch,
        }
    }
}

/// A batch of uniform noise in the shape `recipe`'s encoder takes, `batch` images (`seed` draws
/// it).
pub fn noise_batch(recipe: &Recipe, batch: usize, seed: u64) -> Result<HostBatch, Error> {
    let enc = recipe.encoder_config()?;
    let shape = [
        batch,
        enc.num_frames,
        enc.in_chans,
        enc.img_size[0],
        enc.img_size[1],
    ];
    let mut rng = Rng::new(seed);
    let values = (0..shape.iter().product::<usize>())
        .map(|_| rng.uniform() as f32)
        .collect();
    Ok(HostBatch {
        step: 0,
        values,
        shape,
        forces: None,
    })
}

/// Median seconds per training step of `recipe` (at its batch size and micro-batches) on
/// `device` (an autodiff device), `timed` steps after `warmup`, on noise; `on_step` hears each
/// step's wall seconds.
pub fn time_recipe(
    recipe: &Recipe,
    device: &Device,
    (warmup, timed): (usize, usize),
    mut on_step: impl FnMut(usize, f64),
) -> Result<StepTime, Error> {
    let mut batch = noise_batch(recipe, recipe.optim.batch_size, 1)?;
    let mut model = Trainee::init(recipe, device)?;
    let mut optim = optimizer(recipe);
    let mut times = Vec::new();
    for i in 0..warmup + timed.max(1) {
        batch.step = i;
        let t0 = Instant::now();
        // the loss is read back to the host: the step has run
        model = model
            .train_step(recipe, &mut optim, &batch, std::slice::from_ref(device))
            .0;
        let seconds = t0.elapsed().as_secs_f64();
        on_step(i, seconds);
        if i >= warmup {
            times.push(seconds);
        }
    }
    Ok(StepTime {
        seconds: median(times),
        batch: recipe.optim.batch_size,
    })
}

/// Every float parameter of a module, in visiting order, read back to the host.
pub fn parameters<M: Module>(m: &M) -> Vec<Vec<f32>> {
    struct Collect(Vec<Vec<f32>>);
    impl ModuleVisitor for Collect {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            self.0.push(host(p.val()));
        }
    }
    let mut c = Collect(Vec::new());
    m.visit(&mut c);
    c.0
}

/// Every parameter's gradient (empty where it has none, as an EMA teacher's), read back to the
/// host, in [`parameters`]' order.
pub fn gradients<M: Module>(m: &M, grads: &GradientsParams) -> Vec<Vec<f32>> {
    struct Collect<'a>(&'a GradientsParams, Vec<Vec<f32>>);
    impl ModuleVisitor for Collect<'_> {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            let g = self.0.get::<D>(p.id);
            self.1.push(g.map(host).unwrap_or_default());
        }
    }
    let mut c = Collect(grads, Vec::new());
    m.visit(&mut c);
    c.1
}

fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .unwrap_or_default()
}

/// One training step: its loss, every parameter's gradient and every updated weight.
#[derive(Debug, Clone)]
pub struct OneStep {
    /// The step's loss.
    pub loss: f64,
    /// Gradients in [`parameters`]' order (empty for parameters without one).
    pub gradients: Vec<Vec<f32>>,
    /// The weights after the step.
    pub weights: Vec<Vec<f32>>,
}

/// One training step of `recipe` on `batch` with the model (drawn on the CPU under the recipe's
/// seed, then moved) on the first of `devices` (autodiff devices; several split the batch).
pub fn one_step(recipe: &Recipe, batch: &HostBatch, devices: &[Device]) -> Result<OneStep, Error> {
    let main = &devices[0];
    let model = Trainee::init(recipe, main)?;
    let x = Tensor::<1>::from_floats(batch.values.as_slice(), main).reshape(batch.shape);
    let (grads, _, _) = model.gradients(recipe, x, batch.step, devices);
    let gradients = gradients(&model, &grads);
    let mut optim = optimizer(recipe);
    let (after, loss) = model.train_step(recipe, &mut optim, batch, devices);
    Ok(OneStep {
        loss,
        gradients,
        weights: parameters(&after),
    })
}

/// How far two runs of the same step are apart.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepParity {
    /// |loss_a − loss_b| / |loss_a|.
    pub loss_relative: f64,
    /// The largest |g_a − g_b| of a parameter over its largest |g_a|, over all parameters.
    pub gradient_relative: f32,
    /// The largest |g_a| of the parameter where `gradient_relative` is reached, over the largest
    /// |g_a| of all parameters: near 0, that parameter's gradient is within rounding of zero and
    /// its relative difference says little.
    pub gradient_worst_scale: f32,
    /// The largest |w_a − w_b| of the updated weights wherever the gradient's sign is
    /// determined (|g| more than twice its parameter's largest gradient difference; parameters
    /// without a gradient, as EMA teachers, always).
    pub weight_abs: f32,
    /// The largest |w_a − w_b| where it is not: Adam's first step moves every weight by about
    /// lr · sign(g) whatever |g|, so there the arithmetic does not settle the move; it should
    /// not pass the step, about lr.
    pub undetermined_weight_abs: f32,
    /// How many weights had an undetermined gradient sign.
    pub undetermined: usize,
    /// How many weights in all.
    pub weights: usize,
}

/// Compares two runs of one step (see [`StepParity`]); an error if their parameters differ in
/// number or size.
pub fn compare_steps(a: &OneStep, b: &OneStep) -> Result<StepParity, Error> {
    let shapes = |s: &OneStep| {
        (
            s.weights.iter().map(Vec::len).collect::<Vec<_>>(),
            s.gradients.iter().map(Vec::len).collect::<Vec<_>>(),
        )
    };
    if shapes(a) != shapes(b) {
        return Err(Error::Data(
            "the two steps' parameters differ in number or size".into(),
        ));
    }
    let (gradient_relative, worst_scale) = a
        .gradients
        .iter()
        .zip(&b.gradients)
        .map(|(u, v)| {
            let scale = u.iter().fold(1e-12f32, |m, x| m.max(x.abs()));
            let diff = u.iter().zip(v).fold(0f32, |m, (x, y)| m.max((x - y).abs()));
            (diff / scale, scale)
        })
        .fold((0f32, 0f32), |m, r| if r.0 > m.0 { r } else { m });
    let global_scale = a
        .gradients
        .iter()
        .flatten()
        .fold(1e-12f32, |m, x| m.max(x.abs()));
    let (mut weight_abs, mut undetermined_weight_abs, mut undetermined) = (0f32, 0f32, 0);
    for (((wa, wb), ga), gb) in a
        .weights
        .iter()
        .zip(&b.weights)
        .zip(&a.gradients)
        .zip(&b.gradients)
    {
        let spread = ga
            .iter()
            .zip(gb)
            .fold(0f32, |m, (u, v)| m.max((u - v).abs()));
        for (k, (u, v)) in wa.iter().zip(wb).enumerate() {
            let d = (u - v).abs();
            if ga.get(k).is_some_and(|g| g.abs() <= 2.0 * spread) {
                undetermined += 1;
                undetermined_weight_abs = undetermined_weight_abs.max(d);
            } else {
                weight_abs = weight_abs.max(d);
            }
        }
    }
    Ok(StepParity {
        loss_relative: (a.loss - b.loss).abs() / a.loss.abs().max(1e-12),
        gradient_relative,
        gradient_worst_scale: worst_scale / global_scale,
        weight_abs,
        undetermined_weight_abs,
        undetermined,
        weights: a.weights.iter().map(Vec::len).sum(),
    })
}

/// One step of `recipe` on noise (`batch` images) on `a` and on `b` (autodiff devices), from the
/// same weights, compared.
pub fn step_parity(
    recipe: &Recipe,
    batch: usize,
    a: &Device,
    b: &Device,
) -> Result<StepParity, Error> {
    let mut input = noise_batch(recipe, batch, 17)?;
    input.step = 1;
    let on_a = one_step(recipe, &input, std::slice::from_ref(a))?;
    let on_b = one_step(recipe, &input, std::slice::from_ref(b))?;
    compare_steps(&on_a, &on_b)
}
