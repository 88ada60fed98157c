//! Times one frame of each model with shadows on the GPU adapter, on the press that
//! `sparsh bench-optics` times (a 2 mm ball pressed to a 1.2 mm contact under the GelSight 2017
//! preset, 32 shadow steps): median of `REPEATS` after a warm-up, ms per frame.
//!
//! `cargo run --release -p sparsh-optics --example gpu_shadows [REPEATS]`

use std::path::Path;
use std::time::Instant;

use sparsh_optics::photometric::shadow_settings;
use sparsh_optics::{
    CalibratedRenderer, Calibration, GpuContext, PhotometricRenderer, Renderer, Surface,
};
use sparsh_scene::SensorConfig;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let repeats: usize = std::env::args().nth(1).map_or(Ok(7), |a| a.parse())?;
    let context = GpuContext::shared()?;
    println!("GPU adapter: {}", context.adapter());
    let calib = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/calib/gelsight");
    let calibration = Calibration::load(&calib)?;
    let preset = SensorConfig::preset("gelsight2017").expect("shipped preset");
    for (w, h) in [(320, 240), (640, 480)] {
        let mut sensor = preset.clone();
        sensor.width_px = w;
        sensor.height_px = h;
        sensor.mm_per_px = preset.mm_per_px * preset.width_px as f64 / w as f64;
        let grid = sensor.grid();
        let uz = sparsh_optics::ball::ball_press_uz_mm(grid, [1.0, -0.5], 1.2, 2.0)?;
        let zeros = vec![0.0; grid.len()];
        let surface = Surface {
            grid,
            ux_mm: &zeros,
            uy_mm: &zeros,
            uz_mm: &uz,
        };
        let models = [
            (
                "photometric",
                Renderer::Photometric(PhotometricRenderer::new(
                    &sensor,
                    Some(shadow_settings(&sensor, 32)),
                )?),
            ),
            (
                "calibrated",
                Renderer::Calibrated(
                    CalibratedRenderer::new(&calibration, w, h).with_shadows(&sensor, 32),
                ),
            ),
        ];
        for (name, cpu) in models {
            let gpu = cpu.on_gpu(&context)?;
            gpu.render(&surface)?;
            let mut ms: Vec<f64> = (0..repeats)
                .map(|_| {
                    let t = Instant::now();
                    std::hint::black_box(gpu.render(&surface)).map(|_| t.elapsed())
                })
                .map(|d| d.map(|d| d.as_secs_f64() * 1e3))
                .collect::<Result<_, _>>()?;
            ms.sort_by(f64::total_cmp);
            println!("{name} {w}×{h} with shadows: {:.1} ms", ms[ms.len() / 2]);
        }
    }
    Ok(())
}
