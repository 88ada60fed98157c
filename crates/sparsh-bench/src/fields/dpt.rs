//! The dense decoder of T1A: a DPT head (Ranftl et al., "Vision Transformers for Dense
//! Prediction", ICCV 2021) on four intermediate token maps of a frozen ViT, with a normal branch
//! (a non-negative map, sigmoid) and a shear branch (a 2-D flow in input pixels, tanh-scaled), as
//! the official Sparsh force-field decoder.
//!
//! Reassemble: each hooked token map `[batch, dim, rows, cols]` is projected by a 1 × 1
//! convolution to `channels` and resampled by ×4, ×2, ×1 and ×½ of the token grid — the
//! official scales 4, 8, 16, 32 for 16-pixel patches, i.e. strides patch/4, patch/2, patch and
//! 2·patch. Fusion: RefineNet blocks (two residual convolution units) from the coarsest map to
//! the finest, each result resized to the next map's size. Heads: 3 × 3 convolution, bilinear
//! resize to the input, 3 × 3 convolution, ReLU, 1 × 1 convolution.
//!
//! Optionally (not in the official decoder) an **image skip**: two 3 × 3 convolutions on the
//! encoder's own input `I_t ⊕ I_{t−k}` at full resolution, added to each head before its last
//! ReLU, so that the maps are not bounded by the token grid (a 12 × 9 grid at 96 × 72 with patch
//! 8), as U-Net's skips and monocular-depth decoders' image guidance do.

use burn::nn::PaddingConfig2d;
use burn::nn::conv::{Conv2d, Conv2dConfig, ConvTranspose2d, ConvTranspose2dConfig};
use burn::prelude::*;
use burn::tensor::activation::{relu, sigmoid};
use burn::tensor::module::interpolate;
use burn::tensor::ops::{InterpolateMode, InterpolateOptions};

/// The blocks hooked for a ViT of `depth` blocks: the last of each quarter,
/// `⌈(i + 1)·depth / 4⌉ − 1` — the official `[2, 5, 8, 11]` for 12 blocks, `[1, 2, 4, 5]` for 6.
pub fn hook_blocks(depth: usize) -> Vec<usize> {
    (1..=4)
        .map(|i| (i * depth).div_ceil(4).max(1) - 1)
        .collect()
}

/// Bilinear resize of `[batch, channels, h, w]` to `size` (half-pixel centres, PyTorch's
/// `align_corners=False`). On burn's CPU backend this is its interpolation kernel; burn's GPU
/// backends (wgpu, CUDA) have no backward for bilinear interpolation, so on them the same
/// weights are applied as two matrix products ([`resize_by_matrices`]), which agree with the
/// kernel to rounding and train on every backend.
pub fn resize(x: Tensor<4>, size: [usize; 2]) -> Tensor<4> {
    let [_, _, h, w] = x.dims();
    if [h, w] == size {
        return x;
    }
    if x.device() != Device::flex() {
        return resize_by_matrices(x, size);
    }
    interpolate(
        x,
        InterpolateOptions::new(InterpolateMode::Bilinear)
            .with_align_corners(false)
            .with_output_size(size),
    )
}

/// [`resize`] as `A_h · x · A_wᵀ`, with `A` the bilinear weights of each axis: differentiable
/// on every backend.
pub fn resize_by_matrices(x: Tensor<4>, size: [usize; 2]) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let device = x.device();
    let ah = Tensor::<1>::from_floats(bilinear_weights(h, size[0]).as_slice(), &device)
        .reshape([1, 1, size[0], h])
        .expand([b, c, size[0], h]);
    let awt = Tensor::<1>::from_floats(bilinear_weights(w, size[1]).as_slice(), &device)
        .reshape([1, 1, size[1], w])
        .swap_dims(2, 3)
        .expand([b, c, w, size[1]]);
    ah.matmul(x).matmul(awt)
}

/// The `[to, from]` matrix (row-major) of linear resampling from `from` samples to `to`, half-pixel
/// centres, the source coordinate clamped to the first sample and the neighbour to the last (as
/// burn's and PyTorch's bilinear interpolation).
fn bilinear_weights(from: usize, to: usize) -> Vec<f32> {
    let ratio = from as f64 / to as f64;
    let mut a = vec![0.0f32; to * from];
    for o in 0..to {
        let src = (o as f64 + 0.5) * ratio - 0.5;
        let low = src.floor().max(0.0) as usize;
        let high = (low + 1).min(from - 1);
        let t = (src - low as f64).max(0.0) as f32;
        a[o * from + low] += 1.0 - t;
        a[o * from + high] += t;
    }
    a
}

fn conv(cin: usize, cout: usize, k: usize, device: &Device) -> Conv2d {
    Conv2dConfig::new([cin, cout], [k, k])
        .with_padding(PaddingConfig2d::Explicit(k / 2, k / 2, k / 2, k / 2))
        .init(device)
}

/// Configuration of a [`FieldDecoder`].
#[derive(Config, Debug)]
pub struct FieldDecoderConfig {
    /// Token width of the encoder.
    pub embed_dim: usize,
    /// Token grid `[rows, cols]`.
    pub grid: [usize; 2],
    /// Input `[height, width]` (the output resolution).
    pub img_size: [usize; 2],
    /// Feature channels of the reassembled maps (official: 128).
    #[config(default = 32)]
    pub channels: usize,
    /// Largest flow the shear branch can output (input pixels): `tanh · max_flow_px`.
    #[config(default = 4.0)]
    pub max_flow_px: f64,
    /// Add the image skip, which reads the encoder's input `I_t ⊕ I_{t−k}`.
    #[config(default = false)]
    pub image_skip: bool,
}

/// Channels of the encoder's input `I_t ⊕ I_{t−k}`: two RGB frames.
pub const PAIR_CHANNELS: usize = 6;

/// Width of the image skip's features (the heads' hidden width).
const SKIP_FEATURES: usize = 16;

/// The image skip: `conv(relu(conv(input)))` at the input's resolution.
#[derive(Module, Debug)]
pub struct ImageSkip {
    /// 3 × 3 convolution from the input channels.
    pub conv1: Conv2d,
    /// 3 × 3 convolution to the heads' hidden width.
    pub conv2: Conv2d,
}

impl ImageSkip {
    fn forward(&self, input: Tensor<4>) -> Tensor<4> {
        self.conv2.forward(relu(self.conv1.forward(input)))
    }
}

/// One reassemble stage.
#[derive(Module, Debug)]
pub struct Reassemble {
    /// 1 × 1 projection of the tokens.
    pub project: Conv2d,
    /// Upsampling (×4 or ×2), if any.
    pub up: Option<ConvTranspose2d>,
    /// Downsampling (×½), if any.
    pub down: Option<Conv2d>,
    /// 3 × 3 convolution to the fusion width.
    pub out: Conv2d,
}

impl Reassemble {
    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let mut y = self.project.forward(x);
        if let Some(up) = &self.up {
            y = up.forward(y);
        }
        if let Some(down) = &self.down {
            y = down.forward(y);
        }
        self.out.forward(y)
    }
}

/// A residual convolution unit: `x + conv(relu(conv(relu(x))))`.
#[derive(Module, Debug)]
pub struct ResidualUnit {
    /// First 3 × 3 convolution.
    pub conv1: Conv2d,
    /// Second 3 × 3 convolution.
    pub conv2: Conv2d,
}

impl ResidualUnit {
    fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        x.clone() + self.conv2.forward(relu(self.conv1.forward(relu(x))))
    }
}

/// A fusion block: the coarser path plus this level's map, refined, resized, projected.
#[derive(Module, Debug)]
pub struct Fusion {
    /// Unit on this level's map.
    pub unit1: ResidualUnit,
    /// Unit on the sum.
    pub unit2: ResidualUnit,
    /// 1 × 1 output projection.
    pub out: Conv2d,
}

impl Fusion {
    fn forward(&self, coarser: Option<Tensor<4>>, x: Tensor<4>, to: [usize; 2]) -> Tensor<4> {
        let [_, _, h, w] = x.dims();
        let y = match coarser {
            Some(c) => resize(c, [h, w]) + self.unit1.forward(x),
            None => x,
        };
        self.out.forward(resize(self.unit2.forward(y), to))
    }
}

/// An output head.
#[derive(Module, Debug)]
pub struct DenseHead {
    /// 3 × 3 convolution at the fused resolution.
    pub conv1: Conv2d,
    /// 3 × 3 convolution at the input resolution.
    pub conv2: Conv2d,
    /// 1 × 1 convolution to the outputs.
    pub conv3: Conv2d,
}

impl DenseHead {
    fn forward(&self, x: Tensor<4>, size: [usize; 2], skip: Option<Tensor<4>>) -> Tensor<4> {
        let y = self.conv2.forward(resize(self.conv1.forward(x), size));
        let y = match skip {
            Some(s) => y + s,
            None => y,
        };
        self.conv3.forward(relu(y))
    }
}

/// The DPT field decoder: normal and shear branches on a shared reassemble–fusion trunk.
#[derive(Module, Debug)]
pub struct FieldDecoder {
    /// Reassemble stages, finest first.
    pub reassemble: Vec<Reassemble>,
    /// Fusion blocks, finest first.
    pub fusion: Vec<Fusion>,
    /// Normal branch.
    pub normal: DenseHead,
    /// Shear branch.
    pub shear: DenseHead,
    /// Image skip, if configured.
    pub image_skip: Option<ImageSkip>,
    /// Token grid.
    #[module(skip)]
    pub grid: [usize; 2],
    /// Output size.
    #[module(skip)]
    pub img_size: [usize; 2],
    /// Flow bound (input pixels).
    #[module(skip)]
    pub max_flow_px: f64,
}

/// The decoder's output for a batch.
#[derive(Debug, Clone)]
pub struct FieldOutput {
    /// Normal map `[batch, 1, height, width]` in (0, 1).
    pub normal: Tensor<4>,
    /// Flow `[batch, 2, height, width]` (input pixels; channel 0 along columns, 1 along rows).
    pub flow: Tensor<4>,
}

impl FieldDecoderConfig {
    /// Initialize a [`FieldDecoder`].
    pub fn init(&self, device: &Device) -> FieldDecoder {
        let (d, c) = (self.embed_dim, self.channels);
        let stage = |factor: i32| Reassemble {
            project: conv(d, c, 1, device),
            up: (factor > 1).then(|| {
                let f = factor as usize;
                ConvTranspose2dConfig::new([c, c], [f, f])
                    .with_stride([f, f])
                    .init(device)
            }),
            down: (factor < 0).then(|| {
                Conv2dConfig::new([c, c], [3, 3])
                    .with_stride([2, 2])
                    .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
                    .init(device)
            }),
            out: conv(c, c, 3, device),
        };
        let unit = || ResidualUnit {
            conv1: conv(c, c, 3, device),
            conv2: conv(c, c, 3, device),
        };
        let fusion = || Fusion {
            unit1: unit(),
            unit2: unit(),
            out: conv(c, c, 1, device),
        };
        let head = |outputs: usize| DenseHead {
            conv1: conv(c, c / 2, 3, device),
            conv2: conv(c / 2, SKIP_FEATURES, 3, device),
            conv3: conv(SKIP_FEATURES, outputs, 1, device),
        };
        let image_skip = self.image_skip.then(|| ImageSkip {
            conv1: conv(PAIR_CHANNELS, SKIP_FEATURES, 3, device),
            conv2: conv(SKIP_FEATURES, SKIP_FEATURES, 3, device),
        });
        FieldDecoder {
            // ×4, ×2, ×1, ×½ of the token grid (−1 marks the strided convolution)
            reassemble: [4, 2, 1, -1].into_iter().map(stage).collect(),
            fusion: (0..4).map(|_| fusion()).collect(),
            normal: head(1),
            shear: head(2),
            image_skip,
            grid: self.grid,
            img_size: self.img_size,
            max_flow_px: self.max_flow_px,
        }
    }
}

impl FieldDecoder {
    /// Decodes hooked token maps; the image skip, if any, reads the encoder's `input`.
    ///
    /// # Shapes
    /// - `hooks`: four `[batch, tokens, dim]`, shallowest first
    /// - `input`: `[batch, PAIR_CHANNELS, height, width]`, needed by the skip only
    /// - output: [`FieldOutput`]
    pub fn forward(&self, hooks: Vec<Tensor<3>>, input: Option<Tensor<4>>) -> FieldOutput {
        let [gh, gw] = self.grid;
        let maps: Vec<Tensor<4>> = hooks
            .into_iter()
            .zip(&self.reassemble)
            .map(|(t, stage)| {
                let [b, n, d] = t.dims();
                debug_assert_eq!(n, gh * gw);
                stage.forward(t.swap_dims(1, 2).reshape([b, d, gh, gw]))
            })
            .collect();
        let sizes: Vec<[usize; 2]> = maps.iter().map(|m| [m.dims()[2], m.dims()[3]]).collect();
        let mut path: Option<Tensor<4>> = None;
        for level in (0..4).rev() {
            let to = if level == 0 {
                [2 * sizes[0][0], 2 * sizes[0][1]]
            } else {
                sizes[level - 1]
            };
            path = Some(self.fusion[level].forward(path, maps[level].clone(), to));
        }
        let fused = path.expect("four levels");
        let skip = self
            .image_skip
            .as_ref()
            .map(|s| s.forward(input.expect("a decoder with the image skip is given its input")));
        let size = self.img_size;
        FieldOutput {
            normal: sigmoid(self.normal.forward(fused.clone(), size, skip.clone())),
            flow: self.shear.forward(fused, size, skip).tanh() * self.max_flow_px,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sparsh_ssl::device::{seeded, seeded_module};

    #[test]
    fn hooks_follow_the_official_layout() {
        assert_eq!(hook_blocks(12), vec![2, 5, 8, 11]);
        assert_eq!(hook_blocks(6), vec![1, 2, 4, 5]);
        assert_eq!(hook_blocks(4), vec![0, 1, 2, 3]);
    }

    /// The matrix form of the bilinear resize (the GPUs' path) gives the CPU kernel's values
    /// and gradients, up and down, odd sizes included.
    #[test]
    fn the_matrix_resize_is_the_bilinear_kernel() {
        let device = Device::flex().autodiff();
        for (from, to) in [([3, 2], [12, 9]), ([12, 9], [96, 72]), ([7, 5], [3, 4])] {
            // drawn under the seed's lock: burn's generator is global, shared with other tests
            let (x, r) = seeded(&device, 1, || {
                let draw = |shape: [usize; 2]| {
                    Tensor::<4>::random(
                        [2, 3, shape[0], shape[1]],
                        burn::tensor::Distribution::Default,
                        &device,
                    )
                };
                (draw(from), draw(to))
            });
            let x = x.require_grad();
            let values_and_grad = |y: Tensor<4>| {
                let v: Vec<f32> = y.clone().into_data().try_to_vec().unwrap();
                let g = (y * r.clone()).sum().backward();
                let g: Vec<f32> = x.grad(&g).unwrap().into_data().try_to_vec().unwrap();
                (v, g)
            };
            let (kv, kg) = values_and_grad(resize(x.clone(), to));
            let (mv, mg) = values_and_grad(resize_by_matrices(x.clone(), to));
            // the largest difference relative to the largest value: sums in another order
            let worst = |a: &[f32], b: &[f32]| {
                let scale = a.iter().fold(0f32, |m, u| m.max(u.abs()));
                a.iter().zip(b).fold(0f32, |m, (u, v)| m.max((u - v).abs())) / scale
            };
            let (v, g) = (worst(&kv, &mv), worst(&kg, &mg));
            assert!(v < 1e-6, "{from:?} → {to:?}: values differ by {v:.1e}");
            assert!(g < 1e-6, "{from:?} → {to:?}: gradients differ by {g:.1e}");
        }
    }

    /// An odd token grid (9 columns) still decodes to the input size, in range, with and
    /// without the image skip.
    #[test]
    fn decoder_outputs_bounded_maps_at_input_size() {
        let device = Device::flex();
        for skip in [false, true] {
            let dec = seeded_module(&device, 2, || {
                FieldDecoderConfig::new(16, [12, 9], [96, 72])
                    .with_channels(8)
                    .with_max_flow_px(3.0)
                    .with_image_skip(skip)
                    .init(&device)
            });
            assert_eq!(dec.image_skip.is_some(), skip);
            let (hooks, input) = seeded(&device, 3, || {
                let hooks: Vec<Tensor<3>> = (0..4)
                    .map(|_| {
                        let d = burn::tensor::Distribution::Default;
                        Tensor::<3>::random([2, 108, 16], d, &device)
                    })
                    .collect();
                let d = burn::tensor::Distribution::Default;
                (
                    hooks,
                    Tensor::<4>::random([2, PAIR_CHANNELS, 96, 72], d, &device),
                )
            });
            let out = dec.forward(hooks, Some(input));
            assert_eq!(out.normal.dims(), [2, 1, 96, 72]);
            assert_eq!(out.flow.dims(), [2, 2, 96, 72]);
            let n: Vec<f32> = out.normal.into_data().try_to_vec().unwrap();
            let f: Vec<f32> = out.flow.into_data().try_to_vec().unwrap();
            assert!(n.iter().all(|v| *v > 0.0 && *v < 1.0));
            assert!(f.iter().all(|v| v.abs() <= 3.0));
        }
    }
}
