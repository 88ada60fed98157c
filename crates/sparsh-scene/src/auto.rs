//! `solver = "auto"`: the cheapest rung and mechanics grid predicted to meet a relative force
//! tolerance, from the table of measured errors and costs that `sparsh study` writes
//! (`assets/solver_table.csv`, compiled in).
//!
//! A prediction needs two numbers of the scene: the contact radius a in cells of the candidate
//! grid, and a over the gel thickness h. The table holds, per rung, the worst relative force error
//! the study measured at each (a/cell, a/h) it ran; a query takes the nearest studied point on the
//! safe side (the next coarser a/cell, the next thinner layer), so the prediction is the error of
//! a harder case. Queries outside the studied range have no prediction and are not candidates.

use std::sync::OnceLock;

use crate::{
    FrameTarget, GapField, Gel, Grid, Indenter, IndenterSpec, SensorConfig, ShapeKind, SolverKind,
};

/// The table the study wrote, compiled into the crate.
pub const SOLVER_TABLE_CSV: &str = include_str!("../../../assets/solver_table.csv");

/// Tolerance of `solver = "auto"` when the scene gives none.
pub const DEFAULT_TOLERANCE: f64 = 0.02;

/// One studied point: a rung on a grid of `a_over_cell` cells per contact radius, on a gel with
/// contact radius over thickness `a_over_h`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TableRow {
    /// The rung.
    pub rung: SolverKind,
    /// Contact radius in cells.
    pub a_over_cell: f64,
    /// Contact radius over gel thickness.
    pub a_over_h: f64,
    /// Indentation depth over gel thickness: 0 for the accuracy study's shallow presses, the
    /// swept depth for the rows of the depth sweep (against finite-strain finite elements).
    pub depth_over_h: f64,
    /// Friction coefficient of the depth sweep's row (0 on the accuracy study's rows, which
    /// are read whatever the scene's friction).
    pub friction: f64,
    /// Slide over the contact's rigid footprint radius before the row's force was graded: 0 for
    /// a press (graded on the normal force), > 0 for the press-and-slide sweep (graded on the
    /// tangential force after the slide), whose rows bound only frames loaded tangentially.
    pub slide_over_a: f64,
    /// Worst |relative force error| measured there (∞ where a case failed).
    pub rel_error: f64,
    /// Worst time per frame measured there (ms).
    pub ms_per_frame: f64,
}

/// The table of studied points.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SolverTable {
    /// Rows, in any order.
    pub rows: Vec<TableRow>,
}

const HEADER: &str =
    "rung,a_over_cell,a_over_h,depth_over_h,friction,slide_over_a,rel_error,ms_per_frame";

impl SolverTable {
    /// The compiled-in table.
    pub fn builtin() -> &'static SolverTable {
        static TABLE: OnceLock<SolverTable> = OnceLock::new();
        TABLE.get_or_init(|| {
            SolverTable::parse(SOLVER_TABLE_CSV)
                .unwrap_or_else(|e| panic!("assets/solver_table.csv is corrupt: {e}"))
        })
    }

    /// Parses the CSV text written by [`SolverTable::to_csv`] (`#` lines, which earlier versions
    /// wrote before the header, are skipped).
    pub fn parse(text: &str) -> Result<SolverTable, String> {
        let mut lines = text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty() && !l.starts_with('#'));
        match lines.next() {
            Some((_, h)) if h.trim() == HEADER => {}
            _ => return Err(format!("first row must be `{HEADER}`")),
        }
        let rows = lines
            .map(|(n, line)| {
                let f: Vec<&str> = line.split(',').map(str::trim).collect();
                let bad = |what: &str| format!("line {}: {what}", n + 1);
                if f.len() != 8 {
                    return Err(bad("needs 8 fields"));
                }
                let num = |s: &str| {
                    s.parse::<f64>()
                        .map_err(|_| bad(&format!("`{s}` is not a number")))
                };
                let row = TableRow {
                    rung: f[0].parse().map_err(|e: String| bad(&e))?,
                    a_over_cell: num(f[1])?,
                    a_over_h: num(f[2])?,
                    depth_over_h: num(f[3])?,
                    friction: num(f[4])?,
                    slide_over_a: num(f[5])?,
                    rel_error: num(f[6])?,
                    ms_per_frame: num(f[7])?,
                };
                if !(row.a_over_cell > 0.0
                    && row.a_over_h >= 0.0
                    && row.depth_over_h >= 0.0
                    && row.friction >= 0.0
                    && row.slide_over_a >= 0.0
                    && row.rel_error >= 0.0)
                {
                    return Err(bad(
                        "a_over_cell must be > 0, a_over_h, depth_over_h, friction, slide_over_a \
                         and rel_error ≥ 0",
                    ));
                }
                if row.slide_over_a > 0.0 && row.depth_over_h == 0.0 {
                    return Err(bad("a row with slide_over_a > 0 needs depth_over_h > 0"));
                }
                Ok(row)
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(SolverTable { rows })
    }

    /// What the table holds, for the provenance sidecar the study writes beside it.
    pub const DESCRIPTION: &'static str = "worst |relative force error| and worst ms per frame of \
        each rung at each studied contact radius in cells (a_over_cell) and contact radius over gel \
        thickness (a_over_h) with depth_over_h = 0, and along the depth sweep (depth_over_h > 0, \
        at each swept friction coefficient, against finite-strain finite elements: the normal \
        force of a press with slide_over_a = 0, the tangential force after a slide of \
        slide_over_a footprint radii otherwise); read by solver = \"auto\" and the validity limits";

    /// CSV text (RFC 4180: the header row first, nothing before it), one row per studied point.
    pub fn to_csv(&self) -> String {
        let mut out = String::from(HEADER);
        out.push('\n');
        for r in &self.rows {
            out.push_str(&format!(
                "{},{},{},{},{},{},{:e},{:e}\n",
                r.rung.name(),
                r.a_over_cell,
                r.a_over_h,
                r.depth_over_h,
                r.friction,
                r.slide_over_a,
                r.rel_error,
                r.ms_per_frame
            ));
        }
        out
    }

    /// The studied point that bounds (`rung`, `a_over_cell`, `a_over_h`) from the hard side: the
    /// largest studied a/cell not above the query, then the smallest studied a/h not below it.
    pub fn predict(&self, rung: SolverKind, a_over_cell: f64, a_over_h: f64) -> Option<TableRow> {
        let rows = self
            .rows
            .iter()
            .filter(|r| r.rung == rung && r.depth_over_h == 0.0);
        let cell = rows
            .clone()
            .map(|r| r.a_over_cell)
            .filter(|&c| c <= a_over_cell * (1.0 + 1e-9))
            .reduce(f64::max)?;
        rows.filter(|r| r.a_over_cell == cell && r.a_over_h >= a_over_h * (1.0 - 1e-9))
            .min_by(|a, b| a.a_over_h.total_cmp(&b.a_over_h))
            .copied()
    }
}

impl SolverTable {
    /// The error of `rung` at indentation depth over gel thickness `depth_over_h` with friction
    /// coefficient `friction`, from the depth sweep on the hard side in both: the worst error of
    /// the swept depths up to the shallowest one at or past the query, over the swept frictions
    /// up to the smallest one at or above the scene's (so a rung that once missed does not come
    /// back deeper or with more friction; ∞ past the deepest swept depth). Past the largest swept
    /// friction, every swept friction counts: a normal press sticks wholly there, and more
    /// friction changes nothing. Presses no deeper than the shallowest swept depth are the
    /// small-strain regime the rest of the table covers (the sweep is a sphere on a thin layer,
    /// so its shallow rows also hold the layer's effect, which a/h already bounds): 0 there, and
    /// when the table has no depth rows for the rung. A press is bounded by the presses' rows
    /// alone; a contact `sliding` (loaded tangentially) by those and, read the same way over
    /// both, the press-and-slide rows (`slide_over_a > 0`).
    pub fn depth_error(
        &self,
        rung: SolverKind,
        depth_over_h: f64,
        friction: f64,
        sliding: bool,
    ) -> f64 {
        let press = self.swept_error(rung, depth_over_h, friction, false);
        if sliding {
            press.max(self.swept_error(rung, depth_over_h, friction, true))
        } else {
            press
        }
    }

    /// [`SolverTable::depth_error`] over the presses' rows, and the slides' too if `slides`.
    fn swept_error(&self, rung: SolverKind, depth_over_h: f64, friction: f64, slides: bool) -> f64 {
        let rows: Vec<&TableRow> = self
            .rows
            .iter()
            .filter(|r| r.rung == rung && r.depth_over_h > 0.0 && (slides || r.slide_over_a == 0.0))
            .collect();
        let shallowest = rows.iter().map(|r| r.depth_over_h).reduce(f64::min);
        if shallowest.is_none_or(|d| depth_over_h <= d) {
            return 0.0;
        }
        let Some(bound) = rows
            .iter()
            .map(|r| r.depth_over_h)
            .filter(|&d| d >= depth_over_h * (1.0 - 1e-9))
            .reduce(f64::min)
        else {
            return f64::INFINITY;
        };
        let friction_bound = rows
            .iter()
            .map(|r| r.friction)
            .filter(|&m| m >= friction * (1.0 - 1e-9))
            .reduce(f64::min)
            .unwrap_or(f64::INFINITY);
        rows.iter()
            .filter(|r| r.depth_over_h <= bound && r.friction <= friction_bound)
            .fold(0.0, |worst, r| worst.max(r.rel_error))
    }

    /// The friction coefficients of the depth sweep, ascending.
    pub fn swept_frictions(&self) -> Vec<f64> {
        let mut out: Vec<f64> = self
            .rows
            .iter()
            .filter(|r| r.depth_over_h > 0.0)
            .map(|r| r.friction)
            .collect();
        out.sort_by(f64::total_cmp);
        out.dedup();
        out
    }
}

/// What `solver = "auto"` chose, and why.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AutoChoice {
    /// The rung.
    pub solver: SolverKind,
    /// Pixels per mechanics cell.
    pub mechanics_stride: usize,
    /// Requested relative force tolerance.
    pub tolerance: f64,
    /// Estimated contact radius (mm).
    pub contact_radius_mm: f64,
    /// Estimated contact radius over gel thickness.
    pub a_over_h: f64,
    /// Estimated deepest indentation over gel thickness.
    pub depth_over_h: f64,
    /// Whether the indenter moves along the gel while pressed into it (the depth sweep's
    /// press-and-slide rows bound the error then).
    pub sliding: bool,
    /// Predicted |relative force error| (the worse of the table's bounding point and the depth
    /// sweep at the scene's depth).
    pub predicted_rel_error: f64,
    /// The table's time per frame at that point (ms).
    pub predicted_ms_per_frame: f64,
}

impl AutoChoice {
    /// The prediction meets the tolerance (false when no candidate did and the most accurate
    /// one was taken instead).
    pub fn meets_tolerance(&self) -> bool {
        self.predicted_rel_error <= self.tolerance
    }
}

/// Every (rung, stride) the table can predict for a contact of `contact_radius_mm` pressed
/// `depth_mm` deep (`sliding` along the gel or not) on `sensor`'s image and `gel`: strides divide
/// the image size.
pub fn candidates(
    table: &SolverTable,
    sensor: &SensorConfig,
    gel: &Gel,
    contact_radius_mm: f64,
    depth_mm: f64,
    sliding: bool,
    tolerance: f64,
) -> Vec<AutoChoice> {
    let a_over_h = contact_radius_mm / gel.thickness_mm;
    let depth_over_h = depth_mm / gel.thickness_mm;
    let mut out = Vec::new();
    for solver in SolverKind::ALL {
        let depth_error = table.depth_error(solver, depth_over_h, gel.friction, sliding);
        for stride in 1..=sensor.width_px.min(sensor.height_px) {
            if !(sensor.width_px.is_multiple_of(stride) && sensor.height_px.is_multiple_of(stride))
            {
                continue;
            }
            let a_over_cell = contact_radius_mm / (sensor.mm_per_px * stride as f64);
            if let Some(row) = table.predict(solver, a_over_cell, a_over_h) {
                out.push(AutoChoice {
                    solver,
                    mechanics_stride: stride,
                    tolerance,
                    contact_radius_mm,
                    a_over_h,
                    depth_over_h,
                    sliding,
                    predicted_rel_error: row.rel_error.max(depth_error),
                    predicted_ms_per_frame: row.ms_per_frame,
                });
            }
        }
    }
    out
}

/// The cheapest candidate predicted to meet its tolerance (ties: the coarser grid); when none
/// does, the most accurate one.
pub fn choose(candidates: &[AutoChoice]) -> Option<AutoChoice> {
    let cheapest = candidates
        .iter()
        .filter(|c| c.meets_tolerance())
        .min_by(|a, b| {
            a.predicted_ms_per_frame
                .total_cmp(&b.predicted_ms_per_frame)
                .then(b.mechanics_stride.cmp(&a.mechanics_stride))
        });
    cheapest.copied().or_else(|| most_accurate(candidates))
}

/// The candidate with the smallest predicted error (ties: the cheaper).
pub fn most_accurate(candidates: &[AutoChoice]) -> Option<AutoChoice> {
    candidates
        .iter()
        .min_by(|a, b| {
            a.predicted_rel_error
                .total_cmp(&b.predicted_rel_error)
                .then(
                    a.predicted_ms_per_frame
                        .total_cmp(&b.predicted_ms_per_frame),
                )
        })
        .copied()
}

/// The deepest indentation (mm) along the frames: the largest rigid penetration of the gel
/// surface, or under force control a sphere's Hertz approach a²/R at the largest load (with
/// `contact_radius_mm` its radius there).
pub fn depth_estimate_mm(
    spec: &IndenterSpec,
    indenter: &Indenter,
    frames: &[FrameTarget],
    sensor: &SensorConfig,
    contact_radius_mm: f64,
) -> f64 {
    if frames.iter().any(|f| f.normal_force_n.is_some()) {
        return spec
            .radius_mm
            .map_or(0.0, |r| contact_radius_mm * contact_radius_mm / r);
    }
    let (image, coarse) = (sensor.grid(), coarse_grid(sensor));
    let depth = |grid: Grid, f: &FrameTarget| {
        GapField::cast(indenter, &f.pose, grid)
            .gap_mm
            .iter()
            .filter(|g| g.is_finite())
            .fold(0.0f64, |m, &g| m.max(-g))
    };
    frames
        .iter()
        .map(|f| (depth(coarse, f), f))
        .max_by(|a, b| a.0.total_cmp(&b.0))
        .map_or(0.0, |(_, f)| depth(image, f))
}

/// The sensor's image in cells of 4 × 4 pixels: where the estimates below cast every frame
/// before looking closer.
fn coarse_grid(sensor: &SensorConfig) -> Grid {
    let image = sensor.grid();
    Grid {
        nx: image.nx.div_ceil(4),
        ny: image.ny.div_ceil(4),
        cell_mm: image.cell_mm * 4.0,
    }
}

/// Whether the indenter moves along the gel while pressed into it: two consecutive frames that
/// both reach below the gel's surface (cast on the coarse grid of [`depth_estimate_mm`]; under
/// force control, both loaded) with the indenter moved in x or y or turned about z between them.
pub fn sliding_estimate(
    indenter: &Indenter,
    frames: &[FrameTarget],
    sensor: &SensorConfig,
) -> bool {
    let coarse = coarse_grid(sensor);
    let pressed = |f: &FrameTarget| match f.normal_force_n {
        Some(force) => force > 0.0,
        None => GapField::cast(indenter, &f.pose, coarse)
            .gap_mm
            .iter()
            .any(|&g| g < 0.0),
    };
    let moved = |a: &FrameTarget, b: &FrameTarget| {
        let (p, q) = (a.pose, b.pose);
        p.position_mm.x != q.position_mm.x
            || p.position_mm.y != q.position_mm.y
            || p.rotation_deg.z != q.rotation_deg.z
    };
    frames
        .windows(2)
        .any(|w| moved(&w[0], &w[1]) && pressed(&w[0]) && pressed(&w[1]))
}

/// A lower estimate of the largest contact radius (mm) along the frames: (2/π) times the radius
/// of the rigid penetration's footprint at the deepest-reaching frame (the ratio of Sneddon's
/// cone; Hertz gives 1/√2 and a flat punch 1, so the estimate errs towards fewer cells). Under
/// force control, a sphere's Hertz radius at the largest load.
pub fn contact_radius_estimate_mm(
    spec: &IndenterSpec,
    indenter: &Indenter,
    frames: &[FrameTarget],
    sensor: &SensorConfig,
    gel: &Gel,
) -> Result<f64, String> {
    let max_force = frames
        .iter()
        .filter_map(|f| f.normal_force_n)
        .reduce(f64::max);
    if let Some(force_n) = max_force {
        return match (spec.shape, spec.radius_mm) {
            (ShapeKind::Sphere, Some(r)) => {
                Ok((3.0 * force_n * 1e3 * r / (4.0 * gel.effective_modulus_kpa())).cbrt())
            }
            _ => Err(
                "normal_force_n keyframes need a sphere indenter under solver = \"auto\" \
                      (name a solver instead)"
                    .into(),
            ),
        };
    }
    let (image, coarse) = (sensor.grid(), coarse_grid(sensor));
    let touching = |gap: &GapField| gap.gap_mm.iter().filter(|&&g| g < 0.0).count();
    let deepest = frames
        .iter()
        .map(|f| (touching(&GapField::cast(indenter, &f.pose, coarse)), f))
        .max_by_key(|(n, _)| *n);
    let cells = deepest
        .map(|(_, f)| touching(&GapField::cast(indenter, &f.pose, image)))
        .unwrap_or(0);
    if cells == 0 {
        return Err(
            "the indenter never touches the gel in view, so there is nothing to \
                    choose a solver for"
                .into(),
        );
    }
    let footprint_mm = (cells as f64 * image.cell_area_mm2() / std::f64::consts::PI).sqrt();
    Ok(footprint_mm * 2.0 / std::f64::consts::PI)
}
