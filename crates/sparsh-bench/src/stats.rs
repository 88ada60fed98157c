//! Statistics of the benchmark: bootstrap intervals over test sequences and the spread of
//! randomly initialised encoders.

use sparsh_ssl::rng::Rng;

/// A 95 % percentile-bootstrap interval of `statistic` over `groups` (the test sequences, each a
/// list of sample rows), resampling whole groups with replacement `draws` times from `seed`
/// (Efron & Tibshirani 1993, §13.3). Samples of one sequence are correlated, so resampling
/// sequences rather than frames keeps the interval honest.
pub fn bootstrap_interval(
    groups: &[Vec<usize>],
    draws: usize,
    seed: u64,
    statistic: impl Fn(&[usize]) -> f64,
) -> (f64, f64) {
    if groups.is_empty() || draws == 0 {
        return (f64::NAN, f64::NAN);
    }
    let mut rng = Rng::new(seed);
    let mut values: Vec<f64> = (0..draws)
        .map(|_| {
            let rows: Vec<usize> = (0..groups.len())
                .flat_map(|_| groups[rng.below(groups.len())].iter().copied())
                .collect();
            statistic(&rows)
        })
        .collect();
    values.sort_by(f64::total_cmp);
    (quantile(&values, 0.025), quantile(&values, 0.975))
}

/// The `q` quantile of sorted `values`, linearly interpolated (numpy's default).
pub fn quantile(sorted: &[f64], q: f64) -> f64 {
    let pos = q * (sorted.len() - 1) as f64;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    sorted[lo] + (sorted[hi] - sorted[lo]) * (pos - lo as f64)
}

/// Mean, sample standard deviation, minimum and maximum of a set of scores.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Spread {
    /// Mean.
    pub mean: f64,
    /// Sample standard deviation (n − 1); 0 for one value.
    pub sd: f64,
    /// Smallest value.
    pub min: f64,
    /// Largest value.
    pub max: f64,
}

impl Spread {
    /// The spread of `values` (not empty).
    pub fn of(values: &[f64]) -> Self {
        let n = values.len() as f64;
        let mean = values.iter().sum::<f64>() / n;
        let sd = if values.len() > 1 {
            (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt()
        } else {
            0.0
        };
        Self {
            mean,
            sd,
            min: values.iter().copied().fold(f64::INFINITY, f64::min),
            max: values.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        }
    }
}

/// Rank of `value` among `others` (1 = best): one more than the number of others strictly
/// better, where better is larger when `higher_is_better`.
pub fn rank(value: f64, others: &[f64], higher_is_better: bool) -> usize {
    1 + others
        .iter()
        .filter(|&&o| {
            if higher_is_better {
                o > value
            } else {
                o < value
            }
        })
        .count()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spread_and_rank_by_hand() {
        let s = Spread::of(&[1.0, 2.0, 3.0, 6.0]);
        assert_eq!(s.mean, 3.0);
        // deviations −2, −1, 0, 3: squares sum 14, over 3
        assert!((s.sd - (14.0f64 / 3.0).sqrt()).abs() < 1e-12);
        assert_eq!((s.min, s.max), (1.0, 6.0));
        assert_eq!(Spread::of(&[4.0]).sd, 0.0);
        assert_eq!(rank(2.5, &[1.0, 2.0, 3.0, 6.0], true), 3);
        assert_eq!(rank(2.5, &[1.0, 2.0, 3.0, 6.0], false), 3);
        assert_eq!(rank(0.5, &[1.0, 2.0], false), 1);
        assert_eq!(rank(0.5, &[1.0, 2.0], true), 3);
    }

    #[test]
    fn quantile_interpolates_like_numpy() {
        let v = [1.0, 2.0, 3.0, 4.0, 5.0];
        assert_eq!(quantile(&v, 0.0), 1.0);
        assert_eq!(quantile(&v, 0.5), 3.0);
        // numpy.quantile([1..5], 0.975) = 4.9
        assert!((quantile(&v, 0.975) - 4.9).abs() < 1e-12);
    }

    #[test]
    fn bootstrap_interval_covers_the_mean_and_shrinks_with_more_groups() {
        // groups of one value each, alternating 0 and 1: the mean's interval is about
        // 0.5 ± 1.96·0.5/√n
        let values: Vec<f64> = (0..400).map(|i| (i % 2) as f64).collect();
        let mean =
            |rows: &[usize]| rows.iter().map(|&i| values[i]).sum::<f64>() / rows.len() as f64;
        let groups = |n: usize| (0..n).map(|i| vec![i]).collect::<Vec<_>>();
        let (lo, hi) = bootstrap_interval(&groups(400), 2000, 1, mean);
        assert!(lo < 0.5 && hi > 0.5, "{lo} {hi}");
        let half = 1.96 * 0.5 / 400f64.sqrt();
        assert!(
            ((hi - lo) / 2.0 - half).abs() < 0.2 * half,
            "{lo} {hi} vs ±{half}"
        );
        let (lo100, hi100) = bootstrap_interval(&groups(100), 2000, 1, mean);
        assert!(hi100 - lo100 > 1.5 * (hi - lo));
        // identical groups: no spread at all
        let (a, b) = bootstrap_interval(&[vec![1], vec![3]], 100, 2, |r| {
            r.iter().map(|&i| values[i]).sum::<f64>() / r.len() as f64
        });
        assert_eq!((a, b), (1.0, 1.0));
    }
}
