//! The frame pipeline of the sparsh simulator: for each frame of a scene's trajectory, the gap
//! field of the posed indenter, the contact solve (the solver carries stick/slip history from
//! frame to frame), and the tactile image of the deformed gel. No disk I/O.
#![warn(missing_docs)]

use std::time::Instant;

use image::RgbImage;
use sparsh_contact::{
    ContactError, ContactInput, ContactSolver, Fields, NormalControl, rigid_shift_mm, solver_for,
};
use sparsh_optics::{OpticsError, PhotometricRenderer, Surface};
use sparsh_scene::{FrameTarget, GapField, Pose, Scene};

/// Why a frame could not be simulated.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// The contact solver failed (non-convergence, outside validity).
    #[error("frame {frame}: {source}")]
    Contact {
        /// Frame index.
        frame: usize,
        /// Solver error.
        source: ContactError,
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
    /// Ground-truth fields.
    pub fields: Fields,
    /// Wall-clock time of each stage (not part of any output).
    pub timings: StageTimes,
}

/// Seconds spent in each stage of a frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimes {
    /// Ray-casting the gap field.
    pub gap_s: f64,
    /// The contact solve.
    pub contact_s: f64,
    /// Image formation.
    pub optics_s: f64,
}

/// Runs one scene's trajectory frame by frame.
pub struct Simulator {
    scene: Scene,
    targets: Vec<FrameTarget>,
    solver: Box<dyn ContactSolver>,
    renderer: PhotometricRenderer,
    previous_pose: Option<Pose>,
    next: usize,
}

impl Simulator {
    /// Prepares the solver and renderer of `scene`.
    pub fn new(scene: Scene) -> Result<Simulator, SimError> {
        let solver = solver_for(scene.solver, &scene.gel, scene.grid());
        let renderer = PhotometricRenderer::new(&scene.sensor)?;
        Ok(Simulator {
            targets: scene.frames(),
            scene,
            solver,
            renderer,
            previous_pose: None,
            next: 0,
        })
    }

    /// The scene being simulated.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// Number of frames in the trajectory.
    pub fn frame_count(&self) -> usize {
        self.targets.len()
    }

    /// The sensor's image with nothing touching.
    pub fn background(&self) -> RgbImage {
        self.renderer.background()
    }

    /// Simulates the next frame, or `None` after the last one.
    pub fn next_frame(&mut self) -> Option<Result<Frame, SimError>> {
        let target = *self.targets.get(self.next)?;
        self.next += 1;
        Some(self.simulate(target))
    }

    fn simulate(&mut self, target: FrameTarget) -> Result<Frame, SimError> {
        let grid = self.scene.grid();
        let start = Instant::now();
        let gap = GapField::cast(&self.scene.indenter, &target.pose, grid);
        let rigid_shift_mm = match &self.previous_pose {
            Some(previous) => rigid_shift_mm(previous, &target.pose, &gap),
            None => vec![[0.0; 2]; grid.len()],
        };
        let gap_done = Instant::now();
        let input = ContactInput {
            gap: &gap,
            normal: target
                .normal_force_n
                .map_or(NormalControl::Approach, NormalControl::Force),
            rigid_shift_mm: &rigid_shift_mm,
        };
        let fields = self
            .solver
            .solve(&input)
            .map_err(|source| SimError::Contact {
                frame: target.index,
                source,
            })?;
        let contact_done = Instant::now();
        let mut pose = target.pose;
        pose.position_mm.z -= fields.approach_offset_mm;
        self.previous_pose = Some(pose);
        let image = self.renderer.render(&Surface {
            grid,
            ux_mm: &fields.ux_mm,
            uy_mm: &fields.uy_mm,
            uz_mm: &fields.uz_mm,
        });
        let timings = StageTimes {
            gap_s: (gap_done - start).as_secs_f64(),
            contact_s: (contact_done - gap_done).as_secs_f64(),
            optics_s: contact_done.elapsed().as_secs_f64(),
        };
        Ok(Frame {
            target,
            pose,
            image,
            fields,
            timings,
        })
    }
}
