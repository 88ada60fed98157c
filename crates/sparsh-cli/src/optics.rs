//! `sparsh calibrate` and `sparsh sim2real`: the calibrated optics fitted on, and scored
//! against, real images of a ball pressed into a sensor (Taxim's calibration packs).

use std::path::Path;

use anyhow::{Result, anyhow, bail};
use sparsh_optics::CalibrationPack;
use sparsh_optics::sim2real::{
    BallSetup, FitOptions, FrameScore, calibrate_pack, pack_renderer, render_and_score, summarize,
};

/// Which frames of a pack to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum FrameSet {
    /// Frames 0, 2, 4, …
    Even,
    /// Frames 1, 3, 5, …
    Odd,
    /// Every frame.
    All,
}

impl FrameSet {
    fn indices(self, count: usize) -> Vec<usize> {
        (0..count)
            .filter(|k| match self {
                FrameSet::Even => k % 2 == 0,
                FrameSet::Odd => k % 2 == 1,
                FrameSet::All => true,
            })
            .collect()
    }
}

fn setup(ball_radius_mm: f64, mm_per_px: f64) -> Result<BallSetup> {
    if !(ball_radius_mm.is_finite() && ball_radius_mm > 0.0) {
        bail!("--ball-radius-mm must be > 0, got {ball_radius_mm}");
    }
    if !(mm_per_px.is_finite() && mm_per_px > 0.0) {
        bail!("--pixmm must be > 0, got {mm_per_px}");
    }
    Ok(BallSetup {
        ball_radius_mm,
        mm_per_px,
    })
}

/// Fits a calibration on `frames` of `pack` and saves it to `out`.
pub fn calibrate(
    pack_path: &Path,
    ball_radius_mm: f64,
    mm_per_px: f64,
    frames: FrameSet,
    out: &Path,
) -> Result<()> {
    let setup = setup(ball_radius_mm, mm_per_px)?;
    let pack = CalibrationPack::read(pack_path)?;
    let picked = frames.indices(pack.frames.len());
    let calibration = calibrate_pack(&pack, &picked, setup, FitOptions::default())
        .map_err(|e| anyhow!("{}: {e}", pack_path.display()))?;
    calibration
        .save(out)
        .map_err(|e| anyhow!("{}: {e}", out.display()))?;
    eprintln!(
        "{}: calibrated on {} frames of {}",
        out.display(),
        picked.len(),
        pack_path.display()
    );
    Ok(())
}

/// Renders `frames` of `pack` with the calibration in `calib` and prints PSNR, SSIM and MAE
/// over the full image and the crop of half-width 2a around the contact.
pub fn sim2real(
    pack_path: &Path,
    calib: &Path,
    ball_radius_mm: f64,
    mm_per_px: f64,
    frames: FrameSet,
    json: bool,
    save: Option<&Path>,
) -> Result<()> {
    let setup = setup(ball_radius_mm, mm_per_px)?;
    let pack = CalibrationPack::read(pack_path)?;
    let calibration =
        sparsh_optics::Calibration::load(calib).map_err(|e| anyhow!("{}: {e}", calib.display()))?;
    if let Some(dir) = save {
        std::fs::create_dir_all(dir).map_err(|e| anyhow!("{}: {e}", dir.display()))?;
    }
    let renderer = pack_renderer(&calibration, &pack, setup, None);
    let mut scores: Vec<FrameScore> = Vec::new();
    for k in frames.indices(pack.frames.len()) {
        let (image, score) = render_and_score(&renderer, &pack, k, setup)
            .map_err(|e| anyhow!("{}: frame {k}: {e}", pack_path.display()))?;
        if let Some(dir) = save {
            let png = sparsh_data::encode_png(&image).map_err(anyhow::Error::msg)?;
            sparsh_data::write_atomic(&dir.join(format!("{k:03}.png")), &png)?;
        }
        scores.push(score);
    }
    let summary = summarize(&scores);
    if json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "summary": summary,
                "frames": scores,
            }))?
        );
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
    }
    Ok(())
}
