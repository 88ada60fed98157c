//! Tactile image formation: the deformed gel surface (height and lateral displacement on the
//! sensor grid) becomes the sensor's RGB image. Optics knows nothing of forces.
#![warn(missing_docs)]

pub mod ball;
pub mod calibrated;
pub mod gpu;
pub mod metrics;
pub mod pack;
pub mod photometric;
pub mod shadow;
pub mod sim2real;

use image::RgbImage;
use sparsh_scene::Grid;

pub use calibrated::{CalibratedRenderer, Calibration, ColourMap};
pub use gpu::{Device, GpuContext, GpuError, GpuRenderer};
pub use pack::{CalibrationPack, PackError};
pub use photometric::PhotometricRenderer;

/// One of the image-formation models, behind one `render` call.
#[derive(Debug, Clone)]
pub enum Renderer {
    /// Physically based shading under the sensor's lights ([`PhotometricRenderer`]).
    Photometric(PhotometricRenderer),
    /// A map fitted on real images ([`CalibratedRenderer`]).
    Calibrated(CalibratedRenderer),
    /// Either model as wgpu compute shaders ([`GpuRenderer`]).
    Gpu(GpuRenderer),
}

impl Renderer {
    /// The no-contact image.
    pub fn background(&self) -> RgbImage {
        match self {
            Renderer::Photometric(r) => r.background(),
            Renderer::Calibrated(r) => r.background(),
            Renderer::Gpu(r) => r.background(),
        }
    }

    /// The image of a deformed surface.
    pub fn render(&self, surface: &Surface) -> Result<RgbImage, GpuError> {
        match self {
            Renderer::Photometric(r) => Ok(r.render(surface)),
            Renderer::Calibrated(r) => Ok(r.render(surface)),
            Renderer::Gpu(r) => r.render(surface),
        }
    }

    /// The image of a deformed surface before rounding (RGB, 0–255 scale).
    pub fn render_linear(&self, surface: &Surface) -> Result<Vec<[f32; 3]>, GpuError> {
        match self {
            Renderer::Photometric(r) => Ok(r.render_linear(surface)),
            Renderer::Calibrated(r) => Ok(r.render_linear(surface)),
            Renderer::Gpu(r) => r.render_linear(surface),
        }
    }

    /// The same model on the GPU of `context` (buffers and pipeline made here, once).
    pub fn on_gpu(&self, context: &GpuContext) -> Result<Renderer, GpuError> {
        GpuRenderer::new(self, context).map(Renderer::Gpu)
    }
}

/// Rounds and clamps linear 0–255 RGB values into an 8-bit image.
pub(crate) fn to_image(width_px: usize, height_px: usize, pixels: &[[f32; 3]]) -> RgbImage {
    let raw: Vec<u8> = pixels
        .iter()
        .flat_map(|p| p.map(|v| v.round().clamp(0.0, 255.0) as u8))
        .collect();
    RgbImage::from_raw(width_px as u32, height_px as u32, raw)
        .expect("pixel buffer matches the image size")
}

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
    /// The GPU path failed.
    #[error(transparent)]
    Gpu(#[from] GpuError),
}
