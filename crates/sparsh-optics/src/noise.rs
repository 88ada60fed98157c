//! Seeded imperfections of a sensor instance and its camera: exposure, a smooth variation of the
//! background, and per-pixel Gaussian noise drawn anew each frame.
//!
//! Every random number is a hash of (seed, stream, index) (SplitMix64), not a draw from a
//! sequential generator, so each pixel's value is the same whatever the thread count or order.

use rayon::prelude::*;
use sparsh_scene::Grid;

/// What to add, and the seed to draw it from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Imperfections {
    /// Seed of the sequence (the scene's `seed`).
    pub seed: u64,
    /// Gain on the whole image.
    pub exposure: f64,
    /// Relative amplitude of the background's smooth variation.
    pub background_variation: f64,
    /// Standard deviation of the per-pixel noise (0–255 units).
    pub noise_std: f64,
}

/// SplitMix64's finaliser of the seed, a stream tag and an index: a well-mixed 64-bit hash.
pub fn hash(seed: u64, stream: u64, index: u64) -> u64 {
    let mut z = seed
        ^ stream.wrapping_mul(0xD1B5_4A32_D192_ED03)
        ^ index.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A uniform number in (0, 1) from a hash (53 bits, never 0).
fn uniform(h: u64) -> f64 {
    ((h >> 11) as f64 + 0.5) / (1u64 << 53) as f64
}

/// A standard normal number for (seed, stream, index), by Box–Muller from two hashes.
pub fn gaussian(seed: u64, stream: u64, index: u64) -> f64 {
    let u1 = uniform(hash(seed, stream, 2 * index));
    let u2 = uniform(hash(seed, stream, 2 * index + 1));
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

const STREAM_BACKGROUND: u64 = 1;
const STREAM_NOISE: u64 = 2;
/// Cosine modes of the background variation per axis.
const MODES: usize = 3;

/// The background's relative variation at every pixel, 1 + a·Σ_{k,l} w_{kl}·cos(πk(x+½)/W + φ)·
/// cos(πl(y+½)/H + ψ) over the low modes 0 ≤ k, l < 3 (not both 0), with Gaussian weights
/// normalised so the field's largest possible excursion is a.
pub fn background_field(grid: Grid, seed: u64, amplitude: f64) -> Vec<f64> {
    let modes: Vec<(f64, f64, f64, f64, f64)> = (0..MODES * MODES)
        .skip(1)
        .map(|m| {
            let g = |k: u64| gaussian(seed, STREAM_BACKGROUND, (m * 4) as u64 + k);
            (
                (m % MODES) as f64,
                (m / MODES) as f64,
                g(0),
                g(1) * std::f64::consts::PI,
                g(2) * std::f64::consts::PI,
            )
        })
        .collect();
    let norm: f64 = modes.iter().map(|m| m.2.abs()).sum::<f64>().max(1e-12);
    (0..grid.len())
        .into_par_iter()
        .map(|c| {
            let x = ((c % grid.nx) as f64 + 0.5) / grid.nx as f64;
            let y = ((c / grid.nx) as f64 + 0.5) / grid.ny as f64;
            let v: f64 = modes
                .iter()
                .map(|&(k, l, w, phi, psi)| {
                    w * (std::f64::consts::PI * k * x + phi).cos()
                        * (std::f64::consts::PI * l * y + psi).cos()
                })
                .sum();
            1.0 + amplitude * v / norm
        })
        .collect()
}

impl Imperfections {
    /// Applies them to frame `frame` of the sequence: I' = e·(bg·B + (I − bg)) + σ·n, with B the
    /// background field, e the exposure and n standard normal per pixel, channel and frame.
    pub fn apply(
        &self,
        pixels: &mut [[f32; 3]],
        background: &[[f32; 3]],
        background_field: &[f64],
        frame: usize,
    ) {
        let frame_seed = hash(self.seed, STREAM_NOISE, frame as u64);
        pixels.par_iter_mut().enumerate().for_each(|(c, px)| {
            for ch in 0..3 {
                let bg = background[c][ch] as f64;
                let mut v = self.exposure * (px[ch] as f64 + bg * (background_field[c] - 1.0));
                if self.noise_std > 0.0 {
                    v += self.noise_std * gaussian(frame_seed, STREAM_NOISE, (3 * c + ch) as u64);
                }
                px[ch] = v as f32;
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The noise has the asked mean and spread (moments of 90 000 draws against N(0, 1): the
    /// sample mean's standard error is 1/300).
    #[test]
    fn gaussian_draws_have_unit_moments() {
        let n = 90_000;
        let v: Vec<f64> = (0..n).map(|k| gaussian(42, 7, k)).collect();
        let mean = v.iter().sum::<f64>() / n as f64;
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        let kurt = v.iter().map(|x| (x - mean).powi(4)).sum::<f64>() / n as f64 / (var * var);
        assert!(mean.abs() < 0.015, "{mean}");
        assert!((var - 1.0).abs() < 0.02, "{var}");
        assert!((kurt - 3.0).abs() < 0.1, "{kurt}");
    }

    #[test]
    fn background_field_is_bounded_by_its_amplitude_and_seeded() {
        let grid = Grid {
            nx: 40,
            ny: 30,
            cell_mm: 0.1,
        };
        let a = background_field(grid, 5, 0.1);
        assert!(a.iter().all(|v| (v - 1.0).abs() <= 0.1 + 1e-12));
        assert!(a.iter().any(|v| (v - 1.0).abs() > 0.01), "it varies");
        assert_eq!(a, background_field(grid, 5, 0.1));
        assert_ne!(a, background_field(grid, 6, 0.1));
    }

    /// Without noise or variation, exposure is a plain gain; the noise differs between frames
    /// and is the same for the same frame.
    #[test]
    fn exposure_scales_and_noise_is_per_frame() {
        let bg = vec![[100.0f32; 3]; 50];
        let ones = vec![1.0; 50];
        let quiet = Imperfections {
            seed: 1,
            exposure: 1.25,
            background_variation: 0.0,
            noise_std: 0.0,
        };
        let mut px = vec![[80.0f32; 3]; 50];
        quiet.apply(&mut px, &bg, &ones, 0);
        assert!(px.iter().flatten().all(|&v| v == 100.0));
        let noisy = Imperfections {
            noise_std: 2.0,
            ..quiet
        };
        let run = |frame| {
            let mut px = vec![[80.0f32; 3]; 50];
            noisy.apply(&mut px, &bg, &ones, frame);
            px
        };
        assert_eq!(run(3), run(3));
        assert_ne!(run(3), run(4));
    }
}
