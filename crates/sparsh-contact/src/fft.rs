//! DC-FFT: exact linear (non-periodic) convolution of a traction field on an nx × ny window with
//! influence coefficients, by zero-padding to 2nx × 2ny (Liu, Wang & Liu, Wear 243, 2000).
//!
//! DFT convention: forward X_k = Σ_n x_n e^(−2πi kn/N) along x (realfft, keeping the N/2 + 1
//! non-negative frequencies) then along y (rustfft); the inverse is unnormalised and the 1/(N_x
//! N_y) factor is applied once, when the result is read back. Every influence kernel used here is
//! even under (x, y) → (−x, −y), so its spectrum is real and stored as `f64`.
//!
//! Rows and columns are transformed one by one in a fixed order, so results do not depend on
//! the thread count.

use std::sync::Arc;

use rayon::prelude::*;
use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};
use rustfft::{Fft, FftPlanner, num_complex::Complex};

/// Complex values per parallel task: small windows stay on one thread.
const PARALLEL_MIN: usize = 1 << 15;

/// Zero-padded convolution plans for one window size.
pub(crate) struct Conv {
    /// Window cells along x.
    pub nx: usize,
    /// Window cells along y.
    pub ny: usize,
    px: usize,
    py: usize,
    hx: usize,
    r2c: Arc<dyn RealToComplex<f64>>,
    c2r: Arc<dyn ComplexToReal<f64>>,
    fwd_y: Arc<dyn Fft<f64>>,
    inv_y: Arc<dyn Fft<f64>>,
}

impl std::fmt::Debug for Conv {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Conv({}×{})", self.nx, self.ny)
    }
}

/// A spectrum: `hx` columns of `py` complex values, column-major (one y-transform per column).
pub(crate) type Spectrum = Vec<Complex<f64>>;

impl Conv {
    /// Plans for an `nx × ny` window.
    pub(crate) fn new(nx: usize, ny: usize) -> Conv {
        let (px, py) = (2 * nx, 2 * ny);
        let mut real = RealFftPlanner::<f64>::new();
        let mut complex = FftPlanner::<f64>::new();
        Conv {
            nx,
            ny,
            px,
            py,
            hx: px / 2 + 1,
            r2c: real.plan_fft_forward(px),
            c2r: real.plan_fft_inverse(px),
            fwd_y: complex.plan_fft_forward(py),
            inv_y: complex.plan_fft_inverse(py),
        }
    }

    /// Spectrum of a field of `sx × sy` values (row-major, `sx ≤ 2nx`, `sy ≤ 2ny`), zero-padded.
    fn forward_sized(&self, src: &[f64], sx: usize, sy: usize) -> Spectrum {
        let mut spec = vec![Complex::new(0.0, 0.0); self.hx * self.py];
        let mut row = self.r2c.make_input_vec();
        let mut out = self.r2c.make_output_vec();
        let mut scratch = self.r2c.make_scratch_vec();
        for j in 0..sy {
            let line = &src[j * sx..(j + 1) * sx];
            if line.iter().all(|&v| v == 0.0) {
                continue;
            }
            row[..sx].copy_from_slice(line);
            row[sx..].fill(0.0);
            self.r2c
                .process_with_scratch(&mut row, &mut out, &mut scratch)
                .expect("realfft lengths match their plan");
            for (k, v) in out.iter().enumerate() {
                spec[k * self.py + j] = *v;
            }
        }
        self.columns(&mut spec, &self.fwd_y);
        spec
    }

    /// Transforms every column along y; columns are independent, so running them on several
    /// threads gives the same bits as one.
    fn columns(&self, spec: &mut [Complex<f64>], plan: &Arc<dyn Fft<f64>>) {
        let scratch_len = plan.get_inplace_scratch_len();
        let per_task = (PARALLEL_MIN / self.py).max(1) * self.py;
        spec.par_chunks_mut(per_task).for_each_init(
            || vec![Complex::new(0.0, 0.0); scratch_len],
            |scratch, block| {
                for column in block.chunks_exact_mut(self.py) {
                    plan.process_with_scratch(column, scratch);
                }
            },
        );
    }

    /// Spectrum of a window field (`nx × ny`, row-major).
    pub(crate) fn forward(&self, src: &[f64]) -> Spectrum {
        self.forward_sized(src, self.nx, self.ny)
    }

    /// Real spectrum of an influence kernel given as a function of the cell offset (di, dj),
    /// |di| < nx, |dj| < ny, wrapped onto the padded grid (DC-FFT); the unused offsets ±nx, ±ny
    /// get zero. The kernel must be even, so the imaginary part vanishes.
    pub(crate) fn kernel_spectrum(&self, kernel: impl Fn(isize, isize) -> f64) -> Vec<f64> {
        let (px, py) = (self.px, self.py);
        let mut padded = vec![0.0; px * py];
        for j in 0..py {
            let dj = if j < self.ny {
                j as isize
            } else if j > self.ny {
                j as isize - py as isize
            } else {
                continue;
            };
            for i in 0..px {
                let di = if i < self.nx {
                    i as isize
                } else if i > self.nx {
                    i as isize - px as isize
                } else {
                    continue;
                };
                padded[j * px + i] = kernel(di, dj);
            }
        }
        self.forward_sized(&padded, px, py)
            .iter()
            .map(|c| c.re)
            .collect()
    }

    /// Inverse transform, keeping the window (`nx × ny`, row-major, normalised).
    pub(crate) fn inverse(&self, mut spec: Spectrum) -> Vec<f64> {
        self.columns(&mut spec, &self.inv_y);
        let norm = 1.0 / (self.px * self.py) as f64;
        let mut out = vec![0.0; self.nx * self.ny];
        let mut row = self.c2r.make_input_vec();
        let mut line = self.c2r.make_output_vec();
        let mut scratch = self.c2r.make_scratch_vec();
        for j in 0..self.ny {
            for (k, v) in row.iter_mut().enumerate() {
                *v = spec[k * self.py + j];
            }
            // A real signal has real DC and Nyquist terms; drop round-off there.
            row[0].im = 0.0;
            row[self.hx - 1].im = 0.0;
            self.c2r
                .process_with_scratch(&mut row, &mut line, &mut scratch)
                .expect("realfft lengths match their plan");
            for (o, v) in out[j * self.nx..(j + 1) * self.nx].iter_mut().zip(&line) {
                *o = v * norm;
            }
        }
        out
    }

    /// u = K ∗ p for one real kernel spectrum.
    pub(crate) fn apply(&self, kernel: &[f64], src: &[f64]) -> Vec<f64> {
        let mut spec = self.forward(src);
        for (s, k) in spec.iter_mut().zip(kernel) {
            *s *= *k;
        }
        self.inverse(spec)
    }

    /// (u_x, u_y) = [[K_xx, K_xy], [K_xy, K_yy]] ∗ (q_x, q_y).
    pub(crate) fn apply_pair(
        &self,
        [kxx, kyy, kxy]: [&[f64]; 3],
        qx: &[f64],
        qy: &[f64],
    ) -> [Vec<f64>; 2] {
        let sx = self.forward(qx);
        let sy = self.forward(qy);
        let mut ux = Vec::with_capacity(sx.len());
        let mut uy = Vec::with_capacity(sx.len());
        for k in 0..sx.len() {
            ux.push(sx[k] * kxx[k] + sy[k] * kxy[k]);
            uy.push(sx[k] * kxy[k] + sy[k] * kyy[k]);
        }
        [self.inverse(ux), self.inverse(uy)]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_direct_linear_convolution() {
        let (nx, ny) = (7, 5);
        let conv = Conv::new(nx, ny);
        let kernel = |di: isize, dj: isize| 1.0 / (1.0 + (di * di + 2 * dj * dj) as f64);
        let spectrum = conv.kernel_spectrum(kernel);
        let src: Vec<f64> = (0..nx * ny).map(|k| ((k * 37) % 11) as f64 - 4.0).collect();
        let fast = conv.apply(&spectrum, &src);
        for j in 0..ny {
            for i in 0..nx {
                let mut direct = 0.0;
                for l in 0..ny {
                    for k in 0..nx {
                        direct += kernel(i as isize - k as isize, j as isize - l as isize)
                            * src[l * nx + k];
                    }
                }
                assert!((fast[j * nx + i] - direct).abs() < 1e-12, "{i},{j}");
            }
        }
    }
}
