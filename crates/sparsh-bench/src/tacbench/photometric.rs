//! The classical GelSight height read-out, as a TacBench row: a lookup from a pixel's colour
//! change to the gel surface's slope, calibrated on training frames whose true indentation is
//! known (as a GelSight is calibrated by pressing a ball of known radius: Yuan, Dong & Adelson,
//! *Sensors* 17(12):2762, 2017), the slopes integrated to a height map by Frankot & Chellappa's
//! Fourier projection (IEEE TPAMI 10(4):439, 1988), and the floor oracle's ridge read on that
//! estimated height instead of the true one. Where the frames determine the indentation, this
//! row approaches the floor-ridge; the gap between them is what the shading loses.

use std::sync::Arc;

use faer::Mat;
use faer::linalg::solvers::Solve;
use rustfft::num_complex::Complex;
use rustfft::{Fft, FftPlanner};

/// Monomials of the colour change (r, g, b) up to degree 3.
const COLOUR_TERMS: usize = 20;

/// The lookup's features: the colour monomials, alone and times each coordinate of the
/// position (the LEDs light the gel from its edges, so one slope shades differently across it).
pub const LOOKUP_TERMS: usize = 3 * COLOUR_TERMS;

/// The lookup's features of colour change `c` at `position` (each coordinate in [−1, 1]).
pub fn features(c: [f64; 3], position: [f64; 2]) -> [f64; LOOKUP_TERMS] {
    let m = monomials(c);
    std::array::from_fn(|k| match k / COLOUR_TERMS {
        0 => m[k],
        1 => m[k - COLOUR_TERMS] * position[0],
        _ => m[k - 2 * COLOUR_TERMS] * position[1],
    })
}

/// The 20 monomials of `c` = (r, g, b) of degree ≤ 3, constant first.
fn monomials(c: [f64; 3]) -> [f64; COLOUR_TERMS] {
    let [r, g, b] = c;
    [
        1.0,
        r,
        g,
        b,
        r * r,
        g * g,
        b * b,
        r * g,
        r * b,
        g * b,
        r * r * r,
        g * g * g,
        b * b * b,
        r * r * g,
        r * r * b,
        g * g * r,
        g * g * b,
        b * b * r,
        b * b * g,
        r * g * b,
    ]
}

/// The slope lookup: `[∂h/∂column, ∂h/∂row]` = `weights`ᵀ · [`features`](colour change,
/// position).
#[derive(Debug, Clone)]
pub struct SlopeLookup {
    weights: Mat<f64>,
}

impl SlopeLookup {
    /// Least squares (a 1e-8 relative ridge keeps it solvable where a colour never occurs) of
    /// the slopes on the features, over every ((colour, position), slope) pair `pairs` yields.
    pub fn fit(pairs: impl Iterator<Item = (([f64; 3], [f64; 2]), [f64; 2])>) -> SlopeLookup {
        let mut gram = Mat::<f64>::zeros(LOOKUP_TERMS, LOOKUP_TERMS);
        let mut xty = Mat::<f64>::zeros(LOOKUP_TERMS, 2);
        for ((colour, position), slope) in pairs {
            let m = features(colour, position);
            for i in 0..LOOKUP_TERMS {
                for j in 0..=i {
                    gram[(i, j)] += m[i] * m[j];
                }
                xty[(i, 0)] += m[i] * slope[0];
                xty[(i, 1)] += m[i] * slope[1];
            }
        }
        let trace = (0..LOOKUP_TERMS).map(|i| gram[(i, i)]).sum::<f64>() / LOOKUP_TERMS as f64;
        for i in 0..LOOKUP_TERMS {
            for j in 0..i {
                gram[(j, i)] = gram[(i, j)];
            }
            gram[(i, i)] += 1e-8 * trace.max(1e-300);
        }
        let weights = match gram.llt(faer::Side::Lower) {
            Ok(llt) => llt.solve(&xty),
            Err(_) => Mat::zeros(LOOKUP_TERMS, 2),
        };
        SlopeLookup { weights }
    }

    /// The slope `[∂h/∂column, ∂h/∂row]` a colour change at `position` means.
    pub fn slope(&self, colour: [f64; 3], position: [f64; 2]) -> [f64; 2] {
        let m = features(colour, position);
        std::array::from_fn(|k| (0..LOOKUP_TERMS).map(|i| m[i] * self.weights[(i, k)]).sum())
    }
}

/// Central-difference slopes `(∂h/∂column, ∂h/∂row)` of a `rows × cols` height map (one-sided
/// at the edges), in height units per cell.
pub fn slopes(h: &[f32], rows: usize, cols: usize) -> (Vec<f64>, Vec<f64>) {
    let at = |r: usize, c: usize| h[r * cols + c] as f64;
    let diff = |lo: f64, hi: f64, span: usize| (hi - lo) / span as f64;
    let mut gx = vec![0.0; rows * cols];
    let mut gy = vec![0.0; rows * cols];
    for r in 0..rows {
        for c in 0..cols {
            let (c0, c1) = (c.saturating_sub(1), (c + 1).min(cols - 1));
            let (r0, r1) = (r.saturating_sub(1), (r + 1).min(rows - 1));
            gx[r * cols + c] = diff(at(r, c0), at(r, c1), (c1 - c0).max(1));
            gy[r * cols + c] = diff(at(r0, c), at(r1, c), (r1 - r0).max(1));
        }
    }
    (gx, gy)
}

/// Frankot–Chellappa integration on a `rows × cols` grid: the height whose central-difference
/// slopes are the least-squares projection of `(gx, gy)` onto integrable fields (each Fourier
/// mode: H = −i (sin ωc · Gx + sin ωr · Gy) / (sin² ωc + sin² ωr); modes no central difference
/// sees, the mean and the Nyquist checkerboards, are 0), shifted so that the mean of the
/// outermost ring of cells — the gel the contact leaves alone — is 0.
pub struct Integrator {
    rows: usize,
    cols: usize,
    row_fft: Arc<dyn Fft<f64>>,
    row_ifft: Arc<dyn Fft<f64>>,
    col_fft: Arc<dyn Fft<f64>>,
    col_ifft: Arc<dyn Fft<f64>>,
}

impl Integrator {
    /// Plans the transforms of a `rows × cols` grid.
    pub fn new(rows: usize, cols: usize) -> Integrator {
        let mut planner = FftPlanner::new();
        Integrator {
            rows,
            cols,
            row_fft: planner.plan_fft_forward(cols),
            row_ifft: planner.plan_fft_inverse(cols),
            col_fft: planner.plan_fft_forward(rows),
            col_ifft: planner.plan_fft_inverse(rows),
        }
    }

    /// 2-D transform in place: rows, then columns.
    fn transform(&self, data: &mut [Complex<f64>], row: &dyn Fft<f64>, col: &dyn Fft<f64>) {
        let (rows, cols) = (self.rows, self.cols);
        for r in data.chunks_exact_mut(cols) {
            row.process(r);
        }
        let mut column = vec![Complex::default(); rows];
        for c in 0..cols {
            for r in 0..rows {
                column[r] = data[r * cols + c];
            }
            col.process(&mut column);
            for r in 0..rows {
                data[r * cols + c] = column[r];
            }
        }
    }

    /// The height map of the slopes `(gx, gy)` (see the type's docs).
    pub fn integrate(&self, gx: &[f64], gy: &[f64]) -> Vec<f32> {
        let (rows, cols) = (self.rows, self.cols);
        let to_complex = |g: &[f64]| g.iter().map(|&v| Complex::new(v, 0.0)).collect::<Vec<_>>();
        let (mut fx, mut fy) = (to_complex(gx), to_complex(gy));
        self.transform(&mut fx, &*self.row_fft, &*self.col_fft);
        self.transform(&mut fy, &*self.row_fft, &*self.col_fft);
        let tau = std::f64::consts::TAU;
        let mut h = vec![Complex::default(); rows * cols];
        for r in 0..rows {
            let sy = (tau * r as f64 / rows as f64).sin();
            for c in 0..cols {
                let sx = (tau * c as f64 / cols as f64).sin();
                let denominator = sx * sx + sy * sy;
                if denominator > 1e-12 {
                    let k = r * cols + c;
                    h[k] = Complex::new(0.0, -1.0) * (fx[k] * sx + fy[k] * sy) / denominator;
                }
            }
        }
        self.transform(&mut h, &*self.row_ifft, &*self.col_ifft);
        let n = (rows * cols) as f64;
        let height: Vec<f64> = h.iter().map(|v| v.re / n).collect();
        let ring: Vec<f64> = (0..rows)
            .flat_map(|r| (0..cols).map(move |c| (r, c)))
            .filter(|&(r, c)| r == 0 || c == 0 || r + 1 == rows || c + 1 == cols)
            .map(|(r, c)| height[r * cols + c])
            .collect();
        let base = ring.iter().sum::<f64>() / ring.len().max(1) as f64;
        height.iter().map(|v| (v - base) as f32).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A Gaussian bump's analytic slopes integrate back to the bump.
    #[test]
    fn frankot_chellappa_recovers_a_gaussian_bump() {
        let (rows, cols) = (60, 80);
        let (r0, c0, sigma, a) = (27.0, 43.0, 6.0, 0.5);
        let bump = |r: f64, c: f64| {
            a * (-((r - r0) * (r - r0) + (c - c0) * (c - c0)) / (2.0 * sigma * sigma)).exp()
        };
        let mut gx = vec![0.0; rows * cols];
        let mut gy = vec![0.0; rows * cols];
        for r in 0..rows {
            for c in 0..cols {
                let (rf, cf) = (r as f64, c as f64);
                gx[r * cols + c] = -(cf - c0) / (sigma * sigma) * bump(rf, cf);
                gy[r * cols + c] = -(rf - r0) / (sigma * sigma) * bump(rf, cf);
            }
        }
        let h = Integrator::new(rows, cols).integrate(&gx, &gy);
        let worst = (0..rows * cols)
            .map(|k| (h[k] as f64 - bump((k / cols) as f64, (k % cols) as f64)).abs())
            .fold(0.0, f64::max);
        // central differences see the analytic slope of a bump 6 cells wide to about 1 %
        assert!(worst < 0.02 * a, "worst error {worst} of a {a} bump");
    }

    /// Colours made from slopes by a known cubic are mapped back to the slopes.
    #[test]
    fn lookup_inverts_a_known_shading() {
        let shade = |s: [f64; 2]| {
            [
                0.3 * s[0] + 0.1 * s[1],
                -0.2 * s[0] + 0.25 * s[1],
                0.05 * s[0] - 0.3 * s[1],
            ]
        };
        let grid: Vec<[f64; 2]> = (0..21)
            .flat_map(|i| {
                (0..21).map(move |j| [(i as f64 - 10.0) / 20.0, (j as f64 - 10.0) / 20.0])
            })
            .collect();
        let at = [0.25, -0.5];
        let lookup = SlopeLookup::fit(grid.iter().map(|&s| ((shade(s), at), s)));
        for s in [[0.1, -0.2], [-0.33, 0.05], [0.0, 0.0]] {
            let got = lookup.slope(shade(s), at);
            assert!(
                (got[0] - s[0]).abs() < 1e-6 && (got[1] - s[1]).abs() < 1e-6,
                "{got:?} for {s:?}"
            );
        }
    }

    /// The central differences of a plane are its slope, at the edges too.
    #[test]
    fn slopes_of_a_plane() {
        let (rows, cols) = (5, 7);
        let h: Vec<f32> = (0..rows * cols)
            .map(|k| 0.5 * (k % cols) as f32 - 0.25 * (k / cols) as f32)
            .collect();
        let (gx, gy) = slopes(&h, rows, cols);
        assert!(gx.iter().all(|v| (v - 0.5).abs() < 1e-6));
        assert!(gy.iter().all(|v| (v + 0.25).abs() < 1e-6));
    }
}
