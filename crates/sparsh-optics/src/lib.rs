//! Tactile image formation: the deformed gel surface (height and lateral displacement on the
//! sensor grid) becomes the sensor's RGB image. Optics knows nothing of forces.
#![warn(missing_docs)]

mod photometric;

use sparsh_scene::Grid;

pub use photometric::PhotometricRenderer;

/// The deformed gel surface on the sensor grid (mm, camera frame of [`sparsh_scene::grid`]).
#[derive(Debug, Clone, Copy)]
pub struct Surface<'a> {
    /// The sensor grid (one cell per pixel).
    pub grid: Grid,
    /// Lateral displacement along x (mm).
    pub ux_mm: &'a [f64],
    /// Lateral displacement along y (mm).
    pub uy_mm: &'a [f64],
    /// Normal displacement (mm; negative towards the camera).
    pub uz_mm: &'a [f64],
}

/// Optics failures: a sensor description or background that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum OpticsError {
    /// The background image cannot be read or has the wrong size.
    #[error("{path}: background: {message}")]
    Background {
        /// Image file.
        path: std::path::PathBuf,
        /// What is wrong.
        message: String,
    },
}
