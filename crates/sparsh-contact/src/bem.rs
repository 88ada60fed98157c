//! The boundary-element rungs: an elastic half-space, or a gel layer bonded to a rigid window.
//!
//! Per frame: (1) normal contact by the Polonsky–Keer conjugate gradient (Wear 231, 1999) on a
//! window around the candidate contact, under displacement or load control; (2) the tangential
//! tractions by an incremental Coulomb problem with the previous frame's tractions and
//! displacements as history, solved by semi-smooth Newton with conjugate-gradient steps; (3) the
//! displacement fields on the whole grid by one more DC-FFT convolution. The window keeps the
//! cost proportional to the contact patch; a solution whose contact reaches the window edge, or
//! whose deformed gap is negative outside it, is solved again on a larger window, so the window
//! never changes the answer. Each frame starts from the previous one's solution.

use std::collections::HashMap;
use std::sync::{Arc, OnceLock};
use std::time::Instant;

use rayon::prelude::*;
use sparsh_scene::{GapField, Gel, Grid};

use crate::fft::{Conv, smooth_length};
use crate::kernels::{Component, LayerCorrection, halfspace_cell};
use crate::{ContactError, ContactInput, ContactSolver, Fields, NextFrame, NormalControl};

/// Iteration limits and tolerances of the boundary-element rungs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BemOptions {
    /// Polonsky–Keer stops when Σ|Δp| / Σp over one iteration falls below this.
    pub normal_tolerance: f64,
    /// The tangential iteration stops when its projected-gradient step is below this fraction of
    /// the friction bound ‖μp‖.
    pub tangential_tolerance: f64,
    /// Iteration cap of each problem (and of each conjugate-gradient solve inside a Newton
    /// step); reaching it is [`ContactError::NotConverged`].
    pub max_iterations: usize,
    /// The tangential method.
    pub tangential_method: TangentialMethod,
    /// Start each frame's iterations from the previous frames' solution (pressures and
    /// tractions extrapolated linearly from the last two frames, the normal window around the
    /// last contact); `false` starts from a Hertz-like guess and zero tractions, the path
    /// history being used either way.
    pub warm_start: bool,
}

impl Default for BemOptions {
    fn default() -> Self {
        BemOptions {
            normal_tolerance: 1e-8,
            tangential_tolerance: 1e-6,
            max_iterations: 5000,
            tangential_method: TangentialMethod::SemismoothNewton,
            warm_start: true,
        }
    }
}

/// Work and wall time of the last frame solved by a boundary-element rung.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct BemStats {
    /// Convolutions spent on the normal problem, summed over window enlargements.
    pub normal_convolutions: usize,
    /// Windows the normal problem was solved on (1 unless the contact escaped the first).
    pub normal_windows: usize,
    /// Convolutions spent on the tangential problem.
    pub tangential_convolutions: usize,
    /// Wall time of the normal problem (s), window enlargements and full-grid uz included
    /// (spent during the previous call when that call solved it ahead).
    pub normal_s: f64,
    /// Wall time spent computing the kernel spectra of new window sizes (s), included in the
    /// normal and tangential times.
    pub kernel_s: f64,
    /// Wall time of the tangential problem (s).
    pub tangential_s: f64,
    /// Normal and tangential solves in turn until they agreed (the layered rung with friction;
    /// 0 where the problems are solved once each).
    pub coupling_iterations: usize,
    /// Wall time of the call (s); with [`ContactSolver::solve_ahead`] it includes the next
    /// frame's normal problem, solved beside this frame's tangential one.
    pub total_s: f64,
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
    /// Displacement of a cell under its own unit traction, along x and along y (mm/kPa): the
    /// diagonal of the tangential influence matrix.
    self_xx_mm_per_kpa: f64,
    self_yy_mm_per_kpa: f64,
}

/// Path history: the previous frame's solution on the whole grid.
#[derive(Debug)]
struct History {
    pressure_kpa: Vec<f64>,
    /// The pressure of the frame before, if that frame had contact.
    pressure_before_kpa: Option<Vec<f64>>,
    traction_kpa: [Vec<f64>; 2],
    /// The tractions of the frame before, if that frame had contact.
    traction_before_kpa: Option<[Vec<f64>; 2]>,
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
    /// The cell's own rectangle.
    fn cell(i: usize, j: usize) -> Rect {
        Rect {
            i0: i,
            i1: i + 1,
            j0: j,
            j1: j + 1,
        }
    }

    /// The smallest rectangle holding both.
    fn union(self, other: Rect) -> Rect {
        Rect {
            i0: self.i0.min(other.i0),
            i1: self.i1.max(other.i1),
            j0: self.j0.min(other.j0),
            j1: self.j1.max(other.j1),
        }
    }
}

/// `bounds` grown to hold cell (i, j).
fn include(bounds: Option<Rect>, i: usize, j: usize) -> Option<Rect> {
    let cell = Rect::cell(i, j);
    Some(bounds.map_or(cell, |r| r.union(cell)))
}

/// Bounding box of the cells where `pred` holds (`pred` takes the row-major index).
fn bbox(grid: &Grid, pred: impl Fn(usize) -> bool) -> Option<Rect> {
    let mut r: Option<Rect> = None;
    for j in 0..grid.ny {
        for i in 0..grid.nx {
            if pred(j * grid.nx + i) {
                r = include(r, i, j);
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
///
/// A frame's normal problem needs the last frame's pressures only, not its tractions, so given
/// the next frame's gap ([`ContactSolver::solve_ahead`]) the next normal problem is solved beside
/// this frame's tangential one. The two halves keep their own kernel caches and buffers.
#[derive(Debug)]
pub struct Bem {
    model: Model,
    normal_side: Side,
    tangential_side: Side,
    normal_work: NormalWork,
    newton_work: NewtonWork,
    history: Option<History>,
    /// The next frame's normal problem, solved beside the last frame's tangential one.
    ahead: Option<Ahead>,
    stats: BemStats,
}

/// The rung on its grid: what both halves of a frame read.
#[derive(Debug)]
struct Model {
    name: &'static str,
    gel: Gel,
    grid: Grid,
    layer: Option<LayerCorrection>,
    options: BemOptions,
    /// Influence coefficients of every offset on the grid, `[zz, xx, yy, xy]` (made on first
    /// use): the kernels of every window and spread.
    grid_tables: OnceLock<[Vec<f64>; 4]>,
    /// The layer's normal–tangential coupling coefficients `[zx, zy]` of every offset (made on
    /// first use; none on the half-space, which drops them).
    coupling_tables: OnceLock<[Vec<f64>; 2]>,
}

/// Kernel spectra of one half of the frame's problem, by size. Each half keeps its own: a
/// convolution's work space is locked while in use, so shared spectra would make the halves wait
/// on each other whenever a window and a patch have the same size.
#[derive(Debug, Default)]
struct Side {
    /// Window (or patch) convolutions.
    cache: HashMap<(usize, usize), Arc<Spectra>>,
    /// Spreads onto the whole grid, by padded size.
    spread_cache: HashMap<(usize, usize), Arc<Spread>>,
    /// Seconds spent on kernel spectra of new sizes since the half's frame began.
    kernel_s: f64,
}

/// A normal problem solved ahead, with the frame it was solved for.
#[derive(Debug)]
struct Ahead {
    gap_mm: Vec<f64>,
    normal: NormalControl,
    solved: Result<Normal, ContactError>,
}

/// The previous frame's part in a normal problem.
#[derive(Debug, Clone, Copy)]
struct NormalPast<'a> {
    pressure_kpa: &'a [f64],
    /// The pressure of the frame before, if that frame had contact.
    pressure_before_kpa: Option<&'a [f64]>,
    offset_mm: f64,
}

/// One frame's normal problem.
#[derive(Debug)]
enum Normal {
    /// Nothing touches: the path history ends.
    Free,
    Pressed(NormalFrame),
}

/// One frame's normal contact on the whole grid.
#[derive(Debug)]
struct NormalFrame {
    /// The window it was solved on.
    window: Rect,
    pressure_kpa: Vec<f64>,
    /// Surface displacement into the gel (mm).
    uz_into_mm: Vec<f64>,
    contact: Vec<bool>,
    /// The rigid approach (mm).
    offset_mm: f64,
    load_controlled: bool,
    convolutions: usize,
    windows: usize,
    normal_s: f64,
    kernel_s: f64,
}

/// What the layer's normal–tangential coupling brings to a frame's tangential problem.
#[derive(Clone, Copy)]
struct Coupled<'a> {
    /// The surface's tangential move caused by the frame's pressures (mm, whole grid).
    from_pressure_mm: &'a Pair,
    /// Tractions to start from (the last coupling iteration's), in place of the history's.
    initial_kpa: Option<&'a Pair>,
}

/// A frame solved with the layer's coupling: its normal part (displacement into the gel from
/// the pressures and the tractions), its tangential part, and the work done.
struct CoupledFrame {
    normal: NormalFrame,
    tangential: TangentialFrame,
    stats: BemStats,
}

/// Coupling iterations allowed in a frame before it is [`ContactError::NotConverged`].
const MAX_COUPLING_ITERATIONS: usize = 100;

/// The coupling iteration stops when neither the pressures nor the tractions moved by more than
/// this fraction of the largest pressure (of the friction bound μp for the tractions).
const COUPLING_TOLERANCE: f64 = 1e-6;

/// max |a − b|.
fn max_difference(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).fold(0.0, |m, (a, b)| m.max((a - b).abs()))
}

/// The patch of a frame's tangential problem: the contact's bounding box (tractions vanish
/// outside the contact and only displacements inside it are needed), or the normal window.
fn contact_patch(grid: &Grid, normal: &NormalFrame) -> Rect {
    bbox(grid, |k| normal.contact[k])
        .map(|r| padded_to(grid, r, 8))
        .unwrap_or(normal.window)
}

/// One frame's tangential contact on the whole grid.
struct TangentialFrame {
    traction_kpa: Pair,
    u_tangential_mm: Pair,
    slip: Vec<bool>,
    convolutions: usize,
    tangential_s: f64,
    kernel_s: f64,
}

/// Kernel spectra of a spread: tractions on a patch to displacements on the whole grid.
#[derive(Debug)]
struct Spread {
    conv: Conv,
    zz: Vec<f64>,
    xx: Vec<f64>,
    yy: Vec<f64>,
    xy: Vec<f64>,
    /// The coupling's `[zx, zy]` (imaginary parts; empty on the half-space).
    coupling: [Vec<f64>; 2],
}

/// The padded length of a spread along an axis of `n` cells whose patch-to-grid offsets stay
/// below `reach`: the first of n, 5n/4, 3n/2, 7n/4 and 2n that holds twice the reach (so a
/// trajectory meets few sizes), made 5-smooth. A contact near the middle of the grid pads to
/// about n + its width instead of the 2n of a whole-grid convolution.
fn spread_length(n: usize, reach: usize) -> usize {
    let rung = (4..=8)
        .map(|k| (k * n).div_ceil(4))
        .find(|&m| m >= 2 * reach)
        .unwrap_or(2 * n);
    smooth_length(rung)
}

/// The influence components in the order of the coefficient tables and their spectra.
const COMPONENTS: [Component; 4] = [Component::Zz, Component::Xx, Component::Yy, Component::Xy];

/// Spectra `[zz, xx, yy, xy]` on `conv`'s padded grid of the coefficient tables (non-negative
/// offsets, rows of `row` values): zz, xx and yy are even in both offsets, xy odd in each.
fn kernel_spectra(conv: &Conv, tables: &[Vec<f64>; 4], row: usize) -> [Vec<f64>; 4] {
    std::array::from_fn(|c| {
        let t = &tables[c];
        conv.kernel_spectrum(|di, dj| {
            let sign = if c == 3 {
                (di.signum() * dj.signum()) as f64
            } else {
                1.0
            };
            sign * t[dj.unsigned_abs() * row + di.unsigned_abs()]
        })
    })
}

/// Buffers of the normal problem on a window, kept from frame to frame: once the window has
/// reached its size a solve allocates nothing.
#[derive(Debug, Default)]
struct NormalWork {
    /// The window's gap (mm), the input.
    gap_mm: Vec<f64>,
    /// Pressures (kPa): the initial guess in, the solution out.
    pressure_kpa: Vec<f64>,
    /// Conjugate direction, gap residual, displacement K p, K t and the last pressures.
    t: Vec<f64>,
    g: Vec<f64>,
    u_mm: Vec<f64>,
    kt_mm: Vec<f64>,
    p_old: Vec<f64>,
}

/// Result of the normal problem on a window (the pressures are left in [`NormalWork`]).
struct NormalSolution {
    offset_mm: f64,
    convolutions: usize,
}

impl Bem {
    /// The elastic half-space rung (Love 1929 and Cerruti cell coefficients).
    pub fn halfspace(gel: Gel, grid: Grid) -> Bem {
        Bem::on(Model {
            name: "halfspace",
            gel,
            grid,
            layer: None,
            options: BemOptions::default(),
            grid_tables: OnceLock::new(),
            coupling_tables: OnceLock::new(),
        })
    }

    fn on(model: Model) -> Bem {
        Bem {
            model,
            normal_side: Side::default(),
            tangential_side: Side::default(),
            normal_work: NormalWork::default(),
            newton_work: NewtonWork::default(),
            history: None,
            ahead: None,
            stats: BemStats::default(),
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
        Bem::on(Model {
            name: "layered",
            gel,
            grid,
            layer: Some(layer),
            options: BemOptions::default(),
            grid_tables: OnceLock::new(),
            coupling_tables: OnceLock::new(),
        })
    }

    /// Replaces the iteration limits and tolerances.
    pub fn with_options(mut self, options: BemOptions) -> Bem {
        self.model.options = options;
        self.ahead = None;
        self
    }

    /// Work done on the last frame.
    pub fn stats(&self) -> BemStats {
        self.stats
    }
}

impl Side {
    /// The spread's kernel spectra for tractions on `patch` (cached by padded size).
    fn spread(&mut self, model: &Model, patch: Rect) -> Arc<Spread> {
        let (nx, ny) = (model.grid.nx, model.grid.ny);
        let px = spread_length(nx, patch.i1.max(nx - patch.i0));
        let py = spread_length(ny, patch.j1.max(ny - patch.j0));
        if let Some(s) = self.spread_cache.get(&(px, py)) {
            return s.clone();
        }
        let start = Instant::now();
        let conv = Conv::padded((px / 2).min(nx), (py / 2).min(ny), px, py);
        let [zz, xx, yy, xy] = kernel_spectra(&conv, model.grid_tables(), nx);
        let coupling = match model.layer {
            Some(_) => {
                let tables = model.coupling_tables();
                // zx is odd in x and even in y, zy the reverse.
                [0, 1].map(|c| {
                    conv.odd_kernel_spectrum(|di, dj| {
                        let sign = if c == 0 { di.signum() } else { dj.signum() } as f64;
                        sign * tables[c][dj.unsigned_abs() * nx + di.unsigned_abs()]
                    })
                })
            }
            None => [Vec::new(), Vec::new()],
        };
        let spread = Arc::new(Spread {
            conv,
            zz,
            xx,
            yy,
            xy,
            coupling,
        });
        self.spread_cache.insert((px, py), spread.clone());
        self.kernel_s += start.elapsed().as_secs_f64();
        spread
    }

    /// The kernel spectra of an `nx × ny` window (cached by size).
    fn spectra(&mut self, model: &Model, nx: usize, ny: usize) -> Arc<Spectra> {
        if let Some(s) = self.cache.get(&(nx, ny)) {
            return s.clone();
        }
        let start = Instant::now();
        // A window lies inside the grid, so its offsets are among the grid's.
        let tables = model.grid_tables();
        let conv = Conv::new(nx, ny);
        let [zz, xx, yy, xy] = kernel_spectra(&conv, tables, model.grid.nx);
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
            self_xx_mm_per_kpa: tables[1][0],
            self_yy_mm_per_kpa: tables[2][0],
        });
        self.cache.insert((nx, ny), s.clone());
        self.kernel_s += start.elapsed().as_secs_f64();
        s
    }
}

impl Model {
    /// Influence coefficients of component `c` for the offsets (di, dj) in [0, nx) × [0, ny),
    /// row-major; the other signs follow from symmetry.
    fn table(&self, c: Component, nx: usize, ny: usize) -> Vec<f64> {
        let (cell, e, nu) = (
            self.grid.cell_mm,
            self.gel.youngs_modulus_kpa,
            self.gel.poisson_ratio,
        );
        let layer = self.layer.as_ref();
        (0..ny)
            .into_par_iter()
            .flat_map_iter(|dj| {
                (0..nx).map(move |di| {
                    let (x, y) = (di as f64 * cell, dj as f64 * cell);
                    let mut k = halfspace_cell(c, x, y, cell, e, nu);
                    if let Some(layer) = layer {
                        k += layer.at(c, x, y) * cell * cell;
                    }
                    k
                })
            })
            .collect()
    }

    /// The coefficient tables `[zz, xx, yy, xy]` of every offset on the grid (made on first
    /// use): the kernels of every window and spread.
    fn grid_tables(&self) -> &[Vec<f64>; 4] {
        self.grid_tables.get_or_init(|| {
            let (nx, ny) = (self.grid.nx, self.grid.ny);
            COMPONENTS.map(|c| self.table(c, nx, ny))
        })
    }

    /// The coupling tables `[zx, zy]` of every offset on the grid (made on first use).
    fn coupling_tables(&self) -> &[Vec<f64>; 2] {
        self.coupling_tables.get_or_init(|| {
            let (nx, ny) = (self.grid.nx, self.grid.ny);
            [Component::Zx, Component::Zy].map(|c| self.table(c, nx, ny))
        })
    }

    /// The surface's move into the gel caused by tractions (on the whole grid) that vanish
    /// outside `patch`, through the layer's coupling.
    fn uz_from_traction(&self, side: &mut Side, traction_kpa: &Pair, patch: Rect) -> Vec<f64> {
        let grid = self.grid;
        let spread = side.spread(self, patch);
        let [qx, qy] = [0, 1].map(|c| {
            cells(&grid, patch)
                .map(|k| traction_kpa[c][k])
                .collect::<Vec<_>>()
        });
        let mut uz = vec![0.0; grid.len()];
        spread.conv.spread_odd_pair_into(
            [&spread.coupling[0], &spread.coupling[1]],
            [&qx, &qy],
            (patch.width(), patch.height()),
            (patch.i0, patch.j0),
            (&mut uz, grid.nx),
        );
        uz
    }

    /// The surface's tangential move caused by pressures (on the whole grid) that vanish outside
    /// `patch`, through the layer's coupling.
    fn tangential_from_pressure(&self, side: &mut Side, pressure_kpa: &[f64], patch: Rect) -> Pair {
        let grid = self.grid;
        let spread = side.spread(self, patch);
        let p: Vec<f64> = cells(&grid, patch).map(|k| pressure_kpa[k]).collect();
        let (mut ux, mut uy) = (vec![0.0; grid.len()], vec![0.0; grid.len()]);
        spread.conv.spread_odd_to_pair_into(
            [&spread.coupling[0], &spread.coupling[1]],
            &p,
            (patch.width(), patch.height()),
            (patch.i0, patch.j0),
            ([&mut ux, &mut uy], grid.nx),
        );
        [ux, uy]
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
    /// at every step and Σ p dA is rescaled to the load, and δ comes out as that mean. A step
    /// that neither clips a cell nor adds one moves u = Kp by −τ K t (times the load rescaling),
    /// so such steps cost one convolution instead of two.
    fn solve_normal(
        &self,
        spectra: &Spectra,
        work: &mut NormalWork,
        offset_mm: f64,
        load_n: Option<f64>,
    ) -> Result<NormalSolution, ContactError> {
        let conv = &spectra.conv;
        let NormalWork {
            gap_mm,
            pressure_kpa: p,
            t,
            g,
            u_mm,
            kt_mm,
            p_old,
        } = work;
        let n = gap_mm.len();
        let da = self.grid.cell_area_mm2() * 1e-3; // N per kPa
        for v in [&mut *t, &mut *g, &mut *u_mm, &mut *kt_mm, &mut *p_old] {
            v.clear();
            v.resize(n, 0.0);
        }
        let (gap_mm, p, t, g, u_mm, kt_mm, p_old) = (
            gap_mm.as_slice(),
            p.as_mut_slice(),
            t.as_mut_slice(),
            g.as_mut_slice(),
            u_mm.as_mut_slice(),
            kt_mm.as_mut_slice(),
            p_old.as_mut_slice(),
        );
        let mut u_current = false;
        let mut g_old = 1.0;
        let mut conjugate = false;
        let mut change = f64::INFINITY;
        let mut convolutions = 0;
        for _ in 0..self.options.max_iterations {
            if !u_current {
                conv.apply_into(&spectra.zz, p, u_mm);
                convolutions += 1;
            }
            let mut sum_g = 0.0;
            let mut count = 0usize;
            for k in 0..n {
                g[k] = gap_mm[k] + u_mm[k];
                if p[k] > 0.0 {
                    sum_g += g[k];
                    count += 1;
                }
            }
            if count == 0 {
                return Err(self.out_of_validity("the contact set emptied"));
            }
            let mean_gap = match load_n {
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
                return Ok(NormalSolution {
                    offset_mm: mean_gap,
                    convolutions,
                });
            }
            conv.apply_into(&spectra.zz, t, kt_mm);
            convolutions += 1;
            // Under load control the response r = Kt − mean(Kt) over the contact set.
            let mean_r = if load_n.is_some() {
                (0..n)
                    .filter(|&k| p[k] > 0.0)
                    .map(|k| kt_mm[k])
                    .sum::<f64>()
                    / count as f64
            } else {
                0.0
            };
            let (mut gt, mut rt) = (0.0, 0.0);
            for k in 0..n {
                if p[k] > 0.0 {
                    gt += g[k] * t[k];
                    rt += (kt_mm[k] - mean_r) * t[k];
                }
            }
            let tau = gt / rt;
            let mut overlap = false;
            let mut clipped = false;
            p_old.copy_from_slice(p);
            for k in 0..n {
                if p[k] > 0.0 {
                    let v = p[k] - tau * t[k];
                    clipped |= v < 0.0;
                    p[k] = v.max(0.0);
                } else if g[k] < 0.0 {
                    p[k] -= tau * g[k];
                    overlap = true;
                }
            }
            conjugate = !overlap;
            if p.iter().all(|&v| v == 0.0) {
                // The step lifted every cell off (a guess far too stiff, e.g. a flat face pressed
                // uniformly): halve the previous pressures and restart the conjugate directions.
                for (v, old) in p.iter_mut().zip(p_old.iter()) {
                    *v = 0.5 * old;
                }
                conjugate = false;
                u_current = false;
                continue;
            }
            let factor = match load_n {
                Some(load) => load / (p.iter().sum::<f64>() * da),
                None => 1.0,
            };
            if load_n.is_some() {
                p.iter_mut().for_each(|v| *v *= factor);
            }
            u_current = !(overlap || clipped);
            if u_current {
                for (u, kt) in u_mm.iter_mut().zip(kt_mm.iter()) {
                    *u = factor * (*u - tau * kt);
                }
            }
            let sum_p: f64 = p.iter().sum();
            change = p
                .iter()
                .zip(p_old.iter())
                .map(|(a, b)| (a - b).abs())
                .sum::<f64>()
                / sum_p;
            if !change.is_finite() {
                return Err(self.out_of_validity("non-finite pressure in the normal problem"));
            }
            if change < self.options.normal_tolerance {
                return Ok(NormalSolution {
                    offset_mm: mean_gap,
                    convolutions,
                });
            }
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
    /// Both methods start from `initial_kpa` (the tractions extrapolated from the last two
    /// frames) and stop when the
    /// projected-gradient step ‖P(q + s/L) − q‖, L the largest eigenvalue of the tangential
    /// symbol, is below `tangential_tolerance` ‖μp‖. Returns the tractions, the slip increments
    /// and the convolutions spent.
    fn solve_tangential(
        &self,
        spectra: &Spectra,
        work: &mut NewtonWork,
        bound_kpa: &[f64],
        target_mm: [&[f64]; 2],
        initial_kpa: Pair,
    ) -> Result<(Pair, Pair, usize), ContactError> {
        let mut problem = Tangential {
            spectra,
            bound_kpa,
            target_mm,
            scale_kpa: bound_kpa.iter().map(|b| b * b).sum::<f64>().sqrt(),
            step_kpa_per_mm: 1.0 / spectra.tangential_lipschitz,
            tolerance: self.options.tangential_tolerance,
            max_iterations: self.options.max_iterations,
            convolutions: 0,
        };
        let mut q = initial_kpa;
        problem.project(&mut q);
        let outcome = if problem.scale_kpa == 0.0 {
            let mut s = problem.zeros();
            problem.slip_increment(&q, &mut s);
            Solved::Converged(q, s)
        } else {
            match self.options.tangential_method {
                TangentialMethod::SemismoothNewton => match problem.newton(q, work) {
                    // Newton stalled: the accelerated gradient from its best iterate.
                    Solved::Stalled(q, _) => problem.fista(q),
                    converged => converged,
                },
                TangentialMethod::Fista => problem.fista(q),
            }
        };
        match outcome {
            Solved::Converged(q, s) => Ok((q, s, problem.convolutions)),
            Solved::Stalled(_, residual) if !residual.is_finite() => {
                Err(self.out_of_validity("non-finite traction in the tangential problem"))
            }
            Solved::Stalled(_, residual) => Err(ContactError::NotConverged {
                solver: self.name,
                iterations: self.options.max_iterations,
                residual,
            }),
        }
    }
}

/// How the tangential problem of a frame is solved (both warm-started from the previous frame's
/// tractions, both to the same projected-gradient tolerance).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TangentialMethod {
    /// Semi-smooth Newton on the projected-gradient fixed point q = P(q + s/L), each step a
    /// symmetric positive definite system on the stick cells and the slip cells' tangential
    /// components, solved by preconditioned conjugate gradients with FFT products (Hintermüller,
    /// Ito & Kunisch, SIAM J. Optim. 13, 2002; for the frictional disk constraint Vollebregt,
    /// J. Optim. Theory Appl. 162, 2014). Falls back to FISTA if a Newton step stalls.
    SemismoothNewton,
    /// Accelerated projected gradient (FISTA, Beck & Teboulle 2009) with adaptive restart
    /// (O'Donoghue & Candès 2015), step 1/L.
    Fista,
}

/// Outcome of a tangential method: tractions and slip increments, or the best tractions found
/// and their residual.
enum Solved {
    Converged(Pair, Pair),
    Stalled(Pair, f64),
}

/// One frame's tangential problem on a window.
struct Tangential<'a> {
    spectra: &'a Spectra,
    bound_kpa: &'a [f64],
    target_mm: [&'a [f64]; 2],
    /// ‖μp‖ (kPa), the scale of the stopping test.
    scale_kpa: f64,
    /// The gradient step 1/L (kPa of traction per mm of slip).
    step_kpa_per_mm: f64,
    tolerance: f64,
    max_iterations: usize,
    convolutions: usize,
}

/// Buffers of the semi-smooth Newton method, kept from frame to frame.
#[derive(Debug, Default)]
struct NewtonWork {
    states: Vec<CellState>,
    /// d0, K d0, x, K x, r, z, p and K p of a step.
    scratch: [Pair; 8],
    /// The iterate of smallest residual.
    best_kpa: Pair,
}

/// A cell's state in a semi-smooth Newton step.
#[derive(Debug, Clone, Copy)]
enum CellState {
    /// No friction bound: the traction stays zero.
    Free,
    /// Inside the friction disk: both components are unknowns.
    Stick,
    /// On the disk: the traction's component along the unit vector `n` is held at the bound,
    /// the one across it is an unknown with the extra compliance `lambda_mm_per_kpa`
    /// = (1 − α)/(cα) from the projection's generalised Jacobian (α = μp/|z|, c = 1/L).
    Slip { n: [f64; 2], lambda_mm_per_kpa: f64 },
}

impl Tangential<'_> {
    fn zeros(&self) -> Pair {
        [
            vec![0.0; self.bound_kpa.len()],
            vec![0.0; self.bound_kpa.len()],
        ]
    }

    /// K q, into `out`.
    fn apply(&mut self, q: &Pair, out: &mut Pair) {
        let sp = self.spectra;
        let [ox, oy] = out;
        sp.conv.apply_pair_into(
            [&sp.xx, &sp.yy, &sp.xy],
            [&q[0], &q[1]],
            [ox.as_mut_slice(), oy.as_mut_slice()],
        );
        self.convolutions += 1;
    }

    /// Projects every cell's traction onto its friction disk.
    fn project(&self, q: &mut Pair) {
        for (k, &bound) in self.bound_kpa.iter().enumerate() {
            let norm = q[0][k].hypot(q[1][k]);
            if norm > bound {
                let f = if norm > 0.0 { bound / norm } else { 0.0 };
                q[0][k] *= f;
                q[1][k] *= f;
            }
        }
    }

    /// s = w − K q, into `s`.
    fn slip_increment(&mut self, q: &Pair, s: &mut Pair) {
        self.apply(q, s);
        for (component, target) in s.iter_mut().zip(self.target_mm) {
            for (v, w) in component.iter_mut().zip(target) {
                *v = w - *v;
            }
        }
    }

    /// Semi-smooth Newton (see [`TangentialMethod::SemismoothNewton`]). With z = q + c s,
    /// c = 1/L, the residual F = q − P(z) has the generalised Jacobian I − D(I − cK), D = I on
    /// stick cells (|z| < μp) and α(I − nnᵀ) on slip cells (n = z/|z|, α = μp/|z|). A Newton
    /// step fixes each slip cell's traction along n at the bound and solves, for the stick
    /// tractions and the slip cells' components along t ⊥ n, (ΠKΠ + Λ) v = b with
    /// Λ = (1 − α)/(cα) on the slip components: symmetric positive definite, so conjugate
    /// gradients with a Jacobi preconditioner and inexact (forcing √‖F‖) solves.
    fn newton(&mut self, q: Pair, work: &mut NewtonWork) -> Solved {
        let n = self.bound_kpa.len();
        let NewtonWork {
            states,
            scratch,
            best_kpa,
        } = work;
        states.clear();
        states.resize(n, CellState::Free);
        for v in scratch.iter_mut().flatten() {
            v.clear();
            v.resize(n, 0.0);
        }
        let [d0, kd0, x, kx, r, z, p, kp] = scratch;
        for (b, v) in best_kpa.iter_mut().zip(&q) {
            b.clone_from(v);
        }
        let mut q = q;
        let c = self.step_kpa_per_mm;
        let (kxx, kyy) = (
            self.spectra.self_xx_mm_per_kpa,
            self.spectra.self_yy_mm_per_kpa,
        );
        let mut s = self.zeros();
        let mut best_residual = f64::INFINITY;
        let mut since_best = 0;
        let mut corrected = false;
        self.slip_increment(&q, &mut s);
        for _ in 0..self.max_iterations {
            // Residual and cell states at q.
            let mut residual_sq = 0.0;
            for k in 0..n {
                let g = self.bound_kpa[k];
                let zk = [q[0][k] + c * s[0][k], q[1][k] + c * s[1][k]];
                let norm = zk[0].hypot(zk[1]);
                let projected = if norm > g {
                    let f = g / norm;
                    [zk[0] * f, zk[1] * f]
                } else {
                    zk
                };
                residual_sq += (q[0][k] - projected[0]).powi(2) + (q[1][k] - projected[1]).powi(2);
                states[k] = if g == 0.0 {
                    CellState::Free
                } else if norm <= g {
                    CellState::Stick
                } else {
                    CellState::Slip {
                        n: [zk[0] / norm, zk[1] / norm],
                        lambda_mm_per_kpa: (norm / g - 1.0) / c,
                    }
                };
            }
            let residual = residual_sq.sqrt() / self.scale_kpa;
            if !residual.is_finite() {
                return Solved::Stalled(q, residual);
            }
            if residual < self.tolerance {
                let stuck = !states.iter().any(|s| matches!(s, CellState::Slip { .. }));
                if corrected || !stuck {
                    return Solved::Converged(q, s);
                }
                corrected = true;
                self.correct_net_traction(states, &mut q, &mut s, [p, kp, z]);
                continue;
            }
            if residual < best_residual {
                best_residual = residual;
                for (b, v) in best_kpa.iter_mut().zip(&q) {
                    b.copy_from_slice(v);
                }
                since_best = 0;
            } else {
                since_best += 1;
                if since_best >= 3 {
                    return Solved::Stalled(std::mem::take(best_kpa), best_residual);
                }
            }
            // The fixed normal parts d0 on slip cells, and K d0.
            let mut any_d0 = false;
            for k in 0..n {
                let v = match states[k] {
                    CellState::Slip { n: nk, .. } => {
                        let a = self.bound_kpa[k] - (q[0][k] * nk[0] + q[1][k] * nk[1]);
                        any_d0 |= a != 0.0;
                        [a * nk[0], a * nk[1]]
                    }
                    _ => [0.0, 0.0],
                };
                d0[0][k] = v[0];
                d0[1][k] = v[1];
            }
            if any_d0 {
                self.apply(d0, kd0);
            } else {
                kd0.iter_mut().for_each(|v| v.fill(0.0));
            }
            // Right-hand side, projected on the unknowns.
            for k in 0..n {
                let v = match states[k] {
                    CellState::Free => [0.0, 0.0],
                    CellState::Stick => [s[0][k] - kd0[0][k], s[1][k] - kd0[1][k]],
                    CellState::Slip {
                        n: nk,
                        lambda_mm_per_kpa: lambda,
                    } => {
                        let t = [-nk[1], nk[0]];
                        let qt = q[0][k] * t[0] + q[1][k] * t[1];
                        // 1/(cα) = λ + 1/c.
                        let b = -qt * (lambda + 1.0 / c) - (kd0[0][k] * t[0] + kd0[1][k] * t[1]);
                        [b * t[0], b * t[1]]
                    }
                };
                r[0][k] = v[0];
                r[1][k] = v[1];
            }
            // Preconditioned conjugate gradients from v = 0.
            x.iter_mut().for_each(|v| v.fill(0.0));
            kx.iter_mut().for_each(|v| v.fill(0.0));
            let precondition = |r: &Pair, z: &mut Pair| {
                for k in 0..n {
                    let v = match states[k] {
                        CellState::Free => [0.0, 0.0],
                        CellState::Stick => [r[0][k] / kxx, r[1][k] / kyy],
                        CellState::Slip {
                            n: nk,
                            lambda_mm_per_kpa: lambda,
                        } => {
                            let t = [-nk[1], nk[0]];
                            let diag = t[0] * t[0] * kxx + t[1] * t[1] * kyy + lambda;
                            let rt = (r[0][k] * t[0] + r[1][k] * t[1]) / diag;
                            [rt * t[0], rt * t[1]]
                        }
                    };
                    z[0][k] = v[0];
                    z[1][k] = v[1];
                }
            };
            let dot = |a: &Pair, b: &Pair| -> f64 {
                (0..2)
                    .map(|c| a[c].iter().zip(&b[c]).map(|(u, v)| u * v).sum::<f64>())
                    .sum()
            };
            let forcing = residual.sqrt().min(0.1);
            let r0 = dot(r, r).sqrt();
            precondition(r, z);
            p.clone_from(z);
            let mut rz = dot(r, z);
            for _ in 0..self.max_iterations {
                if r0 == 0.0 {
                    break;
                }
                self.apply(p, kp);
                // A p = Π K p + Λ p, kept in r's slot after the step length is known.
                let mut p_ap = 0.0;
                for k in 0..n {
                    let ap = project_state(states[k], [kp[0][k], kp[1][k]], [p[0][k], p[1][k]]);
                    p_ap += p[0][k] * ap[0] + p[1][k] * ap[1];
                }
                if p_ap <= 0.0 || !p_ap.is_finite() {
                    break;
                }
                let alpha = rz / p_ap;
                for k in 0..n {
                    let ap = project_state(states[k], [kp[0][k], kp[1][k]], [p[0][k], p[1][k]]);
                    for c in 0..2 {
                        x[c][k] += alpha * p[c][k];
                        kx[c][k] += alpha * kp[c][k];
                        r[c][k] -= alpha * ap[c];
                    }
                }
                if dot(r, r).sqrt() <= forcing * r0 {
                    break;
                }
                precondition(r, z);
                let rz_next = dot(r, z);
                let beta = rz_next / rz;
                rz = rz_next;
                for c in 0..2 {
                    for (pk, zk) in p[c].iter_mut().zip(&z[c]) {
                        *pk = zk + beta * *pk;
                    }
                }
            }
            // The step, kept feasible.
            for c in 0..2 {
                for k in 0..n {
                    q[c][k] += d0[c][k] + x[c][k];
                }
            }
            self.project(&mut q);
            self.slip_increment(&q, &mut s);
        }
        Solved::Stalled(std::mem::take(best_kpa), best_residual)
    }

    /// Galerkin correction of a converged, fully stuck Newton iterate by a uniform traction on
    /// the stick cells (a two-dimensional deflation space, as in deflated conjugate gradients,
    /// Saad et al., SIAM J. Sci. Comput. 21, 2000): makes the slip increments sum to zero, so the
    /// net force is exact. A Krylov polynomial fitted to one symmetry class of modes can amplify
    /// round-off in another: a pure twist would otherwise carry a net force of 10⁻⁹ of its
    /// tractions.
    fn correct_net_traction(
        &mut self,
        states: &[CellState],
        q: &mut Pair,
        s: &mut Pair,
        [e, ke_x, ke_y]: [&mut Pair; 3],
    ) {
        let stick: Vec<usize> = (0..states.len())
            .filter(|&k| matches!(states[k], CellState::Stick))
            .collect();
        if stick.is_empty() {
            return;
        }
        for (c, ke) in [(0, &mut *ke_x), (1, &mut *ke_y)] {
            e.iter_mut().for_each(|v| v.fill(0.0));
            for &k in &stick {
                e[c][k] = 1.0;
            }
            self.apply(e, ke);
        }
        let sum = |f: &[f64]| stick.iter().map(|&k| f[k]).sum::<f64>();
        let (a, b, c, d) = (sum(&ke_x[0]), sum(&ke_y[0]), sum(&ke_x[1]), sum(&ke_y[1]));
        let (rx, ry) = (sum(&s[0]), sum(&s[1]));
        let det = a * d - b * c;
        let delta = [(rx * d - ry * b) / det, (a * ry - c * rx) / det];
        if !(delta[0].is_finite() && delta[1].is_finite()) {
            return;
        }
        for &k in &stick {
            q[0][k] += delta[0];
            q[1][k] += delta[1];
        }
        for comp in 0..2 {
            for (k, v) in s[comp].iter_mut().enumerate() {
                *v -= delta[0] * ke_x[comp][k] + delta[1] * ke_y[comp][k];
            }
        }
        if stick
            .iter()
            .any(|&k| q[0][k].hypot(q[1][k]) > self.bound_kpa[k])
        {
            self.project(q);
            self.slip_increment(q, s);
        }
    }

    /// FISTA with adaptive restart (see [`TangentialMethod::Fista`]) from `x`.
    fn fista(&mut self, mut x: Pair) -> Solved {
        let n = self.bound_kpa.len();
        let step = self.step_kpa_per_mm;
        let mut y = x.clone();
        let mut next = self.zeros();
        let mut u = self.zeros();
        let mut t: f64 = 1.0;
        let mut residual = f64::INFINITY;
        for _ in 0..self.max_iterations {
            self.apply(&y, &mut u);
            for c in 0..2 {
                for k in 0..n {
                    next[c][k] = y[c][k] - step * (u[c][k] - self.target_mm[c][k]);
                }
            }
            self.project(&mut next);
            let mut step_sq = 0.0;
            let mut restart_dot = 0.0;
            for c in 0..2 {
                for k in 0..n {
                    let d = next[c][k] - y[c][k];
                    step_sq += d * d;
                    restart_dot += (y[c][k] - next[c][k]) * (next[c][k] - x[c][k]);
                }
            }
            residual = step_sq.sqrt() / self.scale_kpa;
            if !residual.is_finite() {
                return Solved::Stalled(next, residual);
            }
            if residual < self.tolerance {
                self.slip_increment(&next, &mut u);
                return Solved::Converged(next, u);
            }
            if restart_dot > 0.0 {
                t = 1.0;
                y.clone_from(&next);
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
            std::mem::swap(&mut x, &mut next);
        }
        Solved::Stalled(x, residual)
    }
}

/// The Newton operator's cell block applied to a direction: Π (K p) + Λ p, with `kp` = (K p)
/// at the cell and `p` the direction there.
fn project_state(state: CellState, kp: [f64; 2], p: [f64; 2]) -> [f64; 2] {
    match state {
        CellState::Free => [0.0, 0.0],
        CellState::Stick => kp,
        CellState::Slip {
            n,
            lambda_mm_per_kpa: lambda,
        } => {
            let t = [-n[1], n[0]];
            let v = kp[0] * t[0] + kp[1] * t[1] + lambda * (p[0] * t[0] + p[1] * t[1]);
            [v * t[0], v * t[1]]
        }
    }
}

/// The whole-grid indices of the cells of `window`, row by row (of known length, so collecting
/// them allocates once).
fn cells(grid: &Grid, window: Rect) -> impl ExactSizeIterator<Item = usize> + use<> {
    let (nx, w) = (grid.nx, window.width());
    (0..w * window.height()).map(move |c| (window.j0 + c / w) * nx + window.i0 + c % w)
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

impl Model {
    /// The gap field fits the grid and holds no NaN.
    fn check_gap(&self, gap: &GapField) -> Result<(), ContactError> {
        if gap.grid != self.grid || gap.gap_mm.len() != self.grid.len() {
            return Err(self.out_of_validity("gap field or shifts do not match the solver grid"));
        }
        if gap.gap_mm.iter().any(|g| g.is_nan()) {
            return Err(self.out_of_validity("NaN in the gap field"));
        }
        Ok(())
    }

    /// The normal problem of a frame at `gap` after `previous` (the window around the candidate
    /// contact, enlarged until the contact stays inside it).
    fn normal_frame(
        &self,
        side: &mut Side,
        work: &mut NormalWork,
        input: (&GapField, NormalControl),
        previous: Option<NormalPast<'_>>,
    ) -> Result<Normal, ContactError> {
        let start = Instant::now();
        side.kernel_s = 0.0;
        let (gap, normal) = input;
        self.check_gap(gap)?;
        let grid = self.grid;
        let n = grid.len();
        let gap = &gap.gap_mm;
        let nearest_mm = gap.iter().copied().fold(f64::INFINITY, f64::min);
        let load_n = match normal {
            NormalControl::Approach => None,
            NormalControl::Force(f) if !f.is_finite() => {
                return Err(self.out_of_validity(format!("normal force {f} N")));
            }
            NormalControl::Force(f) if f <= 0.0 => return Ok(Normal::Free),
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
            return Ok(Normal::Free);
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

        // Candidate region: rigid penetration at the expected approach, and the last contact.
        let mut offset_mm = match (load_n, previous) {
            (None, _) => 0.0,
            (Some(_), Some(h)) => h.offset_mm,
            (Some(_), None) => nearest_mm + grid.cell_mm,
        };
        let last_contact = previous
            .filter(|_| self.options.warm_start)
            .and_then(|h| bbox(&grid, |k| h.pressure_kpa[k] > 0.0));
        let (mut core, mut grow) = match last_contact {
            // Along a trajectory the contact moves little between frames: the last contact with
            // a margin (the escape test below enlarges the window if it does move further).
            Some(last) => (last, 0.05),
            None => (
                bbox(&grid, |k| {
                    gap[k] < offset_mm || previous.is_some_and(|h| h.pressure_kpa[k] > 0.0)
                })
                .unwrap_or_else(|| bbox(&grid, |k| gap[k] <= nearest_mm).expect("a finite gap")),
                // On a half-space the surface only sinks under pressure, so the contact lies
                // inside the rigid penetration; a layer bulges around its contact and gets a
                // margin.
                if self.layer.is_some() { 0.25 } else { 0.0 },
            ),
        };
        let (mut convolutions, mut windows) = (0, 0);
        let (window, pressure_kpa, uz_into_mm) = loop {
            let window = window_around(&grid, core, grow);
            let spectra = side.spectra(self, window.width(), window.height());
            work.gap_mm.clear();
            work.gap_mm.extend(cells(&grid, window).map(|k| gap[k]));
            // Warm start: the last two frames' pressures extrapolated linearly in time; no
            // pressure where the indenter has moved away from a cell altogether.
            work.pressure_kpa.clear();
            work.pressure_kpa.extend(cells(&grid, window).map(|k| {
                match previous.filter(|_| self.options.warm_start) {
                    _ if !gap[k].is_finite() => 0.0,
                    Some(h) => match h.pressure_before_kpa {
                        Some(before) => (2.0 * h.pressure_kpa[k] - before[k]).max(0.0),
                        None => h.pressure_kpa[k],
                    },
                    None => 0.0,
                }
            }));
            let (gap_w, initial) = (&work.gap_mm, &mut work.pressure_kpa);
            if initial.iter().all(|&p| p == 0.0) {
                let penetrating = gap_w.iter().filter(|&&g| g < offset_mm).count().max(1);
                let radius_mm = (penetrating as f64 * grid.cell_area_mm2() / 3.0).sqrt();
                for (p, g) in initial.iter_mut().zip(gap_w) {
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
            let normal = self.solve_normal(&spectra, work, offset_mm, load_n)?;
            convolutions += normal.convolutions;
            windows += 1;
            offset_mm = normal.offset_mm;
            let pressure = embed(&grid, window, &work.pressure_kpa);
            let mut uz_into = vec![0.0; n];
            let spread = side.spread(self, window);
            spread.conv.spread_into(
                &spread.zz,
                &work.pressure_kpa,
                (window.width(), window.height()),
                (window.i0, window.j0),
                (&mut uz_into, grid.nx),
            );
            // Contact on the window's inner edge, or interpenetration outside the window,
            // means the window was too small.
            let depth_mm = (offset_mm - nearest_mm).max(grid.cell_mm * 1e-3);
            let mut escaped: Option<Rect> = None;
            for j in 0..grid.ny {
                let row = j * grid.nx;
                let inside_rows = (window.j0..window.j1).contains(&j);
                let edge_row = (j == window.j0 && j > 0) || (j + 1 == window.j1 && j + 1 < grid.ny);
                for i in 0..grid.nx {
                    let k = row + i;
                    let escapes = if inside_rows && (window.i0..window.i1).contains(&i) {
                        let on_inner_edge = edge_row
                            || (i == window.i0 && i > 0)
                            || (i + 1 == window.i1 && i + 1 < grid.nx);
                        on_inner_edge && pressure[k] > 0.0
                    } else {
                        gap[k] + uz_into[k] - offset_mm < -1e-6 * depth_mm
                    };
                    if escapes {
                        escaped = include(escaped, i, j);
                    }
                }
            }
            match escaped {
                None => break (window, pressure, uz_into),
                Some(out) => {
                    let contact = bbox(&grid, |k| pressure[k] > 0.0).unwrap_or(out);
                    core = core.union(out).union(contact);
                    if window.width() == grid.nx && window.height() == grid.ny {
                        return Err(self.out_of_validity("contact spreads beyond the grid"));
                    }
                    grow = (2.0 * grow).max(0.25);
                }
            }
        };
        let contact: Vec<bool> = pressure_kpa.iter().map(|&p| p > 0.0).collect();
        let (nx, ny) = (grid.nx, grid.ny);
        let touches_edge = (0..nx).any(|i| contact[i] || contact[(ny - 1) * nx + i])
            || (0..ny).any(|j| contact[j * nx] || contact[j * nx + nx - 1]);
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
        Ok(Normal::Pressed(NormalFrame {
            window,
            pressure_kpa,
            uz_into_mm,
            contact,
            offset_mm,
            load_controlled: load_n.is_some(),
            convolutions,
            windows,
            normal_s: start.elapsed().as_secs_f64(),
            kernel_s: side.kernel_s,
        }))
    }

    /// A frame on the bonded layer with friction: the normal problem (its gap moved by the
    /// surface's sinking under the last tractions) and the tangential one (its slip moved by the
    /// pressures' tangential displacement) solved in turn, each from the other's latest answer —
    /// block Gauss–Seidel on the coupled contact problem, the alternation of normal and
    /// tangential solves of Kalker's and Chen & Wang's (2008) boundary-element methods — until
    /// neither moves by [`COUPLING_TOLERANCE`]. `None`: nothing touches.
    fn coupled_frame(
        &self,
        (normal_side, normal_work): (&mut Side, &mut NormalWork),
        (tangential_side, newton_work): (&mut Side, &mut NewtonWork),
        input: &ContactInput,
        previous: Option<&History>,
    ) -> Result<Option<CoupledFrame>, ContactError> {
        let grid = self.grid;
        let traction_patch = |q: &Pair| {
            bbox(&grid, |k| q[0][k] != 0.0 || q[1][k] != 0.0).map(|r| padded_to(&grid, r, 8))
        };
        let sink_from = |side: &mut Side, q: &Pair| {
            traction_patch(q).map(|patch| self.uz_from_traction(side, q, patch))
        };
        let mut stats = BemStats::default();
        let mut last: Option<(NormalFrame, TangentialFrame)> = None;
        let mut moved = f64::INFINITY;
        for iteration in 1..=MAX_COUPLING_ITERATIONS {
            let traction = match &last {
                Some((_, t)) => Some(&t.traction_kpa),
                None => previous.map(|h| &h.traction_kpa),
            };
            let sink = traction.and_then(|q| sink_from(normal_side, q));
            let gap = match &sink {
                Some(uz) => GapField {
                    grid,
                    gap_mm: input
                        .gap
                        .gap_mm
                        .iter()
                        .zip(uz)
                        .map(|(g, u)| g + u)
                        .collect(),
                },
                None => input.gap.clone(),
            };
            let past = match &last {
                Some((n, _)) => Some(NormalPast {
                    pressure_kpa: &n.pressure_kpa,
                    pressure_before_kpa: None,
                    offset_mm: n.offset_mm,
                }),
                None => previous.map(History::normal_past),
            };
            let Normal::Pressed(normal) =
                self.normal_frame(normal_side, normal_work, (&gap, input.normal), past)?
            else {
                return Ok(None);
            };
            let patch = contact_patch(&grid, &normal);
            let from_pressure =
                self.tangential_from_pressure(tangential_side, &normal.pressure_kpa, patch);
            let tangential = self.tangential_frame(
                tangential_side,
                newton_work,
                input,
                &normal,
                previous,
                Some(Coupled {
                    from_pressure_mm: &from_pressure,
                    initial_kpa: last.as_ref().map(|(_, t)| &t.traction_kpa),
                }),
            )?;
            stats.normal_convolutions += normal.convolutions;
            stats.normal_windows += normal.windows;
            stats.tangential_convolutions += tangential.convolutions;
            stats.normal_s += normal.normal_s;
            stats.tangential_s += tangential.tangential_s;
            stats.kernel_s += normal.kernel_s + tangential.kernel_s;
            stats.coupling_iterations = iteration;
            // (a contact carrying no pressure settles at once instead of dividing by zero)
            let p_max = normal
                .pressure_kpa
                .iter()
                .fold(f64::MIN_POSITIVE, |m, &p| m.max(p));
            if let Some((n0, t0)) = &last {
                let dp = max_difference(&n0.pressure_kpa, &normal.pressure_kpa);
                let dq = (0..2)
                    .map(|c| max_difference(&t0.traction_kpa[c], &tangential.traction_kpa[c]))
                    .fold(0.0, f64::max);
                moved = (dp / p_max).max(dq / (self.gel.friction * p_max));
            }
            let settled = moved <= COUPLING_TOLERANCE;
            last = Some((normal, tangential));
            if settled {
                let (mut normal, tangential) = last.expect("just set");
                if let Some(uz) = sink_from(normal_side, &tangential.traction_kpa) {
                    normal
                        .uz_into_mm
                        .iter_mut()
                        .zip(uz)
                        .for_each(|(u, v)| *u += v);
                }
                return Ok(Some(CoupledFrame {
                    normal,
                    tangential,
                    stats,
                }));
            }
        }
        Err(ContactError::NotConverged {
            solver: self.name,
            iterations: MAX_COUPLING_ITERATIONS,
            residual: moved,
        })
    }

    /// The tangential problem of a frame whose normal contact is `normal`, after `previous`
    /// (with the layer's coupling: the surface's move caused by the pressures, `coupled`).
    fn tangential_frame(
        &self,
        side: &mut Side,
        work: &mut NewtonWork,
        input: &ContactInput,
        normal: &NormalFrame,
        previous: Option<&History>,
        coupled: Option<Coupled<'_>>,
    ) -> Result<TangentialFrame, ContactError> {
        let tangential_start = Instant::now();
        side.kernel_s = 0.0;
        let grid = self.grid;
        let n = grid.len();
        let NormalFrame {
            pressure_kpa,
            contact,
            ..
        } = normal;
        let patch = contact_patch(&grid, normal);
        let spectra = side.spectra(self, patch.width(), patch.height());
        let mu = self.gel.friction;
        let bound: Vec<f64> = cells(&grid, patch).map(|k| mu * pressure_kpa[k]).collect();
        let shift = &input.rigid_shift_mm;
        // The slip increment is (last displacement + rigid shift) − displacement now, of which
        // the pressures' part is known here.
        let from_pressure = |c: usize, k: usize| coupled.map_or(0.0, |d| d.from_pressure_mm[c][k]);
        let target = [0, 1].map(|c| -> Vec<f64> {
            match previous {
                Some(h) => cells(&grid, patch)
                    .map(|k| h.u_tangential_mm[c][k] + shift[k][c] - from_pressure(c, k))
                    .collect(),
                None => cells(&grid, patch)
                    .map(|k| shift[k][c] - from_pressure(c, k))
                    .collect(),
            }
        });
        let initial = [0, 1].map(|c| -> Vec<f64> {
            if let Some(q) = coupled.and_then(|d| d.initial_kpa) {
                return cells(&grid, patch).map(|k| q[c][k]).collect();
            }
            match previous.filter(|_| self.options.warm_start) {
                Some(h) => match &h.traction_before_kpa {
                    Some(before) => cells(&grid, patch)
                        .map(|k| 2.0 * h.traction_kpa[c][k] - before[c][k])
                        .collect(),
                    None => cells(&grid, patch).map(|k| h.traction_kpa[c][k]).collect(),
                },
                None => vec![0.0; bound.len()],
            }
        });
        let (traction_w, slip_increment, convolutions) =
            self.solve_tangential(&spectra, work, &bound, [&target[0], &target[1]], initial)?;
        let tangential_s = tangential_start.elapsed().as_secs_f64();
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
        let (mut ux, mut uy) = (vec![0.0; n], vec![0.0; n]);
        let spread = side.spread(self, patch);
        spread.conv.spread_pair_into(
            [&spread.xx, &spread.yy, &spread.xy],
            [&traction_w[0], &traction_w[1]],
            (patch.width(), patch.height()),
            (patch.i0, patch.j0),
            ([&mut ux, &mut uy], grid.nx),
        );
        if let Some(d) = coupled {
            for (u, v) in [&mut ux, &mut uy].into_iter().zip(d.from_pressure_mm) {
                u.iter_mut().zip(v).for_each(|(u, v)| *u += v);
            }
        }
        Ok(TangentialFrame {
            traction_kpa: traction,
            slip: (0..n).map(|k| contact[k] && slip_full[k] > 0.0).collect(),
            u_tangential_mm: [ux, uy],
            convolutions,
            tangential_s,
            kernel_s: side.kernel_s,
        })
    }
}

impl History {
    /// This frame's part in the next one's normal problem.
    fn normal_past(&self) -> NormalPast<'_> {
        NormalPast {
            pressure_kpa: &self.pressure_kpa,
            pressure_before_kpa: self.pressure_before_kpa.as_deref(),
            offset_mm: self.offset_mm,
        }
    }
}

impl Bem {
    /// Solves one frame after `previous` and, given `next`, that frame's normal problem beside
    /// this one's tangential problem; returns the fields and the history for the next frame
    /// (`None`: no contact, forget the path).
    fn solve_frame(
        &mut self,
        input: &ContactInput,
        previous: Option<&History>,
        next: Option<NextFrame<'_>>,
    ) -> Result<(Fields, Option<History>), ContactError> {
        let start = Instant::now();
        self.stats = BemStats::default();
        let model = &self.model;
        let grid = model.grid;
        model.check_gap(input.gap)?;
        if input.rigid_shift_mm.len() != grid.len() {
            return Err(model.out_of_validity("gap field or shifts do not match the solver grid"));
        }
        if input
            .rigid_shift_mm
            .iter()
            .flatten()
            .any(|s| !s.is_finite())
        {
            return Err(model.out_of_validity("non-finite rigid shift"));
        }
        // The bonded layer couples the normal and tangential problems; with friction they are
        // solved together, without a normal problem ahead (it would need this frame's tractions).
        let coupling = model.layer.is_some();
        if coupling && model.gel.friction > 0.0 {
            self.ahead = None;
            let coupled = model.coupled_frame(
                (&mut self.normal_side, &mut self.normal_work),
                (&mut self.tangential_side, &mut self.newton_work),
                input,
                previous,
            )?;
            let Some(frame) = coupled else {
                return Ok((Fields::zero(grid), None));
            };
            self.stats = frame.stats;
            return Ok(self.finish_frame(start, frame.normal, frame.tangential));
        }
        let normal = match self.ahead.take() {
            Some(ahead) if ahead.normal == input.normal && ahead.gap_mm == input.gap.gap_mm => {
                ahead.solved?
            }
            _ => model.normal_frame(
                &mut self.normal_side,
                &mut self.normal_work,
                (input.gap, input.normal),
                previous.map(History::normal_past),
            )?,
        };
        let Normal::Pressed(normal) = normal else {
            return Ok((Fields::zero(grid), None));
        };
        // The grid's tables are made before the two halves may both need them.
        model.grid_tables();
        // Frictionless, the coupling only moves the surface along it (the tractions stay zero).
        let from_pressure = coupling.then(|| {
            model.tangential_from_pressure(
                &mut self.tangential_side,
                &normal.pressure_kpa,
                contact_patch(&grid, &normal),
            )
        });
        let (tangential, ahead) = rayon::join(
            || {
                model.tangential_frame(
                    &mut self.tangential_side,
                    &mut self.newton_work,
                    input,
                    &normal,
                    previous,
                    from_pressure.as_ref().map(|u| Coupled {
                        from_pressure_mm: u,
                        initial_kpa: None,
                    }),
                )
            },
            || {
                next.map(|next| Ahead {
                    gap_mm: next.gap.gap_mm.clone(),
                    normal: next.normal,
                    solved: model.normal_frame(
                        &mut self.normal_side,
                        &mut self.normal_work,
                        (next.gap, next.normal),
                        Some(NormalPast {
                            pressure_kpa: &normal.pressure_kpa,
                            pressure_before_kpa: previous.map(|h| h.pressure_kpa.as_slice()),
                            offset_mm: normal.offset_mm,
                        }),
                    ),
                })
            },
        );
        let tangential = tangential?;
        self.ahead = ahead;
        self.stats = BemStats {
            normal_convolutions: normal.convolutions,
            normal_windows: normal.windows,
            tangential_convolutions: tangential.convolutions,
            normal_s: normal.normal_s,
            kernel_s: normal.kernel_s + tangential.kernel_s,
            tangential_s: tangential.tangential_s,
            coupling_iterations: 0,
            total_s: 0.0,
        };
        Ok(self.finish_frame(start, normal, tangential))
    }

    /// The fields and the next frame's history from a frame's normal and tangential solutions.
    fn finish_frame(
        &mut self,
        start: Instant,
        normal: NormalFrame,
        tangential: TangentialFrame,
    ) -> (Fields, Option<History>) {
        let grid = self.model.grid;
        let NormalFrame {
            pressure_kpa,
            uz_into_mm,
            contact,
            offset_mm,
            load_controlled,
            ..
        } = normal;
        let TangentialFrame {
            traction_kpa: [tx, ty],
            u_tangential_mm: [ux, uy],
            slip,
            ..
        } = tangential;
        let mut uz_mm = uz_into_mm;
        uz_mm.iter_mut().for_each(|u| *u = -*u);
        let mut fields = Fields {
            grid,
            ux_mm: ux.clone(),
            uy_mm: uy.clone(),
            uz_mm,
            pressure_kpa: pressure_kpa.clone(),
            traction_x_kpa: tx.clone(),
            traction_y_kpa: ty.clone(),
            slip,
            contact,
            force_n: [0.0; 3],
            approach_offset_mm: if load_controlled { offset_mm } else { 0.0 },
        };
        fields.force_n = fields.total_force_n();
        self.stats.total_s = start.elapsed().as_secs_f64();
        let history = History {
            pressure_before_kpa: None,
            traction_before_kpa: None,
            pressure_kpa,
            traction_kpa: [tx, ty],
            u_tangential_mm: [ux, uy],
            offset_mm,
        };
        (fields, Some(history))
    }
}

impl ContactSolver for Bem {
    fn name(&self) -> &'static str {
        self.model.name
    }

    fn solve(&mut self, input: &ContactInput) -> Result<Fields, ContactError> {
        self.solve_ahead(input, None)
    }

    fn solve_ahead(
        &mut self,
        input: &ContactInput,
        next: Option<NextFrame<'_>>,
    ) -> Result<Fields, ContactError> {
        let previous = self.history.take();
        match self.solve_frame(input, previous.as_ref(), next) {
            Ok((fields, history)) => {
                self.history = history.map(|mut h| {
                    if let Some(p) = previous {
                        h.pressure_before_kpa = Some(p.pressure_kpa);
                        h.traction_before_kpa = Some(p.traction_kpa);
                    }
                    h
                });
                Ok(fields)
            }
            Err(e) => {
                // A frame that fails leaves the history of the last good frame in place (and
                // no normal problem solved ahead from its own).
                self.history = previous;
                self.ahead = None;
                Err(e)
            }
        }
    }

    fn reset(&mut self) {
        self.history = None;
        self.ahead = None;
    }
}

#[cfg(test)]
mod tests {
    use std::alloc::{GlobalAlloc, Layout, System};
    use std::cell::Cell;

    use super::*;

    /// The system allocator, counting the allocations of each thread.
    struct Counting;

    thread_local! {
        static ALLOCATIONS: Cell<usize> = const { Cell::new(0) };
    }

    unsafe impl GlobalAlloc for Counting {
        unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
            ALLOCATIONS.with(|n| n.set(n.get() + 1));
            unsafe { System.alloc(layout) }
        }
        unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
            unsafe { System.dealloc(ptr, layout) }
        }
        unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
            ALLOCATIONS.with(|n| n.set(n.get() + 1));
            unsafe { System.realloc(ptr, layout, new_size) }
        }
    }

    #[global_allocator]
    static COUNTING: Counting = Counting;

    /// A frame of a press after another allocates nothing in the normal solve, and its force is
    /// Hertz's (F = 4/3 E* √R δ^3/2) to the grid's accuracy.
    #[test]
    fn a_warm_normal_solve_allocates_nothing() {
        let grid = Grid {
            nx: 64,
            ny: 64,
            cell_mm: 0.05,
        };
        let gel = Gel {
            youngs_modulus_kpa: 300.0,
            poisson_ratio: 0.48,
            thickness_mm: 3.0,
            friction: 1.0,
        };
        let radius_mm = 6.0;
        let mut bem = Bem::halfspace(gel, grid);
        let window = Rect {
            i0: 0,
            i1: grid.nx,
            j0: 0,
            j1: grid.ny,
        };
        let spectra = bem.normal_side.spectra(&bem.model, grid.nx, grid.ny);
        let gap_of = |depth_mm: f64| {
            cells(&grid, window).map(move |k| {
                let (i, j) = (k % grid.nx, k / grid.nx);
                let x = (i as f64 + 0.5 - 32.0) * grid.cell_mm;
                let y = (j as f64 + 0.5 - 32.0) * grid.cell_mm;
                (x * x + y * y) / (2.0 * radius_mm) - depth_mm
            })
        };
        let mut work = NormalWork::default();
        work.gap_mm.extend(gap_of(0.04));
        work.pressure_kpa
            .extend(work.gap_mm.iter().map(|g| (-g).max(0.0)));
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .expect("a pool");
        pool.install(|| {
            // The first frame sizes the buffers (which shows the count works).
            let start = ALLOCATIONS.with(Cell::get);
            bem.model
                .solve_normal(&spectra, &mut work, 0.0, None)
                .expect("the first frame converges");
            assert!(ALLOCATIONS.with(Cell::get) > start);
            let depth_mm = 0.05;
            let before = ALLOCATIONS.with(Cell::get);
            work.gap_mm.clear();
            work.gap_mm.extend(gap_of(depth_mm));
            let solved = bem
                .model
                .solve_normal(&spectra, &mut work, 0.0, None)
                .expect("the second frame converges");
            let allocations = ALLOCATIONS.with(Cell::get) - before;
            assert_eq!(allocations, 0, "allocations in a warm normal solve");
            assert!(solved.convolutions > 0);
            let force_n = work.pressure_kpa.iter().sum::<f64>() * grid.cell_area_mm2() * 1e-3;
            let hertz_n = 4.0 / 3.0
                * gel.effective_modulus_kpa()
                * radius_mm.sqrt()
                * depth_mm.powf(1.5)
                * 1e-3;
            assert!(
                (force_n / hertz_n - 1.0).abs() < 0.03,
                "force {force_n} N vs Hertz {hertz_n} N"
            );
        });
    }
}
