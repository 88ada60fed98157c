//! Calibration from a ball pack and the sim-to-real score: each real frame's ball indentation is
//! rendered (the surface under the marked contact circle, Hertz's or a rung's, see
//! [`crate::ball`]) and compared to
//! the real frame over the full image and over a square of half-width 2a around the contact.

use image::RgbImage;
use rayon::prelude::*;
use serde::Serialize;
use sparsh_scene::{Grid, Light, SensorConfig};

use crate::Surface;
use crate::ball::BallMechanics;
use crate::calibrated::{
    CalibratedRenderer, Calibration, ColourMap, FittedLights, MapFitter, attenuation,
};
use crate::metrics::{Scores, crop, scores};
use crate::pack::CalibrationPack;
use crate::photometric::{light_shares, shadow_settings};
use crate::shadow::{HeightField, cell_visibilities};

/// Pixels farther than this many contact radii from the contact count as background.
const BACKGROUND_RADII: f64 = 3.0;

/// The physical set-up of a pack: ball radius, pixel pitch and the mechanics that turn a marked
/// contact circle into the gel's surface.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct BallSetup {
    /// Radius of the calibration ball (mm).
    pub ball_radius_mm: f64,
    /// Pixel pitch on the gel (mm per pixel).
    pub mm_per_px: f64,
    /// The surface under the ball.
    pub mechanics: BallMechanics,
}

/// Options of the map fit.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FitOptions {
    /// Table nodes per normal component.
    pub nodes: usize,
    /// Laplacian smoothness weight λ (scale-free).
    pub smoothness: f64,
}

impl Default for FitOptions {
    fn default() -> Self {
        FitOptions {
            nodes: 17,
            smoothness: 0.01,
        }
    }
}

/// The sensor grid of a pack and the u_z field of its frame `k` under `setup.mechanics`.
pub fn frame_surface_uz(
    pack: &CalibrationPack,
    k: usize,
    setup: BallSetup,
) -> Result<(Grid, Vec<f64>), String> {
    let (w, h) = pack.size_px();
    let grid = Grid {
        nx: w,
        ny: h,
        cell_mm: setup.mm_per_px,
    };
    let c = pack.centers_px[k];
    // Pixel i's centre is x_mm(i); the pack's coordinates are pixel indices.
    let centre_mm = [
        (c[0] + 0.5 - w as f64 / 2.0) * setup.mm_per_px,
        (c[1] + 0.5 - h as f64 / 2.0) * setup.mm_per_px,
    ];
    let a_mm = pack.radii_px[k] * setup.mm_per_px;
    let uz = setup
        .mechanics
        .uz_mm(grid, centre_mm, a_mm, setup.ball_radius_mm)
        .map_err(|e| format!("touch_radius: frame {k}: {e}"))?;
    Ok((grid, uz))
}

fn far_from_contact(pack: &CalibrationPack, k: usize) -> impl Fn(usize, usize) -> bool {
    let c = pack.centers_px[k];
    let r = BACKGROUND_RADII * pack.radii_px[k];
    move |i, j| (i as f64 - c[0]).hypot(j as f64 - c[1]) > r
}

/// Re-estimates the background as the mean of `frames` over their pixels far from the contact
/// (the pack's `f0` where no frame is far enough), which follows the lighting of the session.
pub fn estimate_background(pack: &CalibrationPack, frames: &[usize]) -> RgbImage {
    let (w, h) = pack.size_px();
    let mut acc = vec![[0.0f64; 3]; w * h];
    let mut count = vec![0u32; w * h];
    for &k in frames {
        let far = far_from_contact(pack, k);
        let px = pack.frames[k].as_raw();
        for c in 0..w * h {
            if far(c % w, c / w) {
                for ch in 0..3 {
                    acc[c][ch] += px[c * 3 + ch] as f64;
                }
                count[c] += 1;
            }
        }
    }
    let f0 = pack.background.as_raw();
    let raw: Vec<u8> = (0..w * h)
        .flat_map(|c| {
            std::array::from_fn::<u8, 3, _>(|ch| match count[c] {
                0 => f0[c * 3 + ch],
                n => (acc[c][ch] / n as f64).round() as u8,
            })
        })
        .collect();
    RgbImage::from_raw(w as u32, h as u32, raw).expect("size matches")
}

/// Frames summed into one partial fit before the partials are added in order: a fixed number,
/// so the sums (and the map) do not depend on the thread count.
const FRAMES_PER_PARTIAL: usize = 4;

/// One fitting frame: the pack frame, its surface and its pixels within 3a of the contact.
struct FitFrame {
    k: usize,
    grid: Grid,
    uz: Vec<f64>,
    cells: Vec<usize>,
}

fn fit_frames(
    pack: &CalibrationPack,
    frames: &[usize],
    setup: BallSetup,
) -> Result<Vec<FitFrame>, String> {
    frames
        .par_iter()
        .map(|&k| {
            let (grid, uz) = frame_surface_uz(pack, k, setup)?;
            let far = far_from_contact(pack, k);
            let cells = (0..grid.len())
                .filter(|&c| !far(c % grid.nx, c / grid.nx))
                .collect();
            Ok(FitFrame { k, grid, uz, cells })
        })
        .collect()
}

/// The normal equations of the map over the fitting frames, pixel p of frame f explained as
/// I_ch = s_ch·(bg_ch + ΔI_ch) with s = `attenuation(f, p)` ([`MapFitter::add_attenuated`]).
fn accumulate(
    pack: &CalibrationPack,
    fit: &[FitFrame],
    background: &[[f32; 3]],
    nodes: usize,
    attenuation: impl Fn(usize, usize) -> [f64; 3] + Sync,
) -> MapFitter {
    let partials: Vec<MapFitter> = fit
        .par_chunks(FRAMES_PER_PARTIAL)
        .enumerate()
        .map(|(chunk, frames)| {
            let mut partial = MapFitter::new(nodes);
            for (j, frame) in frames.iter().enumerate() {
                let f = chunk * FRAMES_PER_PARTIAL + j;
                let zeros = vec![0.0; frame.grid.len()];
                let surface = Surface {
                    grid: frame.grid,
                    ux_mm: &zeros,
                    uy_mm: &zeros,
                    uz_mm: &frame.uz,
                };
                partial.add_attenuated(
                    &surface,
                    &pack.frames[frame.k],
                    background,
                    &frame.cells,
                    |p| attenuation(f, p),
                );
            }
            partial
        })
        .collect();
    let mut total = MapFitter::new(nodes);
    for p in &partials {
        total.merge(p);
    }
    total
}

fn as_rgb_f32(image: &RgbImage) -> Vec<[f32; 3]> {
    image.pixels().map(|p| p.0.map(f32::from)).collect()
}

/// Fits a [`Calibration`] on the pack's `frames`: the background re-estimated on them, then the
/// colour map on their pixels within 3a of the contact.
pub fn calibrate_pack(
    pack: &CalibrationPack,
    frames: &[usize],
    setup: BallSetup,
    options: FitOptions,
) -> Result<Calibration, String> {
    if frames.is_empty() {
        return Err("no frame selected to calibrate on".into());
    }
    let background = estimate_background(pack, frames);
    let fit = fit_frames(pack, frames, setup)?;
    let total = accumulate(
        pack,
        &fit,
        &as_rgb_f32(&background),
        options.nodes,
        |_, _| [1.0; 3],
    );
    let map = total.solve(options.smoothness)?;
    Ok(Calibration {
        map,
        background,
        provenance: provenance(frames, setup, options, total.samples()),
        shadows: None,
    })
}

/// What `map.json` records of a fit: the frames, the ball and pixel pitch, the table's size
/// and smoothness, and how many pixels it was fitted on.
fn provenance(
    frames: &[usize],
    setup: BallSetup,
    options: FitOptions,
    fit_pixels: usize,
) -> serde_json::Value {
    serde_json::json!({
        "frames": frames,
        "ball_radius_mm": setup.ball_radius_mm,
        "mm_per_px": setup.mm_per_px,
        "mechanics": setup.mechanics,
        "nodes": options.nodes,
        "smoothness": options.smoothness,
        "fit_pixels": fit_pixels,
    })
}

/// How [`calibrate_pack_with_shadows`] searches the LEDs' z (mm, camera frame; negative: on
/// the camera side of the gel, −z below it).
#[derive(Debug, Clone)]
pub struct ShadowSearch {
    /// The sensor whose LEDs start the search: their x, y, colour and intensity and its LED
    /// radius are kept; its size and pitch are set to the pack's (the same view in mm when the
    /// preset shares the pack's field of view, as `gelsight2017` and `gelsight_mini_vga` do).
    pub sensor: SensorConfig,
    /// Shadow-march samples per ray.
    pub steps: u32,
    /// Common z of every LED tried first (mm, each < 0).
    pub common_z_mm: Vec<f64>,
    /// Then for each step δ in turn, LED by LED, z ± δ is tried and the better kept when it
    /// lowers the error (mm, each > 0).
    pub refine_mm: Vec<f64>,
}

impl ShadowSearch {
    /// The search of the README: a common z over −1, −2, …, −12 mm and on to −40 mm by 2 mm
    /// (5° to 73° above the gel at the GelSight 2017 preset's 12 mm), then each LED
    /// refined by ±0.5 mm and ±0.25 mm.
    pub fn new(sensor: SensorConfig, steps: u32) -> ShadowSearch {
        ShadowSearch {
            sensor,
            steps,
            common_z_mm: (1..=12)
                .chain((7..=20).map(|h| 2 * h))
                .map(|h| -f64::from(h))
                .collect(),
            refine_mm: vec![0.5, 0.25],
        }
    }
}

/// One light layout tried by the shadow-aware fit.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ShadowTrial {
    /// z of each LED (mm).
    pub light_z_mm: Vec<f64>,
    /// Root-mean-square image error of the refitted map over the fitting pixels (0–255 units,
    /// per channel, before rounding).
    pub rms: f64,
    /// Fraction of (fitting pixel, LED) pairs with the LED partly or wholly hidden (v < 1).
    pub shadowed: f64,
}

/// What the shadow-aware fit tried and kept.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ShadowReport {
    /// The layout kept (its map is the calibration's).
    pub best: ShadowTrial,
    /// Every layout tried, in order.
    pub trials: Vec<ShadowTrial>,
}

/// Relative drop of the RMS error a layout must bring to replace the best so far: smaller
/// changes are at the level of rounding (the shares are f32) or of a handful of penumbra
/// pixels, not signal, so among equals the search keeps the earlier layout.
const RMS_TOLERANCE: f64 = 1e-6;

/// One light's visible fraction v_l at each fitting pixel of each frame: `[frame][pixel]`.
type LightVisibility = Vec<Vec<f64>>;

/// A layout tried by the shadow-aware fit and the map refitted under it.
struct Refit {
    trial: ShadowTrial,
    map: ColourMap,
}

/// Fraction of the visibilities (every light's, [`LightVisibility`]) below 1.
fn shadowed_fraction(vis: &[LightVisibility]) -> f64 {
    let all = vis.iter().flatten().flatten();
    let total = all.clone().count();
    all.filter(|v| **v < 1.0).count() as f64 / total.max(1) as f64
}

/// Fits a [`Calibration`] through the shadows of the search's LEDs (the map the calibrated
/// renderer with shadows needs): every fitting pixel is explained as I_ch = (bg_ch + ΔI_ch)·S_ch
/// with S_ch = 1 − Σ_l w_{l,ch}·(1 − v_l) ([`attenuation`], as the renderer), the visibilities
/// v_l of the frame's Hertz surface ([`crate::shadow`]) and the shares w_{l,ch}
/// ([`light_shares`]); for given lights the map is the linear least-squares fit of
/// [`MapFitter::add_attenuated`]. The LEDs' z are fitted parameters: a common z over
/// `search.common_z_mm`, then each LED in turn by ±δ for each δ of `search.refine_mm`,
/// minimising the RMS image error on the fitting frames only (a layout replaces the best only if
/// it lowers the error by more than [`RMS_TOLERANCE`], relative). Returns the calibration (with
/// the fitted lights, [`FittedLights`]) and the layouts tried ([`ShadowReport`]).
/// Deterministic: frames are summed in fixed groups in order, as in [`calibrate_pack`], so the
/// result does not depend on the thread count.
pub fn calibrate_pack_with_shadows(
    pack: &CalibrationPack,
    frames: &[usize],
    setup: BallSetup,
    options: FitOptions,
    search: &ShadowSearch,
) -> Result<(Calibration, ShadowReport), String> {
    if frames.is_empty() {
        return Err("no frame selected to calibrate on".into());
    }
    if search.steps == 0 {
        return Err("shadow steps must be at least 1".into());
    }
    if search.common_z_mm.is_empty() || search.common_z_mm.iter().any(|z| z.is_nan() || *z >= 0.0) {
        return Err(format!(
            "LED z to try must be < 0 mm (below the gel), got {:?}",
            search.common_z_mm
        ));
    }
    if search
        .refine_mm
        .iter()
        .any(|d| !(d.is_finite() && *d > 0.0))
    {
        return Err(format!(
            "LED z refinement steps must be > 0 mm, got {:?}",
            search.refine_mm
        ));
    }
    if search.sensor.lights.is_empty() {
        return Err(format!("sensor {}: has no lights", search.sensor.name));
    }
    let (w, h) = pack.size_px();
    let mut sensor = search.sensor.clone();
    sensor.width_px = w;
    sensor.height_px = h;
    sensor.mm_per_px = setup.mm_per_px;
    let settings = shadow_settings(&sensor, search.steps);
    let background = estimate_background(pack, frames);
    let bg = as_rgb_f32(&background);
    let fit = fit_frames(pack, frames, setup)?;
    let fields: Vec<HeightField> = fit
        .par_iter()
        .map(|f| HeightField::from_uz(&f.uz, f.grid))
        .collect();
    let n = sensor.lights.len();
    let visibility_of = |light: &Light| -> LightVisibility {
        fit.iter()
            .zip(&fields)
            .map(|(frame, field)| cell_visibilities(field, &frame.cells, light, settings))
            .collect()
    };
    let lights_at = |z_mm: &[f64]| -> Vec<Light> {
        sensor
            .lights
            .iter()
            .zip(z_mm)
            .map(|(l, &z)| Light {
                position_mm: [l.position_mm[0], l.position_mm[1], z],
                ..l.clone()
            })
            .collect()
    };
    // The map refitted under the LEDs at `z_mm` (their visibilities `vis`) and its RMS error.
    let evaluate = |z_mm: &[f64], vis: &[LightVisibility]| -> Result<Refit, String> {
        let mut lit = sensor.clone();
        lit.lights = lights_at(z_mm);
        let shares = light_shares(&lit);
        let total = accumulate(pack, &fit, &bg, options.nodes, |f, p| {
            let c = fit[f].cells[p];
            let v: Vec<f64> = vis.iter().map(|light| light[f][p]).collect();
            attenuation(&shares[c * n..(c + 1) * n], &v).map(f64::from)
        });
        let map = total.solve(options.smoothness)?;
        let rms = (total.residual(&map).max(0.0) / (3 * total.samples()) as f64).sqrt();
        let trial = ShadowTrial {
            light_z_mm: z_mm.to_vec(),
            rms,
            shadowed: shadowed_fraction(vis),
        };
        Ok(Refit { trial, map })
    };
    let improves = |rms: f64, than: f64| rms < than * (1.0 - RMS_TOLERANCE);
    let mut trials = Vec::new();
    let mut best: Option<(Refit, Vec<LightVisibility>)> = None;
    for &z in &search.common_z_mm {
        let z_mm = vec![z; n];
        let vis: Vec<_> = lights_at(&z_mm).iter().map(visibility_of).collect();
        let refit = evaluate(&z_mm, &vis)?;
        trials.push(refit.trial.clone());
        if best
            .as_ref()
            .is_none_or(|(b, _)| improves(refit.trial.rms, b.trial.rms))
        {
            best = Some((refit, vis));
        }
    }
    let (mut kept, mut vis) = best.ok_or("no LED z to try")?;
    for &step in &search.refine_mm {
        for l in 0..n {
            let mut better: Option<(Refit, LightVisibility)> = None;
            let z_l = kept.trial.light_z_mm[l];
            for z in [z_l - step, z_l + step] {
                if z >= 0.0 {
                    continue;
                }
                let mut z_mm = kept.trial.light_z_mm.clone();
                z_mm[l] = z;
                let current = std::mem::replace(&mut vis[l], visibility_of(&lights_at(&z_mm)[l]));
                let refit = evaluate(&z_mm, &vis)?;
                let tried = std::mem::replace(&mut vis[l], current);
                trials.push(refit.trial.clone());
                let to_beat = better.as_ref().map_or(kept.trial.rms, |(b, _)| b.trial.rms);
                if improves(refit.trial.rms, to_beat) {
                    better = Some((refit, tried));
                }
            }
            if let Some((refit, tried)) = better {
                (kept, vis[l]) = (refit, tried);
            }
        }
    }
    let Refit { trial: best, map } = kept;
    let lights = lights_at(&best.light_z_mm);
    Ok((
        Calibration {
            map,
            background,
            provenance: {
                let fit_pixels = fit.iter().map(|f| f.cells.len()).sum();
                let mut p = provenance(frames, setup, options, fit_pixels);
                p["shadow_search"] = serde_json::json!({
                    "common_z_mm": search.common_z_mm,
                    "refine_mm": search.refine_mm,
                    "best": best,
                    "trials": trials,
                });
                p
            },
            shadows: Some(FittedLights {
                sensor: sensor.name.clone(),
                lights,
                led_radius_mm: sensor.led_radius_mm,
                steps: search.steps,
            }),
        },
        ShadowReport { best, trials },
    ))
}

/// One frame's scores.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FrameScore {
    /// Index of the frame in the pack.
    pub frame: usize,
    /// Over the full image.
    pub full: Scores,
    /// Over the square of half-width 2a around the contact.
    pub crop: Scores,
}

/// The renderer of a pack's frames: the calibration at the pack's size, with shadows of
/// `shadows`' lights when given (the sensor's size and pitch are set to the pack's).
pub fn pack_renderer(
    calibration: &Calibration,
    pack: &CalibrationPack,
    setup: BallSetup,
    shadows: Option<(&SensorConfig, u32)>,
) -> CalibratedRenderer {
    let (w, h) = pack.size_px();
    let renderer = CalibratedRenderer::new(calibration, w, h);
    match shadows {
        Some((sensor, steps)) => {
            let mut sensor = sensor.clone();
            sensor.width_px = w;
            sensor.height_px = h;
            sensor.mm_per_px = setup.mm_per_px;
            renderer.with_shadows(&sensor, steps)
        }
        None => renderer,
    }
}

/// Renders frame `k` of the pack (see [`pack_renderer`]) and scores it against the real frame.
pub fn render_and_score(
    renderer: &CalibratedRenderer,
    pack: &CalibrationPack,
    k: usize,
    setup: BallSetup,
) -> Result<(RgbImage, FrameScore), String> {
    let (grid, uz) = frame_surface_uz(pack, k, setup)?;
    let zeros = vec![0.0; grid.len()];
    let sim = renderer.render(&Surface {
        grid,
        ux_mm: &zeros,
        uy_mm: &zeros,
        uz_mm: &uz,
    });
    let real = &pack.frames[k];
    let (c, hw) = (pack.centers_px[k], 2.0 * pack.radii_px[k]);
    let score = FrameScore {
        frame: k,
        full: scores(real, &sim),
        crop: scores(&crop(real, c, hw), &crop(&sim, c, hw)),
    };
    Ok((sim, score))
}

/// Mean and median of each score over frames.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Summary {
    /// Frames scored.
    pub frames: usize,
    /// Means (full image).
    pub full_mean: Scores,
    /// Medians (full image).
    pub full_median: Scores,
    /// Means (crop).
    pub crop_mean: Scores,
    /// Medians (crop).
    pub crop_median: Scores,
}

/// Summarises per-frame scores (mean and median of PSNR, SSIM and MAE separately).
pub fn summarize(scores: &[FrameScore]) -> Summary {
    let stat = |pick: &dyn Fn(&FrameScore) -> Scores| {
        let get = |f: &dyn Fn(Scores) -> f64| -> (f64, f64) {
            let mut v: Vec<f64> = scores.iter().map(|s| f(pick(s))).collect();
            let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
            v.sort_by(f64::total_cmp);
            let median = match v.len() {
                0 => f64::NAN,
                n if n % 2 == 1 => v[n / 2],
                n => (v[n / 2 - 1] + v[n / 2]) / 2.0,
            };
            (mean, median)
        };
        let (p, pm) = get(&|s| s.psnr_db);
        let (s, sm) = get(&|s| s.ssim);
        let (m, mm) = get(&|s| s.mae);
        (
            Scores {
                psnr_db: p,
                ssim: s,
                mae: m,
            },
            Scores {
                psnr_db: pm,
                ssim: sm,
                mae: mm,
            },
        )
    };
    let (full_mean, full_median) = stat(&|s| s.full);
    let (crop_mean, crop_median) = stat(&|s| s.crop);
    Summary {
        frames: scores.len(),
        full_mean,
        full_median,
        crop_mean,
        crop_median,
    }
}
