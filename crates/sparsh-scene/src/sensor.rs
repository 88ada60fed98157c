//! Sensor presets (`assets/sensors/*.toml`, compiled in) and their per-scene overrides.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::{Grid, SceneError};

/// A point light in the camera frame (see [`crate::grid`] for the axes).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Light {
    /// Position (mm); LEDs sit on the camera side of the gel, so z < 0.
    pub position_mm: [f64; 3],
    /// Linear RGB colour of the light, each channel in [0, 1].
    pub color: [f64; 3],
    /// Relative intensity (1 = nominal).
    #[serde(default = "one")]
    pub intensity: f64,
}

fn one() -> f64 {
    1.0
}

/// A fully resolved sensor: camera, gel view and lights.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorConfig {
    /// Preset name (one of [`PRESETS`]).
    pub name: String,
    /// Image width (pixels).
    pub width_px: usize,
    /// Image height (pixels).
    pub height_px: usize,
    /// Size of one pixel on the gel (mm).
    pub mm_per_px: f64,
    /// Frame rate (frames per second).
    pub fps: f64,
    /// The sensor's lights.
    pub lights: Vec<Light>,
    /// Background image (no contact); `None` renders the flat gel under the lights.
    #[serde(default)]
    pub background: Option<PathBuf>,
    /// The camera's vertical field of view (degrees): sets the vignetting (cos⁴ law) and the
    /// view direction of the specular term; `None` is an orthographic camera without vignetting.
    #[serde(default)]
    pub camera_vfov_deg: Option<f64>,
    /// Radius of each LED's emitting disc (mm): the width of the shadows' penumbra.
    #[serde(default = "default_led_radius_mm")]
    pub led_radius_mm: f64,
    /// Specular weight of the gel's coating (Blinn–Phong lobe against the Lambertian term; 0 is
    /// matte).
    #[serde(default)]
    pub specular: f64,
    /// Blinn–Phong exponent of the specular lobe.
    #[serde(default = "default_shininess")]
    pub shininess: f64,
    /// Dots printed on the gel; `None` for a markerless gel.
    #[serde(default)]
    pub markers: Option<MarkerGrid>,
}

fn default_led_radius_mm() -> f64 {
    1.0
}

fn default_shininess() -> f64 {
    20.0
}

/// A rectangular grid of dark dots printed on the gel, centred on the camera's view.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MarkerGrid {
    /// Dots along x (image columns).
    pub cols: usize,
    /// Dots along y (image rows).
    pub rows: usize,
    /// Centre-to-centre spacing (mm).
    pub pitch_mm: f64,
    /// Dot radius (mm).
    pub radius_mm: f64,
    /// Fraction of the light a dot absorbs (0 transparent, 1 black).
    #[serde(default = "default_marker_darkness")]
    pub darkness: f64,
}

fn default_marker_darkness() -> f64 {
    0.85
}

impl MarkerGrid {
    /// Printed centre (mm, camera frame, undeformed gel) of dot (`col`, `row`).
    pub fn centre_mm(&self, col: usize, row: usize) -> [f64; 2] {
        [
            (col as f64 - (self.cols as f64 - 1.0) / 2.0) * self.pitch_mm,
            (row as f64 - (self.rows as f64 - 1.0) / 2.0) * self.pitch_mm,
        ]
    }

    /// Printed centres of every dot, row by row.
    pub fn centres_mm(&self) -> Vec<[f64; 2]> {
        (0..self.rows)
            .flat_map(|r| (0..self.cols).map(move |c| self.centre_mm(c, r)))
            .collect()
    }
}

/// The sensor presets shipped with the project.
pub const PRESETS: [(&str, &str); 5] = [
    ("digit", include_str!("../../../assets/sensors/digit.toml")),
    (
        "digit_vga",
        include_str!("../../../assets/sensors/digit_vga.toml"),
    ),
    (
        "gelsight2017",
        include_str!("../../../assets/sensors/gelsight2017.toml"),
    ),
    (
        "gelsight_mini",
        include_str!("../../../assets/sensors/gelsight_mini.toml"),
    ),
    (
        "gelsight_mini_vga",
        include_str!("../../../assets/sensors/gelsight_mini_vga.toml"),
    ),
];

impl SensorConfig {
    /// The named preset.
    pub fn preset(name: &str) -> Option<SensorConfig> {
        PRESETS
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, text)| toml::from_str(text).expect("shipped sensor presets parse"))
    }

    /// The gel grid the sensor images: one cell per pixel.
    pub fn grid(&self) -> Grid {
        Grid {
            nx: self.width_px,
            ny: self.height_px,
            cell_mm: self.mm_per_px,
        }
    }

    /// Checks every value; `path` names the scene file in errors.
    pub(crate) fn validate(&self, path: &Path) -> Result<(), SceneError> {
        let bad = |field: &str, msg: String| Err(SceneError::invalid(path, field, msg));
        if !(1..=8192).contains(&self.width_px) {
            return bad(
                "sensor.width_px",
                format!("must be in 1..=8192, got {}", self.width_px),
            );
        }
        if !(1..=8192).contains(&self.height_px) {
            return bad(
                "sensor.height_px",
                format!("must be in 1..=8192, got {}", self.height_px),
            );
        }
        if !(self.mm_per_px.is_finite() && self.mm_per_px > 0.0) {
            return bad(
                "sensor.mm_per_px",
                format!("must be > 0, got {}", self.mm_per_px),
            );
        }
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return bad("sensor.fps", format!("must be > 0, got {}", self.fps));
        }
        for (k, light) in self.lights.iter().enumerate() {
            let finite = light
                .position_mm
                .iter()
                .chain(&light.color)
                .all(|v| v.is_finite());
            if !finite || light.color.iter().any(|c| !(0.0..=1.0).contains(c)) {
                return bad(
                    &format!("sensor.lights[{k}]"),
                    "position must be finite and colour channels in [0, 1]".into(),
                );
            }
            if !(light.intensity.is_finite() && light.intensity >= 0.0) {
                return bad(
                    &format!("sensor.lights[{k}].intensity"),
                    format!("must be ≥ 0, got {}", light.intensity),
                );
            }
        }
        if let Some(fov) = self.camera_vfov_deg
            && !(fov.is_finite() && fov > 0.0 && fov < 180.0)
        {
            return bad(
                "sensor.camera_vfov_deg",
                format!("must be in (0, 180), got {fov}"),
            );
        }
        if !(self.led_radius_mm.is_finite() && self.led_radius_mm >= 0.0) {
            return bad(
                "sensor.led_radius_mm",
                format!("must be ≥ 0, got {}", self.led_radius_mm),
            );
        }
        if !(self.specular.is_finite() && self.specular >= 0.0) {
            return bad(
                "sensor.specular",
                format!("must be ≥ 0, got {}", self.specular),
            );
        }
        if !(self.shininess.is_finite() && self.shininess >= 1.0) {
            return bad(
                "sensor.shininess",
                format!("must be ≥ 1, got {}", self.shininess),
            );
        }
        if let Some(m) = &self.markers {
            if m.cols == 0 || m.rows == 0 {
                return bad(
                    "sensor.markers",
                    format!("needs at least one dot, got {} × {}", m.cols, m.rows),
                );
            }
            if !(m.pitch_mm.is_finite() && m.radius_mm > 0.0 && 2.0 * m.radius_mm < m.pitch_mm) {
                return bad(
                    "sensor.markers.radius_mm",
                    format!(
                        "must be > 0 and under half the pitch {} mm, got {}",
                        m.pitch_mm, m.radius_mm
                    ),
                );
            }
            if !(0.0..=1.0).contains(&m.darkness) {
                return bad(
                    "sensor.markers.darkness",
                    format!("must be in [0, 1], got {}", m.darkness),
                );
            }
        }
        if let Some(bg) = &self.background
            && !bg.is_file()
        {
            return bad(
                "sensor.background",
                format!("file {} does not exist", bg.display()),
            );
        }
        Ok(())
    }
}
