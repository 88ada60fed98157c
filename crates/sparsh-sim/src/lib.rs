//! The frame pipeline of the sparsh simulator: for each frame of a scene's trajectory, the gap
//! field of the posed indenter, the contact solve (the solver carries stick/slip history from
//! frame to frame), and the tactile image of the deformed gel. No disk I/O.
#![warn(missing_docs)]

use std::collections::VecDeque;
use std::time::Instant;

use image::RgbImage;
use rayon::prelude::*;
use sparsh_contact::{
    ContactError, ContactInput, ContactSolver, Fields, NextFrame, NormalControl, SlipState,
    rigid_shift_mm, solver_for,
};
use sparsh_optics::{GpuContext, ImageFormation, OpticsError, Surface};
use sparsh_scene::auto::SolverTable;
use sparsh_scene::{
    FrameTarget, GapField, Grid, Pose, RungLimits, Scene, SolverKind, Validity, ValidityPolicy,
};

/// Tangential force over the friction bound μ F_z above which a frame counts as sliding for
/// its rung's validity (the press-and-slide sweep's rows bound it then).
pub const SLIDING_LOAD: f64 = 0.05;

/// Whether a frame with force `force_n` (N) on a gel of friction coefficient `friction` is
/// loaded tangentially: its tangential force is above [`SLIDING_LOAD`] of the friction bound
/// μ F_z (a press of a symmetric indenter carries none, a slide in gross slip all of it), so the
/// press-and-slide rows of the solver table bound its error.
pub fn loaded_tangentially(force_n: [f64; 3], friction: f64) -> bool {
    let [fx, fy, fz] = force_n;
    fx.hypot(fy) > SLIDING_LOAD * friction * fz.abs()
}

/// Why a frame could not be simulated.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// The contact solver failed (non-convergence, outside validity).
    #[error("frame {frame}")]
    Contact {
        /// Frame index.
        frame: usize,
        /// Solver error.
        #[source]
        source: ContactError,
    },
    /// A frame outside its rung's validity under `validity = "error"`.
    #[error(
        "frame {frame}: the {} rung is outside its validity: {validity} at the {:.1} % force \
         tolerance (validity = \"error\"; \"warn\" records it in the labels instead)",
        rung.name(),
        100.0 * tolerance
    )]
    OutsideValidity {
        /// Frame index.
        frame: usize,
        /// The rung that solved it.
        rung: SolverKind,
        /// Which limit it passed.
        validity: Validity,
        /// The scene's relative force tolerance.
        tolerance: f64,
    },
    /// The optics could not be set up.
    #[error(transparent)]
    Optics(#[from] OpticsError),
}

/// One simulated frame.
#[derive(Debug, Clone)]
pub struct Frame {
    /// What the trajectory asked for.
    pub target: FrameTarget,
    /// The indenter's pose as simulated (under load control, z includes the approach found).
    pub pose: Pose,
    /// The sensor image.
    pub image: RgbImage,
    /// Centres of the printed markers on the deformed gel (pixels: x = column, y = row, pixel
    /// (0, 0)'s centre at the origin), row by row; empty for a markerless gel.
    pub markers_px: Vec<[f64; 2]>,
    /// Ground-truth fields over the camera's view.
    pub fields: Fields,
    /// Stick/slip state of the whole contact (also beyond the view).
    pub slip_state: SlipState,
    /// Area of the whole contact (mm², also beyond the view).
    pub contact_area_mm2: f64,
    /// The rung that solved the frame (under `validity = "escalate"`, possibly above the
    /// scene's).
    pub solver: SolverKind,
    /// Whether the frame lies where that rung holds, at the scene's tolerance.
    pub validity: Validity,
    /// Wall-clock time of each stage (not part of any output).
    pub timings: StageTimes,
}

/// Seconds spent in each stage of a frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimes {
    /// Ray-casting the gap field (overlapping the previous frame's contact solve).
    pub gap_s: f64,
    /// The contact solve.
    pub contact_s: f64,
    /// Image formation.
    pub optics_s: f64,
}

/// One frame's contact, solved.
struct Solved {
    gap: GapField,
    fields: Fields,
    pose: Pose,
}

/// One frame's mechanics, ready for its image: the fields over the camera's view and what the
/// labels need of the whole gel.
struct Contacted {
    target: FrameTarget,
    pose: Pose,
    fields: Fields,
    slip_state: SlipState,
    contact_area_mm2: f64,
    solver: SolverKind,
    validity: Validity,
    gap_s: f64,
    contact_s: f64,
}

/// The path-dependent half of the pipeline: gap fields and contact solves, frame after frame.
struct Mechanics {
    targets: Vec<FrameTarget>,
    rung: SolverKind,
    /// Where `rung` holds at the scene's tolerance.
    limits: RungLimits,
    solver: Box<dyn ContactSolver>,
    previous_pose: Option<Pose>,
    next: usize,
    /// The gap fields of the frames from `next` on, cast while earlier frames were solved.
    cast_ahead: VecDeque<Cast>,
}

/// A frame's gap field and the seconds its casting took.
struct Cast {
    index: usize,
    gap: GapField,
    gap_s: f64,
}

impl Cast {
    /// Casts the gap field of `target` on the scene's mechanics grid. It depends on the
    /// commanded pose alone, not on the contact history.
    fn of(scene: &Scene, target: &FrameTarget) -> Cast {
        let start = Instant::now();
        let gap = GapField::cast(&scene.indenter, &target.pose, scene.mechanics_grid());
        Cast {
            index: target.index,
            gap,
            gap_s: start.elapsed().as_secs_f64(),
        }
    }
}

/// Runs one scene's trajectory frame by frame.
///
/// The contact of frame k + 1 depends on frame k's (stick/slip history) but frame k's image does
/// not, so while frame k's image is formed the next frame's contact is already being solved,
/// with frame k + 2's normal problem beside its tangential one and frame k + 3's gap field cast
/// meanwhile (tasks on the rayon pool). Each stage is deterministic, so the frames are the same
/// bits as one stage after the other, whatever the thread count.
pub struct Simulator {
    scene: Scene,
    mechanics: Mechanics,
    renderer: ImageFormation,
    /// The contact of the frame after the last one returned, solved ahead.
    ahead: Option<Result<Contacted, SimError>>,
}

impl Simulator {
    /// Prepares the solver and renderer of `scene`, images formed on the CPU.
    pub fn new(scene: Scene) -> Result<Simulator, SimError> {
        Simulator::on_device(scene, None)
    }

    /// Prepares the solver and renderer of `scene`, images formed on `gpu` if given.
    pub fn on_device(scene: Scene, gpu: Option<&GpuContext>) -> Result<Simulator, SimError> {
        let solver = solver_for(scene.solver, &scene.gel, scene.mechanics_grid());
        let renderer = ImageFormation::new(&scene.sensor, &scene.optics, scene.seed, gpu)?;
        Ok(Simulator {
            mechanics: Mechanics {
                targets: scene.frames(),
                rung: scene.solver,
                limits: RungLimits::of(
                    SolverTable::builtin(),
                    scene.solver,
                    scene.tolerance,
                    scene.gel.friction,
                ),
                solver,
                previous_pose: None,
                next: 0,
                cast_ahead: VecDeque::new(),
            },
            scene,
            renderer,
            ahead: None,
        })
    }

    /// The scene being simulated.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// Number of frames in the trajectory.
    pub fn frame_count(&self) -> usize {
        self.mechanics.targets.len()
    }

    /// The sensor's image with nothing touching.
    pub fn background(&self) -> RgbImage {
        self.renderer.background()
    }

    /// Simulates the next frame, or `None` after the last one. A frame whose contact fails is
    /// an error; the frames after it are still simulated by later calls.
    pub fn next_frame(&mut self) -> Option<Result<Frame, SimError>> {
        let current = match self.ahead.take() {
            Some(contacted) => contacted,
            None => self.mechanics.next_contact(&self.scene)?,
        };
        let current = match current {
            Ok(contacted) => contacted,
            Err(e) => return Some(Err(e)),
        };
        let (scene, renderer, mechanics) = (&self.scene, &self.renderer, &mut self.mechanics);
        let (frame, ahead) = rayon::join(
            || form_image(scene, renderer, current),
            || mechanics.next_contact(scene),
        );
        self.ahead = ahead;
        Some(frame)
    }
}

impl Mechanics {
    /// The next frame's gap field and contact, checked against the rung's validity (and
    /// escalated under `validity = "escalate"`), its fields cropped to the camera's view; `None`
    /// after the last frame.
    ///
    /// The next frame's gap field goes to the solver with this one (the boundary-element rungs
    /// solve its normal problem beside this frame's tangential one), and the gap field of the
    /// frame after that is cast meanwhile.
    fn next_contact(&mut self, scene: &Scene) -> Option<Result<Contacted, SimError>> {
        let target = *self.targets.get(self.next)?;
        self.next += 1;
        let cast = self.cast(scene, &target);
        let following = self.targets.get(self.next).copied();
        let next = following.map(|t| (self.cast(scene, &t), t));
        let after = self.targets.get(self.next + 1).copied();
        let (contacted, after_cast) = rayon::join(
            || self.contact(scene, target, cast, next.as_ref()),
            || after.map(|t| Cast::of(scene, &t)),
        );
        self.cast_ahead = next.map(|(c, _)| c).into_iter().chain(after_cast).collect();
        Some(contacted)
    }

    /// The gap field of `target`: cast ahead, or now.
    fn cast(&mut self, scene: &Scene, target: &FrameTarget) -> Cast {
        match self.cast_ahead.pop_front() {
            Some(cast) if cast.index == target.index => cast,
            _ => {
                self.cast_ahead.clear();
                Cast::of(scene, target)
            }
        }
    }

    /// Solves the contact of `target` (its gap field `cast`) with `solver`, after the frame
    /// posed at `previous`, handing the solver the `next` frame's gap field if known.
    fn solve_contact(
        scene: &Scene,
        solver: &mut dyn ContactSolver,
        target: &FrameTarget,
        cast: Cast,
        previous: Option<&Pose>,
        next: Option<&(Cast, FrameTarget)>,
    ) -> Result<Solved, SimError> {
        let grid = scene.mechanics_grid();
        let Cast { gap, .. } = cast;
        let rigid_shift_mm = match previous {
            Some(previous) => rigid_shift_mm(previous, &target.pose, &gap),
            None => vec![[0.0; 2]; grid.len()],
        };
        let input = ContactInput {
            gap: &gap,
            normal: normal_control(target),
            rigid_shift_mm: &rigid_shift_mm,
        };
        let next = next.map(|(cast, target)| NextFrame {
            gap: &cast.gap,
            normal: normal_control(target),
        });
        let fields = solver
            .solve_ahead(&input, next)
            .map_err(|source| SimError::Contact {
                frame: target.index,
                source,
            })?;
        let mut pose = target.pose;
        pose.position_mm.z -= fields.approach_offset_mm;
        Ok(Solved { gap, fields, pose })
    }

    /// Contact radius over gel thickness (the radius of a circle of the contact's area) and
    /// indentation depth over gel thickness (the deepest rigid penetration, with the approach
    /// found under load control) of a solved frame.
    fn frame_ratios(scene: &Scene, solved: &Solved) -> (f64, f64) {
        let (gap, fields) = (&solved.gap, &solved.fields);
        let h = scene.gel.thickness_mm;
        let a = (fields.contact_area_mm2() / std::f64::consts::PI).sqrt();
        let penetration = gap
            .gap_mm
            .iter()
            .filter(|g| g.is_finite())
            .fold(0.0f64, |m, &g| m.max(-g));
        (
            a / h,
            (penetration + fields.approach_offset_mm).max(0.0) / h,
        )
    }

    fn frame_sliding(scene: &Scene, solved: &Solved) -> bool {
        loaded_tangentially(solved.fields.force_n, scene.gel.friction)
    }

    fn validity(&self, scene: &Scene, solved: &Solved) -> Validity {
        let (a_over_h, depth_over_h) = Mechanics::frame_ratios(scene, solved);
        self.limits.check(
            solved.fields.contact.contains(&true),
            a_over_h,
            depth_over_h,
            Mechanics::frame_sliding(scene, solved),
        )
    }

    /// `validity = "escalate"`: the lowest rung above the current one whose limits hold at this
    /// frame's contact (the top rung if none does), with its path history rebuilt by solving
    /// the trajectory's earlier frames on it. Returns the frame solved on that rung, or `None`
    /// at the top of the ladder.
    fn escalate(
        &mut self,
        scene: &Scene,
        target: &FrameTarget,
        solved: &Solved,
    ) -> Result<Option<Solved>, SimError> {
        let (a_over_h, depth_over_h) = Mechanics::frame_ratios(scene, solved);
        let sliding = Mechanics::frame_sliding(scene, solved);
        let higher: Vec<SolverKind> = SolverKind::ALL
            .into_iter()
            .skip_while(|&k| k != self.rung)
            .skip(1)
            .collect();
        let Some(&top) = higher.last() else {
            return Ok(None);
        };
        let limits_of = |k| {
            RungLimits::of(
                SolverTable::builtin(),
                k,
                scene.tolerance,
                scene.gel.friction,
            )
        };
        let rung = higher
            .into_iter()
            .find(|&k| {
                limits_of(k)
                    .check(true, a_over_h, depth_over_h, sliding)
                    .is_ok()
            })
            .unwrap_or(top);
        let limits = limits_of(rung);
        let mut solver = solver_for(rung, &scene.gel, scene.mechanics_grid());
        let mut previous = None;
        for earlier in &self.targets[..target.index] {
            let cast = Cast::of(scene, earlier);
            let solved = Mechanics::solve_contact(
                scene,
                solver.as_mut(),
                earlier,
                cast,
                previous.as_ref(),
                None,
            )?;
            previous = Some(solved.pose);
        }
        let cast = Cast::of(scene, target);
        let solved = Mechanics::solve_contact(
            scene,
            solver.as_mut(),
            target,
            cast,
            previous.as_ref(),
            None,
        )?;
        self.rung = rung;
        self.limits = limits;
        self.solver = solver;
        Ok(Some(solved))
    }

    fn contact(
        &mut self,
        scene: &Scene,
        target: FrameTarget,
        cast: Cast,
        next: Option<&(Cast, FrameTarget)>,
    ) -> Result<Contacted, SimError> {
        let start = Instant::now();
        let gap_s = cast.gap_s;
        let mut solved = Mechanics::solve_contact(
            scene,
            self.solver.as_mut(),
            &target,
            cast,
            self.previous_pose.as_ref(),
            next,
        )?;
        let mut validity = self.validity(scene, &solved);
        if !validity.is_ok() {
            match scene.validity {
                ValidityPolicy::Error => {
                    return Err(SimError::OutsideValidity {
                        frame: target.index,
                        rung: self.rung,
                        validity,
                        tolerance: scene.tolerance,
                    });
                }
                ValidityPolicy::Warn => {}
                ValidityPolicy::Escalate => {
                    while !validity.is_ok()
                        && let Some(higher) = self.escalate(scene, &target, &solved)?
                    {
                        solved = higher;
                        validity = self.validity(scene, &solved);
                    }
                }
            }
        }
        let Solved { fields, pose, .. } = solved;
        self.previous_pose = Some(pose);
        let slip_state = fields.slip_state();
        let contact_area_mm2 = fields.contact_area_mm2();
        let fields = crop(&fields, scene.mechanics_margin_cells(), scene.view_grid());
        Ok(Contacted {
            target,
            pose,
            fields,
            slip_state,
            contact_area_mm2,
            solver: self.rung,
            validity,
            gap_s,
            contact_s: start.elapsed().as_secs_f64(),
        })
    }
}

/// How a frame's normal problem is driven: its commanded force, else its pose's approach.
fn normal_control(target: &FrameTarget) -> NormalControl {
    target
        .normal_force_n
        .map_or(NormalControl::Approach, NormalControl::Force)
}

/// The image of a frame whose contact is solved: the deformed surface (upsampled to the
/// image's grid when the mechanics is coarser) through the scene's image formation.
fn form_image(
    scene: &Scene,
    renderer: &ImageFormation,
    contacted: Contacted,
) -> Result<Frame, SimError> {
    let start = Instant::now();
    let Contacted {
        target,
        pose,
        fields,
        slip_state,
        contact_area_mm2,
        solver,
        validity,
        gap_s,
        contact_s,
    } = contacted;
    let grid = fields.grid;
    let image_grid = scene.grid();
    let render = |surface: &Surface| {
        (
            renderer.render(surface, target.index),
            renderer.marker_centres_px(surface),
        )
    };
    let (image, markers_px) = if image_grid == grid {
        render(&Surface {
            grid,
            ux_mm: &fields.ux_mm,
            uy_mm: &fields.uy_mm,
            uz_mm: &fields.uz_mm,
        })
    } else {
        let up = |v: &[f64]| upsample(v, grid, image_grid);
        let (ux, uy, uz) = (up(&fields.ux_mm), up(&fields.uy_mm), up(&fields.uz_mm));
        render(&Surface {
            grid: image_grid,
            ux_mm: &ux,
            uy_mm: &uy,
            uz_mm: &uz,
        })
    };
    let image = image?;
    Ok(Frame {
        target,
        pose,
        image,
        markers_px,
        fields,
        slip_state,
        contact_area_mm2,
        solver,
        validity,
        timings: StageTimes {
            gap_s,
            contact_s,
            optics_s: start.elapsed().as_secs_f64(),
        },
    })
}

/// The fields over `view`, the central part of the mechanics grid `margin` cells in from each
/// side. The total force and the approach found stay those of the whole gel.
fn crop(fields: &Fields, margin: usize, view: Grid) -> Fields {
    if margin == 0 {
        return fields.clone();
    }
    fn take<T: Copy>(v: &[T], nx: usize, margin: usize, view: Grid) -> Vec<T> {
        (0..view.ny)
            .flat_map(|j| {
                let row = (j + margin) * nx + margin;
                v[row..row + view.nx].iter().copied()
            })
            .collect()
    }
    let nx = fields.grid.nx;
    let take_f = |v: &[f64]| take(v, nx, margin, view);
    let take_mask = |v: &[bool]| take(v, nx, margin, view);
    Fields {
        grid: view,
        ux_mm: take_f(&fields.ux_mm),
        uy_mm: take_f(&fields.uy_mm),
        uz_mm: take_f(&fields.uz_mm),
        pressure_kpa: take_f(&fields.pressure_kpa),
        traction_x_kpa: take_f(&fields.traction_x_kpa),
        traction_y_kpa: take_f(&fields.traction_y_kpa),
        contact: take_mask(&fields.contact),
        slip: take_mask(&fields.slip),
        force_n: fields.force_n,
        approach_offset_mm: fields.approach_offset_mm,
    }
}

/// Bilinear interpolation of a field on the cell centres of `coarse` at the cell centres of
/// `fine` (same centre and extent), holding the edge values beyond the outermost centres.
pub fn upsample(values: &[f64], coarse: Grid, fine: Grid) -> Vec<f64> {
    let axis = |n_fine: usize, n_coarse: usize, ratio: f64| -> Vec<(usize, usize, f64)> {
        (0..n_fine)
            .map(|i| {
                let t = ((i as f64 + 0.5) / ratio - 0.5).clamp(0.0, (n_coarse - 1) as f64);
                let i0 = (t.floor() as usize).min(n_coarse.saturating_sub(2));
                let i1 = (i0 + 1).min(n_coarse - 1);
                (i0, i1, t - i0 as f64)
            })
            .collect()
    };
    let ratio = coarse.cell_mm / fine.cell_mm;
    let xs = axis(fine.nx, coarse.nx, ratio);
    let ys = axis(fine.ny, coarse.ny, ratio);
    let at = |i: usize, j: usize| values[j * coarse.nx + i];
    let mut out = vec![0.0; fine.len()];
    out.par_chunks_mut(fine.nx)
        .zip(&ys)
        .for_each(|(row, &(j0, j1, wy))| {
            for (o, &(i0, i1, wx)) in row.iter_mut().zip(&xs) {
                let top = at(i0, j0) * (1.0 - wx) + at(i1, j0) * wx;
                let bottom = at(i0, j1) * (1.0 - wx) + at(i1, j1) * wx;
                *o = top * (1.0 - wy) + bottom * wy;
            }
        });
    out
}

#[cfg(test)]
mod tests {

    /// A press carries no tangential load, a slide in gross slip carries μF_z; the threshold is
    /// 5 % of the friction bound, whichever way the force points.
    #[test]
    fn tangential_load_is_read_against_the_friction_bound() {
        assert!(!loaded_tangentially([0.0, 0.0, 1.0], 1.0));
        assert!(!loaded_tangentially([0.03, 0.04, 1.0], 1.0));
        assert!(loaded_tangentially([0.03, 0.045, 1.0], 1.0));
        assert!(loaded_tangentially([-0.5, 0.0, 0.5], 1.0));
        assert!(!loaded_tangentially([0.0, 0.0, 1.0], 0.0));
        assert!(loaded_tangentially([0.0, -0.06, 1.0], 1.0));
    }
    use super::*;

    /// Bilinear interpolation reproduces a linear field exactly between the outermost centres.
    #[test]
    fn upsampling_is_exact_for_linear_fields() {
        let coarse = Grid {
            nx: 8,
            ny: 6,
            cell_mm: 0.4,
        };
        let fine = Grid {
            nx: 32,
            ny: 24,
            cell_mm: 0.1,
        };
        let linear = |x: f64, y: f64| 0.3 + 2.0 * x - 0.7 * y;
        let values: Vec<f64> = (0..coarse.len())
            .map(|c| linear(coarse.x_mm(c % coarse.nx), coarse.y_mm(c / coarse.nx)))
            .collect();
        let up = upsample(&values, coarse, fine);
        let (x_max, y_max) = (coarse.x_mm(coarse.nx - 1), coarse.y_mm(coarse.ny - 1));
        let mut inside = 0;
        for (c, value) in up.iter().enumerate() {
            let (x, y) = (fine.x_mm(c % fine.nx), fine.y_mm(c / fine.nx));
            if x.abs() <= x_max && y.abs() <= y_max {
                assert!((value - linear(x, y)).abs() < 1e-12, "({x}, {y})");
                inside += 1;
            }
        }
        assert!(inside > fine.len() / 2);
    }
}
