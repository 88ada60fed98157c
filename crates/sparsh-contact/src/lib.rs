//! Elastomer contact mechanics for vision-based tactile sensors: a ladder of solvers behind one
//! trait ([`ContactSolver`]), each returning the same ground truth ([`Fields`]).
//!
//! Conventions: the gel grid and camera frame of [`sparsh_scene::grid`]; pressure `p ≥ 0`
//! compresses the gel; tractions `qx, qy` are the shear stresses the indenter applies to the gel
//! surface along +x, +y; `uz < 0` where the surface is pushed towards the camera. Units: mm, kPa,
//! N (1 kPa · 1 mm² = 1 mN).
//!
//! Rungs: [`Geometric`] (no physics claims), [`Bem`] (`halfspace` and `layered`: boundary
//! elements with Polonsky–Keer normal contact and incremental Coulomb friction) and [`Fem`]
//! (finite strain: a neo-Hookean gel meshed in 3-D, the reference for deep presses). The BEM rungs
//! neglect normal–tangential coupling (Goodman's approximation, exact at ν = 0.5): `uz` comes from
//! the pressure, `ux, uy` from the tractions. [`mod@reference`] holds the analytic solutions and
//! [`validation`] the cases behind `sparsh validate`; [`study`] charts speed against accuracy.
#![warn(missing_docs)]

mod bem;
mod fem;
mod fft;
mod geometric;
mod kernels;
pub mod reference;
pub mod study;
pub mod validation;

use rayon::prelude::*;
use sparsh_scene::{GapField, Gel, Grid, Pose, SolverKind};

pub use bem::{Bem, BemOptions, BemStats, TangentialMethod};
pub use fem::{Fem, FemOptions, FemStats, NU_INCOMPRESSIBLE, NeoHookean};
pub use geometric::Geometric;

/// How the normal problem is driven in a frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum NormalControl {
    /// The gap field already holds the indenter's approach (displacement control).
    Approach,
    /// Find the extra rigid approach that gives this normal load (N).
    Force(f64),
}

/// What a solver gets for one frame.
#[derive(Debug, Clone, Copy)]
pub struct ContactInput<'a> {
    /// Gap at this frame's pose (mm; negative = penetration).
    pub gap: &'a GapField,
    /// Displacement or load control.
    pub normal: NormalControl,
    /// Rigid tangential displacement of the indenter's surface point above each cell since the
    /// previous frame (mm, [dx, dy] per cell); drives stick and slip.
    pub rigid_shift_mm: &'a [[f64; 2]],
}

/// The frame after the one being solved, as far as its normal problem needs it
/// ([`ContactSolver::solve_ahead`]).
#[derive(Debug, Clone, Copy)]
pub struct NextFrame<'a> {
    /// Gap at the next frame's pose (mm).
    pub gap: &'a GapField,
    /// Its displacement or load control.
    pub normal: NormalControl,
}

/// Stick/slip state of a whole contact.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SlipState {
    /// No cell in contact.
    NoContact,
    /// Every contact cell sticks.
    Stick,
    /// Some cells slip, some stick.
    Partial,
    /// Every contact cell slips.
    Gross,
}

impl SlipState {
    /// Classifies a contact from its masks.
    pub fn from_masks(contact: &[bool], slip: &[bool]) -> SlipState {
        let in_contact = contact.iter().filter(|&&c| c).count();
        let slipping = contact.iter().zip(slip).filter(|(c, s)| **c && **s).count();
        match (in_contact, slipping) {
            (0, _) => SlipState::NoContact,
            (_, 0) => SlipState::Stick,
            (n, s) if s == n => SlipState::Gross,
            _ => SlipState::Partial,
        }
    }

    /// Lower-case name used in labels.
    pub fn name(self) -> &'static str {
        match self {
            SlipState::NoContact => "no_contact",
            SlipState::Stick => "stick",
            SlipState::Partial => "partial",
            SlipState::Gross => "gross",
        }
    }
}

/// Ground truth of one frame on the gel grid (row-major, like [`Grid`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Fields {
    /// The gel grid.
    pub grid: Grid,
    /// Surface displacement along x (mm).
    pub ux_mm: Vec<f64>,
    /// Surface displacement along y (mm).
    pub uy_mm: Vec<f64>,
    /// Surface displacement along z (mm; negative towards the camera).
    pub uz_mm: Vec<f64>,
    /// Contact pressure (kPa, ≥ 0).
    pub pressure_kpa: Vec<f64>,
    /// Shear traction along x (kPa).
    pub traction_x_kpa: Vec<f64>,
    /// Shear traction along y (kPa).
    pub traction_y_kpa: Vec<f64>,
    /// Cells in contact.
    pub contact: Vec<bool>,
    /// Contact cells that slip.
    pub slip: Vec<bool>,
    /// Total force on the gel: [Σ qx dA, Σ qy dA, Σ p dA] (N); the normal load is positive.
    pub force_n: [f64; 3],
    /// Extra rigid approach found under load control (mm; 0 under displacement control).
    pub approach_offset_mm: f64,
}

impl Fields {
    /// All-zero fields: no contact.
    pub fn zero(grid: Grid) -> Fields {
        let n = grid.len();
        Fields {
            grid,
            ux_mm: vec![0.0; n],
            uy_mm: vec![0.0; n],
            uz_mm: vec![0.0; n],
            pressure_kpa: vec![0.0; n],
            traction_x_kpa: vec![0.0; n],
            traction_y_kpa: vec![0.0; n],
            contact: vec![false; n],
            slip: vec![false; n],
            force_n: [0.0; 3],
            approach_offset_mm: 0.0,
        }
    }

    /// Stick/slip state of the contact.
    pub fn slip_state(&self) -> SlipState {
        SlipState::from_masks(&self.contact, &self.slip)
    }

    /// Contact area (mm²).
    pub fn contact_area_mm2(&self) -> f64 {
        self.contact.iter().filter(|&&c| c).count() as f64 * self.grid.cell_area_mm2()
    }

    /// Sums tractions into [`Fields::force_n`] (kPa · mm² → N), in a fixed order.
    pub fn total_force_n(&self) -> [f64; 3] {
        let da = self.grid.cell_area_mm2() * 1e-3;
        let sum = |v: &[f64]| v.iter().sum::<f64>() * da;
        [
            sum(&self.traction_x_kpa),
            sum(&self.traction_y_kpa),
            sum(&self.pressure_kpa),
        ]
    }
}

/// A solver fails loudly instead of returning a quiet wrong answer.
#[derive(Debug, thiserror::Error)]
pub enum ContactError {
    /// An iterative method did not reach its tolerance.
    #[error("{solver}: no convergence after {iterations} iterations (residual {residual:.3e})")]
    NotConverged {
        /// Solver name.
        solver: &'static str,
        /// Iterations spent.
        iterations: usize,
        /// Final residual.
        residual: f64,
    },
    /// The requested state is outside what the model can represent.
    #[error("{solver}: outside validity: {reason}")]
    OutOfValidity {
        /// Solver name.
        solver: &'static str,
        /// Why.
        reason: String,
    },
}

/// One rung of the solver ladder. A solver keeps its own path history (previous tractions and
/// slip), so frames of one trajectory must be solved in order; [`ContactSolver::reset`] starts a
/// new trajectory.
pub trait ContactSolver: Send {
    /// Short name (`geometric`, …).
    fn name(&self) -> &'static str;
    /// Solves one frame.
    fn solve(&mut self, input: &ContactInput) -> Result<Fields, ContactError>;
    /// Solves one frame, and may start on `next` meanwhile: the boundary-element rungs solve the
    /// next frame's normal problem beside this frame's tangential one (it needs this frame's
    /// pressures, not its tractions) and use it when the next call's gap and control are
    /// `next`'s. Gives the same bits as [`ContactSolver::solve`].
    fn solve_ahead(
        &mut self,
        input: &ContactInput,
        next: Option<NextFrame<'_>>,
    ) -> Result<Fields, ContactError> {
        let _ = next;
        self.solve(input)
    }
    /// Forgets the path history.
    fn reset(&mut self);
}

/// The solver a scene asks for, on `grid`.
pub fn solver_for(kind: SolverKind, gel: &Gel, grid: Grid) -> Box<dyn ContactSolver> {
    match kind {
        SolverKind::Geometric => Box::new(Geometric::new(*gel, grid)),
        SolverKind::Halfspace => Box::new(Bem::halfspace(*gel, grid)),
        SolverKind::Layered => Box::new(Bem::layered(*gel, grid)),
        SolverKind::Fem => Box::new(Fem::new(*gel, grid)),
    }
}

/// Rigid tangential displacement (mm, [dx, dy] per cell) of the indenter's surface point above
/// each cell between two poses: the point at height `gap` (0 where nothing is above) is carried
/// from `previous` to `current` as a rigid body. This is [`ContactInput::rigid_shift_mm`].
/// The two rotations are built once (not per cell), and cells are independent tasks, so the
/// bits do not depend on the thread count.
pub fn rigid_shift_mm(previous: &Pose, current: &Pose, gap: &GapField) -> Vec<[f64; 2]> {
    let grid = gap.grid;
    let (to_previous, from_current) = (previous.rotation(), current.rotation().inverse());
    (0..grid.len())
        .into_par_iter()
        .with_min_len(4096)
        .map(|k| {
            let (i, j) = (k % grid.nx, k / grid.nx);
            let z = if gap.gap_mm[k].is_finite() {
                gap.gap_mm[k]
            } else {
                0.0
            };
            let point = glam::DVec3::new(grid.x_mm(i), grid.y_mm(j), z);
            let local = from_current * (point - current.position_mm);
            let moved = to_previous * local + previous.position_mm;
            [point.x - moved.x, point.y - moved.y]
        })
        .collect()
}
