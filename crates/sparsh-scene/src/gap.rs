//! Gap fields: the signed distance from the undeformed gel surface (z = 0) up to the indenter,
//! along the sensor normal, at every gel grid cell.

use glam::DVec3;
use rayon::prelude::*;

use crate::{Grid, Indenter, Pose};

/// Gap (mm) at every cell of `grid`: z of the indenter's lowest surface point above the cell.
/// Negative means the rigid indenter penetrates the undeformed gel; `+∞` means no part of the
/// indenter lies above (or below) the cell.
#[derive(Debug, Clone, PartialEq)]
pub struct GapField {
    /// The gel grid.
    pub grid: Grid,
    /// Gap per cell (mm), row-major.
    pub gap_mm: Vec<f64>,
}

impl GapField {
    /// Casts one ray per cell along +z (the sensor normal, towards the indenter) from below the
    /// indenter, through a BVH for meshes or analytically for primitives.
    pub fn cast(indenter: &Indenter, pose: &Pose, grid: Grid) -> GapField {
        let start_z = pose.position_mm.z - indenter.bounding_radius_mm() - 1.0;
        let rotation_inv = pose.rotation().inverse();
        let dir_local = rotation_inv * DVec3::Z;
        let mut gap_mm = vec![f64::INFINITY; grid.len()];
        gap_mm
            .par_chunks_mut(grid.nx)
            .enumerate()
            .for_each(|(j, row)| {
                let y = grid.y_mm(j);
                for (i, g) in row.iter_mut().enumerate() {
                    let origin = DVec3::new(grid.x_mm(i), y, start_z);
                    let local = rotation_inv * (origin - pose.position_mm);
                    if let Some(t) = indenter.ray_entry(local, dir_local) {
                        *g = start_z + t;
                    }
                }
            });
        GapField { grid, gap_mm }
    }

    /// The deepest penetration (mm, ≥ 0).
    pub fn max_penetration_mm(&self) -> f64 {
        self.gap_mm.iter().fold(0.0, |m, &g| m.max(-g))
    }
}
