//! Online force probe of a frozen encoder, fitted on training sequences and scored on held-out
//! ones: an attentive probe after Sparsh's TacBench decoder (one learned query cross-attending
//! over the tokens, then an MLP; Sparsh paper §5, a simplified V-JEPA `AttentivePooler` without
//! its second MLP block), and a linear (ridge) read-out of the mean-pooled tokens.

use burn::module::{Module, Param};
use burn::nn::{LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::optim::{AdamWConfig, GradientsParams};
use burn::prelude::*;
use burn::tensor::module::attention;
use burn::tensor::ops::AttentionModuleOptions;

use crate::Error;
use crate::data::{AugmentConfig, HostBatch, Sampler};
use crate::kernels::gelu;
use crate::rng::Rng;
use crate::vit::{LN_EPS, Vit};

/// Labelled, unaugmented samples for the probe, split by sequence.
#[derive(Debug, Clone)]
pub struct ProbeSet {
    batches: Vec<HostBatch>,
    test: Vec<bool>,
    forces: Vec<[f64; 3]>,
}

/// The probe's scores on the held-out samples, in mN.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeScore {
    /// RMSE over all three axes of the attentive probe (of the ridge read-out when the
    /// attentive probe is off).
    pub rmse_mn: f64,
    /// RMSE over all three axes of the ridge read-out of the mean-pooled tokens.
    pub linear_mn: f64,
    /// RMSE of predicting the training mean (what a useless encoder scores).
    pub baseline_mn: f64,
    /// Spread of the pooled features across samples: the standard deviation over samples,
    /// averaged over feature dimensions (near 0 when the encoder has collapsed to a constant).
    pub feature_std: f64,
    /// Effective number of directions the tokens vary along from frame to frame:
    /// [`content_rank`] of the tokens (1 to the width; low when the encoder has collapsed
    /// onto a few dimensions).
    pub feature_rank: f64,
}

impl ProbeSet {
    /// Up to `max` evenly spaced labelled samples; every fifth sequence is held out (every fifth
    /// sample when there are fewer than five labelled sequences), and of the others an evenly
    /// spaced `label_fraction` is kept for fitting (the label budget). `None` when the data
    /// carry no force labels or too few samples; an error when a frame cannot be read.
    pub fn new(
        sampler: &Sampler,
        max: usize,
        chunk: usize,
        label_fraction: f64,
    ) -> Result<Option<Self>, Error> {
        let labelled: Vec<usize> = (0..sampler.samples.len())
            .filter(|&i| {
                sampler.data().sequences[sampler.samples[i].0]
                    .forces
                    .is_some()
            })
            .collect();
        if labelled.len() < 10 || max < 10 {
            return Ok(None);
        }
        let stride = labelled.len().div_ceil(max);
        let picks: Vec<usize> = labelled.into_iter().step_by(stride).collect();
        let seqs: std::collections::BTreeSet<usize> =
            picks.iter().map(|&i| sampler.samples[i].0).collect();
        let test: Vec<bool> = picks
            .iter()
            .enumerate()
            .map(|(k, &i)| {
                if seqs.len() >= 5 {
                    sampler.samples[i].0 % 5 == 4
                } else {
                    k % 5 == 4
                }
            })
            .collect();
        // the budget: training rows whose running share crosses a multiple of `label_fraction`
        let mut train_seen = 0usize;
        let (picks, test): (Vec<usize>, Vec<bool>) = picks
            .into_iter()
            .zip(test)
            .filter(|&(_, t)| {
                if t {
                    return true;
                }
                let keep = ((train_seen + 1) as f64 * label_fraction).floor()
                    > (train_seen as f64 * label_fraction).floor();
                train_seen += 1;
                keep
            })
            .unzip();
        if test.iter().all(|&t| t) || !test.iter().any(|&t| t) {
            return Ok(None);
        }
        let batches: Vec<HostBatch> = picks
            .chunks(chunk.max(1))
            .map(|c| sampler.batch(c, &AugmentConfig::none(), 0, 0))
            .collect::<Result<_, _>>()?;
        let forces = batches
            .iter()
            .flat_map(|b| b.forces.clone().expect("labelled samples"))
            .map(|f| f.map(f64::from))
            .collect();
        Ok(Some(Self {
            batches,
            test,
            forces,
        }))
    }

    /// Samples the probes are fitted on and samples they are scored on.
    pub fn sizes(&self) -> (usize, usize) {
        let held_out = self.test.iter().filter(|&&t| t).count();
        (self.test.len() - held_out, held_out)
    }

    /// The attentive probe (as in [`ProbeSet::score`]) on the raw input patches instead of an
    /// encoder's tokens: the `patch`×`patch` squares of every frame and channel of a sample,
    /// flattened into one token each (no positions): what any encoder's tokens are up against.
    /// Trained on `device` (the probe drawn on the CPU under `seed` and moved).
    pub fn score_patches(
        &self,
        patch: usize,
        attentive_epochs: usize,
        seed: u64,
        device: &Device,
    ) -> f64 {
        let (tokens, dims) = self.patch_tokens(patch);
        attentive_score(
            &tokens,
            dims,
            &self.forces,
            &self.test,
            attentive_epochs,
            seed,
            device,
        )
    }

    /// Raw patches of every sample as tokens (see [`patch_tokens`]).
    fn patch_tokens(&self, patch: usize) -> (Vec<f32>, [usize; 3]) {
        let mut tokens = Vec::new();
        let mut dims = [0, 0, 0];
        for b in &self.batches {
            let (t, [n, k, d]) = patch_tokens(b, patch);
            tokens.extend(t);
            dims = [dims[0] + n, k, d];
        }
        (tokens, dims)
    }

    /// Fits and scores the probes on `encoder` (frozen; no gradients reach it): the ridge
    /// read-out always, the attentive probe trained for `attentive_epochs` epochs (seeded by
    /// `seed`) when that is above 0. Both run on the encoder's device.
    pub fn score(&self, encoder: &Vit, attentive_epochs: usize, seed: u64) -> ProbeScore {
        let enc = encoder.clone().valid();
        let device = crate::device::device_of(&enc);
        let (mut tokens, mut dims) = (Vec::new(), [0, 0, 0]);
        for b in &self.batches {
            let x = Tensor::<1>::from_floats(b.values.as_slice(), &device).reshape(b.shape);
            let out = enc.forward(x, None).patches;
            let [n, t, d] = out.dims();
            dims = [dims[0] + n, t, d];
            tokens.extend(
                out.into_data()
                    .convert::<f32>()
                    .try_to_vec::<f32>()
                    .expect("f32"),
            );
        }
        let [_, t, d] = dims;
        let pooled: Vec<Vec<f64>> = tokens
            .chunks(t * d)
            .map(|s| {
                (0..d)
                    .map(|j| (0..t).map(|k| s[k * d + j] as f64).sum::<f64>() / t as f64)
                    .collect()
            })
            .collect();
        let linear = ridge_score(&pooled, &self.forces, &self.test);
        let rmse_mn = if attentive_epochs > 0 {
            attentive_score(
                &tokens,
                dims,
                &self.forces,
                &self.test,
                attentive_epochs,
                seed,
                &device,
            )
        } else {
            linear.rmse_mn
        };
        ProbeScore {
            rmse_mn,
            linear_mn: linear.rmse_mn,
            baseline_mn: linear.baseline_mn,
            feature_std: feature_std(&pooled),
            feature_rank: content_rank(&tokens, dims),
        }
    }
}

/// The raw input patches of a batch as tokens, `[samples, (height/patch)·(width/patch),
/// frames·channels·patch²]` row-major: the patches in row-major grid order, each patch's values
/// in (frame, channel, row, column) order.
pub fn patch_tokens(batch: &HostBatch, patch: usize) -> (Vec<f32>, [usize; 3]) {
    let [n, f, c, h, w] = batch.shape;
    let (gh, gw) = (h / patch, w / patch);
    let d = f * c * patch * patch;
    let mut tokens = Vec::with_capacity(n * gh * gw * d);
    for sample in batch.values.chunks(f * c * h * w) {
        for gy in 0..gh {
            for gx in 0..gw {
                for plane in sample.chunks(h * w) {
                    for y in gy * patch..(gy + 1) * patch {
                        tokens.extend_from_slice(
                            &plane[y * w + gx * patch..y * w + (gx + 1) * patch],
                        );
                    }
                }
            }
        }
    }
    (tokens, [n, gh * gw, d])
}

/// Configuration of an [`AttentiveProbe`].
#[derive(Config, Debug)]
pub struct AttentiveProbeConfig {
    /// Token width.
    pub dim: usize,
    /// Attention heads.
    pub num_heads: usize,
    /// Outputs.
    #[config(default = 3)]
    pub outputs: usize,
}

/// The attentive probe, after TacBench's: a learned query cross-attends over the layer-normed
/// tokens (one multi-head attention with a residual; the official pooler's further MLP block is
/// left out), then a layer norm and an MLP D → D/4 → outputs.
#[derive(Module, Debug)]
pub struct AttentiveProbe {
    /// The learned query `[1, 1, dim]`.
    pub query: Param<Tensor<3>>,
    /// Norm of the tokens.
    pub norm: LayerNorm,
    /// Query projection.
    pub q: Linear,
    /// Key and value projection (`[dim, 2·dim]`).
    pub kv: Linear,
    /// Output projection of the attention.
    pub proj: Linear,
    /// Norm before the MLP.
    pub head_norm: LayerNorm,
    /// MLP hidden layer (D → D/4).
    pub fc1: Linear,
    /// MLP output layer.
    pub fc2: Linear,
    /// Heads.
    pub num_heads: usize,
}

impl AttentiveProbeConfig {
    /// Initialize an [`AttentiveProbe`] (`num_heads` must divide `dim`).
    pub fn init(&self, device: &Device) -> AttentiveProbe {
        let d = self.dim;
        assert!(
            self.num_heads > 0 && d.is_multiple_of(self.num_heads),
            "{} heads do not divide width {d}",
            self.num_heads
        );
        let norm = || LayerNormConfig::new(d).with_epsilon(LN_EPS).init(device);
        AttentiveProbe {
            query: Param::from_tensor(Tensor::random(
                [1, 1, d],
                burn::tensor::Distribution::Normal(0.0, 0.02),
                device,
            )),
            norm: norm(),
            q: LinearConfig::new(d, d).init(device),
            kv: LinearConfig::new(d, 2 * d).init(device),
            proj: LinearConfig::new(d, d).init(device),
            head_norm: norm(),
            fc1: LinearConfig::new(d, (d / 4).max(1)).init(device),
            fc2: LinearConfig::new((d / 4).max(1), self.outputs).init(device),
            num_heads: self.num_heads,
        }
    }
}

impl AttentiveProbe {
    /// Read-out of `[batch, tokens, dim]` tokens → `[batch, outputs]`.
    pub fn forward(&self, x: Tensor<3>) -> Tensor<2> {
        let [b, n, d] = x.dims();
        let h = self.num_heads;
        let query = self.query.val().repeat_dim(0, b);
        let q = self
            .q
            .forward(query.clone())
            .reshape([b, 1, h, d / h])
            .swap_dims(1, 2);
        let kv = self
            .kv
            .forward(self.norm.forward(x))
            .reshape([b, n, 2, h, d / h])
            .permute([2, 0, 3, 1, 4]);
        let part = |i: usize| kv.clone().narrow(0, i, 1).reshape([b, h, n, d / h]);
        let attended = attention(
            q,
            part(0),
            part(1),
            None,
            None,
            AttentionModuleOptions::default(),
        );
        let pooled = query
            + self
                .proj
                .forward(attended.swap_dims(1, 2).reshape([b, 1, d]));
        let hidden = gelu(
            self.fc1
                .forward(self.head_norm.forward(pooled.reshape([b, d]))),
        );
        self.fc2.forward(hidden)
    }
}

/// Trains an [`AttentiveProbe`] on the rows of `tokens` (`[samples, tokens, dim]`, row-major)
/// not marked `test` and returns its RMSE (mN, forces in N) over the test rows and three axes.
/// Tokens are standardized per (token, feature) and forces per axis with the training rows'
/// statistics; AdamW (weight decay 0.01) with the learning rate falling from 1e-3 to 0 on a
/// half cosine over the run (so the probe ends at a settled minimum rather than a noisy
/// iterate), batches of 32, MSE, `epochs` passes in an order drawn from `seed`, on `device`
/// (the probe drawn on the CPU under `seed` and moved there).
#[allow(clippy::too_many_arguments)]
pub fn attentive_score(
    tokens: &[f32],
    dims: [usize; 3],
    y: &[[f64; 3]],
    test: &[bool],
    epochs: usize,
    seed: u64,
    device: &Device,
) -> f64 {
    let [_, t, d] = dims;
    let row = t * d;
    let train: Vec<usize> = (0..y.len()).filter(|&i| !test[i]).collect();
    let tests: Vec<usize> = (0..y.len()).filter(|&i| test[i]).collect();
    let (mean, std) = column_stats(&train, row, 1e-8, |i, j| tokens[i * row + j] as f64);
    let scale: Vec<f64> = std.iter().map(|s| 1.0 / s).collect();
    let standard = |rows: &[usize]| -> Vec<f32> {
        rows.iter()
            .flat_map(|&i| {
                tokens[i * row..(i + 1) * row]
                    .iter()
                    .zip(&mean)
                    .zip(&scale)
                    .map(|((&v, &m), &s)| ((v as f64 - m) * s) as f32)
            })
            .collect()
    };
    let (ymean, ystd) = column_stats(&train, 3, 1e-9, |i, k| y[i][k]);
    let heads = if d % 64 == 0 { d / 64 } else { 1 };
    let cpu = Device::flex().autodiff();
    let probe = crate::device::seeded_module(&cpu, seed, || {
        AttentiveProbeConfig::new(d, heads).init(&cpu)
    });
    let device = device.clone().autodiff();
    let mut probe = crate::device::on_device(probe, &device);
    let mut optim = AdamWConfig::new().with_weight_decay(0.01).init();
    let total_steps = (epochs * train.len().div_ceil(32)).max(1);
    let mut step = 0;
    for epoch in 0..epochs {
        let order = Rng::for_step(seed, epoch as u64, 7).permutation(train.len());
        for chunk in order.chunks(32) {
            let rows: Vec<usize> = chunk.iter().map(|&k| train[k]).collect();
            let x = Tensor::<1>::from_floats(standard(&rows).as_slice(), &device).reshape([
                rows.len(),
                t,
                d,
            ]);
            let target: Vec<f32> = rows
                .iter()
                .flat_map(|&i| {
                    let (ymean, ystd) = (&ymean, &ystd);
                    (0..3).map(move |k| ((y[i][k] - ymean[k]) / ystd[k]) as f32)
                })
                .collect();
            let target =
                Tensor::<1>::from_floats(target.as_slice(), &device).reshape([rows.len(), 3]);
            let loss = (probe.forward(x) - target).powi_scalar(2).mean();
            let grads = GradientsParams::from_grads(loss.backward(), &probe);
            let lr =
                0.5e-3 * (1.0 + (std::f64::consts::PI * step as f64 / total_steps as f64).cos());
            probe = optim.step(lr, probe, grads);
            step += 1;
        }
    }
    let probe = probe.valid();
    let mut se = 0.0;
    for rows in tests.chunks(64) {
        let x = Tensor::<1>::from_floats(standard(rows).as_slice(), &device.clone().inner())
            .reshape([rows.len(), t, d]);
        let pred = probe
            .forward(x)
            .into_data()
            .convert::<f32>()
            .try_to_vec::<f32>()
            .expect("f32");
        for (r, &i) in rows.iter().enumerate() {
            for k in 0..3 {
                let p = ymean[k] + ystd[k] * pred[r * 3 + k] as f64;
                se += (p - y[i][k]).powi(2);
            }
        }
    }
    1000.0 * (se / (3 * tests.len()) as f64).sqrt()
}

/// Standard deviation of each feature over the samples, averaged over the features.
pub fn feature_std(x: &[Vec<f64>]) -> f64 {
    let (n, d) = (x.len() as f64, x[0].len());
    (0..d)
        .map(|j| {
            let m = x.iter().map(|v| v[j]).sum::<f64>() / n;
            (x.iter().map(|v| (v[j] - m).powi(2)).sum::<f64>() / n).sqrt()
        })
        .sum::<f64>()
        / d as f64
}

/// Participation ratio (Σλ)² / Σλ² = tr(C)² / ‖C‖²_F of the covariance C of the tokens'
/// deviations from their per-position means (`tokens` `[samples, tokens, dim]`, row-major):
/// the effective number of feature directions the content varies along, `dim` for isotropic
/// variation and 1 when it lies on one line (the dimensional-collapse measure of Garrido et
/// al., "RankMe", ICML 2023, in its second-moment form); 0 when no token varies.
pub fn content_rank(tokens: &[f32], dims: [usize; 3]) -> f64 {
    let [n, t, d] = dims;
    let mut position_mean = vec![0.0f64; t * d];
    for sample in tokens.chunks(t * d) {
        for (m, &v) in position_mean.iter_mut().zip(sample) {
            *m += v as f64;
        }
    }
    // sum, then divide: exact for a constant token (the f32 sums fit f64's mantissa)
    for m in &mut position_mean {
        *m /= n as f64;
    }
    let mut cov = vec![0.0f64; d * d];
    let mut dev = vec![0.0f64; d];
    for sample in tokens.chunks(t * d) {
        for (token, mean) in sample.chunks(d).zip(position_mean.chunks(d)) {
            for ((x, &v), &m) in dev.iter_mut().zip(token).zip(mean) {
                *x = v as f64 - m;
            }
            for (a, &xa) in dev.iter().enumerate() {
                for (c, &xb) in cov[a * d..=a * d + a].iter_mut().zip(&dev) {
                    *c += xa * xb;
                }
            }
        }
    }
    let (mut trace, mut frobenius) = (0.0, 0.0);
    for a in 0..d {
        trace += cov[a * d + a];
        for b in 0..=a {
            frobenius += if a == b { 1.0 } else { 2.0 } * cov[a * d + b].powi(2);
        }
    }
    if frobenius > 0.0 {
        trace * trace / frobenius
    } else {
        0.0
    }
}

/// Ridge regression on standardized features (λ = 1e-2 · samples), scored on the test rows
/// (`rmse_mn` = `linear_mn`; `feature_std` of the result is left at 0, [`feature_std`]
/// computes it).
pub fn ridge_score(x: &[Vec<f64>], y: &[[f64; 3]], test: &[bool]) -> ProbeScore {
    let d = x[0].len();
    let train: Vec<usize> = (0..x.len()).filter(|&i| !test[i]).collect();
    let tests: Vec<usize> = (0..x.len()).filter(|&i| test[i]).collect();
    let nt = train.len() as f64;
    let (mean, std) = column_stats(&train, d, 1e-8, |i, j| x[i][j]);
    let z = |i: usize| -> Vec<f64> { (0..d).map(|j| (x[i][j] - mean[j]) / std[j]).collect() };
    let (ymean, _) = column_stats(&train, 3, 0.0, |i, k| y[i][k]);
    // normal equations (ZᵀZ + λI) W = Zᵀ(Y − ȳ)
    let lambda = 1e-2 * nt;
    let mut a = vec![0.0; d * d];
    let mut b = vec![[0.0; 3]; d];
    for &i in &train {
        let zi = z(i);
        for p in 0..d {
            for q in 0..d {
                a[p * d + q] += zi[p] * zi[q];
            }
            for k in 0..3 {
                b[p][k] += zi[p] * (y[i][k] - ymean[k]);
            }
        }
    }
    for p in 0..d {
        a[p * d + p] += lambda;
    }
    let w = cholesky_solve(&mut a, d, &b);
    let (mut se, mut se0) = (0.0, 0.0);
    for &i in &tests {
        let zi = z(i);
        for k in 0..3 {
            let pred = ymean[k] + (0..d).map(|p| zi[p] * w[p][k]).sum::<f64>();
            se += (pred - y[i][k]).powi(2);
            se0 += (ymean[k] - y[i][k]).powi(2);
        }
    }
    let n = (3 * tests.len()) as f64;
    let rmse_mn = 1000.0 * (se / n).sqrt();
    ProbeScore {
        rmse_mn,
        linear_mn: rmse_mn,
        baseline_mn: 1000.0 * (se0 / n).sqrt(),
        feature_std: 0.0,
        feature_rank: 0.0,
    }
}

/// Mean and standard deviation (at least `floor`) over `rows` of each of `n` features, where
/// `value(row, feature)` reads the data: the training statistics both probes standardize with.
fn column_stats(
    rows: &[usize],
    n: usize,
    floor: f64,
    value: impl Fn(usize, usize) -> f64,
) -> (Vec<f64>, Vec<f64>) {
    let count = rows.len() as f64;
    let mut mean = vec![0.0; n];
    for &i in rows {
        for (j, m) in mean.iter_mut().enumerate() {
            *m += value(i, j) / count;
        }
    }
    let mut var = vec![0.0; n];
    for &i in rows {
        for (j, v) in var.iter_mut().enumerate() {
            *v += (value(i, j) - mean[j]).powi(2) / count;
        }
    }
    let std = var.iter().map(|v| v.sqrt().max(floor)).collect();
    (mean, std)
}

/// Solves `A X = B` for symmetric positive definite `A` (`d × d`, overwritten).
fn cholesky_solve(a: &mut [f64], d: usize, b: &[[f64; 3]]) -> Vec<[f64; 3]> {
    for j in 0..d {
        let mut s = a[j * d + j];
        for k in 0..j {
            s -= a[j * d + k] * a[j * d + k];
        }
        let l = s.max(1e-12).sqrt();
        a[j * d + j] = l;
        for i in j + 1..d {
            let mut s = a[i * d + j];
            for k in 0..j {
                s -= a[i * d + k] * a[j * d + k];
            }
            a[i * d + j] = s / l;
        }
    }
    let mut y = b.to_vec();
    let sub = |yi: &mut [f64; 3], yk: [f64; 3], l: f64| {
        for (a, b) in yi.iter_mut().zip(yk) {
            *a -= l * b;
        }
    };
    for i in 0..d {
        for k in 0..i {
            let yk = y[k];
            sub(&mut y[i], yk, a[i * d + k]);
        }
        y[i].iter_mut().for_each(|v| *v /= a[i * d + i]);
    }
    for i in (0..d).rev() {
        for k in i + 1..d {
            let yk = y[k];
            sub(&mut y[i], yk, a[k * d + i]);
        }
        y[i].iter_mut().for_each(|v| *v /= a[i * d + i]);
    }
    y
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn ridge_recovers_a_linear_map_and_beats_the_mean() {
        let mut rng = Rng::new(4);
        let n = 400;
        let x: Vec<Vec<f64>> = (0..n)
            .map(|_| (0..5).map(|_| rng.range_f64(-1.0, 1.0)).collect())
            .collect();
        let y: Vec<[f64; 3]> = x
            .iter()
            .map(|v| [v[0] - 2.0 * v[1], 0.5 * v[2], v[3] + v[4] + 3.0])
            .collect();
        let test: Vec<bool> = (0..n).map(|i| i % 4 == 0).collect();
        let s = ridge_score(&x, &y, &test);
        assert!(s.rmse_mn < 0.05 * s.baseline_mn, "{s:?}");
        // features carrying no information score no better than the mean
        let noise: Vec<Vec<f64>> = (0..n)
            .map(|_| (0..5).map(|_| rng.range_f64(-1.0, 1.0)).collect())
            .collect();
        let s = ridge_score(&noise, &y, &test);
        assert!(s.rmse_mn > 0.9 * s.baseline_mn, "{s:?}");
    }

    /// Tokens carrying a localized signal: one token per sample, at a random place, holds the
    /// amplitudes `a` and `b` along features 0 and 1 and a marker along feature 2, over noise
    /// elsewhere; the labels are (a, −a/2, b).
    fn localized_tokens(rng: &mut Rng, n: usize, t: usize, d: usize) -> (Vec<f32>, Vec<[f64; 3]>) {
        let mut tokens = Vec::with_capacity(n * t * d);
        let mut y = Vec::with_capacity(n);
        for _ in 0..n {
            let (a, b, at) = (
                rng.range_f64(-1.0, 1.0),
                rng.range_f64(-1.0, 1.0),
                rng.below(t),
            );
            for k in 0..t {
                for j in 0..d {
                    let signal = match (k == at, j) {
                        (true, 0) => 3.0 * a,
                        (true, 1) => 3.0 * b,
                        (true, 2) => 2.0,
                        _ => 0.0,
                    };
                    tokens.push((signal + rng.range_f64(-0.1, 0.1)) as f32);
                }
            }
            y.push([a, -0.5 * a, b]);
        }
        (tokens, y)
    }

    #[test]
    fn attentive_probe_reads_a_localized_signal_and_not_noise() {
        let mut rng = Rng::new(9);
        let (n, t, d) = (320, 12, 32);
        let test: Vec<bool> = (0..n).map(|i| i % 5 == 4).collect();
        let (tokens, y) = localized_tokens(&mut rng, n, t, d);
        let baseline = ridge_score(&vec![vec![0.0; 1]; n], &y, &test).baseline_mn;
        let rmse = attentive_score(&tokens, [n, t, d], &y, &test, 40, 1, &Device::flex());
        assert!(rmse < 0.35 * baseline, "{rmse} vs mean {baseline}");
        // the same labels over tokens drawn independently of them
        let (noise, _) = localized_tokens(&mut rng, n, t, d);
        let rmse = attentive_score(&noise, [n, t, d], &y, &test, 40, 1, &Device::flex());
        assert!(rmse > 0.9 * baseline, "{rmse} vs mean {baseline}");
        // seeded: the same score again
        assert_eq!(
            rmse,
            attentive_score(&noise, [n, t, d], &y, &test, 40, 1, &Device::flex())
        );
    }

    #[test]
    fn patch_tokens_are_the_row_major_patches() {
        // two samples of one frame, two channels, 4×4 pixels; value = 100·sample + 16·channel + pixel
        let values: Vec<f32> = (0..2)
            .flat_map(|s| {
                (0..2).flat_map(move |c| (0..16).map(move |p| (100 * s + 16 * c + p) as f32))
            })
            .collect();
        let set = ProbeSet {
            batches: vec![HostBatch {
                step: 0,
                values,
                shape: [2, 1, 2, 4, 4],
                forces: None,
            }],
            test: vec![false, true],
            forces: vec![[0.0; 3]; 2],
        };
        let (tokens, dims) = set.patch_tokens(2);
        assert_eq!(dims, [2, 4, 8]);
        // sample 0, token 1 (grid row 0, column 1): channel 0 pixels 2, 3, 6, 7, then channel 1
        assert_eq!(
            &tokens[8..16],
            &[2.0, 3.0, 6.0, 7.0, 18.0, 19.0, 22.0, 23.0]
        );
        // sample 1, token 2 (grid row 1, column 0)
        let t = (4 + 2) * 8;
        assert_eq!(
            &tokens[t..t + 8],
            &[108.0, 109.0, 112.0, 113.0, 124.0, 125.0, 128.0, 129.0]
        );
    }

    #[test]
    fn content_rank_counts_the_directions_tokens_vary_along() {
        let mut rng = Rng::for_step(5, 0, 0);
        let (n, t, d) = (400, 3, 8);
        // a per-position offset that never varies, plus content along `k` directions
        let tokens = |k: usize, rng: &mut Rng| -> Vec<f32> {
            (0..n * t * d)
                .map(|i| {
                    let (token, j) = ((i / d) % t, i % d);
                    let content = if j < k { rng.range_f64(-1.0, 1.0) } else { 0.0 };
                    (10.0 * token as f64 + content) as f32
                })
                .collect()
        };
        // isotropic content over k = 8 and 3 directions: the ratio approaches k
        let all = content_rank(&tokens(8, &mut rng), [n, t, d]);
        let three = content_rank(&tokens(3, &mut rng), [n, t, d]);
        assert!((all - 8.0).abs() < 0.4, "{all}");
        assert!((three - 3.0).abs() < 0.2, "{three}");
        // one direction, at any scale, and no variation at all
        let line: Vec<f32> = (0..n * t)
            .flat_map(|i| {
                let s = (i % 7) as f32 - 3.0;
                (0..d).map(move |j| 2.0 * s * j as f32)
            })
            .collect();
        assert!((content_rank(&line, [n, t, d]) - 1.0).abs() < 1e-9);
        let constant = vec![0.7f32; n * t * d];
        assert_eq!(content_rank(&constant, [n, t, d]), 0.0);
    }

    #[test]
    fn feature_std_is_the_mean_spread_and_zero_for_a_constant() {
        // two features: ±1 (std 1) and 3·(±1) (std 3) → mean 2
        let x: Vec<Vec<f64>> = (0..10)
            .map(|i| {
                let s = if i % 2 == 0 { 1.0 } else { -1.0 };
                vec![s, 3.0 * s + 7.0]
            })
            .collect();
        assert!((feature_std(&x) - 2.0).abs() < 1e-12);
        assert_eq!(feature_std(&vec![vec![0.3, -2.0]; 6]), 0.0);
    }
}
