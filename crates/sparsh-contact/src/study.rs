//! Speed against accuracy of the solver rungs, and where each one fails (`sparsh study`).
//!
//! - **Accuracy study**: every rung × grid resolution (contact radius a in cells) × scene with an
//!   analytic answer — Hertz, flat punch, cone (Sneddon), Cattaneo–Mindlin (tangential force) on a
//!   thick gel (a/h = 0.002), and a sphere on incompressible bonded layers of a/h = 0.01 … 1 (Garcia
//!   & Garcia 2018) — timing each frame and comparing the force with the analytic one.
//! - **Stability map**: per rung, one parameter at a time pushed towards where models break:
//!   indentation depth over gel thickness, cone semi-angle down to 10° and a box edge, Poisson
//!   ratio up to 0.5, friction 0–2, tangential load up to and past gross slip, grid coarseness.
//!   Every point records whether it met the tolerance, missed it, did not converge, left the
//!   model's validity or (never expected) produced a non-finite value or a panic — with the
//!   reason.
//! - **Solver table**: the worst error and cost of each rung at each studied (a/cell, a/h), built
//!   from a subset of the scenes (the cone and a/h = 0.3 are held out to test `solver = "auto"`
//!   on), read by [`sparsh_scene::auto`].
//!
//! Times are the fastest of `repeats` runs on the calling thread's rayon pool (`sparsh study`
//! runs on one thread so that other load on the machine perturbs the numbers least).

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::Path;
use std::time::Instant;

use glam::DVec3;
use sparsh_scene::auto::{SolverTable, TableRow};
use sparsh_scene::{Pose, Scene, SolverKind};

use crate::validation::{Case, Check, evaluate_case, run};
use crate::{ContactError, FemOptions};

/// Gel thickness of the half-space scenes (mm): a/h = 0.002 for their 1 mm contacts.
const THICK_GEL_MM: f64 = 500.0;

/// Gel thickness of the depth sweep (mm; a 5 mm sphere pressed into it).
const DEPTH_SWEEP_GEL_MM: f64 = 2.0;

/// Slide of the press-and-slide sweep over the press's rigid footprint radius.
const SLIDE_OVER_FOOTPRINT: f64 = 0.5;

/// Multiplier updates a frame of a finite-element reference may take: on the press-and-slide
/// sweep's δ/h 0.2, μ = 1 slide the last frame needs 106 (the rung's default cap is 100).
const REFERENCE_MAX_UPDATES: usize = 250;

/// What to run.
#[derive(Debug, Clone, PartialEq)]
pub struct StudyOptions {
    /// Grid resolutions of the accuracy study: contact radius in cells.
    pub contact_cells: Vec<f64>,
    /// Cell size of the stability sweeps other than grid coarseness (mm, for 1 mm contacts).
    pub stability_cell_mm: f64,
    /// Relative force error a point must meet (the stability map's pass mark).
    pub tolerance: f64,
    /// Runs per timed point; the fastest counts.
    pub repeats: usize,
    /// Indentation depths over gel thickness of the depth sweep.
    pub depth_over_thickness: Vec<f64>,
    /// Friction coefficients of the depth sweep (each depth is pressed at each).
    pub depth_friction: Vec<f64>,
    /// Depths over gel thickness of the press-and-slide sweep: the depth sweep's press, then a
    /// slide of half its footprint radius, graded on the tangential force.
    pub slide_depth_over_thickness: Vec<f64>,
    /// Friction coefficients of the press-and-slide sweep.
    pub slide_friction: Vec<f64>,
    /// Frames the press-and-slide sweep's slide is solved in (after the press's one): at the
    /// full study's reference mesh the μ = 1.5 slide at δ/h 0.05 settles only in ten (in five
    /// the last frame's multipliers keep wandering), and the δ/h 0.3, μ = 0.5 slide's Newton
    /// solves converge only in steps that short.
    pub slide_frames: usize,
    /// Elements per contact radius of the finite-element reference of the depth sweep (solved
    /// on a grid of half the sweep's cell).
    pub reference_elements_per_radius: f64,
    /// Run only these stability sweeps ([`SWEEPS`]) and no accuracy study; empty: the whole
    /// study. A partial study's solver table misses rows, so it is not one to ship.
    pub sweeps: Vec<String>,
    /// Stability points solved at once, each on a thread of its own (1: one after the other).
    /// The results do not depend on it; the times are each point's own thread's.
    pub jobs: usize,
}

/// The stability map's sweeps, in the order they run.
pub const SWEEPS: [&str; 7] = [
    "depth_over_thickness",
    "press_slide",
    "sharpness",
    "poisson_ratio",
    "friction",
    "tangential_load",
    "contact_cells",
];

/// The sweeps whose points are rows of the solver table (depth rows), and which rows each owns.
pub const TABLE_SWEEPS: [&str; 2] = ["depth_over_thickness", "press_slide"];

/// Whether `row` of a solver table comes from sweep `name` (presses at depth from the depth
/// sweep, slides from the press-and-slide sweep; no row from the other sweeps).
pub fn sweep_owns_row(name: &str, row: &TableRow) -> bool {
    match name {
        "depth_over_thickness" => row.depth_over_h > 0.0 && row.slide_over_a == 0.0,
        "press_slide" => row.slide_over_a > 0.0,
        _ => false,
    }
}

/// `table` with the rows of the sweeps `partial` ran replaced by `partial`'s: how a study of
/// some sweeps ([`StudyOptions::sweeps`]) brings a whole study's table up to date.
pub fn update_table(table: &SolverTable, partial: &Study) -> SolverTable {
    let replaced = |r: &TableRow| {
        partial
            .options
            .sweeps
            .iter()
            .any(|name| sweep_owns_row(name, r))
    };
    SolverTable {
        rows: table
            .rows
            .iter()
            .filter(|r| !replaced(r))
            .chain(&partial.table.rows)
            .copied()
            .collect(),
    }
}

impl StudyOptions {
    /// The full study (`sparsh study`).
    pub fn full() -> StudyOptions {
        StudyOptions {
            contact_cells: vec![2.5, 5.0, 10.0, 20.0, 40.0],
            stability_cell_mm: 0.1,
            tolerance: 0.02,
            repeats: 3,
            depth_over_thickness: vec![0.01, 0.05, 0.1, 0.2, 0.3, 0.4, 0.6, 0.8, 1.0, 1.2],
            depth_friction: vec![0.0, 0.5, 1.0, 1.5],
            slide_depth_over_thickness: vec![0.05, 0.1, 0.2, 0.3],
            slide_friction: vec![0.5, 1.0, 1.5],
            slide_frames: 10,
            reference_elements_per_radius: 12.0,
            sweeps: Vec::new(),
            jobs: 1,
        }
    }

    /// A small study for CI (`sparsh study --quick`): coarse grids, one run per point.
    pub fn quick() -> StudyOptions {
        StudyOptions {
            contact_cells: vec![2.5, 5.0, 10.0],
            stability_cell_mm: 0.2,
            tolerance: 0.02,
            repeats: 1,
            depth_over_thickness: vec![0.05, 0.2, 0.4, 1.2],
            depth_friction: vec![0.0, 1.0],
            slide_depth_over_thickness: vec![0.1],
            slide_friction: vec![1.0],
            slide_frames: 5,
            reference_elements_per_radius: 8.0,
            sweeps: Vec::new(),
            jobs: 1,
        }
    }
}

/// How a point ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    /// Within tolerance.
    Ok,
    /// Solved, but the force misses the reference by more than the tolerance.
    OverTolerance,
    /// An iteration cap was reached ([`ContactError::NotConverged`]).
    NotConverged,
    /// The solver refused the state ([`ContactError::OutOfValidity`]).
    OutOfValidity,
    /// The solver returned a non-finite force (a bug: never expected).
    NonFinite,
    /// The solver panicked (a bug: never expected).
    Panic,
}

impl Outcome {
    /// Every outcome, best first.
    pub const ALL: [Outcome; 6] = [
        Outcome::Ok,
        Outcome::OverTolerance,
        Outcome::NotConverged,
        Outcome::OutOfValidity,
        Outcome::NonFinite,
        Outcome::Panic,
    ];

    /// Name used in the CSV files.
    pub fn name(self) -> &'static str {
        match self {
            Outcome::Ok => "ok",
            Outcome::OverTolerance => "over_tolerance",
            Outcome::NotConverged => "not_converged",
            Outcome::OutOfValidity => "out_of_validity",
            Outcome::NonFinite => "non_finite",
            Outcome::Panic => "panic",
        }
    }
}

/// One timed, compared solve.
#[derive(Debug, Clone, PartialEq)]
pub struct Measurement {
    /// Reference force (N; `None` when the solve failed).
    pub reference_n: Option<f64>,
    /// Solver force (N).
    pub simulated_n: Option<f64>,
    /// (simulated − reference)/scale, with scale = |reference|, or the normal load when the
    /// reference is zero (friction 0).
    pub rel_error: Option<f64>,
    /// Fastest wall time per frame (ms); the time to failure for failed points.
    pub ms_per_frame: f64,
    /// Frames solved per run.
    pub frames: usize,
    /// How it ended.
    pub outcome: Outcome,
    /// Why it is not `ok` (empty when it is).
    pub reason: String,
}

/// One point of the accuracy study.
#[derive(Debug, Clone, PartialEq)]
pub struct StudyPoint {
    /// Scene name (`hertz`, `flat_punch`, `cone`, `cattaneo_mindlin`, `bonded_layer_0.5`, …).
    pub scene: String,
    /// Rung.
    pub rung: SolverKind,
    /// Contact radius over cell size (nominal, from the analytic radius).
    pub a_over_cell: f64,
    /// Cell size (mm).
    pub cell_mm: f64,
    /// Grid cells per side.
    pub cells_per_side: usize,
    /// Contact radius over gel thickness.
    pub a_over_h: f64,
    /// Whether the solver table is built from this point (the others test `solver = "auto"`).
    pub in_table: bool,
    /// The result.
    pub measurement: Measurement,
}

/// One point of the stability map.
#[derive(Debug, Clone, PartialEq)]
pub struct StabilityPoint {
    /// Swept parameter (`depth_over_thickness`, `sharpness`, …).
    pub sweep: &'static str,
    /// Its value as shown on the map (`δ/h 0.4`, `δ/h 0.4, μ 1`, `cone 10°`, `box edge`).
    pub label: String,
    /// The gel's friction coefficient.
    pub friction: f64,
    /// Indentation depth over gel thickness of the depth sweep (0 elsewhere).
    pub depth_over_h: f64,
    /// Contact radius over gel thickness of the depth sweep (0 elsewhere; the rigid footprint's).
    pub a_over_h: f64,
    /// Rung.
    pub rung: SolverKind,
    /// Cell size (mm).
    pub cell_mm: f64,
    /// What the force is compared with.
    pub reference: &'static str,
    /// The result.
    pub measurement: Measurement,
}

/// Everything a study produces.
#[derive(Debug, Clone, PartialEq)]
pub struct Study {
    /// Options it ran with.
    pub options: StudyOptions,
    /// Accuracy study.
    pub points: Vec<StudyPoint>,
    /// Stability map.
    pub stability: Vec<StabilityPoint>,
    /// The table for `solver = "auto"`.
    pub table: SolverTable,
}

/// The gel, indenter and pose of a scene, without its grid.
#[derive(Debug, Clone)]
struct Setup {
    indenter: String,
    depth_mm: f64,
    position_xy_mm: [f64; 2],
    rotation_deg: [f64; 3],
    poisson: f64,
    thickness_mm: f64,
    friction: f64,
    box_mm: f64,
    /// Slide along x after the press (mm; 0: a press alone), in `slide_frames` frames.
    slide_mm: f64,
    slide_frames: usize,
}

impl Setup {
    fn sphere(radius_mm: f64, depth_mm: f64) -> Setup {
        Setup {
            indenter: format!("shape = \"sphere\"\nradius_mm = {radius_mm:?}"),
            depth_mm,
            position_xy_mm: [0.0, 0.0],
            rotation_deg: [0.0; 3],
            poisson: 0.48,
            thickness_mm: THICK_GEL_MM,
            friction: 1.0,
            box_mm: 6.4,
            slide_mm: 0.0,
            slide_frames: 0,
        }
    }

    /// The poses after the press: the slide's frames (none without a slide).
    fn slide_poses(&self) -> Vec<Pose> {
        let [x, y] = self.position_xy_mm;
        let steps = if self.slide_mm > 0.0 {
            self.slide_frames
        } else {
            0
        };
        (1..=steps)
            .map(|k| Pose {
                position_mm: DVec3::new(
                    x + self.slide_mm * k as f64 / steps as f64,
                    y,
                    -self.depth_mm,
                ),
                rotation_deg: DVec3::from_array(self.rotation_deg),
            })
            .collect()
    }

    /// The force component a sweep point is graded on: tangential (x) after a slide, normal
    /// otherwise.
    fn graded_component(&self) -> usize {
        if self.slide_mm > 0.0 { 0 } else { 2 }
    }

    /// Rigid cone pressed so that Sneddon's contact radius is 1 mm.
    fn cone(half_angle_deg: f64) -> Setup {
        let depth_mm = std::f64::consts::FRAC_PI_2 / half_angle_deg.to_radians().tan();
        Setup {
            indenter: format!(
                "shape = \"cone\"\nhalf_angle_deg = {half_angle_deg:?}\nheight_mm = {:?}",
                depth_mm + 2.0
            ),
            depth_mm,
            ..Setup::sphere(1.0, 0.0)
        }
    }

    /// The scene on a square grid of `cell_mm` cells (odd count, so a cell sits on the axis).
    fn scene(&self, kind: SolverKind, cell_mm: f64) -> Result<Scene, String> {
        let n = ((self.box_mm / cell_mm).round() as usize / 2 * 2 + 1).max(9);
        let [x, y] = self.position_xy_mm;
        let text = format!(
            "solver = \"{}\"\n[sensor]\npreset = \"digit\"\nwidth_px = {n}\nheight_px = {n}\n\
             mm_per_px = {cell_mm:?}\n[gel]\nyoungs_modulus_kpa = 300.0\npoisson_ratio = {:?}\n\
             thickness_mm = {:?}\nfriction = {:?}\n[indenter]\n{}\n[[trajectory]]\n\
             time_s = 0.0\nposition_mm = [{x:?}, {y:?}, {:?}]\nrotation_deg = {:?}\n",
            kind.name(),
            self.poisson,
            self.thickness_mm,
            self.friction,
            self.indenter,
            -self.depth_mm,
            self.rotation_deg,
        );
        Scene::parse(Path::new("study"), text).map_err(|e| format!("scene: {e}"))
    }
}

/// A solve that succeeded: reference and simulated force, frames, and the error's scale.
struct Sample {
    reference_n: f64,
    simulated_n: f64,
    scale_n: f64,
    frames: usize,
}

/// Times `trial` (fastest of `repeats`, or the first run when it takes over a second), catches
/// failures and panics, and grades the force.
fn measure(
    tolerance: f64,
    repeats: usize,
    trial: &dyn Fn() -> Result<Sample, String>,
) -> Measurement {
    let failed = |outcome, reason: String, ms| Measurement {
        reference_n: None,
        simulated_n: None,
        rel_error: None,
        ms_per_frame: ms,
        frames: 0,
        outcome,
        reason,
    };
    let mut best_ms = f64::INFINITY;
    let mut sample = None;
    for _ in 0..repeats.max(1) {
        let start = Instant::now();
        let result = catch_unwind(AssertUnwindSafe(trial));
        let ms = start.elapsed().as_secs_f64() * 1e3;
        match result {
            Err(payload) => {
                let message = payload
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| payload.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "unknown panic".into());
                return failed(Outcome::Panic, format!("panic: {message}"), ms);
            }
            Ok(Err(reason)) => {
                let outcome = if reason.contains("no convergence") {
                    Outcome::NotConverged
                } else {
                    Outcome::OutOfValidity
                };
                return failed(outcome, reason, ms);
            }
            Ok(Ok(s)) => {
                best_ms = best_ms.min(ms / s.frames.max(1) as f64);
                sample = Some(s);
                // A run of seconds is timed well enough once (the finite elements).
                if ms > 1000.0 {
                    break;
                }
            }
        }
    }
    let Some(s) = sample else {
        return failed(Outcome::Panic, "no run".into(), 0.0);
    };
    let rel = (s.simulated_n - s.reference_n) / s.scale_n;
    let (outcome, reason) = if !(rel.is_finite() && s.simulated_n.is_finite()) {
        (
            Outcome::NonFinite,
            format!(
                "non-finite force {} against {}",
                s.simulated_n, s.reference_n
            ),
        )
    } else if rel.abs() > tolerance {
        (
            Outcome::OverTolerance,
            format!(
                "force error {:+.2} % beyond ±{} %",
                100.0 * rel,
                100.0 * tolerance
            ),
        )
    } else {
        (Outcome::Ok, String::new())
    };
    Measurement {
        reference_n: Some(s.reference_n),
        simulated_n: Some(s.simulated_n),
        rel_error: rel.is_finite().then_some(rel),
        ms_per_frame: best_ms,
        frames: s.frames,
        outcome,
        reason,
    }
}

/// Solves an analytic case and returns its force against the analytic one.
fn analytic_trial(scene: &Scene, case: &Case) -> Result<Sample, String> {
    let evaluation = evaluate_case(scene, case, scene.grid()).map_err(|e| e.to_string())?;
    let force = &evaluation.values[0];
    let scale_n = if force.analytic != 0.0 {
        force.analytic.abs()
    } else {
        evaluation.normal_force_n.abs()
    };
    Ok(Sample {
        reference_n: force.analytic,
        simulated_n: force.simulated,
        scale_n,
        frames: evaluation.frames,
    })
}

/// The graded force component of a sweep's scene ([`Setup::graded_component`]) at its last
/// frame, after its slide, on its own grid.
fn sweep_force_n(scene: &Scene, setup: &Setup) -> Result<(f64, usize), ContactError> {
    let r = run(scene, scene.solver, scene.grid(), &setup.slide_poses())?;
    Ok((r.fields.force_n[setup.graded_component()], r.frames))
}

/// A scene of the accuracy study.
struct AnalyticScene {
    name: String,
    setup: Setup,
    case: Case,
    a_over_h: f64,
    in_table: bool,
}

fn case(check: Check) -> Case {
    Case {
        check,
        q_over_mu_p: f64::NAN,
        tangential_steps: 4,
    }
}

fn mindlin(q_over_mu_p: f64) -> Case {
    Case {
        q_over_mu_p,
        ..case(Check::CattaneoMindlin)
    }
}

/// Bonded-layer contact radii over thickness of the accuracy study; 0.3 is held out of the table.
const LAYER_A_OVER_H: [f64; 6] = [0.01, 0.03, 0.1, 0.3, 0.5, 1.0];

/// Every scene has a 1 mm analytic contact radius (Hertz radius for the layers).
fn analytic_scenes() -> Vec<AnalyticScene> {
    let thick = 1.0 / THICK_GEL_MM;
    let incompressible = |mut s: Setup| {
        s.poisson = 0.5;
        s
    };
    let mut scenes = vec![
        AnalyticScene {
            name: "hertz".into(),
            setup: Setup::sphere(100.0, 0.01),
            case: case(Check::Hertz),
            a_over_h: thick,
            in_table: true,
        },
        AnalyticScene {
            name: "flat_punch".into(),
            setup: Setup {
                indenter: "shape = \"cylinder\"\nradius_mm = 1.0\nheight_mm = 2.0".into(),
                ..Setup::sphere(1.0, 0.01)
            },
            case: case(Check::FlatPunch),
            a_over_h: thick,
            in_table: true,
        },
        AnalyticScene {
            name: "cone".into(),
            setup: Setup::cone(80.0),
            case: case(Check::Cone),
            a_over_h: thick,
            in_table: false,
        },
        AnalyticScene {
            name: "cattaneo_mindlin".into(),
            setup: Setup {
                friction: 0.5,
                ..incompressible(Setup::sphere(100.0, 0.01))
            },
            case: mindlin(0.5),
            a_over_h: thick,
            in_table: true,
        },
    ];
    for chi in LAYER_A_OVER_H {
        scenes.push(AnalyticScene {
            name: format!("bonded_layer_{chi}"),
            setup: Setup {
                thickness_mm: 1.0 / chi,
                // Garcia & Garcia's layer is frictionless; with friction the finite elements
                // see the radial shear a stuck surface carries (the boundary elements do not).
                friction: 0.0,
                ..incompressible(Setup::sphere(100.0, 0.01))
            },
            case: case(Check::BondedLayer),
            a_over_h: chi,
            in_table: chi != 0.3,
        });
    }
    scenes
}

/// One parameter value of a stability sweep: its label, the setup, the reference, the cell.
struct SweepPoint {
    sweep: &'static str,
    label: String,
    setup: Setup,
    case: Option<Case>,
    cell_mm: f64,
    /// Without an analytic case: the rung whose solution on a grid of half the cell is the
    /// reference (the half-space rung, or finite elements at finite depth).
    reference_rung: SolverKind,
    /// Depth over thickness and rigid footprint over thickness (depth sweep; 0 elsewhere).
    depth_over_h: f64,
    a_over_h: f64,
}

impl SweepPoint {
    fn friction(&self) -> f64 {
        self.setup.friction
    }
}

/// The reference names of the stability map, by check.
fn reference_name(case: Option<&Case>, reference_rung: SolverKind) -> &'static str {
    if case.is_none() && reference_rung == SolverKind::Fem {
        return "fem (neo-Hookean, finite strain) on a finer mesh and a twice finer grid";
    }
    match case.map(|c| c.check) {
        Some(Check::BondedLayer) => "bonded layer (Garcia & Garcia; exact solution at χ = 1)",
        Some(Check::Cone) => "Sneddon cone",
        Some(Check::Hertz) => "Hertz",
        Some(Check::CattaneoMindlin) => "Cattaneo-Mindlin tangential force",
        Some(_) => "analytic",
        None => "halfspace on a twice finer grid",
    }
}

fn stability_sweeps(options: &StudyOptions) -> Vec<SweepPoint> {
    let cell_mm = options.stability_cell_mm;
    let mut points = Vec::new();
    let mut push = |sweep, label: String, setup, case, cell_mm| {
        points.push(SweepPoint {
            sweep,
            label,
            setup,
            case,
            cell_mm,
            reference_rung: SolverKind::Halfspace,
            depth_over_h: 0.0,
            a_over_h: 0.0,
        })
    };
    // A 5 mm sphere on a 2 mm incompressible layer pressed up to and past the layer's
    // thickness, at each friction coefficient, against the finite-strain (neo-Hookean) finite
    // elements with the same friction: linear theory is not the answer at depth, and friction
    // there stiffens the press beyond what the linear coupling of the layer gives. δ ≥ h no
    // rung may accept.
    // The same press then slid by half its footprint radius, graded on the tangential force:
    // where the layer's normal–tangential coupling and the stuck surface's finite strain move
    // the friction force. Its rows enter the solver table beside the presses', so `auto` and
    // the validity limits take the worse of the two at each depth and friction.
    let mut depth_points = Vec::new();
    let presses = options.depth_friction.iter().flat_map(|&mu| {
        options
            .depth_over_thickness
            .iter()
            .map(move |&d| (mu, d, false))
    });
    let slides = options.slide_friction.iter().flat_map(|&mu| {
        options
            .slide_depth_over_thickness
            .iter()
            .map(move |&d| (mu, d, true))
    });
    for (mu, ratio, slide) in presses.chain(slides) {
        let (radius, h) = (5.0, DEPTH_SWEEP_GEL_MM);
        let depth = ratio * h;
        let footprint = (2.0f64 * radius * depth - depth * depth).max(0.0).sqrt();
        let slide_mm = if slide {
            SLIDE_OVER_FOOTPRINT * footprint
        } else {
            0.0
        };
        let setup = Setup {
            poisson: 0.5,
            thickness_mm: h,
            friction: mu,
            box_mm: 3.2 * footprint + 1.0 + 2.0 * slide_mm,
            slide_mm,
            slide_frames: options.slide_frames,
            ..Setup::sphere(radius, depth)
        };
        depth_points.push(SweepPoint {
            sweep: if slide {
                "press_slide"
            } else {
                "depth_over_thickness"
            },
            label: match (slide, mu == 0.0) {
                (true, _) => format!("δ/h {ratio}, μ {mu}, slide {SLIDE_OVER_FOOTPRINT} a"),
                (false, true) => format!("δ/h {ratio}"),
                (false, false) => format!("δ/h {ratio}, μ {mu}"),
            },
            setup,
            case: None,
            cell_mm,
            reference_rung: SolverKind::Fem,
            depth_over_h: ratio,
            a_over_h: footprint / h,
        });
    }
    for angle in [80.0, 60.0, 45.0, 30.0, 20.0, 10.0] {
        push(
            "sharpness",
            format!("cone {angle}°"),
            Setup::cone(angle),
            Some(case(Check::Cone)),
            cell_mm,
        );
    }
    // A 3 mm cube rolled 45° about x: its lower edge, along x, pressed 0.1 mm.
    let half_diagonal = 1.5 * std::f64::consts::FRAC_1_SQRT_2;
    push(
        "sharpness",
        "box edge".into(),
        Setup {
            indenter: "shape = \"box\"\nsize_mm = [3.0, 3.0, 3.0]".into(),
            depth_mm: 0.1 - half_diagonal,
            position_xy_mm: [0.0, half_diagonal],
            rotation_deg: [45.0, 0.0, 0.0],
            ..Setup::sphere(1.0, 0.0)
        },
        None,
        cell_mm,
    );
    for nu in [0.0, 0.2, 0.3, 0.4, 0.45, 0.49, 0.5] {
        push(
            "poisson_ratio",
            format!("ν {nu}"),
            Setup {
                poisson: nu,
                ..Setup::sphere(100.0, 0.01)
            },
            Some(case(Check::Hertz)),
            cell_mm,
        );
    }
    for mu in [0.0, 0.25, 0.5, 1.0, 1.5, 2.0] {
        push(
            "friction",
            format!("μ {mu}"),
            Setup {
                friction: mu,
                poisson: 0.5,
                ..Setup::sphere(100.0, 0.01)
            },
            Some(mindlin(0.5)),
            cell_mm,
        );
    }
    for q in [0.2, 0.5, 0.8, 0.95, 1.0, 1.5] {
        push(
            "tangential_load",
            format!("Q/μP {q}"),
            Setup {
                friction: 0.5,
                poisson: 0.5,
                ..Setup::sphere(100.0, 0.01)
            },
            Some(mindlin(q)),
            cell_mm,
        );
    }
    for cells in [0.5f64, 1.0, 2.0, 4.0, 8.0, 16.0] {
        let cell = 1.0 / cells;
        push(
            "contact_cells",
            format!("a/cell {cells}"),
            Setup {
                box_mm: (9.0 * cell).max(6.4),
                ..Setup::sphere(100.0, 0.01)
            },
            Some(case(Check::Hertz)),
            cell,
        );
    }
    depth_points.extend(points);
    depth_points
}

/// Runs the accuracy study and the stability map (or only the sweeps of
/// [`StudyOptions::sweeps`]); `progress` gets one line per point.
pub fn run_study(options: &StudyOptions, progress: &mut dyn FnMut(&str)) -> Study {
    let mut points = Vec::new();
    let whole = options.sweeps.is_empty();
    let scenes = if whole { analytic_scenes() } else { Vec::new() };
    for scene in scenes {
        for &cells in &options.contact_cells {
            let cell_mm = 1.0 / cells;
            for rung in SolverKind::ALL {
                let trial = || {
                    let s = scene.setup.scene(rung, cell_mm)?;
                    analytic_trial(&s, &scene.case)
                };
                let measurement = measure(options.tolerance, options.repeats, &trial);
                let cells_per_side = scene
                    .setup
                    .scene(rung, cell_mm)
                    .map(|s| s.grid().nx)
                    .unwrap_or(0);
                progress(&format!(
                    "{:<18} {:<9} a/cell {:>4} {:>8.2} ms/frame  {}",
                    scene.name,
                    rung.name(),
                    cells,
                    measurement.ms_per_frame,
                    measurement
                        .rel_error
                        .map_or(measurement.reason.clone(), |e| format!("{:+.3e}", e))
                ));
                points.push(StudyPoint {
                    scene: scene.name.clone(),
                    rung,
                    a_over_cell: cells,
                    cell_mm,
                    cells_per_side,
                    a_over_h: scene.a_over_h,
                    in_table: scene.in_table,
                    measurement,
                });
            }
        }
    }

    let sweeps: Vec<SweepPoint> = stability_sweeps(options)
        .into_iter()
        .filter(|p| whole || options.sweeps.iter().any(|s| s == p.sweep))
        .collect();
    let stability = solve_sweep_points(&sweeps, options, progress);

    let table = solver_table(&points, &stability);
    Study {
        options: options.clone(),
        points,
        stability,
        table,
    }
}

/// One stability point: its reference (for a press at depth the finite elements on a finer
/// mesh), then every rung against it, in [`SolverKind::ALL`]'s order.
fn solve_sweep_point(
    point: &SweepPoint,
    options: &StudyOptions,
    progress: &mut dyn FnMut(String),
) -> Vec<StabilityPoint> {
    let mut solved = Vec::new();
    let reference = reference_name(point.case.as_ref(), point.reference_rung);
    // Without a closed form (the box edge, a press at depth) the reference is the half-space
    // or the finite-element rung on a grid of half the cell size.
    let fem = FemOptions {
        elements_per_radius: options.reference_elements_per_radius,
        max_updates: REFERENCE_MAX_UPDATES,
        ..FemOptions::default()
    };
    let fine = match point.case {
        None => point
            .setup
            .scene(point.reference_rung, point.cell_mm / 2.0)
            .and_then(|s| {
                let r = crate::validation::run_with(
                    &s,
                    s.solver,
                    s.grid(),
                    fem,
                    &point.setup.slide_poses(),
                )
                .map_err(|e| e.to_string())?;
                Ok((r.fields.force_n[point.setup.graded_component()], r.frames))
            }),
        Some(_) => Ok((f64::NAN, 0)),
    };
    for rung in SolverKind::ALL {
        let trial = || {
            let s = point.setup.scene(rung, point.cell_mm)?;
            match &point.case {
                Some(case) => analytic_trial(&s, case),
                None => {
                    let (reference_n, _) =
                        fine.clone().map_err(|e| format!("reference failed: {e}"))?;
                    let (simulated_n, frames) =
                        sweep_force_n(&s, &point.setup).map_err(|e| e.to_string())?;
                    Ok(Sample {
                        reference_n,
                        simulated_n,
                        scale_n: reference_n.abs(),
                        frames,
                    })
                }
            }
        };
        let measurement = measure(options.tolerance, 1, &trial);
        progress(format!(
            "stability {:<20} {:<10} {:<9} {}",
            point.sweep,
            point.label,
            rung.name(),
            if measurement.outcome == Outcome::Ok {
                "ok".to_string()
            } else {
                measurement.reason.clone()
            }
        ));
        solved.push(StabilityPoint {
            sweep: point.sweep,
            label: point.label.clone(),
            friction: point.friction(),
            depth_over_h: point.depth_over_h,
            a_over_h: point.a_over_h,
            rung,
            cell_mm: point.cell_mm,
            reference,
            measurement,
        });
    }
    solved
}

/// A worker's report: a progress line, or a point's results by its index.
enum Report {
    Line(String),
    Solved(usize, Vec<StabilityPoint>),
}

/// The stability points' results in the points' order, solved by [`StudyOptions::jobs`]
/// threads (each with a rayon pool of one thread, as `sparsh study` runs a single job), taking
/// the next unsolved point as they finish; progress lines are passed on as they arrive.
fn solve_sweep_points(
    sweeps: &[SweepPoint],
    options: &StudyOptions,
    progress: &mut dyn FnMut(&str),
) -> Vec<StabilityPoint> {
    if options.jobs <= 1 || sweeps.len() <= 1 {
        return sweeps
            .iter()
            .flat_map(|point| solve_sweep_point(point, options, &mut |line| progress(&line)))
            .collect();
    }
    let next = std::sync::atomic::AtomicUsize::new(0);
    let mut solved: Vec<Option<Vec<StabilityPoint>>> = vec![None; sweeps.len()];
    std::thread::scope(|scope| {
        let (sender, reports) = std::sync::mpsc::channel();
        for _ in 0..options.jobs.min(sweeps.len()) {
            let (sender, next) = (sender.clone(), &next);
            scope.spawn(move || {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(1)
                    .build()
                    .expect("a rayon pool of one thread");
                loop {
                    let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    let Some(point) = sweeps.get(i) else { break };
                    let lines = sender.clone();
                    let result = pool.install(|| {
                        solve_sweep_point(point, options, &mut |line| {
                            let _ = lines.send(Report::Line(line));
                        })
                    });
                    let _ = sender.send(Report::Solved(i, result));
                }
            });
        }
        drop(sender);
        for report in reports {
            match report {
                Report::Line(line) => progress(&line),
                Report::Solved(i, result) => solved[i] = Some(result),
            }
        }
    });
    solved.into_iter().flatten().flatten().collect()
}

/// The solver table from the accuracy study's `in_table` points: at each rung and resolution,
/// a row for the thick gel (worst over the half-space scenes) and one per bonded layer (worst of
/// the half-space scenes and that layer; a rung that declines thick gels as outside its
/// validity, the finite elements, is judged on the layer alone). Failed points count as an
/// infinite error. Then, per rung, one row per point of the stability map's depth sweep and of
/// its press-and-slide sweep (their errors against the finite-strain reference: the normal
/// force of a press, the tangential force after a slide, marked by its `slide_over_a`;
/// [`SolverTable::depth_error`] reads the slides' rows for sliding contacts only).
pub fn solver_table(points: &[StudyPoint], stability: &[StabilityPoint]) -> SolverTable {
    let error = |p: &StudyPoint| {
        p.measurement
            .rel_error
            .filter(|_| matches!(p.measurement.outcome, Outcome::Ok | Outcome::OverTolerance))
            .map_or(f64::INFINITY, f64::abs)
    };
    let worst = |pts: &[&StudyPoint]| {
        pts.iter().fold((0.0f64, 0.0f64), |(e, ms), p| {
            (e.max(error(p)), ms.max(p.measurement.ms_per_frame))
        })
    };
    let mut resolutions: Vec<f64> = points.iter().map(|p| p.a_over_cell).collect();
    resolutions.sort_by(f64::total_cmp);
    resolutions.dedup();
    let mut layers: Vec<f64> = points
        .iter()
        .filter(|p| p.in_table && p.a_over_h > 1.0 / THICK_GEL_MM)
        .map(|p| p.a_over_h)
        .collect();
    layers.sort_by(f64::total_cmp);
    layers.dedup();
    let mut rows = Vec::new();
    for rung in SolverKind::ALL {
        for &cells in &resolutions {
            let at: Vec<&StudyPoint> = points
                .iter()
                .filter(|p| p.in_table && p.rung == rung && p.a_over_cell == cells)
                .collect();
            let thick: Vec<&StudyPoint> = at
                .iter()
                .copied()
                .filter(|p| p.a_over_h <= 1.0 / THICK_GEL_MM)
                .collect();
            if thick.is_empty() {
                continue;
            }
            let (base_error, base_ms) = worst(&thick);
            rows.push(TableRow {
                rung,
                a_over_cell: cells,
                a_over_h: 1.0 / THICK_GEL_MM,
                depth_over_h: 0.0,
                friction: 0.0,
                slide_over_a: 0.0,
                rel_error: base_error,
                ms_per_frame: base_ms,
            });
            let declines_thick = thick
                .iter()
                .all(|p| p.measurement.outcome == Outcome::OutOfValidity);
            let (base_error, base_ms) = if declines_thick {
                (0.0, 0.0)
            } else {
                (base_error, base_ms)
            };
            for &chi in &layers {
                let layer: Vec<&StudyPoint> =
                    at.iter().copied().filter(|p| p.a_over_h == chi).collect();
                let (e, ms) = worst(&layer);
                rows.push(TableRow {
                    rung,
                    a_over_cell: cells,
                    a_over_h: chi,
                    depth_over_h: 0.0,
                    friction: 0.0,
                    slide_over_a: 0.0,
                    rel_error: base_error.max(e),
                    ms_per_frame: base_ms.max(ms),
                });
            }
        }
        for p in stability
            .iter()
            .filter(|p| p.rung == rung && p.depth_over_h > 0.0)
        {
            let m = &p.measurement;
            rows.push(TableRow {
                rung,
                a_over_cell: p.a_over_h * DEPTH_SWEEP_GEL_MM / p.cell_mm,
                a_over_h: p.a_over_h,
                depth_over_h: p.depth_over_h,
                friction: p.friction,
                slide_over_a: if p.sweep == "press_slide" {
                    SLIDE_OVER_FOOTPRINT
                } else {
                    0.0
                },
                rel_error: m
                    .rel_error
                    .filter(|_| matches!(m.outcome, Outcome::Ok | Outcome::OverTolerance))
                    .map_or(f64::INFINITY, f64::abs),
                ms_per_frame: m.ms_per_frame,
            });
        }
    }
    SolverTable { rows }
}

fn opt(v: Option<f64>) -> String {
    v.map_or(String::new(), |v| format!("{v:e}"))
}

fn csv_text(reason: &str) -> String {
    format!("\"{}\"", reason.replace('"', "'"))
}

impl Study {
    /// `study.csv`: one row per accuracy point.
    pub fn points_csv(&self) -> String {
        let mut out = String::from(
            "scene,rung,a_over_cell,cell_mm,cells_per_side,a_over_h,in_table,frames,\
             ms_per_frame,reference_n,simulated_n,rel_error,outcome,reason\n",
        );
        for p in &self.points {
            let m = &p.measurement;
            out.push_str(&format!(
                "{},{},{},{},{},{},{},{},{:.4},{},{},{},{},{}\n",
                p.scene,
                p.rung.name(),
                p.a_over_cell,
                p.cell_mm,
                p.cells_per_side,
                p.a_over_h,
                p.in_table,
                m.frames,
                m.ms_per_frame,
                opt(m.reference_n),
                opt(m.simulated_n),
                opt(m.rel_error),
                m.outcome.name(),
                csv_text(&m.reason)
            ));
        }
        out
    }

    /// `stability.csv`: one row per stability point.
    pub fn stability_csv(&self) -> String {
        let mut out = String::from(
            "sweep,value,friction,rung,cell_mm,reference,reference_n,simulated_n,rel_error,outcome,\
             reason\n",
        );
        for p in &self.stability {
            let m = &p.measurement;
            out.push_str(&format!(
                "{},{},{},{},{},{},{},{},{},{},{}\n",
                p.sweep,
                csv_text(&p.label),
                p.friction,
                p.rung.name(),
                p.cell_mm,
                csv_text(p.reference),
                opt(m.reference_n),
                opt(m.simulated_n),
                opt(m.rel_error),
                m.outcome.name(),
                csv_text(&m.reason)
            ));
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sweep_names_are_the_sweeps_that_run() {
        let mut run: Vec<&str> = stability_sweeps(&StudyOptions::full())
            .iter()
            .map(|p| p.sweep)
            .collect();
        run.dedup();
        assert_eq!(run, SWEEPS);
    }

    fn point(sweep: &'static str, depth_over_h: f64, rel_error: f64) -> StabilityPoint {
        StabilityPoint {
            sweep,
            label: String::new(),
            friction: 1.0,
            depth_over_h,
            a_over_h: 0.5,
            rung: SolverKind::Layered,
            cell_mm: 0.1,
            reference: "fem",
            measurement: Measurement {
                reference_n: Some(1.0),
                simulated_n: Some(1.0 + rel_error),
                rel_error: Some(rel_error),
                ms_per_frame: 1.0,
                frames: 1,
                outcome: Outcome::OverTolerance,
                reason: String::new(),
            },
        }
    }

    /// Each depth row of the table is owned by the one sweep it came from, and a study of the
    /// press-and-slide sweep alone replaces that sweep's rows of a whole table, keeping the rest.
    #[test]
    fn a_sweep_replaces_its_own_rows_of_the_table() {
        let whole = [
            point("depth_over_thickness", 0.1, 0.01),
            point("press_slide", 0.1, 0.04),
            point("sharpness", 0.0, 0.5),
        ];
        let table = solver_table(&[], &whole);
        assert_eq!(table.rows.len(), 2);
        for (row, sweep) in table
            .rows
            .iter()
            .zip(["depth_over_thickness", "press_slide"])
        {
            let owners: Vec<&str> = TABLE_SWEEPS
                .into_iter()
                .filter(|s| sweep_owns_row(s, row))
                .collect();
            assert_eq!(owners, [sweep], "{row:?}");
        }
        let slides = [
            point("press_slide", 0.1, 0.02),
            point("press_slide", 0.2, 0.05),
        ];
        let partial = Study {
            options: StudyOptions {
                sweeps: vec!["press_slide".into()],
                ..StudyOptions::quick()
            },
            points: Vec::new(),
            table: solver_table(&[], &slides),
            stability: slides.to_vec(),
        };
        let updated = update_table(&table, &partial);
        let errors: Vec<(f64, f64, f64)> = updated
            .rows
            .iter()
            .map(|r| (r.depth_over_h, r.slide_over_a, r.rel_error))
            .collect();
        assert_eq!(
            errors,
            [
                (0.1, 0.0, 0.01),
                (0.1, SLIDE_OVER_FOOTPRINT, 0.02),
                (0.2, SLIDE_OVER_FOOTPRINT, 0.05)
            ]
        );
    }
}
