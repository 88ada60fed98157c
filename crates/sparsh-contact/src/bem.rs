//! The boundary-element rungs: an elastic half-space, or a gel layer bonded to a rigid window.
//!
//! Per frame: (1) normal contact by the Polonsky–Keer conjugate gradient (Wear 231, 1999) on a
//! window around the candidate contact, under displacement or load control; (2) the tangential
//! tractions by an incremental Coulomb problem with the previous frame's tractions and
//! displacements as history; (3) the displacement fields on the whole grid by one more DC-FFT
//! convolution. The window keeps the cost proportional to the contact patch; a solution whose
//! contact reaches the window edge, or whose deformed gap is negative outside it, is solved
//! again on a larger window, so the window never changes the answer.

use std::collections::HashMap;
use std::sync::Arc;

use rayon::prelude::*;
use sparsh_scene::{Gel, Grid};

use crate::fft::Conv;
use crate::kernels::{Component, LayerCorrection, halfspace_cell};
use crate::{ContactError, ContactInput, ContactSolver, Fields, NormalControl};

/// Iteration limits and tolerances of the boundary-element rungs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BemOptions {
    /// Polonsky–Keer stops when Σ|Δp| / Σp over one iteration falls below this.
    pub normal_tolerance: f64,
    /// The tangential iteration stops when its projected-gradient step is below this fraction of
    /// the friction bound ‖μp‖.
    pub tangential_tolerance: f64,
    /// Iteration cap of each problem; reaching it is [`ContactError::NotConverged`].
    pub max_iterations: usize,
}

impl Default for BemOptions {
    fn default() -> Self {
        BemOptions {
            normal_tolerance: 1e-8,
            tangential_tolerance: 1e-6,
            max_iterations: 5000,
        }
    }
}

/// Kernel spectra of one window size.
#[derive(Debug)]
struct Spectra {
    conv: Conv,
    zz: Vec<f64>,
    xx: Vec<f64>,
    yy: Vec<f64>,
    xy: Vec<f64>,
    /// Largest eigenvalue of the 2 × 2 tangential symbol (mm/kPa): a Lipschitz constant of the
    /// tangential energy's gradient on the window.
    tangential_lipschitz: f64,
}

/// Path history: the previous frame's solution on the whole grid.
#[derive(Debug, Clone)]
struct History {
    pressure_kpa: Vec<f64>,
    traction_kpa: [Vec<f64>; 2],
    u_tangential_mm: [Vec<f64>; 2],
    offset_mm: f64,
}

/// A pair of fields along x and y.
type Pair = [Vec<f64>; 2];

/// A rectangle of cells [i0, i1) × [j0, j1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Rect {
    i0: usize,
    i1: usize,
    j0: usize,
    j1: usize,
}

impl Rect {
    fn width(&self) -> usize {
        self.i1 - self.i0
    }
    fn height(&self) -> usize {
        self.j1 - self.j0
    }
    fn contains(&self, i: usize, j: usize) -> bool {
        (self.i0..self.i1).contains(&i) && (self.j0..self.j1).contains(&j)
    }
}

/// Bounding box of the cells where `pred` holds.
fn bbox(grid: &Grid, pred: impl Fn(usize) -> bool) -> Option<Rect> {
    let mut r: Option<Rect> = None;
    for j in 0..grid.ny {
        for i in 0..grid.nx {
            if pred(j * grid.nx + i) {
                r = Some(match r {
                    None => Rect {
                        i0: i,
                        i1: i + 1,
                        j0: j,
                        j1: j + 1,
                    },
                    Some(r) => Rect {
                        i0: r.i0.min(i),
                        i1: r.i1.max(i + 1),
                        j0: r.j0.min(j),
                        j1: r.j1.max(j + 1),
                    },
                });
            }
        }
    }
    r
}

/// The window around `core`: grown by `grow` of its size (at least 2 cells) on every side,
/// rounded up to a multiple of 8 cells (few distinct FFT sizes) and kept inside the grid.
fn window_around(grid: &Grid, core: Rect, grow: f64) -> Rect {
    let fit = |lo: usize, hi: usize, n: usize| {
        let margin = ((grow * (hi - lo) as f64).ceil() as usize).max(2);
        let want = (hi - lo + 2 * margin).next_multiple_of(8).min(n);
        let centre = (lo + hi) / 2;
        let start = centre.saturating_sub(want / 2).min(n - want);
        (start, start + want)
    };
    let (i0, i1) = fit(core.i0, core.i1, grid.nx);
    let (j0, j1) = fit(core.j0, core.j1, grid.ny);
    Rect { i0, i1, j0, j1 }
}

/// `core` grown to a multiple of `multiple` cells along each axis (fewer distinct FFT sizes),
/// kept inside the grid.
fn padded_to(grid: &Grid, core: Rect, multiple: usize) -> Rect {
    let fit = |lo: usize, hi: usize, n: usize| {
        let want = (hi - lo).next_multiple_of(multiple).min(n);
        let start = lo.min(n - want);
        (start, start + want)
    };
    let (i0, i1) = fit(core.i0, core.i1, grid.nx);
    let (j0, j1) = fit(core.j0, core.j1, grid.ny);
    Rect { i0, i1, j0, j1 }
}

/// Elastic half-space or bonded-layer boundary elements on a grid (see the module docs).
#[derive(Debug)]
pub struct Bem {
    name: &'static str,
    gel: Gel,
    grid: Grid,
    layer: Option<LayerCorrection>,
    options: BemOptions,
    cache: HashMap<(usize, usize), Arc<Spectra>>,
    history: Option<History>,
}

/// Result of the normal problem on a window.
struct NormalSolution {
    pressure_kpa: Vec<f64>,
    offset_mm: f64,
}

impl Bem {
    /// The elastic half-space rung (Love 1929 and Cerruti cell coefficients).
    pub fn halfspace(gel: Gel, grid: Grid) -> Bem {
        Bem {
            name: "halfspace",
            gel,
            grid,
            layer: None,
            options: BemOptions::default(),
            cache: HashMap::new(),
            history: None,
        }
    }

    /// The bonded-layer rung: the gel of `gel.thickness_mm` on a rigid base, normal compliance of
    /// Carbone & Mangialardi (2008, eq. A.30) as a real-space correction to Love's coefficients
    /// (see the crate README). The tangential coefficients stay those of the half-space, an
    /// approximation that underestimates the tangential stiffness once the contact radius
    /// approaches the thickness.
    pub fn layered(gel: Gel, grid: Grid) -> Bem {
        let r_max_mm = f64::hypot(grid.nx as f64, grid.ny as f64) * grid.cell_mm + grid.cell_mm;
        let step_mm = (0.25 * grid.cell_mm).min(0.05 * gel.thickness_mm);
        let layer = LayerCorrection::new(
            gel.youngs_modulus_kpa,
            gel.poisson_ratio,
            gel.thickness_mm,
            r_max_mm,
            step_mm,
        );
        Bem {
            name: "layered",
            layer: Some(layer),
            ..Bem::halfspace(gel, grid)
        }
    }

    /// Replaces the iteration limits and tolerances.
    pub fn with_options(mut self, options: BemOptions) -> Bem {
        self.options = options;
        self
    }

    fn spectra(&mut self, nx: usize, ny: usize) -> Arc<Spectra> {
        if let Some(s) = self.cache.get(&(nx, ny)) {
            return s.clone();
        }
        let (cell, e, nu) = (
            self.grid.cell_mm,
            self.gel.youngs_modulus_kpa,
            self.gel.poisson_ratio,
        );
        let layer = self.layer.as_ref();
        // Coefficients for non-negative offsets; the others follow from symmetry.
        let table = |c: Component| -> Vec<f64> {
            (0..ny)
                .into_par_iter()
                .flat_map_iter(|dj| {
                    (0..nx).map(move |di| {
                        let (x, y) = (di as f64 * cell, dj as f64 * cell);
                        let mut k = halfspace_cell(c, x, y, cell, e, nu);
                        if let (Component::Zz, Some(layer)) = (c, layer) {
                            k += layer.at(x.hypot(y)) * cell * cell;
                        }
                        k
                    })
                })
                .collect()
        };
        let conv = Conv::new(nx, ny);
        let even = |t: &[f64]| {
            conv.kernel_spectrum(|di, dj| t[dj.unsigned_abs() * nx + di.unsigned_abs()])
        };
        let zz = even(&table(Component::Zz));
        let xx = even(&table(Component::Xx));
        let yy = even(&table(Component::Yy));
        let t = table(Component::Xy);
        let xy = conv.kernel_spectrum(|di, dj| {
            (di.signum() * dj.signum()) as f64 * t[dj.unsigned_abs() * nx + di.unsigned_abs()]
        });
        let tangential_lipschitz = (0..xx.len())
            .map(|k| {
                let (a, b, c) = (xx[k], yy[k], xy[k]);
                let mid = 0.5 * (a + b);
                let rad = (0.25 * (a - b) * (a - b) + c * c).sqrt();
                (mid + rad).abs().max((mid - rad).abs())
            })
            .fold(0.0, f64::max);
        let s = Arc::new(Spectra {
            conv,
            zz,
            xx,
            yy,
            xy,
            tangential_lipschitz,
        });
        self.cache.insert((nx, ny), s.clone());
        s
    }

    fn out_of_validity(&self, reason: impl Into<String>) -> ContactError {
        ContactError::OutOfValidity {
            solver: self.name,
            reason: reason.into(),
        }
    }

    /// Polonsky & Keer (1999) conjugate gradient on a window: minimise the complementary energy
    /// with p ≥ 0 and gap h + u(p) − δ ≥ 0, equality where p > 0. Under displacement control δ
    /// is fixed at `offset_mm`; under load control the mean gap over the contact set is removed
    /// at every step and Σ p dA is rescaled to the load, and δ comes out as that mean.
    fn solve_normal(
        &self,
        spectra: &Spectra,
        gap_mm: &[f64],
        initial_kpa: Vec<f64>,
        offset_mm: f64,
        load_n: Option<f64>,
    ) -> Result<NormalSolution, ContactError> {
        let conv = &spectra.conv;
        let n = gap_mm.len();
        let da = self.grid.cell_area_mm2() * 1e-3; // N per kPa
        let mut p = initial_kpa;
        let mut t = vec![0.0; n];
        let mut g = vec![0.0; n];
        let mut g_old = 1.0;
        let mut conjugate = false;
        let mut mean_gap = offset_mm;
        let mut change = f64::INFINITY;
        for _ in 0..self.options.max_iterations {
            let u = conv.apply(&spectra.zz, &p);
            let mut sum_g = 0.0;
            let mut count = 0usize;
            for k in 0..n {
                g[k] = gap_mm[k] + u[k];
                if p[k] > 0.0 {
                    sum_g += g[k];
                    count += 1;
                }
            }
            if count == 0 {
                return Err(self.out_of_validity("the contact set emptied"));
            }
            mean_gap = match load_n {
                Some(_) => sum_g / count as f64,
                None => offset_mm,
            };
            let mut big_g = 0.0;
            for k in 0..n {
                g[k] -= mean_gap;
                if p[k] > 0.0 {
                    big_g += g[k] * g[k];
                }
            }
            let beta = if conjugate { big_g / g_old } else { 0.0 };
            for k in 0..n {
                t[k] = if p[k] > 0.0 { g[k] + beta * t[k] } else { 0.0 };
            }
            g_old = big_g;
            if big_g == 0.0 {
                break;
            }
            let mut r = conv.apply(&spectra.zz, &t);
            if load_n.is_some() {
                let mean_r =
                    (0..n).filter(|&k| p[k] > 0.0).map(|k| r[k]).sum::<f64>() / count as f64;
                r.iter_mut().for_each(|v| *v -= mean_r);
            }
            let (mut gt, mut rt) = (0.0, 0.0);
            for k in 0..n {
                if p[k] > 0.0 {
                    gt += g[k] * t[k];
                    rt += r[k] * t[k];
                }
            }
            let tau = gt / rt;
            let mut overlap = false;
            let p_old = p.clone();
            for k in 0..n {
                if p[k] > 0.0 {
                    p[k] = (p[k] - tau * t[k]).max(0.0);
                } else if g[k] < 0.0 {
                    p[k] -= tau * g[k];
                    overlap = true;
                }
            }
            conjugate = !overlap;
            if p.iter().all(|&v| v == 0.0) {
                // The step lifted every cell off (a guess far too stiff, e.g. a flat face pressed
                // uniformly): halve the previous pressures and restart the conjugate directions.
                p = p_old.iter().map(|v| 0.5 * v).collect();
                conjugate = false;
                continue;
            }
            if let Some(load) = load_n {
                let total = p.iter().sum::<f64>() * da;
                p.iter_mut().for_each(|v| *v *= load / total);
            }
            let sum_p: f64 = p.iter().sum();
            change = p
                .iter()
                .zip(&p_old)
                .map(|(a, b)| (a - b).abs())
                .sum::<f64>()
                / sum_p;
            if !change.is_finite() {
                return Err(self.out_of_validity("non-finite pressure in the normal problem"));
            }
            if change < self.options.normal_tolerance {
                return Ok(NormalSolution {
                    pressure_kpa: p,
                    offset_mm: mean_gap,
                });
            }
        }
        if g_old == 0.0 {
            return Ok(NormalSolution {
                pressure_kpa: p,
                offset_mm: mean_gap,
            });
        }
        Err(ContactError::NotConverged {
            solver: self.name,
            iterations: self.options.max_iterations,
            residual: change,
        })
    }

    /// Incremental Coulomb friction on a window: with w = u_prev + Δ (the previous tangential
    /// displacement plus the indenter's rigid shift), find q minimising ½ qᵀKq − wᵀq subject to
    /// |q_i| ≤ μ p_i. Its optimality conditions are Coulomb's law with maximum dissipation: the
    /// slip increment s = w − Kq vanishes where |q| < μp and is parallel to q where |q| = μp.
    /// Solved by accelerated projected gradient (FISTA, Beck & Teboulle 2009) with adaptive
    /// restart (O'Donoghue & Candès 2015), step 1/L with L the largest eigenvalue of the
    /// tangential symbol. Returns the tractions and the slip increments.
    fn solve_tangential(
        &self,
        spectra: &Spectra,
        bound_kpa: &[f64],
        target_mm: [&[f64]; 2],
        initial_kpa: [Vec<f64>; 2],
    ) -> Result<(Pair, Pair), ContactError> {
        let conv = &spectra.conv;
        let kernels = [
            spectra.xx.as_slice(),
            spectra.yy.as_slice(),
            spectra.xy.as_slice(),
        ];
        let n = bound_kpa.len();
        let step = 1.0 / spectra.tangential_lipschitz;
        let project = |x: &mut [Vec<f64>; 2]| {
            for k in 0..n {
                let norm = x[0][k].hypot(x[1][k]);
                if norm > bound_kpa[k] {
                    let s = if norm > 0.0 { bound_kpa[k] / norm } else { 0.0 };
                    x[0][k] *= s;
                    x[1][k] *= s;
                }
            }
        };
        let scale = bound_kpa.iter().map(|b| b * b).sum::<f64>().sqrt();
        let mut x = initial_kpa;
        project(&mut x);
        if scale == 0.0 {
            let u = conv.apply_pair(kernels, &x[0], &x[1]);
            let s = [0, 1].map(|c| (0..n).map(|k| target_mm[c][k] - u[c][k]).collect());
            return Ok((x, s));
        }
        let mut y = x.clone();
        let mut t: f64 = 1.0;
        let mut residual = f64::INFINITY;
        for _ in 0..self.options.max_iterations {
            let u = conv.apply_pair(kernels, &y[0], &y[1]);
            let mut next = [vec![0.0; n], vec![0.0; n]];
            for c in 0..2 {
                for k in 0..n {
                    next[c][k] = y[c][k] - step * (u[c][k] - target_mm[c][k]);
                }
            }
            project(&mut next);
            let mut step_sq = 0.0;
            let mut restart_dot = 0.0;
            for c in 0..2 {
                for k in 0..n {
                    let d = next[c][k] - y[c][k];
                    step_sq += d * d;
                    restart_dot += (y[c][k] - next[c][k]) * (next[c][k] - x[c][k]);
                }
            }
            residual = step_sq.sqrt() / scale;
            if !residual.is_finite() {
                return Err(self.out_of_validity("non-finite traction in the tangential problem"));
            }
            if residual < self.options.tangential_tolerance {
                let u = conv.apply_pair(kernels, &next[0], &next[1]);
                let s = [0, 1].map(|c| (0..n).map(|k| target_mm[c][k] - u[c][k]).collect());
                return Ok((next, s));
            }
            if restart_dot > 0.0 {
                t = 1.0;
                y = next.clone();
            } else {
                let t_next = 0.5 * (1.0 + (1.0 + 4.0 * t * t).sqrt());
                let w = (t - 1.0) / t_next;
                for c in 0..2 {
                    for k in 0..n {
                        y[c][k] = next[c][k] + w * (next[c][k] - x[c][k]);
                    }
                }
                t = t_next;
            }
            x = next;
        }
        Err(ContactError::NotConverged {
            solver: self.name,
            iterations: self.options.max_iterations,
            residual,
        })
    }
}

/// Copies the cells of `window` out of a whole-grid field.
fn crop(grid: &Grid, window: Rect, field: &[f64]) -> Vec<f64> {
    let mut out = Vec::with_capacity(window.width() * window.height());
    for j in window.j0..window.j1 {
        out.extend_from_slice(&field[j * grid.nx + window.i0..j * grid.nx + window.i1]);
    }
    out
}

/// Writes a window field into a whole-grid field (zero elsewhere).
fn embed(grid: &Grid, window: Rect, values: &[f64]) -> Vec<f64> {
    let mut out = vec![0.0; grid.len()];
    let w = window.width();
    for (r, j) in (window.j0..window.j1).enumerate() {
        out[j * grid.nx + window.i0..j * grid.nx + window.i1]
            .copy_from_slice(&values[r * w..(r + 1) * w]);
    }
    out
}

impl ContactSolver for Bem {
    fn name(&self) -> &'static str {
        self.name
    }

    fn solve(&mut self, input: &ContactInput) -> Result<Fields, ContactError> {
        let grid = self.grid;
        let n = grid.len();
        let gap = &input.gap.gap_mm;
        if input.gap.grid != grid || gap.len() != n || input.rigid_shift_mm.len() != n {
            return Err(self.out_of_validity("gap field or shifts do not match the solver grid"));
        }
        if gap.iter().any(|g| g.is_nan()) {
            return Err(self.out_of_validity("NaN in the gap field"));
        }
        if input
            .rigid_shift_mm
            .iter()
            .flatten()
            .any(|s| !s.is_finite())
        {
            return Err(self.out_of_validity("non-finite rigid shift"));
        }
        let nearest_mm = gap.iter().copied().fold(f64::INFINITY, f64::min);
        let load_n = match input.normal {
            NormalControl::Approach => None,
            NormalControl::Force(f) if !f.is_finite() => {
                return Err(self.out_of_validity(format!("normal force {f} N")));
            }
            NormalControl::Force(f) if f <= 0.0 => {
                self.history = None;
                return Ok(Fields::zero(grid));
            }
            NormalControl::Force(f) => {
                if !nearest_mm.is_finite() {
                    return Err(self.out_of_validity(
                        "load control with an indenter that is not above the gel",
                    ));
                }
                Some(f)
            }
        };
        if load_n.is_none() && nearest_mm >= 0.0 {
            self.history = None;
            return Ok(Fields::zero(grid));
        }
        if let Some(layer_mm) = self.layer.as_ref().map(|_| self.gel.thickness_mm)
            && layer_mm < 2.0 * grid.cell_mm
        {
            return Err(self.out_of_validity(format!(
                "gel thickness {layer_mm} mm is under two cells of {} mm",
                grid.cell_mm
            )));
        }
        let e_star = self.gel.effective_modulus_kpa();
        let da_n = grid.cell_area_mm2() * 1e-3;
        // A frame that fails leaves the history of the last good frame in place.
        let previous = self.history.clone();

        // Candidate region: rigid penetration at the expected approach, and the last contact.
        let mut offset_mm = match (load_n, &previous) {
            (None, _) => 0.0,
            (Some(_), Some(h)) => h.offset_mm,
            (Some(_), None) => nearest_mm + grid.cell_mm,
        };
        let mut core = bbox(&grid, |k| {
            gap[k] < offset_mm || previous.as_ref().is_some_and(|h| h.pressure_kpa[k] > 0.0)
        })
        .unwrap_or_else(|| bbox(&grid, |k| gap[k] <= nearest_mm).expect("a finite gap"));
        // On a half-space the surface only sinks under pressure, so the contact lies inside the
        // rigid penetration; a layer bulges around its contact and gets a margin.
        let mut grow = if self.layer.is_some() { 0.25 } else { 0.0 };
        let full = self.spectra(grid.nx, grid.ny);
        let (window, pressure_kpa, uz_into_mm) = loop {
            let window = window_around(&grid, core, grow);
            let spectra = self.spectra(window.width(), window.height());
            let gap_w = crop(&grid, window, gap);
            let mut initial = match &previous {
                Some(h) => crop(&grid, window, &h.pressure_kpa),
                None => vec![0.0; gap_w.len()],
            };
            // No pressure where the indenter has moved away from a cell altogether.
            for (p, g) in initial.iter_mut().zip(&gap_w) {
                if !g.is_finite() {
                    *p = 0.0;
                }
            }
            if initial.iter().all(|&p| p == 0.0) {
                let penetrating = gap_w.iter().filter(|&&g| g < offset_mm).count().max(1);
                let radius_mm = (penetrating as f64 * grid.cell_area_mm2() / 3.0).sqrt();
                for (p, g) in initial.iter_mut().zip(&gap_w) {
                    *p = (e_star * (offset_mm - g) / radius_mm).max(0.0);
                }
                if initial.iter().all(|&p| p == 0.0) {
                    let k = gap_w.iter().enumerate().fold(
                        0,
                        |m, (k, g)| {
                            if *g < gap_w[m] { k } else { m }
                        },
                    );
                    initial[k] = 1.0;
                }
            }
            if let Some(load) = load_n {
                let total = initial.iter().sum::<f64>() * da_n;
                initial.iter_mut().for_each(|p| *p *= load / total);
            }
            let normal = self.solve_normal(&spectra, &gap_w, initial, offset_mm, load_n)?;
            offset_mm = normal.offset_mm;
            let pressure = embed(&grid, window, &normal.pressure_kpa);
            let uz_into = full.conv.apply(&full.zz, &pressure);
            // Contact on the window's inner edge, or interpenetration outside the window,
            // means the window was too small.
            let depth_mm = (offset_mm - nearest_mm).max(grid.cell_mm * 1e-3);
            let escaped = |k: usize| {
                let (i, j) = (k % grid.nx, k / grid.nx);
                let on_inner_edge = window.contains(i, j)
                    && ((i == window.i0 && i > 0)
                        || (i + 1 == window.i1 && i + 1 < grid.nx)
                        || (j == window.j0 && j > 0)
                        || (j + 1 == window.j1 && j + 1 < grid.ny));
                (on_inner_edge && pressure[k] > 0.0)
                    || (!window.contains(i, j)
                        && gap[k] + uz_into[k] - offset_mm < -1e-6 * depth_mm)
            };
            match bbox(&grid, escaped) {
                None => break (window, pressure, uz_into),
                Some(out) => {
                    let contact = bbox(&grid, |k| pressure[k] > 0.0).unwrap_or(out);
                    core = Rect {
                        i0: core.i0.min(out.i0).min(contact.i0),
                        i1: core.i1.max(out.i1).max(contact.i1),
                        j0: core.j0.min(out.j0).min(contact.j0),
                        j1: core.j1.max(out.j1).max(contact.j1),
                    };
                    if window.width() == grid.nx && window.height() == grid.ny {
                        return Err(self.out_of_validity("contact spreads beyond the grid"));
                    }
                    grow = (2.0 * grow).max(0.25);
                }
            }
        };
        let contact: Vec<bool> = pressure_kpa.iter().map(|&p| p > 0.0).collect();
        let touches_edge = (0..n).any(|k| {
            let (i, j) = (k % grid.nx, k / grid.nx);
            contact[k] && (i == 0 || j == 0 || i + 1 == grid.nx || j + 1 == grid.ny)
        });
        if touches_edge {
            return Err(self.out_of_validity("the contact patch touches the grid edge"));
        }
        // No gel is deeper than its thickness, whatever the rung models below it.
        if offset_mm - nearest_mm >= self.gel.thickness_mm {
            return Err(self.out_of_validity(format!(
                "indentation {:.3} mm exceeds the gel thickness {} mm",
                offset_mm - nearest_mm,
                self.gel.thickness_mm
            )));
        }

        // Tangential problem on the contact's bounding box: tractions vanish outside the
        // contact and only displacements inside it are needed.
        let patch = bbox(&grid, |k| contact[k])
            .map(|r| padded_to(&grid, r, 8))
            .unwrap_or(window);
        let spectra = self.spectra(patch.width(), patch.height());
        let mu = self.gel.friction;
        let bound: Vec<f64> = crop(&grid, patch, &pressure_kpa)
            .iter()
            .map(|p| mu * p)
            .collect();
        let shift = [0, 1].map(|c| {
            let all: Vec<f64> = input.rigid_shift_mm.iter().map(|s| s[c]).collect();
            crop(&grid, patch, &all)
        });
        let target = [0, 1].map(|c| {
            let prev = match &previous {
                Some(h) => crop(&grid, patch, &h.u_tangential_mm[c]),
                None => vec![0.0; shift[c].len()],
            };
            prev.iter()
                .zip(&shift[c])
                .map(|(u, s)| u + s)
                .collect::<Vec<f64>>()
        });
        let initial = [0, 1].map(|c| match &previous {
            Some(h) => crop(&grid, patch, &h.traction_kpa[c]),
            None => vec![0.0; bound.len()],
        });
        let (traction_w, slip_increment) =
            self.solve_tangential(&spectra, &bound, [&target[0], &target[1]], initial)?;
        let target_scale = target.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
        let slip_tol = 1e-6 * target_scale.max(1e-9 * grid.cell_mm);
        let slip_w: Vec<f64> = (0..bound.len())
            .map(|k| {
                let on_cone = traction_w[0][k].hypot(traction_w[1][k]) >= bound[k] * (1.0 - 1e-6);
                let moving = slip_increment[0][k].hypot(slip_increment[1][k]) > slip_tol;
                if bound[k] > 0.0 && on_cone && moving || mu == 0.0 && moving {
                    1.0
                } else {
                    0.0
                }
            })
            .collect();
        let slip_full = embed(&grid, patch, &slip_w);
        let traction = [0, 1].map(|c| embed(&grid, patch, &traction_w[c]));
        let [ux, uy] =
            full.conv
                .apply_pair([&full.xx, &full.yy, &full.xy], &traction[0], &traction[1]);

        let mut fields = Fields::zero(grid);
        fields.uz_mm = uz_into_mm.iter().map(|u| -u).collect();
        fields.ux_mm = ux.clone();
        fields.uy_mm = uy.clone();
        fields.pressure_kpa = pressure_kpa.clone();
        fields.traction_x_kpa = traction[0].clone();
        fields.traction_y_kpa = traction[1].clone();
        fields.slip = (0..n).map(|k| contact[k] && slip_full[k] > 0.0).collect();
        fields.contact = contact;
        fields.force_n = fields.total_force_n();
        fields.approach_offset_mm = if load_n.is_some() { offset_mm } else { 0.0 };
        let [tx, ty] = traction;
        self.history = Some(History {
            pressure_kpa,
            traction_kpa: [tx, ty],
            u_tangential_mm: [ux, uy],
            offset_mm,
        });
        Ok(fields)
    }

    fn reset(&mut self) {
        self.history = None;
    }
}
