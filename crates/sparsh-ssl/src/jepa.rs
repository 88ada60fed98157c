//! I-JEPA (Assran et al. 2023) and V-JEPA (Bardes et al. 2024): a narrow predictor maps the
//! context tokens of the encoder to the layer-normed features an EMA target encoder gives the
//! masked tokens. I-JEPA: one context block, four target blocks, smooth-L1. V-JEPA: tube masks
//! on clips, L1.

use burn::module::Param;
use burn::nn::{LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::prelude::*;

use crate::ema::ema_update;
use crate::masks::JepaMasks;
use crate::vit::{
    Block, BlockConfig, LN_EPS, Vit, VitConfig, batch_standardize, gather_tokens, index_tensor,
    sincos_tensor,
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
    /// Patch grid `[frames, rows, columns]`.
    pub grid: [usize; 3],
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
            pos: sincos_tensor(p, self.grid, device),
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
                self.encoder.grid(),
            )
            .with_mlp_ratio(self.encoder.mlp_ratio)
            .init(device),
            loss_kind: self.loss,
            target_norm: self.target_norm,
        }
    }
}

/// Layer norm without affine parameters over the last axis (`F.layer_norm(h, (dim,))`).
fn plain_layer_norm(h: Tensor<3>) -> Tensor<3> {
    let c = h.clone() - h.mean_dim(2);
    let var = c.clone().powi_scalar(2).mean_dim(2);
    c / (var + 1e-5).sqrt()
}

impl Jepa {
    /// Latent regression loss averaged over the mask sets and their target sets.
    ///
    /// ```text
    /// h = layer_norm(target_encoder(x))  [then batch_standardize(h) under TargetNorm::LayerBatch]
    /// z = encoder(x[context])
    /// loss = mean_sets mean_targets ℓ(predictor(z, context, target), h[target])
    /// ```
    ///
    /// # Shapes
    /// - `x`: `[batch, frames, channels, height, width]` → `[1]`
    pub fn loss(&self, x: Tensor<5>, mask_sets: &[JepaMasks]) -> Tensor<1> {
        let device = x.device();
        let h = plain_layer_norm(
            self.target_encoder
                .forward(x.clone().detach(), None)
                .patches,
        );
        let h = match self.target_norm {
            TargetNorm::Layer => h,
            TargetNorm::LayerBatch => batch_standardize(h),
        }
        .detach();
        let tokens = self.encoder.embed(x);
        let mut total: Option<Tensor<1>> = None;
        for masks in mask_sets {
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
            let target = gather_tokens(h.clone().repeat_dim(0, m), tgt_idx);
            let d = (pred - target).abs();
            let l = match self.loss_kind {
                JepaLoss::L1 => d.mean(),
                JepaLoss::SmoothL1 => {
                    let q = d.clone().clamp_max(1.0);
                    (q.clone() * (d - q.mul_scalar(0.5))).mean()
                }
            };
            total = Some(match total {
                Some(acc) => acc + l,
                None => l,
            });
        }
        total
            .expect("at least one mask set")
            .div_scalar(mask_sets.len() as f64)
    }

    /// After an optimizer step: EMA of the target encoder with `momentum`.
    pub fn after_step(mut self, momentum: f64) -> Self {
        self.target_encoder = ema_update(self.target_encoder, &self.encoder, momentum);
        self
    }
}
