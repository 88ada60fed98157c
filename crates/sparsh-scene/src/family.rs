//! Dataset files: families of sequences with randomised indenters, motions, gels and sensor
//! instances. Every sequence is drawn from its own seed, derived from the file's seed and the
//! sequence's index alone, so any split of the work (threads, shards, resumed runs) yields the
//! same sequences.
//!
//! A plain scene file (one `[indenter]`, one `[[trajectory]]`) is a dataset of one sequence.

use std::path::{Path, PathBuf};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Deserialize;

use crate::{
    Anchor, Gel, IndenterSpec, Keyframe, LengthUnit, OpticsSpec, OutputSpec, Pattern, Scene,
    SceneError, SensorSection, ShapeKind, SolverKind, ValidityPolicy, check_margin,
    check_no_escalation, check_stride, check_tolerance, one_cell,
};

/// A number, or a `[min, max]` range drawn uniformly per sequence.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(untagged)]
pub enum Range {
    /// Always this value.
    Fixed(f64),
    /// Uniform in `[min, max]`.
    Uniform([f64; 2]),
}

impl Range {
    fn bounds(self) -> (f64, f64) {
        match self {
            Range::Fixed(v) => (v, v),
            Range::Uniform([lo, hi]) => (lo, hi),
        }
    }

    fn sample(self, rng: &mut ChaCha8Rng) -> f64 {
        let (lo, hi) = self.bounds();
        if lo == hi {
            lo
        } else {
            lo + (hi - lo) * rng.random::<f64>()
        }
    }

    fn check(self, path: &Path, field: &str) -> Result<(), SceneError> {
        let (lo, hi) = self.bounds();
        if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
            return Err(SceneError::invalid(
                path,
                field,
                format!("range must be finite with min ≤ max, got [{lo}, {hi}]"),
            ));
        }
        Ok(())
    }
}

/// `[family.gel]`: each property fixed or a range.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct GelRanges {
    youngs_modulus_kpa: Option<Range>,
    poisson_ratio: Option<Range>,
    thickness_mm: Option<Range>,
    friction: Option<Range>,
}

/// `[family.randomize]`: sensor-instance randomisation.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct Randomize {
    /// Multiplier of every light's intensity, drawn per light and sequence.
    led_intensity: Option<Range>,
    /// Largest change of a light's colour channels (added, then clamped to [0, 1]).
    led_color_jitter: Option<f64>,
    /// Exposure gain, drawn per sequence (sets `optics.exposure`).
    exposure: Option<Range>,
    /// Amplitude of the background's smooth variation, drawn per sequence.
    background_variation: Option<Range>,
    /// Camera noise standard deviation (0–255), drawn per sequence.
    noise_std: Option<Range>,
}

/// `[[family.indenters]]`: one indenter kind with parameter ranges.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct IndenterRanges {
    shape: ShapeKind,
    radius_mm: Option<Range>,
    height_mm: Option<Range>,
    half_angle_deg: Option<Range>,
    size_mm: Option<[Range; 3]>,
    pattern: Option<Pattern>,
    pitch_mm: Option<Range>,
    depth_mm: Option<Range>,
    crown_radius_mm: Option<Range>,
    mesh: Option<PathBuf>,
    scale: Option<Range>,
    units: Option<LengthUnit>,
    anchor: Option<Anchor>,
    /// `train` (default) or `test`: sequences with this indenter belong to that split.
    #[serde(default)]
    split: Split,
}

/// Dataset split of a sequence.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Split {
    /// Training data.
    #[default]
    Train,
    /// Held out for testing.
    Test,
}

impl Split {
    /// Lower-case name used in labels.
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Test => "test",
        }
    }
}

/// Kinds of motion a family draws its trajectories from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MotionKind {
    /// Approach, press to depth (or load) over the first half, hold.
    Press,
    /// Press over the first third, then slide `slide_mm` along `direction_deg`.
    PressSlide,
    /// Press over the first third, then turn `twist_deg` about the sensor normal.
    Twist,
    /// Press over the first third, then rock `roll_deg` about the horizontal axis across
    /// `direction_deg` (through the tip) while moving `slide_mm` along it.
    Roll,
    /// Press over the first quarter, then `steps` random moves of up to `slide_mm` and up to
    /// ±`twist_deg`.
    RandomWalk,
}

/// `[family.motion]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct MotionSpec {
    kind: MotionKind,
    /// Indentation depth of the tip (mm); default [0.3, 1.0]. Ignored under `normal_force_n`.
    depth_mm: Option<Range>,
    /// Pressing load (N); when set, every frame is load-controlled.
    normal_force_n: Option<Range>,
    /// Slide length (mm); default [0.5, 2.0].
    slide_mm: Option<Range>,
    /// Slide direction in the gel plane (deg from +x); default [0, 360].
    direction_deg: Option<Range>,
    /// Twist about the sensor normal (deg); default [-30, 30].
    twist_deg: Option<Range>,
    /// Roll angle (deg); default [-15, 15].
    roll_deg: Option<Range>,
    /// Moves of a random walk; default 4.
    steps: Option<usize>,
    /// Start of the tip in x and y (mm); default 0.
    start_x_mm: Option<Range>,
    start_y_mm: Option<Range>,
    /// Initial turn of the indenter about the sensor normal (deg); default 0.
    yaw_deg: Option<Range>,
}

/// `[[family]]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct FamilyFile {
    name: String,
    sequences: usize,
    frames_per_sequence: usize,
    #[serde(default)]
    solver: SolverKind,
    tolerance: Option<f64>,
    #[serde(default)]
    validity: ValidityPolicy,
    #[serde(default = "one_cell")]
    mechanics_stride: usize,
    #[serde(default)]
    mechanics_margin_mm: f64,
    sensor: SensorSection,
    #[serde(default)]
    gel: GelRanges,
    #[serde(default)]
    randomize: Randomize,
    #[serde(default)]
    optics: OpticsSpec,
    indenters: Vec<IndenterRanges>,
    motion: MotionSpec,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct DatasetFile {
    #[serde(default)]
    seed: u64,
    #[serde(default)]
    output: OutputSpec,
    family: Vec<FamilyFile>,
}

/// One sequence of a dataset, ready to simulate.
#[derive(Debug, Clone)]
pub struct SequenceScene {
    /// Index of the sequence in the dataset.
    pub sequence: usize,
    /// Family it was drawn from.
    pub family: String,
    /// Split of its indenter.
    pub split: Split,
    /// Dataset index of its first frame.
    pub first_frame: usize,
    /// The concrete scene (its `seed` is the sequence's own).
    pub scene: Scene,
}

/// A dataset description: a family file, or a single scene.
#[derive(Debug, Clone)]
pub struct DatasetSpec {
    /// The file.
    pub path: PathBuf,
    /// Its text.
    pub source: String,
    /// Dataset seed.
    pub seed: u64,
    /// What to write.
    pub output: OutputSpec,
    kind: SpecKind,
}

#[derive(Debug, Clone)]
enum SpecKind {
    Single(Box<Scene>),
    Families(Vec<FamilyFile>),
}

impl DatasetSpec {
    /// Reads a dataset file (with `[[family]]` tables) or a single scene file.
    pub fn load(path: &Path) -> Result<DatasetSpec, SceneError> {
        let source = std::fs::read_to_string(path).map_err(|source| SceneError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let is_family = source
            .parse::<toml::Table>()
            .map(|t| t.contains_key("family"))
            .unwrap_or(false);
        if !is_family {
            let scene = Scene::parse(path, source.clone())?;
            return Ok(DatasetSpec {
                path: path.to_path_buf(),
                seed: scene.seed,
                output: scene.output.clone(),
                source,
                kind: SpecKind::Single(Box::new(scene)),
            });
        }
        let file: DatasetFile =
            toml::from_str(&source).map_err(|e| SceneError::from_toml(path, &source, e))?;
        for (k, family) in file.family.iter().enumerate() {
            family.check(path, &format!("family[{k}]"))?;
        }
        let spec = DatasetSpec {
            path: path.to_path_buf(),
            seed: file.seed,
            output: file.output,
            source,
            kind: SpecKind::Families(file.family),
        };
        // Draw the first sequence of each family now, so a bad mesh or sensor fails at load.
        let mut first = 0;
        if let SpecKind::Families(families) = &spec.kind {
            for family in families {
                spec.sequence(first)?;
                first += family.sequences;
            }
        }
        Ok(spec)
    }

    /// Number of sequences.
    pub fn sequence_count(&self) -> usize {
        match &self.kind {
            SpecKind::Single(_) => 1,
            SpecKind::Families(f) => f.iter().map(|f| f.sequences).sum(),
        }
    }

    /// The solver rungs its sequences use.
    pub fn solvers(&self) -> Vec<SolverKind> {
        match &self.kind {
            SpecKind::Single(scene) => vec![scene.solver],
            SpecKind::Families(f) => f.iter().map(|f| f.solver).collect(),
        }
    }

    /// Number of frames of every sequence together.
    pub fn frame_count(&self) -> usize {
        match &self.kind {
            SpecKind::Single(scene) => scene.frames().len(),
            SpecKind::Families(f) => f.iter().map(|f| f.sequences * f.frames_per_sequence).sum(),
        }
    }

    /// Sequence `index`, drawn from the seed of that index.
    pub fn sequence(&self, index: usize) -> Result<SequenceScene, SceneError> {
        let families = match &self.kind {
            SpecKind::Single(scene) => {
                return Ok(SequenceScene {
                    sequence: 0,
                    family: "scene".into(),
                    split: Split::Train,
                    first_frame: 0,
                    scene: (**scene).clone(),
                });
            }
            SpecKind::Families(f) => f,
        };
        let (mut first_sequence, mut first_frame) = (0, 0);
        for (k, family) in families.iter().enumerate() {
            if index < first_sequence + family.sequences {
                let seed = sequence_seed(self.seed, index);
                let within = index - first_sequence;
                let (scene, split) = family.draw(self, &format!("family[{k}]"), seed)?;
                return Ok(SequenceScene {
                    sequence: index,
                    family: family.name.clone(),
                    split,
                    first_frame: first_frame + within * family.frames_per_sequence,
                    scene,
                });
            }
            first_sequence += family.sequences;
            first_frame += family.sequences * family.frames_per_sequence;
        }
        panic!(
            "sequence {index} out of range ({} sequences)",
            self.sequence_count()
        )
    }
}

/// SplitMix64 of the dataset seed and the sequence index: a seed per sequence that does not
/// depend on which other sequences are generated.
pub fn sequence_seed(dataset_seed: u64, sequence: usize) -> u64 {
    let mut z = dataset_seed ^ (sequence as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

impl FamilyFile {
    fn check(&self, path: &Path, at: &str) -> Result<(), SceneError> {
        check_tolerance(path, &format!("{at}.tolerance"), self.tolerance)?;
        check_no_escalation(path, &format!("{at}.validity"), self.validity)?;
        if self.sequences == 0 || self.frames_per_sequence == 0 {
            return Err(SceneError::invalid(
                path,
                format!("{at}.sequences"),
                "sequences and frames_per_sequence must be at least 1",
            ));
        }
        if self.indenters.is_empty() {
            return Err(SceneError::invalid(
                path,
                format!("{at}.indenters"),
                "needs at least one [[family.indenters]] entry",
            ));
        }
        let g = &self.gel;
        for (name, range) in [
            ("youngs_modulus_kpa", g.youngs_modulus_kpa),
            ("poisson_ratio", g.poisson_ratio),
            ("thickness_mm", g.thickness_mm),
            ("friction", g.friction),
        ] {
            if let Some(r) = range {
                r.check(path, &format!("{at}.gel.{name}"))?;
            }
        }
        // Both ends of every range must make a valid gel.
        for pick in [0, 1] {
            let end = |r: Option<Range>, default: f64| {
                r.map_or(default, |r| [r.bounds().0, r.bounds().1][pick])
            };
            let d = Gel::default();
            Gel {
                youngs_modulus_kpa: end(g.youngs_modulus_kpa, d.youngs_modulus_kpa),
                poisson_ratio: end(g.poisson_ratio, d.poisson_ratio),
                thickness_mm: end(g.thickness_mm, d.thickness_mm),
                friction: end(g.friction, d.friction),
            }
            .validate(path, &format!("{at}.gel"))?;
        }
        // Both ends of every indenter range must make a valid indenter (meshes load here).
        for (k, entry) in self.indenters.iter().enumerate() {
            for pick in [0, 1] {
                let end = |r: Option<Range>| r.map(|r| [r.bounds().0, r.bounds().1][pick]);
                IndenterSpec {
                    shape: entry.shape,
                    radius_mm: end(entry.radius_mm),
                    height_mm: end(entry.height_mm),
                    half_angle_deg: end(entry.half_angle_deg),
                    size_mm: entry
                        .size_mm
                        .map(|s| s.map(|r| [r.bounds().0, r.bounds().1][pick])),
                    pattern: entry.pattern,
                    pitch_mm: end(entry.pitch_mm),
                    depth_mm: end(entry.depth_mm),
                    crown_radius_mm: end(entry.crown_radius_mm),
                    mesh: entry.mesh.clone(),
                    scale: end(entry.scale),
                    units: entry.units,
                    anchor: entry.anchor,
                }
                .build(path)
                .map_err(|e| rename_indenter_field(e, &format!("{at}.indenters[{k}]")))?;
            }
        }
        let m = &self.motion;
        for (name, range) in [
            ("depth_mm", m.depth_mm),
            ("normal_force_n", m.normal_force_n),
            ("slide_mm", m.slide_mm),
            ("direction_deg", m.direction_deg),
            ("twist_deg", m.twist_deg),
            ("roll_deg", m.roll_deg),
            ("start_x_mm", m.start_x_mm),
            ("start_y_mm", m.start_y_mm),
            ("yaw_deg", m.yaw_deg),
        ] {
            if let Some(r) = range {
                r.check(path, &format!("{at}.motion.{name}"))?;
            }
        }
        if let Some(r) = self.randomize.led_intensity {
            r.check(path, &format!("{at}.randomize.led_intensity"))?;
            if r.bounds().0 < 0.0 {
                return Err(SceneError::invalid(
                    path,
                    format!("{at}.randomize.led_intensity"),
                    "must be ≥ 0",
                ));
            }
        }
        Ok(())
    }

    /// Draws one concrete scene from the family.
    fn draw(&self, spec: &DatasetSpec, at: &str, seed: u64) -> Result<(Scene, Split), SceneError> {
        let path = &spec.path;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut sensor = self.sensor.resolve(path)?;
        check_stride(
            path,
            &format!("{at}.mechanics_stride"),
            self.mechanics_stride,
            &sensor,
        )?;
        check_margin(
            path,
            &format!("{at}.mechanics_margin_mm"),
            self.mechanics_margin_mm,
        )?;
        if let Some(r) = self.randomize.led_intensity {
            for light in &mut sensor.lights {
                light.intensity *= r.sample(&mut rng);
            }
        }
        if let Some(jitter) = self.randomize.led_color_jitter {
            for light in &mut sensor.lights {
                for c in &mut light.color {
                    *c = (*c + jitter * (2.0 * rng.random::<f64>() - 1.0)).clamp(0.0, 1.0);
                }
            }
        }
        let mut optics = self.optics.clone();
        let r = &self.randomize;
        for (range, value) in [
            (r.exposure, &mut optics.exposure),
            (r.background_variation, &mut optics.background_variation),
            (r.noise_std, &mut optics.noise_std),
        ] {
            if let Some(range) = range {
                *value = range.sample(&mut rng);
            }
        }
        optics.resolve(path, &format!("{at}.optics"), sensor.lights.len())?;
        let d = Gel::default();
        let g = &self.gel;
        let gel = Gel {
            youngs_modulus_kpa: g
                .youngs_modulus_kpa
                .map_or(d.youngs_modulus_kpa, |r| r.sample(&mut rng)),
            poisson_ratio: g
                .poisson_ratio
                .map_or(d.poisson_ratio, |r| r.sample(&mut rng)),
            thickness_mm: g
                .thickness_mm
                .map_or(d.thickness_mm, |r| r.sample(&mut rng)),
            friction: g.friction.map_or(d.friction, |r| r.sample(&mut rng)),
        };
        let choice = &self.indenters[rng.random_range(0..self.indenters.len())];
        let mut draw = |r: Option<Range>| r.map(|r| r.sample(&mut rng));
        let indenter_spec = IndenterSpec {
            shape: choice.shape,
            radius_mm: draw(choice.radius_mm),
            height_mm: draw(choice.height_mm),
            half_angle_deg: draw(choice.half_angle_deg),
            size_mm: choice.size_mm.map(|s| s.map(|r| r.sample(&mut rng))),
            pattern: choice.pattern,
            pitch_mm: None,
            depth_mm: None,
            crown_radius_mm: None,
            mesh: choice.mesh.clone(),
            scale: choice.scale.map(|r| r.sample(&mut rng)),
            units: choice.units,
            anchor: choice.anchor,
        };
        // Drawn after the other keys, so the draws of files without them stay as they were.
        let indenter_spec = IndenterSpec {
            pitch_mm: choice.pitch_mm.map(|r| r.sample(&mut rng)),
            depth_mm: choice.depth_mm.map(|r| r.sample(&mut rng)),
            crown_radius_mm: choice.crown_radius_mm.map(|r| r.sample(&mut rng)),
            ..indenter_spec
        };
        let indenter = indenter_spec
            .build(path)
            .map_err(|e| rename_indenter_field(e, &format!("{at}.indenters")))?;
        let duration_s = self.frames_per_sequence as f64 / sensor.fps;
        let trajectory = self.motion.keyframes(duration_s, &mut rng);
        let scene = Scene {
            path: path.clone(),
            source: spec.source.clone(),
            seed,
            solver: self.solver,
            mechanics_stride: self.mechanics_stride,
            auto: None,
            tolerance: check_tolerance(path, &format!("{at}.tolerance"), self.tolerance)?,
            validity: self.validity,
            mechanics_margin_mm: self.mechanics_margin_mm,
            sensor,
            gel,
            indenter_spec,
            indenter,
            trajectory,
            optics,
            output: spec.output.clone(),
        };
        Ok((scene, choice.split))
    }
}

/// Names a family's indenter entry instead of `indenter` in an error.
fn rename_indenter_field(err: SceneError, table: &str) -> SceneError {
    match err {
        SceneError::Invalid {
            path,
            field,
            message,
        } => SceneError::Invalid {
            path,
            field: field.replacen("indenter", table, 1),
            message,
        },
        other => other,
    }
}

impl MotionSpec {
    /// Keyframes over `[0, duration_s]`; the tip starts 0.3 mm above the gel.
    fn keyframes(&self, duration_s: f64, rng: &mut ChaCha8Rng) -> Vec<Keyframe> {
        let pick = |r: Option<Range>, default: Range, rng: &mut ChaCha8Rng| {
            r.unwrap_or(default).sample(rng)
        };
        let depth = pick(self.depth_mm, Range::Uniform([0.3, 1.0]), rng);
        let force = self.normal_force_n.map(|r| r.sample(rng));
        let slide = pick(self.slide_mm, Range::Uniform([0.5, 2.0]), rng);
        let direction = pick(self.direction_deg, Range::Uniform([0.0, 360.0]), rng).to_radians();
        let twist = pick(self.twist_deg, Range::Uniform([-30.0, 30.0]), rng);
        let roll = pick(self.roll_deg, Range::Uniform([-15.0, 15.0]), rng);
        let x0 = pick(self.start_x_mm, Range::Fixed(0.0), rng);
        let y0 = pick(self.start_y_mm, Range::Fixed(0.0), rng);
        let yaw = pick(self.yaw_deg, Range::Fixed(0.0), rng);
        let pressed_z = if force.is_some() { 0.0 } else { -depth };
        let key = |t: f64, x: f64, y: f64, z: f64, rot: [f64; 3], f: Option<f64>| Keyframe {
            time_s: t * duration_s,
            position_mm: [x, y, z],
            rotation_deg: rot,
            normal_force_n: f,
        };
        let start = key(0.0, x0, y0, 0.3, [0.0, 0.0, yaw], force.map(|_| 0.0));
        let (dx, dy) = (direction.cos(), direction.sin());
        let mut keys = vec![start];
        match self.kind {
            MotionKind::Press => {
                keys.push(key(0.5, x0, y0, pressed_z, [0.0, 0.0, yaw], force));
                keys.push(key(1.0, x0, y0, pressed_z, [0.0, 0.0, yaw], force));
            }
            MotionKind::PressSlide | MotionKind::Twist | MotionKind::Roll => {
                keys.push(key(1.0 / 3.0, x0, y0, pressed_z, [0.0, 0.0, yaw], force));
                let (end_xy, rot) = match self.kind {
                    MotionKind::PressSlide => ((x0 + slide * dx, y0 + slide * dy), [0.0, 0.0, yaw]),
                    MotionKind::Twist => ((x0, y0), [0.0, 0.0, yaw + twist]),
                    // Rocking about the horizontal axis across the direction of travel.
                    _ => (
                        (x0 + slide * dx, y0 + slide * dy),
                        [-roll * dy, roll * dx, yaw],
                    ),
                };
                keys.push(key(1.0, end_xy.0, end_xy.1, pressed_z, rot, force));
            }
            MotionKind::RandomWalk => {
                keys.push(key(0.25, x0, y0, pressed_z, [0.0, 0.0, yaw], force));
                let steps = self.steps.unwrap_or(4).max(1);
                let (mut x, mut y, mut turn) = (x0, y0, yaw);
                let twist_range = self.twist_deg.unwrap_or(Range::Uniform([-30.0, 30.0]));
                let max_step = self
                    .slide_mm
                    .unwrap_or(Range::Uniform([0.5, 2.0]))
                    .bounds()
                    .1;
                for s in 1..=steps {
                    let heading = rng.random::<f64>() * std::f64::consts::TAU;
                    let length = max_step * rng.random::<f64>();
                    x += length * heading.cos();
                    y += length * heading.sin();
                    turn += twist_range.sample(rng) / steps as f64;
                    let t = 0.25 + 0.75 * s as f64 / steps as f64;
                    keys.push(key(t, x, y, pressed_z, [0.0, 0.0, turn], force));
                }
            }
        }
        keys
    }
}
