//! Photometric model: Lambertian shading of the gel surface under the sensor's point lights,
//! applied as a change over the background image so a real background keeps its look.

use image::RgbImage;
use rayon::prelude::*;
use sparsh_scene::SensorConfig;

use crate::{OpticsError, Surface};

/// Grey level of the synthetic background where no light reaches.
const AMBIENT: f32 = 30.0;
/// Brightest channel of the synthetic flat-gel background.
const PEAK: f32 = 200.0;

/// Renders `bg + g·(S(n) − S(n₀))`, where S(n) = Σ_l c_l I_l max(n·l̂, 0) (d₀/|L − P|)² is the
/// Lambertian irradiance of the surface normal n at surface point P from each point light at L
/// (colour c_l, intensity I_l), n₀ the undeformed normal, d₀ = 10 mm and g a gain that maps the
/// flat gel's brightest channel to a mid-high grey.
#[derive(Debug, Clone)]
pub struct PhotometricRenderer {
    sensor: SensorConfig,
    /// Background, RGB in 0–255, row-major.
    background: Vec<[f32; 3]>,
    /// Shading of the undeformed gel.
    flat: Vec<[f32; 3]>,
    gain: f32,
}

impl PhotometricRenderer {
    /// Prepares the flat-gel shading and the background (the sensor's image file if it names
    /// one, otherwise the flat gel under its lights).
    pub fn new(sensor: &SensorConfig) -> Result<PhotometricRenderer, OpticsError> {
        let grid = sensor.grid();
        let zeros = vec![0.0; grid.len()];
        let flat_surface = Surface {
            grid,
            ux_mm: &zeros,
            uy_mm: &zeros,
            uz_mm: &zeros,
        };
        let flat = shade(sensor, &flat_surface);
        let brightest = flat
            .iter()
            .flat_map(|c| c.iter().copied())
            .fold(f32::MIN_POSITIVE, f32::max);
        let gain = (PEAK - AMBIENT) / brightest;
        let background = match &sensor.background {
            Some(path) => load_background(path, sensor)?,
            None => flat.iter().map(|c| c.map(|v| AMBIENT + gain * v)).collect(),
        };
        Ok(PhotometricRenderer {
            sensor: sensor.clone(),
            background,
            flat,
            gain,
        })
    }

    /// The no-contact image.
    pub fn background(&self) -> RgbImage {
        to_image(&self.sensor, &self.background)
    }

    /// The image of a deformed surface.
    pub fn render(&self, surface: &Surface) -> RgbImage {
        let lit = shade(&self.sensor, surface);
        let pixels: Vec<[f32; 3]> = lit
            .par_iter()
            .zip(&self.flat)
            .zip(&self.background)
            .map(|((s, f), b)| std::array::from_fn(|c| b[c] + self.gain * (s[c] - f[c])))
            .collect();
        to_image(&self.sensor, &pixels)
    }
}

/// Lambertian irradiance per pixel and colour channel.
fn shade(sensor: &SensorConfig, surface: &Surface) -> Vec<[f32; 3]> {
    let grid = surface.grid;
    let (nx, ny) = (grid.nx, grid.ny);
    let uz = surface.uz_mm;
    const D0_MM2: f64 = 100.0;
    (0..grid.len())
        .into_par_iter()
        .map(|c| {
            let (i, j) = (c % nx, c / nx);
            let at = |ii: usize, jj: usize| uz[jj * nx + ii];
            let (il, ir) = (i.saturating_sub(1), (i + 1).min(nx - 1));
            let (ju, jd) = (j.saturating_sub(1), (j + 1).min(ny - 1));
            let dzdx = (at(ir, j) - at(il, j)) / ((ir - il).max(1) as f64 * grid.cell_mm);
            let dzdy = (at(i, jd) - at(i, ju)) / ((jd - ju).max(1) as f64 * grid.cell_mm);
            // Normal of z = uz(x, y) facing the camera (−z).
            let norm = (dzdx * dzdx + dzdy * dzdy + 1.0).sqrt();
            let n = [dzdx / norm, dzdy / norm, -1.0 / norm];
            let p = [
                grid.x_mm(i) + surface.ux_mm[c],
                grid.y_mm(j) + surface.uy_mm[c],
                uz[c],
            ];
            let mut rgb = [0.0f32; 3];
            for light in &sensor.lights {
                let l = [
                    light.position_mm[0] - p[0],
                    light.position_mm[1] - p[1],
                    light.position_mm[2] - p[2],
                ];
                let d2 = l[0] * l[0] + l[1] * l[1] + l[2] * l[2];
                let cos = (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]) / d2.sqrt();
                let e = light.intensity * cos.max(0.0) * D0_MM2 / d2;
                for (out, col) in rgb.iter_mut().zip(light.color) {
                    *out += (col * e) as f32;
                }
            }
            rgb
        })
        .collect()
}

fn to_image(sensor: &SensorConfig, pixels: &[[f32; 3]]) -> RgbImage {
    crate::to_image(sensor.width_px, sensor.height_px, pixels)
}

fn load_background(
    path: &std::path::Path,
    sensor: &SensorConfig,
) -> Result<Vec<[f32; 3]>, OpticsError> {
    let err = |message: String| OpticsError::Background {
        path: path.to_path_buf(),
        message,
    };
    let img = image::open(path).map_err(|e| err(e.to_string()))?.to_rgb8();
    if img.dimensions() != (sensor.width_px as u32, sensor.height_px as u32) {
        return Err(err(format!(
            "is {}×{}, the sensor is {}×{}",
            img.width(),
            img.height(),
            sensor.width_px,
            sensor.height_px
        )));
    }
    Ok(img.pixels().map(|p| p.0.map(f32::from)).collect())
}
