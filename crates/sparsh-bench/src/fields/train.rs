//! Training the field decoder on a frozen encoder's hooked tokens, self-supervised (the T1A
//! recipe) or supervised by the ground truth (the ceiling), and predicting with it.

use burn::module::Module;
use burn::optim::{AdamWConfig, GradientsParams};
use burn::prelude::*;
use sparsh_ssl::rng::Rng;

use crate::tacbench::probe::RowStats;
use sparsh_ssl::device::seeded_module;
use sparsh_ssl::vit::Vit;

use super::data::{FramePairs, Pair, PairTruth};
use super::dpt::{FieldDecoder, FieldDecoderConfig, PAIR_CHANNELS, hook_blocks};
use super::loss::{LossWeights, Shading, normal_loss, shear_loss};

/// Hooked token maps of a frozen encoder for a list of pairs.
#[derive(Debug, Clone)]
pub struct HookTokens {
    /// Values `[pairs, hooks, tokens, dim]`, row-major.
    pub values: Vec<f32>,
    /// The shape.
    pub dims: [usize; 4],
    /// The encoder's inputs `I_t ⊕ I_{t−k}` of every row, `[pairs, PAIR_CHANNELS, height, width]`
    /// row-major, which the decoder's image skip reads; empty when not kept.
    pub inputs: Vec<f32>,
    /// `[height, width]` of the inputs.
    pub input_size: [usize; 2],
}

impl HookTokens {
    /// Tokens without their inputs (for a decoder without the image skip).
    pub fn without_inputs(values: Vec<f32>, dims: [usize; 4]) -> Self {
        Self {
            values,
            dims,
            inputs: Vec::new(),
            input_size: [0, 0],
        }
    }

    /// The four `[rows, tokens, dim]` maps of some rows and, for `decoder`'s image skip, their
    /// inputs `[rows, PAIR_CHANNELS, height, width]`, on `device`.
    fn batch(
        &self,
        rows: &[usize],
        decoder: &FieldDecoder,
        device: &Device,
    ) -> (Vec<Tensor<3>>, Option<Tensor<4>>) {
        let [_, k, t, d] = self.dims;
        let inputs = decoder.image_skip.is_some().then(|| {
            let [h, w] = self.input_size;
            let n = PAIR_CHANNELS * h * w;
            let x: Vec<f32> = rows
                .iter()
                .flat_map(|&i| self.inputs[i * n..(i + 1) * n].iter().copied())
                .collect();
            Tensor::<1>::from_floats(x.as_slice(), device).reshape([
                rows.len(),
                PAIR_CHANNELS,
                h,
                w,
            ])
        });
        let hooks = (0..k)
            .map(|h| {
                let x: Vec<f32> = rows
                    .iter()
                    .flat_map(|&i| {
                        let at = (i * k + h) * t * d;
                        self.values[at..at + t * d].iter().copied()
                    })
                    .collect();
                Tensor::<1>::from_floats(x.as_slice(), device).reshape([rows.len(), t, d])
            })
            .collect();
        (hooks, inputs)
    }
}

/// Per (hook, token, feature) statistics of hooked tokens over the training pairs
/// ([`RowStats`]): the decoder reads standardized tokens, as the TacBench probe does.
pub type TokenStats = RowStats;

/// Floor of a position's standard deviation, as a fraction of the median over positions: a
/// token position that barely varies in training (a patch no training contact reached) is not
/// blown up on a test frame that does touch it.
pub const POOLED_DEVIATION_FLOOR: f64 = 0.1;

impl HookTokens {
    /// The statistics of every row, each position's deviation floored at
    /// [`POOLED_DEVIATION_FLOOR`] times the median deviation over positions.
    pub fn stats(&self) -> TokenStats {
        let [n, k, t, d] = self.dims;
        let mut stats = RowStats::of(&self.values, k * t * d, &(0..n).collect::<Vec<_>>());
        let mut deviations: Vec<f64> = stats.inv_std.iter().map(|s| 1.0 / s).collect();
        deviations.sort_by(f64::total_cmp);
        let floor = POOLED_DEVIATION_FLOOR * deviations[deviations.len() / 2];
        if floor > 0.0 {
            for s in &mut stats.inv_std {
                *s = s.min(1.0 / floor);
            }
        }
        stats
    }

    /// Standardizes every row with `stats`.
    pub fn standardize(&mut self, stats: &TokenStats) {
        stats.apply(&mut self.values);
    }
}

/// Runs the frozen encoder over the pairs on `device` and keeps the tokens of its hooked blocks
/// ([`hook_blocks`]).
pub fn encode_hooks(vit: &Vit, data: &FramePairs, pairs: &[Pair], device: &Device) -> HookTokens {
    encode_inputs(vit, data.size(), pairs.len(), device, |rows| {
        data.pair_inputs(pairs, &rows.collect::<Vec<_>>())
    })
}

/// Runs the frozen encoder over `n` samples of `size` (`[height, width]`), whose inputs
/// `I_t ⊕ I_{t−k}` (`[6, height, width]` each, concatenated) `input` assembles for a range of
/// samples, and keeps the tokens of its hooked blocks ([`hook_blocks`]) and the inputs (for the
/// decoder's image skip). Computed on `device`
/// (the encoder is moved there if it lives elsewhere).
pub fn encode_inputs(
    vit: &Vit,
    size: [usize; 2],
    n: usize,
    device: &Device,
    input: impl Fn(std::ops::Range<usize>) -> Vec<f32>,
) -> HookTokens {
    // an encoder drawn on the autodiff device would record (and keep) every activation
    let device = device.clone().inner();
    let vit = sparsh_ssl::device::on_device(vit.valid(), &device);
    let hooks = hook_blocks(vit.blocks.len());
    let [h, w] = size;
    let (mut values, mut dims) = (Vec::new(), [n, hooks.len(), 0, vit.dim()]);
    let mut inputs = Vec::with_capacity(n * PAIR_CHANNELS * h * w);
    for start in (0..n).step_by(32) {
        let rows = start..(start + 32).min(n);
        let chunk = input(rows.clone());
        inputs.extend_from_slice(&chunk);
        let x = Tensor::<1>::from_floats(chunk.as_slice(), &device).reshape([
            rows.len(),
            1,
            PAIR_CHANNELS,
            h,
            w,
        ]);
        let maps = vit.forward_hooks(x, &hooks);
        dims[2] = maps[0].dims()[1];
        values.extend(
            Tensor::stack::<4>(maps, 1)
                .into_data()
                .convert::<f32>()
                .try_into_vec::<f32>()
                .expect("f32 tokens"),
        );
    }
    HookTokens {
        values,
        dims,
        inputs,
        input_size: size,
    }
}

/// The trained model: decoder and, for the self-supervised normal branch, its shading.
#[derive(Module, Debug)]
pub struct FieldModel {
    /// The DPT decoder.
    pub decoder: FieldDecoder,
    /// Slope → colour change (unused by the supervised ceiling).
    pub shading: Shading,
}

/// Training settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrainOptions {
    /// Optimizer steps.
    pub steps: usize,
    /// Pairs per step.
    pub batch_size: usize,
    /// Peak learning rate (AdamW, weight decay 1e-4, half-cosine to 0).
    pub lr: f64,
    /// Seed of the initial draw and of the batch order.
    pub seed: u64,
    /// Loss weights.
    pub weights: LossWeights,
    /// Self-supervised: the shear loss reads only the pairs of gels that print markers (the
    /// photometric loss scores the gel's true flow lowest only where the gel carries texture
    /// that moves with it).
    pub shear_on_markers: bool,
}

/// Ground-truth targets of the supervised models (the decoder's ceiling and the U-Net).
#[derive(Debug, Clone)]
pub struct Targets {
    /// Per pair: pressure over `pressure_scale_kpa`, clipped to [0, 1].
    pub normal: Vec<Vec<f32>>,
    /// Per pair: flow (input pixels), interleaved x, y per pixel.
    pub flow: Vec<Vec<[f32; 2]>>,
    /// Per pair: each pixel's loss weight, `1 + contact_weight` in contact and 1 outside.
    pub weight: Vec<Vec<f32>>,
    /// The pressure that maps to 1 (the 95th percentile of the training pressures in contact).
    pub pressure_scale_kpa: f64,
}

impl Targets {
    /// Targets from the truths of the training pairs; pixels in contact weigh
    /// `1 + contact_weight` in the loss (a contact covers a few per cent of a frame: with equal
    /// weights the squared error is mostly the empty gel's).
    pub fn new(truths: &[PairTruth], contact_weight: f64) -> Self {
        let mut inside: Vec<f32> = truths
            .iter()
            .flat_map(|t| {
                t.pressure_kpa
                    .iter()
                    .zip(&t.contact)
                    .filter(|(_, c)| **c)
                    .map(|(p, _)| *p)
            })
            .collect();
        inside.sort_by(f32::total_cmp);
        let scale = inside
            .get(inside.len() * 95 / 100)
            .map_or(1.0, |&p| (p as f64).max(1e-6));
        Self {
            normal: truths
                .iter()
                .map(|t| {
                    t.pressure_kpa
                        .iter()
                        .map(|&p| (p as f64 / scale).clamp(0.0, 1.0) as f32)
                        .collect()
                })
                .collect(),
            flow: truths.iter().map(|t| t.flow_px.clone()).collect(),
            weight: truths
                .iter()
                .map(|t| {
                    t.contact
                        .iter()
                        .map(|&c| if c { 1.0 + contact_weight as f32 } else { 1.0 })
                        .collect()
                })
                .collect(),
            pressure_scale_kpa: scale,
        }
    }

    /// The weighted squared errors of `normal` (`[b, 1, h, w]`) and `flow` (`[b, 2, h, w]`)
    /// against the targets of `rows`: `Σ w·(D − D*)² / Σ w` and the same over both flow
    /// components (halved), the normal and shear terms apart. With `contact_weight` 0 they are
    /// the plain mean squared errors, the conditional mean of the map and the flow.
    pub fn loss(
        &self,
        normal: Tensor<4>,
        flow: Tensor<4>,
        rows: &[usize],
        device: &Device,
    ) -> (Tensor<1>, Tensor<1>) {
        let [b, _, h, w] = normal.dims();
        let gather = |f: &dyn Fn(usize) -> Vec<f32>, channels: usize| {
            let v: Vec<f32> = rows.iter().flat_map(|&i| f(i)).collect();
            Tensor::<1>::from_floats(v.as_slice(), device).reshape([b, channels, h, w])
        };
        let tn = gather(&|i| self.normal[i].clone(), 1);
        let tf = gather(
            &|i| {
                let f = &self.flow[i];
                f.iter()
                    .map(|v| v[0])
                    .chain(f.iter().map(|v| v[1]))
                    .collect()
            },
            2,
        );
        let weight = gather(&|i| self.weight[i].clone(), 1);
        let total = weight.clone().sum();
        let normal_term = ((normal - tn).powi_scalar(2) * weight.clone()).sum() / total.clone();
        let flow_term = ((flow - tf).powi_scalar(2) * weight).sum() / (total * 2.0);
        (normal_term, flow_term)
    }
}

/// What a decoder learns from.
#[derive(Debug, Clone, Copy)]
pub enum Signal<'a> {
    /// The frames of the pairs (self-supervised; no field is read).
    Frames {
        /// The data.
        data: &'a FramePairs,
        /// The pairs, one per row of the tokens.
        pairs: &'a [Pair],
    },
    /// Ground-truth targets, one per row of the tokens (the supervised ceiling): squared error
    /// on the normal map and the flow, weighted towards the contact ([`Targets::loss`]; a
    /// squared error, as an absolute one regresses sparse contacts and small flows to their
    /// median, 0).
    Fields(&'a Targets),
}

/// Trains a decoder on `tokens` from `signal`, on `device` (the model drawn on the CPU under
/// `opts.seed` and moved). Returns the model (on `device`, without autodiff) and the loss of
/// every step.
pub fn train(
    tokens: &HookTokens,
    signal: Signal<'_>,
    config: &FieldDecoderConfig,
    opts: TrainOptions,
    device: &Device,
    progress: &dyn Fn(usize, f64),
) -> (FieldModel, Vec<f64>) {
    let cpu = Device::flex().autodiff();
    let model = seeded_module(&cpu, opts.seed, || FieldModel {
        decoder: config.init(&cpu),
        shading: Shading::new(&cpu),
    });
    let device = device.clone().inner().autodiff();
    let mut model = sparsh_ssl::device::on_device(model, &device);
    let [h, w] = config.img_size;
    let frames = |data: &FramePairs, pairs: &[Pair], rows: &[usize], back: bool| {
        let v: Vec<f32> = rows
            .iter()
            .flat_map(|&i| {
                let (now, before) = data.frames(pairs[i]);
                if back { before } else { now }.iter().copied()
            })
            .collect();
        Tensor::<1>::from_floats(v.as_slice(), &device).reshape([rows.len(), 3, h, w])
    };
    let mut optim = AdamWConfig::new().with_weight_decay(1e-4).init();
    let mut curve = Vec::with_capacity(opts.steps);
    let n = tokens.dims[0];
    let mut order: Vec<usize> = Vec::new();
    let mut cursor = 0;
    let mut epoch = 0u64;
    for step in 0..opts.steps {
        let mut rows = Vec::with_capacity(opts.batch_size);
        while rows.len() < opts.batch_size.min(n) {
            if cursor == order.len() {
                order = Rng::for_step(opts.seed, epoch, 11).permutation(n);
                epoch += 1;
                cursor = 0;
            }
            rows.push(order[cursor]);
            cursor += 1;
        }
        let (hooks, inputs) = tokens.batch(&rows, &model.decoder, &device);
        let out = model.decoder.forward(hooks, inputs);
        let loss = match signal {
            Signal::Frames { data, pairs } => {
                let now = frames(data, pairs, &rows, false);
                let normal = normal_loss(out.normal, now.clone(), &model.shading, &opts.weights);
                let sheared: Vec<usize> = (0..rows.len())
                    .filter(|&k| {
                        !opts.shear_on_markers
                            || data.sequences[pairs[rows[k]].sequence].has_markers()
                    })
                    .collect();
                if sheared.len() == rows.len() {
                    normal
                        + shear_loss(
                            out.flow,
                            now,
                            frames(data, pairs, &rows, true),
                            &opts.weights,
                        )
                } else if sheared.is_empty() {
                    normal
                } else {
                    let picked: Vec<usize> = sheared.iter().map(|&k| rows[k]).collect();
                    let index = Tensor::<1, Int>::from_ints(
                        sheared
                            .iter()
                            .map(|&k| k as i64)
                            .collect::<Vec<_>>()
                            .as_slice(),
                        &device,
                    );
                    normal
                        + shear_loss(
                            out.flow.select(0, index),
                            frames(data, pairs, &picked, false),
                            frames(data, pairs, &picked, true),
                            &opts.weights,
                        )
                }
            }
            Signal::Fields(t) => {
                let (normal, flow) = t.loss(out.normal, out.flow, &rows, &device);
                normal + flow
            }
        };
        let value = loss.clone().into_scalar::<f32>() as f64;
        curve.push(value);
        progress(step, value);
        let grads = GradientsParams::from_grads(loss.backward(), &model);
        let lr =
            0.5 * opts.lr * (1.0 + (std::f64::consts::PI * step as f64 / opts.steps as f64).cos());
        model = optim.step(lr, model, grads);
    }
    (model.valid(), curve)
}

/// A decoder's prediction for one pair.
#[derive(Debug, Clone, PartialEq)]
pub struct Prediction {
    /// Normal map, `height × width`.
    pub normal: Vec<f32>,
    /// Flow per pixel (input pixels).
    pub flow: Vec<[f32; 2]>,
}

impl Prediction {
    /// The predictions of a batch: `normal` `[b, 1, h, w]` and `flow` `[b, 2, h, w]`.
    pub fn of_batch(normal: Tensor<4>, flow: Tensor<4>) -> Vec<Self> {
        let [b, _, h, w] = normal.dims();
        let values = |t: Tensor<4>| -> Vec<f32> {
            t.into_data().convert::<f32>().try_into_vec().expect("f32")
        };
        let (normal, flow) = (values(normal), values(flow));
        let n = h * w;
        (0..b)
            .map(|i| {
                let fx = &flow[(2 * i) * n..(2 * i + 1) * n];
                let fy = &flow[(2 * i + 1) * n..(2 * i + 2) * n];
                Prediction {
                    normal: normal[i * n..(i + 1) * n].to_vec(),
                    flow: fx.iter().zip(fy).map(|(&x, &y)| [x, y]).collect(),
                }
            })
            .collect()
    }
}

/// Predictions for every row of `tokens`, computed on the device `model` lives on.
pub fn predict(model: &FieldModel, tokens: &HookTokens) -> Vec<Prediction> {
    let device = sparsh_ssl::device::device_of(model).inner();
    let rows: Vec<usize> = (0..tokens.dims[0]).collect();
    let mut out = Vec::with_capacity(rows.len());
    for chunk in rows.chunks(16) {
        let (hooks, inputs) = tokens.batch(chunk, &model.decoder, &device);
        let y = model.decoder.forward(hooks, inputs);
        out.extend(Prediction::of_batch(y.normal, y.flow));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fields::loss::LossWeights;

    /// The supervised decoder learns a map it can read from the tokens: one token per sample
    /// is marked, the target normal map is 1 under that token's patch.
    #[test]
    fn the_supervised_decoder_localizes_a_marked_token() {
        let (gh, gw, d, p) = (4usize, 3usize, 16usize, 4usize);
        let (h, w) = (gh * p, gw * p);
        let n = 48;
        let mut rng = Rng::new(5);
        let mut values = Vec::new();
        let mut normal = Vec::new();
        for _ in 0..n {
            let at = rng.below(gh * gw);
            for _hook in 0..4 {
                for t in 0..gh * gw {
                    for j in 0..d {
                        let v = if t == at && j < 4 { 2.0 } else { 0.0 };
                        values.push(v + rng.range_f64(-0.1, 0.1) as f32);
                    }
                }
            }
            let (r, c) = (at / gw, at % gw);
            normal.push(
                (0..h * w)
                    .map(|i| ((i / w) / p == r && (i % w) / p == c) as u8 as f32)
                    .collect::<Vec<f32>>(),
            );
        }
        let tokens = HookTokens::without_inputs(values, [n, 4, gh * gw, d]);
        let targets = Targets {
            normal,
            flow: vec![vec![[0.0; 2]; h * w]; n],
            weight: vec![vec![1.0; h * w]; n],
            pressure_scale_kpa: 1.0,
        };
        let cfg = FieldDecoderConfig::new(d, [gh, gw], [h, w]).with_channels(16);
        let opts = TrainOptions {
            steps: 300,
            batch_size: 8,
            lr: 3e-3,
            seed: 0,
            weights: LossWeights::default(),
            shear_on_markers: false,
        };
        let (model, curve) = train(
            &tokens,
            Signal::Fields(&targets),
            &cfg,
            opts,
            &Device::flex(),
            &|_, _| {},
        );
        assert!(curve[curve.len() - 1] < 0.2 * curve[0], "{curve:?}");
        let preds = predict(&model, &tokens);
        let mut ious = Vec::new();
        for (pr, t) in preds.iter().zip(&targets.normal) {
            let mask: Vec<bool> = t.iter().map(|v| *v > 0.5).collect();
            ious.push(super::super::metrics::iou(&pr.normal, 0.5, &mask).unwrap_or(0.0));
        }
        let mean = ious.iter().sum::<f64>() / n as f64;
        assert!(mean > 0.5, "mean IoU {mean}");
    }

    /// The supervised loss against a hand computation: on a 1 × 2 map with one pixel in
    /// contact (weight 1 + 3) the normal term is (4·0.5² + 1·0.2²)/5 and the flow term
    /// (4·(1² + 0²) + 1·(0² + 2²))/(2·5); with no weight, the plain means.
    #[test]
    fn the_supervised_loss_weighs_the_contact_as_computed_by_hand() {
        let truth = PairTruth {
            pressure_kpa: vec![10.0, 0.0],
            indentation_mm: vec![0.0; 2],
            contact: vec![true, false],
            shear_traction_kpa: vec![0.0; 2],
            flow_px: vec![[1.0, 0.0], [0.0, 0.0]],
        };
        let device = Device::flex();
        let normal =
            Tensor::<1>::from_floats([0.5f32, 0.2].as_slice(), &device).reshape([1, 1, 1, 2]);
        let flow = Tensor::<1>::from_floats([0.0f32, 0.0, 0.0, 2.0].as_slice(), &device)
            .reshape([1, 2, 1, 2]);
        for (weight, want) in [
            (3.0, [(4.0 * 0.25 + 0.04) / 5.0, (4.0 * 1.0 + 4.0) / 10.0]),
            (0.0, [(0.25 + 0.04) / 2.0, (1.0 + 4.0) / 4.0]),
        ] {
            let targets = Targets::new(std::slice::from_ref(&truth), weight);
            assert_eq!(targets.normal[0], [1.0, 0.0]);
            let (n, f) = targets.loss(normal.clone(), flow.clone(), &[0], &device);
            let got = [n.into_scalar::<f32>() as f64, f.into_scalar::<f32>() as f64];
            for (g, w) in got.iter().zip(want) {
                assert!(
                    (g - w).abs() < 1e-6,
                    "weight {weight}: {got:?} against {want:?}"
                );
            }
        }
    }

    /// The image skip reads what the tokens do not show: the tokens are noise, the target is a
    /// 4 × 4 square at a random place of the input's first channel. With the skip the supervised
    /// decoder finds it on samples it was not trained on; without, it cannot.
    #[test]
    fn the_image_skip_reads_a_contact_the_tokens_do_not_show() {
        let (gh, gw, d, h, w) = (4usize, 3usize, 8usize, 16usize, 12usize);
        let mut rng = Rng::new(9);
        let mut samples = |n: usize| {
            let values: Vec<f32> = (0..n * 4 * gh * gw * d)
                .map(|_| rng.range_f64(-1.0, 1.0) as f32)
                .collect();
            let (mut inputs, mut normal) = (Vec::new(), Vec::new());
            for _ in 0..n {
                let (r, c) = (rng.below(h - 4), rng.below(w - 4));
                let square: Vec<f32> = (0..h * w)
                    .map(|i| {
                        let inside = (r..r + 4).contains(&(i / w)) && (c..c + 4).contains(&(i % w));
                        inside as u8 as f32
                    })
                    .collect();
                inputs.extend(square.iter().copied());
                inputs.extend(std::iter::repeat_n(0.0, (PAIR_CHANNELS - 1) * h * w));
                normal.push(square);
            }
            let tokens = HookTokens {
                values,
                dims: [n, 4, gh * gw, d],
                inputs,
                input_size: [h, w],
            };
            (tokens, normal)
        };
        let (train_tokens, normal) = samples(32);
        let (test_tokens, test_normal) = samples(16);
        let targets = Targets {
            normal,
            flow: vec![vec![[0.0; 2]; h * w]; 32],
            weight: vec![vec![1.0; h * w]; 32],
            pressure_scale_kpa: 1.0,
        };
        let opts = TrainOptions {
            steps: 200,
            batch_size: 8,
            lr: 3e-3,
            seed: 0,
            weights: LossWeights::default(),
            shear_on_markers: false,
        };
        // mean prediction on the square minus off it, over the test samples
        let contrast = |skip: bool| {
            let cfg = FieldDecoderConfig::new(d, [gh, gw], [h, w])
                .with_channels(8)
                .with_image_skip(skip);
            let signal = Signal::Fields(&targets);
            let device = Device::flex();
            let (model, _) = train(&train_tokens, signal, &cfg, opts, &device, &|_, _| {});
            let (mut on, mut off) = ((0.0, 0.0), (0.0, 0.0));
            for (p, t) in predict(&model, &test_tokens).iter().zip(&test_normal) {
                for (v, inside) in p.normal.iter().zip(t) {
                    let sum = if *inside > 0.5 { &mut on } else { &mut off };
                    *sum = (sum.0 + *v as f64, sum.1 + 1.0);
                }
            }
            on.0 / on.1 - off.0 / off.1
        };
        let (with, without) = (contrast(true), contrast(false));
        assert!(with > 0.25, "with the skip: contrast {with}");
        assert!(without < 0.1, "without the skip: contrast {without}");
    }

    /// A blob shaded by its slope (as the gel under a LED) moving half a pixel per frame.
    fn moving_blob(h: usize, w: usize, frames: usize) -> Vec<Vec<f32>> {
        (0..frames)
            .map(|t| {
                let (cx, cy) = (4.0 + 0.5 * t as f32, 7.0);
                let mut out = vec![0.0f32; 3 * h * w];
                for y in 0..h {
                    for x in 0..w {
                        let (dx, dy) = (x as f32 - cx, y as f32 - cy);
                        let g = (-(dx * dx + dy * dy) / 8.0).exp();
                        let (gx, gy) = (-dx / 4.0 * g, -dy / 4.0 * g);
                        for (c, (a, b)) in
                            [(1.0, 0.0), (-0.5, 0.8), (-0.5, -0.8)].iter().enumerate()
                        {
                            out[(c * h + y) * w + x] = 0.5 + 0.3 * (a * gx + b * gy);
                        }
                    }
                }
                out
            })
            .collect()
    }

    /// With the shear loss on marker gels only, a markerless training set leaves the shear
    /// head where it was drawn (no gradient reaches it), while the normal head trains; on every
    /// pair, the shear head moves.
    #[test]
    fn the_shear_loss_on_marker_gels_reads_no_markerless_pair() {
        let (data, tokens) = blob_pairs();
        let cfg = FieldDecoderConfig::new(16, [4, 3], [16, 12]).with_channels(8);
        let head = |h: &crate::fields::dpt::DenseHead| -> Vec<f32> {
            h.conv3
                .weight
                .val()
                .into_data()
                .convert::<f32>()
                .try_into_vec()
                .unwrap()
        };
        let cpu = Device::flex().autodiff();
        let drawn = seeded_module(&cpu, 0, || FieldModel {
            decoder: cfg.init(&cpu),
            shading: Shading::new(&cpu),
        });
        for markers_only in [true, false] {
            let opts = TrainOptions {
                steps: 3,
                batch_size: 4,
                lr: 1e-3,
                seed: 0,
                weights: LossWeights::default(),
                shear_on_markers: markers_only,
            };
            let signal = Signal::Frames {
                data: &data,
                pairs: &data.train,
            };
            let (model, _) = train(&tokens, signal, &cfg, opts, &Device::flex(), &|_, _| {});
            let shear_same = head(&model.decoder.shear) == head(&drawn.decoder.shear);
            let normal_same = head(&model.decoder.normal) == head(&drawn.decoder.normal);
            assert_eq!(shear_same, markers_only, "markers only: {markers_only}");
            assert!(!normal_same);
        }
    }

    /// A blob moving over 8 frames of 16 × 12 (no markers), its pairs `(t, t − 2)` and random
    /// tokens for them.
    fn blob_pairs() -> (FramePairs, HookTokens) {
        use crate::fields::geometry::InputGeometry;
        use sparsh_ssl::data::{Dataset, Sequence};
        use std::sync::Arc;
        let (h, w, offset) = (16usize, 12usize, 2usize);
        let frames: Vec<_> = moving_blob(h, w, 8).into_iter().map(Arc::new).collect();
        let pairs: Vec<Pair> = (offset..8).map(|t| Pair { sequence: 0, t }).collect();
        let data = FramePairs {
            dir: std::path::PathBuf::new(),
            dataset: Dataset {
                sequences: vec![Sequence {
                    frames: Sequence::decoded(frames),
                    forces: None,
                    rest_frame: None,
                }],
                size: [h, w],
            },
            sequences: vec![super::super::data::SequenceInfo {
                test: false,
                seen_test: false,
                family: "blob".into(),
                frame_index: (0..8).collect(),
                mm_per_px: Some(0.1),
                markers_px: vec![Vec::new(); 8],
                geometry: InputGeometry::new(w, h, [h, w]),
            }],
            offset,
            train: pairs.clone(),
            test: Vec::new(),
            seen: Vec::new(),
        };
        let mut rng = Rng::new(2);
        let tokens = HookTokens::without_inputs(
            (0..pairs.len() * 4 * 12 * 16)
                .map(|_| rng.range_f64(-1.0, 1.0) as f32)
                .collect(),
            [pairs.len(), 4, 12, 16],
        );
        (data, tokens)
    }

    /// One optimizer step on the normal loss lowers it, and one on the shear loss lowers it.
    #[test]
    fn one_step_lowers_each_self_supervised_loss() {
        use crate::fields::loss::{normal_loss, shear_loss};
        let (h, w) = (16usize, 12usize);
        let (data, tokens) = blob_pairs();
        let pairs = data.train.clone();
        let cfg = FieldDecoderConfig::new(16, [4, 3], [h, w]).with_channels(8);
        let device = Device::flex().autodiff();
        let rows: Vec<usize> = (0..pairs.len()).collect();
        let image = |back: bool| {
            let v: Vec<f32> = pairs
                .iter()
                .flat_map(|&p| {
                    let (now, before) = data.frames(p);
                    if back { before } else { now }
                        .iter()
                        .copied()
                        .collect::<Vec<_>>()
                })
                .collect();
            Tensor::<1>::from_floats(v.as_slice(), &device).reshape([pairs.len(), 3, h, w])
        };
        let weights = LossWeights::default();
        let losses = |m: &FieldModel| {
            let (hooks, inputs) = tokens.batch(&rows, &m.decoder, &device);
            let out = m.decoder.forward(hooks, inputs);
            (
                normal_loss(out.normal, image(false), &m.shading, &weights),
                shear_loss(out.flow, image(false), image(true), &weights),
            )
        };
        for which in 0..2 {
            let model = seeded_module(&device, 3, || FieldModel {
                decoder: cfg.init(&device),
                shading: Shading::new(&device),
            });
            let pick = |m: &FieldModel| {
                let (n, s) = losses(m);
                if which == 0 { n } else { s }
            };
            let before = pick(&model);
            let grads = GradientsParams::from_grads(before.backward(), &model);
            let before: f32 = pick(&model).into_scalar();
            let mut optim = AdamWConfig::new().init();
            let model = optim.step(1e-3, model, grads);
            let after: f32 = pick(&model).into_scalar();
            assert!(after < before, "loss {which}: {before} → {after}");
        }
    }

    #[test]
    fn standardized_tokens_have_zero_mean_and_unit_spread() {
        let mut t = HookTokens::without_inputs(vec![1.0, 10.0, 3.0, 10.0, 5.0, 10.0], [3, 1, 1, 2]);
        let stats = t.stats();
        t.standardize(&stats);
        let f0: Vec<f32> = t.values.iter().step_by(2).copied().collect();
        let sd = (8.0f32 / 3.0).sqrt();
        for (got, want) in f0.iter().zip([-2.0 / sd, 0.0, 2.0 / sd]) {
            assert!((got - want).abs() < 1e-5, "{f0:?}");
        }
        // a constant feature is centred, not blown up
        assert!(t.values.iter().skip(1).step_by(2).all(|v| *v == 0.0));
        // and a test row that moves it is scaled by the pooled floor (a tenth of the median
        // deviation, here feature 0's), not by its own zero deviation
        let mut test = HookTokens::without_inputs(vec![3.0, 11.0], [1, 1, 1, 2]);
        test.standardize(&stats);
        let want = 1.0 / (POOLED_DEVIATION_FLOOR as f32 * sd);
        assert!((test.values[1] - want).abs() < 1e-4, "{:?}", test.values);
    }

    /// A decoder saved with `save_file` and loaded onto a fresh draw predicts what it did.
    #[test]
    fn a_saved_decoder_loads_back_unchanged() {
        let device = Device::flex();
        let cfg = FieldDecoderConfig::new(16, [4, 3], [16, 12]).with_channels(8);
        let a = seeded_module(&device, 1, || FieldModel {
            decoder: cfg.init(&device),
            shading: Shading::new(&device),
        });
        let b = seeded_module(&device, 2, || FieldModel {
            decoder: cfg.init(&device),
            shading: Shading::new(&device),
        });
        let tokens = HookTokens::without_inputs(
            (0..2 * 4 * 12 * 16)
                .map(|i| ((i * 37) % 11) as f32 / 11.0)
                .collect(),
            [2, 4, 12, 16],
        );
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("d.bpk");
        a.clone().save_file(&path).unwrap();
        let loaded = b.clone().try_load_file(&path).unwrap();
        let (pa, pb, pl) = (
            predict(&a, &tokens),
            predict(&b, &tokens),
            predict(&loaded, &tokens),
        );
        assert_ne!(pa, pb, "two draws differ");
        assert_eq!(pa, pl, "the loaded decoder is the saved one");
    }
}
