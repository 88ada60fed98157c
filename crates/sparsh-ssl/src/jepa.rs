//! I-JEPA (Assran et al. 2023) and V-JEPA (Bardes et al. 2024): a narrow predictor maps the
//! context tokens of the encoder to the layer-normed features an EMA target encoder gives the
//! masked tokens. I-JEPA: one context block, four target blocks, smooth-L1. V-JEPA: tube masks
//! on clips, L1.

use burn::module::Param;
use burn::nn::{LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::prelude::*;

use crate::ema::ema_update;
use crate::masks::JepaMasks;
use crate::pos_embed::sincos_tensor;
use crate::vit::{
    Block, BlockConfig, LN_EPS, Vit, VitConfig, batch_standardize, gather_tokens, index_tensor,
};

/// Regression loss in latent space.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JepaLoss {
    /// Smooth L1 with β = 1 (I-JEPA).
    SmoothL1,
    /// L1 (V-JEPA).
    L1,
}

/// How the target encoder's features are normalized into regression targets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TargetNorm {
    /// Layer norm per token (official I-JEPA and V-JEPA).
    Layer,
    /// Layer norm per token, then each (token, feature) standardized over the batch: the
    /// pattern every sample shares (on difference images, the flat background) is removed, so
    /// the targets are the sample-specific part at unit scale and a collapsing encoder cannot
    /// shrink them.
    LayerBatch,
}

/// Configuration of a [`Predictor`].
#[derive(Config, Debug)]
pub struct PredictorConfig {
    /// Encoder width (input and output).
    pub embed_dim: usize,
    /// Predictor width (official I-JEPA 192, V-JEPA 384).
    pub predictor_dim: usize,
    /// Predictor blocks (official I-JEPA 6, V-JEPA 12).
    pub depth: usize,
    /// Predictor heads.
    pub num_heads: usize,
    /// MLP ratio.
    #[config(default = 4.0)]
    pub mlp_ratio: f64,
    /// Axes of the position embedding ([`VitConfig::pos_grid`]).
    pub pos_grid: Vec<usize>,
}

/// The JEPA predictor.
#[derive(Module, Debug)]
pub struct Predictor {
    /// Encoder width → predictor width.
    pub predictor_embed: Linear,
    /// Learned mask token `[1, 1, predictor_dim]`.
    pub mask_token: Param<Tensor<3>>,
    /// Blocks.
    pub predictor_blocks: Vec<Block>,
    /// Final norm.
    pub predictor_norm: LayerNorm,
    /// Predictor width → encoder width.
    pub predictor_proj: Linear,
    /// Fixed position embedding `[1, tokens, predictor_dim]`.
    #[module(skip)]
    pub pos: Tensor<3>,
}

impl PredictorConfig {
    /// Initialize a [`Predictor`].
    pub fn init(&self, device: &Device) -> Predictor {
        let p = self.predictor_dim;
        Predictor {
            predictor_embed: LinearConfig::new(self.embed_dim, p).init(device),
            mask_token: Param::from_tensor(Tensor::random(
                [1, 1, p],
                burn::tensor::Distribution::Normal(0.0, 0.02),
                device,
            )),
            predictor_blocks: (0..self.depth)
                .map(|_| BlockConfig::new(p, self.num_heads, self.mlp_ratio).init(device))
                .collect(),
            predictor_norm: LayerNormConfig::new(p).with_epsilon(LN_EPS).init(device),
            predictor_proj: LinearConfig::new(p, self.embed_dim).init(device),
            pos: sincos_tensor(p, &self.pos_grid, device),
        }
    }
}

impl Predictor {
    /// Predicts the target tokens' features from the context tokens.
    ///
    /// # Shapes
    /// - `context`: `[batch, k_context, embed_dim]`, `context_idx`: `[batch, k_context]`
    /// - `target_idx`: `[batch, k_target]` → `[batch, k_target, embed_dim]`
    pub fn forward(
        &self,
        context: Tensor<3>,
        context_idx: Tensor<2, Int>,
        target_idx: Tensor<2, Int>,
    ) -> Tensor<3> {
        let [b, kc, _] = context.dims();
        let kt = target_idx.dims()[1];
        let [_, n, p] = self.pos.dims();
        let pos = self
            .pos
            .clone()
            .to_device(&context.device())
            .expand([b, n, p]);
        let x = self.predictor_embed.forward(context) + gather_tokens(pos.clone(), context_idx);
        let m = self.mask_token.val().expand([b, kt, p]) + gather_tokens(pos, target_idx);
        let mut z = Tensor::cat(vec![x, m], 1);
        for block in &self.predictor_blocks {
            z = block.forward(z);
        }
        self.predictor_proj
            .forward(self.predictor_norm.forward(z).narrow(1, kc, kt))
    }
}

/// Configuration of [`Jepa`].
#[derive(Config, Debug)]
pub struct JepaConfig {
    /// The encoder.
    pub encoder: VitConfig,
    /// Predictor width.
    pub predictor_dim: usize,
    /// Predictor blocks.
    pub predictor_depth: usize,
    /// Predictor heads.
    pub predictor_heads: usize,
    /// Latent regression loss.
    pub loss: JepaLoss,
    /// Target normalization.
    #[config(default = "TargetNorm::Layer")]
    pub target_norm: TargetNorm,
}

/// Context encoder, EMA target encoder and predictor.
#[derive(Module, Debug)]
pub struct Jepa {
    /// The encoder being pretrained (context encoder).
    pub encoder: Vit,
    /// EMA target encoder (no gradient).
    pub target_encoder: Vit,
    /// The predictor.
    pub predictor: Predictor,
    /// Loss kind.
    #[module(skip)]
    pub loss_kind: JepaLoss,
    /// Target normalization.
    #[module(skip)]
    pub target_norm: TargetNorm,
}

impl JepaConfig {
    /// Initialize a [`Jepa`]; the target encoder starts as a copy of the encoder.
    pub fn init(&self, device: &Device) -> Jepa {
        let encoder = self.encoder.init(device);
        let target_encoder = ema_update(self.encoder.init(device), &encoder, 0.0).no_grad();
        Jepa {
            encoder,
            target_encoder,
            predictor: PredictorConfig::new(
                self.encoder.embed_dim,
                self.predictor_dim,
                self.predictor_depth,
                self.predictor_heads,
                self.encoder.pos_grid(),
            )
            .with_mlp_ratio(self.encoder.mlp_ratio)
            .init(device),
            loss_kind: self.loss,
            target_norm: self.target_norm,
        }
    }
}

/// The regression targets from the target encoder's tokens `h`: layer norm without affine
/// parameters over the features (`F.layer_norm(h, (dim,))`, eps 1e-5, in the official I-JEPA
/// and V-JEPA code), then, under [`TargetNorm::LayerBatch`], standardized over the batch.
///
/// # Shapes
/// - `h`: `[batch, tokens, dim]` → same
pub fn regression_targets(h: Tensor<3>, norm: TargetNorm) -> Tensor<3> {
    let c = h.clone() - h.mean_dim(2);
    let var = c.clone().powi_scalar(2).mean_dim(2);
    let h = c / (var + 1e-5).sqrt();
    match norm {
        TargetNorm::Layer => h,
        TargetNorm::LayerBatch => batch_standardize(h),
    }
}

/// The latent regression loss over the mask sets, each pair (prediction, target) of shape
/// `[rows, k_target, dim]`: the mean over the sets of the mean over all elements of
///
/// ```text
/// SmoothL1 (I-JEPA, F.smooth_l1_loss, β = 1): ½ d² where |d| < 1, |d| − ½ elsewhere
/// L1 (V-JEPA `loss_fn`, loss_exp = 1):        |d|
/// ```
/// with `d = pred − target`.
pub fn latent_loss(pairs: Vec<(Tensor<3>, Tensor<3>)>, kind: JepaLoss) -> Tensor<1> {
    let n = pairs.len();
    pairs
        .into_iter()
        .map(|(pred, target)| {
            let d = (pred - target).abs();
            match kind {
                JepaLoss::L1 => d.mean(),
                JepaLoss::SmoothL1 => {
                    let q = d.clone().clamp_max(1.0);
                    (q.clone() * (d - q.mul_scalar(0.5))).mean()
                }
            }
        })
        .reduce(|acc, l| acc + l)
        .expect("at least one mask set")
        .div_scalar(n as f64)
}

impl Jepa {
    /// Latent regression loss averaged over the mask sets and their target sets.
    ///
    /// ```text
    /// h = regression_targets(target_encoder(x))
    /// z = encoder(x[context])
    /// loss = latent_loss over the sets of (predictor(z, context, target), h[target])
    /// ```
    ///
    /// # Shapes
    /// - `x`: `[batch, frames, channels, height, width]` → `[1]`
    pub fn loss(&self, x: Tensor<5>, mask_sets: &[JepaMasks]) -> Tensor<1> {
        let device = x.device();
        let h = regression_targets(
            self.target_encoder
                .forward(x.clone().detach(), None)
                .patches,
            self.target_norm,
        )
        .detach();
        let tokens = self.encoder.embed(x);
        let pairs = mask_sets
            .iter()
            .map(|masks| {
                let m = masks.targets.len();
                let ctx_idx = index_tensor(&masks.context, &device);
                let z = self
                    .encoder
                    .forward_tokens(gather_tokens(tokens.clone(), ctx_idx.clone()))
                    .patches;
                let rows: Vec<Vec<usize>> = masks.targets.iter().flatten().cloned().collect();
                let tgt_idx = index_tensor(&rows, &device);
                let pred = self.predictor.forward(
                    z.repeat_dim(0, m),
                    ctx_idx.repeat_dim(0, m),
                    tgt_idx.clone(),
                );
                (pred, gather_tokens(h.clone().repeat_dim(0, m), tgt_idx))
            })
            .collect();
        latent_loss(pairs, self.loss_kind)
    }

    /// After an optimizer step: EMA of the target encoder with `momentum`.
    pub fn after_step(mut self, momentum: f64) -> Self {
        self.target_encoder = ema_update(self.target_encoder, &self.encoder, momentum);
        self
    }
}
