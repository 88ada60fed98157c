//! `[optics]`: which image-formation model renders the scene, and its imperfections.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::SceneError;

/// The image-formation model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OpticsModel {
    /// Shading under the sensor's lights.
    #[default]
    Photometric,
    /// A slope-to-colour map fitted on real images (`sparsh calibrate`).
    Calibrated,
}

/// `[optics]`: the model, shadows and seeded imperfections (all off by default).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OpticsSpec {
    /// Image-formation model.
    #[serde(default)]
    pub model: OpticsModel,
    /// Calibration directory (`map.json`, `background.png`) of the calibrated model, relative
    /// to the scene file; resolved to a full path on load.
    #[serde(default)]
    pub calibration: Option<PathBuf>,
    /// Cast shadows of the sensor's lights (off by default: they cost several times the
    /// shading; see `sparsh bench-optics`).
    #[serde(default)]
    pub shadows: bool,
    /// Height-field samples per shadow ray.
    #[serde(default = "default_steps")]
    pub shadow_steps: u32,
    /// Standard deviation of the camera's per-pixel Gaussian noise (0–255 units), drawn anew
    /// each frame.
    #[serde(default)]
    pub noise_std: f64,
    /// Exposure: a gain on the whole image.
    #[serde(default = "unit")]
    pub exposure: f64,
    /// Relative amplitude of a smooth multiplicative variation over the background (uneven
    /// coating and lighting of a sensor instance).
    #[serde(default)]
    pub background_variation: f64,
}

fn default_steps() -> u32 {
    32
}

fn unit() -> f64 {
    1.0
}

impl Default for OpticsSpec {
    fn default() -> Self {
        OpticsSpec {
            model: OpticsModel::default(),
            calibration: None,
            shadows: false,
            shadow_steps: default_steps(),
            noise_std: 0.0,
            exposure: 1.0,
            background_variation: 0.0,
        }
    }
}

impl OpticsSpec {
    /// Checks every value against a sensor with `lights` lights and resolves the calibration
    /// path against `path`'s folder; errors name the key under `table`.
    pub(crate) fn resolve(
        &mut self,
        path: &Path,
        table: &str,
        lights: usize,
    ) -> Result<(), SceneError> {
        let bad = |field: &str, msg: String| {
            Err(SceneError::invalid(path, format!("{table}.{field}"), msg))
        };
        let dir = path.parent().unwrap_or(Path::new("."));
        match (self.model, &self.calibration) {
            (OpticsModel::Calibrated, None) => {
                return bad(
                    "calibration",
                    "the calibrated model needs a calibration directory".into(),
                );
            }
            (_, Some(c)) => {
                let full = dir.join(c);
                if !full.join("map.json").is_file() {
                    return bad(
                        "calibration",
                        format!("{} has no map.json (see sparsh calibrate)", full.display()),
                    );
                }
                self.calibration = Some(full);
            }
            _ => {}
        }
        if self.shadows && lights == 0 {
            return bad(
                "shadows",
                "the sensor has no lights to cast shadows from".into(),
            );
        }
        if !(1..=1024).contains(&self.shadow_steps) {
            return bad(
                "shadow_steps",
                format!("must be in 1..=1024, got {}", self.shadow_steps),
            );
        }
        for (key, v) in [
            ("noise_std", self.noise_std),
            ("exposure", self.exposure),
            ("background_variation", self.background_variation),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(key, format!("must be ≥ 0, got {v}"));
            }
        }
        if self.background_variation >= 1.0 {
            return bad(
                "background_variation",
                format!("must be below 1, got {}", self.background_variation),
            );
        }
        Ok(())
    }
}
