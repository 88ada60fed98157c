//! Validation cases: scene files of `scenes/validation/` solved by the boundary-element rungs
//! and compared with the analytic solutions of [`crate::reference`].
//!
//! Each case is an ordinary scene file with one extra table, `[validation]`, removed before the
//! scene is parsed:
//!
//! ```toml
//! [validation]
//! check = "hertz"            # hertz | hertz_load | flat_punch | cone | cattaneo_mindlin
//!                            # | bonded_layer | layered_vs_halfspace
//!                            # | torsion_stuck | torsion_sliding
//! tolerance = { force = 0.01, contact_radius = 0.02 }   # relative; others are reported only
//! q_over_mu_p = 0.5          # cattaneo_mindlin: tangential load as a fraction of μP
//! tangential_steps = 4       # cattaneo_mindlin: increments of the tangential shift
//! refine = [2.0, 1.0, 0.5]   # optional convergence study: cell-size factors, coarse to fine
//! ```
//!
//! The normal problem follows the scene's trajectory (its last frame is evaluated); a
//! `cattaneo_mindlin` case then shifts the indenter along +x by Mindlin's δ_t for the requested
//! Q/μP and compares the tangential force and the stick radius; a `torsion_*` case twists the
//! indenter about the gel normal along its trajectory (`rotation_deg` z) and compares the
//! twisting moment with Lubkin's fully stuck or fully sliding limit. Lengths measured from a
//! solution: contact radius √(A/π) with A the area of the cells carrying pressure, stick radius
//! likewise from the cells that stick.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};
use sparsh_scene::{GapField, Grid, Pose, Scene, SceneError, SolverKind};

use crate::reference::{self, CattaneoMindlin, Hertz};
use crate::{
    ContactError, ContactInput, Fem, FemOptions, Fields, NormalControl, rigid_shift_mm, solver_for,
};

/// The analytic solution a case is compared with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Check {
    /// Sphere under displacement control: force, contact radius, peak pressure (Hertz).
    Hertz,
    /// Sphere under load control: approach, contact radius, peak pressure (Hertz).
    HertzLoad,
    /// Flat cylindrical punch at a given depth: force (Boussinesq).
    FlatPunch,
    /// Cone at a given depth: force and contact radius (Sneddon).
    Cone,
    /// Sphere, then a tangential shift: tangential force and stick radius (Cattaneo–Mindlin).
    CattaneoMindlin,
    /// Sphere pressed, then twisted about the gel normal by the trajectory's rotation β (friction
    /// high enough that no cell slips): twisting moment against Lubkin's fully stuck
    /// M = 16Ga³β/3 (Johnson §7.3).
    TorsionStuck,
    /// Sphere pressed, then twisted far past the stuck range: twisting moment against Lubkin's
    /// sliding limit M = 3πμPa/16 under the Hertz pressure (Johnson §7.3).
    TorsionSliding,
    /// Sphere on an incompressible bonded layer, with the scene's rung: force (Garcia & Garcia 2018).
    BondedLayer,
    /// The layered rung on a layer much thicker than the contact against the half-space rung.
    LayeredVsHalfspace,
    /// The scene's rung against the layered rung on the same grid and frames: force, and the
    /// tangential force along the layered rung's where the last frame carries a shear load (a
    /// second method; for the finite-element rung in the small-strain limit).
    VersusLayered,
    /// The scene's rung at ν = 0.49 and at ν = 0.4999: force over E* = E/(1 − ν²), which the
    /// elastic solution keeps (to the bottom effect) and a locking element inflates.
    Locking,
    /// Sphere on a thick block at finite depth: force against Hertz (with the bottom effect),
    /// against Sneddon's exact sphere in linear elasticity (the indenter's shape alone) and
    /// against the neo-Hookean closed form attributed to Lin et al. (2009); reported only.
    FiniteStrainSphere,
}

/// The `[validation]` table.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct Spec {
    check: Check,
    #[serde(default)]
    tolerance: BTreeMap<String, f64>,
    q_over_mu_p: Option<f64>,
    #[serde(default = "default_steps")]
    tangential_steps: usize,
    #[serde(default)]
    refine: Vec<f64>,
    /// Finite-element convergence study: elements per contact radius, coarse to fine.
    #[serde(default)]
    elements_per_radius: Vec<f64>,
}

fn default_steps() -> usize {
    4
}

/// One row of the validation table.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CaseResult {
    /// Case name (the scene file's stem).
    pub case: String,
    /// Compared quantity, with its unit.
    pub quantity: String,
    /// Reference value.
    pub analytic: f64,
    /// Solver value.
    pub simulated: f64,
    /// (simulated − analytic)/analytic.
    pub rel_error: f64,
    /// Allowed |rel_error|; `None` for values that are reported only.
    pub tolerance: Option<f64>,
    /// Wall time of the case (ms).
    pub ms: f64,
}

impl CaseResult {
    /// Within tolerance (always true for reported-only rows).
    pub fn passed(&self) -> bool {
        self.tolerance.is_none_or(|t| self.rel_error.abs() <= t)
    }
}

/// Errors of one quantity as the grid is refined.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Convergence {
    /// Case name.
    pub case: String,
    /// Quantity.
    pub quantity: String,
    /// Cell sizes, coarse to fine (mm); for a finite-element mesh study (a case named
    /// `… (elements per radius)`), 1/(elements per contact radius).
    pub cell_mm: Vec<f64>,
    /// Relative errors at those cell sizes.
    pub rel_error: Vec<f64>,
    /// Observed orders between consecutive grids, ln(e₁/e₂)/ln(h₁/h₂).
    pub observed_order: Vec<f64>,
}

/// Everything `sparsh validate` prints.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    /// Table rows.
    pub rows: Vec<CaseResult>,
    /// Grid-refinement studies.
    pub convergence: Vec<Convergence>,
}

impl Report {
    /// Every row within tolerance.
    pub fn passed(&self) -> bool {
        self.rows.iter().all(CaseResult::passed)
    }
}

/// Why a validation run could not be completed.
#[derive(Debug, thiserror::Error)]
pub enum ValidationError {
    /// Reading the case directory or a file failed.
    #[error("{path}: {cause}")]
    Io {
        /// Path.
        path: PathBuf,
        /// Cause (in the message, not chained, so a report prints it once).
        cause: std::io::Error,
    },
    /// A case file is not a valid scene or `[validation]` table.
    #[error("{path}: {reason}")]
    Spec {
        /// Path.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// The scene part failed to load.
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// A solver failed on a case.
    #[error("{case}: {cause}")]
    Contact {
        /// Case name.
        case: String,
        /// Cause (in the message, not chained, so a report prints it once).
        cause: ContactError,
    },
}

/// Runs every `*.toml` case of `dir`, in file-name order.
pub fn run_cases(dir: &Path) -> Result<Report, ValidationError> {
    let io = |cause| ValidationError::Io {
        path: dir.to_path_buf(),
        cause,
    };
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io)?
        .map(|e| e.map(|e| e.path()))
        .collect::<Result<_, _>>()
        .map_err(io)?;
    paths.retain(|p| p.extension().is_some_and(|e| e == "toml"));
    paths.sort();
    let mut report = Report {
        rows: Vec::new(),
        convergence: Vec::new(),
    };
    for path in paths {
        let case = run_case(&path)?;
        report.rows.extend(case.rows);
        report.convergence.extend(case.convergence);
    }
    Ok(report)
}

/// Runs one case file.
pub fn run_case(path: &Path) -> Result<Report, ValidationError> {
    let spec_err = |reason: String| ValidationError::Spec {
        path: path.to_path_buf(),
        reason,
    };
    let source = std::fs::read_to_string(path).map_err(|cause| ValidationError::Io {
        path: path.to_path_buf(),
        cause,
    })?;
    let mut table: toml::Table = source.parse().map_err(|e| spec_err(format!("{e}")))?;
    let spec_value = table
        .remove("validation")
        .ok_or_else(|| spec_err("missing [validation] table".into()))?;
    let spec: Spec = spec_value
        .try_into()
        .map_err(|e| spec_err(format!("[validation]: {e}")))?;
    let scene_text = toml::to_string(&table).map_err(|e| spec_err(format!("{e}")))?;
    let scene = Scene::parse(path, scene_text)?;
    let case = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let contact_err = |cause| ValidationError::Contact {
        case: case.clone(),
        cause,
    };

    let start = Instant::now();
    let base = scene.grid();
    let values = evaluate(&scene, &spec, base).map_err(contact_err)?;
    let ms = start.elapsed().as_secs_f64() * 1e3;
    let rows = values
        .iter()
        .map(|v| CaseResult {
            case: case.clone(),
            quantity: v.quantity.to_string(),
            analytic: v.analytic,
            simulated: v.simulated,
            rel_error: v.rel_error(),
            tolerance: spec
                .tolerance
                .get(v.quantity.split(' ').next().unwrap_or(""))
                .copied(),
            ms,
        })
        .collect();

    let mut convergence = Vec::new();
    if !spec.refine.is_empty() {
        let mut studies: Vec<Convergence> = Vec::new();
        for &factor in &spec.refine {
            // Keep the box and the parity of the cell counts (odd counts keep a cell centred on
            // the axis of an axisymmetric case).
            let count = |n: usize| {
                let m = (n as f64 / factor).round() as usize;
                if n % 2 == 1 {
                    m / 2 * 2 + 1
                } else {
                    m.next_multiple_of(2)
                }
            };
            let grid = Grid {
                nx: count(base.nx),
                ny: count(base.ny),
                cell_mm: base.cell_mm * factor,
            };
            let values = if factor == 1.0 {
                values.clone()
            } else {
                evaluate(&scene, &spec, grid).map_err(contact_err)?
            };
            record(&mut studies, &case, grid.cell_mm, &values);
        }
        convergence = with_orders(studies);
    }
    if !spec.elements_per_radius.is_empty() {
        // The finite-element mesh refined at a fixed grid: the "cell" is the fine zone's element
        // size, a/(elements per radius), with a the contact radius of the finest solution.
        let case_spec = Case {
            check: spec.check,
            q_over_mu_p: spec.q_over_mu_p.unwrap_or(f64::NAN),
            tangential_steps: spec.tangential_steps,
        };
        let mut studies: Vec<Convergence> = Vec::new();
        for &per_radius in &spec.elements_per_radius {
            let options = FemOptions {
                elements_per_radius: per_radius,
                ..FemOptions::default()
            };
            let values = evaluate_case_with(&scene, &case_spec, base, options)
                .map_err(contact_err)?
                .values;
            let name = format!("{case} (elements per radius)");
            record(&mut studies, &name, 1.0 / per_radius, &values);
        }
        convergence.extend(with_orders(studies));
    }
    Ok(Report { rows, convergence })
}

/// Adds one refinement level's errors to the convergence studies of `case`, one per quantity.
fn record(studies: &mut Vec<Convergence>, case: &str, size: f64, values: &[Value]) {
    for v in values {
        let index = match studies.iter().position(|s| s.quantity == v.quantity) {
            Some(i) => i,
            None => {
                studies.push(Convergence {
                    case: case.to_string(),
                    quantity: v.quantity.to_string(),
                    cell_mm: Vec::new(),
                    rel_error: Vec::new(),
                    observed_order: Vec::new(),
                });
                studies.len() - 1
            }
        };
        studies[index].cell_mm.push(size);
        studies[index].rel_error.push(v.rel_error());
    }
}

/// The observed orders between consecutive levels, ln(e₁/e₂)/ln(h₁/h₂).
fn with_orders(mut studies: Vec<Convergence>) -> Vec<Convergence> {
    for s in &mut studies {
        s.observed_order = s
            .rel_error
            .windows(2)
            .zip(s.cell_mm.windows(2))
            .map(|(e, h)| (e[0].abs() / e[1].abs()).ln() / (h[0] / h[1]).ln())
            .collect();
    }
    studies
}

/// A compared quantity.
#[derive(Debug, Clone, PartialEq)]
pub struct Value {
    /// Quantity, with its unit (`force (N)`, …).
    pub quantity: &'static str,
    /// Reference value.
    pub analytic: f64,
    /// Solver value.
    pub simulated: f64,
}

impl Value {
    /// (simulated − analytic)/analytic.
    pub fn rel_error(&self) -> f64 {
        (self.simulated - self.analytic) / self.analytic
    }
}

/// The compared quantities of one check, with the work spent on them.
#[derive(Debug, Clone, PartialEq)]
pub struct Evaluation {
    /// Compared quantities; the first is the force the check is about.
    pub values: Vec<Value>,
    /// Frames solved (a Cattaneo–Mindlin check solves the normal problem twice).
    pub frames: usize,
    /// Normal load of the last frame solved (N).
    pub normal_force_n: f64,
}

/// The outcome of a trajectory: the last frame's fields, its total approach of the indenter's
/// tip (mm, for unrotated indenters) and the number of frames solved.
pub(crate) struct Run {
    pub(crate) fields: Fields,
    pub(crate) approach_mm: f64,
    pub(crate) frames: usize,
}

/// Solves the scene's frames in order on `grid` with `kind`, then `extra` poses (tangential
/// steps) at the last frame's normal control.
pub(crate) fn run(
    scene: &Scene,
    kind: SolverKind,
    grid: Grid,
    extra: &[Pose],
) -> Result<Run, ContactError> {
    run_fem(scene, kind, grid, extra, FemOptions::default(), scene.gel)
}

/// [`run`] with the finite-element rung's options.
pub(crate) fn run_with(
    scene: &Scene,
    kind: SolverKind,
    grid: Grid,
    fem: FemOptions,
    extra: &[Pose],
) -> Result<Run, ContactError> {
    run_fem(scene, kind, grid, extra, fem, scene.gel)
}

/// [`run`] with the finite-element rung's options and another gel.
fn run_fem(
    scene: &Scene,
    kind: SolverKind,
    grid: Grid,
    extra: &[Pose],
    fem: FemOptions,
    gel: sparsh_scene::Gel,
) -> Result<Run, ContactError> {
    let mut solver: Box<dyn crate::ContactSolver> = match kind {
        SolverKind::Fem => Box::new(Fem::new(gel, grid).with_options(fem)),
        _ => solver_for(kind, &gel, grid),
    };
    let frames = scene.frames();
    let mut steps: Vec<(Pose, Option<f64>)> =
        frames.iter().map(|f| (f.pose, f.normal_force_n)).collect();
    let last_force = steps.last().and_then(|s| s.1);
    steps.extend(extra.iter().map(|p| (*p, last_force)));
    let mut previous: Option<Pose> = None;
    let mut last = None;
    let frames = steps.len();
    for (pose, force) in steps {
        let gap = GapField::cast(&scene.indenter, &pose, grid);
        let shift = match &previous {
            Some(p) => rigid_shift_mm(p, &pose, &gap),
            None => vec![[0.0, 0.0]; grid.len()],
        };
        let input = ContactInput {
            gap: &gap,
            normal: force.map_or(NormalControl::Approach, NormalControl::Force),
            rigid_shift_mm: &shift,
        };
        let fields = solver.solve(&input)?;
        // The tip's approach from the pose, not from the sampled gap (which misses the tip when
        // no cell centre lies under it): the analytic indenters have their tip at the origin.
        let approach_mm = fields.approach_offset_mm - pose.position_mm.z;
        last = Some(Run {
            fields,
            approach_mm,
            frames,
        });
        previous = Some(pose);
    }
    Ok(last.expect("a scene has at least one frame"))
}

fn contact_radius_mm(fields: &Fields) -> f64 {
    (fields.contact_area_mm2() / std::f64::consts::PI).sqrt()
}

/// Twisting moment about the vertical axis through `centre`, Σ ((x − x₀) q_y − (y − y₀) q_x) dA
/// (N·mm).
fn twisting_moment_n_mm(fields: &Fields, centre: [f64; 2]) -> f64 {
    let g = fields.grid;
    (0..g.len())
        .map(|k| {
            let (x, y) = (g.x_mm(k % g.nx) - centre[0], g.y_mm(k / g.nx) - centre[1]);
            x * fields.traction_y_kpa[k] - y * fields.traction_x_kpa[k]
        })
        .sum::<f64>()
        * g.cell_area_mm2()
        * 1e-3
}

fn peak_pressure_kpa(fields: &Fields) -> f64 {
    fields.pressure_kpa.iter().copied().fold(0.0, f64::max)
}

fn evaluate(scene: &Scene, spec: &Spec, grid: Grid) -> Result<Vec<Value>, ContactError> {
    let case = Case {
        check: spec.check,
        q_over_mu_p: spec.q_over_mu_p.unwrap_or(f64::NAN),
        tangential_steps: spec.tangential_steps,
    };
    Ok(evaluate_case(scene, &case, grid)?.values)
}

/// What a check needs beyond its scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Case {
    /// The analytic solution compared with.
    pub check: Check,
    /// Cattaneo–Mindlin: tangential load as a fraction of μP; at 1 or more the shift is this
    /// multiple of the shift that starts gross sliding, and the reference load is μP.
    pub q_over_mu_p: f64,
    /// Cattaneo–Mindlin: increments of the tangential shift.
    pub tangential_steps: usize,
}

/// Solves `scene` with its own solver rung on `grid` (the layered-against-half-space check
/// runs both) and compares with the analytic solution of `case.check`.
pub fn evaluate_case(scene: &Scene, case: &Case, grid: Grid) -> Result<Evaluation, ContactError> {
    evaluate_case_with(scene, case, grid, FemOptions::default())
}

/// [`evaluate_case`] with the finite-element rung's mesh and iteration options.
pub fn evaluate_case_with(
    scene: &Scene,
    case: &Case,
    grid: Grid,
    fem: FemOptions,
) -> Result<Evaluation, ContactError> {
    let gel = scene.gel;
    let run = |scene: &Scene, kind, grid, extra: &[Pose]| {
        run_fem(scene, kind, grid, extra, fem, scene.gel)
    };
    let e_star = gel.effective_modulus_kpa();
    let spec_indenter = &scene.indenter_spec;
    let radius_mm = spec_indenter.radius_mm.unwrap_or(f64::NAN);
    let hertz = Hertz {
        radius_mm,
        effective_modulus_kpa: e_star,
    };
    let v = |quantity, analytic, simulated| Value {
        quantity,
        analytic,
        simulated,
    };
    let mut frames = 0;
    let mut normal_force_n = 0.0;
    let mut count = |r: Run| {
        frames += r.frames;
        normal_force_n = r.fields.force_n[2];
        r
    };
    let out = match case.check {
        Check::Hertz => {
            let r = count(run(scene, scene.solver, grid, &[])?);
            let force = hertz.force_n(r.approach_mm);
            vec![
                v("force (N)", force, r.fields.force_n[2]),
                v(
                    "contact_radius (mm)",
                    hertz.contact_radius_mm(force),
                    contact_radius_mm(&r.fields),
                ),
                v(
                    "peak_pressure (kPa)",
                    hertz.peak_pressure_kpa(force),
                    peak_pressure_kpa(&r.fields),
                ),
            ]
        }
        Check::HertzLoad => {
            let r = count(run(scene, scene.solver, grid, &[])?);
            let force = r.fields.force_n[2];
            vec![
                v("approach (mm)", hertz.approach_mm(force), r.approach_mm),
                v(
                    "contact_radius (mm)",
                    hertz.contact_radius_mm(force),
                    contact_radius_mm(&r.fields),
                ),
                v(
                    "peak_pressure (kPa)",
                    hertz.peak_pressure_kpa(force),
                    peak_pressure_kpa(&r.fields),
                ),
            ]
        }
        Check::FlatPunch => {
            let r = count(run(scene, scene.solver, grid, &[])?);
            vec![v(
                "force (N)",
                reference::flat_punch_force_n(radius_mm, r.approach_mm, e_star),
                r.fields.force_n[2],
            )]
        }
        Check::Cone => {
            let alpha = spec_indenter
                .half_angle_deg
                .unwrap_or(f64::NAN)
                .to_radians();
            let r = count(run(scene, scene.solver, grid, &[])?);
            vec![
                v(
                    "force (N)",
                    reference::cone_force_n(r.approach_mm, alpha, e_star),
                    r.fields.force_n[2],
                ),
                v(
                    "contact_radius (mm)",
                    reference::cone_contact_radius_mm(r.approach_mm, alpha),
                    contact_radius_mm(&r.fields),
                ),
            ]
        }
        Check::CattaneoMindlin => {
            let ratio = case.q_over_mu_p;
            let normal = count(run(scene, scene.solver, grid, &[])?);
            let force = hertz.force_n(normal.approach_mm);
            let cm = CattaneoMindlin {
                contact_radius_mm: hertz.contact_radius_mm(force),
                normal_force_n: force,
                friction: gel.friction,
                shear_modulus_kpa: gel.youngs_modulus_kpa / (2.0 * (1.0 + gel.poisson_ratio)),
                poisson_ratio: gel.poisson_ratio,
            };
            let last = scene.frames().last().expect("frames").pose;
            let shift = if ratio >= 1.0 {
                cm.shift_mm(1.0) * ratio
            } else {
                cm.shift_mm(ratio)
            };
            let load_ratio = ratio.min(1.0);
            let steps = case.tangential_steps.max(1);
            let extra: Vec<Pose> = (1..=steps)
                .map(|k| {
                    let mut p = last;
                    p.position_mm.x += shift * k as f64 / steps as f64;
                    p
                })
                .collect();
            let r = count(run(scene, scene.solver, grid, &extra)?);
            let stick_cells = r
                .fields
                .contact
                .iter()
                .zip(&r.fields.slip)
                .filter(|(c, s)| **c && !**s)
                .count();
            let stick_mm =
                (stick_cells as f64 * grid.cell_area_mm2() / std::f64::consts::PI).sqrt();
            vec![
                v(
                    "tangential_force (N)",
                    load_ratio * gel.friction * force,
                    r.fields.force_n[0],
                ),
                v(
                    "stick_radius (mm)",
                    cm.stick_radius_mm(load_ratio),
                    stick_mm,
                ),
            ]
        }
        Check::TorsionStuck | Check::TorsionSliding => {
            let r = count(run(scene, scene.solver, grid, &[])?);
            let frames = scene.frames();
            let (first, last) = (frames[0].pose, frames[frames.len() - 1].pose);
            let force = hertz.force_n(r.approach_mm);
            let a = hertz.contact_radius_mm(force);
            let analytic = if case.check == Check::TorsionStuck {
                let twist_rad = (last.rotation_deg.z - first.rotation_deg.z).to_radians();
                let shear_kpa = gel.youngs_modulus_kpa / (2.0 * (1.0 + gel.poisson_ratio));
                16.0 / 3.0 * shear_kpa * a.powi(3) * twist_rad * 1e-3
            } else {
                3.0 * std::f64::consts::PI / 16.0 * gel.friction * force * a
            };
            let centre = [last.position_mm.x, last.position_mm.y];
            vec![v(
                "moment (N·mm)",
                analytic,
                twisting_moment_n_mm(&r.fields, centre),
            )]
        }
        Check::BondedLayer => {
            let r = count(run(scene, scene.solver, grid, &[])?);
            let hertz_a = (radius_mm * r.approach_mm).sqrt();
            let chi = hertz_a / gel.thickness_mm;
            let factor = reference::bonded_layer_force_factor(chi).ok_or_else(|| {
                ContactError::OutOfValidity {
                    solver: "bonded-layer reference",
                    reason: format!("no reference at χ = {chi:.3}: known for χ ≤ 0.5 and at χ = 1"),
                }
            })?;
            vec![
                v(
                    "force (N)",
                    hertz.force_n(r.approach_mm) * factor,
                    r.fields.force_n[2],
                ),
                v("contact_radius (mm)", hertz_a, contact_radius_mm(&r.fields)),
            ]
        }
        Check::VersusLayered => {
            let own = count(run(scene, scene.solver, grid, &[])?);
            let layer = count(run(scene, SolverKind::Layered, grid, &[])?);
            let [fx, fy, fz] = layer.fields.force_n;
            let mut rows = vec![v("force (N)", fz, own.fields.force_n[2])];
            // A slide (a shear load over a twentieth of the normal one) is graded on it too.
            if fx.hypot(fy) > 0.05 * fz.abs() {
                let along = |f: [f64; 3]| (f[0] * fx + f[1] * fy) / fx.hypot(fy);
                rows.push(v(
                    "tangential_force (N)",
                    along(layer.fields.force_n),
                    along(own.fields.force_n),
                ));
            }
            rows
        }
        Check::Locking => {
            let mut at = |nu: f64| -> Result<f64, ContactError> {
                let gel = sparsh_scene::Gel {
                    poisson_ratio: nu,
                    ..scene.gel
                };
                let r = count(run_fem(scene, scene.solver, grid, &[], fem, gel)?);
                Ok(r.fields.force_n[2] / gel.effective_modulus_kpa())
            };
            let (compressible, incompressible) = (at(0.49)?, at(0.4999)?);
            vec![v("force_over_e_star (N/kPa)", compressible, incompressible)]
        }
        Check::FiniteStrainSphere => {
            let r = count(run(scene, scene.solver, grid, &[])?);
            let hertz_a = (radius_mm * r.approach_mm).sqrt();
            let bottom = reference::garcia_bottom_effect(hertz_a / gel.thickness_mm);
            let x = (r.approach_mm / radius_mm).sqrt();
            let lin = reference::lin_neo_hookean_factor(x * x);
            let sneddon = reference::sneddon_sphere_force_n(
                radius_mm,
                r.approach_mm,
                hertz.effective_modulus_kpa,
            )
            .ok_or_else(|| ContactError::OutOfValidity {
                solver: "Sneddon sphere reference",
                reason: format!("no contact (approach {} mm)", r.approach_mm),
            })?;
            vec![
                v(
                    "force_vs_hertz (N)",
                    hertz.force_n(r.approach_mm) * bottom,
                    r.fields.force_n[2],
                ),
                v(
                    "force_vs_sneddon_sphere (N)",
                    sneddon * bottom,
                    r.fields.force_n[2],
                ),
                v(
                    "force_vs_lin2009 (N)",
                    hertz.force_n(r.approach_mm) * bottom * lin,
                    r.fields.force_n[2],
                ),
            ]
        }
        Check::LayeredVsHalfspace => {
            let half = count(run(scene, SolverKind::Halfspace, grid, &[])?);
            let layer = count(run(scene, SolverKind::Layered, grid, &[])?);
            vec![v(
                "force (N)",
                half.fields.force_n[2],
                layer.fields.force_n[2],
            )]
        }
    };
    Ok(Evaluation {
        values: out,
        frames,
        normal_force_n,
    })
}
