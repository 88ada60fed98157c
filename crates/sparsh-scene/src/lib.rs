//! Scene files for the sparsh tactile simulator: the sensor, the gel, the indenter and its
//! trajectory, the contact solver and what to write — parsed from TOML (unknown keys rejected),
//! checked, and resolved into ready-to-use parts (sensor preset with overrides, ray-castable
//! indenter, frame targets). The format is documented in `scenes/README.md`.
//!
//! Units: millimetres, seconds, degrees, newtons, kilopascals. Frame: see [`grid`].
#![warn(missing_docs)]

pub mod auto;
mod error;
mod family;
mod gap;
pub mod grid;
mod indenter;
mod optics;
mod sensor;
mod trajectory;
pub mod validity;

use std::path::{Path, PathBuf};

use serde::Deserialize;

pub use auto::AutoChoice;
pub use error::SceneError;
pub use family::{DatasetSpec, MotionKind, Range, SequenceScene, Split, sequence_seed};
pub use gap::GapField;
pub use grid::Grid;
pub use indenter::{
    Anchor, Indenter, IndenterSpec, LengthUnit, MeshIndenter, Pattern, ShapeKind, TexturedPlate,
    TriMesh,
};
pub use optics::{OpticsModel, OpticsSpec};
pub use sensor::{Light, MarkerGrid, PRESETS, SensorConfig};
pub use trajectory::{FrameTarget, Keyframe, MAX_FRAMES, Pose, sample};
pub use validity::{RungLimits, Validity, ValidityPolicy};

/// The gel's elastic and frictional properties (`[gel]`).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Gel {
    /// Young's modulus E (kPa).
    #[serde(default = "Gel::default_modulus")]
    pub youngs_modulus_kpa: f64,
    /// Poisson ratio ν, in (−1, 0.5].
    #[serde(default = "Gel::default_poisson")]
    pub poisson_ratio: f64,
    /// Thickness of the elastomer over its rigid window (mm).
    #[serde(default = "Gel::default_thickness")]
    pub thickness_mm: f64,
    /// Coulomb friction coefficient μ between gel and indenter.
    #[serde(default = "Gel::default_friction")]
    pub friction: f64,
}

impl Default for Gel {
    fn default() -> Self {
        Gel {
            youngs_modulus_kpa: Gel::default_modulus(),
            poisson_ratio: Gel::default_poisson(),
            thickness_mm: Gel::default_thickness(),
            friction: Gel::default_friction(),
        }
    }
}

impl Gel {
    fn default_modulus() -> f64 {
        300.0
    }
    fn default_poisson() -> f64 {
        0.48
    }
    fn default_thickness() -> f64 {
        3.0
    }
    fn default_friction() -> f64 {
        1.0
    }

    /// Plane-strain modulus E* = E/(1 − ν²) of the gel against a rigid indenter (kPa).
    pub fn effective_modulus_kpa(&self) -> f64 {
        self.youngs_modulus_kpa / (1.0 - self.poisson_ratio * self.poisson_ratio)
    }

    /// Checks every value; errors name the key under `table` (e.g. `gel`).
    pub(crate) fn validate(&self, path: &Path, table: &str) -> Result<(), SceneError> {
        let bad = |field: &str, msg: String| {
            Err(SceneError::invalid(
                path,
                field.replacen("gel", table, 1),
                msg,
            ))
        };
        if !(self.youngs_modulus_kpa.is_finite() && self.youngs_modulus_kpa > 0.0) {
            return bad(
                "gel.youngs_modulus_kpa",
                format!("must be > 0, got {}", self.youngs_modulus_kpa),
            );
        }
        if !(self.poisson_ratio > -1.0 && self.poisson_ratio <= 0.5) {
            return bad(
                "gel.poisson_ratio",
                format!("must be in (-1, 0.5], got {}", self.poisson_ratio),
            );
        }
        if !(self.thickness_mm.is_finite() && self.thickness_mm > 0.0) {
            return bad(
                "gel.thickness_mm",
                format!("must be > 0, got {}", self.thickness_mm),
            );
        }
        if !(self.friction.is_finite() && self.friction >= 0.0) {
            return bad(
                "gel.friction",
                format!("must be ≥ 0, got {}", self.friction),
            );
        }
        Ok(())
    }
}

/// Contact solver rung (`solver = "..."`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum SolverKind {
    /// Clipped penetration smoothed by a Gaussian pyramid; Winkler pressure; no tangential
    /// tractions.
    #[default]
    Geometric,
    /// Elastic half-space boundary elements: Love's (Boussinesq) and Cerruti influence
    /// coefficients of uniform tractions on the cells, DC-FFT convolution, Polonsky–Keer normal
    /// contact and incremental Coulomb partial slip.
    Halfspace,
    /// As `halfspace`, with the normal compliance of a gel layer of `thickness_mm` bonded to its
    /// rigid window (Carbone & Mangialardi 2008, eq. A.30).
    Layered,
    /// Finite elements: the gel as a nearly incompressible neo-Hookean solid bonded to its
    /// window, at finite strain, with Coulomb friction (the reference for deep presses).
    Fem,
}

impl SolverKind {
    /// Every rung, cheapest first.
    pub const ALL: [SolverKind; 4] = [
        SolverKind::Geometric,
        SolverKind::Halfspace,
        SolverKind::Layered,
        SolverKind::Fem,
    ];

    /// The name used in scene files.
    pub fn name(self) -> &'static str {
        match self {
            SolverKind::Geometric => "geometric",
            SolverKind::Halfspace => "halfspace",
            SolverKind::Layered => "layered",
            SolverKind::Fem => "fem",
        }
    }
}

impl std::str::FromStr for SolverKind {
    type Err = String;

    fn from_str(s: &str) -> Result<SolverKind, String> {
        SolverKind::ALL
            .into_iter()
            .find(|k| k.name() == s)
            .ok_or_else(|| format!("unknown solver `{s}` (geometric, halfspace, layered or fem)"))
    }
}

/// What `solver = "..."` asks for: a rung, or `auto` (the cheapest rung and grid predicted to
/// meet `tolerance`, see [`auto`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
enum SolverRequest {
    #[default]
    Geometric,
    Halfspace,
    Layered,
    Fem,
    Auto,
}

/// A ground-truth field channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FieldName {
    /// Pressure (kPa).
    P,
    /// Shear traction along x (kPa).
    Qx,
    /// Shear traction along y (kPa).
    Qy,
    /// Surface displacement along x (mm).
    Ux,
    /// Surface displacement along y (mm).
    Uy,
    /// Surface displacement along z (mm; negative = pressed towards the camera).
    Uz,
    /// Contact mask (1 in contact).
    Contact,
    /// Slip mask (1 where the contact slips).
    Slip,
}

impl FieldName {
    /// Every field, in the order they are written.
    pub const ALL: [FieldName; 8] = [
        FieldName::P,
        FieldName::Qx,
        FieldName::Qy,
        FieldName::Ux,
        FieldName::Uy,
        FieldName::Uz,
        FieldName::Contact,
        FieldName::Slip,
    ];

    /// Channel name in the EXR file.
    pub fn channel(self) -> &'static str {
        match self {
            FieldName::P => "p",
            FieldName::Qx => "qx",
            FieldName::Qy => "qy",
            FieldName::Ux => "ux",
            FieldName::Uy => "uy",
            FieldName::Uz => "uz",
            FieldName::Contact => "contact",
            FieldName::Slip => "slip",
        }
    }
}

/// Storage precision of field channels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Precision {
    /// 32-bit float.
    #[default]
    F32,
    /// 16-bit float.
    F16,
}

/// What a dataset keeps (`[output]`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputSpec {
    /// Write PNG frames.
    #[serde(default = "yes")]
    pub frames: bool,
    /// Field channels to write; empty writes no EXR files.
    #[serde(default = "all_fields")]
    pub fields: Vec<FieldName>,
    /// Field precision.
    #[serde(default)]
    pub field_precision: Precision,
    /// Friction-cone slip label of the official Sparsh code: slip when ‖F_xy‖ > ratio · F_z.
    #[serde(default = "default_slip_cone_ratio")]
    pub slip_cone_ratio: f64,
}

impl Default for OutputSpec {
    fn default() -> Self {
        OutputSpec {
            frames: true,
            fields: all_fields(),
            field_precision: Precision::F32,
            slip_cone_ratio: default_slip_cone_ratio(),
        }
    }
}

fn default_slip_cone_ratio() -> f64 {
    1.6
}

fn yes() -> bool {
    true
}

fn all_fields() -> Vec<FieldName> {
    FieldName::ALL.to_vec()
}

/// `[sensor]`: a preset and optional overrides.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct SensorSection {
    preset: String,
    width_px: Option<usize>,
    height_px: Option<usize>,
    mm_per_px: Option<f64>,
    fps: Option<f64>,
    lights: Option<Vec<Light>>,
    background: Option<PathBuf>,
    /// `false` removes the preset's printed markers (a plain gel).
    markers: Option<bool>,
}

impl SensorSection {
    /// The preset with the overrides applied and checked; paths are relative to `path`'s folder.
    pub(crate) fn resolve(&self, path: &Path) -> Result<SensorConfig, SceneError> {
        let dir = path.parent().unwrap_or(Path::new("."));
        let mut sensor = SensorConfig::preset(&self.preset).ok_or_else(|| {
            let names: Vec<&str> = PRESETS.iter().map(|(n, _)| *n).collect();
            SceneError::invalid(
                path,
                "sensor.preset",
                format!(
                    "unknown preset `{}` (one of {})",
                    self.preset,
                    names.join(", ")
                ),
            )
        })?;
        sensor.width_px = self.width_px.unwrap_or(sensor.width_px);
        sensor.height_px = self.height_px.unwrap_or(sensor.height_px);
        sensor.mm_per_px = self.mm_per_px.unwrap_or(sensor.mm_per_px);
        sensor.fps = self.fps.unwrap_or(sensor.fps);
        if let Some(lights) = &self.lights {
            sensor.lights = lights.clone();
        }
        sensor.background = self.background.as_ref().map(|b| dir.join(b));
        match (self.markers, sensor.markers.is_some()) {
            (Some(false), _) => sensor.markers = None,
            (Some(true), false) => {
                return Err(SceneError::invalid(
                    path,
                    "sensor.markers",
                    format!("preset `{}` has no markers to keep", self.preset),
                ));
            }
            _ => {}
        }
        sensor.validate(path)?;
        Ok(sensor)
    }
}

/// The scene file as written.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneFile {
    #[serde(default)]
    seed: u64,
    #[serde(default)]
    solver: SolverRequest,
    tolerance: Option<f64>,
    #[serde(default)]
    validity: ValidityPolicy,
    mechanics_stride: Option<usize>,
    #[serde(default)]
    mechanics_margin_mm: f64,
    sensor: SensorSection,
    #[serde(default)]
    gel: Gel,
    indenter: IndenterSpec,
    trajectory: Vec<Keyframe>,
    #[serde(default)]
    optics: OpticsSpec,
    #[serde(default)]
    output: OutputSpec,
}

/// A checked scene, ready to simulate.
#[derive(Debug, Clone)]
pub struct Scene {
    /// The scene file.
    pub path: PathBuf,
    /// Its text, as read (datasets keep a copy).
    pub source: String,
    /// Seed of every random choice.
    pub seed: u64,
    /// Contact solver rung (chosen by the table under `solver = "auto"`).
    pub solver: SolverKind,
    /// Pixels per mechanics cell along each axis (1: the contact is solved at every pixel).
    pub mechanics_stride: usize,
    /// What `solver = "auto"` chose and why; `None` for a named solver.
    pub auto: Option<AutoChoice>,
    /// Relative force tolerance: what `solver = "auto"` chooses for, and where each rung's
    /// validity stops ([`validity`]).
    pub tolerance: f64,
    /// What happens to a frame outside its rung's validity.
    pub validity: ValidityPolicy,
    /// How far the gel, and the contact solve, extends beyond the camera's view on each side
    /// (mm; rounded up to whole mechanics cells).
    pub mechanics_margin_mm: f64,
    /// Sensor with overrides applied.
    pub sensor: SensorConfig,
    /// Gel material.
    pub gel: Gel,
    /// Indenter spec as written.
    pub indenter_spec: IndenterSpec,
    /// Ray-castable indenter.
    pub indenter: Indenter,
    /// Keyframes, sorted by time.
    pub trajectory: Vec<Keyframe>,
    /// Image formation (calibration path resolved).
    pub optics: OpticsSpec,
    /// What to write.
    pub output: OutputSpec,
}

impl Scene {
    /// Reads, parses and checks a scene file; loads its mesh and background paths relative to it.
    pub fn load(path: &Path) -> Result<Scene, SceneError> {
        let source = std::fs::read_to_string(path).map_err(|source| SceneError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Scene::parse(path, source)
    }

    /// Parses and checks scene text; `path` names it in errors and anchors relative paths.
    pub fn parse(path: &Path, source: String) -> Result<Scene, SceneError> {
        let mut file: SceneFile =
            toml::from_str(&source).map_err(|e| SceneError::from_toml(path, &source, e))?;
        let sensor = file.sensor.resolve(path)?;
        file.optics.resolve(path, "optics", sensor.lights.len())?;
        if let Some(stride) = file.mechanics_stride {
            check_stride(path, "mechanics_stride", stride, &sensor)?;
        }
        check_margin(path, "mechanics_margin_mm", file.mechanics_margin_mm)?;
        file.gel.validate(path, "gel")?;
        let trajectory = file.trajectory;
        if trajectory.is_empty() {
            return Err(SceneError::invalid(
                path,
                "trajectory",
                "needs at least one [[trajectory]] keyframe",
            ));
        }
        for (k, key) in trajectory.iter().enumerate() {
            let finite = key
                .position_mm
                .iter()
                .chain(&key.rotation_deg)
                .chain(&[key.time_s])
                .all(|v| v.is_finite());
            if !finite {
                return Err(SceneError::invalid(
                    path,
                    format!("trajectory[{k}]"),
                    "time, position and rotation must be finite",
                ));
            }
            if k > 0 && key.time_s <= trajectory[k - 1].time_s {
                return Err(SceneError::invalid(
                    path,
                    format!("trajectory[{k}].time_s"),
                    format!(
                        "times must increase, got {} after {}",
                        key.time_s,
                        trajectory[k - 1].time_s
                    ),
                ));
            }
            if let Some(f) = key.normal_force_n
                && !(f.is_finite() && f >= 0.0)
            {
                return Err(SceneError::invalid(
                    path,
                    format!("trajectory[{k}].normal_force_n"),
                    format!("must be ≥ 0, got {f}"),
                ));
            }
        }
        let last = trajectory.len() - 1;
        let span_frames = (trajectory[last].time_s - trajectory[0].time_s) * sensor.fps;
        if span_frames.round() > MAX_FRAMES as f64 {
            return Err(SceneError::invalid(
                path,
                format!("trajectory[{last}].time_s"),
                format!(
                    "the trajectory spans {span_frames:.0} frames at {} fps, more than the \
                     {MAX_FRAMES} a scene may render; split it into several scenes",
                    sensor.fps
                ),
            ));
        }
        let indenter = file.indenter.build(path)?;
        let tolerance = check_tolerance(path, "tolerance", file.tolerance)?;
        let fixed = |kind| {
            check_no_escalation(path, "validity", file.validity)?;
            Ok((kind, file.mechanics_stride.unwrap_or(1), None))
        };
        let (solver, mechanics_stride, auto) = match file.solver {
            SolverRequest::Geometric => fixed(SolverKind::Geometric)?,
            SolverRequest::Halfspace => fixed(SolverKind::Halfspace)?,
            SolverRequest::Layered => fixed(SolverKind::Layered)?,
            SolverRequest::Fem => fixed(SolverKind::Fem)?,
            SolverRequest::Auto => {
                if file.mechanics_stride.is_some() {
                    return Err(SceneError::invalid(
                        path,
                        "mechanics_stride",
                        "is chosen by solver = \"auto\"; remove it or name a solver",
                    ));
                }
                let frames = sample(&trajectory, sensor.fps);
                let radius = auto::contact_radius_estimate_mm(
                    &file.indenter,
                    &indenter,
                    &frames,
                    &sensor,
                    &file.gel,
                )
                .map_err(|m| SceneError::invalid(path, "solver", m))?;
                let depth =
                    auto::depth_estimate_mm(&file.indenter, &indenter, &frames, &sensor, radius);
                let sliding = auto::sliding_estimate(&indenter, &frames, &sensor);
                let table = auto::SolverTable::builtin();
                let candidates =
                    auto::candidates(table, &sensor, &file.gel, radius, depth, sliding, tolerance);
                let choice = auto::choose(&candidates).ok_or_else(|| {
                    SceneError::invalid(
                        path,
                        "solver",
                        format!(
                            "auto: no studied rung resolves a contact radius of about \
                             {radius:.3} mm at {} mm per pixel",
                            sensor.mm_per_px
                        ),
                    )
                })?;
                (choice.solver, choice.mechanics_stride, Some(choice))
            }
        };
        Ok(Scene {
            path: path.to_path_buf(),
            source,
            seed: file.seed,
            solver,
            mechanics_stride,
            auto,
            tolerance,
            validity: file.validity,
            mechanics_margin_mm: file.mechanics_margin_mm,
            sensor,
            gel: file.gel,
            indenter_spec: file.indenter,
            indenter,
            trajectory,
            optics: file.optics,
            output: file.output,
        })
    }

    /// The frames this scene renders, at the sensor's frame rate.
    pub fn frames(&self) -> Vec<FrameTarget> {
        sample(&self.trajectory, self.sensor.fps)
    }

    /// The image grid (one cell per sensor pixel).
    pub fn grid(&self) -> Grid {
        self.sensor.grid()
    }

    /// The grid the contact is solved on: `mechanics_stride` pixels per cell along each axis,
    /// centred like the image grid and extending [`Scene::mechanics_margin_cells`] beyond it on
    /// every side.
    pub fn mechanics_grid(&self) -> Grid {
        let s = self.mechanics_stride;
        let m = self.mechanics_margin_cells();
        Grid {
            nx: self.sensor.width_px / s + 2 * m,
            ny: self.sensor.height_px / s + 2 * m,
            cell_mm: self.sensor.mm_per_px * s as f64,
        }
    }

    /// Mechanics cells beyond the camera's view on each side.
    pub fn mechanics_margin_cells(&self) -> usize {
        let cell_mm = self.sensor.mm_per_px * self.mechanics_stride as f64;
        (self.mechanics_margin_mm / cell_mm - 1e-9).ceil().max(0.0) as usize
    }

    /// The part of the mechanics grid the camera sees.
    pub fn view_grid(&self) -> Grid {
        let s = self.mechanics_stride;
        Grid {
            nx: self.sensor.width_px / s,
            ny: self.sensor.height_px / s,
            cell_mm: self.sensor.mm_per_px * s as f64,
        }
    }
}

/// The margin must be finite, ≥ 0 and at most 100 mm.
pub(crate) fn check_margin(path: &Path, field: &str, margin_mm: f64) -> Result<(), SceneError> {
    if !(margin_mm.is_finite() && (0.0..=100.0).contains(&margin_mm)) {
        return Err(SceneError::invalid(
            path,
            field,
            format!("must be in [0, 100] mm, got {margin_mm}"),
        ));
    }
    Ok(())
}

/// The relative force tolerance a scene gives, or [`auto::DEFAULT_TOLERANCE`]: in (0, 1).
pub(crate) fn check_tolerance(
    path: &Path,
    field: &str,
    tolerance: Option<f64>,
) -> Result<f64, SceneError> {
    let tolerance = tolerance.unwrap_or(auto::DEFAULT_TOLERANCE);
    if tolerance > 0.0 && tolerance < 1.0 {
        Ok(tolerance)
    } else {
        Err(SceneError::invalid(
            path,
            field,
            format!("must be a relative force error in (0, 1), got {tolerance}"),
        ))
    }
}

/// `validity = "escalate"` needs `solver = "auto"`: it climbs the ladder from the rung chosen.
pub(crate) fn check_no_escalation(
    path: &Path,
    field: &str,
    policy: ValidityPolicy,
) -> Result<(), SceneError> {
    if policy == ValidityPolicy::Escalate {
        return Err(SceneError::invalid(
            path,
            field,
            "\"escalate\" climbs the solver ladder from the rung solver = \"auto\" chose; with a \
             named solver use \"warn\" or \"error\"",
        ));
    }
    Ok(())
}

pub(crate) fn one_cell() -> usize {
    1
}

/// The stride must be at least 1 and divide the image size.
pub(crate) fn check_stride(
    path: &Path,
    field: &str,
    stride: usize,
    sensor: &SensorConfig,
) -> Result<(), SceneError> {
    if stride == 0
        || !sensor.width_px.is_multiple_of(stride)
        || !sensor.height_px.is_multiple_of(stride)
    {
        return Err(SceneError::invalid(
            path,
            field,
            format!(
                "must be ≥ 1 and divide the image size {}×{}, got {stride}",
                sensor.width_px, sensor.height_px
            ),
        ));
    }
    Ok(())
}
