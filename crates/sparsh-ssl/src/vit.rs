//! The Vision Transformer encoder of Sparsh: no `[cls]` token, fixed sinusoidal position
//! embeddings ([`crate::pos_embed`]), optional register tokens, optional layer scale,
//! layer-normalized tokens out (official `tactile_ssl/model/vision_transformer.py`).
//!
//! Inputs are clips `[batch, frames, channels, height, width]`. The image objectives use one
//! "frame" of 6 channels (I_t ⊕ I_{t−5}); V-JEPA uses 4 frames of 3 channels cut into tubelets of
//! 2 frames. A patch (tubelet) is flattened in the order `(channel, frame, row, column)`, the order
//! of the official `Conv2d`/`Conv3d` patch-embedding weights `[dim, C, (t,) p, p]`, so the
//! patch embedding is a [`Linear`] on flattened patches.

use burn::module::Param;
use burn::nn::{LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::prelude::*;
use burn::tensor::module::attention;
use burn::tensor::ops::AttentionModuleOptions;

use crate::Error;
use crate::kernels::{gelu, layer_norm};
use crate::pos_embed::sincos_tensor;

/// Layer-norm epsilon of the official encoder (DINOv2-style blocks).
pub const LN_EPS: f64 = 1e-6;

/// Configuration of a [`Vit`].
#[derive(Config, Debug)]
pub struct VitConfig {
    /// Input size `[height, width]` in pixels (official: `[320, 240]`, portrait).
    pub img_size: [usize; 2],
    /// Patch side in pixels (official: 16).
    pub patch_size: usize,
    /// Channels per frame (6 for I_t ⊕ I_{t−5}, 3 for V-JEPA clips).
    #[config(default = 6)]
    pub in_chans: usize,
    /// Frames per clip (1 for images, 4 for V-JEPA).
    #[config(default = 1)]
    pub num_frames: usize,
    /// Frames per tubelet (1 for images, 2 for V-JEPA).
    #[config(default = 1)]
    pub tubelet_size: usize,
    /// Token width.
    #[config(default = 192)]
    pub embed_dim: usize,
    /// Number of transformer blocks.
    #[config(default = 12)]
    pub depth: usize,
    /// Attention heads.
    #[config(default = 3)]
    pub num_heads: usize,
    /// Hidden width of the MLP as a multiple of `embed_dim`.
    #[config(default = 4.0)]
    pub mlp_ratio: f64,
    /// Register tokens prepended to the patch tokens (DINO uses one as its `[cls]`).
    #[config(default = 0)]
    pub num_registers: usize,
    /// Layer scale: the initial value of each block's per-channel residual scales `ls1`, `ls2`
    /// (official `init_values`: 1 for MAE, DINO, I-JEPA and V-JEPA, 1e-5 for DINOv2); `None`
    /// for blocks without layer scale.
    #[config(default = "None")]
    pub layer_scale: Option<f64>,
}

/// Named encoder sizes of the official code (`vit_tiny`, `vit_small`, `vit_base`).
pub fn size_preset(name: &str) -> Option<(usize, usize, usize)> {
    match name {
        "tiny" => Some((192, 12, 3)),
        "small" => Some((384, 12, 6)),
        "base" => Some((768, 12, 12)),
        _ => None,
    }
}

impl VitConfig {
    /// Patch grid `[frames / tubelet, height / patch, width / patch]`.
    pub fn grid(&self) -> [usize; 3] {
        [
            self.num_frames / self.tubelet_size,
            self.img_size[0] / self.patch_size,
            self.img_size[1] / self.patch_size,
        ]
    }

    /// Axes of the position embedding: `[rows, columns]` for images, `[frames / tubelet, rows,
    /// columns]` for clips (`num_frames > 1`, the official `is_video`).
    pub fn pos_grid(&self) -> Vec<usize> {
        let [gt, gh, gw] = self.grid();
        if self.num_frames > 1 {
            vec![gt, gh, gw]
        } else {
            vec![gh, gw]
        }
    }

    /// Number of patch (tubelet) tokens.
    pub fn num_patches(&self) -> usize {
        self.grid().iter().product()
    }

    /// Values in one flattened patch: `channels · tubelet · patch²`.
    pub fn patch_dim(&self) -> usize {
        self.in_chans * self.tubelet_size * self.patch_size * self.patch_size
    }

    /// Checks the shapes; the error names the offending field.
    pub fn validate(&self) -> Result<(), Error> {
        let bad = |field: &str, why: String| Err(Error::Config(format!("{field}: {why}")));
        if self.patch_size == 0 || self.tubelet_size == 0 || self.num_heads == 0 {
            return bad(
                "patch_size/tubelet_size/num_heads",
                "must be positive".into(),
            );
        }
        for (i, name) in ["height", "width"].iter().enumerate() {
            if self.img_size[i] == 0 || !self.img_size[i].is_multiple_of(self.patch_size) {
                return bad(
                    "img_size",
                    format!(
                        "{name} {} is not a positive multiple of patch_size {}",
                        self.img_size[i], self.patch_size
                    ),
                );
            }
        }
        if self.num_frames == 0 || !self.num_frames.is_multiple_of(self.tubelet_size) {
            return bad(
                "num_frames",
                format!(
                    "{} is not a positive multiple of tubelet_size {}",
                    self.num_frames, self.tubelet_size
                ),
            );
        }
        if self.embed_dim == 0 || !self.embed_dim.is_multiple_of(self.num_heads) {
            return bad(
                "embed_dim",
                format!(
                    "{} is not a positive multiple of num_heads {}",
                    self.embed_dim, self.num_heads
                ),
            );
        }
        if !self.embed_dim.is_multiple_of(2) {
            return bad(
                "embed_dim",
                format!("{} must be even (sinusoidal embeddings)", self.embed_dim),
            );
        }
        if let Some(g) = self.layer_scale
            && !(g.is_finite() && g > 0.0)
        {
            return bad("layer_scale", format!("{g} is not a positive number"));
        }
        Ok(())
    }

    /// Initialize a [`Vit`] (call [`validate`](Self::validate) first on user input).
    pub fn init(&self, device: &Device) -> Vit {
        let d = self.embed_dim;
        let registers = (self.num_registers > 0).then(|| {
            Param::from_tensor(Tensor::random(
                [1, self.num_registers, d],
                burn::tensor::Distribution::Normal(0.0, 1e-6),
                device,
            ))
        });
        Vit {
            patch_embed: LinearConfig::new(self.patch_dim(), d).init(device),
            register_tokens: registers,
            blocks: (0..self.depth)
                .map(|_| {
                    BlockConfig::new(d, self.num_heads, self.mlp_ratio)
                        .with_layer_scale(self.layer_scale)
                        .init(device)
                })
                .collect(),
            norm: LayerNormConfig::new(d).with_epsilon(LN_EPS).init(device),
            pos_embed: sincos_tensor(d, &self.pos_grid(), device),
            pos_grid: self.pos_grid(),
            patch_size: self.patch_size,
            tubelet_size: self.tubelet_size,
        }
    }
}

/// Cuts clips into flattened patches (tubelets).
///
/// # Shapes
/// - `x`: `[batch, frames, channels, height, width]`
/// - output: `[batch, tokens, channels · tubelet · patch²]`, tokens row-major over
///   `(frame / tubelet, row, column)`, values in `(channel, frame, row, column)` order.
pub fn patchify(x: Tensor<5>, patch: usize, tubelet: usize) -> Tensor<3> {
    let [b, t, c, h, w] = x.dims();
    let (gt, gh, gw) = (t / tubelet, h / patch, w / patch);
    x.reshape([b, gt, tubelet, c, gh, patch, gw, patch])
        .permute([0, 1, 4, 6, 3, 2, 5, 7])
        .reshape([b, gt * gh * gw, c * tubelet * patch * patch])
}

/// `h` standardized per (token, feature) over the batch: `(h − mean_b h) / √(var_b h + 1e-8)`.
///
/// # Shapes
/// - `h`: `[batch, tokens, dim]` → same
pub fn batch_standardize(h: Tensor<3>) -> Tensor<3> {
    let c = h.clone() - h.mean_dim(0);
    let var = c.clone().powi_scalar(2).mean_dim(0);
    c / (var + 1e-8).sqrt()
}

/// Picks tokens per sample.
///
/// # Shapes
/// - `x`: `[batch, tokens, dim]`, `idx`: `[batch, k]` → `[batch, k, dim]`
pub fn gather_tokens(x: Tensor<3>, idx: Tensor<2, Int>) -> Tensor<3> {
    let [b, k] = idx.dims();
    let d = x.dims()[2];
    x.gather(1, idx.reshape([b, k, 1]).repeat_dim(2, d))
}

/// Index rows as an integer tensor `[rows, k]` (all rows must have the same length).
pub fn index_tensor(rows: &[Vec<usize>], device: &Device) -> Tensor<2, Int> {
    let k = rows.first().map_or(0, Vec::len);
    let flat: Vec<i64> = rows.iter().flatten().map(|&i| i as i64).collect();
    Tensor::<1, Int>::from_data(TensorData::new(flat, [rows.len() * k]), device)
        .reshape([rows.len(), k])
}

/// Configuration of a multi-head self-attention layer.
#[derive(Config, Debug)]
pub struct AttentionConfig {
    /// Token width.
    pub dim: usize,
    /// Heads.
    pub num_heads: usize,
}

/// Multi-head self-attention with one fused `qkv` projection (official key names).
#[derive(Module, Debug)]
pub struct Attention {
    /// `[dim, 3·dim]` projection to queries, keys and values.
    pub qkv: Linear,
    /// Output projection.
    pub proj: Linear,
    /// Heads.
    pub num_heads: usize,
}

impl AttentionConfig {
    /// Initialize an [`Attention`].
    pub fn init(&self, device: &Device) -> Attention {
        Attention {
            qkv: LinearConfig::new(self.dim, 3 * self.dim).init(device),
            proj: LinearConfig::new(self.dim, self.dim).init(device),
            num_heads: self.num_heads,
        }
    }
}

impl Attention {
    /// `proj(softmax(q kᵀ / √d_head) v)` per head.
    ///
    /// # Shapes
    /// - `x`: `[batch, tokens, dim]` → `[batch, tokens, dim]`
    pub fn forward(&self, x: Tensor<3>) -> Tensor<3> {
        let [b, n, d] = x.dims();
        let h = self.num_heads;
        let qkv = self
            .qkv
            .forward(x)
            .reshape([b, n, 3, h, d / h])
            .permute([2, 0, 3, 1, 4]);
        let part = |i: usize| qkv.clone().narrow(0, i, 1).reshape([b, h, n, d / h]);
        let out = attention(
            part(0),
            part(1),
            part(2),
            None,
            None,
            AttentionModuleOptions::default(),
        );
        self.proj.forward(out.swap_dims(1, 2).reshape([b, n, d]))
    }
}

/// Configuration of a pre-norm transformer block.
#[derive(Config, Debug)]
pub struct BlockConfig {
    /// Token width.
    pub dim: usize,
    /// Heads.
    pub num_heads: usize,
    /// MLP hidden width as a multiple of `dim`.
    pub mlp_ratio: f64,
    /// Initial layer-scale value (see [`VitConfig::layer_scale`]); `None` for none.
    #[config(default = "None")]
    pub layer_scale: Option<f64>,
}

/// The two-layer GELU MLP of a block (`fc1`, `fc2`).
#[derive(Module, Debug)]
pub struct Mlp {
    /// First layer.
    pub fc1: Linear,
    /// Second layer.
    pub fc2: Linear,
}

/// Pre-norm transformer block: `x + γ₁ ⊙ attn(norm1 x)`, then `x + γ₂ ⊙ mlp(norm2 x)`, with the
/// layer-scale vectors `γ` (official `LayerScale`, `tactile_ssl/model/layers/layer_scale.py`,
/// applied in `Block.forward`, `tactile_ssl/model/layers/block.py`) or without (`γ = 1`).
#[derive(Module, Debug)]
pub struct Block {
    /// Norm before attention.
    pub norm1: LayerNorm,
    /// Self-attention.
    pub attn: Attention,
    /// Layer scale `γ₁` `[dim]` of the attention branch (official `ls1.gamma`).
    pub ls1: Option<Param<Tensor<1>>>,
    /// Norm before the MLP.
    pub norm2: LayerNorm,
    /// MLP.
    pub mlp: Mlp,
    /// Layer scale `γ₂` `[dim]` of the MLP branch (official `ls2.gamma`).
    pub ls2: Option<Param<Tensor<1>>>,
}

impl BlockConfig {
    /// Initialize a [`Block`].
    pub fn init(&self, device: &Device) -> Block {
        let hidden = (self.dim as f64 * self.mlp_ratio) as usize;
        let gamma = || {
            self.layer_scale
                .map(|g| Param::from_tensor(Tensor::ones([self.dim], device).mul_scalar(g)))
        };
        Block {
            norm1: LayerNormConfig::new(self.dim)
                .with_epsilon(LN_EPS)
                .init(device),
            attn: AttentionConfig::new(self.dim, self.num_heads).init(device),
            ls1: gamma(),
            norm2: LayerNormConfig::new(self.dim)
                .with_epsilon(LN_EPS)
                .init(device),
            mlp: Mlp {
                fc1: LinearConfig::new(self.dim, hidden).init(device),
                fc2: LinearConfig::new(hidden, self.dim).init(device),
            },
            ls2: gamma(),
        }
    }
}

impl Block {
    /// One block.
    ///
    /// # Shapes
    /// - `x`: `[batch, tokens, dim]` → `[batch, tokens, dim]`
    pub fn forward(&self, x: Tensor<3>) -> Tensor<3> {
        let scaled = |y: Tensor<3>, gamma: &Option<Param<Tensor<1>>>| match gamma {
            Some(g) => y * g.val().unsqueeze::<3>(),
            None => y,
        };
        let x = x.clone()
            + scaled(
                self.attn.forward(layer_norm(x, &self.norm1, LN_EPS)),
                &self.ls1,
            );
        let y = self.mlp.fc2.forward(gelu(self.mlp.fc1.forward(layer_norm(
            x.clone(),
            &self.norm2,
            LN_EPS,
        ))));
        x + scaled(y, &self.ls2)
    }
}

/// The encoder's output: layer-normalized tokens.
#[derive(Debug, Clone)]
pub struct VitOutput {
    /// Patch tokens `[batch, kept tokens, dim]`.
    pub patches: Tensor<3>,
    /// Register tokens `[batch, registers, dim]` (`None` without registers).
    pub registers: Option<Tensor<3>>,
}

/// The Sparsh Vision Transformer encoder.
#[derive(Module, Debug)]
pub struct Vit {
    /// Patch embedding on flattened patches, weight `[patch_dim, dim]`.
    pub patch_embed: Linear,
    /// Register tokens `[1, registers, dim]`.
    pub register_tokens: Option<Param<Tensor<3>>>,
    /// Transformer blocks.
    pub blocks: Vec<Block>,
    /// Final norm.
    pub norm: LayerNorm,
    /// Fixed position embedding `[1, tokens, dim]` (not trained).
    #[module(skip)]
    pub pos_embed: Tensor<3>,
    /// Axes of the position embedding ([`VitConfig::pos_grid`]).
    #[module(skip)]
    pub pos_grid: Vec<usize>,
    /// Patch side.
    #[module(skip)]
    pub patch_size: usize,
    /// Tubelet length.
    #[module(skip)]
    pub tubelet_size: usize,
}

impl Vit {
    /// Token width.
    pub fn dim(&self) -> usize {
        self.pos_embed.dims()[2]
    }

    /// Patch tokens with position embeddings, before the blocks.
    ///
    /// # Shapes
    /// - `x`: `[batch, frames, channels, height, width]` → `[batch, tokens, dim]`
    pub fn embed(&self, x: Tensor<5>) -> Tensor<3> {
        let device = x.device();
        let tokens = self
            .patch_embed
            .forward(patchify(x, self.patch_size, self.tubelet_size));
        tokens + self.pos_embed.clone().to_device(&device)
    }

    /// Encodes clips, optionally keeping only the tokens `keep` (masked encoding).
    ///
    /// # Shapes
    /// - `x`: `[batch, frames, channels, height, width]`
    /// - `keep`: `[batch, k]` token indices (all tokens when `None`)
    /// - output patches: `[batch, k, dim]`; registers `[batch, registers, dim]`
    pub fn forward(&self, x: Tensor<5>, keep: Option<Tensor<2, Int>>) -> VitOutput {
        let tokens = self.embed(x);
        let tokens = match keep {
            Some(idx) => gather_tokens(tokens, idx),
            None => tokens,
        };
        self.forward_tokens(tokens)
    }

    /// Layer-normalized patch tokens after each block in `hooks` (0-based, ascending, repeats
    /// allowed), the
    /// intermediate layers a dense (DPT) decoder reads (DINOv2's `get_intermediate_layers` with
    /// `norm = True`); register tokens are dropped.
    ///
    /// # Shapes
    /// - `x`: `[batch, frames, channels, height, width]` → one `[batch, tokens, dim]` per hook
    pub fn forward_hooks(&self, x: Tensor<5>, hooks: &[usize]) -> Vec<Tensor<3>> {
        let tokens = self.embed(x);
        let [b, _, d] = tokens.dims();
        let r = self.register_tokens.as_ref().map_or(0, |p| p.dims()[1]);
        let mut x = match &self.register_tokens {
            Some(reg) => Tensor::cat(vec![reg.val().expand([b, r, d]), tokens], 1),
            None => tokens,
        };
        let mut out = Vec::with_capacity(hooks.len());
        let last = hooks.iter().copied().max().unwrap_or(0);
        for (i, block) in self.blocks.iter().enumerate().take(last + 1) {
            x = block.forward(x);
            // a block hooked twice (shallow encoders) is read twice
            for _ in hooks.iter().filter(|&&h| h == i) {
                let n = x.dims()[1];
                out.push(layer_norm(x.clone(), &self.norm, LN_EPS).narrow(1, r, n - r));
            }
        }
        out
    }

    /// Runs registers + blocks + norm on already embedded tokens `[batch, k, dim]`.
    pub fn forward_tokens(&self, tokens: Tensor<3>) -> VitOutput {
        let [b, _, d] = tokens.dims();
        let r = self.register_tokens.as_ref().map_or(0, |p| p.dims()[1]);
        let mut x = match &self.register_tokens {
            Some(reg) => Tensor::cat(vec![reg.val().expand([b, r, d]), tokens], 1),
            None => tokens,
        };
        for block in &self.blocks {
            x = block.forward(x);
        }
        let x = layer_norm(x, &self.norm, LN_EPS);
        let n = x.dims()[1];
        VitOutput {
            registers: (r > 0).then(|| x.clone().narrow(1, 0, r)),
            patches: x.narrow(1, r, n - r),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patchify_puts_each_pixel_in_its_patch_and_order() {
        let device = Device::flex();
        // value encodes (t, c, y, x)
        let (t, c, h, w) = (2, 3, 4, 6);
        let vals: Vec<f32> = (0..t * c * h * w).map(|i| i as f32).collect();
        let x = Tensor::<1>::from_floats(vals.as_slice(), &device).reshape([1, t, c, h, w]);
        let p = patchify(x, 2, 2);
        assert_eq!(p.dims(), [1, 6, 3 * 2 * 2 * 2]);
        let data = p.into_data().try_to_vec::<f32>().unwrap();
        let pd = 24;
        for tok in 0..6 {
            let (pr, pc) = (tok / 3, tok % 3);
            for ci in 0..3 {
                for ti in 0..2 {
                    for yy in 0..2 {
                        for xx in 0..2 {
                            let k = ((ci * 2 + ti) * 2 + yy) * 2 + xx;
                            let want = (((ti * c + ci) * h + pr * 2 + yy) * w + pc * 2 + xx) as f32;
                            assert_eq!(data[tok * pd + k], want);
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn sincos_rows_are_distinct_and_bounded() {
        let e = crate::pos_embed::sincos_embedding(16, &[3, 4]);
        assert_eq!(e.len(), 12 * 16);
        assert!(e.iter().all(|v| v.abs() <= 1.0));
        // position (0,0): sin terms 0, cos terms 1
        assert_eq!(&e[0..4], &[0.0; 4]);
        assert_eq!(&e[4..8], &[1.0; 4]);
        for a in 0..12 {
            for b in a + 1..12 {
                assert_ne!(e[a * 16..(a + 1) * 16], e[b * 16..(b + 1) * 16]);
            }
        }
    }

    #[test]
    fn config_rejects_indivisible_image() {
        let cfg = VitConfig::new([30, 24], 8);
        let err = cfg.validate().unwrap_err().to_string();
        assert!(err.contains("img_size"), "{err}");
    }

    #[test]
    fn encoder_shapes_with_registers_and_masking() {
        let device = Device::flex();
        let cfg = VitConfig::new([16, 12], 4)
            .with_embed_dim(32)
            .with_depth(2)
            .with_num_heads(4)
            .with_num_registers(2);
        cfg.validate().unwrap();
        let vit = crate::device::seeded_module(&device, 1, || cfg.init(&device));
        let x = crate::device::seeded_random(
            &device,
            3,
            [2, 1, 6, 16, 12],
            burn::tensor::Distribution::Default,
        );
        let out = vit.forward(x.clone(), None);
        assert_eq!(out.patches.dims(), [2, 12, 32]);
        assert_eq!(out.registers.unwrap().dims(), [2, 2, 32]);
        let keep = index_tensor(&[vec![0, 5, 7], vec![11, 1, 2]], &device);
        assert_eq!(vit.forward(x, Some(keep)).patches.dims(), [2, 3, 32]);
    }

    /// The last hook equals the encoder's own output, and an earlier hook differs from it.
    #[test]
    fn hooks_end_at_the_encoder_output() {
        let device = Device::flex();
        let cfg = VitConfig::new([16, 12], 4)
            .with_embed_dim(32)
            .with_depth(3)
            .with_num_heads(4)
            .with_num_registers(1);
        let vit = crate::device::seeded_module(&device, 2, || cfg.init(&device));
        let x = crate::device::seeded_random(
            &device,
            3,
            [2, 1, 6, 16, 12],
            burn::tensor::Distribution::Default,
        );
        let hooks = vit.forward_hooks(x.clone(), &[0, 2, 2]);
        assert_eq!(hooks.len(), 3);
        let full: Vec<f32> = vit
            .forward(x, None)
            .patches
            .into_data()
            .try_to_vec()
            .unwrap();
        let last: Vec<f32> = hooks[1].clone().into_data().try_to_vec().unwrap();
        let first: Vec<f32> = hooks[0].clone().into_data().try_to_vec().unwrap();
        assert_eq!(last.len(), full.len());
        assert!(last.iter().zip(&full).all(|(a, b)| (a - b).abs() < 1e-5));
        assert!(first.iter().zip(&full).any(|(a, b)| (a - b).abs() > 1e-3));
    }

    /// Per (token, feature): zero mean and unit variance over the batch, whatever the shared
    /// offset and scale; a feature constant over the batch stays 0 instead of dividing by 0.
    #[test]
    fn batch_standardize_removes_the_shared_pattern() {
        let device = Device::flex();
        // [batch 4, tokens 2, dim 2]: token 0 feature 0 = 10 + small sample term; the rest constant
        let v = [
            10.0, 3.0, 3.0, 3.0, 10.002, 3.0, 3.0, 3.0, 9.999, 3.0, 3.0, 3.0, 10.001, 3.0, 3.0, 3.0,
        ];
        let h = Tensor::<1>::from_floats(v, &device).reshape([4, 2, 2]);
        let out: Vec<f32> = batch_standardize(h).into_data().try_to_vec().unwrap();
        let col: Vec<f64> = (0..4).map(|b| out[b * 4] as f64).collect();
        let mean = col.iter().sum::<f64>() / 4.0;
        let var = col.iter().map(|c| (c - mean).powi(2)).sum::<f64>() / 4.0;
        assert!(mean.abs() < 1e-3 && (var - 1.0).abs() < 0.02, "{col:?}");
        // ordering of the samples kept: 10.002 highest, 9.999 lowest
        assert!(
            col[1] > col[3] && col[3] > col[0] && col[0] > col[2],
            "{col:?}"
        );
        for b in 0..4 {
            for k in 1..4 {
                assert_eq!(out[b * 4 + k], 0.0);
            }
        }
    }
}
