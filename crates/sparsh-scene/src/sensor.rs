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
    /// Preset name (`digit`, `gelsight2017`, `gelsight_mini`).
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
}

/// The sensor presets shipped with the project.
pub const PRESETS: [(&str, &str); 3] = [
    ("digit", include_str!("../../../assets/sensors/digit.toml")),
    (
        "gelsight2017",
        include_str!("../../../assets/sensors/gelsight2017.toml"),
    ),
    (
        "gelsight_mini",
        include_str!("../../../assets/sensors/gelsight_mini.toml"),
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
