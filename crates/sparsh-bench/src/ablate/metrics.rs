//! Scores of predicted contact circles against the real frames' marked circles: centre error
//! (px), radius error (px and % of the true radius), medians and 90th percentiles, the share of
//! frames within 3 px and 5 % and within 5 px and 10 %, with 95 % bootstrap intervals that
//! resample the real frames and the training seeds.

use serde::{Deserialize, Serialize};
use sparsh_ssl::rng::Rng;

use super::data::Circle;
use crate::stats::quantile;

/// One frame's errors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameError {
    /// Distance between the centres (px).
    pub centre_px: f64,
    /// |r̂ − r| (px).
    pub radius_px: f64,
    /// |r̂ − r| / r (%).
    pub radius_pct: f64,
}

impl FrameError {
    /// The errors of `predicted` against `truth`.
    pub fn of(predicted: Circle, truth: Circle) -> Self {
        let radius_px = (predicted.r_px - truth.r_px).abs();
        FrameError {
            centre_px: (predicted.cx_px - truth.cx_px).hypot(predicted.cy_px - truth.cy_px),
            radius_px,
            radius_pct: 100.0 * radius_px / truth.r_px,
        }
    }
}

/// The scores of a row (one model on one variant), over every seed's predictions.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Scores {
    /// Median centre error (px).
    pub centre_median_px: f64,
    /// Its 95 % bootstrap interval.
    pub centre_median_ci: [f64; 2],
    /// 90th percentile of the centre error (px).
    pub centre_p90_px: f64,
    /// Median radius error (px).
    pub radius_median_px: f64,
    /// 90th percentile of the radius error (px).
    pub radius_p90_px: f64,
    /// Median radius error (%).
    pub radius_median_pct: f64,
    /// Its 95 % bootstrap interval.
    pub radius_median_pct_ci: [f64; 2],
    /// 90th percentile of the radius error (%).
    pub radius_p90_pct: f64,
    /// Share of predictions with centre within 3 px and radius within 5 %.
    pub within_3px_5pct: f64,
    /// Share of predictions with centre within 5 px and radius within 10 %.
    pub within_5px_10pct: f64,
}

fn sorted(mut v: Vec<f64>) -> Vec<f64> {
    v.sort_by(f64::total_cmp);
    v
}

fn statistics(errors: &[&FrameError]) -> [f64; 8] {
    let c = sorted(errors.iter().map(|e| e.centre_px).collect());
    let r = sorted(errors.iter().map(|e| e.radius_px).collect());
    let p = sorted(errors.iter().map(|e| e.radius_pct).collect());
    let n = errors.len() as f64;
    let share = |px: f64, pct: f64| {
        errors
            .iter()
            .filter(|e| e.centre_px <= px && e.radius_pct <= pct)
            .count() as f64
            / n
    };
    [
        quantile(&c, 0.5),
        quantile(&c, 0.9),
        quantile(&r, 0.5),
        quantile(&r, 0.9),
        quantile(&p, 0.5),
        quantile(&p, 0.9),
        share(3.0, 5.0),
        share(5.0, 10.0),
    ]
}

/// Scores `errors[seed][frame]` (every seed scored on the same frames): the statistics pool all
/// seeds' predictions; the intervals come from `draws` bootstrap resamples of frames and of
/// seeds, both with replacement (percentile method).
pub fn score(errors: &[Vec<FrameError>], draws: usize, seed: u64) -> Scores {
    let all: Vec<&FrameError> = errors.iter().flatten().collect();
    let s = statistics(&all);
    let (n_seeds, n_frames) = (errors.len(), errors.first().map_or(0, Vec::len));
    let mut rng = Rng::new(seed);
    let mut centre = Vec::with_capacity(draws);
    let mut radius = Vec::with_capacity(draws);
    for _ in 0..draws {
        let seeds: Vec<usize> = (0..n_seeds).map(|_| rng.below(n_seeds)).collect();
        let frames: Vec<usize> = (0..n_frames).map(|_| rng.below(n_frames)).collect();
        let pick: Vec<&FrameError> = seeds
            .iter()
            .flat_map(|&s| frames.iter().map(move |&f| &errors[s][f]))
            .collect();
        let c = sorted(pick.iter().map(|e| e.centre_px).collect());
        let p = sorted(pick.iter().map(|e| e.radius_pct).collect());
        centre.push(quantile(&c, 0.5));
        radius.push(quantile(&p, 0.5));
    }
    let ci = |v: Vec<f64>| {
        if v.is_empty() {
            return [f64::NAN, f64::NAN];
        }
        let v = sorted(v);
        [quantile(&v, 0.025), quantile(&v, 0.975)]
    };
    Scores {
        centre_median_px: s[0],
        centre_median_ci: ci(centre),
        centre_p90_px: s[1],
        radius_median_px: s[2],
        radius_p90_px: s[3],
        radius_median_pct: s[4],
        radius_median_pct_ci: ci(radius),
        radius_p90_pct: s[5],
        within_3px_5pct: s[6],
        within_5px_10pct: s[7],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn circle(cx: f64, cy: f64, r: f64) -> Circle {
        Circle {
            cx_px: cx,
            cy_px: cy,
            r_px: r,
        }
    }

    #[test]
    fn errors_follow_from_the_geometry() {
        let e = FrameError::of(circle(3.0, 4.0, 55.0), circle(0.0, 0.0, 50.0));
        assert_eq!((e.centre_px, e.radius_px, e.radius_pct), (5.0, 5.0, 10.0));
    }

    #[test]
    fn perfect_predictions_score_zero_with_a_degenerate_interval() {
        let truth: Vec<Circle> = (0..10).map(|k| circle(k as f64, 2.0, 40.0)).collect();
        let errors: Vec<Vec<FrameError>> = (0..3)
            .map(|_| truth.iter().map(|&t| FrameError::of(t, t)).collect())
            .collect();
        let s = score(&errors, 200, 1);
        assert_eq!(s.centre_median_px, 0.0);
        assert_eq!(s.centre_median_ci, [0.0, 0.0]);
        assert_eq!((s.within_3px_5pct, s.within_5px_10pct), (1.0, 1.0));
    }

    #[test]
    fn the_interval_holds_the_median_and_widens_with_spread() {
        // seed s misses every centre by s + frame/10 px
        let errors = |spread: f64| -> Vec<Vec<FrameError>> {
            (0..3)
                .map(|s| {
                    (0..20)
                        .map(|f| FrameError {
                            centre_px: 4.0 + spread * (s as f64 + f as f64 / 10.0),
                            radius_px: 1.0,
                            radius_pct: 2.0,
                        })
                        .collect()
                })
                .collect()
        };
        let narrow = score(&errors(0.1), 500, 2);
        let wide = score(&errors(1.0), 500, 2);
        for s in [narrow, wide] {
            assert!(s.centre_median_ci[0] <= s.centre_median_px);
            assert!(s.centre_median_px <= s.centre_median_ci[1]);
        }
        let width = |s: Scores| s.centre_median_ci[1] - s.centre_median_ci[0];
        assert!(width(wide) > 5.0 * width(narrow));
        // never within 3 px; within 5 px: every narrow miss, and of the wide ones frames 0–10 of
        // seed 0 and frame 0 of seed 1 (12 of 60)
        assert_eq!(wide.within_3px_5pct, 0.0);
        assert_eq!(narrow.within_5px_10pct, 1.0);
        assert!((wide.within_5px_10pct - 0.2).abs() < 1e-12);
    }

    /// Ten predictions of two seeds against circles of radius 20 px, every statistic worked out
    /// by hand: the medians and 90th percentiles interpolate linearly between order statistics
    /// (numpy's default), and a prediction exactly 3 px and 5 % off counts as within 3 px and
    /// 5 % (the bounds are inclusive).
    #[test]
    fn statistics_of_hand_checked_predictions() {
        let truth = circle(100.0, 50.0, 20.0);
        // (centre offset along x, predicted radius): centres 0, 1, 3, 3, 4 and 6, 2, 8, 0.5, 3 px
        // off; radii 0, 0.5, 1, 1.5, 2 and 1, 0, 3, 2.5, 1 px off (0, 2.5, 5, 7.5, 10 and 5, 0,
        // 15, 12.5, 5 % of 20 px)
        let seeds = [
            [
                (0.0, 20.0),
                (1.0, 20.5),
                (3.0, 21.0),
                (3.0, 18.5),
                (4.0, 22.0),
            ],
            [
                (6.0, 21.0),
                (2.0, 20.0),
                (8.0, 23.0),
                (0.5, 17.5),
                (3.0, 19.0),
            ],
        ];
        let errors: Vec<Vec<FrameError>> = seeds
            .iter()
            .map(|frames| {
                frames
                    .iter()
                    .map(|&(dx, r)| FrameError::of(circle(100.0 + dx, 50.0, r), truth))
                    .collect()
            })
            .collect();
        let s = score(&errors, 100, 3);
        // centres sorted: 0, 0.5, 1, 2, 3, 3, 3, 4, 6, 8 → median (3 + 3)/2 = 3;
        // p90 at rank 0.9 · 9 = 8.1: 6 + 0.1 · (8 − 6) = 6.2
        assert_eq!(s.centre_median_px, 3.0);
        assert!((s.centre_p90_px - 6.2).abs() < 1e-12, "{}", s.centre_p90_px);
        // radii (px) sorted: 0, 0, 0.5, 1, 1, 1, 1.5, 2, 2.5, 3 → median 1; p90 2.5 + 0.1 · 0.5
        assert_eq!(s.radius_median_px, 1.0);
        assert!(
            (s.radius_p90_px - 2.55).abs() < 1e-12,
            "{}",
            s.radius_p90_px
        );
        assert_eq!(s.radius_median_pct, 5.0);
        assert!(
            (s.radius_p90_pct - 12.75).abs() < 1e-12,
            "{}",
            s.radius_p90_pct
        );
        // within 3 px and 5 %: (0, 0 %), (1, 2.5 %), (3, 5 %) on both bounds, (2, 0 %), (3, 5 %)
        // → 5 of 10; within 5 px and 10 %: those and (3, 7.5 %), (4, 10 %) → 7 of 10 ((0.5,
        // 12.5 %) and (6, 5 %) stay out)
        assert_eq!(s.within_3px_5pct, 0.5);
        assert_eq!(s.within_5px_10pct, 0.7);
        // the intervals hold the medians and lie within the data's range
        assert!(s.centre_median_ci[0] <= 3.0 && 3.0 <= s.centre_median_ci[1]);
        assert!(s.centre_median_ci[0] >= 0.0 && s.centre_median_ci[1] <= 8.0);
        assert!(s.radius_median_pct_ci[0] <= 5.0 && 5.0 <= s.radius_median_pct_ci[1]);
    }
}
