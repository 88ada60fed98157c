//! Photometric model: the gel surface shaded under the sensor's point lights (Lambert plus a
//! Blinn–Phong lobe, inverse-square falloff, cast shadows, cos⁴ vignetting), applied as a change
//! over the background image so a real background keeps its look.

use image::RgbImage;
use rayon::prelude::*;
use sparsh_scene::{Light, SensorConfig};

use crate::shadow::{ShadowSettings, visibilities};
use crate::{OpticsError, Surface};

/// Grey level of the synthetic background where no light reaches.
const AMBIENT: f32 = 30.0;
/// Brightest channel of the synthetic flat-gel background.
const PEAK: f32 = 200.0;
/// Reference distance of the lights' inverse-square falloff (mm²): d₀ = 10 mm.
const D0_MM2: f64 = 100.0;

/// Renders `bg + g·V·(S(n) − S(n₀))`, where S is the radiance of the surface towards the camera
/// summed over the lights ([`radiance`]), n₀ the undeformed normal, V the vignetting
/// ([`vignetting`]) and g a gain that maps the flat gel's brightest channel to a mid-high grey.
/// Without a background image, bg = V·(a + g·S(n₀)) with a dim ambient level a.
#[derive(Debug, Clone)]
pub struct PhotometricRenderer {
    pub(crate) sensor: SensorConfig,
    /// Background, RGB in 0–255, row-major.
    pub(crate) background: Vec<[f32; 3]>,
    /// Shading of the undeformed gel.
    pub(crate) flat: Vec<[f32; 3]>,
    /// Vignetting per pixel.
    pub(crate) vignette: Vec<f32>,
    pub(crate) gain: f32,
    pub(crate) shadows: Option<ShadowSettings>,
}

impl PhotometricRenderer {
    /// Prepares the flat-gel shading and the background (the sensor's image file if it names
    /// one, otherwise the flat gel under its lights); `shadows` marches cast shadows.
    pub fn new(
        sensor: &SensorConfig,
        shadows: Option<ShadowSettings>,
    ) -> Result<PhotometricRenderer, OpticsError> {
        let grid = sensor.grid();
        let zeros = vec![0.0; grid.len()];
        let flat_surface = Surface {
            grid,
            ux_mm: &zeros,
            uy_mm: &zeros,
            uz_mm: &zeros,
        };
        let flat = shade(sensor, &flat_surface, None);
        let brightest = flat
            .iter()
            .flat_map(|c| c.iter().copied())
            .fold(f32::MIN_POSITIVE, f32::max);
        let gain = (PEAK - AMBIENT) / brightest;
        let vignette: Vec<f32> = (0..grid.len())
            .map(|c| vignetting(sensor, c % grid.nx, c / grid.nx) as f32)
            .collect();
        let background = match &sensor.background {
            Some(path) => load_background(path, sensor)?,
            None => flat
                .iter()
                .zip(&vignette)
                .map(|(c, v)| c.map(|s| v * (AMBIENT + gain * s)))
                .collect(),
        };
        Ok(PhotometricRenderer {
            sensor: sensor.clone(),
            background,
            flat,
            vignette,
            gain,
            shadows,
        })
    }

    /// The no-contact image.
    pub fn background(&self) -> RgbImage {
        to_image(&self.sensor, &self.background)
    }

    /// The image of a deformed surface.
    pub fn render(&self, surface: &Surface) -> RgbImage {
        to_image(&self.sensor, &self.render_linear(surface))
    }

    /// The image of a deformed surface before rounding (RGB, 0–255 scale).
    pub fn render_linear(&self, surface: &Surface) -> Vec<[f32; 3]> {
        let visible = self
            .shadows
            .map(|s| visibilities(surface.uz_mm, surface.grid, &self.sensor.lights, s));
        let lit = shade(&self.sensor, surface, visible.as_deref());
        lit.par_iter()
            .zip(&self.flat)
            .zip(&self.background)
            .zip(&self.vignette)
            .map(|(((s, f), b), v)| std::array::from_fn(|c| b[c] + self.gain * v * (s[c] - f[c])))
            .collect()
    }
}

/// Relative illumination of pixel (i, j) through the camera lens, the cos⁴ law
/// V = cos⁴θ = (1 + (r/f)²)⁻², with r the pixel's distance from the image centre and
/// f = (H/2)/tan(fov/2) the focal length, both in pixels. 1 everywhere without a field of view.
pub fn vignetting(sensor: &SensorConfig, i: usize, j: usize) -> f64 {
    let Some(fov_deg) = sensor.camera_vfov_deg else {
        return 1.0;
    };
    let f_px = sensor.height_px as f64 / 2.0 / (fov_deg.to_radians() / 2.0).tan();
    let x = i as f64 + 0.5 - sensor.width_px as f64 / 2.0;
    let y = j as f64 + 0.5 - sensor.height_px as f64 / 2.0;
    let tan2 = (x * x + y * y) / (f_px * f_px);
    1.0 / ((1.0 + tan2) * (1.0 + tan2))
}

/// The camera's position (mm): on the optical axis at the distance where the gel's view fills
/// the field of view, or `None` (orthographic) without one.
pub(crate) fn camera_mm(sensor: &SensorConfig) -> Option<[f64; 3]> {
    let fov = sensor.camera_vfov_deg?;
    let half_view_mm = sensor.height_px as f64 * sensor.mm_per_px / 2.0;
    Some([0.0, 0.0, -half_view_mm / (fov.to_radians() / 2.0).tan()])
}

/// Radiance towards the camera of a surface point `p` (mm) with unit normal `n` (facing the
/// camera) under one light, per unit light colour: I·[max(n·l̂, 0) + k_s·max(n·ĥ, 0)^s]·d₀²/|L − P|²,
/// with l̂ toward the light, v̂ toward the camera, ĥ = (l̂ + v̂)/|l̂ + v̂| (Blinn–Phong; the
/// specular lobe only where the light reaches, n·l̂ > 0).
pub fn radiance(
    n: [f64; 3],
    p: [f64; 3],
    view: [f64; 3],
    light: &Light,
    sensor: &SensorConfig,
) -> f64 {
    let l = sub(light.position_mm, p);
    let d2 = dot(l, l);
    let l = scale(l, 1.0 / d2.sqrt());
    let cos = dot(n, l);
    if cos <= 0.0 {
        return 0.0;
    }
    let specular = if sensor.specular > 0.0 {
        let h = add(l, view);
        let h = scale(h, 1.0 / dot(h, h).sqrt());
        sensor.specular * dot(n, h).max(0.0).powf(sensor.shininess)
    } else {
        0.0
    };
    light.intensity * (cos + specular) * D0_MM2 / d2
}

/// Unit vector from `p` toward the camera (straight down the axis for an orthographic one).
fn view_direction(camera: Option<[f64; 3]>, p: [f64; 3]) -> [f64; 3] {
    match camera {
        Some(cam) => {
            let v = sub(cam, p);
            scale(v, 1.0 / dot(v, v).sqrt())
        }
        None => [0.0, 0.0, -1.0],
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

fn scale(a: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Radiance per pixel and colour channel, Σ_l c_l·v_l·[`radiance`], with v_l the fraction of
/// light l reaching the pixel (`visible`, `lights.len()` per pixel; all 1 when `None`).
fn shade(sensor: &SensorConfig, surface: &Surface, visible: Option<&[f64]>) -> Vec<[f32; 3]> {
    let grid = surface.grid;
    let uz = surface.uz_mm;
    let camera = camera_mm(sensor);
    let lights = &sensor.lights;
    (0..grid.len())
        .into_par_iter()
        .map(|c| {
            let (i, j) = (c % grid.nx, c / grid.nx);
            let [dzdx, dzdy] = crate::calibrated::gradient(uz, grid, i, j);
            // Normal of z = uz(x, y) facing the camera (−z).
            let norm = (dzdx * dzdx + dzdy * dzdy + 1.0).sqrt();
            let n = [dzdx / norm, dzdy / norm, -1.0 / norm];
            let p = [
                grid.x_mm(i) + surface.ux_mm[c],
                grid.y_mm(j) + surface.uy_mm[c],
                uz[c],
            ];
            let view = view_direction(camera, p);
            let mut rgb = [0.0f32; 3];
            for (k, light) in lights.iter().enumerate() {
                let shadow = visible.map_or(1.0, |v| v[c * lights.len() + k]);
                let e = shadow * radiance(n, p, view, light, sensor);
                for (out, col) in rgb.iter_mut().zip(light.color) {
                    *out += (col * e) as f32;
                }
            }
            rgb
        })
        .collect()
}

/// Shadow settings of a sensor: its LEDs' radius, `steps` samples per ray.
pub fn shadow_settings(sensor: &SensorConfig, steps: u32) -> ShadowSettings {
    ShadowSettings {
        steps,
        led_radius_mm: sensor.led_radius_mm,
        ..ShadowSettings::default()
    }
}

/// Each light's share of every pixel's flat-gel radiance per channel (`lights.len()` triples
/// per pixel, summing to 1 per channel where any light reaches): how much of the pixel's colour
/// a shadow of that light removes.
pub fn light_shares(sensor: &SensorConfig) -> Vec<[f32; 3]> {
    let grid = sensor.grid();
    let camera = camera_mm(sensor);
    let lights = &sensor.lights;
    (0..grid.len())
        .into_par_iter()
        .flat_map_iter(|c| {
            let p = [grid.x_mm(c % grid.nx), grid.y_mm(c / grid.nx), 0.0];
            let view = view_direction(camera, p);
            let per: Vec<[f64; 3]> = lights
                .iter()
                .map(|l| {
                    let e = radiance([0.0, 0.0, -1.0], p, view, l, sensor);
                    l.color.map(|col| col * e)
                })
                .collect();
            let total: [f64; 3] = std::array::from_fn(|ch| per.iter().map(|v| v[ch]).sum());
            per.into_iter().map(move |v| {
                std::array::from_fn(|ch| {
                    if total[ch] > 0.0 {
                        (v[ch] / total[ch]) as f32
                    } else {
                        0.0
                    }
                })
            })
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

#[cfg(test)]
mod tests {
    use super::*;

    fn sensor() -> SensorConfig {
        let mut s = SensorConfig::preset("digit").unwrap();
        s.width_px = 64;
        s.height_px = 48;
        s.mm_per_px = 0.1;
        s
    }

    /// cos⁴ at the corner of a known field of view, 1 at the centre.
    #[test]
    fn vignetting_follows_the_cos4_law() {
        let mut s = sensor();
        s.camera_vfov_deg = Some(60.0);
        // A pixel half the image height below the centre sits at the field's edge: θ = 30°.
        s.height_px = 48;
        let edge = vignetting(&s, 31, 47);
        let x = 0.5f64;
        let y = 23.5f64;
        let theta = ((x * x + y * y).sqrt() / 24.0 * 30f64.to_radians().tan()).atan();
        assert!((edge - theta.cos().powi(4)).abs() < 1e-12);
        assert!(edge < 0.6 && edge > 0.5, "cos⁴ 30° ≈ 0.5625, got {edge}");
        s.camera_vfov_deg = None;
        assert_eq!(vignetting(&s, 0, 0), 1.0);
    }

    /// Lambert's law alone: a light straight above a flat patch at distance d₀ gives its
    /// intensity; tilting the normal by θ away from it gives cos θ.
    #[test]
    fn radiance_is_lambertian_without_specular() {
        let s = sensor();
        let light = Light {
            position_mm: [0.0, 0.0, -10.0],
            color: [1.0; 3],
            intensity: 0.7,
        };
        let up = radiance([0.0, 0.0, -1.0], [0.0; 3], [0.0, 0.0, -1.0], &light, &s);
        assert!((up - 0.7).abs() < 1e-12);
        let t = 0.4f64;
        let tilted = radiance(
            [t.sin(), 0.0, -t.cos()],
            [0.0; 3],
            [0.0, 0.0, -1.0],
            &light,
            &s,
        );
        assert!((tilted - 0.7 * t.cos()).abs() < 1e-12);
        // Facing away: no light.
        assert_eq!(
            radiance([0.0, 0.0, 1.0], [0.0; 3], [0.0, 0.0, -1.0], &light, &s),
            0.0
        );
    }

    /// The specular lobe peaks at the mirror direction: light and camera both on the axis.
    #[test]
    fn specular_lobe_peaks_at_the_mirror_direction() {
        let mut s = sensor();
        s.specular = 0.5;
        s.shininess = 10.0;
        let light = Light {
            position_mm: [0.0, 0.0, -10.0],
            color: [1.0; 3],
            intensity: 1.0,
        };
        let mirror = radiance([0.0, 0.0, -1.0], [0.0; 3], [0.0, 0.0, -1.0], &light, &s);
        assert!((mirror - 1.5).abs() < 1e-12);
        let t = 0.2f64;
        let off = radiance(
            [t.sin(), 0.0, -t.cos()],
            [0.0; 3],
            [0.0, 0.0, -1.0],
            &light,
            &s,
        );
        // l̂ = v̂ = −z so ĥ = −z and n·ĥ = cos t.
        assert!((off - (t.cos() + 0.5 * t.cos().powf(10.0))).abs() < 1e-12);
    }

    #[test]
    fn light_shares_sum_to_one_per_channel() {
        let s = sensor();
        let shares = light_shares(&s);
        let n = s.lights.len();
        for px in shares.chunks(n) {
            for ch in 0..3 {
                let total: f32 = px.iter().map(|v| v[ch]).sum();
                assert!((total - 1.0).abs() < 1e-5);
            }
        }
    }

    /// Shadows only darken, and a flat gel renders as its background with or without them.
    #[test]
    fn shadows_only_darken_and_vanish_on_a_flat_gel() {
        let s = sensor();
        let grid = s.grid();
        let zeros = vec![0.0; grid.len()];
        let bump: Vec<f64> = (0..grid.len())
            .map(|c| {
                let (x, y) = (grid.x_mm(c % grid.nx), grid.y_mm(c / grid.nx));
                -0.8 * (-(x * x + y * y) / 0.5).exp()
            })
            .collect();
        let plain = PhotometricRenderer::new(&s, None).unwrap();
        let shadowed = PhotometricRenderer::new(&s, Some(shadow_settings(&s, 32))).unwrap();
        let flat = Surface {
            grid,
            ux_mm: &zeros,
            uy_mm: &zeros,
            uz_mm: &zeros,
        };
        assert_eq!(shadowed.render(&flat), plain.background());
        let pressed = Surface {
            uz_mm: &bump,
            ..flat
        };
        let a = plain.render_linear(&pressed);
        let b = shadowed.render_linear(&pressed);
        let mut darker = 0;
        for (p, q) in a.iter().zip(&b) {
            for ch in 0..3 {
                assert!(q[ch] <= p[ch] + 1e-4);
                darker += usize::from(q[ch] < p[ch] - 1.0);
            }
        }
        assert!(darker > 10, "the bump shadows some pixels ({darker})");
    }
}
