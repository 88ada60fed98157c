//! Anderson acceleration of a fixed-point iteration x ← G(x) (Anderson 1965; the "type II"
//! form of Walker & Ni 2011, "Anderson acceleration for fixed-point iterations", SIAM J.
//! Numer. Anal. 49(4), eq. 2.1 with the differences' least squares of section 3).

use std::collections::VecDeque;

/// The last `depth` differences of the map's values and residuals, and the next iterate they
/// give.
pub(super) struct Anderson {
    depth: usize,
    /// G(x_{k+1}) − G(x_k), newest last.
    map_steps: VecDeque<Vec<f64>>,
    /// f_{k+1} − f_k with f = G(x) − x, newest last.
    residual_steps: VecDeque<Vec<f64>>,
    /// The last G(x) and its residual.
    last: Option<(Vec<f64>, Vec<f64>)>,
}

impl Anderson {
    /// Mixing of the last `depth` iterates (0: the plain iteration).
    pub(super) fn new(depth: usize) -> Anderson {
        Anderson {
            depth,
            map_steps: VecDeque::new(),
            residual_steps: VecDeque::new(),
            last: None,
        }
    }

    /// Forgets the history: the next step is the plain one, G(x).
    pub(super) fn reset(&mut self) {
        self.map_steps.clear();
        self.residual_steps.clear();
        self.last = None;
    }

    /// The next iterate from x_k and G(x_k): G(x_k) − ΔG γ, with γ the least-squares
    /// coefficients minimising |f_k − ΔF γ|₂ over the kept differences. With no history, or
    /// differences that are linearly dependent, the plain step G(x_k) (and the history restarts).
    pub(super) fn next(&mut self, x: &[f64], map: &[f64]) -> Vec<f64> {
        let residual: Vec<f64> = map.iter().zip(x).map(|(g, x)| g - x).collect();
        if self.depth == 0 {
            return map.to_vec();
        }
        if let Some((last_map, last_residual)) = self.last.take() {
            self.map_steps
                .push_back(map.iter().zip(&last_map).map(|(a, b)| a - b).collect());
            self.residual_steps.push_back(
                residual
                    .iter()
                    .zip(&last_residual)
                    .map(|(a, b)| a - b)
                    .collect(),
            );
            if self.residual_steps.len() > self.depth {
                self.map_steps.pop_front();
                self.residual_steps.pop_front();
            }
        }
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(a, b)| a * b).sum::<f64>();
        // Normal equations (ΔFᵀΔF) γ = ΔFᵀ f, m ≤ depth unknowns.
        let gram: Vec<Vec<f64>> = self
            .residual_steps
            .iter()
            .map(|row| {
                self.residual_steps
                    .iter()
                    .chain(std::iter::once(&residual))
                    .map(|column| dot(row, column))
                    .collect()
            })
            .collect();
        let coefficients = solve_dense(gram);
        self.last = Some((map.to_vec(), residual));
        let Some(gamma) = coefficients else {
            self.map_steps.clear();
            self.residual_steps.clear();
            return map.to_vec();
        };
        let mut next = map.to_vec();
        for (g, step) in gamma.iter().zip(&self.map_steps) {
            next.iter_mut().zip(step).for_each(|(n, s)| *n -= g * s);
        }
        next
    }
}

/// Solves the m × (m + 1) augmented system by Gaussian elimination with partial pivoting;
/// `None` when a pivot falls below 1e-12 of the largest diagonal entry (dependent columns).
fn solve_dense(mut a: Vec<Vec<f64>>) -> Option<Vec<f64>> {
    let m = a.len();
    let scale = (0..m).fold(0.0f64, |s, i| s.max(a[i][i]));
    if m == 0 || scale <= 0.0 {
        return (m == 0).then(Vec::new);
    }
    for c in 0..m {
        let pivot = (c..m).max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs()))?;
        if a[pivot][c].abs() <= 1e-12 * scale {
            return None;
        }
        a.swap(c, pivot);
        let (upper, lower) = a.split_at_mut(c + 1);
        let pivot_row = &upper[c];
        for row in lower {
            let f = row[c] / pivot_row[c];
            row.iter_mut()
                .zip(pivot_row)
                .skip(c)
                .for_each(|(v, p)| *v -= f * p);
        }
    }
    let mut x = vec![0.0; m];
    for r in (0..m).rev() {
        let tail: f64 = (r + 1..m).map(|k| a[r][k] * x[k]).sum();
        x[r] = (a[r][m] - tail) / a[r][r];
    }
    Some(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Steps of x ← A x + b (A = `diagonal` plus a small coupling) until within 1e-6 of the
    /// solution of (I − A) x = b found independently by elimination; 500 when never.
    fn steps_to_fixed_point(diagonal: [f64; 6], depth: usize) -> usize {
        let n = diagonal.len();
        let a: Vec<Vec<f64>> = (0..n)
            .map(|i| {
                (0..n)
                    .map(|j| {
                        if i == j {
                            diagonal[i]
                        } else {
                            0.01 * ((i + 2 * j) % 3) as f64
                        }
                    })
                    .collect()
            })
            .collect();
        let b: Vec<f64> = (0..n).map(|i| 1.0 + i as f64).collect();
        let map = |x: &[f64]| -> Vec<f64> {
            (0..n)
                .map(|i| (0..n).map(|j| a[i][j] * x[j]).sum::<f64>() + b[i])
                .collect()
        };
        let exact = solve_dense(
            (0..n)
                .map(|i| {
                    let mut row: Vec<f64> = (0..n)
                        .map(|j| f64::from(u8::from(i == j)) - a[i][j])
                        .collect();
                    row.push(b[i]);
                    row
                })
                .collect(),
        )
        .unwrap();
        let mut anderson = Anderson::new(depth);
        let mut x = vec![0.0; n];
        for k in 1..=500 {
            x = anderson.next(&x, &map(&x));
            let error = x
                .iter()
                .zip(&exact)
                .fold(0.0f64, |m, (x, e)| m.max((x - e).abs()));
            if error < 1e-6 {
                return k;
            }
        }
        500
    }

    /// Spectral radius 0.92, the plain multiplier update's rate on a μ = 1.5 slide at the
    /// rung's default mesh: the plain iteration needs ~200 steps, the mixed one a tenth.
    #[test]
    fn anderson_converges_fast_to_a_slow_linear_fixed_point() {
        let diagonal = [0.92, 0.82, 0.72, 0.62, 0.52, 0.42];
        let plain = steps_to_fixed_point(diagonal, 0);
        let mixed = steps_to_fixed_point(diagonal, 5);
        assert!(plain > 150, "plain iteration: {plain} steps");
        assert!(mixed <= plain / 10, "mixed: {mixed} steps against {plain}");
    }

    /// An eigenvalue above 1 (the plain update drifting away, as on the reference mesh of that
    /// slide): the plain iteration diverges, the mixed one converges.
    #[test]
    fn anderson_converges_where_the_plain_iteration_diverges() {
        let diagonal = [1.08, 0.82, 0.72, 0.62, 0.52, 0.42];
        assert_eq!(steps_to_fixed_point(diagonal, 0), 500);
        let mixed = steps_to_fixed_point(diagonal, 5);
        assert!(mixed < 40, "mixed: {mixed} steps");
    }

    #[test]
    fn dependent_differences_fall_back_to_the_plain_step() {
        let mut anderson = Anderson::new(3);
        // G(x) = x + 1 everywhere: every residual is the same, so the differences vanish.
        let mut x = vec![0.0; 4];
        for _ in 0..4 {
            let g: Vec<f64> = x.iter().map(|v| v + 1.0).collect();
            let next = anderson.next(&x, &g);
            assert_eq!(next, g);
            x = next;
        }
    }
}
