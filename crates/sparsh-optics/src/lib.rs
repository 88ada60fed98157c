//! Tactile image formation: the deformed gel surface (height and lateral displacement on the
//! sensor grid) becomes the sensor's RGB image. Optics knows nothing of forces.
#![warn(missing_docs)]

pub mod ball;
pub mod calibrated;
pub mod gpu;
pub mod markers;
pub mod metrics;
pub mod noise;
pub mod pack;
pub mod photometric;
pub mod shadow;
pub mod sim2real;

use image::RgbImage;
use sparsh_scene::{Grid, MarkerGrid, OpticsModel, OpticsSpec, SensorConfig};

pub use calibrated::{CalibratedRenderer, Calibration, ColourMap, FittedLights};
pub use gpu::{GpuContext, GpuError, GpuRenderer};
pub use pack::{CalibrationPack, Circle, FrameSet, PackError};
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

/// A scene's whole image formation: the model (with its shadows), the printed markers carried
/// by the lateral displacement, and the sensor instance's seeded imperfections.
#[derive(Debug, Clone)]
pub struct ImageFormation {
    renderer: Renderer,
    grid: Grid,
    markers: Option<MarkerGrid>,
    imperfections: noise::Imperfections,
    /// Background of the model before imperfections (RGB, 0–255 scale).
    background: Vec<[f32; 3]>,
    background_field: Vec<f64>,
}

impl ImageFormation {
    /// Builds the model `optics` asks for (calibration directory already resolved) for
    /// `sensor`, on the GPU of `gpu` if given, its imperfections drawn from `seed`. The
    /// calibrated model with shadows casts the calibration's fitted lights when it was fitted
    /// through shadows ([`CalibratedRenderer::with_shadows`]), marching `optics.shadow_steps`.
    pub fn new(
        sensor: &SensorConfig,
        optics: &OpticsSpec,
        seed: u64,
        gpu: Option<&GpuContext>,
    ) -> Result<ImageFormation, OpticsError> {
        let grid = sensor.grid();
        let renderer = match optics.model {
            OpticsModel::Photometric => Renderer::Photometric(PhotometricRenderer::new(
                sensor,
                optics
                    .shadows
                    .then(|| photometric::shadow_settings(sensor, optics.shadow_steps)),
            )?),
            OpticsModel::Calibrated => {
                let dir = optics
                    .calibration
                    .as_deref()
                    .unwrap_or(std::path::Path::new("."));
                let calibration =
                    Calibration::load(dir).map_err(|message| OpticsError::Calibration {
                        path: dir.to_path_buf(),
                        message,
                    })?;
                let r = CalibratedRenderer::new(&calibration, grid.nx, grid.ny);
                Renderer::Calibrated(if optics.shadows {
                    r.with_shadows(sensor, optics.shadow_steps)
                } else {
                    r
                })
            }
        };
        let renderer = match gpu {
            Some(context) => renderer.on_gpu(context)?,
            None => renderer,
        };
        let background = renderer
            .background()
            .pixels()
            .map(|p| p.0.map(f32::from))
            .collect();
        Ok(ImageFormation {
            renderer,
            grid,
            markers: sensor.markers,
            imperfections: noise::Imperfections {
                seed,
                exposure: optics.exposure,
                background_variation: optics.background_variation,
                noise_std: optics.noise_std,
            },
            background,
            background_field: noise::background_field(grid, seed, optics.background_variation),
        })
    }

    /// The no-contact image: markers at rest, exposure and background variation, no noise.
    pub fn background(&self) -> RgbImage {
        let zeros = vec![0.0; self.grid.len()];
        let rest = Surface {
            grid: self.grid,
            ux_mm: &zeros,
            uy_mm: &zeros,
            uz_mm: &zeros,
        };
        let mut pixels = self.background.clone();
        self.finish(&mut pixels, &rest, None);
        to_image(self.grid.nx, self.grid.ny, &pixels)
    }

    /// Frame `frame`'s image of a deformed surface.
    pub fn render(&self, surface: &Surface, frame: usize) -> Result<RgbImage, OpticsError> {
        let i = &self.imperfections;
        let plain = i.exposure == 1.0 && i.background_variation == 0.0 && i.noise_std == 0.0;
        if plain && self.markers.is_none() {
            return Ok(self.renderer.render(surface)?);
        }
        let mut pixels = self.renderer.render_linear(surface)?;
        self.finish(&mut pixels, surface, Some(frame));
        Ok(to_image(self.grid.nx, self.grid.ny, &pixels))
    }

    /// Markers, then imperfections (noise only for a frame).
    fn finish(&self, pixels: &mut [[f32; 3]], surface: &Surface, frame: Option<usize>) {
        if let Some(m) = &self.markers {
            markers::draw_markers(pixels, m, surface);
        }
        let imperfections = noise::Imperfections {
            noise_std: if frame.is_some() {
                self.imperfections.noise_std
            } else {
                0.0
            },
            ..self.imperfections
        };
        imperfections.apply(
            pixels,
            &self.background,
            &self.background_field,
            frame.unwrap_or(0),
        );
    }

    /// The dots' centres on the deformed gel in pixel coordinates (x = column, y = row, pixel
    /// (0, 0)'s centre at the origin), row by row; empty for a markerless gel.
    pub fn marker_centres_px(&self, surface: &Surface) -> Vec<[f64; 2]> {
        self.markers.as_ref().map_or_else(Vec::new, |m| {
            markers::marker_centres_mm(m, surface)
                .into_iter()
                .map(|c| markers::mm_to_px(surface.grid, c))
                .collect()
        })
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
    /// The calibration directory cannot be used.
    #[error("{path}: calibration: {message}")]
    Calibration {
        /// Calibration directory.
        path: std::path::PathBuf,
        /// What is wrong.
        message: String,
    },
}
