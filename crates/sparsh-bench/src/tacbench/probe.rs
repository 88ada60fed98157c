//! Training a task head on an encoder: the attentive probe on frozen tokens, or the same head
//! on a ViT trained with it from scratch (the end-to-end baseline). The epoch scored on the
//! test split is the one best on the validation split — never chosen on test, the defect of the
//! official notebook.

use burn::module::{Module, Param};
use burn::optim::{AdamWConfig, GradientsParams};
use burn::prelude::*;
use sparsh_ssl::data::HostBatch;
use sparsh_ssl::device::seeded_module;
use sparsh_ssl::probe::{AttentiveProbe, AttentiveProbeConfig};
use sparsh_ssl::rng::Rng;
use sparsh_ssl::vit::Vit;

use super::tasks::{Head, Metric, Sample, score};

/// Rows (indices into the task's samples) of the three splits.
#[derive(Debug, Clone, PartialEq)]
pub struct Split {
    /// Labelled training rows (the budget's share).
    pub train: Vec<usize>,
    /// Validation rows: the epoch is chosen on them.
    pub val: Vec<usize>,
    /// Test rows: scored once, with the chosen epoch.
    pub test: Vec<usize>,
    /// Seen-shape test rows (in distribution; may be empty), scored as `test`.
    pub seen: Vec<usize>,
}

/// Training settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitOptions {
    /// Passes over the training rows.
    pub epochs: usize,
    /// Batch size.
    pub batch_size: usize,
    /// Peak learning rate (AdamW, weight decay 0.01, half-cosine decay to 0).
    pub lr: f64,
    /// Seed of the head's initial draw and of the batch order.
    pub seed: u64,
    /// Stop after this many epochs without a better validation score (0: run every epoch).
    pub patience: usize,
}

/// The outcome of one training.
#[derive(Debug, Clone, PartialEq)]
pub struct Fit {
    /// Epoch (from 1) whose model was scored on test.
    pub best_epoch: usize,
    /// The validation metric after each epoch.
    pub val_curve: Vec<f64>,
    /// Decoded predictions for the test rows, in their order.
    pub test_preds: Vec<Vec<f64>>,
    /// Decoded predictions for the seen-shape test rows, in their order.
    pub seen_preds: Vec<Vec<f64>>,
}

/// Frozen tokens of every sample, `[samples, tokens, dim]` row-major.
#[derive(Debug, Clone)]
pub struct Tokens {
    /// Values.
    pub values: Vec<f32>,
    /// `[samples, tokens, dim]`.
    pub dims: [usize; 3],
}

impl Tokens {
    /// Standardizes every (token, feature) with its mean and standard deviation over the rows
    /// `pool` (the training split's samples: their images, not their labels, so every budget
    /// shares the statistics).
    pub fn standardize(&mut self, pool: &[usize]) {
        let [_, t, d] = self.dims;
        RowStats::of(&self.values, t * d, pool).apply(&mut self.values);
    }
}

/// Per-position mean and inverse standard deviation over rows of equal length: a frozen
/// encoder's tokens vary across samples by a small fraction of their size, so probes and
/// decoders read them standardized with statistics of the training samples.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RowStats {
    /// Mean per position.
    pub mean: Vec<f64>,
    /// Inverse standard deviation per position (the deviation floored at 1e-6).
    pub inv_std: Vec<f64>,
}

impl RowStats {
    /// Statistics of the rows `pool` of `values`, cut into rows of `row` values.
    pub fn of(values: &[f32], row: usize, pool: &[usize]) -> Self {
        let n = pool.len().max(1) as f64;
        let mut mean = vec![0.0f64; row];
        let mut var = vec![0.0f64; row];
        for &i in pool {
            for (m, &v) in mean.iter_mut().zip(&values[i * row..(i + 1) * row]) {
                *m += v as f64 / n;
            }
        }
        for &i in pool {
            for ((s, &v), &m) in var
                .iter_mut()
                .zip(&values[i * row..(i + 1) * row])
                .zip(&mean)
            {
                *s += (v as f64 - m).powi(2) / n;
            }
        }
        Self {
            mean,
            inv_std: var.iter().map(|v| 1.0 / v.sqrt().max(1e-6)).collect(),
        }
    }

    /// Standardizes every row of `values` in place.
    pub fn apply(&self, values: &mut [f32]) {
        for sample in values.chunks_mut(self.mean.len()) {
            for ((v, &m), &s) in sample.iter_mut().zip(&self.mean).zip(&self.inv_std) {
                *v = ((*v as f64 - m) * s) as f32;
            }
        }
    }
}

/// The input of a model for some rows, on a device.
type Input<'a> = dyn Fn(&[usize], &Device) -> Tensor<3> + Sync + 'a;

/// Trains the attentive probe (Sparsh's TacBench head, [`AttentiveProbe`]) on frozen `tokens`,
/// on `device` (the head drawn on the CPU under `opts.seed`, then moved).
pub fn fit_frozen(
    tokens: &Tokens,
    samples: &[Sample],
    head: &Head,
    classes: usize,
    split: &Split,
    opts: FitOptions,
    device: &Device,
) -> Fit {
    let [_, t, d] = tokens.dims;
    let input = |rows: &[usize], device: &Device| {
        let x: Vec<f32> = rows
            .iter()
            .flat_map(|&i| tokens.values[i * t * d..(i + 1) * t * d].iter().copied())
            .collect();
        Tensor::<1>::from_floats(x.as_slice(), device).reshape([rows.len(), t, d])
    };
    let probe = new_probe(d, head, classes, opts.seed, &Device::flex().autodiff());
    fit(
        probe,
        &input,
        &|m: &AttentiveProbe, x| m.forward(x),
        samples,
        head,
        classes,
        split,
        opts,
        device,
    )
}

/// The encoder and the probe head trained together.
#[derive(Module, Debug)]
pub struct EndToEnd {
    /// The ViT.
    pub encoder: Vit,
    /// The attentive probe on its tokens.
    pub head: AttentiveProbe,
}

/// Trains `encoder` (a fresh draw) together with the attentive probe on the images of the
/// training rows: the end-to-end baseline of the same capacity. `images` assembles the
/// unaugmented input batch of some rows. Trained on `device`; `encoder` and the head are drawn
/// on the CPU (the head under `opts.seed`) and moved.
#[allow(clippy::too_many_arguments)]
pub fn fit_end_to_end(
    encoder: Vit,
    images: &(dyn Fn(&[usize]) -> HostBatch + Sync),
    samples: &[Sample],
    head: &Head,
    classes: usize,
    split: &Split,
    opts: FitOptions,
    device: &Device,
) -> Fit {
    let d = encoder.dim();
    let probe = new_probe(d, head, classes, opts.seed, &Device::flex().autodiff());
    let model = EndToEnd {
        encoder,
        head: probe,
    };
    // the images stay 5-D: pass them flattened through the 3-D input and reshape inside
    let shape = images(&split.train[..1]).shape;
    let [_, frames, channels, h, w] = shape;
    let rows = statistics_rows(&split.train);
    let standardizer = Standardizer::fit(
        frames * channels,
        h * w,
        rows.chunks(32).map(|chunk| images(chunk).values),
    );
    let input = |rows: &[usize], device: &Device| {
        let mut b = images(rows);
        standardizer.apply(&mut b.values);
        Tensor::<1>::from_floats(b.values.as_slice(), device).reshape([
            rows.len(),
            1,
            b.values.len() / rows.len(),
        ])
    };
    let forward = move |m: &EndToEnd, x: Tensor<3>| {
        let [n, _, _] = x.dims();
        let [_, f, c, h, w] = shape;
        let tokens = m.encoder.forward(x.reshape([n, f, c, h, w]), None).patches;
        m.head.forward(tokens)
    };
    fit(
        model, &input, &forward, samples, head, classes, split, opts, device,
    )
}

/// Each input channel standardized by its mean and standard deviation over training inputs:
/// what the end-to-end model and the ceiling CNN read. Background-subtracted frames sit at a
/// constant with a contact's change a few hundredths of it (a tenth of the gel pressed), which
/// a fresh network passes on buried under its biases and, in a ViT, the position embedding,
/// where the frozen probes read tokens standardized on their pool.
pub(super) struct Standardizer {
    /// Values per channel plane.
    plane: usize,
    /// Per channel: its mean.
    mean: Vec<f32>,
    /// Per channel: one over its standard deviation (1e6 at most).
    scale: Vec<f32>,
}

impl Standardizer {
    /// Statistics of `inputs`, each the values of whole samples laid out `[channels, plane]`
    /// (any number of samples one after another).
    pub(super) fn fit(
        channels: usize,
        plane: usize,
        inputs: impl Iterator<Item = Vec<f32>>,
    ) -> Self {
        let (mut sum, mut squares, mut count) = (
            vec![0.0f64; channels],
            vec![0.0f64; channels],
            vec![0.0f64; channels],
        );
        for values in inputs {
            for (k, &v) in values.iter().enumerate() {
                let c = (k / plane) % channels;
                sum[c] += v as f64;
                squares[c] += (v as f64) * (v as f64);
                count[c] += 1.0;
            }
        }
        let mean: Vec<f64> = sum
            .iter()
            .zip(&count)
            .map(|(s, n)| s / n.max(1.0))
            .collect();
        let scale = squares
            .iter()
            .zip(&count)
            .zip(&mean)
            .map(|((q, n), m)| {
                let variance = (q / n.max(1.0) - m * m).max(0.0);
                (1.0 / variance.sqrt().max(1e-6)) as f32
            })
            .collect();
        Standardizer {
            plane,
            mean: mean.iter().map(|&m| m as f32).collect(),
            scale,
        }
    }

    /// Standardizes `values` (whole samples, laid out as in [`Standardizer::fit`]) in place.
    pub(super) fn apply(&self, values: &mut [f32]) {
        let channels = self.mean.len();
        for (k, v) in values.iter_mut().enumerate() {
            let c = (k / self.plane) % channels;
            *v = (*v - self.mean[c]) * self.scale[c];
        }
    }
}

/// At most this many training rows, evenly spaced, give a [`Standardizer`]'s statistics.
const STANDARDIZE_ROWS: usize = 256;

/// Training rows for the statistics: at most [`STANDARDIZE_ROWS`], evenly spaced.
pub(super) fn statistics_rows(train: &[usize]) -> Vec<usize> {
    let step = train.len().div_ceil(STANDARDIZE_ROWS).max(1);
    train.iter().copied().step_by(step).collect()
}

/// A fresh attentive probe for `head` on `d`-wide tokens, drawn from `seed`, its output bias
/// set to [`Head::force_bias`] when the head has one.
fn new_probe(d: usize, head: &Head, classes: usize, seed: u64, device: &Device) -> AttentiveProbe {
    let mut probe = seeded_module(device, seed, || {
        AttentiveProbeConfig::new(d, heads_for(d))
            .with_outputs(head.outputs(classes))
            .init(device)
    });
    if let Some(bias) = force_bias(head, device) {
        probe.fc2.bias = Some(bias);
    }
    probe
}

/// The output bias that starts a force head at the training mean ([`Head::force_bias`]), on
/// `device`; `None` for heads without one.
pub(super) fn force_bias(head: &Head, device: &Device) -> Option<Param<Tensor<1>>> {
    let b = head.force_bias?;
    let bias: Vec<f32> = b.iter().map(|&v| v as f32).collect();
    Some(Param::from_tensor(Tensor::from_floats(
        bias.as_slice(),
        device,
    )))
}

/// Heads of the probe's attention: one per 64 features (12 for ViT-base as the official
/// probe), else one.
fn heads_for(d: usize) -> usize {
    if d.is_multiple_of(64) { d / 64 } else { 1 }
}

/// The training loop the fits share, on `device` (`model` is moved there).
#[allow(clippy::too_many_arguments)]
pub(super) fn fit<M: Module + Clone>(
    model: M,
    input: &Input<'_>,
    forward: &(dyn Fn(&M, Tensor<3>) -> Tensor<2> + Sync),
    samples: &[Sample],
    head: &Head,
    classes: usize,
    split: &Split,
    opts: FitOptions,
    device: &Device,
) -> Fit {
    let plain = device.clone().inner();
    let device = device.clone().inner().autodiff();
    let mut model = sparsh_ssl::device::on_device(model, &device);
    let width = head.target_width(classes);
    let targets = |rows: &[usize]| {
        let t: Vec<f32> = rows
            .iter()
            .flat_map(|&i| head.encode(&samples[i].target, classes))
            .collect();
        Tensor::<1>::from_floats(t.as_slice(), &device).reshape([rows.len(), width])
    };
    let metric: Metric = head.kind.metrics()[0];
    let predict = |m: &M, rows: &[usize]| -> Vec<Vec<f64>> {
        let valid = m.valid();
        let mut out = Vec::with_capacity(rows.len());
        for chunk in rows.chunks(64) {
            let y = forward(&valid, input(chunk, &plain))
                .into_data()
                .convert::<f32>()
                .try_into_vec::<f32>()
                .expect("f32 outputs");
            let k = y.len() / chunk.len();
            out.extend(y.chunks(k).map(|r| head.decode(r)));
        }
        out
    };
    let mut optim = AdamWConfig::new().with_weight_decay(0.01).init();
    let steps_per_epoch = split.train.len().div_ceil(opts.batch_size).max(1);
    let total = (opts.epochs * steps_per_epoch) as f64;
    let mut step = 0usize;
    let mut best: Option<(f64, usize, M)> = None;
    let mut val_curve = Vec::with_capacity(opts.epochs);
    let mut all_preds = vec![Vec::new(); samples.len()];
    for epoch in 0..opts.epochs {
        let order = Rng::for_step(opts.seed, epoch as u64, 7).permutation(split.train.len());
        for chunk in order.chunks(opts.batch_size) {
            let rows: Vec<usize> = chunk.iter().map(|&k| split.train[k]).collect();
            let loss = head.loss(forward(&model, input(&rows, &device)), targets(&rows));
            let grads = GradientsParams::from_grads(loss.backward(), &model);
            let lr = 0.5 * opts.lr * (1.0 + (std::f64::consts::PI * step as f64 / total).cos());
            model = optim.step(lr, model, grads);
            step += 1;
        }
        let preds = predict(&model, &split.val);
        for (&i, p) in split.val.iter().zip(preds) {
            all_preds[i] = p;
        }
        let value = score(metric, &split.val, &all_preds, samples);
        val_curve.push(value);
        // a non-finite validation score never wins over a finite one
        let better = match &best {
            None => true,
            Some((b, _, _)) if !b.is_finite() => value.is_finite(),
            Some((b, _, _)) => {
                if metric.higher_is_better() {
                    value > *b
                } else {
                    value < *b
                }
            }
        };
        if better {
            best = Some((value, epoch + 1, model.clone()));
        }
        let since_best = epoch + 1 - best.as_ref().map_or(0, |b| b.1);
        if opts.patience > 0 && since_best >= opts.patience {
            break;
        }
    }
    let (_, best_epoch, chosen) = best.expect("at least one epoch");
    Fit {
        best_epoch,
        val_curve,
        test_preds: predict(&chosen, &split.test),
        seen_preds: predict(&chosen, &split.seen),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tacbench::tasks::{Target, TaskKind};

    /// One token per sample carries the force (scaled by 3) along features 0–2 and a marker along
    /// feature 3, at a random place, over noise elsewhere.
    fn localized(
        rng: &mut Rng,
        n: usize,
        t: usize,
        d: usize,
        informative: bool,
    ) -> (Tokens, Vec<Sample>) {
        let mut values = Vec::with_capacity(n * t * d);
        let mut samples = Vec::with_capacity(n);
        for i in 0..n {
            let f = [
                rng.range_f64(-1.0, 1.0),
                rng.range_f64(-1.0, 1.0),
                rng.range_f64(0.2, 2.0),
            ];
            let at = rng.below(t);
            for k in 0..t {
                for j in 0..d {
                    let signal = match (informative && k == at, j) {
                        (true, 0..=2) => 3.0 * f.get(j).copied().unwrap_or(0.0),
                        (true, 3) => 2.0, // marks the token
                        _ => 0.0,
                    };
                    values.push((signal + rng.range_f64(-0.1, 0.1)) as f32);
                }
            }
            samples.push(Sample {
                sequence: i / 4,
                frame: i % 4,
                target: Target::Force(f),
            });
        }
        (
            Tokens {
                values,
                dims: [n, t, d],
            },
            samples,
        )
    }

    #[test]
    fn the_probe_reads_force_from_informative_tokens_and_picks_the_epoch_on_validation() {
        let mut rng = Rng::new(3);
        let (n, t, d) = (400, 8, 16);
        let rows: Vec<usize> = (0..n).collect();
        let split = Split {
            train: rows.iter().copied().filter(|i| i % 5 < 3).collect(),
            val: rows.iter().copied().filter(|i| i % 5 == 3).collect(),
            test: rows.iter().copied().filter(|i| i % 5 == 4).collect(),
            seen: Vec::new(),
        };
        let opts = FitOptions {
            epochs: 40,
            batch_size: 32,
            lr: 1e-3,
            seed: 1,
            patience: 0,
        };
        let score_of = |tokens: &mut Tokens, samples: &[Sample]| {
            tokens.standardize(&split.train);
            let refs: Vec<&Sample> = split.train.iter().map(|&i| &samples[i]).collect();
            let head = Head::new(TaskKind::Force, 0, [4.0, 4.0, 5.0], &refs);
            let fit = fit_frozen(tokens, samples, &head, 0, &split, opts, &Device::flex());
            let mut preds = vec![Vec::new(); samples.len()];
            for (&i, p) in split.test.iter().zip(&fit.test_preds) {
                preds[i] = p.clone();
            }
            // the chosen epoch is the best on validation
            let best = fit.val_curve.iter().copied().fold(f64::INFINITY, f64::min);
            assert_eq!(fit.val_curve[fit.best_epoch - 1], best);
            crate::tacbench::tasks::score(Metric::RmseMn, &split.test, &preds, samples)
        };
        // the constant predictor: the training mean
        let constant = |samples: &[Sample]| {
            let mut m = [0.0; 3];
            for &i in &split.train {
                if let Target::Force(f) = samples[i].target {
                    (0..3).for_each(|k| m[k] += f[k] / split.train.len() as f64);
                }
            }
            let preds = vec![m.to_vec(); samples.len()];
            crate::tacbench::tasks::score(Metric::RmseMn, &split.test, &preds, samples)
        };
        let (mut tokens, samples) = localized(&mut rng, n, t, d, true);
        let (read, mean) = (score_of(&mut tokens, &samples), constant(&samples));
        assert!(
            read < 0.7 * mean,
            "informative tokens: {read} mN vs the mean's {mean}"
        );
        let (mut noise, samples) = localized(&mut rng, n, t, d, false);
        let (read, mean) = (score_of(&mut noise, &samples), constant(&samples));
        assert!(read > 0.9 * mean, "noise: {read} mN vs the mean's {mean}");
    }

    #[test]
    fn standardized_tokens_have_zero_mean_and_unit_spread_over_the_pool() {
        let mut t = Tokens {
            values: vec![1.0, 10.0, 3.0, 10.0, 100.0, -5.0],
            dims: [3, 1, 2],
        };
        t.standardize(&[0, 1]);
        // feature 0 over rows 0, 1: mean 2, sd 1; feature 1 constant (sd floored): centred only
        assert_eq!(&t.values[..4], &[-1.0, 0.0, 1.0, 0.0]);
        assert_eq!(t.values[4], 98.0);
    }

    #[test]
    fn a_standardizer_gives_each_channel_zero_mean_and_unit_spread() {
        // two samples of two channels on planes of 3 values: channel 0 holds 1, 2, …, 6 over
        // the samples (mean 3.5, deviation √(35/12)), channel 1 is 10 everywhere but one 16
        let samples = vec![
            vec![1.0, 2.0, 3.0, 10.0, 10.0, 16.0],
            vec![4.0, 5.0, 6.0, 10.0, 10.0, 10.0],
        ];
        let s = Standardizer::fit(2, 3, samples.clone().into_iter());
        let mut both: Vec<f32> = samples.concat();
        s.apply(&mut both);
        let sd0 = (35.0f32 / 12.0).sqrt();
        assert!((both[0] - (1.0 - 3.5) / sd0).abs() < 1e-5, "{both:?}");
        assert!((both[7] - (5.0 - 3.5) / sd0).abs() < 1e-5, "{both:?}");
        // channel 1: mean 11, deviation √5 (one 16 among six values)
        assert!((both[5] - 5.0 / 5f32.sqrt()).abs() < 1e-5, "{both:?}");
        assert!((both[3] + 1.0 / 5f32.sqrt()).abs() < 1e-5, "{both:?}");
        for c in 0..2 {
            let v: Vec<f32> = both
                .chunks(3)
                .enumerate()
                .filter(|(k, _)| k % 2 == c)
                .flat_map(|(_, p)| p.to_vec())
                .collect();
            let mean = v.iter().sum::<f32>() / 6.0;
            let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f32>() / 6.0;
            assert!(
                mean.abs() < 1e-5 && (var - 1.0).abs() < 1e-4,
                "{c}: {mean} {var}"
            );
        }
        // a constant channel is centred, not blown up to infinity
        let mut flat = vec![2.0f32; 3];
        Standardizer::fit(1, 3, std::iter::once(flat.clone())).apply(&mut flat);
        assert_eq!(flat, vec![0.0; 3]);
    }
}
