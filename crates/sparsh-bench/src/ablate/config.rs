//! The ablation description (`ablations/NAME.toml`): the base dataset scene, the real pack and
//! its test frames, the models' training settings and the variants — each a set of overrides of
//! the scene's `[[family]]` tables. Paths are relative to the config file; unknown keys are
//! errors naming the file and the key.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use sparsh_optics::FrameSet;

use super::models::TrainOptions;
use crate::Error;

/// `[probe]`: the attentive probe on a frozen encoder (pretrained and randomly initialised).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProbeConfig {
    /// The encoder's recipe (architecture, input size).
    pub recipe: PathBuf,
    /// Pretrained weights; without them only the random encoders are probed.
    #[serde(default)]
    pub weights: Option<PathBuf>,
    /// Training of the probe.
    pub train: TrainOptions,
}

/// `[real]`: the ceiling — the CNN trained on the pack's own frames, each test frame scored by
/// a model that never saw it.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RealConfig {
    /// Test frames are dealt into this many folds; each fold's model trains on every other
    /// frame of the pack (with its mirror images).
    pub folds: usize,
    /// Training of each fold's CNN.
    pub train: TrainOptions,
    /// A calibration (`sparsh calibrate` directory) whose renders re-fit each scored frame's
    /// circle from its mark (`sim2real --refit`): the row of the marks' own noise, the fitted
    /// circles scored as predictions of the marks.
    #[serde(default)]
    pub marks_calibration: Option<PathBuf>,
}

/// One `[[variant]]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VariantConfig {
    /// Name in tables and charts.
    pub name: String,
    /// Keys of every `[[family]]` table to set: dotted paths (`"optics.model"`) to values.
    #[serde(default)]
    pub set: toml::Table,
    /// Dotted paths to remove (`"randomize.noise_std"`).
    #[serde(default)]
    pub remove: Vec<String>,
    /// Also train the attentive probe on frozen encoders (needs `[probe]`).
    #[serde(default)]
    pub probe: bool,
}

/// The file as written.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct AblationFile {
    scene: PathBuf,
    pack: PathBuf,
    pack_mm_per_px: f64,
    #[serde(default = "odd")]
    test_frames: FrameSet,
    #[serde(default = "three")]
    seeds: usize,
    #[serde(default = "input_size")]
    input_size: [usize; 2],
    #[serde(default = "bootstrap")]
    bootstrap: usize,
    #[serde(default = "validation_share")]
    validation_share: f64,
    #[serde(default)]
    keep_data: bool,
    cnn: TrainOptions,
    #[serde(default)]
    probe: Option<ProbeConfig>,
    real: RealConfig,
    variant: Vec<VariantConfig>,
}

fn odd() -> FrameSet {
    FrameSet::Odd
}
fn three() -> usize {
    3
}
fn input_size() -> [usize; 2] {
    [120, 160]
}
fn bootstrap() -> usize {
    1000
}
fn validation_share() -> f64 {
    0.1
}

/// A loaded ablation: paths resolved against the config's folder.
#[derive(Debug, Clone)]
pub struct AblationConfig {
    /// The config file.
    pub path: PathBuf,
    /// Its text (copied into the output).
    pub source: String,
    /// The base dataset scene (a `[[family]]` file).
    pub scene: PathBuf,
    /// The real Taxim pack.
    pub pack: PathBuf,
    /// The pack's pixel pitch (mm): synthetic circles are mapped onto its pixels.
    pub pack_mm_per_px: f64,
    /// The pack's frames scored.
    pub test_frames: FrameSet,
    /// Training seeds per learned row.
    pub seeds: usize,
    /// Model input `[height, width]`: frames are box-filtered to it.
    pub input_size: [usize; 2],
    /// Bootstrap resamples of the intervals.
    pub bootstrap: usize,
    /// Share of the synthetic sequences held out to choose the epoch.
    pub validation_share: f64,
    /// Keep each variant's generated dataset after scoring it.
    pub keep_data: bool,
    /// The CNN's training.
    pub cnn: TrainOptions,
    /// The frozen-encoder probe.
    pub probe: Option<ProbeConfig>,
    /// The real-data ceiling.
    pub real: RealConfig,
    /// The variants, in order.
    pub variants: Vec<VariantConfig>,
}

fn check_train(path: &Path, field: &str, t: &TrainOptions) -> Result<(), Error> {
    if t.epochs == 0 || t.batch_size == 0 || !(t.lr > 0.0 && t.lr.is_finite()) {
        return Err(Error::config(
            path,
            field,
            format!(
                "epochs and batch_size must be ≥ 1 and lr > 0, got {} / {} / {}",
                t.epochs, t.batch_size, t.lr
            ),
        ));
    }
    Ok(())
}

impl AblationConfig {
    /// Reads and checks `path`.
    pub fn load(path: &Path) -> Result<Self, Error> {
        let source = std::fs::read_to_string(path).map_err(|e| Error::file(path, e))?;
        let file: AblationFile = toml::from_str(&source)
            .map_err(|e| Error::file(path, e.to_string().lines().collect::<Vec<_>>().join(" ")))?;
        let dir = path.parent().unwrap_or(Path::new("."));
        let bad = |field: &str, msg: String| Err(Error::config(path, field, msg));
        if !(file.pack_mm_per_px > 0.0 && file.pack_mm_per_px.is_finite()) {
            return bad(
                "pack_mm_per_px",
                format!("must be positive, got {}", file.pack_mm_per_px),
            );
        }
        if file.seeds == 0 {
            return bad("seeds", "must be at least 1".into());
        }
        if file.input_size.contains(&0) {
            return bad("input_size", "must be positive".into());
        }
        if !(0.0..0.9).contains(&file.validation_share) {
            return bad(
                "validation_share",
                format!("must be in [0, 0.9), got {}", file.validation_share),
            );
        }
        if file.real.folds < 2 {
            return bad("real.folds", "must be at least 2".into());
        }
        check_train(path, "cnn", &file.cnn)?;
        check_train(path, "real.train", &file.real.train)?;
        if let Some(p) = &file.probe {
            check_train(path, "probe.train", &p.train)?;
        }
        if file.variant.is_empty() {
            return bad("variant", "at least one [[variant]] is needed".into());
        }
        let mut slugs = Vec::new();
        for (i, v) in file.variant.iter().enumerate() {
            if v.probe && file.probe.is_none() {
                return bad(
                    &format!("variant[{i}].probe"),
                    "needs a [probe] section".into(),
                );
            }
            let s = slug(&v.name);
            if s.is_empty() || slugs.contains(&s) {
                return bad(
                    &format!("variant[{i}].name"),
                    format!(
                        "`{}` is empty or not distinct from another variant's",
                        v.name
                    ),
                );
            }
            slugs.push(s);
        }
        let probe = file.probe.map(|p| ProbeConfig {
            recipe: dir.join(p.recipe),
            weights: p.weights.map(|w| dir.join(w)),
            train: p.train,
        });
        Ok(AblationConfig {
            path: path.to_path_buf(),
            source,
            scene: dir.join(file.scene),
            pack: dir.join(file.pack),
            pack_mm_per_px: file.pack_mm_per_px,
            test_frames: file.test_frames,
            seeds: file.seeds,
            input_size: file.input_size,
            bootstrap: file.bootstrap,
            validation_share: file.validation_share,
            keep_data: file.keep_data,
            cnn: file.cnn,
            probe,
            real: RealConfig {
                marks_calibration: file.real.marks_calibration.map(|c| dir.join(c)),
                ..file.real
            },
            variants: file.variant,
        })
    }
}

/// A variant's directory name: lower-case letters and digits, other runs of characters as `_`.
pub fn slug(name: &str) -> String {
    let mut s = String::new();
    for c in name.chars() {
        if c.is_ascii_alphanumeric() {
            s.push(c.to_ascii_lowercase());
        } else if !s.ends_with('_') {
            s.push('_');
        }
    }
    s.trim_matches('_').to_string()
}

/// Keys of the scene holding paths relative to the scene file.
const PATH_KEYS: [&str; 2] = ["optics.calibration", "sensor.background"];

/// The base scene's text with `variant`'s overrides applied to every `[[family]]` and its
/// relative paths made absolute (the variant's scene is written elsewhere).
pub fn variant_scene(
    config: &AblationConfig,
    variant: &VariantConfig,
    sequences: Option<usize>,
) -> Result<String, Error> {
    let text = std::fs::read_to_string(&config.scene).map_err(|e| Error::file(&config.scene, e))?;
    let mut doc: toml::Table = toml::from_str(&text).map_err(|e| {
        Error::file(
            &config.scene,
            e.to_string().lines().collect::<Vec<_>>().join(" "),
        )
    })?;
    let dir = config.scene.parent().unwrap_or(Path::new("."));
    let Some(toml::Value::Array(families)) = doc.get_mut("family") else {
        return Err(Error::config(
            &config.scene,
            "family",
            "the base scene must be a dataset file with [[family]] tables",
        ));
    };
    let field = |i: usize, key: &str| format!("variant `{}`: {key} (family {i})", variant.name);
    for (i, family) in families.iter_mut().enumerate() {
        let toml::Value::Table(family) = family else {
            continue;
        };
        for (key, value) in &variant.set {
            set_path(family, key, value.clone())
                .map_err(|m| Error::config(&config.path, field(i, key), m))?;
        }
        for key in &variant.remove {
            remove_path(family, key).map_err(|m| Error::config(&config.path, field(i, key), m))?;
        }
        if let Some(n) = sequences {
            family.insert("sequences".into(), toml::Value::Integer(n as i64));
        }
        for key in PATH_KEYS {
            absolutize(family, key, dir);
        }
        if let Some(toml::Value::Array(indenters)) = family.get_mut("indenters") {
            for ind in indenters.iter_mut() {
                if let toml::Value::Table(t) = ind {
                    absolutize(t, "mesh", dir);
                }
            }
        }
    }
    toml::to_string(&doc).map_err(|e| Error::file(&config.scene, e))
}

fn set_path(table: &mut toml::Table, key: &str, value: toml::Value) -> Result<(), String> {
    let mut parts: Vec<&str> = key.split('.').collect();
    let last = parts.pop().ok_or("empty key")?;
    let mut t = table;
    for p in parts {
        let entry = t
            .entry(p.to_string())
            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
        t = entry
            .as_table_mut()
            .ok_or_else(|| format!("`{p}` is not a table"))?;
    }
    t.insert(last.to_string(), value);
    Ok(())
}

fn remove_path(table: &mut toml::Table, key: &str) -> Result<(), String> {
    let mut parts: Vec<&str> = key.split('.').collect();
    let last = parts.pop().ok_or("empty key")?;
    let mut t = table;
    for p in parts {
        t = t
            .get_mut(p)
            .and_then(|v| v.as_table_mut())
            .ok_or_else(|| format!("the base scene has no table `{p}` to remove from"))?;
    }
    t.remove(last)
        .map(|_| ())
        .ok_or_else(|| "the base scene has no such key to remove".into())
}

fn absolutize(table: &mut toml::Table, key: &str, dir: &Path) {
    let mut parts: Vec<&str> = key.split('.').collect();
    let Some(last) = parts.pop() else { return };
    let mut t = table;
    for p in parts {
        match t.get_mut(p).and_then(|v| v.as_table_mut()) {
            Some(next) => t = next,
            None => return,
        }
    }
    if let Some(toml::Value::String(s)) = t.get_mut(last) {
        let p = Path::new(s.as_str());
        if p.is_relative() {
            *s = absolute(&dir.join(p)).display().to_string();
        }
    }
}

/// `p` made absolute against the working directory (not resolved through links).
pub fn absolute(p: &Path) -> PathBuf {
    std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slugs_are_plain() {
        assert_eq!(
            slug("Photometric optics (no map)"),
            "photometric_optics_no_map"
        );
        assert_eq!(slug("--"), "");
    }

    #[test]
    fn overrides_set_remove_and_fail_on_what_is_not_there() {
        let mut t: toml::Table =
            toml::from_str("solver = \"halfspace\"\n[optics]\nmodel = \"calibrated\"\n").unwrap();
        set_path(&mut t, "optics.shadows", toml::Value::Boolean(true)).unwrap();
        set_path(&mut t, "randomize.noise_std", toml::Value::Float(1.0)).unwrap();
        remove_path(&mut t, "optics.model").unwrap();
        assert_eq!(
            t["optics"].get("shadows"),
            Some(&toml::Value::Boolean(true))
        );
        assert!(t["optics"].get("model").is_none());
        assert_eq!(t["randomize"]["noise_std"].as_float(), Some(1.0));
        assert!(remove_path(&mut t, "gel.friction").is_err());
        assert!(set_path(&mut t, "solver.kind", toml::Value::Integer(1)).is_err());
    }
}
