//! MAE (He et al. 2022): encode the visible 25 % of the patches, reconstruct the pixels of the
//! masked ones with a light decoder, L2 on the masked patches only ([`masked_mse`]).

use burn::module::Param;
use burn::nn::{LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::prelude::*;

use crate::masks::MaeMask;
use crate::pos_embed::sincos_tensor;
use crate::vit::{
    Block, BlockConfig, LN_EPS, Vit, VitConfig, gather_tokens, index_tensor, patchify,
};

/// Configuration of [`Mae`] (official defaults: mask 0.75, decoder 512 / 8 / 16).
#[derive(Config, Debug)]
pub struct MaeConfig {
    /// The encoder.
    pub encoder: VitConfig,
    /// Fraction of patches masked.
    #[config(default = 0.75)]
    pub mask_ratio: f64,
    /// Decoder width.
    #[config(default = 512)]
    pub decoder_dim: usize,
    /// Decoder blocks.
    #[config(default = 8)]
    pub decoder_depth: usize,
    /// Decoder heads.
    #[config(default = 16)]
    pub decoder_heads: usize,
    /// Regress per-patch standardized pixels (MAE's `norm_pix_loss`; off in Sparsh).
    #[config(default = false)]
    pub norm_pix_loss: bool,
}

/// MAE: encoder, decoder and pixel head.
#[derive(Module, Debug)]
pub struct Mae {
    /// The encoder being pretrained.
    pub encoder: Vit,
    /// Encoder width → decoder width.
    pub decoder_embed: Linear,
    /// Learned mask token `[1, 1, decoder_dim]`.
    pub mask_token: Param<Tensor<3>>,
    /// Decoder blocks.
    pub decoder_blocks: Vec<Block>,
    /// Decoder norm.
    pub decoder_norm: LayerNorm,
    /// Decoder width → flattened patch.
    pub decoder_pred: Linear,
    /// Fixed decoder position embedding `[1, tokens, decoder_dim]`.
    #[module(skip)]
    pub decoder_pos: Tensor<3>,
    /// Per-patch standardized targets ([`masked_mse`]).
    #[module(skip)]
    pub norm_pix_loss: bool,
}

impl MaeConfig {
    /// Initialize a [`Mae`].
    pub fn init(&self, device: &Device) -> Mae {
        let e = &self.encoder;
        let dd = self.decoder_dim;
        Mae {
            encoder: e.init(device),
            decoder_embed: LinearConfig::new(e.embed_dim, dd).init(device),
            mask_token: Param::from_tensor(Tensor::random(
                [1, 1, dd],
                burn::tensor::Distribution::Normal(0.0, 0.02),
                device,
            )),
            decoder_blocks: (0..self.decoder_depth)
                .map(|_| BlockConfig::new(dd, self.decoder_heads, e.mlp_ratio).init(device))
                .collect(),
            decoder_norm: LayerNormConfig::new(dd).with_epsilon(LN_EPS).init(device),
            decoder_pred: LinearConfig::new(dd, e.patch_dim()).init(device),
            decoder_pos: sincos_tensor(dd, &e.pos_grid(), device),
            norm_pix_loss: self.norm_pix_loss,
        }
    }
}

/// MAE's reconstruction loss (He et al. 2022, §3 "Reconstruction target"; official
/// `MAEModule.compute_loss`): the mean squared error per patch, averaged over the masked patches
/// only.
///
/// ```text
/// target_i = (patch_i − mean_j patch_ij) / √(var_j patch_ij + 1e-6)   [norm_pix only; var unbiased, as torch.var]
/// loss = Σ_i mask_i · mean_j (pred_ij − target_ij)² / Σ_i mask_i
/// ```
///
/// # Shapes
/// - `pred`, `target`: `[batch, tokens, patch_dim]`, `masked`: `[batch][tokens]` → `[1]`
pub fn masked_mse(
    pred: Tensor<3>,
    target: Tensor<3>,
    masked: &[Vec<bool>],
    norm_pix: bool,
) -> Tensor<1> {
    let device = pred.device();
    let [b, n, d] = target.dims();
    let target = if norm_pix {
        let c = target.clone() - target.mean_dim(2);
        let var = c
            .clone()
            .powi_scalar(2)
            .sum_dim(2)
            .div_scalar((d.max(2) - 1) as f64);
        c / (var + 1e-6).sqrt()
    } else {
        target
    };
    let per_patch = (pred - target).powi_scalar(2).mean_dim(2).reshape([b, n]);
    let weights: Vec<f32> = masked
        .iter()
        .flatten()
        .map(|&m| if m { 1.0 } else { 0.0 })
        .collect();
    let count = weights.iter().sum::<f32>().max(1.0);
    let w = Tensor::<1>::from_floats(weights.as_slice(), &device).reshape([b, n]);
    (per_patch * w).sum().div_scalar(count)
}

impl Mae {
    /// Reconstruction loss of the masked patches ([`masked_mse`]).
    ///
    /// # Shapes
    /// - `x`: `[batch, frames, channels, height, width]`
    /// - output: `[1]`
    pub fn loss(&self, x: Tensor<5>, mask: &MaeMask) -> Tensor<1> {
        let device = x.device();
        let target = patchify(
            x.clone(),
            self.encoder.patch_size,
            self.encoder.tubelet_size,
        );
        let [b, n, _] = target.dims();
        let keep = index_tensor(&mask.keep, &device);
        let latent = self.encoder.forward(x, Some(keep)).patches;
        let y = self.decoder_embed.forward(latent);
        let [_, k, dd] = y.dims();
        let mask_tokens = self.mask_token.val().expand([b, n - k, dd]);
        let shuffled = Tensor::cat(vec![y, mask_tokens], 1);
        let mut z = gather_tokens(shuffled, index_tensor(&mask.restore, &device))
            + self.decoder_pos.clone().to_device(&device);
        for block in &self.decoder_blocks {
            z = block.forward(z);
        }
        let pred = self.decoder_pred.forward(self.decoder_norm.forward(z));
        masked_mse(pred, target, &mask.masked, self.norm_pix_loss)
    }
}
