//! The GPU path against the CPU path: the same surfaces give images within one 8-bit level per
//! channel, for both models with and without shadows, at both sensor resolutions. Without a GPU adapter the tests say so
//! and pass, unless `SPARSH_REQUIRE_GPU=1` (set in CI, which installs Mesa's lavapipe).

use image::RgbImage;
use sparsh_optics::ball::ball_press_uz_mm;
use sparsh_optics::photometric::shadow_settings;
use sparsh_optics::{
    CalibratedRenderer, Calibration, ColourMap, FittedLights, GpuContext, PhotometricRenderer,
    Renderer, Surface,
};
use sparsh_scene::{Grid, Light, SensorConfig};

fn context() -> Option<GpuContext> {
    match GpuContext::shared() {
        Ok(ctx) => {
            eprintln!("GPU adapter: {}", ctx.adapter());
            Some(ctx)
        }
        Err(e) if std::env::var("SPARSH_REQUIRE_GPU").as_deref() == Ok("1") => {
            panic!("SPARSH_REQUIRE_GPU=1 but {e}")
        }
        Err(e) => {
            eprintln!("skipped: {e}");
            None
        }
    }
}

/// A ball pressed off-centre with a sheared, swirling lateral field: slopes of every direction
/// and sizes from flat to steep at the contact rim.
struct Deformation {
    grid: Grid,
    ux: Vec<f64>,
    uy: Vec<f64>,
    uz: Vec<f64>,
}

impl Deformation {
    fn ball(grid: Grid, centre_mm: [f64; 2], contact_radius_mm: f64) -> Deformation {
        let uz = ball_press_uz_mm(grid, centre_mm, contact_radius_mm, 2.0).unwrap();
        let (mut ux, mut uy) = (Vec::new(), Vec::new());
        for j in 0..grid.ny {
            for i in 0..grid.nx {
                let (x, y) = (grid.x_mm(i) - centre_mm[0], grid.y_mm(j) - centre_mm[1]);
                let bump = 0.08 * (-(x * x + y * y) / 4.0).exp();
                ux.push(bump * (1.0 - y));
                uy.push(bump * (0.5 + x));
            }
        }
        Deformation { grid, ux, uy, uz }
    }

    fn surface(&self) -> Surface<'_> {
        Surface {
            grid: self.grid,
            ux_mm: &self.ux,
            uy_mm: &self.uy,
            uz_mm: &self.uz,
        }
    }
}

/// Largest per-channel difference and the number of channels that differ at all.
fn difference(a: &RgbImage, b: &RgbImage) -> (u8, usize) {
    assert_eq!(a.dimensions(), b.dimensions());
    a.as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(x, y)| x.abs_diff(*y))
        .fold((0, 0), |(m, n), d| (m.max(d), n + usize::from(d > 0)))
}

/// Renders two surfaces on both paths (the GPU renderer reused between them), checks parity,
/// run-to-run identity on the GPU, and that the contact really changed the image.
fn check_parity(label: &str, cpu: Renderer, ctx: &GpuContext, surfaces: [Deformation; 2]) {
    let gpu = cpu.on_gpu(ctx).unwrap();
    let background = cpu.background();
    assert_eq!(gpu.background(), background);
    for (k, d) in surfaces.iter().enumerate() {
        let want = cpu.render(&d.surface()).unwrap();
        let got = gpu.render(&d.surface()).unwrap();
        let (max, count) = difference(&want, &got);
        let n = want.as_raw().len();
        eprintln!(
            "{label} surface {k}: max abs difference {max}/255, {count} of {n} channels differ"
        );
        assert!(max <= 1, "{label} surface {k}: CPU and GPU differ by {max}");
        // Before rounding: f32 against the CPU's f64 arithmetic.
        let linear = cpu
            .render_linear(&d.surface())
            .unwrap()
            .iter()
            .zip(&gpu.render_linear(&d.surface()).unwrap())
            .flat_map(|(a, b)| (0..3).map(move |ch| (a[ch] - b[ch]).abs()))
            .fold(0.0f32, f32::max);
        eprintln!("{label} surface {k}: before rounding, max abs difference {linear:.2e}");
        assert!(
            linear < 0.1,
            "{label} surface {k}: linear values differ by {linear}"
        );
        let (contrast, _) = difference(&want, &background);
        assert!(
            contrast >= 20,
            "{label} surface {k}: the contact barely shows ({contrast})"
        );
        assert_eq!(
            gpu.render(&d.surface()).unwrap(),
            got,
            "{label}: GPU image not repeatable"
        );
    }
}

fn digit(width_px: usize, height_px: usize) -> SensorConfig {
    let mut sensor = SensorConfig::preset("digit").unwrap();
    sensor.mm_per_px *= sensor.width_px as f64 / width_px as f64;
    sensor.width_px = width_px;
    sensor.height_px = height_px;
    sensor
}

fn two_presses(grid: Grid) -> [Deformation; 2] {
    [
        Deformation::ball(grid, [1.3, -0.7], 1.1),
        Deformation::ball(grid, [-3.0, 2.0], 1.6),
    ]
}

/// The shadows must change the image, or their parity would prove nothing.
fn assert_shadows_show(label: &str, plain: &Renderer, shadowed: &Renderer, grid: Grid) {
    let d = &two_presses(grid)[0];
    let (a, b) = (
        plain.render(&d.surface()).unwrap(),
        shadowed.render(&d.surface()).unwrap(),
    );
    let (max, count) = difference(&a, &b);
    assert!(
        max >= 5 && count >= 100,
        "{label}: shadows change {count} channels by at most {max}"
    );
}

#[test]
fn photometric_model_matches_the_cpu() {
    let Some(ctx) = context() else { return };
    for (w, h) in [(320, 240), (640, 480)] {
        let sensor = digit(w, h);
        let plain = Renderer::Photometric(PhotometricRenderer::new(&sensor, None).unwrap());
        let settings = shadow_settings(&sensor, 32);
        let shadowed =
            Renderer::Photometric(PhotometricRenderer::new(&sensor, Some(settings)).unwrap());
        assert_shadows_show("photometric", &plain, &shadowed, sensor.grid());
        for (label, cpu) in [("", plain), (" with shadows", shadowed)] {
            check_parity(
                &format!("photometric {w}×{h}{label}"),
                cpu,
                &ctx,
                two_presses(sensor.grid()),
            );
        }
    }
}

/// A smooth map with colour changes of ±80 levels over the normal disc and a position-dependent
/// part, over a background with a gradient and texture.
fn synthetic_calibration(width_px: usize, height_px: usize) -> Calibration {
    let nodes = 17;
    let mut coef = Vec::new();
    for b in 0..3 {
        for v in 0..nodes {
            for u in 0..nodes {
                let (nu, nv) = (
                    2.0 * u as f32 / (nodes - 1) as f32 - 1.0,
                    2.0 * v as f32 / (nodes - 1) as f32 - 1.0,
                );
                let scale = [80.0, 25.0, -30.0][b];
                coef.push([
                    scale * (2.0 * nu).sin(),
                    scale * (1.5 * nv + 0.3 * nu).sin(),
                    scale * (nu * nu - nv * nv),
                ]);
            }
        }
    }
    let background = RgbImage::from_fn(width_px as u32, height_px as u32, |x, y| {
        image::Rgb([
            (60 + x * 120 / width_px as u32) as u8,
            (90 + y * 100 / height_px as u32) as u8,
            (110 + (x * 7 + y * 13) % 40) as u8,
        ])
    });
    Calibration {
        map: ColourMap {
            format: "sparsh-calibrated-map/1".into(),
            nodes,
            coef,
        },
        background,
        provenance: serde_json::Value::Null,
        shadows: None,
    }
}

/// The calibration fitted through shadows of lights other than the sensor's: `sensor`'s LEDs
/// turned by 40° about the axis and lowered to z = −2.5 mm, with 0.6 mm emitters.
fn with_fitted_lights(calibration: Calibration, sensor: &SensorConfig) -> Calibration {
    let (sin, cos) = 40f64.to_radians().sin_cos();
    let lights = sensor
        .lights
        .iter()
        .map(|l| {
            let [x, y, _] = l.position_mm;
            Light {
                position_mm: [cos * x - sin * y, sin * x + cos * y, -2.5],
                ..l.clone()
            }
        })
        .collect();
    Calibration {
        shadows: Some(FittedLights {
            sensor: sensor.name.clone(),
            lights,
            led_radius_mm: 0.6,
            steps: 32,
        }),
        ..calibration
    }
}

#[test]
fn calibrated_model_matches_the_cpu() {
    let Some(ctx) = context() else { return };
    for (w, h) in [(320, 240), (640, 480)] {
        let sensor = digit(w, h);
        let cal = synthetic_calibration(w, h);
        let plain = Renderer::Calibrated(CalibratedRenderer::new(&cal, w, h));
        let shadowed =
            Renderer::Calibrated(CalibratedRenderer::new(&cal, w, h).with_shadows(&sensor, 32));
        assert_shadows_show("calibrated", &plain, &shadowed, sensor.grid());
        let fitted = with_fitted_lights(cal, &sensor);
        let refitted =
            Renderer::Calibrated(CalibratedRenderer::new(&fitted, w, h).with_shadows(&sensor, 32));
        assert_shadows_show("fitted lights", &shadowed, &refitted, sensor.grid());
        for (label, cpu) in [
            ("", plain),
            (" with shadows", shadowed),
            (" with shadows of fitted lights", refitted),
        ] {
            check_parity(
                &format!("calibrated {w}×{h}{label}"),
                cpu,
                &ctx,
                two_presses(sensor.grid()),
            );
        }
    }
}
