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

/// Per-pixel features of a surface: the normal's lateral components and the position bases.
fn features(surface: &Surface) -> Vec<([f64; 2], [f64; BASES])> {
    let grid = surface.grid;
    let (nx, ny) = (grid.nx, grid.ny);
    let uz = surface.uz_mm;
    (0..grid.len())
        .into_par_iter()
        .map(|c| {
            let (i, j) = (c % nx, c / nx);
            let [gx, gy] = gradient(uz, grid, i, j);
            let norm = (1.0 + gx * gx + gy * gy).sqrt();
            let x = (i as f64 + 0.5) / nx as f64 - 0.5;
            let y = (j as f64 + 0.5) / ny as f64 - 0.5;
            ([gx / norm, gy / norm], [1.0, x, y])
        })
        .collect()
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
        features(surface)
            .par_iter()
            .map(|(n, basis)| {
                let (idx, w) = nodes_of(self.nodes, *n);
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

/// Least-squares accumulator for a [`ColourMap`]: the normal equations kept per table cell.
#[derive(Debug, Clone)]
pub struct MapFitter {
    nodes: usize,
    /// Σ φφᵀ (dense, K × K with K = BASES·N²).
    normal: Vec<f64>,
    /// Σ φ·ΔI per channel.
    rhs: Vec<[f64; 3]>,
    samples: usize,
}

impl MapFitter {
    /// An empty fit with `nodes` table nodes per normal component (at least 3).
    pub fn new(nodes: usize) -> MapFitter {
        let nodes = nodes.max(3);
        let k = BASES * nodes * nodes;
        MapFitter {
            nodes,
            normal: vec![0.0; k * k],
            rhs: vec![[0.0; 3]; k],
            samples: 0,
        }
    }

    #[allow(clippy::needless_range_loop)] // three channels side by side read clearer indexed
    /// Adds the pixels of one frame for which `use_pixel(i, j)` holds: the real image `real`
    /// is explained as `background + ΔI(surface)`.
    pub fn add_frame(
        &mut self,
        surface: &Surface,
        real: &RgbImage,
        background: &[[f32; 3]],
        use_pixel: impl Fn(usize, usize) -> bool,
    ) {
        let k_total = BASES * self.nodes * self.nodes;
        let plane = self.nodes * self.nodes;
        let feats = features(surface);
        let nx = surface.grid.nx;
        for (c, (n, basis)) in feats.iter().enumerate() {
            if !use_pixel(c % nx, c / nx) {
                continue;
            }
            let (idx, w) = nodes_of(self.nodes, *n);
            let mut cols = [0usize; 12];
            let mut vals = [0.0f64; 12];
            for b in 0..BASES {
                for q in 0..4 {
                    cols[b * 4 + q] = b * plane + idx[q];
                    vals[b * 4 + q] = basis[b] * w[q];
                }
            }
            let px = real.as_raw();
            let target: [f64; 3] =
                std::array::from_fn(|ch| px[c * 3 + ch] as f64 - background[c][ch] as f64);
            for p in 0..12 {
                let row = cols[p] * k_total;
                for q in 0..12 {
                    self.normal[row + cols[q]] += vals[p] * vals[q];
                }
                for ch in 0..3 {
                    self.rhs[cols[p]][ch] += vals[p] * target[ch];
                }
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
        for (a, b) in self.normal.iter_mut().zip(&other.normal) {
            *a += b;
        }
        for (a, b) in self.rhs.iter_mut().zip(&other.rhs) {
            for ch in 0..3 {
                a[ch] += b[ch];
            }
        }
        self.samples += other.samples;
    }

    /// Solves (ΦᵀΦ + λ s DᵀD + 10⁻⁶ s I) c = ΦᵀΔI, with D the second differences of each table
    /// along both axes (a thin-plate-like penalty that leaves affine tables free) and
    /// s = trace(ΦᵀΦ)/K, which makes λ (`smoothness`) scale-free.
    pub fn solve(&self, smoothness: f64) -> Result<ColourMap, String> {
        if self.samples == 0 {
            return Err("no pixel to fit the map on".into());
        }
        let n = self.nodes;
        let k_total = BASES * n * n;
        let mut a = self.normal.clone();
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
        let x = cholesky_solve(&mut a, &self.rhs, k_total)?;
        Ok(ColourMap {
            format: FORMAT.into(),
            nodes: n,
            coef: x.iter().map(|c| c.map(|v| v as f32)).collect(),
        })
    }
}

#[allow(clippy::needless_range_loop)] // three channels side by side read clearer indexed
/// Solves A x = b for symmetric positive definite A (row-major, overwritten by its Cholesky
/// factor), three right-hand sides.
fn cholesky_solve(a: &mut [f64], b: &[[f64; 3]], n: usize) -> Result<Vec<[f64; 3]>, String> {
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
            for ch in 0..3 {
                y[i][ch] -= a[i * n + k] * y[k][ch];
            }
        }
        for ch in 0..3 {
            y[i][ch] /= a[i * n + i];
        }
    }
    for i in (0..n).rev() {
        for k in i + 1..n {
            for ch in 0..3 {
                y[i][ch] -= a[k * n + i] * y[k][ch];
            }
        }
        for ch in 0..3 {
            y[i][ch] /= a[i * n + i];
        }
    }
    Ok(y)
}

/// A calibration on disk: `map.json` (the [`ColourMap`] and how it was fitted) and
/// `background.png` (the no-contact image re-estimated from the calibration frames).
#[derive(Debug, Clone)]
pub struct Calibration {
    /// The colour map.
    pub map: ColourMap,
    /// Background image (RGB).
    pub background: RgbImage,
    /// Free-form provenance written next to the map (pack, frames, ball radius, pixel pitch).
    pub provenance: serde_json::Value,
}

#[derive(Serialize, Deserialize)]
struct MapFile {
    #[serde(flatten)]
    map: ColourMap,
    #[serde(default)]
    provenance: serde_json::Value,
}

impl Calibration {
    /// Writes `map.json` and `background.png` into `dir` (created if needed), each through a
    /// temporary name then renamed.
    pub fn save(&self, dir: &Path) -> Result<(), String> {
        std::fs::create_dir_all(dir)
            .map_err(|e| format!("{}: cannot create: {e}", dir.display()))?;
        let json = serde_json::to_string(&MapFile {
            map: self.map.clone(),
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
        })
    }
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
/// I_ch = (bg_ch + ΔI_ch)·Σ_l w_{l,ch}·v_l, where v_l is the visible fraction of light l
/// ([`crate::shadow`]) and w_{l,ch} its share of the pixel's flat-gel radiance in channel ch
/// ([`crate::photometric::light_shares`]): a shadow removes what its light contributes.
#[derive(Debug, Clone)]
pub struct CalibratedRenderer {
    pub(crate) map: ColourMap,
    pub(crate) background: Vec<[f32; 3]>,
    pub(crate) width_px: usize,
    pub(crate) height_px: usize,
    pub(crate) shadows: Option<CalibratedShadows>,
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
        }
    }

    /// Casts shadows of `sensor`'s lights (its grid must match the image size), marching
    /// `steps` samples per ray.
    pub fn with_shadows(mut self, sensor: &SensorConfig, steps: u32) -> CalibratedRenderer {
        assert_eq!(
            (sensor.width_px, sensor.height_px),
            (self.width_px, self.height_px),
            "sensor and image differ in size"
        );
        self.shadows = Some(CalibratedShadows {
            lights: sensor.lights.clone(),
            shares: light_shares(sensor),
            settings: shadow_settings(sensor, steps),
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
                    for (ch, value) in px.iter_mut().enumerate() {
                        *value *= w.iter().zip(v).map(|(w, v)| w[ch] * *v as f32).sum::<f32>();
                    }
                });
        }
        pixels
    }
}
