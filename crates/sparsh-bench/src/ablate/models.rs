//! The learned contact-circle regressors: a small convolutional network on the difference image,
//! and Sparsh's attentive probe on a frozen encoder's tokens. Both regress the circle's centre
//! and radius standardized with the training circles' statistics (squared error, the centre
//! weighted to count in the radius' pixels, `CircleScale::loss_weights`), AdamW with a half-cosine
//! learning rate, and keep the epoch best on a validation split the real frames never enter.

use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{Linear, LinearConfig, PaddingConfig2d};
use burn::optim::{AdamWConfig, GradientsParams};
use burn::prelude::*;
use burn::tensor::activation::{relu, softmax};
use burn::tensor::module::avg_pool2d;
use burn::tensor::ops::AvgPoolOptions;
use sparsh_ssl::rng::Rng;

use super::data::Circle;

/// A small fully convolutional network (≈ 0.04 M parameters). The `[3, h, w]` difference image
/// is averaged 2 × 2 and passed through four 3 × 3 convolutions with ReLU (the first of stride
/// 2, the last two dilated). The centre is the soft-argmax of a 1 × 1 convolution's map (the expected cell
/// position under its softmax, Nibali et al. 2018), the radius an MLP of the globally averaged
/// features: both are translation-equivariant or -invariant by construction, so a position is
/// never memorised from the training set's layout.
#[derive(Module, Debug)]
pub struct CircleCnn {
    /// Convolutions.
    pub convs: Vec<Conv2d>,
    /// The centre's score map.
    pub heat: Conv2d,
    /// Hidden layer of the radius MLP.
    pub fc1: Linear,
    /// Radius output.
    pub fc2: Linear,
}

/// Channels, strides and dilations of the CNN's convolutions: the last two see ±5 and ±9 cells
/// of a quarter-resolution map, wider than the largest contact.
const CNN_LAYERS: [(usize, usize, usize); 4] = [(16, 2, 1), (32, 1, 1), (32, 1, 2), (32, 1, 4)];

impl CircleCnn {
    /// A fresh network.
    pub fn new(device: &Device) -> Self {
        let mut convs = Vec::new();
        let mut cin = 3;
        for (c, stride, dilation) in CNN_LAYERS {
            convs.push(
                Conv2dConfig::new([cin, c], [3, 3])
                    .with_stride([stride, stride])
                    .with_dilation([dilation, dilation])
                    .with_padding(PaddingConfig2d::Explicit(
                        dilation, dilation, dilation, dilation,
                    ))
                    .init(device),
            );
            cin = c;
        }
        CircleCnn {
            convs,
            heat: Conv2dConfig::new([cin, 1], [1, 1]).init(device),
            fc1: LinearConfig::new(cin, 32).init(device),
            fc2: LinearConfig::new(32, 1).init(device),
        }
    }

    /// `[n, 3, h, w]` difference images (8-bit levels) → `[n, 3]`: the centre in normalized
    /// image coordinates (−1 … 1 from the first pixel's left edge to the last one's right edge)
    /// and the standardized radius.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<2> {
        let mut x = avg_pool2d(x / 32.0, AvgPoolOptions::new([2, 2]));
        for conv in &self.convs {
            x = relu(conv.forward(x));
        }
        let [n, c, h, w] = x.dims();
        let device = x.device();
        let p = softmax(self.heat.forward(x.clone()).reshape([n, h * w]), 1);
        let ramp = |k: usize| -> Vec<f32> {
            (0..k)
                .map(|i| 2.0 * (i as f32 + 0.5) / k as f32 - 1.0)
                .collect()
        };
        let us = Tensor::<1>::from_floats(ramp(w).as_slice(), &device)
            .reshape([1, w])
            .repeat_dim(0, h)
            .reshape([1, h * w]);
        let vs = Tensor::<1>::from_floats(ramp(h).as_slice(), &device)
            .reshape([h, 1])
            .repeat_dim(1, w)
            .reshape([1, h * w]);
        let u = (p.clone() * us).sum_dim(1);
        let v = (p * vs).sum_dim(1);
        let pooled = x.mean_dim(3).mean_dim(2).reshape([n, c]);
        let r = self.fc2.forward(relu(self.fc1.forward(pooled)));
        Tensor::cat(vec![u, v, r], 1)
    }
}

/// Training settings of a regressor.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainOptions {
    /// Passes over the training frames.
    pub epochs: usize,
    /// Batch size.
    pub batch_size: usize,
    /// Peak learning rate (AdamW, weight decay 0.01, half-cosine decay to 0).
    pub lr: f64,
}

/// The regression targets of a circle: its centre in normalized image coordinates (−1 … 1
/// across the frame) and its radius standardized with the training circles' mean and deviation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CircleScale {
    /// Frame `[width, height]` (pixels of the circles).
    size: [f64; 2],
    /// Mean circle of the training set.
    mean: Circle,
    /// Deviation of the training radii (floored at 1 px).
    radius_sd: f64,
}

impl CircleScale {
    /// The statistics of `circles` on a `size` = `[width, height]` frame.
    pub fn of(circles: &[Circle], size: [usize; 2]) -> Self {
        let n = circles.len().max(1) as f64;
        let mean = Circle {
            cx_px: circles.iter().map(|c| c.cx_px).sum::<f64>() / n,
            cy_px: circles.iter().map(|c| c.cy_px).sum::<f64>() / n,
            r_px: circles.iter().map(|c| c.r_px).sum::<f64>() / n,
        };
        let var = circles
            .iter()
            .map(|c| (c.r_px - mean.r_px).powi(2))
            .sum::<f64>()
            / n;
        CircleScale {
            size: size.map(|v| v as f64),
            mean,
            radius_sd: var.sqrt().max(1.0),
        }
    }

    /// The mean circle (the constant predictor).
    pub fn mean(&self) -> Circle {
        self.mean
    }

    fn encode(&self, c: &Circle) -> [f32; 3] {
        [
            (2.0 * (c.cx_px + 0.5) / self.size[0] - 1.0) as f32,
            (2.0 * (c.cy_px + 0.5) / self.size[1] - 1.0) as f32,
            ((c.r_px - self.mean.r_px) / self.radius_sd) as f32,
        ]
    }

    /// Weights of the encoded errors in the loss: the centre's normalized coordinates times
    /// half the frame over the radius deviation, so each of centre x, centre y and radius
    /// counts its error in the same pixels (unweighted, a centre off by one radius deviation
    /// would cost (2σ_r/width)² of what the radius off by as much costs).
    fn loss_weights(&self) -> [f32; 3] {
        [
            (self.size[0] / 2.0 / self.radius_sd) as f32,
            (self.size[1] / 2.0 / self.radius_sd) as f32,
            1.0,
        ]
    }

    fn decode(&self, z: &[f32]) -> Circle {
        Circle {
            cx_px: (z[0] as f64 + 1.0) * self.size[0] / 2.0 - 0.5,
            cy_px: (z[1] as f64 + 1.0) * self.size[1] / 2.0 - 0.5,
            r_px: (self.mean.r_px + self.radius_sd * z[2] as f64).max(0.0),
        }
    }
}

/// A model's forward pass on some rows of its data (the closure builds the input batch).
pub type Forward<'a, M> = dyn Fn(&M, &[usize], &Device) -> Tensor<2> + Sync + 'a;

/// A trained regressor: the model of the chosen epoch and how to read its outputs.
pub struct Fitted<M> {
    /// The model (valid mode).
    pub model: M,
    /// The target standardization.
    pub scale: CircleScale,
    /// Epoch (from 1) kept.
    pub best_epoch: usize,
    /// Its predictions of the validation rows, in their order.
    pub val_preds: Vec<Circle>,
}

impl<M: Module + Clone> Fitted<M> {
    /// Predicted circles of `rows` (fed to `forward`).
    pub fn predict(&self, forward: &Forward<'_, M>, rows: &[usize]) -> Vec<Circle> {
        predict(&self.model, &self.scale, forward, rows)
    }
}

/// Predictions of `model`, computed where it lives.
fn predict<M: Module + Clone>(
    model: &M,
    scale: &CircleScale,
    forward: &Forward<'_, M>,
    rows: &[usize],
) -> Vec<Circle> {
    let valid = model.valid();
    let device = sparsh_ssl::device::device_of(&valid);
    let mut out = Vec::with_capacity(rows.len());
    for chunk in rows.chunks(64) {
        let y = forward(&valid, chunk, &device)
            .into_data()
            .convert::<f32>()
            .try_into_vec::<f32>()
            .expect("f32 outputs");
        out.extend(y.chunks(3).map(|z| scale.decode(z)));
    }
    out
}

/// Trains `model` on `train` (row, circle) pairs of a `size` = `[width, height]` frame; with
/// `val` rows, keeps the epoch of least validation MSE, else the last. Batches are drawn from
/// `seed`. Trained on `device` (`model`, drawn on the CPU, is moved there).
#[allow(clippy::too_many_arguments)]
pub fn fit<M: Module + Clone>(
    model: M,
    size: [usize; 2],
    forward: &Forward<'_, M>,
    train: &[(usize, Circle)],
    val: &[(usize, Circle)],
    opts: TrainOptions,
    seed: u64,
    device: &Device,
) -> Fitted<M> {
    let device = device.clone().inner().autodiff();
    let mut model = sparsh_ssl::device::on_device(model, &device);
    let circles: Vec<Circle> = train.iter().map(|t| t.1).collect();
    let scale = CircleScale::of(&circles, size);
    let targets = |pairs: &[&(usize, Circle)], device: &Device| {
        let t: Vec<f32> = pairs.iter().flat_map(|p| scale.encode(&p.1)).collect();
        Tensor::<1>::from_floats(t.as_slice(), device).reshape([pairs.len(), 3])
    };
    let weights = scale.loss_weights();
    let weight = Tensor::<1>::from_floats(weights.as_slice(), &device).reshape([1, 3]);
    let mut optim = AdamWConfig::new().with_weight_decay(0.01).init();
    let steps_per_epoch = train.len().div_ceil(opts.batch_size).max(1);
    let total = (opts.epochs * steps_per_epoch) as f64;
    let mut step = 0usize;
    let mut best: Option<(f64, usize, M, Vec<Circle>)> = None;
    for epoch in 0..opts.epochs {
        let order = Rng::for_step(seed, epoch as u64, 11).permutation(train.len());
        for chunk in order.chunks(opts.batch_size) {
            let pairs: Vec<&(usize, Circle)> = chunk.iter().map(|&k| &train[k]).collect();
            let rows: Vec<usize> = pairs.iter().map(|p| p.0).collect();
            let diff =
                (forward(&model, &rows, &device) - targets(&pairs, &device)) * weight.clone();
            let loss = (diff.clone() * diff).mean();
            let grads = GradientsParams::from_grads(loss.backward(), &model);
            let lr = 0.5 * opts.lr * (1.0 + (std::f64::consts::PI * step as f64 / total).cos());
            model = optim.step(lr, model, grads);
            step += 1;
        }
        if val.is_empty() {
            continue;
        }
        let rows: Vec<usize> = val.iter().map(|v| v.0).collect();
        let preds = predict(&model, &scale, forward, &rows);
        let mse = preds
            .iter()
            .zip(val)
            .map(|(p, v)| {
                let (a, b) = (scale.encode(p), scale.encode(&v.1));
                (0..3)
                    .map(|k| ((a[k] - b[k]) * weights[k]).powi(2) as f64)
                    .sum::<f64>()
            })
            .sum::<f64>()
            / val.len() as f64;
        if best.as_ref().is_none_or(|b| mse.is_finite() && mse < b.0) {
            best = Some((mse, epoch + 1, model.clone(), preds));
        }
    }
    let (model, best_epoch, val_preds) = match best {
        Some((_, e, m, p)) => (m, e, p),
        None => (model, opts.epochs, Vec::new()),
    };
    Fitted {
        model: model.valid(),
        scale,
        best_epoch,
        val_preds,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The disc images' height and width (px).
    const DISC_H: usize = 24;
    const DISC_W: usize = 32;

    /// `n` images (3 channels, row-major) each holding one bright disc drawn at random under
    /// `seed`, and each image's index with its disc.
    fn discs(n: usize, seed: u64) -> (Vec<f32>, Vec<(usize, Circle)>) {
        let (h, w) = (DISC_H, DISC_W);
        let mut rng = Rng::new(seed);
        let mut images = vec![0.0f32; n * 3 * h * w];
        let mut pairs = Vec::new();
        for k in 0..n {
            let c = Circle {
                cx_px: rng.range_f64(8.0, 24.0),
                cy_px: rng.range_f64(7.0, 17.0),
                r_px: rng.range_f64(3.0, 6.0),
            };
            for y in 0..h {
                for x in 0..w {
                    if (x as f64 - c.cx_px).hypot(y as f64 - c.cy_px) <= c.r_px {
                        for ch in 0..3 {
                            images[((k * 3 + ch) * h + y) * w + x] = 40.0 * (ch + 1) as f32;
                        }
                    }
                }
            }
            pairs.push((k, c));
        }
        (images, pairs)
    }

    /// The CNN's forward pass on the disc images of `rows`.
    fn disc_forward(
        images: &[f32],
    ) -> impl Fn(&CircleCnn, &[usize], &Device) -> Tensor<2> + Sync + '_ {
        let (h, w) = (DISC_H, DISC_W);
        move |m: &CircleCnn, rows: &[usize], device: &Device| {
            let x: Vec<f32> = rows
                .iter()
                .flat_map(|&k| images[k * 3 * h * w..(k + 1) * 3 * h * w].iter().copied())
                .collect();
            m.forward(Tensor::<1>::from_floats(x.as_slice(), device).reshape([rows.len(), 3, h, w]))
        }
    }

    #[test]
    fn the_scale_round_trips_and_its_mean_is_the_average_circle() {
        let circles = [
            Circle {
                cx_px: 100.0,
                cy_px: 50.0,
                r_px: 40.0,
            },
            Circle {
                cx_px: 300.0,
                cy_px: 70.0,
                r_px: 60.0,
            },
        ];
        let s = CircleScale::of(&circles, [640, 480]);
        assert_eq!(
            s.mean(),
            Circle {
                cx_px: 200.0,
                cy_px: 60.0,
                r_px: 50.0
            }
        );
        let back = s.decode(&s.encode(&circles[1]));
        assert!((back.cx_px - 300.0).abs() < 1e-3 && (back.r_px - 60.0).abs() < 1e-3);
        // the frame's edges are ±1, its middle 0
        assert_eq!(s.encode(&circles[0])[2], -1.0);
        let mid = Circle {
            cx_px: 319.5,
            cy_px: -0.5,
            r_px: 50.0,
        };
        assert_eq!(s.encode(&mid)[..2], [0.0, -1.0]);
        // Weighted, a centre 5 px off along x, along y, and a radius 5 px off cost the same:
        // 5 px over the radii's deviation of 10 px.
        let w = s.loss_weights();
        let off = |dx: f64, dy: f64, dr: f64| {
            let (a, b) = (
                s.encode(&circles[1]),
                s.encode(&Circle {
                    cx_px: 300.0 + dx,
                    cy_px: 70.0 + dy,
                    r_px: 60.0 + dr,
                }),
            );
            (0..3).map(|k| ((b[k] - a[k]) * w[k]).powi(2)).sum::<f32>()
        };
        for cost in [off(5.0, 0.0, 0.0), off(0.0, 5.0, 0.0), off(0.0, 0.0, 5.0)] {
            assert!((cost - 0.25).abs() < 1e-4, "{cost}");
        }
    }

    /// Bright discs on a flat image: the CNN must find where and how large they are, far better
    /// than the mean circle, on discs it never saw.
    #[test]
    fn the_cnn_locates_discs_it_was_not_trained_on() {
        let (h, w) = (DISC_H, DISC_W);
        let (images, pairs) = discs(320, 5);
        let device = Device::flex().autodiff();
        let model = sparsh_ssl::device::seeded_module(&device, 3, || CircleCnn::new(&device));
        let forward = disc_forward(&images);
        let (train, test) = pairs.split_at(256);
        let opts = TrainOptions {
            epochs: 30,
            batch_size: 32,
            lr: 3e-3,
        };
        let fitted = fit(
            model,
            [w, h],
            &forward,
            train,
            &test[..32],
            opts,
            1,
            &Device::flex(),
        );
        let rows: Vec<usize> = test[32..].iter().map(|t| t.0).collect();
        let preds = fitted.predict(&forward, &rows);
        let err = |p: &[Circle]| -> f64 {
            p.iter()
                .zip(&test[32..])
                .map(|(p, t)| (p.cx_px - t.1.cx_px).hypot(p.cy_px - t.1.cy_px))
                .sum::<f64>()
                / p.len() as f64
        };
        let mean = vec![fitted.scale.mean(); rows.len()];
        let (learned, constant) = (err(&preds), err(&mean));
        assert!(
            learned < 0.3 * constant,
            "centre error {learned:.2} px vs the mean circle's {constant:.2}"
        );
    }

    /// Trained on wgpu (Mesa's lavapipe here, a software Vulkan driver), the CNN drawn on the
    /// CPU under the same seed keeps the CPU's epoch and predicts its circles to within
    /// rounding. Skipped without an adapter unless SPARSH_REQUIRE_GPU=1.
    #[test]
    fn the_cnn_trained_on_wgpu_predicts_the_cpu_circles() {
        use sparsh_ssl::device::{DeviceKind, Devices};
        let gpu = match Devices::choose(DeviceKind::Wgpu, &[]) {
            Ok(d) => d.main().clone(),
            Err(e) if std::env::var("SPARSH_REQUIRE_GPU").is_ok_and(|v| v == "1") => {
                panic!("SPARSH_REQUIRE_GPU=1 and {e}")
            }
            Err(e) => {
                eprintln!("skipped: {e}");
                return;
            }
        };
        let (h, w) = (DISC_H, DISC_W);
        let (images, pairs) = discs(48, 7);
        let forward = disc_forward(&images);
        let (train, rest) = pairs.split_at(32);
        let (val, test) = rest.split_at(8);
        let opts = TrainOptions {
            epochs: 3,
            batch_size: 8,
            lr: 3e-3,
        };
        let rows: Vec<usize> = test.iter().map(|t| t.0).collect();
        let run = |device: &Device| {
            let cpu = Device::flex().autodiff();
            let model = sparsh_ssl::device::seeded_module(&cpu, 3, || CircleCnn::new(&cpu));
            let t0 = std::time::Instant::now();
            let fitted = fit(model, [w, h], &forward, train, val, opts, 1, device);
            let preds = fitted.predict(&forward, &rows);
            eprintln!("{device:?}: {:.1} s", t0.elapsed().as_secs_f64());
            (fitted.best_epoch, fitted.val_preds, preds)
        };
        let (a, b) = (run(&Device::flex()), run(&gpu));
        assert_eq!(a.0, b.0, "epoch chosen");
        let worst =
            a.1.iter()
                .chain(&a.2)
                .zip(b.1.iter().chain(&b.2))
                .map(|(p, q)| {
                    (p.cx_px - q.cx_px)
                        .abs()
                        .max((p.cy_px - q.cy_px).abs())
                        .max((p.r_px - q.r_px).abs())
                })
                .fold(0f64, f64::max);
        eprintln!("circles differ by up to {worst:.2e} px");
        assert!(worst <= 1e-2, "circles differ by {worst:.2e} px");
    }
}
