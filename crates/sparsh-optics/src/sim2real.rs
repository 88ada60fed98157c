//! Calibration from a ball pack and the sim-to-real score: each real frame's ball indentation is
//! rendered (Hertz surface from the marked contact radius, see [`crate::ball`]) and compared to
//! the real frame over the full image and over a square of half-width 2a around the contact.

use image::RgbImage;
use rayon::prelude::*;
use serde::Serialize;
use sparsh_scene::{Grid, SensorConfig};

use crate::calibrated::{CalibratedRenderer, Calibration, MapFitter};
use crate::metrics::{Scores, crop, scores};
use crate::pack::CalibrationPack;
use crate::{Surface, ball};

/// Pixels farther than this many contact radii from the contact count as background.
const BACKGROUND_RADII: f64 = 3.0;

/// The physical set-up of a pack: ball radius and pixel pitch.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct BallSetup {
    /// Radius of the calibration ball (mm).
    pub ball_radius_mm: f64,
    /// Pixel pitch on the gel (mm per pixel).
    pub mm_per_px: f64,
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

/// The sensor grid of a pack and the Hertz u_z field of its frame `k`.
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
    let uz = ball::ball_press_uz_mm(grid, centre_mm, a_mm, setup.ball_radius_mm)
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
    let bg: Vec<[f32; 3]> = background.pixels().map(|p| p.0.map(f32::from)).collect();
    let surfaces = frames
        .iter()
        .map(|&k| frame_surface_uz(pack, k, setup))
        .collect::<Result<Vec<_>, _>>()?;
    // One accumulator per frame, summed in frame order: the result does not depend on threads.
    let partials: Vec<MapFitter> = frames
        .par_iter()
        .zip(&surfaces)
        .map(|(&k, (grid, uz))| {
            let zeros = vec![0.0; grid.len()];
            let surface = Surface {
                grid: *grid,
                ux_mm: &zeros,
                uy_mm: &zeros,
                uz_mm: uz,
            };
            let mut fit = MapFitter::new(options.nodes);
            let far = far_from_contact(pack, k);
            fit.add_frame(&surface, &pack.frames[k], &bg, |i, j| !far(i, j));
            fit
        })
        .collect();
    let mut total = MapFitter::new(options.nodes);
    for p in &partials {
        total.merge(p);
    }
    let map = total.solve(options.smoothness)?;
    Ok(Calibration {
        map,
        background,
        provenance: serde_json::json!({
            "frames": frames,
            "ball_radius_mm": setup.ball_radius_mm,
            "mm_per_px": setup.mm_per_px,
            "nodes": options.nodes,
            "smoothness": options.smoothness,
            "fit_pixels": total.samples(),
        }),
    })
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
