//! Calibration from a ball pack and the sim-to-real score: each real frame's ball indentation is
//! rendered (the surface under the marked contact circle, Hertz's or a rung's, see
//! [`crate::ball`]) and compared to
//! the real frame over the full image and over a square of half-width 2a around the contact; and
//! the circle each frame shows, fitted by rendering ([`fit_circle`]), against the pack's mark.

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
use crate::noise::gaussian;
use crate::pack::{CalibrationPack, Circle};
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

impl BallSetup {
    /// The set-up a calibration was fitted with, as its `map.json` records it
    /// (`provenance.ball_radius_mm`, `provenance.mm_per_px`, and [`recorded_mechanics`]).
    pub fn recorded(calibration: &Calibration) -> Result<BallSetup, String> {
        let positive = |key: &str| -> Result<f64, String> {
            let v = calibration.provenance.get(key);
            v.and_then(|v| v.as_f64())
                .filter(|x| x.is_finite() && *x > 0.0)
                .ok_or_else(|| {
                    format!(
                        "map.json: provenance.{key}: expected a number > 0, got {}",
                        v.map_or("nothing".into(), |v| v.to_string())
                    )
                })
        };
        Ok(BallSetup {
            ball_radius_mm: positive("ball_radius_mm")?,
            mm_per_px: positive("mm_per_px")?,
            mechanics: recorded_mechanics(calibration)?,
        })
    }
}

/// The mechanics a calibration was fitted under (`provenance.mechanics` of its `map.json`;
/// Hertz when absent, as every calibration before the field was).
pub fn recorded_mechanics(calibration: &Calibration) -> Result<BallMechanics, String> {
    match calibration.provenance.get("mechanics") {
        None => Ok(BallMechanics::Hertz),
        Some(v) => {
            let mechanics: BallMechanics = serde_json::from_value(v.clone())
                .map_err(|e| format!("map.json: provenance.mechanics: {e}"))?;
            mechanics
                .check()
                .map_err(|e| format!("map.json: provenance.{e}"))?;
            Ok(mechanics)
        }
    }
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
    circle_surface_uz(pack.size_px(), pack.marked_circle(k), setup)
        .map_err(|e| format!("touch_radius: frame {k}: {e}"))
}

/// The sensor grid of a `(width, height)` pixel image and the u_z field under `setup.mechanics`
/// of a ball whose contact circle is `circle`.
fn circle_surface_uz(
    (w, h): (usize, usize),
    circle: Circle,
    setup: BallSetup,
) -> Result<(Grid, Vec<f64>), String> {
    let grid = Grid {
        nx: w,
        ny: h,
        cell_mm: setup.mm_per_px,
    };
    let c = circle.centre_px;
    // Pixel i's centre is x_mm(i); the pack's coordinates are pixel indices.
    let centre_mm = [
        (c[0] + 0.5 - w as f64 / 2.0) * setup.mm_per_px,
        (c[1] + 0.5 - h as f64 / 2.0) * setup.mm_per_px,
    ];
    let a_mm = circle.radius_px * setup.mm_per_px;
    let uz = setup
        .mechanics
        .uz_mm(grid, centre_mm, a_mm, setup.ball_radius_mm)?;
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
            let v: Vec<f64> = scores.iter().map(|s| f(pick(s))).collect();
            let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
            (mean, quantile(v, 0.5))
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

/// Largest and smallest steps (pixels) of [`fit_circle`]'s compass search.
const FIT_STEPS_PX: (f64, f64) = (4.0, 1.0 / 32.0);
/// Renders [`fit_circle`] may spend on one frame before it reports non-convergence.
const FIT_MAX_RENDERS: usize = 800;

/// A contact circle fitted to a frame by rendering it ([`fit_circle`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CircleFit {
    /// The circle the search started from (for a pack's frame, its mark).
    pub start: Circle,
    /// The circle whose render is closest to the frame.
    pub fitted: Circle,
    /// RMS difference (0–255 units) over the window between the frame and the render of
    /// `start`, and of `fitted`.
    pub rms_start: f64,
    /// See `rms_start`.
    pub rms_fitted: f64,
    /// Renders the search took.
    pub renders: usize,
}

/// Pixels (x, y) of the square of half-width 2a around `circle`, inside a `(w, h)` image: the
/// window of the crop score ([`render_and_score`]).
fn window(circle: Circle, (w, h): (usize, usize)) -> Vec<usize> {
    let hw = 2.0 * circle.radius_px;
    let span = |c: f64, n: usize| {
        let lo = (c - hw).ceil().max(0.0) as usize;
        let hi = ((c + hw).floor().max(0.0) as usize).min(n - 1);
        lo..=hi
    };
    let (xs, ys) = (span(circle.centre_px[0], w), span(circle.centre_px[1], h));
    ys.flat_map(|y| xs.clone().map(move |x| y * w + x))
        .collect()
}

/// The linear render of a ball press whose contact circle is `circle`.
fn render_circle(
    renderer: &CalibratedRenderer,
    size: (usize, usize),
    circle: Circle,
    setup: BallSetup,
) -> Result<Vec<[f32; 3]>, String> {
    let (grid, uz) = circle_surface_uz(size, circle, setup)?;
    let zeros = vec![0.0; grid.len()];
    Ok(renderer.render_linear(&Surface {
        grid,
        ux_mm: &zeros,
        uy_mm: &zeros,
        uz_mm: &uz,
    }))
}

/// Fits the contact circle of `image` by rendering (analysis by synthesis): the centre and
/// radius whose ball press, rendered by `renderer` under `setup.mechanics`, is closest to the
/// image in RMS over the square of half-width 2a around `start` (a fixed window, so every
/// candidate is scored on the same pixels). Compass search (Kolda, Lewis & Torczon, SIAM Review
/// 45(3), 2003, §3): from `start`, each of centre x, centre y and radius is tried at ± the step,
/// the best improvement is taken, and the step halves when none improves, from 4 px down to
/// 1/32 px. Errors when the search has not converged within 800 renders, or when `start`
/// cannot be rendered.
pub fn fit_circle(
    renderer: &CalibratedRenderer,
    image: &RgbImage,
    start: Circle,
    setup: BallSetup,
) -> Result<CircleFit, String> {
    let size = (image.width() as usize, image.height() as usize);
    let pixels = window(start, size);
    let raw = image.as_raw();
    let rms = |circle: Circle| -> Result<f64, String> {
        let sim = render_circle(renderer, size, circle, setup)?;
        let sum: f64 = pixels
            .iter()
            .map(|&p| {
                (0..3)
                    .map(|ch| (f64::from(sim[p][ch]) - f64::from(raw[3 * p + ch])).powi(2))
                    .sum::<f64>()
            })
            .sum();
        Ok((sum / (3 * pixels.len()) as f64).sqrt())
    };
    let rms_start = rms(start)?;
    let mut renders = 1;
    let (mut best, mut best_rms) = (start, rms_start);
    let mut step = FIT_STEPS_PX.0;
    while step >= FIT_STEPS_PX.1 {
        let mut moved = None;
        for (axis, sign) in [
            (0, 1.0),
            (0, -1.0),
            (1, 1.0),
            (1, -1.0),
            (2, 1.0),
            (2, -1.0),
        ] {
            let mut trial = best;
            match axis {
                2 => trial.radius_px += sign * step,
                _ => trial.centre_px[axis] += sign * step,
            }
            renders += 1;
            // A radius the ball cannot make is not a candidate.
            if let Ok(e) = rms(trial)
                && e < moved.map_or(best_rms, |(_, m)| m)
            {
                moved = Some((trial, e));
            }
        }
        match moved {
            Some((trial, e)) => (best, best_rms) = (trial, e),
            None => step /= 2.0,
        }
        if renders > FIT_MAX_RENDERS {
            return Err(format!(
                "the circle fit did not converge in {FIT_MAX_RENDERS} renders (at step {step} px)"
            ));
        }
    }
    Ok(CircleFit {
        start,
        fitted: best,
        rms_start,
        rms_fitted: best_rms,
        renders,
    })
}

/// A frame rendered at `circle` with white Gaussian noise of standard deviation `noise_std`
/// (0–255 units, seeded by `seed`), rounded to 8 bits: the check of [`fit_circle`]'s precision.
pub fn noisy_render(
    renderer: &CalibratedRenderer,
    size: (usize, usize),
    circle: Circle,
    setup: BallSetup,
    noise_std: f64,
    seed: u64,
) -> Result<RgbImage, String> {
    let sim = render_circle(renderer, size, circle, setup)?;
    let raw: Vec<u8> = sim
        .iter()
        .enumerate()
        .flat_map(|(p, px)| {
            std::array::from_fn::<u8, 3, _>(|ch| {
                let n = noise_std * gaussian(seed, 0, (3 * p + ch) as u64);
                (f64::from(px[ch]) + n).round().clamp(0.0, 255.0) as u8
            })
        })
        .collect();
    Ok(RgbImage::from_raw(size.0 as u32, size.1 as u32, raw).expect("size matches"))
}

/// One frame's mark against the circle fitted by rendering, and the fit's precision there.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FrameRefit {
    /// Index of the frame in the pack.
    pub frame: usize,
    /// The fit to the real frame, started from its mark.
    pub fit: CircleFit,
    /// The same fit on a frame rendered at the fitted circle with white noise of the real
    /// fit's residual RMS, started from the mark again: its error is the fit's own.
    pub check: CircleFit,
}

/// Fits frame `k`'s circle by rendering, from its mark ([`fit_circle`]), then checks the fit on
/// a frame rendered at the fitted circle with noise of the fit's residual ([`noisy_render`],
/// seeded by `k`).
pub fn refit_frame(
    renderer: &CalibratedRenderer,
    pack: &CalibrationPack,
    k: usize,
    setup: BallSetup,
) -> Result<FrameRefit, String> {
    let mark = pack.marked_circle(k);
    let fit = fit_circle(renderer, &pack.frames[k], mark, setup)?;
    let synthetic = noisy_render(
        renderer,
        pack.size_px(),
        fit.fitted,
        setup,
        fit.rms_fitted,
        k as u64,
    )?;
    let check = fit_circle(renderer, &synthetic, mark, setup)
        .map_err(|e| format!("precision check: {e}"))?;
    Ok(FrameRefit {
        frame: k,
        fit,
        check,
    })
}

/// The marks of a pack against the circles fitted by rendering ([`refit_frame`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RefitSummary {
    /// Frames fitted.
    pub frames: usize,
    /// Median and 90th percentile of the distance between marked and fitted centre (px).
    pub centre_median_px: f64,
    /// See `centre_median_px`.
    pub centre_p90_px: f64,
    /// Mean of fitted − marked centre (px): the part a model trained on the marks learns.
    pub centre_mean_offset_px: [f64; 2],
    /// Median distance after removing that mean offset (px).
    pub centre_median_about_offset_px: f64,
    /// Median and 90th percentile of |fitted − marked radius| / marked radius (%).
    pub radius_median_pct: f64,
    /// See `radius_median_pct`.
    pub radius_p90_pct: f64,
    /// Mean of fitted − marked radius (px).
    pub radius_mean_offset_px: f64,
    /// Median RMS difference over the window at the marks and at the fitted circles (0–255).
    pub rms_marked_median: f64,
    /// See `rms_marked_median`.
    pub rms_fitted_median: f64,
    /// Median centre error (px) and radius error (%) of the precision checks.
    pub check_centre_median_px: f64,
    /// See `check_centre_median_px`.
    pub check_radius_median_pct: f64,
}

/// The `q` quantile of `values`, linearly interpolated between order statistics (numpy's
/// default); NaN for none.
fn quantile(mut values: Vec<f64>, q: f64) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    values.sort_by(f64::total_cmp);
    let pos = q * (values.len() - 1) as f64;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    values[lo] + (values[hi] - values[lo]) * (pos - lo as f64)
}

/// Summarises per-frame refits: distances, offsets and radius errors of the marks against the
/// fitted circles, and of the precision checks against their known circles.
pub fn summarize_refits(refits: &[FrameRefit]) -> RefitSummary {
    let n = refits.len().max(1) as f64;
    let dist = |a: Circle, b: Circle| {
        (a.centre_px[0] - b.centre_px[0]).hypot(a.centre_px[1] - b.centre_px[1])
    };
    let radius_pct = |truth: Circle, other: Circle| {
        100.0 * (other.radius_px - truth.radius_px).abs() / truth.radius_px
    };
    let offset: [f64; 2] = std::array::from_fn(|i| {
        refits
            .iter()
            .map(|r| r.fit.fitted.centre_px[i] - r.fit.start.centre_px[i])
            .sum::<f64>()
            / n
    });
    let centres: Vec<f64> = refits
        .iter()
        .map(|r| dist(r.fit.fitted, r.fit.start))
        .collect();
    let about_offset: Vec<f64> = refits
        .iter()
        .map(|r| {
            let d = |i: usize| r.fit.fitted.centre_px[i] - r.fit.start.centre_px[i] - offset[i];
            d(0).hypot(d(1))
        })
        .collect();
    let radii: Vec<f64> = refits
        .iter()
        .map(|r| radius_pct(r.fit.start, r.fit.fitted))
        .collect();
    let each = |f: &dyn Fn(&FrameRefit) -> f64| refits.iter().map(f).collect::<Vec<f64>>();
    RefitSummary {
        frames: refits.len(),
        centre_median_px: quantile(centres.clone(), 0.5),
        centre_p90_px: quantile(centres, 0.9),
        centre_mean_offset_px: offset,
        centre_median_about_offset_px: quantile(about_offset, 0.5),
        radius_median_pct: quantile(radii.clone(), 0.5),
        radius_p90_pct: quantile(radii, 0.9),
        radius_mean_offset_px: refits
            .iter()
            .map(|r| r.fit.fitted.radius_px - r.fit.start.radius_px)
            .sum::<f64>()
            / n,
        rms_marked_median: quantile(each(&|r| r.fit.rms_start), 0.5),
        rms_fitted_median: quantile(each(&|r| r.fit.rms_fitted), 0.5),
        check_centre_median_px: quantile(each(&|r| dist(r.check.fitted, r.fit.fitted)), 0.5),
        check_radius_median_pct: quantile(each(&|r| radius_pct(r.fit.fitted, r.check.fitted)), 0.5),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn refit(
        start: ([f64; 2], f64),
        fitted: ([f64; 2], f64),
        check: ([f64; 2], f64),
    ) -> FrameRefit {
        let circle = |(centre_px, radius_px): ([f64; 2], f64)| Circle {
            centre_px,
            radius_px,
        };
        let fit = |s, f| CircleFit {
            start: circle(s),
            fitted: circle(f),
            rms_start: 4.0,
            rms_fitted: 3.0,
            renders: 10,
        };
        FrameRefit {
            frame: 0,
            fit: fit(start, fitted),
            check: fit(start, check),
        }
    }

    /// Three frames worked by hand: fitted − marked centres (3, 4), (0, 0) and (−6, 8) are 5, 0
    /// and 10 px off (median 5, p90 at 0.8 between 5 and 10: 9); their mean offset is (−1, 4),
    /// about which the distances are √(16 + 0), √(1 + 16), √(25 + 16) (median √17); radii 60 →
    /// 63, 50 → 50, 40 → 38 are 5 %, 0 % and 5 % off (mean offset +1/3 px).
    #[test]
    fn refit_summaries_match_hand_computed_statistics() {
        let refits = [
            refit(
                ([10.0, 10.0], 60.0),
                ([13.0, 14.0], 63.0),
                ([13.0, 14.1], 63.0),
            ),
            refit(
                ([50.0, 50.0], 50.0),
                ([50.0, 50.0], 50.0),
                ([50.3, 50.4], 50.5),
            ),
            refit(
                ([90.0, 90.0], 40.0),
                ([84.0, 98.0], 38.0),
                ([84.0, 98.0], 38.0),
            ),
        ];
        let s = summarize_refits(&refits);
        assert_eq!(s.frames, 3);
        assert!((s.centre_median_px - 5.0).abs() < 1e-12, "{s:?}");
        assert!((s.centre_p90_px - 9.0).abs() < 1e-12, "{s:?}");
        assert!((s.centre_mean_offset_px[0] + 1.0).abs() < 1e-12, "{s:?}");
        assert!((s.centre_mean_offset_px[1] - 4.0).abs() < 1e-12, "{s:?}");
        assert!(
            (s.centre_median_about_offset_px - 17f64.sqrt()).abs() < 1e-12,
            "{s:?}"
        );
        assert!((s.radius_median_pct - 5.0).abs() < 1e-12, "{s:?}");
        assert!((s.radius_mean_offset_px - 1.0 / 3.0).abs() < 1e-12, "{s:?}");
        // checks off by 0.1, 0.5 and 0 px; radius by 0, 1 and 0 %
        assert!((s.check_centre_median_px - 0.1).abs() < 1e-9, "{s:?}");
        assert_eq!(s.check_radius_median_pct, 0.0);
        assert_eq!((s.rms_marked_median, s.rms_fitted_median), (4.0, 3.0));
    }
}
