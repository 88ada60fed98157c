//! Online force probe: a linear (ridge) read-out of 3-axis force from the frozen encoder's
//! mean-pooled tokens, fitted on training sequences and scored on held-out ones.

use burn::module::Module;
use burn::prelude::*;

use crate::data::{AugmentConfig, HostBatch, Sampler};
use crate::vit::Vit;

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
    /// RMSE of the ridge read-out over all three axes.
    pub rmse_mn: f64,
    /// RMSE of predicting the training mean (what a useless encoder scores).
    pub baseline_mn: f64,
    /// Spread of the pooled features across samples: the standard deviation over samples,
    /// averaged over feature dimensions (near 0 when the encoder has collapsed to a constant).
    pub feature_std: f64,
}

impl ProbeSet {
    /// Up to `max` evenly spaced labelled samples; every fifth sequence is held out (every fifth
    /// sample when there are fewer than five labelled sequences). `None` when the data carry no
    /// force labels or too few samples.
    pub fn new(sampler: &Sampler, max: usize, chunk: usize) -> Option<Self> {
        let labelled: Vec<usize> = (0..sampler.samples.len())
            .filter(|&i| {
                sampler.data().sequences[sampler.samples[i].0]
                    .forces
                    .is_some()
            })
            .collect();
        if labelled.len() < 10 || max < 10 {
            return None;
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
        if test.iter().all(|&t| t) || !test.iter().any(|&t| t) {
            return None;
        }
        let batches: Vec<HostBatch> = picks
            .chunks(chunk.max(1))
            .map(|c| sampler.batch(c, &AugmentConfig::none(), 0, 0))
            .collect();
        let forces = batches
            .iter()
            .flat_map(|b| b.forces.clone().expect("labelled samples"))
            .map(|f| f.map(f64::from))
            .collect();
        Some(Self {
            batches,
            test,
            forces,
        })
    }

    /// Fits and scores the probe on `encoder` (frozen; no gradients are recorded).
    pub fn score(&self, encoder: &Vit) -> ProbeScore {
        let enc = encoder.clone().valid();
        let device = Device::flex();
        let mut feats: Vec<Vec<f64>> = Vec::new();
        for b in &self.batches {
            let x = Tensor::<1>::from_floats(b.values.as_slice(), &device).reshape(b.shape);
            let out = enc.forward(x, None);
            let pooled = out.patches.mean_dim(1);
            let [n, _, d] = pooled.dims();
            let v = pooled
                .into_data()
                .convert::<f32>()
                .try_to_vec::<f32>()
                .expect("f32");
            feats.extend((0..n).map(|i| v[i * d..(i + 1) * d].iter().map(|&x| x as f64).collect()));
        }
        ProbeScore {
            feature_std: feature_std(&feats),
            ..ridge_score(&feats, &self.forces, &self.test)
        }
    }
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

/// Ridge regression on standardized features (λ = 1e-2 · samples), scored on the test rows
/// (`feature_std` of the result is left at 0; [`feature_std`] computes it).
pub fn ridge_score(x: &[Vec<f64>], y: &[[f64; 3]], test: &[bool]) -> ProbeScore {
    let d = x[0].len();
    let train: Vec<usize> = (0..x.len()).filter(|&i| !test[i]).collect();
    let tests: Vec<usize> = (0..x.len()).filter(|&i| test[i]).collect();
    let nt = train.len() as f64;
    let mean: Vec<f64> = (0..d)
        .map(|j| train.iter().map(|&i| x[i][j]).sum::<f64>() / nt)
        .collect();
    let std: Vec<f64> = (0..d)
        .map(|j| {
            let v = train
                .iter()
                .map(|&i| (x[i][j] - mean[j]).powi(2))
                .sum::<f64>()
                / nt;
            v.sqrt().max(1e-8)
        })
        .collect();
    let z = |i: usize| -> Vec<f64> { (0..d).map(|j| (x[i][j] - mean[j]) / std[j]).collect() };
    let ymean: [f64; 3] = std::array::from_fn(|k| train.iter().map(|&i| y[i][k]).sum::<f64>() / nt);
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
    ProbeScore {
        rmse_mn: 1000.0 * (se / n).sqrt(),
        baseline_mn: 1000.0 * (se0 / n).sqrt(),
        feature_std: 0.0,
    }
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
