//! DC-FFT: exact linear (non-periodic) convolution of a traction field on an nx × ny window with
//! influence coefficients, by zero-padding to at least 2nx × 2ny (Liu, Wang & Liu, Wear 243,
//! 2000). The padded lengths are rounded up to even 5-smooth numbers (2^a 3^b 5^c), where the
//! mixed-radix FFT is fastest; any length ≥ 2n gives the same linear convolution.
//!
//! DFT convention: forward X_k = Σ_n x_n e^(−2πi kn/N) along x (realfft, keeping the N/2 + 1
//! non-negative frequencies) then along y (rustfft); the inverse is unnormalised and the 1/(N_x
//! N_y) factor is applied once, when the result is read back. Every influence kernel used here is
//! even under (x, y) → (−x, −y), so its spectrum is real and stored as `f64`.
//!
//! Rows and columns are transformed one by one in a fixed order, so results do not depend on
//! the thread count. The spectra and FFT scratch live in buffers kept with the plans, so a
//! convolution allocates nothing once a window size has been used.

use std::cell::RefCell;
use std::sync::{Arc, Mutex};

use rayon::prelude::*;
use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};
use rustfft::{Fft, FftPlanner, num_complex::Complex};

/// Complex values per parallel task: small windows stay on one thread.
const PARALLEL_MIN: usize = 1 << 15;

thread_local! {
    /// Scratch of the column transforms, per worker thread, grown on demand.
    static COLUMN_SCRATCH: RefCell<Vec<Complex<f64>>> = const { RefCell::new(Vec::new()) };
    /// Buffers of the inverse row transforms, per worker thread.
    static ROW_BUFFERS: RefCell<RowBuffers> = const {
        RefCell::new(RowBuffers {
            row: Vec::new(),
            line: Vec::new(),
            scratch: Vec::new(),
        })
    };
}

/// A spectrum row, its real inverse transform and the transform's scratch.
struct RowBuffers {
    row: Vec<Complex<f64>>,
    line: Vec<f64>,
    scratch: Vec<Complex<f64>>,
}

/// The smallest even 5-smooth number ≥ `n`.
pub(crate) fn smooth_length(n: usize) -> usize {
    (n.max(2)..)
        .find(|&m| {
            let mut r = m;
            for f in [2, 3, 5] {
                while r % f == 0 {
                    r /= f;
                }
            }
            r == 1 && m % 2 == 0
        })
        .expect("5-smooth numbers are unbounded")
}

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
    buffers: Mutex<Buffers>,
}

/// Work space of one window size, reused by every convolution.
struct Buffers {
    spectra: [Spectrum; 2],
    real_row: Vec<f64>,
    complex_row: Vec<Complex<f64>>,
    r2c_scratch: Vec<Complex<f64>>,
}

impl std::fmt::Debug for Conv {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Conv({}×{})", self.nx, self.ny)
    }
}

/// A spectrum: `hx` columns of `py` complex values, column-major (one y-transform per column).
type Spectrum = Vec<Complex<f64>>;

impl Conv {
    /// Plans for an `nx × ny` window.
    pub(crate) fn new(nx: usize, ny: usize) -> Conv {
        Conv::padded(nx, ny, smooth_length(2 * nx), smooth_length(2 * ny))
    }

    /// Plans for kernels at offsets |di| < `nx`, |dj| < `ny` on a `px × py` padded grid
    /// (`px ≥ 2nx`, `py ≥ 2ny`): a window of `nx × ny`, or the spread of a patch
    /// ([`Conv::spread_pair_into`]).
    pub(crate) fn padded(nx: usize, ny: usize, px: usize, py: usize) -> Conv {
        assert!(
            px >= 2 * nx && py >= 2 * ny,
            "padding too small for the offsets"
        );
        let hx = px / 2 + 1;
        let mut real = RealFftPlanner::<f64>::new();
        let mut complex = FftPlanner::<f64>::new();
        let r2c = real.plan_fft_forward(px);
        let c2r = real.plan_fft_inverse(px);
        let buffers = Buffers {
            spectra: [0, 1].map(|_| vec![Complex::new(0.0, 0.0); hx * py]),
            real_row: r2c.make_input_vec(),
            complex_row: r2c.make_output_vec(),
            r2c_scratch: r2c.make_scratch_vec(),
        };
        Conv {
            nx,
            ny,
            px,
            py,
            hx,
            r2c,
            c2r,
            fwd_y: complex.plan_fft_forward(py),
            inv_y: complex.plan_fft_inverse(py),
            buffers: Mutex::new(buffers),
        }
    }

    /// Spectrum of a field of `sx × sy` values (row-major, `sx ≤ px`, `sy ≤ py`), zero-padded,
    /// into `spec`.
    fn forward_into(
        &self,
        src: &[f64],
        (sx, sy): (usize, usize),
        spec: &mut [Complex<f64>],
        row: &mut [f64],
        out: &mut [Complex<f64>],
        scratch: &mut [Complex<f64>],
    ) {
        spec.fill(Complex::new(0.0, 0.0));
        for j in 0..sy {
            let line = &src[j * sx..(j + 1) * sx];
            if line.iter().all(|&v| v == 0.0) {
                continue;
            }
            row[..sx].copy_from_slice(line);
            row[sx..].fill(0.0);
            self.r2c
                .process_with_scratch(row, out, scratch)
                .expect("realfft lengths match their plan");
            for (k, v) in out.iter().enumerate() {
                spec[k * self.py + j] = *v;
            }
        }
        self.columns(spec, &self.fwd_y);
    }

    /// Transforms every column along y; columns are independent, so running them on several
    /// threads gives the same bits as one.
    fn columns(&self, spec: &mut [Complex<f64>], plan: &Arc<dyn Fft<f64>>) {
        let scratch_len = plan.get_inplace_scratch_len();
        let per_task = (PARALLEL_MIN / self.py).max(1) * self.py;
        spec.par_chunks_mut(per_task).for_each(|block| {
            COLUMN_SCRATCH.with_borrow_mut(|scratch| {
                if scratch.len() < scratch_len {
                    scratch.resize(scratch_len, Complex::new(0.0, 0.0));
                }
                plan.process_with_scratch(block, scratch);
            });
        });
    }

    /// Real spectrum of an influence kernel given as a function of the cell offset (di, dj),
    /// |di| < nx, |dj| < ny, wrapped onto the padded grid (DC-FFT); the other offsets get zero.
    /// The kernel must be even, so the imaginary part vanishes.
    pub(crate) fn kernel_spectrum(&self, kernel: impl Fn(isize, isize) -> f64) -> Vec<f64> {
        self.kernel_spectrum_complex(kernel)
            .iter()
            .map(|c| c.re)
            .collect()
    }

    /// The imaginary part of the spectrum of a kernel odd in one offset and even in the other
    /// (whose real part vanishes), wrapped as in [`Conv::kernel_spectrum`].
    pub(crate) fn odd_kernel_spectrum(&self, kernel: impl Fn(isize, isize) -> f64) -> Vec<f64> {
        self.kernel_spectrum_complex(kernel)
            .iter()
            .map(|c| c.im)
            .collect()
    }

    fn kernel_spectrum_complex(&self, kernel: impl Fn(isize, isize) -> f64) -> Vec<Complex<f64>> {
        let (px, py) = (self.px, self.py);
        // The offset stored at padded index `i` of a length-`p` axis with `n` window cells.
        let offset = |i: usize, n: usize, p: usize| {
            if i < n {
                Some(i as isize)
            } else if i + n > p {
                Some(i as isize - p as isize)
            } else {
                None
            }
        };
        let mut padded = vec![0.0; px * py];
        for j in 0..py {
            let Some(dj) = offset(j, self.ny, py) else {
                continue;
            };
            for i in 0..px {
                if let Some(di) = offset(i, self.nx, px) {
                    padded[j * px + i] = kernel(di, dj);
                }
            }
        }
        let mut spec = vec![Complex::new(0.0, 0.0); self.hx * py];
        let mut row = self.r2c.make_input_vec();
        let mut out = self.r2c.make_output_vec();
        let mut scratch = self.r2c.make_scratch_vec();
        self.forward_into(
            &padded,
            (px, py),
            &mut spec,
            &mut row,
            &mut out,
            &mut scratch,
        );
        spec
    }

    /// Inverse transform of `spec` (destroyed) into `dst`, rows of `width` values: value (i, j)
    /// of `dst` is the padded result at ((i − i0) mod px, (j − j0) mod py), `(i0, j0)` =
    /// `origin`, normalised. Rows are independent tasks, like the columns.
    fn inverse_shifted_into(
        &self,
        spec: &mut [Complex<f64>],
        dst: &mut [f64],
        width: usize,
        (i0, j0): (usize, usize),
    ) {
        self.columns(spec, &self.inv_y);
        let spec = &*spec;
        let norm = 1.0 / (self.px * self.py) as f64;
        let rows_per_task = (PARALLEL_MIN / self.px).max(1);
        let scratch_len = self.c2r.get_scratch_len();
        // The first `split` outputs of a row wrap around to the end of the padded line.
        let split = i0.min(width);
        dst.par_chunks_mut(rows_per_task * width)
            .enumerate()
            .for_each(|(task, block)| {
                ROW_BUFFERS.with_borrow_mut(|RowBuffers { row, line, scratch }| {
                    row.resize(self.hx, Complex::new(0.0, 0.0));
                    line.resize(self.px, 0.0);
                    if scratch.len() < scratch_len {
                        scratch.resize(scratch_len, Complex::new(0.0, 0.0));
                    }
                    for (r, out) in block.chunks_exact_mut(width).enumerate() {
                        let j = (task * rows_per_task + r + self.py - j0 % self.py) % self.py;
                        for (k, v) in row.iter_mut().enumerate() {
                            *v = spec[k * self.py + j];
                        }
                        // A real signal has real DC and Nyquist terms; drop round-off there.
                        row[0].im = 0.0;
                        row[self.hx - 1].im = 0.0;
                        self.c2r
                            .process_with_scratch(row, line, scratch)
                            .expect("realfft lengths match their plan");
                        let (wrapped, ahead) = out.split_at_mut(split);
                        for (o, v) in wrapped.iter_mut().zip(&line[self.px - split..]) {
                            *o = v * norm;
                        }
                        for (o, v) in ahead.iter_mut().zip(line.iter()) {
                            *o = v * norm;
                        }
                    }
                });
            });
    }

    /// u = K ∗ p for one real kernel spectrum, into `dst` (`nx × ny`).
    pub(crate) fn apply_into(&self, kernel: &[f64], src: &[f64], dst: &mut [f64]) {
        let size = (self.nx, self.ny);
        self.spread_into(kernel, src, size, (0, 0), (dst, self.nx));
    }

    /// u = K ∗ p on a `width`-wide grid (`dst`) for a field `p` given on an `sx × sy` patch of
    /// it whose first cell is `origin`: the patch is transformed at the padded grid's origin
    /// and the result read back shifted, so the padding need only cover the offsets between
    /// the patch and the grid (each below the plan's `nx × ny`), not twice the grid.
    pub(crate) fn spread_into(
        &self,
        kernel: &[f64],
        src: &[f64],
        size: (usize, usize),
        origin: (usize, usize),
        (dst, width): (&mut [f64], usize),
    ) {
        let mut guard = self.buffers.lock().expect("convolution buffers");
        let b = &mut *guard;
        let [spec, _] = &mut b.spectra;
        self.forward_into(
            src,
            size,
            spec,
            &mut b.real_row,
            &mut b.complex_row,
            &mut b.r2c_scratch,
        );
        for (s, k) in spec.iter_mut().zip(kernel) {
            *s *= *k;
        }
        self.inverse_shifted_into(spec, dst, width, origin);
    }

    /// The spectra of a pair of `size` fields into the buffers' two spectra.
    fn forward_pair_into(&self, b: &mut Buffers, [qx, qy]: [&[f64]; 2], size: (usize, usize)) {
        let [sx, sy] = &mut b.spectra;
        for (q, spec) in [(qx, sx), (qy, sy)] {
            self.forward_into(
                q,
                size,
                spec,
                &mut b.real_row,
                &mut b.complex_row,
                &mut b.r2c_scratch,
            );
        }
    }

    /// [`Conv::spread_into`] of the tangential pair: (u_x, u_y) = [[K_xx, K_xy], [K_xy, K_yy]] ∗
    /// (q_x, q_y).
    pub(crate) fn spread_pair_into(
        &self,
        [kxx, kyy, kxy]: [&[f64]; 3],
        [qx, qy]: [&[f64]; 2],
        size: (usize, usize),
        origin: (usize, usize),
        ([ux, uy], width): ([&mut [f64]; 2], usize),
    ) {
        let mut guard = self.buffers.lock().expect("convolution buffers");
        let b = &mut *guard;
        self.forward_pair_into(b, [qx, qy], size);
        let [sx, sy] = &mut b.spectra;
        for k in 0..sx.len() {
            let (a, c) = (sx[k], sy[k]);
            sx[k] = a * kxx[k] + c * kxy[k];
            sy[k] = a * kxy[k] + c * kyy[k];
        }
        for (spec, dst) in [(sx, ux), (sy, uy)] {
            self.inverse_shifted_into(spec, dst, width, origin);
        }
    }

    /// [`Conv::spread_into`] of the normal–tangential coupling from tractions:
    /// u_z = K_zx ∗ q_x + K_zy ∗ q_y, with K_zx, K_zy odd ([`Conv::odd_kernel_spectrum`] gives
    /// `kzx` and `kzy`, the imaginary parts of their spectra).
    pub(crate) fn spread_odd_pair_into(
        &self,
        [kzx, kzy]: [&[f64]; 2],
        [qx, qy]: [&[f64]; 2],
        size: (usize, usize),
        origin: (usize, usize),
        (dst, width): (&mut [f64], usize),
    ) {
        let mut guard = self.buffers.lock().expect("convolution buffers");
        let b = &mut *guard;
        self.forward_pair_into(b, [qx, qy], size);
        let [sx, sy] = &mut b.spectra;
        for k in 0..sx.len() {
            // i (kzx Q_x + kzy Q_y).
            let v = sx[k] * kzx[k] + sy[k] * kzy[k];
            sx[k] = Complex::new(-v.im, v.re);
        }
        self.inverse_shifted_into(sx, dst, width, origin);
    }

    /// [`Conv::spread_into`] of the coupling from pressures: (u_x, u_y) = −(K_zx, K_zy) ∗ p
    /// (reciprocity: a pressure moves the surface along x as a traction along x moves it
    /// into the gel, mirrored).
    pub(crate) fn spread_odd_to_pair_into(
        &self,
        [kzx, kzy]: [&[f64]; 2],
        p: &[f64],
        size: (usize, usize),
        origin: (usize, usize),
        ([ux, uy], width): ([&mut [f64]; 2], usize),
    ) {
        let mut guard = self.buffers.lock().expect("convolution buffers");
        let b = &mut *guard;
        let [sx, sy] = &mut b.spectra;
        self.forward_into(
            p,
            size,
            sx,
            &mut b.real_row,
            &mut b.complex_row,
            &mut b.r2c_scratch,
        );
        for k in 0..sx.len() {
            // −i k P.
            let v = sx[k];
            sy[k] = Complex::new(v.im * kzy[k], -v.re * kzy[k]);
            sx[k] = Complex::new(v.im * kzx[k], -v.re * kzx[k]);
        }
        for (spec, dst) in [(sx, ux), (sy, uy)] {
            self.inverse_shifted_into(spec, dst, width, origin);
        }
    }

    /// (u_x, u_y) = [[K_xx, K_xy], [K_xy, K_yy]] ∗ (q_x, q_y), into `dst`.
    pub(crate) fn apply_pair_into(
        &self,
        kernels: [&[f64]; 3],
        q: [&[f64]; 2],
        dst: [&mut [f64]; 2],
    ) {
        let size = (self.nx, self.ny);
        self.spread_pair_into(kernels, q, size, (0, 0), (dst, self.nx));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn padded_lengths_are_even_and_5_smooth() {
        assert_eq!(smooth_length(14), 16);
        assert_eq!(smooth_length(272), 288);
        assert_eq!(smooth_length(632), 640);
        assert_eq!(smooth_length(792), 800);
        assert_eq!(smooth_length(10), 10);
    }

    /// A patch anywhere on a larger grid, spread over the whole grid with the least padding,
    /// equals the direct sum; so do the pair, component by component, and the coupling spreads.
    #[test]
    fn spread_of_a_patch_matches_direct_sums() {
        let (width, height) = (13, 9);
        let (sx, sy, i0, j0) = (4, 3, 8, 1);
        // offsets between the patch and the grid reach 11 along x and 7 along y
        let conv = Conv::padded(12, 8, smooth_length(24), smooth_length(16));
        let kernels: [fn(isize, isize) -> f64; 3] = [
            |di, dj| 1.0 / (1.0 + (di * di + 2 * dj * dj) as f64),
            |di, dj| 1.0 / (2.0 + (2 * di * di + dj * dj) as f64),
            |di, dj| (di.signum() * dj.signum()) as f64 / (3.0 + (di * di + dj * dj) as f64),
        ];
        let spectra = kernels.map(|k| conv.kernel_spectrum(k));
        let src: [Vec<f64>; 2] = [3, 5].map(|m| {
            (0..sx * sy)
                .map(|k| ((k * 37) % (m + 8)) as f64 - 4.0)
                .collect()
        });
        let direct = |kernel: &dyn Fn(isize, isize) -> f64, field: &[f64], i: usize, j: usize| {
            let mut sum = 0.0;
            for l in 0..sy {
                for k in 0..sx {
                    let (di, dj) = (
                        i as isize - (i0 + k) as isize,
                        j as isize - (j0 + l) as isize,
                    );
                    sum += kernel(di, dj) * field[l * sx + k];
                }
            }
            sum
        };
        let mut u = vec![0.0; width * height];
        conv.spread_into(&spectra[0], &src[0], (sx, sy), (i0, j0), (&mut u, width));
        let (mut ux, mut uy) = (vec![0.0; width * height], vec![0.0; width * height]);
        conv.spread_pair_into(
            [&spectra[0], &spectra[1], &spectra[2]],
            [&src[0], &src[1]],
            (sx, sy),
            (i0, j0),
            ([&mut ux, &mut uy], width),
        );
        let [kxx, kyy, kxy] = kernels;
        for j in 0..height {
            for i in 0..width {
                let k = j * width + i;
                assert!(
                    (u[k] - direct(&kxx, &src[0], i, j)).abs() < 1e-12,
                    "{i},{j}"
                );
                let want_x = direct(&kxx, &src[0], i, j) + direct(&kxy, &src[1], i, j);
                let want_y = direct(&kxy, &src[0], i, j) + direct(&kyy, &src[1], i, j);
                assert!((ux[k] - want_x).abs() < 1e-12, "x {i},{j}");
                assert!((uy[k] - want_y).abs() < 1e-12, "y {i},{j}");
            }
        }

        // The coupling spreads (odd kernels, imaginary spectra), both ways.
        let kzx = |di: isize, dj: isize| di as f64 / (1.0 + (di * di + 2 * dj * dj) as f64);
        let kzy = |di: isize, dj: isize| dj as f64 / (2.0 + (2 * di * di + dj * dj) as f64);
        let odd = [conv.odd_kernel_spectrum(kzx), conv.odd_kernel_spectrum(kzy)];
        let mut uz = vec![0.0; width * height];
        conv.spread_odd_pair_into(
            [&odd[0], &odd[1]],
            [&src[0], &src[1]],
            (sx, sy),
            (i0, j0),
            (&mut uz, width),
        );
        conv.spread_odd_to_pair_into(
            [&odd[0], &odd[1]],
            &src[1],
            (sx, sy),
            (i0, j0),
            ([&mut ux, &mut uy], width),
        );
        for j in 0..height {
            for i in 0..width {
                let k = j * width + i;
                let want_z = direct(&kzx, &src[0], i, j) + direct(&kzy, &src[1], i, j);
                assert!((uz[k] - want_z).abs() < 1e-12, "z {i},{j}");
                assert!(
                    (ux[k] + direct(&kzx, &src[1], i, j)).abs() < 1e-12,
                    "x {i},{j}"
                );
                assert!(
                    (uy[k] + direct(&kzy, &src[1], i, j)).abs() < 1e-12,
                    "y {i},{j}"
                );
            }
        }
    }

    #[test]
    fn matches_direct_linear_convolution() {
        let (nx, ny) = (7, 5);
        let conv = Conv::new(nx, ny);
        let kernel = |di: isize, dj: isize| 1.0 / (1.0 + (di * di + 2 * dj * dj) as f64);
        let spectrum = conv.kernel_spectrum(kernel);
        let src: Vec<f64> = (0..nx * ny).map(|k| ((k * 37) % 11) as f64 - 4.0).collect();
        let mut fast = vec![0.0; nx * ny];
        conv.apply_into(&spectrum, &src, &mut fast);
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
