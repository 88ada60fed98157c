//! `sparsh calibrate` and `sparsh sim2real`: the calibrated optics fitted on, and scored
//! against, real images of a ball pressed into a sensor (Taxim's calibration packs).

use std::path::Path;

use anyhow::{Context, Result, anyhow, bail};
use rayon::prelude::*;
use sparsh_optics::ball::BallMechanics;
use sparsh_optics::sim2real::{
    BallSetup, FitOptions, FrameRefit, FrameScore, ShadowSearch, calibrate_pack,
    calibrate_pack_with_shadows, pack_renderer, recorded_mechanics, refit_frame, render_and_score,
    summarize, summarize_refits,
};
use sparsh_optics::{Calibration, CalibrationPack, FrameSet};
use sparsh_scene::SensorConfig;

/// The `--mechanics` of `calibrate`, with the gel it needs.
pub fn mechanics(
    name: &str,
    thickness_mm: Option<f64>,
    poisson_ratio: f64,
) -> Result<BallMechanics> {
    let thickness =
        || thickness_mm.ok_or_else(|| anyhow!("--mechanics {name} needs --gel-thickness-mm"));
    let mechanics = match name {
        "hertz" => BallMechanics::Hertz,
        "halfspace" => BallMechanics::Halfspace,
        "geometric" => BallMechanics::Geometric {
            thickness_mm: thickness()?,
        },
        "layered" => BallMechanics::Layered {
            thickness_mm: thickness()?,
            poisson_ratio,
        },
        other => {
            bail!("--mechanics: unknown model {other:?} (hertz, geometric, halfspace, layered)")
        }
    };
    if thickness_mm.is_some()
        && matches!(mechanics, BallMechanics::Hertz | BallMechanics::Halfspace)
    {
        bail!("--gel-thickness-mm is used only with --mechanics geometric or layered");
    }
    if let Some(h) = thickness_mm
        && !(h.is_finite() && h > 0.0)
    {
        bail!("--gel-thickness-mm must be > 0, got {h}");
    }
    if !(poisson_ratio.is_finite() && poisson_ratio > -1.0 && poisson_ratio <= 0.5) {
        bail!("--poisson-ratio must be in (−1, 0.5], got {poisson_ratio}");
    }
    Ok(mechanics)
}

/// The mechanics a calibration was fitted under ([`recorded_mechanics`]), errors naming its
/// map.json.
fn mechanics_of(calib: &Path, calibration: &Calibration) -> Result<BallMechanics> {
    recorded_mechanics(calibration).map_err(|e| anyhow!("{}/{e}", calib.display()))
}

fn setup(ball_radius_mm: f64, mm_per_px: f64, mechanics: BallMechanics) -> Result<BallSetup> {
    if !(ball_radius_mm.is_finite() && ball_radius_mm > 0.0) {
        bail!("--ball-radius-mm must be > 0, got {ball_radius_mm}");
    }
    if !(mm_per_px.is_finite() && mm_per_px > 0.0) {
        bail!("--pixmm must be > 0, got {mm_per_px}");
    }
    Ok(BallSetup {
        ball_radius_mm,
        mm_per_px,
        mechanics,
    })
}

/// The pixel pitch of a Taxim pack: `--pixmm` when given, else `sensor.pixmm` of the
/// `params.json` beside the pack (Taxim's layout); one line on stderr says which.
fn pack_pixel_pitch(pack_path: &Path, pixmm: Option<f64>) -> Result<f64> {
    let params = pack_path.with_file_name("params.json");
    let recorded = || -> Result<f64> {
        let text = std::fs::read_to_string(&params).map_err(|e| {
            anyhow!(
                "{}: --pixmm not given and no params.json beside the pack to read the pixel pitch \
                 from ({e})",
                pack_path.display()
            )
        })?;
        let value: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| anyhow!("{}: not JSON: {e}", params.display()))?;
        match value
            .pointer("/sensor/pixmm")
            .and_then(serde_json::Value::as_f64)
        {
            Some(v) if v.is_finite() && v > 0.0 => Ok(v),
            Some(v) => bail!("{}: sensor.pixmm must be > 0, got {v}", params.display()),
            None => bail!(
                "{}: no number at sensor.pixmm (give --pixmm instead)",
                params.display()
            ),
        }
    };
    match pixmm {
        Some(v) => {
            if let Ok(r) = recorded()
                && r != v
            {
                eprintln!(
                    "{}: --pixmm {v} overrides the pack's {r} mm/px",
                    params.display()
                );
            }
            Ok(v)
        }
        None => {
            let v = recorded()?;
            eprintln!("{}: pixel pitch {v} mm/px", params.display());
            Ok(v)
        }
    }
}

/// The shadow options of `calibrate` and `sim2real`.
#[derive(Debug, Clone, Copy)]
pub struct ShadowOptions<'a> {
    /// Fit through (calibrate) or render with (sim2real) cast shadows.
    pub shadows: bool,
    /// Shadow-march samples per ray.
    pub steps: Option<u32>,
    /// Sensor preset (LED layout and shading).
    pub sensor: Option<&'a str>,
}

/// Longest shadow march accepted (samples per ray).
const MAX_SHADOW_STEPS: u32 = 1024;

fn shadow_steps(steps: u32) -> Result<u32> {
    if !(1..=MAX_SHADOW_STEPS).contains(&steps) {
        bail!("--shadow-steps must be in 1..={MAX_SHADOW_STEPS}, got {steps}");
    }
    Ok(steps)
}

fn preset(name: &str) -> Result<SensorConfig> {
    SensorConfig::preset(name).ok_or_else(|| {
        let names: Vec<&str> = sparsh_scene::PRESETS.iter().map(|(n, _)| *n).collect();
        anyhow!(
            "--sensor: unknown preset {name} (one of {})",
            names.join(", ")
        )
    })
}

/// Fits a calibration on `frames` of `pack` and saves it to `out`; with `shadows.shadows`,
/// through the shadows of `shadows.sensor`'s LEDs, their z fitted too.
pub fn calibrate(
    pack_path: &Path,
    ball_radius_mm: f64,
    mm_per_px: Option<f64>,
    frames: FrameSet,
    out: &Path,
    shadows: ShadowOptions,
    mechanics: BallMechanics,
) -> Result<()> {
    let setup = setup(
        ball_radius_mm,
        pack_pixel_pitch(pack_path, mm_per_px)?,
        mechanics,
    )?;
    let search = match (shadows.shadows, shadows.sensor) {
        (true, Some(name)) => Some(ShadowSearch::new(
            preset(name)?,
            shadow_steps(shadows.steps.unwrap_or(32))?,
        )),
        (true, None) => bail!(
            "--shadows needs --sensor, the preset whose LED layout starts the fit (gelsight2017, gelsight_mini_vga)"
        ),
        (false, Some(_)) => bail!("--sensor is used only with --shadows"),
        (false, None) => None,
    };
    let pack = CalibrationPack::read(pack_path)?;
    let picked = frames.indices(pack.frames.len());
    let started = std::time::Instant::now();
    let calibration = match &search {
        Some(search) => {
            let (calibration, report) =
                calibrate_pack_with_shadows(&pack, &picked, setup, FitOptions::default(), search)
                    .map_err(|e| anyhow!("{}: {e}", pack_path.display()))?;
            eprintln!(
                "{}: LEDs at z = {:?} mm: RMS error {:.3} on the fitting pixels, {:.2} % of pixel-LED pairs shadowed ({} layouts tried)",
                out.display(),
                report.best.light_z_mm,
                report.best.rms,
                100.0 * report.best.shadowed,
                report.trials.len()
            );
            calibration
        }
        None => calibrate_pack(&pack, &picked, setup, FitOptions::default())
            .map_err(|e| anyhow!("{}: {e}", pack_path.display()))?,
    };
    calibration
        .save(out)
        .map_err(|e| anyhow!("{}: {e}", out.display()))?;
    eprintln!(
        "{}: calibrated on {} frames of {} under {} in {:.1} s",
        out.display(),
        picked.len(),
        pack_path.display(),
        mechanics.describe(),
        started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// What `sparsh sim2real` scores and writes.
pub struct Sim2realOptions<'a> {
    /// Ball radius (mm).
    pub ball_radius_mm: f64,
    /// Pixel pitch of the pack (mm per pixel); default: the calibration's.
    pub mm_per_px: Option<f64>,
    /// Render with shadows (of the calibration's fitted LEDs when it has them).
    pub shadows: ShadowOptions<'a>,
    /// Frames to score.
    pub frames: FrameSet,
    /// Print JSON instead of a table.
    pub json: bool,
    /// Directory for each rendered frame.
    pub save: Option<&'a Path>,
    /// PNG of real | simulated | difference for the median frame.
    pub figure: Option<&'a Path>,
    /// Fit each scored frame's circle by rendering and compare the marks to the fits.
    pub refit: bool,
}

/// The pixel pitch of a sim2real run: recorded once, in the calibration's `map.json`
/// (`provenance.mm_per_px`); `--pixmm` may repeat it but not contradict it.
fn pitch(map_json: &Path, calibration: &Calibration, given: Option<f64>) -> Result<f64> {
    let recorded = calibration.provenance.get("mm_per_px");
    let recorded = match recorded {
        None => None,
        Some(v) => Some(
            v.as_f64()
                .filter(|p| p.is_finite() && *p > 0.0)
                .ok_or_else(|| {
                    anyhow!(
                        "{}: provenance.mm_per_px: expected a number > 0, got {v}",
                        map_json.display()
                    )
                })?,
        ),
    };
    match (recorded, given) {
        (Some(r), Some(g)) if (r - g).abs() > 1e-9 * r => bail!(
            "{}: provenance.mm_per_px is {r} but --pixmm is {g}; drop --pixmm or recalibrate",
            map_json.display()
        ),
        (Some(r), _) => Ok(r),
        (None, Some(g)) => Ok(g),
        (None, None) => bail!(
            "--pixmm is needed: {} records no provenance.mm_per_px",
            map_json.display()
        ),
    }
}

/// Renders the chosen frames of `pack` with the calibration in `calib` and prints PSNR, SSIM
/// and MAE over the full image and the crop of half-width 2a around the contact.
pub fn sim2real(pack_path: &Path, calib: &Path, options: Sim2realOptions) -> Result<()> {
    // The error names calib/map.json (or background.png) already.
    let calibration = Calibration::load(calib).map_err(anyhow::Error::msg)?;
    let map_json = calib.join("map.json");
    let setup = setup(
        options.ball_radius_mm,
        pitch(&map_json, &calibration, options.mm_per_px)?,
        mechanics_of(calib, &calibration)?,
    )?;
    let fitted = calibration.shadows.as_ref();
    let opts = options.shadows;
    let shadows = if opts.shadows {
        let name = opts
            .sensor
            .or(fitted.map(|f| f.sensor.as_str()))
            .ok_or_else(|| {
                anyhow!(
                    "--shadows needs --sensor here: {} was fitted without shadows and names no sensor",
                    map_json.display()
                )
            })?;
        let steps = shadow_steps(opts.steps.or(fitted.map(|f| f.steps)).unwrap_or(32))?;
        if fitted.is_none() {
            eprintln!(
                "{}: the map was fitted without shadows (calibrate --shadows fits it through them); casting {name}'s LEDs",
                map_json.display()
            );
        }
        Some((preset(name)?, steps))
    } else {
        if opts.sensor.is_some() || opts.steps.is_some() {
            bail!("--sensor and --shadow-steps are used only with --shadows");
        }
        if fitted.is_some() {
            eprintln!(
                "{}: the map was fitted through shadows; rendering without them (add --shadows)",
                map_json.display()
            );
        }
        None
    };
    let pack = CalibrationPack::read(pack_path)?;
    if let Some(dir) = options.save {
        std::fs::create_dir_all(dir).map_err(|e| anyhow!("{}: {e}", dir.display()))?;
    }
    let renderer = pack_renderer(
        &calibration,
        &pack,
        setup,
        shadows.as_ref().map(|(sensor, steps)| (sensor, *steps)),
    );
    let mut scores: Vec<FrameScore> = Vec::new();
    let mut images = Vec::new();
    for k in options.frames.indices(pack.frames.len()) {
        let (image, score) = render_and_score(&renderer, &pack, k, setup)
            .map_err(|e| anyhow!("{}: frame {k}: {e}", pack_path.display()))?;
        if let Some(dir) = options.save {
            let png = sparsh_data::encode_png(&image).map_err(anyhow::Error::msg)?;
            sparsh_data::write_atomic(&dir.join(format!("{k:03}.png")), &png)?;
        }
        scores.push(score);
        if options.figure.is_some() {
            images.push(image);
        }
    }
    if let Some(path) = options.figure
        && !scores.is_empty()
    {
        let mut order: Vec<usize> = (0..scores.len()).collect();
        order.sort_by(|&a, &b| scores[a].crop.psnr_db.total_cmp(&scores[b].crop.psnr_db));
        let median = order[order.len() / 2];
        let figure = side_by_side(&pack.frames[scores[median].frame], &images[median]);
        let png = sparsh_data::encode_png(&figure).map_err(anyhow::Error::msg)?;
        sparsh_data::write_atomic(path, &png)?;
        eprintln!(
            "{}: frame {} (median crop PSNR {:.2} dB)",
            path.display(),
            scores[median].frame,
            scores[median].crop.psnr_db
        );
    }
    let refits: Vec<FrameRefit> = if options.refit {
        let frames: Vec<usize> = scores.iter().map(|s| s.frame).collect();
        frames
            .par_iter()
            .map(|&k| {
                refit_frame(&renderer, &pack, k, setup)
                    .map_err(|e| anyhow!("{}: frame {k}: {e}", pack_path.display()))
            })
            .collect::<Result<_>>()?
    } else {
        Vec::new()
    };
    let json = options.json;
    let summary = summarize(&scores);
    if json {
        let mut out = serde_json::json!({
            "summary": summary,
            "frames": scores,
        });
        if options.refit {
            out["refit"] = serde_json::json!({
                "summary": summarize_refits(&refits),
                "frames": refits,
            });
        }
        println!("{}", serde_json::to_string_pretty(&out)?);
    } else {
        println!("| region | statistic | PSNR (dB) | SSIM | MAE (0–255) |");
        println!("|---|---|---|---|---|");
        for (region, stat, s) in [
            ("full", "mean", summary.full_mean),
            ("full", "median", summary.full_median),
            ("crop", "mean", summary.crop_mean),
            ("crop", "median", summary.crop_median),
        ] {
            println!(
                "| {region} | {stat} | {:.2} | {:.3} | {:.2} |",
                s.psnr_db, s.ssim, s.mae
            );
        }
        println!("{} frames", summary.frames);
        if options.refit {
            print_refits(&refits);
        }
    }
    Ok(())
}

/// The marks against the circles fitted by rendering, as `sim2real --refit` prints them.
fn print_refits(refits: &[FrameRefit]) {
    let r = summarize_refits(refits);
    println!();
    println!(
        "marks against the circles fitted by rendering ({} frames):",
        r.frames
    );
    println!(
        "  centre: median {:.2} px, p90 {:.2}; mean offset (fitted − marked) ({:+.2}, {:+.2}) px, median {:.2} px about it",
        r.centre_median_px,
        r.centre_p90_px,
        r.centre_mean_offset_px[0],
        r.centre_mean_offset_px[1],
        r.centre_median_about_offset_px
    );
    println!(
        "  radius: median {:.2} %, p90 {:.2} %; mean offset {:+.2} px",
        r.radius_median_pct, r.radius_p90_pct, r.radius_mean_offset_px
    );
    println!(
        "  RMS over the 2a window: {:.2} at the marks, {:.2} at the fits (medians, 0–255)",
        r.rms_marked_median, r.rms_fitted_median
    );
    println!(
        "  the fit on frames rendered at the fitted circles with noise of its residual: centre {:.2} px, radius {:.2} % (medians)",
        r.check_centre_median_px, r.check_radius_median_pct
    );
}

/// Taxim 1.4.1's CPU render of one 640×480 frame of the same ball press on the 2-core machine
/// the README's figures come from (JAX CPU on both cores; median of 10 after a warm-up, idle
/// machine; `crates/sparsh-optics/benches/taxim_render.py` re-measures it): with shadows,
/// without.
const TAXIM_640_MS: (f64, f64) = (595.2, 120.8);

/// `sparsh bench-optics`: median time per frame of each model, with and without shadows, at
/// 320×240 and 640×480 on each CPU thread count, against Taxim's CPU render at 640×480.
pub fn bench(
    calib: &Path,
    repeats: usize,
    threads: &[usize],
    device: crate::dataset::DeviceArg,
) -> Result<()> {
    use sparsh_optics::{PhotometricRenderer, Renderer, Surface, photometric::shadow_settings};
    anyhow::ensure!(repeats > 0, "--repeats must be at least 1");
    // the error names the file (CALIB/map.json)
    let calibration = Calibration::load(calib).map_err(anyhow::Error::msg)?;
    let preset = sparsh_scene::SensorConfig::preset("gelsight2017").expect("shipped preset");
    let gpu = device.context()?;
    let median_ms = |renderer: &Renderer, surface: &Surface| -> Result<f64> {
        renderer.render(surface)?;
        let mut times = Vec::with_capacity(repeats);
        for _ in 0..repeats {
            let t = std::time::Instant::now();
            std::hint::black_box(renderer.render(surface)?);
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(f64::total_cmp);
        Ok(times[times.len() / 2])
    };
    println!(
        "| model | size | shadows | device | threads | ms/frame | × faster than Taxim (640×480, same shadows) |"
    );
    println!("|---|---|---|---|---|---|---|");
    for (w, h) in [(320usize, 240usize), (640, 480)] {
        // The same 18.9 × 14.2 mm view at both sizes; a 2 mm ball pressed to a 1.2 mm contact.
        let mut sensor = preset.clone();
        sensor.width_px = w;
        sensor.height_px = h;
        sensor.mm_per_px = preset.mm_per_px * preset.width_px as f64 / w as f64;
        let grid = sensor.grid();
        let uz = sparsh_optics::ball::ball_press_uz_mm(grid, [1.0, -0.5], 1.2, 2.0)
            .map_err(anyhow::Error::msg)?;
        let zeros = vec![0.0; grid.len()];
        let surface = Surface {
            grid,
            ux_mm: &zeros,
            uy_mm: &zeros,
            uz_mm: &uz,
        };
        for shadows in [false, true] {
            let steps = 32;
            let photometric = Renderer::Photometric(PhotometricRenderer::new(
                &sensor,
                shadows.then(|| shadow_settings(&sensor, steps)),
            )?);
            let calibrated = sparsh_optics::CalibratedRenderer::new(&calibration, w, h);
            let calibrated = Renderer::Calibrated(if shadows {
                calibrated.with_shadows(&sensor, steps)
            } else {
                calibrated
            });
            for (name, renderer) in [("photometric", &photometric), ("calibrated", &calibrated)] {
                let taxim = if shadows {
                    TAXIM_640_MS.0
                } else {
                    TAXIM_640_MS.1
                };
                // Taxim was timed at 640×480 only: a ratio at another size would compare sizes
                let ratio = |ms: f64| match (w, h) {
                    (640, 480) => format!("{:.1}", taxim / ms),
                    _ => "–".into(),
                };
                let row = |device: &str, threads: &str, ms: f64| {
                    println!(
                        "| {name} | {w}×{h} | {} | {device} | {threads} | {ms:.1} | {} |",
                        if shadows { "yes" } else { "no" },
                        ratio(ms)
                    );
                };
                for &n in threads {
                    let pool = rayon::ThreadPoolBuilder::new()
                        .num_threads(n)
                        .build()
                        .context("cannot start a thread pool")?;
                    let ms = pool.install(|| median_ms(renderer, &surface))?;
                    row("cpu", &n.to_string(), ms);
                }
                if let Some(context) = &gpu {
                    let on_gpu = renderer.on_gpu(context)?;
                    row(
                        &format!("gpu ({})", context.adapter()),
                        "–",
                        median_ms(&on_gpu, &surface)?,
                    );
                }
            }
        }
    }
    println!(
        "Taxim 1.4.1, JAX CPU, 640×480 (benches/taxim_render.py on the README machine): {} ms with shadows, {} ms without.",
        TAXIM_640_MS.0, TAXIM_640_MS.1
    );
    Ok(())
}

/// real | simulated | 128 + 4·(simulated − real), side by side.
fn side_by_side(real: &image::RgbImage, sim: &image::RgbImage) -> image::RgbImage {
    let (w, h) = real.dimensions();
    image::RgbImage::from_fn(3 * w, h, |x, y| {
        let (panel, x) = (x / w, x % w);
        let (r, s) = (real.get_pixel(x, y).0, sim.get_pixel(x, y).0);
        match panel {
            0 => image::Rgb(r),
            1 => image::Rgb(s),
            _ => image::Rgb(std::array::from_fn(|c| {
                (128.0 + 4.0 * (s[c] as f64 - r[c] as f64)).clamp(0.0, 255.0) as u8
            })),
        }
    })
}
