//! The geometric rung (Taxim-like, no physics claims): the clipped penetration of the rigid
//! indenter, smoothed by a Gaussian so the gel drapes around the contact, with a Winkler
//! foundation for the pressure.

use rayon::prelude::*;
use sparsh_scene::{Gel, Grid};

use crate::{ContactError, ContactInput, ContactSolver, Fields, NormalControl};

/// Penetration d = max(−g, 0); surface uz = −max(d, G_σ ∗ d) with σ = h/2 (h the gel
/// thickness); pressure p = (E*/h)·d, a Winkler bed of the gel's plane-strain modulus over its
/// thickness; no tangential tractions or lateral displacement (slip is never reported).
#[derive(Debug, Clone)]
pub struct Geometric {
    gel: Gel,
    grid: Grid,
}

impl Geometric {
    /// A geometric solver for `gel` on `grid`.
    pub fn new(gel: Gel, grid: Grid) -> Geometric {
        Geometric { gel, grid }
    }

    /// Winkler modulus E*/h (kPa per mm of penetration).
    pub fn winkler_kpa_per_mm(&self) -> f64 {
        self.gel.effective_modulus_kpa() / self.gel.thickness_mm
    }

    fn normal_load_n(&self, gap: &[f64], offset_mm: f64) -> f64 {
        let k = self.winkler_kpa_per_mm() * self.grid.cell_area_mm2() * 1e-3;
        gap.iter().map(|g| (offset_mm - g).max(0.0)).sum::<f64>() * k
    }

    /// The extra approach (mm) that makes the Winkler load equal `target_n`, by bisection (the
    /// load grows monotonically with the approach).
    fn approach_for_load(&self, gap: &[f64], target_n: f64) -> Result<f64, ContactError> {
        let nearest = gap.iter().copied().fold(f64::INFINITY, f64::min);
        if !nearest.is_finite() {
            return Err(ContactError::OutOfValidity {
                solver: "geometric",
                reason: "load control with an indenter that is not above the gel".into(),
            });
        }
        let mut lo = nearest;
        let mut hi = nearest + self.grid.cell_mm;
        while self.normal_load_n(gap, hi) < target_n {
            hi += 2.0 * (hi - nearest);
            if hi - nearest > 1e3 {
                return Err(ContactError::OutOfValidity {
                    solver: "geometric",
                    reason: format!("load {target_n} N needs more than 1 m of approach"),
                });
            }
        }
        for _ in 0..100 {
            let mid = 0.5 * (lo + hi);
            if self.normal_load_n(gap, mid) < target_n {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        Ok(0.5 * (lo + hi))
    }
}

impl ContactSolver for Geometric {
    fn name(&self) -> &'static str {
        "geometric"
    }

    fn solve(&mut self, input: &ContactInput) -> Result<Fields, ContactError> {
        let grid = self.grid;
        let gap = &input.gap.gap_mm;
        let offset = match input.normal {
            NormalControl::Approach => 0.0,
            NormalControl::Force(f) if f <= 0.0 => {
                -gap.iter().copied().fold(f64::INFINITY, f64::min).min(0.0)
            }
            NormalControl::Force(f) => self.approach_for_load(gap, f)?,
        };
        let depth: Vec<f64> = gap.iter().map(|g| (offset - g).max(0.0)).collect();
        let deepest = depth.iter().copied().fold(0.0, f64::max);
        if deepest >= self.gel.thickness_mm {
            return Err(ContactError::OutOfValidity {
                solver: "geometric",
                reason: format!(
                    "indentation {deepest:.3} mm reaches the gel thickness {} mm",
                    self.gel.thickness_mm
                ),
            });
        }
        let mut fields = Fields::zero(grid);
        fields.approach_offset_mm = offset;
        if depth.iter().all(|&d| d == 0.0) {
            return Ok(fields);
        }
        let sigma_cells = 0.5 * self.gel.thickness_mm / grid.cell_mm;
        let smooth = gaussian_blur(&depth, grid.nx, grid.ny, sigma_cells);
        let k = self.winkler_kpa_per_mm();
        for c in 0..grid.len() {
            fields.uz_mm[c] = -depth[c].max(smooth[c]);
            fields.pressure_kpa[c] = k * depth[c];
            fields.contact[c] = depth[c] > 0.0;
        }
        fields.force_n = fields.total_force_n();
        Ok(fields)
    }

    fn reset(&mut self) {}
}

/// Separable Gaussian blur with standard deviation `sigma` (cells), truncated at 3σ, with the
/// field taken as zero outside the grid.
fn gaussian_blur(src: &[f64], nx: usize, ny: usize, sigma: f64) -> Vec<f64> {
    let radius = (3.0 * sigma).ceil().max(1.0) as isize;
    let weights: Vec<f64> = (-radius..=radius)
        .map(|k| (-(k * k) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let norm: f64 = weights.iter().sum();
    let weights: Vec<f64> = weights.iter().map(|w| w / norm).collect();
    let blur_line = |line: &[f64], out: &mut [f64]| {
        // Only the taps that land on the grid: a kernel far wider than the grid (a thick gel on
        // fine cells) costs the grid's width, not the kernel's.
        let n = line.len() as isize;
        for (i, o) in out.iter_mut().enumerate() {
            let i = i as isize;
            let (first, last) = ((-radius).max(-i), radius.min(n - 1 - i));
            let mut acc = 0.0;
            for k in first..=last {
                acc += weights[(k + radius) as usize] * line[(i + k) as usize];
            }
            *o = acc;
        }
    };
    let mut rows = vec![0.0; nx * ny];
    rows.par_chunks_mut(nx)
        .zip(src.par_chunks(nx))
        .for_each(|(out, line)| blur_line(line, out));
    let mut cols_t = vec![0.0; nx * ny];
    cols_t.par_chunks_mut(ny).enumerate().for_each(|(i, out)| {
        let column: Vec<f64> = (0..ny).map(|j| rows[j * nx + i]).collect();
        blur_line(&column, out);
    });
    let mut out = vec![0.0; nx * ny];
    for i in 0..nx {
        for j in 0..ny {
            out[j * nx + i] = cols_t[i * ny + j];
        }
    }
    out
}
