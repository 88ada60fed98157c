//! The finite-strain rung: the gel as a nearly incompressible neo-Hookean solid meshed in 3-D,
//! bonded to the rigid window at its base, pressed by the rigid indenter.
//!
//! - **Material and element**: [`element`] — total-Lagrangian 8-node boxes with the
//!   mean-dilatation (Q1/P0) volumetric term, so ν → 0.5 does not lock.
//! - **Mesh**: [`mesh`] — a graded tensor-product grid covering the sensor grid plus a margin,
//!   with a uniform fine zone (`elements_per_radius` elements per contact radius) around the
//!   penetrating cells; rebuilt, with the state carried over by interpolation, when the contact
//!   leaves the fine zone or outgrows its resolution.
//! - **Contact**: node-to-rigid-surface. Each surface node's gap is the indenter height above
//!   its *deformed* position (bilinear in the gap field) minus its deflection; the normal
//!   constraint is enforced by an augmented Lagrangian (Alart & Curnier 1991; Wriggers,
//!   *Computational Contact Mechanics*, ch. 6), Coulomb friction by a penalty-regularised
//!   return map on the increment since the previous frame (the path history), with the friction
//!   bound μp fixed over each Newton solve and updated with the multipliers (Laursen & Simo
//!   1993), and once before a frame's first solve from the pressure its starting displacement
//!   predicts, so that nodes the indenter newly reaches do not enter that solve frictionless.
//! - **Solution**: for fixed multipliers the problem is the minimum of a potential (strain
//!   energy + contact + friction), solved by Newton with an Armijo backtracking line search on
//!   that potential (inverted elements count as infinite energy, so a step never inverts one),
//!   a step the line search shortened followed by one with slipping nodes' secant friction
//!   stiffness (a majorizer of the friction potential, so it cannot overshoot the stick disc);
//!   the Hessian is factorised by faer's sparse supernodal Cholesky in a nested-dissection order
//!   of the mesh, its symbolic analysis reused across iterations and frames, single-threaded so
//!   the answer does not depend on the thread count. The last factor preconditions conjugate
//!   gradients on later Newton systems (a modified Newton), and a fresh one is made when those
//!   stop converging fast, or straight away when many surface nodes changed their contact or
//!   friction state since it was made. A Hessian that is not positive definite (buckling, strong
//!   compression) is shifted (Levenberg) until it is.
//! - **Fields**: displacement, pressure and traction interpolated from the surface nodes onto the
//!   sensor grid at the material point that sits above each cell after deformation (Eulerian
//!   view, what the camera sees); forces are the nodal sums.

mod anderson;
mod element;
mod mesh;

use std::sync::Arc;
use std::time::Instant;

use faer::Par;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::perm::PermRef;
use faer::sparse::linalg::cholesky::{
    LltRef, SymbolicCholesky, SymmetricOrdering, factorize_symbolic_cholesky,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Side};
use rayon::prelude::*;
use sparsh_scene::{Gel, Grid};

use anderson::Anderson;
pub use element::NeoHookean;
use element::{Box8, ElementState, PACKED, evaluate_into, packed};
use mesh::{Mesh, graded_axis, graded_depth, locate};

use crate::{ContactError, ContactInput, ContactSolver, Fields, NormalControl};

/// Poisson ratio the rung uses for an exactly incompressible gel (κ/μ = 5000).
pub const NU_INCOMPRESSIBLE: f64 = 0.4999;

/// Mesh and iteration settings of the finite-element rung.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FemOptions {
    /// Elements per contact radius in the fine zone.
    pub elements_per_radius: f64,
    /// Size ratio of neighbouring elements outside the fine zone.
    pub growth: f64,
    /// Normal and tangential penalty as a multiple of E / (fine element size).
    pub penalty: f64,
    /// Newton iterations per solve before [`ContactError::NotConverged`].
    pub max_newton: usize,
    /// Multiplier updates per frame before [`ContactError::NotConverged`] (default 100: with
    /// the mixing of [`FemOptions::anderson_depth`] a frame of the study's δ/h = 0.05 slide at
    /// μ = 1.5 needs up to 26 at the rung's default mesh and 69 at the study reference's).
    pub max_updates: usize,
    /// The multiplier update stops when no node's pressure changes by more than this fraction
    /// of the peak pressure.
    pub pressure_tolerance: f64,
    /// Start each frame's Newton iteration from the previous frame's solution (else from rest).
    pub warm_start: bool,
    /// After a Newton step that the line search had to shorten, give slipping nodes their
    /// secant friction stiffness for the next step (see [`contact_terms`]); `false`: always the
    /// consistent tangent.
    pub slip_secant: bool,
    /// Give each solve's first Newton iteration the friction bounds of the pressure its starting
    /// displacement predicts, μ max(0, λ − ε g) (see [`Fem::solve_fixed`]); `false`: the last
    /// solve's bounds μλ.
    pub predict_bounds: bool,
    /// Surface nodes whose contact or friction state may differ from the kept factor's before a
    /// Newton step refactorises without trying the conjugate gradients (default 12, twice the
    /// conjugate gradients' iteration cap; the reason is at `MAX_CHANGED_NODES` in the source);
    /// `usize::MAX`: always try them first.
    pub max_changed_nodes: usize,
    /// Past multiplier updates mixed into the next one by Anderson acceleration (default 5; 0:
    /// the plain update λ ← max(0, λ − ε g)). With friction the pressures and friction bounds
    /// feed each other through the layer's normal–tangential coupling: on a slide at μ = 1.5
    /// the plain update settles slowly (41 updates a frame at the default mesh) or drifts away
    /// (at 12 elements per radius), which the mixing extrapolates.
    pub anderson_depth: usize,
}

impl Default for FemOptions {
    fn default() -> Self {
        FemOptions {
            elements_per_radius: 8.0,
            growth: 1.6,
            penalty: 100.0,
            max_newton: 60,
            max_updates: 100,
            pressure_tolerance: 1e-3,
            warm_start: true,
            slip_secant: true,
            predict_bounds: true,
            max_changed_nodes: MAX_CHANGED_NODES,
            anderson_depth: 5,
        }
    }
}

/// Work done on the last frame, and where its time went.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FemStats {
    /// Newton iterations.
    pub newton_iterations: usize,
    /// Sparse Cholesky factorisations of the Hessian (one per Newton iteration whose step the
    /// last factor could not give).
    pub factorizations: usize,
    /// Conjugate-gradient iterations preconditioned by the last factor.
    pub pcg_iterations: usize,
    /// Multiplier updates.
    pub updates: usize,
    /// Free degrees of freedom of the mesh.
    pub dofs: usize,
    /// Nonzeros of the Cholesky factor.
    pub factor_nonzeros: usize,
    /// Elements of the mesh.
    pub elements: usize,
    /// Times the mesh was rebuilt this frame.
    pub remeshes: usize,
    /// Seconds assembling the gradient and Hessian.
    pub assemble_s: f64,
    /// Seconds in numeric factorisations.
    pub factor_s: f64,
    /// Seconds in triangular solves and conjugate-gradient iterations.
    pub solve_s: f64,
    /// Seconds evaluating the potential in line searches.
    pub line_search_s: f64,
}

impl FemStats {
    /// Adds the work of `other` (its mesh sizes replace these).
    pub fn accumulate(&mut self, other: &FemStats) {
        self.newton_iterations += other.newton_iterations;
        self.factorizations += other.factorizations;
        self.pcg_iterations += other.pcg_iterations;
        self.updates += other.updates;
        self.remeshes += other.remeshes;
        self.assemble_s += other.assemble_s;
        self.factor_s += other.factor_s;
        self.solve_s += other.solve_s;
        self.line_search_s += other.line_search_s;
        self.dofs = other.dofs;
        self.factor_nonzeros = other.factor_nonzeros;
        self.elements = other.elements;
    }
}

/// The finite-strain rung (`solver = "fem"`).
pub struct Fem {
    gel: Gel,
    grid: Grid,
    material: NeoHookean,
    options: FemOptions,
    state: Option<State>,
    stats: FemStats,
    /// The double-precision Cholesky factor's buffer, reused across factorisations.
    factor_work: Vec<f64>,
}

/// The sparse Hessian's lower triangle (CSC) and its symbolic Cholesky.
struct System {
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    symbolic: Arc<SymbolicCholesky<usize>>,
    /// Per element, per entry of its Hessian's packed lower triangle (see [`packed`]): the
    /// position in `row_idx` of the global pair it adds to, or `u32::MAX` when the pair involves
    /// a fixed dof.
    scatter: Vec<[u32; PACKED]>,
}

/// Solution and path history on one mesh.
struct State {
    mesh: Mesh,
    system: Arc<System>,
    /// Displacement of every node (3 per node; the window's nodes stay 0).
    u: Vec<f64>,
    /// Augmented-Lagrangian multiplier per surface node (kPa).
    lambda: Vec<f64>,
    /// Friction bound μp per surface node for the current solve (kPa).
    bound: Vec<f64>,
    /// Friction traction (indenter on gel, reversed: gel on indenter) per surface node at the
    /// end of the previous frame (kPa).
    q_prev: Vec<[f64; 2]>,
    /// Surface nodes' tangential displacement at the end of the previous frame (mm).
    ut_prev: Vec<[f64; 2]>,
    /// Extra approach of the previous frame (load control's first guess; mm).
    offset_mm: f64,
    /// The last Cholesky factor of the Hessian on this mesh (values for `system.symbolic`), in
    /// single precision, kept to precondition later Newton steps.
    factor: Option<Vec<f32>>,
    /// Each surface node's Hessian block when the kept factor was made.
    factor_states: Vec<NodeState>,
}

/// The indenter above the gel for one frame: heights on the grid's cell centres, an extra
/// approach, and the rigid tangential shift since the previous frame.
struct Indenter<'a> {
    grid: Grid,
    height_mm: &'a [f64],
    approach_mm: f64,
    shift_mm: &'a [[f64; 2]],
}

/// Tangential penalty over the normal one: the stick springs add about 0.4 % to the contact's
/// tangential compliance at 8 elements per radius, and the stick/slip kink stays mild enough for
/// Newton.
const TANGENTIAL_PENALTY: f64 = 0.25;

/// Thickest gel, in contact radii, the rung meshes once the contact is resolved (2 cells).
const THICK_BLOCK: f64 = 20.0;

/// Height treated as "nothing above" (mm) where the gap is not finite or off the grid.
const FAR_MM: f64 = 1e3;

impl Indenter<'_> {
    /// Bilinear height of the indenter above (x, y) and its slope, lowered by the approach.
    fn height(&self, x: f64, y: f64) -> (f64, f64, f64) {
        let g = self.grid;
        let fx = x / g.cell_mm + g.nx as f64 / 2.0 - 0.5;
        let fy = y / g.cell_mm + g.ny as f64 / 2.0 - 0.5;
        if !(fx >= 0.0 && fy >= 0.0 && fx <= (g.nx - 1) as f64 && fy <= (g.ny - 1) as f64) {
            return (FAR_MM, 0.0, 0.0);
        }
        let i = (fx.floor() as usize).min(g.nx.saturating_sub(2));
        let j = (fy.floor() as usize).min(g.ny.saturating_sub(2));
        let (tx, ty) = (fx - i as f64, fy - j as f64);
        let at = |i: usize, j: usize| {
            let v = self.height_mm[j * g.nx + i];
            if v.is_finite() { v.min(FAR_MM) } else { FAR_MM }
        };
        let (h00, h10, h01, h11) = (at(i, j), at(i + 1, j), at(i, j + 1), at(i + 1, j + 1));
        let h = h00 * (1.0 - tx) * (1.0 - ty)
            + h10 * tx * (1.0 - ty)
            + h01 * (1.0 - tx) * ty
            + h11 * tx * ty;
        let hx = ((h10 - h00) * (1.0 - ty) + (h11 - h01) * ty) / g.cell_mm;
        let hy = ((h01 - h00) * (1.0 - tx) + (h11 - h10) * tx) / g.cell_mm;
        (h - self.approach_mm, hx, hy)
    }

    /// Bilinear rigid shift at (x, y) (zero off the grid).
    fn shift(&self, x: f64, y: f64) -> [f64; 2] {
        let g = self.grid;
        let fx = (x / g.cell_mm + g.nx as f64 / 2.0 - 0.5).clamp(0.0, (g.nx - 1) as f64);
        let fy = (y / g.cell_mm + g.ny as f64 / 2.0 - 0.5).clamp(0.0, (g.ny - 1) as f64);
        let i = (fx.floor() as usize).min(g.nx.saturating_sub(2));
        let j = (fy.floor() as usize).min(g.ny.saturating_sub(2));
        let (tx, ty) = (fx - i as f64, fy - j as f64);
        let at =
            |i: usize, j: usize, c: usize| self.shift_mm.get(j * g.nx + i).map_or(0.0, |s| s[c]);
        let mut out = [0.0; 2];
        for (c, o) in out.iter_mut().enumerate() {
            *o = at(i, j, c) * (1.0 - tx) * (1.0 - ty)
                + at(i + 1, j, c) * tx * (1.0 - ty)
                + at(i, j + 1, c) * (1.0 - tx) * ty
                + at(i + 1, j + 1, c) * tx * ty;
        }
        out
    }
}

/// The friction Hessian of a slipping node (see [`contact_terms`]).
#[derive(Debug, Clone, Copy, PartialEq)]
enum SlipStiffness {
    /// The consistent tangent A e_t b/|t| (I − d dᵀ): none along the slip.
    Consistent,
    /// The secant A e_t b/|t| in both tangential directions.
    Secant,
}

/// A potential's value, gradient over the free dofs and (optionally) Hessian values.
struct Assembled {
    energy: f64,
    /// Largest nodal contact force (mN).
    peak_contact_force: f64,
    gradient: Vec<f64>,
    hessian: Vec<f64>,
    /// Each surface node's contact and friction state (which Hessian block it contributed).
    node_states: Vec<NodeState>,
}

/// What failed inside a solve.
enum Failure {
    /// Newton's cap (the residual: the largest nodal force, mN).
    NotConverged {
        iterations: usize,
        residual: f64,
    },
    /// The multiplier updates' cap (the residual: the last update's largest pressure or bound
    /// change over the peak pressure).
    Updates {
        updates: usize,
        residual: f64,
    },
    Inverted,
}

impl Fem {
    /// The rung for `gel` on `grid`.
    pub fn new(gel: Gel, grid: Grid) -> Fem {
        let nu = gel.poisson_ratio.min(NU_INCOMPRESSIBLE);
        Fem {
            gel,
            grid,
            material: NeoHookean::from_young(gel.youngs_modulus_kpa, nu),
            options: FemOptions::default(),
            state: None,
            stats: FemStats::default(),
            factor_work: Vec::new(),
        }
    }

    /// Replaces the mesh and iteration settings.
    pub fn with_options(mut self, options: FemOptions) -> Fem {
        self.options = options;
        self
    }

    /// Work done on the last frame.
    pub fn stats(&self) -> FemStats {
        self.stats
    }

    /// Element size of the fine zone for a contact of radius `radius_mm`: `elements_per_radius`
    /// per radius, but no finer than the grid the fields are sampled on and no coarser than
    /// half the gel.
    fn fine_mm(&self, radius_mm: f64) -> f64 {
        (radius_mm / self.options.elements_per_radius)
            .max(self.grid.cell_mm)
            .min(self.gel.thickness_mm / 2.0)
    }

    /// Penalty (kPa/mm) on a mesh.
    fn penalty(&self, mesh: &Mesh) -> f64 {
        self.options.penalty * self.gel.youngs_modulus_kpa / mesh.fine_mm
    }

    /// The mesh for a contact whose penetrating cells span `bbox` = [x0, x1, y0, y1] with an
    /// equivalent radius `radius_mm`.
    fn build_mesh(&self, bbox: [f64; 4], radius_mm: f64) -> Mesh {
        let h = self.gel.thickness_mm;
        let fine = self.fine_mm(radius_mm);
        let pad = 0.3 * radius_mm + 2.0 * fine;
        let zone = [bbox[0] - pad, bbox[1] + pad, bbox[2] - pad, bbox[3] + pad];
        // The layer's displacements decay within a few thicknesses of the contact, a thick
        // block's as 1/r² beyond a few contact radii.
        let margin = 2.0 * h.min(10.0 * radius_mm) + 2.0 * radius_mm;
        let half_x = self.grid.nx as f64 * self.grid.cell_mm / 2.0;
        let half_y = self.grid.ny as f64 * self.grid.cell_mm / 2.0;
        let growth = self.options.growth;
        Mesh {
            x: graded_axis(
                (-half_x).min(zone[0] - margin),
                half_x.max(zone[1] + margin),
                zone[0],
                zone[1],
                fine,
                growth,
            ),
            y: graded_axis(
                (-half_y).min(zone[2] - margin),
                half_y.max(zone[3] + margin),
                zone[2],
                zone[3],
                fine,
                growth,
            ),
            z: graded_depth(h, fine, growth, 6),
            fine_zone: zone,
            fine_mm: fine,
        }
    }

    /// The state on `mesh`, carried over from `old` by interpolation (or at rest).
    fn new_state(&self, mesh: Mesh, old: Option<&State>) -> State {
        let system = Arc::new(build_system(&mesh));
        let surface = mesh.x.len() * mesh.y.len();
        let mut state = State {
            u: vec![0.0; 3 * mesh.nodes()],
            lambda: vec![0.0; surface],
            bound: vec![0.0; surface],
            q_prev: vec![[0.0; 2]; surface],
            ut_prev: vec![[0.0; 2]; surface],
            offset_mm: old.map_or(0.0, |o| o.offset_mm),
            factor: None,
            factor_states: Vec::new(),
            mesh,
            system,
        };
        if let Some(old) = old {
            let m = &state.mesh;
            for n in 0..m.nodes() {
                let p = m.position(n);
                let v = old.interpolate_volume(p);
                state.u[3 * n..3 * n + 3].copy_from_slice(&v);
            }
            for n in 0..surface {
                let p = m.position(n);
                let s = old.interpolate_surface(p[0], p[1]);
                state.lambda[n] = s.lambda;
                state.bound[n] = s.bound;
                state.q_prev[n] = s.q_prev;
                state.ut_prev[n] = s.ut_prev;
            }
        }
        state
    }

    /// Assembles the potential at `u` (fixed multipliers and friction bounds), with its Hessian
    /// when `hessian` says which slip stiffness it takes.
    fn assemble(
        &self,
        st: &State,
        u: &[f64],
        ind: &Indenter,
        hessian: Option<SlipStiffness>,
    ) -> Result<Assembled, Failure> {
        let mesh = &st.mesh;
        let sys = &st.system;
        let [nx, ny, _] = mesh.counts();
        let nfree = mesh.free_dofs();
        let mut gradient = vec![0.0; nfree];
        let mut values = if hessian.is_some() {
            vec![0.0; sys.row_idx.len()]
        } else {
            Vec::new()
        };
        let mut energy = 0.0;
        let (ex, ey) = (nx - 1, ny - 1);
        let n_el = mesh.elements();
        const CHUNK: usize = 2048;
        // Elements are evaluated in parallel into `terms`, then added in element order, so the
        // sums do not depend on the thread count.
        let mut terms = vec![ElementState::default(); CHUNK.min(n_el)];
        for start in (0..n_el).step_by(CHUNK) {
            let chunk = &mut terms[..(start + CHUNK).min(n_el) - start];
            chunk
                .par_iter_mut()
                .enumerate()
                .try_for_each(|(offset, out)| {
                    let e = start + offset;
                    let (i, j, k) = (e % ex, (e / ex) % ey, e / (ex * ey));
                    let nodes = mesh.element_nodes(i, j, k);
                    let b = Box8::new(mesh.element_size(i, j, k));
                    let mut ue = [[0.0; 3]; 8];
                    for (a, &n) in nodes.iter().enumerate() {
                        ue[a].copy_from_slice(&u[3 * n..3 * n + 3]);
                    }
                    evaluate_into(&self.material, &b, &ue, hessian.is_some(), out)
                        .map_err(|_| Failure::Inverted)
                })?;
            for (offset, s) in chunk.iter().enumerate() {
                let e = start + offset;
                let (i, j, k) = (e % ex, (e / ex) % ey, e / (ex * ey));
                energy += s.energy;
                for (a, &n) in mesh.element_nodes(i, j, k).iter().enumerate() {
                    if 3 * n < nfree {
                        for c in 0..3 {
                            gradient[3 * n + c] += s.gradient[a * 3 + c];
                        }
                    }
                }
                if hessian.is_some() {
                    for (&slot, &h) in sys.scatter[e].iter().zip(&s.hessian) {
                        if slot != u32::MAX {
                            values[slot as usize] += h;
                        }
                    }
                }
            }
        }
        // Contact and friction on the surface nodes (k = 0).
        let eps = self.penalty(mesh);
        let mut peak_contact_force = 0.0f64;
        let mut node_states = Vec::with_capacity(nx * ny);
        for n in 0..nx * ny {
            let (i, j) = (n % nx, n / nx);
            let area = mesh.surface_area_mm2(i, j);
            let c = contact_terms(
                st,
                n,
                area,
                eps,
                &u[3 * n..3 * n + 3],
                [mesh.x[i], mesh.y[j]],
                ind,
                hessian.unwrap_or(SlipStiffness::Consistent),
            );
            energy += c.energy;
            peak_contact_force = peak_contact_force.max(area * c.pressure);
            node_states.push(c.state);
            for d in 0..3 {
                gradient[3 * n + d] += c.gradient[d];
            }
            if hessian.is_some() {
                for col in 0..3 {
                    let base = sys.col_ptr[3 * n + col];
                    // Column 3n + col holds rows 3n + col, 3n + col + 1, … first (ascending).
                    for row in col..3 {
                        values[base + (row - col)] += c.hessian[row][col];
                    }
                }
            }
        }
        Ok(Assembled {
            energy,
            peak_contact_force,
            gradient,
            hessian: values,
            node_states,
        })
    }

    /// The potential alone at `u` (line searches).
    fn energy(&self, st: &State, u: &[f64], ind: &Indenter) -> Result<f64, Failure> {
        let mesh = &st.mesh;
        let [nx, ny, _] = mesh.counts();
        let (ex, ey) = (nx - 1, ny - 1);
        let parts: Vec<Result<f64, Failure>> = (0..mesh.elements())
            .into_par_iter()
            .map(|e| {
                let (i, j, k) = (e % ex, (e / ex) % ey, e / (ex * ey));
                let nodes = mesh.element_nodes(i, j, k);
                let mut ue = [[0.0; 3]; 8];
                for (a, &n) in nodes.iter().enumerate() {
                    ue[a].copy_from_slice(&u[3 * n..3 * n + 3]);
                }
                element::energy(&self.material, &Box8::new(mesh.element_size(i, j, k)), &ue)
                    .map_err(|_| Failure::Inverted)
            })
            .collect();
        let mut energy = 0.0;
        for p in parts {
            energy += p?;
        }
        let eps = self.penalty(mesh);
        for n in 0..nx * ny {
            let (i, j) = (n % nx, n / nx);
            let area = mesh.surface_area_mm2(i, j);
            let xy = [mesh.x[i], mesh.y[j]];
            energy += contact_terms(
                st,
                n,
                area,
                eps,
                &u[3 * n..3 * n + 3],
                xy,
                ind,
                SlipStiffness::Consistent,
            )
            .energy;
        }
        Ok(energy)
    }

    /// Minimises the potential for fixed multipliers: Newton with a backtracking line search. A
    /// step the line search shortened is followed by one with slipping nodes' secant stiffness
    /// (when [`FemOptions::slip_secant`]): it cannot carry their friction through the stick
    /// disc, where the consistent tangent, flat along the slip, overshoots; a full step returns
    /// to the consistent tangent and its quadratic convergence.
    fn newton(&mut self, st: &mut State, ind: &Indenter) -> Result<(), Failure> {
        let nfree = st.mesh.free_dofs();
        let length = ind_scale(st);
        // Nodal forces below 1e-5 of the largest contact force (and below 1e-8 of E times a
        // fine element's face, round-off of the volumetric terms) are noise (mN).
        let floor = 1e-8 * self.gel.youngs_modulus_kpa * st.mesh.fine_mm.powi(2);
        let mut slip = SlipStiffness::Consistent;
        for it in 0..self.options.max_newton {
            let clock = Instant::now();
            let a = self.assemble(st, &st.u, ind, Some(slip))?;
            self.stats.assemble_s += clock.elapsed().as_secs_f64();
            let residual = a.gradient.iter().fold(0.0f64, |m, g| m.max(g.abs()));
            if residual <= (1e-5 * a.peak_contact_force).max(floor) {
                return Ok(());
            }
            self.stats.newton_iterations += 1;
            let step = self.newton_step(st, &a);
            let clock = Instant::now();
            let slope: f64 = step.iter().zip(&a.gradient).map(|(s, g)| s * g).sum();
            let step_max = step.iter().fold(0.0f64, |m, s| m.max(s.abs()));
            if step_max <= 1e-10 * length {
                return Ok(());
            }
            let mut alpha = 1.0;
            let mut accepted = false;
            let mut trial = st.u.clone();
            for _ in 0..40 {
                for (t, (u, s)) in trial[..nfree]
                    .iter_mut()
                    .zip(st.u[..nfree].iter().zip(&step))
                {
                    *t = u + alpha * s;
                }
                if self
                    .energy(st, &trial, ind)
                    .is_ok_and(|e| e <= a.energy + 1e-4 * alpha * slope)
                {
                    accepted = true;
                    break;
                }
                // Near the solution the energy's decrease drowns in round-off: accept the full
                // step when it shrinks the residual instead.
                if alpha == 1.0
                    && -slope <= 1e-10 * a.energy.abs()
                    && self.assemble(st, &trial, ind, None).is_ok_and(|t| {
                        t.gradient.iter().fold(0.0f64, |m, g| m.max(g.abs())) < 0.5 * residual
                    })
                {
                    accepted = true;
                    break;
                }
                alpha *= 0.5;
            }
            self.stats.line_search_s += clock.elapsed().as_secs_f64();
            if !accepted {
                let residual = a.gradient.iter().fold(0.0f64, |m, g| m.max(g.abs()));
                return Err(Failure::NotConverged {
                    iterations: it + 1,
                    residual,
                });
            }
            st.u = trial;
            slip = if self.options.slip_secant && alpha < 1.0 {
                SlipStiffness::Secant
            } else {
                SlipStiffness::Consistent
            };
            if alpha == 1.0 && step_max <= 1e-8 * length {
                return Ok(());
            }
        }
        let a = self.assemble(st, &st.u, ind, None)?;
        Err(Failure::NotConverged {
            iterations: self.options.max_newton,
            residual: a.gradient.iter().fold(0.0f64, |m, g| m.max(g.abs())),
        })
    }

    /// Conjugate gradients for H x = `rhs` preconditioned by `factor`, timed and counted;
    /// `None` when they do not converge.
    fn preconditioned_step(
        &mut self,
        system: &System,
        factor: &[f32],
        a: &Assembled,
        rhs: &[f64],
    ) -> Option<Vec<f64>> {
        let clock = Instant::now();
        let solved = pcg(system, factor, &a.hessian, rhs);
        self.stats.solve_s += clock.elapsed().as_secs_f64();
        match solved {
            Ok((x, iterations)) => {
                self.stats.pcg_iterations += iterations;
                Some(x)
            }
            Err(iterations) => {
                self.stats.pcg_iterations += iterations;
                None
            }
        }
    }

    /// The Newton step H s = −g: conjugate gradients preconditioned by the last factor while it
    /// converges within [`PCG_ITERATIONS`] to a relative residual of [`PCG_TOLERANCE`] (a
    /// modified Newton that refactorises only when the Hessian has moved: across multiplier
    /// updates and warm-started frames it changes little), else a fresh factorisation — made
    /// without trying the conjugate gradients when [`FemOptions::max_changed_nodes`] or more
    /// surface nodes changed their contact or friction state since the kept factor was made.
    /// The factorisation is in single precision and its step too is found by the conjugate
    /// gradients (1–3 iterations); only when it fails is H factorised in double precision.
    fn newton_step(&mut self, st: &mut State, a: &Assembled) -> Vec<f64> {
        let mut step: Vec<f64> = a.gradient.iter().map(|g| -g).collect();
        let changed = st
            .factor_states
            .iter()
            .zip(&a.node_states)
            .filter(|(kept, now)| kept != now)
            .count();
        if let Some(factor) = st
            .factor
            .as_ref()
            .filter(|_| changed < self.options.max_changed_nodes)
            && let Some(x) = self.preconditioned_step(&st.system, factor, a, &step)
        {
            return x;
        }
        st.factor_states.clone_from(&a.node_states);
        let kept = st.factor.get_or_insert_with(Vec::new);
        let clock = Instant::now();
        let factorized = factorize_single(&st.system, &a.hessian, kept);
        self.stats.factor_s += clock.elapsed().as_secs_f64();
        self.stats.factorizations += 1;
        if factorized && let Some(x) = self.preconditioned_step(&st.system, kept, a, &step) {
            return x;
        }
        // No positive pivot in single precision, or no step from its factor (negative
        // curvature): the double-precision factor, shifted until positive definite, and its
        // direct step.
        let clock = Instant::now();
        factorize_shifted(&st.system, &a.hessian, &mut self.factor_work);
        self.stats.factor_s += clock.elapsed().as_secs_f64();
        self.stats.factorizations += 1;
        let clock = Instant::now();
        solve_with(&st.system, &self.factor_work, &mut step);
        self.stats.solve_s += clock.elapsed().as_secs_f64();
        kept.clear();
        kept.extend(self.factor_work.iter().map(|&v| v as f32));
        step
    }

    /// Solves one frame on the current mesh: Newton solves alternating with multiplier updates.
    ///
    /// With [`FemOptions::predict_bounds`] the friction bounds are updated once before the first
    /// solve, from the pressure the starting displacement (the last frame's, or the last ramp
    /// step's) gives under this frame's indenter, μ max(0, λ − ε g): the same formula as the
    /// update after a solve. Otherwise a node the indenter newly reaches enters the first solve
    /// frictionless (its bound μλ is 0) and gets its bound only at the first update, a jump of up
    /// to 25 kPa that the next Newton solve needs 4–11 line-searched steps to absorb. The
    /// converged frame is the same to the multiplier tolerance (both end when no pressure and no
    /// bound changes by more than it).
    ///
    /// From the second update on, the multipliers are the Anderson mixing
    /// ([`FemOptions::anderson_depth`]) of the last updates, kept non-negative, and the bounds μ
    /// times them; the mixing restarts whenever the norm of the pressure change grows. The frame
    /// ends on the plain update's change, so the converged frame is the same to the tolerance.
    /// Failing to settle within [`FemOptions::max_updates`] is [`Failure::Updates`], with the
    /// last change relative to the peak pressure.
    fn solve_fixed(&mut self, st: &mut State, ind: &Indenter) -> Result<(), Failure> {
        let eps = self.penalty(&st.mesh);
        if self.options.predict_bounds {
            let predicted = surface_pressures(st, ind, eps);
            for (b, p) in st.bound.iter_mut().zip(predicted) {
                *b = self.gel.friction * p;
            }
        }
        let mut anderson = Anderson::new(self.options.anderson_depth);
        let (mut last_norm, mut relative) = (f64::INFINITY, f64::NAN);
        for update in 0..self.options.max_updates {
            self.newton(st, ind)?;
            self.stats.updates += 1;
            let pressures = surface_pressures(st, ind, eps);
            let peak = pressures.iter().fold(0.0f64, |m, &p| m.max(p));
            let change = pressures
                .iter()
                .zip(&st.lambda)
                .fold(0.0f64, |m, (p, l)| m.max((p - l).abs()));
            let bound_change = pressures
                .iter()
                .zip(&st.bound)
                .fold(0.0f64, |m, (p, b)| m.max((self.gel.friction * p - b).abs()));
            let tol = self.options.pressure_tolerance * peak.max(1e-12);
            relative = change.max(bound_change) / peak.max(1e-12);
            if update > 0 && change <= tol && bound_change <= tol.max(1e-300) {
                st.lambda = pressures;
                self.set_bounds(st);
                return Ok(());
            }
            if peak == 0.0 && update > 0 {
                st.lambda = pressures;
                self.set_bounds(st);
                return Ok(());
            }
            // The first update follows bounds predicted from another displacement: not a step
            // of the fixed point the mixing extrapolates. The mixing restarts where the change's
            // Euclidean norm grew (the largest change alone swings with single nodes at the
            // contact's edge: restarting on it left the plain update, which on the μ = 1.5
            // slide of the press-and-slide sweep diverges).
            let norm = pressures
                .iter()
                .zip(&st.lambda)
                .map(|(p, l)| (p - l) * (p - l))
                .sum::<f64>()
                .sqrt();
            if update == 0 || norm > last_norm {
                anderson.reset();
            }
            last_norm = norm;
            st.lambda = if update == 0 {
                pressures
            } else {
                anderson.next(&st.lambda, &pressures)
            };
            st.lambda.iter_mut().for_each(|l| *l = l.max(0.0));
            self.set_bounds(st);
        }
        Err(Failure::Updates {
            updates: self.options.max_updates,
            residual: relative,
        })
    }

    /// Friction bounds μλ from the multipliers.
    fn set_bounds(&self, st: &mut State) {
        for (b, l) in st.bound.iter_mut().zip(&st.lambda) {
            *b = self.gel.friction * l;
        }
    }
}

/// Each surface node's augmented-Lagrangian pressure max(0, λ − ε g) at the state's displacement
/// (kPa): the multiplier update (Alart & Curnier 1991).
fn surface_pressures(st: &State, ind: &Indenter, eps: f64) -> Vec<f64> {
    let nx = st.mesh.x.len();
    (0..st.lambda.len())
        .map(|n| {
            let (i, j) = (n % nx, n / nx);
            let g = deformed_gap(&st.u[3 * n..3 * n + 3], [st.mesh.x[i], st.mesh.y[j]], ind);
            (st.lambda[n] - eps * g).max(0.0)
        })
        .collect()
}

/// The smallest finite gap of a frame (mm; negative = penetration).
fn deepest_gap(input: &ContactInput) -> f64 {
    input
        .gap
        .gap_mm
        .iter()
        .filter(|g| g.is_finite())
        .fold(f64::INFINITY, |m, &g| m.min(g))
}

/// A length scale for step tolerances: the largest displacement, at least 1 µm.
fn ind_scale(st: &State) -> f64 {
    st.u.iter().fold(1e-3f64, |m, u| m.max(u.abs()))
}

/// Gap of a surface node at reference (x, y) with displacement `u` (mm).
fn deformed_gap(u: &[f64], xy: [f64; 2], ind: &Indenter) -> f64 {
    let (h, _, _) = ind.height(xy[0] + u[0], xy[1] + u[1]);
    h - u[2]
}

/// One surface node's contact and friction potential, gradient and Hessian block.
struct NodeTerms {
    energy: f64,
    gradient: [f64; 3],
    hessian: [[f64; 3]; 3],
    pressure: f64,
    traction: [f64; 2],
    state: NodeState,
}

impl NodeTerms {
    /// Whether the node's friction is at its bound.
    fn slipping(&self) -> bool {
        matches!(self.state.friction, FrictionState::Slip(_))
    }
}

/// A surface node's contact and friction state: which block it adds to the Hessian.
#[derive(Debug, Clone, Copy, PartialEq)]
struct NodeState {
    /// Pressed (normal penalty block present).
    contact: bool,
    friction: FrictionState,
}

/// A surface node's friction in one Hessian.
#[derive(Debug, Clone, Copy, PartialEq)]
enum FrictionState {
    /// No friction bound (not pressed in the last multiplier update).
    Free,
    /// Sticking: the tangential penalty block.
    Stick,
    /// Slipping, with this stiffness.
    Slip(SlipStiffness),
}

/// `slip`: with [`SlipStiffness::Secant`] a slipping node's friction Hessian is its secant
/// stiffness A e_t b/|t| in both tangential directions instead of the consistent
/// A e_t b/|t| (I − d dᵀ). The quadratic with that curvature lies above the friction potential (from |t| ≤ |t₀|/2 + |t|²/(2|t₀|); Weiszfeld's
/// majorization, as in iteratively reweighted least squares for Huber's loss), so its step
/// cannot overshoot the kink at the stick disc.
#[allow(clippy::too_many_arguments)]
fn contact_terms(
    st: &State,
    n: usize,
    area: f64,
    eps: f64,
    u: &[f64],
    xy: [f64; 2],
    ind: &Indenter,
    slip: SlipStiffness,
) -> NodeTerms {
    let mut t = NodeTerms {
        energy: 0.0,
        gradient: [0.0; 3],
        hessian: [[0.0; 3]; 3],
        pressure: 0.0,
        traction: [0.0; 2],
        state: NodeState {
            contact: false,
            friction: FrictionState::Free,
        },
    };
    let (h, hx, hy) = ind.height(xy[0] + u[0], xy[1] + u[1]);
    let g = h - u[2];
    let p = (st.lambda[n] - eps * g).max(0.0);
    if p > 0.0 {
        // A/(2ε) max(0, λ − ε g)²: gradient −A p ∇g, Hessian A ε ∇g ∇gᵀ (the indenter's
        // curvature term dropped), ∇g = (∂h/∂x, ∂h/∂y, −1).
        let dg = [hx, hy, -1.0];
        t.energy += area * p * p / (2.0 * eps);
        for r in 0..3 {
            t.gradient[r] -= area * p * dg[r];
            for c in 0..3 {
                t.hessian[r][c] += area * eps * dg[r] * dg[c];
            }
        }
        t.pressure = p;
        t.state.contact = true;
    }
    let b = st.bound[n];
    if b > 0.0 {
        let shift = ind.shift(xy[0] + st.ut_prev[n][0], xy[1] + st.ut_prev[n][1]);
        let w = [
            u[0] - st.ut_prev[n][0] - shift[0],
            u[1] - st.ut_prev[n][1] - shift[1],
        ];
        let et = TANGENTIAL_PENALTY * eps;
        let trial = [st.q_prev[n][0] + et * w[0], st.q_prev[n][1] + et * w[1]];
        let norm = trial[0].hypot(trial[1]);
        if norm <= b {
            t.energy += area * norm * norm / (2.0 * et);
            for (d, trial_d) in trial.iter().enumerate() {
                t.gradient[d] += area * trial_d;
                t.hessian[d][d] += area * et;
            }
            t.traction = [-trial[0], -trial[1]];
            t.state.friction = FrictionState::Stick;
        } else {
            let dir = [trial[0] / norm, trial[1] / norm];
            t.energy += area * (b * norm - 0.5 * b * b) / et;
            for d in 0..2 {
                t.gradient[d] += area * b * dir[d];
                for e in 0..2 {
                    let delta = if d == e { 1.0 } else { 0.0 };
                    let along = match slip {
                        SlipStiffness::Secant => 0.0,
                        SlipStiffness::Consistent => dir[d] * dir[e],
                    };
                    t.hessian[d][e] += area * et * (b / norm) * (delta - along);
                }
            }
            t.traction = [-b * dir[0], -b * dir[1]];
            t.state.friction = FrictionState::Slip(slip);
        }
    }
    t
}

/// Interpolated surface history at a point.
struct SurfaceSample {
    lambda: f64,
    bound: f64,
    q_prev: [f64; 2],
    ut_prev: [f64; 2],
}

/// The previous frame's path history on the surface nodes.
struct History {
    mesh: Mesh,
    q_prev: Vec<[f64; 2]>,
    ut_prev: Vec<[f64; 2]>,
}

impl State {
    fn history(&self) -> History {
        History {
            mesh: self.mesh.clone(),
            q_prev: self.q_prev.clone(),
            ut_prev: self.ut_prev.clone(),
        }
    }

    /// Puts back the previous frame's history (on this state's mesh when it has not changed).
    fn restore_history(&mut self, h: &History) {
        if h.mesh == self.mesh {
            self.q_prev.clone_from(&h.q_prev);
            self.ut_prev.clone_from(&h.ut_prev);
        }
    }

    /// Trilinear displacement at a reference point (clamped to the block).
    fn interpolate_volume(&self, p: [f64; 3]) -> [f64; 3] {
        let m = &self.mesh;
        let (i, tx) = locate(&m.x, p[0]);
        let (j, ty) = locate(&m.y, p[1]);
        // z descends with k: locate on −z.
        let neg: Vec<f64> = m.z.iter().map(|z| -z).collect();
        let (k, tz) = locate(&neg, -p[2]);
        let mut out = [0.0; 3];
        for a in 0..8 {
            let (di, dj, dk) = (a & 1, (a >> 1) & 1, (a >> 2) & 1);
            let w = if di == 1 { tx } else { 1.0 - tx }
                * if dj == 1 { ty } else { 1.0 - ty }
                * if dk == 1 { tz } else { 1.0 - tz };
            let n = m.node(i + di, j + dj, k + dk);
            for (o, u) in out.iter_mut().zip(&self.u[3 * n..3 * n + 3]) {
                *o += w * u;
            }
        }
        out
    }

    /// Bilinear weights of the surface nodes around (x, y).
    fn surface_weights(&self, x: f64, y: f64) -> [(usize, f64); 4] {
        let m = &self.mesh;
        let (i, tx) = locate(&m.x, x);
        let (j, ty) = locate(&m.y, y);
        [
            (m.node(i, j, 0), (1.0 - tx) * (1.0 - ty)),
            (m.node(i + 1, j, 0), tx * (1.0 - ty)),
            (m.node(i, j + 1, 0), (1.0 - tx) * ty),
            (m.node(i + 1, j + 1, 0), tx * ty),
        ]
    }

    fn interpolate_surface(&self, x: f64, y: f64) -> SurfaceSample {
        let mut s = SurfaceSample {
            lambda: 0.0,
            bound: 0.0,
            q_prev: [0.0; 2],
            ut_prev: [0.0; 2],
        };
        for (n, w) in self.surface_weights(x, y) {
            s.lambda += w * self.lambda[n];
            s.bound += w * self.bound[n];
            for c in 0..2 {
                s.q_prev[c] += w * self.q_prev[n][c];
                s.ut_prev[c] += w * self.ut_prev[n][c];
            }
        }
        s
    }
}

/// The Hessian's sparsity (every pair of nodes sharing an element, lower triangle) and the
/// per-element scatter map.
fn build_system(mesh: &Mesh) -> System {
    let [nx, ny, nz] = mesh.counts();
    let nfree = mesh.free_dofs();
    let mut col_ptr = Vec::with_capacity(nfree + 1);
    let mut row_idx = Vec::new();
    col_ptr.push(0);
    for dof in 0..nfree {
        let n = dof / 3;
        let (i, j, k) = (n % nx, (n / nx) % ny, n / (nx * ny));
        for dk in -1i64..=1 {
            for dj in -1i64..=1 {
                for di in -1i64..=1 {
                    let (ii, jj, kk) = (i as i64 + di, j as i64 + dj, k as i64 + dk);
                    if ii < 0
                        || jj < 0
                        || kk < 0
                        || ii >= nx as i64
                        || jj >= ny as i64
                        || kk >= nz as i64 - 1
                    {
                        continue;
                    }
                    let m = mesh.node(ii as usize, jj as usize, kk as usize);
                    for c in 0..3 {
                        let r = 3 * m + c;
                        if r >= dof {
                            row_idx.push(r);
                        }
                    }
                }
            }
        }
        col_ptr.push(row_idx.len());
    }
    let (ex, ey) = (nx - 1, ny - 1);
    let scatter = (0..mesh.elements())
        .into_par_iter()
        .map(|e| {
            let (i, j, k) = (e % ex, (e / ex) % ey, e / (ex * ey));
            let nodes = mesh.element_nodes(i, j, k);
            let mut map = [u32::MAX; PACKED];
            for p in 0..24 {
                for q in 0..=p {
                    let (r, c) = (3 * nodes[p / 3] + p % 3, 3 * nodes[q / 3] + q % 3);
                    if r >= nfree || c >= nfree {
                        continue;
                    }
                    let (r, c) = (r.max(c), r.min(c));
                    let rows = &row_idx[col_ptr[c]..col_ptr[c + 1]];
                    let at = rows
                        .binary_search(&r)
                        .expect("pattern holds every element pair");
                    map[packed(p, q)] = (col_ptr[c] + at) as u32;
                }
            }
            map
        })
        .collect();
    let symbolic = SymbolicSparseColMatRef::new_checked(nfree, nfree, &col_ptr, None, &row_idx);
    let order = mesh.nested_dissection();
    let mut inverse = vec![0; nfree];
    for (p, &d) in order.iter().enumerate() {
        inverse[d] = p;
    }
    let symbolic = factorize_symbolic_cholesky(
        symbolic,
        Side::Lower,
        SymmetricOrdering::Custom(PermRef::new_checked(&order, &inverse, nfree)),
        Default::default(),
    )
    .expect("symbolic Cholesky of a mesh pattern");
    System {
        col_ptr,
        row_idx,
        symbolic: Arc::new(symbolic),
        scatter,
    }
}

/// Conjugate-gradient iterations allowed with a stale factor before refactorising. With the
/// factor made in single precision a factorisation of the deep press's 30 k unknowns costs about
/// 14 iterations' time (0.14 s against 10 ms); capped at 6 iterations (and
/// [`MAX_CHANGED_NODES`] at 12) the press took 1.07–1.21 s a frame against 1.32–1.62 s at 12 (and
/// 24) in alternating runs, 1.20–1.33 s at 8, 1.35 s at 4. The runs are in the book's contact
/// chapter.
const PCG_ITERATIONS: usize = 6;

/// Surface nodes whose contact or friction state differs from the kept factor's from which a
/// Newton step refactorises without trying the conjugate gradients (the default of
/// [`FemOptions::max_changed_nodes`]: 2 × [`PCG_ITERATIONS`]).
/// Each such node is a rank-one to rank-three change of the Hessian, and conjugate gradients
/// preconditioned by a factor exact but for a rank-m change need up to m + 1 iterations. On the
/// deep press (20 frames, with a cap of 12 iterations and a factor made in double precision)
/// 30 of the 42 preconditioned solves attempted with 24 or more changed nodes failed, 12
/// iterations lost each, and the 12 that converged took 7–12, where a factorisation cost about
/// 19 iterations' time; below 24 nodes 7 of 67 failed.
const MAX_CHANGED_NODES: usize = 2 * PCG_ITERATIONS;

/// Relative residual ‖H s + g‖ / ‖g‖ at which a preconditioned step is accepted (an inexact
/// Newton step; Dembo, Eisenstat & Steihaug 1982).
const PCG_TOLERANCE: f64 = 1e-4;

/// The Cholesky factor of H into `l` (its buffer reused across factorisations: a fresh one costs
/// the page faults of ~100 MB; the factorisation zeroes it itself), shifting H by τ·diag(H)
/// until it is positive definite.
fn factorize_shifted(sys: &System, values: &[f64], l: &mut Vec<f64>) {
    let n = sys.col_ptr.len() - 1;
    let symbolic = SymbolicSparseColMatRef::new_checked(n, n, &sys.col_ptr, None, &sys.row_idx);
    l.resize(sys.symbolic.len_val(), 0.0);
    let par = Par::Seq;
    let mut buffer = MemBuffer::new(
        sys.symbolic
            .factorize_numeric_llt_scratch::<f64>(par, Default::default()),
    );
    let mut shifted = Vec::new();
    let mut tau = 0.0;
    loop {
        if tau > 0.0 {
            shifted.clear();
            shifted.extend_from_slice(values);
            for c in 0..n {
                // The diagonal is the first entry of each column.
                shifted[sys.col_ptr[c]] *= 1.0 + tau;
            }
        }
        let mat = SparseColMatRef::new(symbolic, if tau > 0.0 { &shifted } else { values });
        let stack = MemStack::new(&mut buffer);
        match sys.symbolic.factorize_numeric_llt(
            l,
            mat,
            Side::Lower,
            Default::default(),
            par,
            stack,
            Default::default(),
        ) {
            Ok(_) => return,
            Err(_) => tau = if tau == 0.0 { 1e-8 } else { tau * 10.0 },
        }
    }
}

/// The Cholesky factor of H in single precision into `l`; `false` when a pivot is not positive
/// (the factorisation is then redone in double precision, [`factorize_shifted`]). Half the bytes
/// and twice the SIMD lanes of the double-precision factorisation; its rounding (a relative 6e-8
/// per entry, amplified by H's conditioning) only slows the conjugate gradients it
/// preconditions, which solve with H itself in double precision.
fn factorize_single(sys: &System, values: &[f64], l: &mut Vec<f32>) -> bool {
    let n = sys.col_ptr.len() - 1;
    let symbolic = SymbolicSparseColMatRef::new_checked(n, n, &sys.col_ptr, None, &sys.row_idx);
    l.resize(sys.symbolic.len_val(), 0.0);
    let par = Par::Seq;
    let mut buffer = MemBuffer::new(
        sys.symbolic
            .factorize_numeric_llt_scratch::<f32>(par, Default::default()),
    );
    let single: Vec<f32> = values.iter().map(|&v| v as f32).collect();
    sys.symbolic
        .factorize_numeric_llt(
            l,
            SparseColMatRef::new(symbolic, &single),
            Side::Lower,
            Default::default(),
            par,
            MemStack::new(&mut buffer),
            Default::default(),
        )
        .is_ok()
}

/// Solves L Lᵀ x = b in place.
fn solve_with(sys: &System, factor: &[f64], rhs: &mut [f64]) {
    let n = rhs.len();
    let par = Par::Seq;
    let mut buffer = MemBuffer::new(sys.symbolic.solve_in_place_scratch::<f64>(1, par));
    let llt = LltRef::new(&sys.symbolic, factor);
    let rhs = MatMut::from_column_major_slice_mut(rhs, n, 1);
    llt.solve_in_place_with_conj(Conj::No, rhs, par, MemStack::new(&mut buffer));
}

/// z = (L Lᵀ)⁻¹ r with a factor rounded to single precision: the conjugate gradients' products
/// and sums stay in double precision, and the preconditioner, already a factor of an earlier
/// Hessian, moves by a relative 6e-8 per entry, far less than the Hessian moves between Newton
/// steps; its triangular solves, most of a frame's time, read half the bytes.
fn precondition(sys: &System, factor: &[f32], r: &[f64], z: &mut [f64]) {
    let n = r.len();
    let par = Par::Seq;
    let mut buffer = MemBuffer::new(sys.symbolic.solve_in_place_scratch::<f32>(1, par));
    let llt = LltRef::new(&sys.symbolic, factor);
    let mut x: Vec<f32> = r.iter().map(|&v| v as f32).collect();
    let rhs = MatMut::from_column_major_slice_mut(&mut x, n, 1);
    llt.solve_in_place_with_conj(Conj::No, rhs, par, MemStack::new(&mut buffer));
    z.iter_mut().zip(&x).for_each(|(z, &x)| *z = x as f64);
}

/// y = H x for the symmetric H stored as its lower triangle.
fn symmetric_product(sys: &System, values: &[f64], x: &[f64], y: &mut [f64]) {
    y.iter_mut().for_each(|v| *v = 0.0);
    for c in 0..x.len() {
        let (from, to) = (sys.col_ptr[c], sys.col_ptr[c + 1]);
        let mut sum = 0.0;
        for (&r, &v) in sys.row_idx[from..to].iter().zip(&values[from..to]) {
            y[r] += v * x[c];
            if r != c {
                sum += v * x[r];
            }
        }
        y[c] += sum;
    }
}

/// Solves H x = b by conjugate gradients preconditioned with the Cholesky factor of an earlier
/// Hessian (Saad, *Iterative Methods for Sparse Linear Systems*, alg. 9.1), from x = 0 so every
/// iterate is a descent direction. `Err(iterations)` when H shows negative curvature or the
/// residual does not fall to [`PCG_TOLERANCE`] within [`PCG_ITERATIONS`].
fn pcg(
    sys: &System,
    factor: &[f32],
    values: &[f64],
    b: &[f64],
) -> Result<(Vec<f64>, usize), usize> {
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let n = b.len();
    let target = PCG_TOLERANCE * dot(b, b).sqrt();
    let mut x = vec![0.0; n];
    let mut r = b.to_vec();
    let mut z = vec![0.0; n];
    precondition(sys, factor, &r, &mut z);
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    let mut hp = vec![0.0; n];
    for it in 1..=PCG_ITERATIONS {
        symmetric_product(sys, values, &p, &mut hp);
        let curvature = dot(&p, &hp);
        // Negative curvature, or NaN from a broken system: not this solver's to fix.
        if curvature.is_nan() || curvature <= 0.0 {
            return Err(it);
        }
        let alpha = rz / curvature;
        for k in 0..n {
            x[k] += alpha * p[k];
            r[k] -= alpha * hp[k];
        }
        if dot(&r, &r).sqrt() <= target {
            return Ok((x, it));
        }
        precondition(sys, factor, &r, &mut z);
        let rz_next = dot(&r, &z);
        let beta = rz_next / rz;
        rz = rz_next;
        for k in 0..n {
            p[k] = z[k] + beta * p[k];
        }
    }
    Err(PCG_ITERATIONS)
}

impl ContactSolver for Fem {
    fn name(&self) -> &'static str {
        "fem"
    }

    fn solve(&mut self, input: &ContactInput) -> Result<Fields, ContactError> {
        self.stats = FemStats::default();
        let h = self.gel.thickness_mm;
        let heights = &input.gap.gap_mm;
        let deepest = heights
            .iter()
            .filter(|g| g.is_finite())
            .fold(f64::INFINITY, |m, &g| m.min(g));
        match input.normal {
            NormalControl::Approach => {
                if -deepest >= h {
                    return Err(ContactError::OutOfValidity {
                        solver: "fem",
                        reason: format!(
                            "the indenter reaches {:.3} mm into a {h} mm gel: a press at or past the gel's thickness",
                            -deepest
                        ),
                    });
                }
                self.solve_at(input, 0.0)
            }
            NormalControl::Force(_) if !deepest.is_finite() => Err(ContactError::OutOfValidity {
                solver: "fem",
                reason: "no part of the indenter is above the gel, so no approach gives a load"
                    .into(),
            }),
            NormalControl::Force(target_n) => self.solve_load(input, target_n, deepest),
        }
    }

    fn reset(&mut self) {
        self.state = None;
    }
}

impl Fem {
    /// Load control: the extra approach whose normal force is within 0.1 % of `target_n` (the
    /// accuracy of the multiplier iteration), by regula falsi with the Illinois modification,
    /// bracketed from first touch (zero force); every trial starts from the previous frame's
    /// path history and warm-starts from the last trial.
    fn solve_load(
        &mut self,
        input: &ContactInput,
        target_n: f64,
        deepest: f64,
    ) -> Result<Fields, ContactError> {
        let h = self.gel.thickness_mm;
        // The extra approach at which the indenter's lowest point reaches the surface.
        let touch = deepest;
        if target_n <= 0.0 {
            return self.solve_at(input, touch - 1e-3 * h);
        }
        let history = self.state.as_ref().map(State::history);
        let mut guess = self
            .state
            .as_ref()
            .map_or(touch + 1e-3 * h, |s| s.offset_mm)
            .max(touch + 1e-3 * h);
        let mut lo = (touch, -target_n);
        let mut hi: Option<(f64, f64)> = None;
        let mut last_side = 0i8;
        let mut total = FemStats::default();
        const TRIALS: usize = 60;
        for _ in 0..TRIALS {
            if guess - touch >= h {
                return Err(ContactError::OutOfValidity {
                    solver: "fem",
                    reason: format!(
                        "a normal load of {target_n} N presses the indenter through the {h} mm gel"
                    ),
                });
            }
            if let (Some(s), Some(saved)) = (self.state.as_mut(), history.as_ref()) {
                s.restore_history(saved);
            }
            self.stats = FemStats::default();
            let fields = self.solve_at(input, guess)?;
            total.accumulate(&self.stats);
            let force = fields.force_n[2];
            let f = force - target_n;
            if f.abs() <= 1e-3 * target_n {
                self.stats = total;
                if let Some(s) = self.state.as_mut() {
                    s.offset_mm = guess;
                }
                return Ok(fields);
            }
            let width = hi.map_or(f64::INFINITY, |(x, _)| x - lo.0);
            if width <= 1e-12 * h {
                // The bracket closed on a jump of the force: no approach gives the load.
                return Err(ContactError::NotConverged {
                    solver: "fem",
                    iterations: total.newton_iterations,
                    residual: f.abs(),
                });
            }
            if f < 0.0 {
                lo = (guess, f);
                if let (-1, Some(h)) = (last_side, hi.as_mut()) {
                    h.1 *= 0.5;
                }
                last_side = -1;
            } else {
                hi = Some((guess, f));
                if last_side == 1 {
                    lo.1 *= 0.5;
                }
                last_side = 1;
            }
            guess = match hi {
                // Expand as F ∝ d^{3/2} from first touch until the load is passed.
                None => {
                    let d = (guess - touch).max(1e-6 * h);
                    let scale = if force > 0.0 {
                        (target_n / force).powf(2.0 / 3.0).clamp(1.05, 4.0)
                    } else {
                        4.0
                    };
                    touch + d * scale
                }
                Some((xh, fh)) => lo.0 - lo.1 * (xh - lo.0) / (fh - lo.1),
            };
        }
        Err(ContactError::NotConverged {
            solver: "fem",
            iterations: TRIALS,
            residual: f64::NAN,
        })
    }

    /// Displacement control with the indenter lowered by `approach_mm`.
    fn solve_at(&mut self, input: &ContactInput, approach_mm: f64) -> Result<Fields, ContactError> {
        let grid = self.grid;
        let ind = Indenter {
            grid,
            height_mm: &input.gap.gap_mm,
            approach_mm,
            shift_mm: input.rigid_shift_mm,
        };
        // The penetrating cells: the fine zone and the mesh resolution follow them.
        let mut bbox = [
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        let mut count = 0usize;
        for j in 0..grid.ny {
            for i in 0..grid.nx {
                let g = input.gap.gap_mm[j * grid.nx + i];
                if g.is_finite() && g - approach_mm < 0.0 {
                    let (x, y) = (grid.x_mm(i), grid.y_mm(j));
                    bbox = [
                        bbox[0].min(x),
                        bbox[1].max(x),
                        bbox[2].min(y),
                        bbox[3].max(y),
                    ];
                    count += 1;
                }
            }
        }
        if count == 0 {
            // Nothing touches: the gel is at rest and forgets its friction history.
            self.state = None;
            return Ok(Fields::zero(grid));
        }
        let half = grid.cell_mm / 2.0;
        let bbox = [
            bbox[0] - half,
            bbox[1] + half,
            bbox[2] - half,
            bbox[3] + half,
        ];
        let radius = (count as f64 * grid.cell_area_mm2() / std::f64::consts::PI)
            .sqrt()
            .max(grid.cell_mm);
        let h = self.gel.thickness_mm;
        if h > THICK_BLOCK * radius && radius >= 2.0 * grid.cell_mm {
            return Err(ContactError::OutOfValidity {
                solver: "fem",
                reason: format!(
                    "a {h} mm gel is {:.0} contact radii thick, beyond the {THICK_BLOCK} the fem rung \
                     meshes: a thick block is the half-space rung's regime",
                    h / radius
                ),
            });
        }
        let target_fine = self.fine_mm(radius);
        let fits = |s: &State| {
            let z = s.mesh.fine_zone;
            bbox[0] >= z[0]
                && bbox[1] <= z[1]
                && bbox[2] >= z[2]
                && bbox[3] <= z[3]
                && s.mesh.fine_mm <= 1.25 * target_fine
                && s.mesh.fine_mm >= target_fine / 2.5
        };
        let from_rest = self.state.is_none() || !self.options.warm_start;
        let mut state = match self.state.take() {
            Some(s) if fits(&s) => s,
            old => {
                self.stats.remeshes += 1;
                let mesh = self.build_mesh(bbox, radius);
                self.new_state(mesh, old.as_ref())
            }
        };
        if !self.options.warm_start {
            state.u.iter_mut().for_each(|u| *u = 0.0);
            state.lambda.iter_mut().for_each(|l| *l = 0.0);
        }
        self.stats.dofs = state.mesh.free_dofs();
        self.stats.factor_nonzeros = state.system.symbolic.len_val();
        self.stats.elements = state.mesh.elements();
        // From rest, a deep press is reached in increments of at most a fifth of the gel.
        let depth = approach_mm - deepest_gap(input);
        let steps = if from_rest {
            ((depth / (0.2 * h)).ceil() as usize).max(1)
        } else {
            1
        };
        let attempt = if steps > 1 {
            self.ramp(&mut state, input, approach_mm, steps)
        } else {
            self.solve_fixed(&mut state, &ind)
        };
        let attempt = match attempt {
            // Too large a step from the warm start: ramp from rest in twice the increments. Not
            // when the multiplier updates ran out: their fixed point is the same from rest, and
            // the ramp would only repeat the cap at each increment.
            Err(Failure::NotConverged { .. } | Failure::Inverted) => {
                self.ramp(&mut state, input, approach_mm, 2 * steps.max(4))
            }
            other => other,
        };
        match attempt {
            Ok(()) => {}
            Err(Failure::Inverted) => {
                return Err(ContactError::OutOfValidity {
                    solver: "fem",
                    reason:
                        "an element inverted (J ≤ 0): the press is beyond what the mesh resolves"
                            .into(),
                });
            }
            Err(
                Failure::NotConverged {
                    iterations,
                    residual,
                }
                | Failure::Updates {
                    updates: iterations,
                    residual,
                },
            ) => {
                return Err(ContactError::NotConverged {
                    solver: "fem",
                    iterations,
                    residual,
                });
            }
        }
        let fields = self.fields(&mut state, &ind, approach_mm);
        self.state = Some(state);
        Ok(fields)
    }

    /// Solves from rest in `steps` increments of the approach (the indenter lowered from where
    /// it first touches); the friction history is kept.
    fn ramp(
        &mut self,
        state: &mut State,
        input: &ContactInput,
        approach_mm: f64,
        steps: usize,
    ) -> Result<(), Failure> {
        let depth = approach_mm - deepest_gap(input);
        state.u.iter_mut().for_each(|u| *u = 0.0);
        state.lambda.iter_mut().for_each(|l| *l = 0.0);
        for k in 1..=steps {
            let ind = Indenter {
                grid: self.grid,
                height_mm: &input.gap.gap_mm,
                approach_mm: approach_mm - depth * (1.0 - k as f64 / steps as f64),
                shift_mm: input.rigid_shift_mm,
            };
            self.solve_fixed(state, &ind)?;
        }
        Ok(())
    }

    /// The converged state as fields on the grid; records the path history for the next frame.
    fn fields(&self, st: &mut State, ind: &Indenter, approach_mm: f64) -> Fields {
        let grid = self.grid;
        let mesh = &st.mesh;
        let nx = mesh.x.len();
        let eps = self.penalty(mesh);
        let surface = mesh.x.len() * mesh.y.len();
        let mut pressure = vec![0.0; surface];
        let mut traction = vec![[0.0; 2]; surface];
        let mut slip = vec![false; surface];
        let mut force = [0.0; 3];
        for n in 0..surface {
            let (i, j) = (n % nx, n / nx);
            let area = mesh.surface_area_mm2(i, j);
            let t = contact_terms(
                st,
                n,
                area,
                eps,
                &st.u[3 * n..3 * n + 3],
                [mesh.x[i], mesh.y[j]],
                ind,
                SlipStiffness::Consistent,
            );
            pressure[n] = t.pressure;
            traction[n] = t.traction;
            slip[n] = t.slipping() && t.pressure > 0.0;
            force[0] += area * t.traction[0] * 1e-3;
            force[1] += area * t.traction[1] * 1e-3;
            force[2] += area * t.pressure * 1e-3;
        }
        let mut f = Fields::zero(grid);
        for j in 0..grid.ny {
            for i in 0..grid.nx {
                let k = j * grid.nx + i;
                let (x, y) = (grid.x_mm(i), grid.y_mm(j));
                // The material point above this cell after deformation: X + u(X) = x.
                let mut xy = [x, y];
                for _ in 0..4 {
                    let mut u = [0.0; 2];
                    for (n, w) in st.surface_weights(xy[0], xy[1]) {
                        u[0] += w * st.u[3 * n];
                        u[1] += w * st.u[3 * n + 1];
                    }
                    xy = [x - u[0], y - u[1]];
                }
                let weights = st.surface_weights(xy[0], xy[1]);
                // The stick/slip state of the nearest node that carries pressure (a cell at the
                // contact's edge may be nearer a node outside it).
                let nearest = weights
                    .iter()
                    .fold((None, -1.0), |best, &(n, w)| {
                        if pressure[n] > 0.0 && w > best.1 {
                            (Some(n), w)
                        } else {
                            best
                        }
                    })
                    .0;
                let mut u = [0.0; 3];
                let (mut p, mut q) = (0.0, [0.0; 2]);
                for &(n, w) in &weights {
                    for (uc, un) in u.iter_mut().zip(&st.u[3 * n..3 * n + 3]) {
                        *uc += w * un;
                    }
                    p += w * pressure[n];
                    q[0] += w * traction[n][0];
                    q[1] += w * traction[n][1];
                }
                f.ux_mm[k] = u[0];
                f.uy_mm[k] = u[1];
                f.uz_mm[k] = u[2];
                // In contact where the nodes' own criterion, max(0, λ − ε g) > 0, holds at this
                // point of the surface: the multiplier interpolated, the gap between the
                // interpolated surface and the indenter taken here. The contact's edge falls
                // inside an element, not at the nearest node.
                let lambda: f64 = weights.iter().map(|&(n, w)| w * st.lambda[n]).sum();
                if lambda - eps * deformed_gap(&u, xy, ind) > 0.0 {
                    f.contact[k] = true;
                    f.slip[k] = nearest.is_some_and(|n| slip[n]);
                    f.pressure_kpa[k] = p;
                    f.traction_x_kpa[k] = q[0];
                    f.traction_y_kpa[k] = q[1];
                }
            }
        }
        f.force_n = force;
        f.approach_offset_mm = approach_mm;
        // Path history for the next frame: this frame's friction tractions (gel on indenter) and
        // tangential displacements.
        for (n, t) in traction.iter().enumerate() {
            st.q_prev[n] = [-t[0], -t[1]];
            st.ut_prev[n] = [st.u[3 * n], st.u[3 * n + 1]];
        }
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Bem;
    use sparsh_scene::GapField;

    fn sphere_gap(grid: Grid, radius: f64, depth: f64) -> GapField {
        let gap_mm = (0..grid.len())
            .map(|k| {
                let (x, y) = (grid.x_mm(k % grid.nx), grid.y_mm(k / grid.nx));
                let r2 = x * x + y * y;
                if r2 < radius * radius {
                    radius - (radius * radius - r2).sqrt() - depth
                } else {
                    f64::INFINITY
                }
            })
            .collect();
        GapField { grid, gap_mm }
    }

    fn press(solver: &mut dyn ContactSolver, gap: &GapField) -> Fields {
        let shift = vec![[0.0; 2]; gap.grid.len()];
        solver
            .solve(&ContactInput {
                gap,
                normal: NormalControl::Approach,
                rigid_shift_mm: &shift,
            })
            .unwrap()
    }

    fn layer(thickness_mm: f64, friction: f64) -> Gel {
        Gel {
            youngs_modulus_kpa: 300.0,
            poisson_ratio: 0.5,
            thickness_mm,
            friction,
        }
    }

    /// A 100 mm sphere 0.01 mm deep (contact radius ≈ 1 mm) on a grid of 0.05 mm cells.
    fn shallow() -> (Grid, GapField) {
        let grid = Grid {
            nx: 81,
            ny: 81,
            cell_mm: 0.05,
        };
        (grid, sphere_gap(grid, 100.0, 0.01))
    }

    #[test]
    fn small_strain_matches_the_layered_rung_on_a_thin_layer() {
        // χ = √(Rδ)/h = 1: the two methods share nothing but the elasticity of the layer.
        let (grid, gap) = shallow();
        let gel = layer(1.0, 0.0);
        let fem = press(&mut Fem::new(gel, grid), &gap);
        let bem = press(&mut Bem::layered(gel, grid), &gap);
        let rel = fem.force_n[2] / bem.force_n[2] - 1.0;
        assert!(rel.abs() < 0.02, "{rel}");
        // Axisymmetry: no net shear, and the deflection peaks on the axis.
        assert!(fem.force_n[0].abs() < 1e-6 * fem.force_n[2]);
        let centre = (grid.ny / 2) * grid.nx + grid.nx / 2;
        let min = fem.uz_mm.iter().copied().fold(f64::INFINITY, f64::min);
        assert!(fem.uz_mm[centre] <= min + 1e-12);
        assert!(
            (fem.uz_mm[centre] + 0.01).abs() < 1e-4,
            "{}",
            fem.uz_mm[centre]
        );
    }

    #[test]
    fn a_press_through_the_gel_is_refused() {
        let grid = Grid {
            nx: 41,
            ny: 41,
            cell_mm: 0.2,
        };
        let gap = sphere_gap(grid, 5.0, 2.5);
        let shift = vec![[0.0; 2]; grid.len()];
        let err = Fem::new(layer(2.0, 1.0), grid)
            .solve(&ContactInput {
                gap: &gap,
                normal: NormalControl::Approach,
                rigid_shift_mm: &shift,
            })
            .unwrap_err();
        assert!(matches!(
            err,
            ContactError::OutOfValidity { solver: "fem", .. }
        ));
        assert!(
            err.to_string().contains("2.500 mm into a 2 mm gel"),
            "{err}"
        );
    }

    #[test]
    fn a_load_with_nothing_above_the_gel_is_refused() {
        let (grid, _) = shallow();
        let nothing = GapField {
            grid,
            gap_mm: vec![f64::INFINITY; grid.len()],
        };
        let shift = vec![[0.0; 2]; grid.len()];
        let err = Fem::new(layer(1.0, 0.5), grid)
            .solve(&ContactInput {
                gap: &nothing,
                normal: NormalControl::Force(0.01),
                rigid_shift_mm: &shift,
            })
            .unwrap_err();
        assert!(err.to_string().contains("no part of the indenter"), "{err}");
    }

    #[test]
    fn an_iteration_cap_is_a_typed_error_with_its_residual() {
        // A Newton cap of one iteration, and a cap of one multiplier update (the frame needs
        // at least two: the first is never the last); each failure names its cap and a finite
        // residual (the update's is the relative pressure change).
        let (grid, gap) = shallow();
        let shift = vec![[0.0; 2]; grid.len()];
        for (options, cap) in [
            (
                FemOptions {
                    max_newton: 1,
                    ..FemOptions::default()
                },
                1,
            ),
            (
                FemOptions {
                    max_updates: 1,
                    ..FemOptions::default()
                },
                1,
            ),
        ] {
            let err = Fem::new(layer(1.0, 0.5), grid)
                .with_options(options)
                .solve(&ContactInput {
                    gap: &gap,
                    normal: NormalControl::Approach,
                    rigid_shift_mm: &shift,
                })
                .unwrap_err();
            match err {
                ContactError::NotConverged {
                    solver: "fem",
                    residual,
                    iterations,
                } => assert!(
                    iterations == cap && residual.is_finite() && residual > 0.0,
                    "{options:?}: {iterations} iterations, residual {residual}"
                ),
                other => panic!("{other}"),
            }
        }
    }

    #[test]
    fn load_control_finds_the_load() {
        let (grid, gap) = shallow();
        let shift = vec![[0.0; 2]; grid.len()];
        let mut fem = Fem::new(layer(1.0, 0.5), grid);
        // Lift the sphere 0.005 mm off its 0.01 mm press and ask for a load instead.
        let lifted = GapField {
            grid,
            gap_mm: gap.gap_mm.iter().map(|g| g + 0.005).collect(),
        };
        let f = fem
            .solve(&ContactInput {
                gap: &lifted,
                normal: NormalControl::Force(0.02),
                rigid_shift_mm: &shift,
            })
            .unwrap();
        assert!((f.force_n[2] - 0.02).abs() < 2e-5, "{:?}", f.force_n);
        assert!(f.approach_offset_mm > 0.0);
    }

    #[test]
    fn sliding_far_enough_slips_at_the_friction_bound() {
        // Coulomb: once every contact node slips, Q = μP.
        let (grid, gap) = shallow();
        let gel = layer(1.0, 0.4);
        let mut fem = Fem::new(gel, grid);
        let still = vec![[0.0; 2]; grid.len()];
        press(&mut fem, &gap);
        let step = vec![[0.01, 0.0]; grid.len()];
        let mut last = None;
        for _ in 0..4 {
            last = Some(
                fem.solve(&ContactInput {
                    gap: &gap,
                    normal: NormalControl::Approach,
                    rigid_shift_mm: &step,
                })
                .unwrap(),
            );
        }
        let f = last.unwrap();
        assert_eq!(f.slip_state(), crate::SlipState::Gross);
        let ratio = f.force_n[0] / (gel.friction * f.force_n[2]);
        assert!((ratio - 1.0).abs() < 0.01, "{ratio}");
        // Standing still afterwards: the tractions stay (stick), the history is kept.
        let g = fem
            .solve(&ContactInput {
                gap: &gap,
                normal: NormalControl::Approach,
                rigid_shift_mm: &still,
            })
            .unwrap();
        assert!((g.force_n[0] - f.force_n[0]).abs() < 0.02 * f.force_n[0].abs());
    }

    #[test]
    fn predicted_bounds_the_refactorisation_rule_and_mixed_updates_leave_the_answers_unchanged() {
        // A frictional press deepened over three frames, then slid over two: the friction
        // bounds predicted before each solve, refactorising on many changed nodes and the
        // Anderson mixing of the multiplier updates are speed choices, so the rung without them is a second method for the same frames (they agree
        // to the multiplier tolerance, 0.1 % of the peak pressure).
        let (grid, _) = shallow();
        let gel = layer(1.0, 1.0);
        let still = vec![[0.0; 2]; grid.len()];
        let slide = vec![[0.004, 0.0]; grid.len()];
        let frames: Vec<(GapField, &[[f64; 2]])> = [0.004, 0.007, 0.01]
            .iter()
            .map(|&d| (sphere_gap(grid, 100.0, d), still.as_slice()))
            .chain((0..2).map(|_| (sphere_gap(grid, 100.0, 0.01), slide.as_slice())))
            .collect();
        let run = |options: FemOptions| {
            let mut fem = Fem::new(gel, grid).with_options(options);
            frames
                .iter()
                .map(|(gap, shift)| {
                    fem.solve(&ContactInput {
                        gap,
                        normal: NormalControl::Approach,
                        rigid_shift_mm: shift,
                    })
                    .unwrap()
                })
                .collect::<Vec<_>>()
        };
        let fast = run(FemOptions::default());
        let plain = run(FemOptions {
            predict_bounds: false,
            max_changed_nodes: usize::MAX,
            anderson_depth: 0,
            ..FemOptions::default()
        });
        for (k, (a, b)) in fast.iter().zip(&plain).enumerate() {
            let scale = b.force_n[2];
            for c in 0..3 {
                assert!(
                    (a.force_n[c] - b.force_n[c]).abs() < 2e-3 * scale,
                    "frame {k}, force {c}: {} against {}",
                    a.force_n[c],
                    b.force_n[c]
                );
            }
            let peak = b.pressure_kpa.iter().fold(0.0f64, |m, &p| m.max(p));
            let worst = a
                .pressure_kpa
                .iter()
                .zip(&b.pressure_kpa)
                .fold(0.0f64, |m, (p, q)| m.max((p - q).abs()));
            assert!(
                worst < 1e-2 * peak,
                "frame {k}: pressure off by {worst} of {peak}"
            );
        }
        // The slide moved the tractions: the comparison covers friction, not only the press.
        assert!(plain[4].force_n[0].abs() > 0.1 * plain[4].force_n[2]);
    }

    #[test]
    fn the_secant_friction_quadratic_lies_above_the_potential_and_the_tangent_does_not() {
        // A press, then a slide whose trial tractions leave the stick disc: at each slipping
        // node, the friction potential at w + δ against the quadratic model of each Hessian.
        let (grid, gap) = shallow();
        let mut fem = Fem::new(layer(1.0, 0.5), grid);
        press(&mut fem, &gap);
        let mut st = fem.state.take().unwrap();
        // No normal term: every node lowered far below the indenter, multipliers zero.
        st.lambda.iter_mut().for_each(|l| *l = 0.0);
        let shift = vec![[0.02, 0.0]; grid.len()];
        let ind = Indenter {
            grid,
            height_mm: &gap.gap_mm,
            approach_mm: 0.0,
            shift_mm: &shift,
        };
        let eps = fem.penalty(&st.mesh);
        let nx = st.mesh.x.len();
        let (mut slipping, mut tangent_below) = (0, 0);
        for n in 0..st.lambda.len() {
            let (i, j) = (n % nx, n / nx);
            let area = st.mesh.surface_area_mm2(i, j);
            let xy = [st.mesh.x[i], st.mesh.y[j]];
            let u0 = [st.u[3 * n], st.u[3 * n + 1], -1.0];
            let at = |u: &[f64], secant| contact_terms(&st, n, area, eps, u, xy, &ind, secant);
            let (sec, tan) = (
                at(&u0, SlipStiffness::Secant),
                at(&u0, SlipStiffness::Consistent),
            );
            if !sec.slipping() {
                continue;
            }
            slipping += 1;
            // The trial traction's length over the tangential penalty: how far w moves before
            // the trial reaches the disc's centre (the secant stiffness is A e_t b / |t|).
            let et = TANGENTIAL_PENALTY * eps;
            let reach = area * st.bound[n] / sec.hessian[0][0];
            assert!(reach > st.bound[n] / et);
            for k in 0..16 {
                let angle = k as f64 * std::f64::consts::PI / 8.0;
                for scale in [0.25, 0.5, 1.0, 1.5, 2.0, 3.0] {
                    let d = [
                        scale * reach * angle.cos(),
                        scale * reach * angle.sin(),
                        0.0,
                    ];
                    let u = [u0[0] + d[0], u0[1] + d[1], u0[2]];
                    let exact = at(&u, SlipStiffness::Consistent).energy;
                    let model = |t: &NodeTerms| {
                        let mut m = t.energy;
                        for r in 0..3 {
                            m += t.gradient[r] * d[r];
                            for c in 0..3 {
                                m += 0.5 * d[r] * t.hessian[r][c] * d[c];
                            }
                        }
                        m
                    };
                    let tol = 1e-9 * sec.energy.abs().max(1e-12);
                    assert!(
                        exact <= model(&sec) + tol,
                        "node {n}: {exact} > {}",
                        model(&sec)
                    );
                    if exact > model(&tan) + tol {
                        tangent_below += 1;
                    }
                }
            }
        }
        assert!(slipping > 10, "{slipping} slipping nodes");
        // The consistent tangent, flat along the slip, falls below the potential there.
        assert!(tangent_below > 0);
    }

    /// A layer pressed with friction, its state, and the Newton system at the pressed state.
    fn pressed_newton_system() -> (Fem, State, Assembled) {
        let (grid, gap) = shallow();
        let mut fem = Fem::new(layer(1.0, 0.5), grid);
        press(&mut fem, &gap);
        let st = fem.state.take().unwrap();
        let shift = vec![[0.0; 2]; grid.len()];
        let ind = Indenter {
            grid,
            height_mm: &gap.gap_mm,
            approach_mm: 0.0,
            shift_mm: &shift,
        };
        let now = fem
            .assemble(&st, &st.u, &ind, Some(SlipStiffness::Consistent))
            .ok()
            .unwrap();
        (fem, st, now)
    }

    /// ‖x − s‖ / ‖s‖ for the step s = H⁻¹ rhs of a fresh double-precision factorisation.
    fn off_direct_step(sys: &System, hessian: &[f64], rhs: &[f64], x: &[f64]) -> f64 {
        let mut direct = rhs.to_vec();
        let mut factor = Vec::new();
        factorize_shifted(sys, hessian, &mut factor);
        solve_with(sys, &factor, &mut direct);
        let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
        let diff: Vec<f64> = x.iter().zip(&direct).map(|(a, b)| a - b).collect();
        norm(&diff) / norm(&direct)
    }

    #[test]
    fn preconditioned_steps_match_a_fresh_factorisation() {
        // The Newton system of a pressed state solved by conjugate gradients preconditioned
        // with the factor of the Hessian before four nodes came into contact (their normal
        // penalty left out, a rank-4 change), against the direct solve.
        let (fem, st, now) = pressed_newton_system();
        let mut pressed_nodes: Vec<usize> = (0..st.lambda.len()).collect();
        pressed_nodes.sort_by(|a, b| st.lambda[*b].total_cmp(&st.lambda[*a]));
        let mut stale = now.hessian.clone();
        let nx = st.mesh.x.len();
        for &n in &pressed_nodes[..4] {
            let area = st.mesh.surface_area_mm2(n % nx, n / nx);
            stale[st.system.col_ptr[3 * n + 2]] -= area * fem.penalty(&st.mesh);
        }
        let mut factor = Vec::new();
        factorize_shifted(&st.system, &stale, &mut factor);
        let stale_factor: Vec<f32> = factor.iter().map(|&v| v as f32).collect();
        let rhs: Vec<f64> = now.gradient.iter().map(|g| -g).collect();
        let (x, iterations) = pcg(&st.system, &stale_factor, &now.hessian, &rhs).unwrap();
        let off = off_direct_step(&st.system, &now.hessian, &rhs, &x);
        assert!(off < 1e-3, "{off}");
        assert!((2..=PCG_ITERATIONS).contains(&iterations), "{iterations}");
    }

    #[test]
    fn a_single_precision_factor_gives_the_direct_step_in_a_few_iterations() {
        // The Newton system of a pressed, nearly incompressible layer with friction: its own
        // factor rounded through single precision preconditions it to the double-precision
        // direct step.
        let (_, st, now) = pressed_newton_system();
        let mut single = Vec::new();
        assert!(factorize_single(&st.system, &now.hessian, &mut single));
        let rhs: Vec<f64> = now.gradient.iter().map(|g| -g).collect();
        let (x, iterations) = pcg(&st.system, &single, &now.hessian, &rhs).unwrap();
        let off = off_direct_step(&st.system, &now.hessian, &rhs, &x);
        assert!(off < 1e-3, "{off}");
        assert!(iterations <= 3, "{iterations}");
    }

    #[test]
    fn nested_dissection_fills_less_than_minimum_degree() {
        // The deep press's mesh at 0.5 mm (contact radius 1.7 mm) on the DIGIT grid.
        let grid = Grid {
            nx: 320,
            ny: 240,
            cell_mm: 0.0532,
        };
        let fem = Fem::new(layer(3.0, 1.0), grid);
        let mesh = fem.build_mesh([-1.7, 1.7, -1.7, 1.7], 1.7);
        let pattern = build_system(&mesh);
        let nested = pattern.symbolic.len_val();
        let n = mesh.free_dofs();
        let amd = factorize_symbolic_cholesky(
            SymbolicSparseColMatRef::new_checked(n, n, &pattern.col_ptr, None, &pattern.row_idx),
            Side::Lower,
            SymmetricOrdering::Amd,
            Default::default(),
        )
        .unwrap()
        .len_val();
        eprintln!("factor nonzeros: nested dissection {nested}, minimum degree {amd}");
        assert!((nested as f64) < 0.8 * amd as f64, "{nested} {amd}");
    }

    #[test]
    fn the_thread_count_does_not_change_a_bit() {
        let (grid, gap) = shallow();
        let solve = |threads| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| press(&mut Fem::new(layer(1.0, 0.5), grid), &gap))
        };
        assert_eq!(solve(1), solve(2));
    }
}
