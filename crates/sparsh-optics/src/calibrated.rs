//! Calibrated model: a per-sensor map from surface gradient and pixel position to colour change,
//! fitted on real images of a ball pressed into the gel, applied over the sensor's background.
//!
//! The map: with the unit normal's lateral components (nx, ny) = (∂u_z/∂x, ∂u_z/∂y)/√(1 + |∇u_z|²)
//! (bounded in the unit disc, so steep slopes stay on the table) and the pixel's normalised
//! position (x, y) ∈ [−½, ½]², the colour change is ΔI = T₀(nx, ny) + x·T_x(nx, ny) + y·T_y(nx, ny),
//! each T a bilinearly interpolated table on an N × N grid over [−1, 1]². Taxim (Si & Yuan, RA-L
//! 2022) also maps gradient and position to colour, with per-bin polynomials; the bilinear tables
//! keep the image smooth across bins. The tables are fitted by linear least squares with a
//! second-difference smoothness penalty (Tikhonov), which also fills nodes no pixel visited.

use std::path::Path;

use image::RgbImage;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sparsh_scene::{Grid, Light, SensorConfig};

use crate::Surface;
use crate::photometric::{light_shares, shadow_settings};
use crate::shadow::{ShadowSettings, visibilities};

/// Position bases of the map: 1, x, y.
const BASES: usize = 3;
/// Format tag of `map.json`.
const FORMAT: &str = "sparsh-calibrated-map/1";

/// The fitted gradient(+position) → colour-change map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ColourMap {
    /// Format tag.
    pub format: String,
    /// Table nodes per normal component (N).
    pub nodes: usize,
    /// Colour change (RGB, 0–255 units) at each node: index `(b·N + v)·N + u` for basis b
    /// (1, x, y), node u along nx and v along ny.
    pub coef: Vec<[f32; 3]>,
}

/// Bilinear node indices and weights of a normal (nx, ny).
fn nodes_of(nodes: usize, n: [f64; 2]) -> ([usize; 4], [f64; 4]) {
    let span = (nodes - 1) as f64;
    let fu = ((n[0] + 1.0) / 2.0 * span).clamp(0.0, span);
    let fv = ((n[1] + 1.0) / 2.0 * span).clamp(0.0, span);
    let iu = (fu.floor() as usize).min(nodes - 2);
    let iv = (fv.floor() as usize).min(nodes - 2);
    let (tu, tv) = (fu - iu as f64, fv - iv as f64);
    let k = iv * nodes + iu;
    (
        [k, k + 1, k + nodes, k + nodes + 1],
        [
            (1.0 - tu) * (1.0 - tv),
            tu * (1.0 - tv),
            (1.0 - tu) * tv,
            tu * tv,
        ],
    )
}

/// Features of cell `c` of a surface: the normal's lateral components and the position bases.
fn feature(surface: &Surface, c: usize) -> ([f64; 2], [f64; BASES]) {
    let grid = surface.grid;
    let (nx, ny) = (grid.nx, grid.ny);
    let (i, j) = (c % nx, c / nx);
    let [gx, gy] = gradient(surface.uz_mm, grid, i, j);
    let norm = (1.0 + gx * gx + gy * gy).sqrt();
    let x = (i as f64 + 0.5) / nx as f64 - 0.5;
    let y = (j as f64 + 0.5) / ny as f64 - 0.5;
    ([gx / norm, gy / norm], [1.0, x, y])
}

/// Central differences inside, one-sided at the border (like `numpy.gradient`).
pub(crate) fn gradient(uz: &[f64], grid: Grid, i: usize, j: usize) -> [f64; 2] {
    let (nx, ny) = (grid.nx, grid.ny);
    let at = |ii: usize, jj: usize| uz[jj * nx + ii];
    let (il, ir) = (i.saturating_sub(1), (i + 1).min(nx - 1));
    let (ju, jd) = (j.saturating_sub(1), (j + 1).min(ny - 1));
    [
        (at(ir, j) - at(il, j)) / ((ir - il).max(1) as f64 * grid.cell_mm),
        (at(i, jd) - at(i, ju)) / ((jd - ju).max(1) as f64 * grid.cell_mm),
    ]
}

impl ColourMap {
    /// Colour change of every pixel of a surface.
    pub fn delta(&self, surface: &Surface) -> Vec<[f32; 3]> {
        let plane = self.nodes * self.nodes;
        (0..surface.grid.len())
            .into_par_iter()
            .map(|c| {
                let (n, basis) = feature(surface, c);
                let (idx, w) = nodes_of(self.nodes, n);
                let mut out = [0.0f64; 3];
                for (b, beta) in basis.iter().enumerate() {
                    for (k, wk) in idx.iter().zip(w) {
                        let c = self.coef[b * plane + k];
                        for ch in 0..3 {
                            out[ch] += beta * wk * c[ch] as f64;
                        }
                    }
                }
                out.map(|v| v as f32)
            })
            .collect()
    }
}

/// Least-squares accumulator for a [`ColourMap`]: the normal equations per colour channel.
///
/// Each pixel of a frame is explained as I_ch = s_ch·(bg_ch + ΔI_ch) with a known attenuation
/// s_ch (1 without shadows; 1 − Σ_l w_{l,ch}·(1 − v_l) through them, [`attenuation`]). Since ΔI_ch
/// = φ·c_ch is linear in the coefficients, the rows are s_ch·φ and the targets
/// t_ch = I_ch − s_ch·bg_ch: the fit minimises the image-space error
/// Σ (s_ch·(bg_ch + φ·c_ch) − I_ch)², i.e. ΔI fitted to I/s − bg with weights s².
#[derive(Debug, Clone)]
pub struct MapFitter {
    nodes: usize,
    /// Σ s_ch²·φφᵀ per channel (dense, K × K with K = BASES·N²).
    normal: [Vec<f64>; 3],
    /// Σ s_ch·φ·t_ch per channel.
    rhs: Vec<[f64; 3]>,
    /// Σ t_ch² per channel (for [`MapFitter::residual`]).
    target_sq: [f64; 3],
    samples: usize,
}

impl MapFitter {
    /// An empty fit with `nodes` table nodes per normal component (at least 3).
    pub fn new(nodes: usize) -> MapFitter {
        let nodes = nodes.max(3);
        let k = BASES * nodes * nodes;
        MapFitter {
            nodes,
            normal: std::array::from_fn(|_| vec![0.0; k * k]),
            rhs: vec![[0.0; 3]; k],
            target_sq: [0.0; 3],
            samples: 0,
        }
    }

    #[allow(clippy::needless_range_loop)] // three channels side by side read clearer indexed
    /// Adds the pixels `cells` (row-major cell indices) of one frame, the p-th explained as
    /// I_ch = s_ch·(background_ch + ΔI_ch(surface)) with s = `attenuation(p)` (see the type).
    pub fn add_attenuated(
        &mut self,
        surface: &Surface,
        real: &RgbImage,
        background: &[[f32; 3]],
        cells: &[usize],
        attenuation: impl Fn(usize) -> [f64; 3],
    ) {
        let k_total = BASES * self.nodes * self.nodes;
        let plane = self.nodes * self.nodes;
        let px = real.as_raw();
        for (p, &c) in cells.iter().enumerate() {
            let (n, basis) = feature(surface, c);
            let (idx, w) = nodes_of(self.nodes, n);
            let mut cols = [0usize; 12];
            let mut vals = [0.0f64; 12];
            for b in 0..BASES {
                for q in 0..4 {
                    cols[b * 4 + q] = b * plane + idx[q];
                    vals[b * 4 + q] = basis[b] * w[q];
                }
            }
            let s = attenuation(p);
            for ch in 0..3 {
                let target = px[c * 3 + ch] as f64 - s[ch] * background[c][ch] as f64;
                let s2 = s[ch] * s[ch];
                let normal = &mut self.normal[ch];
                for a in 0..12 {
                    let row = cols[a] * k_total;
                    let va = s2 * vals[a];
                    for b in 0..12 {
                        normal[row + cols[b]] += va * vals[b];
                    }
                    self.rhs[cols[a]][ch] += s[ch] * vals[a] * target;
                }
                self.target_sq[ch] += target * target;
            }
            self.samples += 1;
        }
    }

    /// Pixels added so far.
    pub fn samples(&self) -> usize {
        self.samples
    }

    /// Adds another fitter's sums (same node count).
    pub fn merge(&mut self, other: &MapFitter) {
        assert_eq!(self.nodes, other.nodes, "fitters differ in table size");
        for (mine, theirs) in self.normal.iter_mut().zip(&other.normal) {
            for (a, b) in mine.iter_mut().zip(theirs) {
                *a += b;
            }
        }
        for (a, b) in self.rhs.iter_mut().zip(&other.rhs) {
            for ch in 0..3 {
                a[ch] += b[ch];
            }
        }
        for ch in 0..3 {
            self.target_sq[ch] += other.target_sq[ch];
        }
        self.samples += other.samples;
    }

    /// The data term of the fit at `map`'s coefficients c, summed over channels:
    /// Σ_ch ‖s_ch·φ·c_ch − t_ch‖² = Σ_ch (Σt² − 2·cᵀΣs·φ·t + cᵀ(Σs²φφᵀ)c), the squared
    /// image-space error over the added pixels (0–255 units², before rounding).
    pub fn residual(&self, map: &ColourMap) -> f64 {
        let k_total = BASES * self.nodes * self.nodes;
        assert_eq!(
            map.coef.len(),
            k_total,
            "map and fitter differ in table size"
        );
        (0..3)
            .map(|ch| {
                let c: Vec<f64> = map.coef.iter().map(|v| v[ch] as f64).collect();
                let quadratic: f64 = self.normal[ch]
                    .par_chunks(k_total)
                    .zip(&c)
                    .map(|(row, ci)| ci * row.iter().zip(&c).map(|(a, cj)| a * cj).sum::<f64>())
                    .collect::<Vec<f64>>()
                    .iter()
                    .sum();
                let linear: f64 = self.rhs.iter().zip(&c).map(|(b, ci)| b[ch] * ci).sum();
                self.target_sq[ch] - 2.0 * linear + quadratic
            })
            .sum()
    }

    /// Solves, per channel, (ΦᵀΦ + λ s DᵀD + 10⁻⁶ s I) c = ΦᵀΔI (rows weighted as in the type's
    /// doc), with D the second differences of each table along both axes (a thin-plate-like
    /// penalty that leaves affine tables free) and s = trace(ΦᵀΦ)/K, which makes λ
    /// (`smoothness`) scale-free.
    pub fn solve(&self, smoothness: f64) -> Result<ColourMap, String> {
        if self.samples == 0 {
            return Err("no pixel to fit the map on".into());
        }
        let n = self.nodes;
        let k_total = BASES * n * n;
        let mut coef = vec![[0.0f32; 3]; k_total];
        for ch in 0..3 {
            let mut a = self.normal[ch].clone();
            let scale = (0..k_total).map(|k| a[k * k_total + k]).sum::<f64>() / k_total as f64;
            let lam = smoothness * scale;
            // Second differences along u and along v: affine tables cost nothing.
            for b in 0..BASES {
                for v in 0..n {
                    for u in 0..n {
                        let k = b * n * n + v * n + u;
                        for step in [1, n] {
                            let interior = if step == 1 {
                                u > 0 && u + 1 < n
                            } else {
                                v > 0 && v + 1 < n
                            };
                            if !interior {
                                continue;
                            }
                            let stencil = [(k - step, 1.0), (k, -2.0), (k + step, 1.0)];
                            for (p, wp) in stencil {
                                for (q, wq) in stencil {
                                    a[p * k_total + q] += lam * wp * wq;
                                }
                            }
                        }
                    }
                }
            }
            for k in 0..k_total {
                a[k * k_total + k] += 1e-6 * scale;
            }
            let b: Vec<f64> = self.rhs.iter().map(|r| r[ch]).collect();
            let x = cholesky_solve(&mut a, &b, k_total)?;
            for (out, v) in coef.iter_mut().zip(x) {
                out[ch] = v as f32;
            }
        }
        Ok(ColourMap {
            format: FORMAT.into(),
            nodes: n,
            coef,
        })
    }
}

/// Solves A x = b for symmetric positive definite A (row-major, overwritten by its Cholesky
/// factor).
fn cholesky_solve(a: &mut [f64], b: &[f64], n: usize) -> Result<Vec<f64>, String> {
    for j in 0..n {
        let mut d = a[j * n + j];
        for k in 0..j {
            d -= a[j * n + k] * a[j * n + k];
        }
        if d.is_nan() || d <= 0.0 {
            return Err("the calibration system is not positive definite".into());
        }
        let d = d.sqrt();
        a[j * n + j] = d;
        let (head, tail) = a.split_at_mut((j + 1) * n);
        let row_j = &head[j * n..j * n + j];
        tail.par_chunks_mut(n).for_each(|row_i| {
            let s: f64 = row_i[..j].iter().zip(row_j).map(|(x, y)| x * y).sum();
            row_i[j] = (row_i[j] - s) / d;
        });
    }
    let mut y = b.to_vec();
    for i in 0..n {
        for k in 0..i {
            y[i] -= a[i * n + k] * y[k];
        }
        y[i] /= a[i * n + i];
    }
    for i in (0..n).rev() {
        for k in i + 1..n {
            y[i] -= a[k * n + i] * y[k];
        }
        y[i] /= a[i * n + i];
    }
    Ok(y)
}

/// A calibration on disk: `map.json` (the [`ColourMap`], how it was fitted and, for a map fitted
/// through shadows, the lights it was fitted with) and `background.png` (the no-contact image
/// re-estimated from the calibration frames).
#[derive(Debug, Clone)]
pub struct Calibration {
    /// The colour map.
    pub map: ColourMap,
    /// Background image (RGB).
    pub background: RgbImage,
    /// Free-form provenance written next to the map (pack, frames, ball radius, pixel pitch).
    pub provenance: serde_json::Value,
    /// The lights the map was fitted through (`None`: fitted without shadows).
    pub shadows: Option<FittedLights>,
}

/// The lights of a map fitted through shadows ([`crate::sim2real::calibrate_pack_with_shadows`]):
/// the map explains a pixel as (bg + ΔI)·(1 − Σ_l w_l·(1 − v_l)) under exactly these lights, so
/// a renderer with shadows casts them from these.
#[derive(Debug, Clone, PartialEq)]
pub struct FittedLights {
    /// Sensor preset whose shading (for the lights' shares w_l) and LED layout the fit started
    /// from.
    pub sensor: String,
    /// The lights, with their fitted positions (mm, camera frame).
    pub lights: Vec<Light>,
    /// Radius of each LED's emitting disc (mm).
    pub led_radius_mm: f64,
    /// Shadow-march samples per ray used in the fit.
    pub steps: u32,
}

/// One light as written in `map.json` (`sparsh_scene::Light` is read-only).
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct LightFile {
    position_mm: [f64; 3],
    color: [f64; 3],
    intensity: f64,
}

#[derive(Serialize, Deserialize)]
struct MapFile {
    #[serde(flatten)]
    map: ColourMap,
    /// True when the map was fitted through shadows; then the next four fields are present.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    shadows: bool,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    sensor: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    lights: Option<Vec<LightFile>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    led_radius_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    shadow_steps: Option<u32>,
    #[serde(default)]
    provenance: serde_json::Value,
}

impl MapFile {
    /// The fitted lights, checked: all four fields with `shadows = true`, none without.
    fn fitted_lights(&self) -> Result<Option<FittedLights>, String> {
        let given = [
            ("sensor", self.sensor.is_some()),
            ("lights", self.lights.is_some()),
            ("led_radius_mm", self.led_radius_mm.is_some()),
            ("shadow_steps", self.shadow_steps.is_some()),
        ];
        if !self.shadows {
            return match given.iter().find(|(_, present)| *present) {
                Some((field, _)) => Err(format!("{field}: given but shadows is not true")),
                None => Ok(None),
            };
        }
        let missing = |field: &str| format!("{field}: missing (shadows is true)");
        let sensor = self.sensor.clone().ok_or_else(|| missing("sensor"))?;
        let lights = self.lights.as_ref().ok_or_else(|| missing("lights"))?;
        let led_radius_mm = self.led_radius_mm.ok_or_else(|| missing("led_radius_mm"))?;
        let steps = self.shadow_steps.ok_or_else(|| missing("shadow_steps"))?;
        if lights.is_empty() {
            return Err("lights: empty".into());
        }
        for (l, light) in lights.iter().enumerate() {
            let values = light.position_mm.iter().chain(&light.color);
            if values.chain([&light.intensity]).any(|v| !v.is_finite()) {
                return Err(format!("lights: light {l} has a non-finite value"));
            }
        }
        if !(led_radius_mm.is_finite() && led_radius_mm >= 0.0) {
            return Err(format!("led_radius_mm: must be ≥ 0, got {led_radius_mm}"));
        }
        if steps == 0 {
            return Err("shadow_steps: must be at least 1".into());
        }
        Ok(Some(FittedLights {
            sensor,
            lights: lights
                .iter()
                .map(|l| Light {
                    position_mm: l.position_mm,
                    color: l.color,
                    intensity: l.intensity,
                })
                .collect(),
            led_radius_mm,
            steps,
        }))
    }
}

impl Calibration {
    /// Writes `map.json` and `background.png` into `dir` (created if needed), each through a
    /// temporary name then renamed.
    pub fn save(&self, dir: &Path) -> Result<(), String> {
        std::fs::create_dir_all(dir)
            .map_err(|e| format!("{}: cannot create: {e}", dir.display()))?;
        let fitted = self.shadows.as_ref();
        let json = serde_json::to_string(&MapFile {
            map: self.map.clone(),
            shadows: fitted.is_some(),
            sensor: fitted.map(|f| f.sensor.clone()),
            lights: fitted.map(|f| {
                f.lights
                    .iter()
                    .map(|l| LightFile {
                        position_mm: l.position_mm,
                        color: l.color,
                        intensity: l.intensity,
                    })
                    .collect()
            }),
            led_radius_mm: fitted.map(|f| f.led_radius_mm),
            shadow_steps: fitted.map(|f| f.steps),
            provenance: self.provenance.clone(),
        })
        .map_err(|e| e.to_string())?;
        write_atomic(&dir.join("map.json"), |p| {
            std::fs::write(p, json.as_bytes()).map_err(|e| e.to_string())
        })?;
        write_atomic(&dir.join("background.png"), |p| {
            self.background
                .save_with_format(p, image::ImageFormat::Png)
                .map_err(|e| e.to_string())
        })
    }

    /// Reads a calibration directory written by [`Calibration::save`].
    pub fn load(dir: &Path) -> Result<Calibration, String> {
        let map_path = dir.join("map.json");
        let text = std::fs::read_to_string(&map_path)
            .map_err(|e| format!("{}: cannot read: {e}", map_path.display()))?;
        let file: MapFile =
            serde_json::from_str(&text).map_err(|e| format!("{}: {e}", map_path.display()))?;
        let shadows = file
            .fitted_lights()
            .map_err(|e| format!("{}: {e}", map_path.display()))?;
        let map = file.map;
        if map.format != FORMAT {
            return Err(format!(
                "{}: format: expected {FORMAT}, got {}",
                map_path.display(),
                map.format
            ));
        }
        if map.nodes < 3 || map.coef.len() != BASES * map.nodes * map.nodes {
            return Err(format!(
                "{}: coef: expected {} entries for {} nodes, got {}",
                map_path.display(),
                BASES * map.nodes * map.nodes,
                map.nodes,
                map.coef.len()
            ));
        }
        if map.coef.iter().flatten().any(|v| !v.is_finite()) {
            return Err(format!(
                "{}: coef: contains a non-finite value",
                map_path.display()
            ));
        }
        let bg_path = dir.join("background.png");
        let background = image::open(&bg_path)
            .map_err(|e| format!("{}: {e}", bg_path.display()))?
            .to_rgb8();
        Ok(Calibration {
            map,
            background,
            provenance: file.provenance,
            shadows,
        })
    }
}

/// The shadow attenuation S_ch = 1 − Σ_l w_{l,ch}·(1 − v_l) of a pixel with light shares
/// `shares` and visible fractions `visible` (one per light): in f32 as on the GPU, exactly 1
/// when no light is hidden.
pub fn attenuation(shares: &[[f32; 3]], visible: &[f64]) -> [f32; 3] {
    std::array::from_fn(|ch| {
        1.0 - shares
            .iter()
            .zip(visible)
            .map(|(w, v)| w[ch] * (1.0 - *v as f32))
            .sum::<f32>()
    })
}

/// Writes through `<name>.tmp` then renames, so readers never see half a file.
pub(crate) fn write_atomic(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), String>,
) -> Result<(), String> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = std::path::PathBuf::from(tmp);
    write(&tmp).map_err(|e| format!("{}: {e}", path.display()))?;
    std::fs::rename(&tmp, path).map_err(|e| format!("{}: {e}", path.display()))
}

/// Renders with a [`ColourMap`] over a background: I = clamp(round(bg + ΔI)), and with shadows
/// I_ch = (bg_ch + ΔI_ch)·S_ch with S_ch = 1 − Σ_l w_{l,ch}·(1 − v_l), where v_l is the
/// visible fraction of light l ([`crate::shadow`]) and w_{l,ch} its share of the pixel's
/// flat-gel radiance in channel ch ([`crate::photometric::light_shares`]): a shadow removes
/// what its light contributes. As the shares sum to 1, S_ch = Σ_l w_{l,ch}·v_l; written as a
/// loss it is exactly 1 where every light is in view ([`attenuation`]). The
/// lights are the calibration's fitted ones when it has them ([`FittedLights`]), otherwise the
/// sensor's.
#[derive(Debug, Clone)]
pub struct CalibratedRenderer {
    pub(crate) map: ColourMap,
    pub(crate) background: Vec<[f32; 3]>,
    pub(crate) width_px: usize,
    pub(crate) height_px: usize,
    pub(crate) shadows: Option<CalibratedShadows>,
    /// The lights the map was fitted through, if any.
    fitted: Option<FittedLights>,
}

/// What the calibrated model needs to cast shadows: the sensor's lights and their shares.
#[derive(Debug, Clone)]
pub(crate) struct CalibratedShadows {
    pub(crate) lights: Vec<Light>,
    pub(crate) shares: Vec<[f32; 3]>,
    pub(crate) settings: ShadowSettings,
}

impl CalibratedRenderer {
    /// A renderer of `width_px × height_px` images; the calibration's background is resized
    /// (bilinear) when its size differs.
    pub fn new(calibration: &Calibration, width_px: usize, height_px: usize) -> CalibratedRenderer {
        let bg = &calibration.background;
        let bg = if bg.dimensions() == (width_px as u32, height_px as u32) {
            bg.clone()
        } else {
            image::imageops::resize(
                bg,
                width_px as u32,
                height_px as u32,
                image::imageops::FilterType::Triangle,
            )
        };
        CalibratedRenderer {
            map: calibration.map.clone(),
            background: bg.pixels().map(|p| p.0.map(f32::from)).collect(),
            width_px,
            height_px,
            shadows: None,
            fitted: calibration.shadows.clone(),
        }
    }

    /// Casts shadows (its grid must match the image size), marching `steps` samples per ray:
    /// of the calibration's fitted lights and LED radius when it has them, otherwise of
    /// `sensor`'s; the lights' shares w_{l,ch} follow from `sensor`'s shading with those lights.
    pub fn with_shadows(mut self, sensor: &SensorConfig, steps: u32) -> CalibratedRenderer {
        assert_eq!(
            (sensor.width_px, sensor.height_px),
            (self.width_px, self.height_px),
            "sensor and image differ in size"
        );
        let mut sensor = sensor.clone();
        if let Some(fitted) = &self.fitted {
            sensor.lights = fitted.lights.clone();
            sensor.led_radius_mm = fitted.led_radius_mm;
        }
        self.shadows = Some(CalibratedShadows {
            shares: light_shares(&sensor),
            settings: shadow_settings(&sensor, steps),
            lights: sensor.lights,
        });
        self
    }

    /// The no-contact image.
    pub fn background(&self) -> RgbImage {
        crate::to_image(self.width_px, self.height_px, &self.background)
    }

    /// The image of a deformed surface (its grid must match the image size).
    pub fn render(&self, surface: &Surface) -> RgbImage {
        assert_eq!(
            (surface.grid.nx, surface.grid.ny),
            (self.width_px, self.height_px),
            "surface grid and image differ in size"
        );
        crate::to_image(self.width_px, self.height_px, &self.render_linear(surface))
    }

    /// The image of a deformed surface before rounding (RGB, 0–255 scale).
    pub fn render_linear(&self, surface: &Surface) -> Vec<[f32; 3]> {
        let delta = self.map.delta(surface);
        let mut pixels: Vec<[f32; 3]> = delta
            .par_iter()
            .zip(&self.background)
            .map(|(d, b)| std::array::from_fn(|c| b[c] + d[c]))
            .collect();
        if let Some(sh) = &self.shadows {
            let n = sh.lights.len();
            let visible = visibilities(surface.uz_mm, surface.grid, &sh.lights, sh.settings);
            pixels
                .par_iter_mut()
                .zip(visible.par_chunks(n))
                .zip(sh.shares.par_chunks(n))
                .for_each(|((px, v), w)| {
                    let s = attenuation(w, v);
                    for (value, s) in px.iter_mut().zip(s) {
                        *value *= s;
                    }
                });
        }
        pixels
    }
}
