//! Trajectory keyframes and their interpolation at the sensor's frame rate.

use glam::{DQuat, DVec3, EulerRot};
use serde::Deserialize;

/// One `[[trajectory]]` entry.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Keyframe {
    /// Time (s).
    pub time_s: f64,
    /// Position of the indenter's local origin (its tip) in the camera frame (mm); z = −d presses
    /// the tip d millimetres into the undeformed gel.
    pub position_mm: [f64; 3],
    /// Rotation about the local origin: X, then Y, then Z Euler angles (degrees).
    #[serde(default)]
    pub rotation_deg: [f64; 3],
    /// Target normal force (N, pressing); when this and the neighbouring keyframe both set it,
    /// the solver finds the approach that gives it and `position_mm[2]` is ignored.
    pub normal_force_n: Option<f64>,
}

/// A rigid pose of the indenter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Translation (mm).
    pub position_mm: DVec3,
    /// X, Y, Z Euler angles (degrees).
    pub rotation_deg: DVec3,
}

impl Pose {
    /// Rotation as a quaternion.
    pub fn rotation(&self) -> DQuat {
        let r = self.rotation_deg * (std::f64::consts::PI / 180.0);
        DQuat::from_euler(EulerRot::XYZ, r.x, r.y, r.z)
    }

    /// Maps a point of the indenter's local frame into the camera frame.
    pub fn apply(&self, local: DVec3) -> DVec3 {
        self.rotation() * local + self.position_mm
    }

    /// Maps a camera-frame point into the indenter's local frame.
    pub fn inverse_apply(&self, world: DVec3) -> DVec3 {
        self.rotation().inverse() * (world - self.position_mm)
    }
}

/// What one frame asks of the simulation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameTarget {
    /// Frame index from 0.
    pub index: usize,
    /// Time (s).
    pub time_s: f64,
    /// Indenter pose (its z is the starting guess under force control).
    pub pose: Pose,
    /// Target normal force (N) when the frame is force-controlled.
    pub normal_force_n: Option<f64>,
}

/// Most frames one scene's trajectory may span: 1 000 000 (4.6 h at 60 fps, ~100 GB of
/// 320×240 PNGs), so a mistyped time fails at load instead of exhausting memory.
pub const MAX_FRAMES: usize = 1_000_000;

/// Frames sampled at `fps` over the keyframes' span: frame k is at t₀ + k/fps, and there are
/// round((t_last − t₀)·fps) of them (a 2 s trajectory at 60 fps has 120 frames); a single
/// keyframe gives one frame. Between keyframes, position, rotation and force are linear in time.
pub fn sample(keys: &[Keyframe], fps: f64) -> Vec<FrameTarget> {
    let t0 = keys[0].time_s;
    let span = keys[keys.len() - 1].time_s - t0;
    let count = ((span * fps).round() as usize).max(1);
    (0..count)
        .map(|index| {
            let time_s = t0 + index as f64 / fps;
            let k = keys
                .windows(2)
                .position(|w| time_s < w[1].time_s)
                .unwrap_or(keys.len().saturating_sub(2));
            let (a, b) = (&keys[k], &keys[(k + 1).min(keys.len() - 1)]);
            let w = if b.time_s > a.time_s {
                ((time_s - a.time_s) / (b.time_s - a.time_s)).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let lerp3 = |x: [f64; 3], y: [f64; 3]| DVec3::from(x).lerp(DVec3::from(y), w);
            FrameTarget {
                index,
                time_s,
                pose: Pose {
                    position_mm: lerp3(a.position_mm, b.position_mm),
                    rotation_deg: lerp3(a.rotation_deg, b.rotation_deg),
                },
                normal_force_n: match (a.normal_force_n, b.normal_force_n) {
                    (Some(fa), Some(fb)) => Some(fa + w * (fb - fa)),
                    (Some(fa), None) if keys.len() == 1 => Some(fa),
                    _ => None,
                },
            }
        })
        .collect()
}
