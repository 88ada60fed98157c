//! The shadow-aware calibration on frames whose answer is known: a ball pack synthesised from a
//! known colour map over a known background, under the GelSight 2017 preset's LEDs at a known
//! z with cast shadows (I_ch = (bg_ch + ΔI_ch)·S_ch, the forward model of the calibrated
//! renderer). The fit must find the LEDs' z and reproduce held-out frames better than the
//! shadow-free fit; calibrations with fitted lights reach scenes through `map.json`.

use image::RgbImage;
use sparsh_optics::ball::BallMechanics;
use sparsh_optics::sim2real::{
    BallSetup, FitOptions, ShadowSearch, calibrate_pack, calibrate_pack_with_shadows,
    frame_surface_uz, pack_renderer, render_and_score, summarize,
};
use sparsh_optics::{
    CalibratedRenderer, Calibration, CalibrationPack, ColourMap, FittedLights, ImageFormation,
    Surface,
};
use sparsh_scene::{OpticsModel, OpticsSpec, SensorConfig};

const W: usize = 240;
const H: usize = 180;
const SETUP: BallSetup = BallSetup {
    ball_radius_mm: 2.0,
    mm_per_px: 0.059,
    mechanics: BallMechanics::Hertz,
};
/// The LEDs' z the frames are made with (mm).
const TRUE_Z_MM: f64 = -4.0;
const STEPS: u32 = 32;

/// The preset whose LED layout (x, y, colours) the frames and the fit share.
fn sensor() -> SensorConfig {
    let mut s = SensorConfig::preset("gelsight2017").unwrap();
    s.width_px = W;
    s.height_px = H;
    s.mm_per_px = SETUP.mm_per_px;
    s
}

/// The known map: each table affine in the normal (bilinear tables hold it exactly), with a
/// position term, node values written out from n = (2u/(N − 1) − 1, 2v/(N − 1) − 1).
fn true_map() -> ColourMap {
    let nodes = 17;
    let mut coef = Vec::new();
    for b in 0..3 {
        for v in 0..nodes {
            for u in 0..nodes {
                let nx = 2.0 * u as f32 / (nodes - 1) as f32 - 1.0;
                let ny = 2.0 * v as f32 / (nodes - 1) as f32 - 1.0;
                coef.push(match b {
                    0 => [
                        60.0 * nx - 20.0 * ny,
                        -40.0 * nx + 50.0 * ny,
                        25.0 * nx + 35.0 * ny,
                    ],
                    1 => [30.0 * nx, 0.0, 0.0],
                    _ => [0.0, 20.0 * ny, 0.0],
                });
            }
        }
    }
    ColourMap {
        format: "sparsh-calibrated-map/1".into(),
        nodes,
        coef,
    }
}

fn background() -> RgbImage {
    RgbImage::from_fn(W as u32, H as u32, |x, y| {
        image::Rgb([
            (100 + x / 4) as u8,
            (120 + y / 4) as u8,
            (90 + (x + y) / 8) as u8,
        ])
    })
}

/// The known map as a calibration fitted through the preset's LEDs moved to z = `z_mm`.
fn calibration_at(z_mm: f64) -> Calibration {
    let s = sensor();
    let lights = s
        .lights
        .iter()
        .map(|l| sparsh_scene::Light {
            position_mm: [l.position_mm[0], l.position_mm[1], z_mm],
            ..l.clone()
        })
        .collect();
    Calibration {
        map: true_map(),
        background: background(),
        provenance: serde_json::Value::Null,
        shadows: Some(FittedLights {
            sensor: s.name.clone(),
            lights,
            led_radius_mm: s.led_radius_mm,
            steps: STEPS,
        }),
    }
}

/// Twelve presses (contact radius 0.6–1.0 mm) spread over the view, rendered with shadows.
fn synthetic_pack() -> CalibrationPack {
    let centers_px: Vec<[f64; 2]> = (0..12)
        .map(|k| {
            let t = k as f64;
            [
                (60.0 + 11.0 * t + 20.0 * (1.7 * t).sin()).round(),
                (60.0 + 5.0 * t + 15.0 * (1.1 * t).cos()).round(),
            ]
        })
        .collect();
    let radii_px: Vec<f64> = (0..12).map(|k| 10.0 + (k % 5) as f64 * 1.7).collect();
    let mut pack = CalibrationPack {
        background: background(),
        frames: Vec::new(),
        centers_px,
        radii_px,
    };
    let renderer =
        CalibratedRenderer::new(&calibration_at(TRUE_Z_MM), W, H).with_shadows(&sensor(), STEPS);
    for k in 0..12 {
        let (grid, uz) = frame_surface_uz(&pack, k, SETUP).unwrap();
        let zeros = vec![0.0; grid.len()];
        pack.frames.push(renderer.render(&Surface {
            grid,
            ux_mm: &zeros,
            uy_mm: &zeros,
            uz_mm: &uz,
        }));
    }
    pack
}

#[test]
fn shadow_aware_fit_recovers_the_led_height_and_beats_the_shadow_free_fit() {
    let pack = synthetic_pack();
    let even: Vec<usize> = (0..12).step_by(2).collect();
    let search = ShadowSearch {
        common_z_mm: vec![-2.0, -3.0, -4.0, -5.0, -6.0, -8.0, -12.0],
        ..ShadowSearch::new(sensor(), STEPS)
    };
    let (fitted, report) =
        calibrate_pack_with_shadows(&pack, &even, SETUP, FitOptions::default(), &search).unwrap();
    eprintln!("kept {:?}", report.best);
    assert!(report.best.shadowed > 0.01, "the frames carry shadows");
    let lights = &fitted.shadows.as_ref().unwrap().lights;
    for l in lights {
        let z = l.position_mm[2];
        assert!(
            (z - TRUE_Z_MM).abs() <= 1.0,
            "LED z {z} mm, truth {TRUE_Z_MM}"
        );
    }
    // Held-out frames: the shadow-aware map with its shadows against the shadow-free map.
    let plain = calibrate_pack(&pack, &even, SETUP, FitOptions::default()).unwrap();
    let score = |cal: &Calibration, shadows: bool| {
        let s = sensor();
        let renderer = pack_renderer(cal, &pack, SETUP, shadows.then_some((&s, STEPS)));
        let scores: Vec<_> = (1..12)
            .step_by(2)
            .map(|k| render_and_score(&renderer, &pack, k, SETUP).unwrap().1)
            .collect();
        summarize(&scores).crop_mean
    };
    let (aware, free) = (score(&fitted, true), score(&plain, false));
    eprintln!("held-out crops: shadow-aware {aware:?}, shadow-free {free:?}");
    assert!(
        aware.psnr_db > free.psnr_db + 3.0,
        "shadow-aware {} dB, shadow-free {} dB",
        aware.psnr_db,
        free.psnr_db
    );
    assert!(aware.mae < free.mae, "{} vs {}", aware.mae, free.mae);
}

/// The fitted lights survive `map.json`, reach a scene's image formation (which then casts
/// them rather than the sensor's), and old calibrations without them still load.
#[test]
fn fitted_lights_go_through_map_json_into_scenes() {
    // 6 mm below the gel: not the preset's 4 mm.
    let truth = calibration_at(-6.0);
    let dir = tempfile::tempdir().unwrap();
    truth.save(dir.path()).unwrap();
    let loaded = Calibration::load(dir.path()).unwrap();
    assert_eq!(loaded.shadows, truth.shadows);
    assert_eq!(loaded.map, truth.map);

    // Markers off: only the model's image is compared.
    let sensor = SensorConfig {
        markers: None,
        ..sensor()
    };
    let optics = OpticsSpec {
        model: OpticsModel::Calibrated,
        calibration: Some(dir.path().to_path_buf()),
        shadows: true,
        ..OpticsSpec::default()
    };
    let scene = ImageFormation::new(&sensor, &optics, 0, None).unwrap();
    // The same map without fitted lights, under a sensor that carries the fitted ones.
    let mut moved = sensor.clone();
    moved.lights = truth.shadows.clone().unwrap().lights;
    let unfitted = Calibration {
        shadows: None,
        ..truth.clone()
    };
    let expected = CalibratedRenderer::new(&unfitted, W, H).with_shadows(&moved, STEPS);
    let preset = CalibratedRenderer::new(&unfitted, W, H).with_shadows(&sensor, STEPS);
    let pack = synthetic_pack();
    let (grid, uz) = frame_surface_uz(&pack, 3, SETUP).unwrap();
    let zeros = vec![0.0; grid.len()];
    let surface = Surface {
        grid,
        ux_mm: &zeros,
        uy_mm: &zeros,
        uz_mm: &uz,
    };
    let image = scene.render(&surface, 0).unwrap();
    assert!(
        image == expected.render(&surface),
        "the fitted LEDs are cast"
    );
    assert!(
        image != preset.render(&surface),
        "the preset's LEDs sit elsewhere"
    );

    let shipped =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/calib/gelsight");
    assert_eq!(Calibration::load(&shipped).unwrap().shadows, None);
}

#[test]
fn inconsistent_shadow_fields_are_named() {
    let dir = tempfile::tempdir().unwrap();
    calibration_at(TRUE_Z_MM).save(dir.path()).unwrap();
    let path = dir.path().join("map.json");
    let text = std::fs::read_to_string(&path).unwrap();
    let mut json: serde_json::Value = serde_json::from_str(&text).unwrap();
    let cases = [
        ("lights", serde_json::Value::Null, "lights: missing"),
        ("shadows", false.into(), "given but shadows is not true"),
        ("shadow_steps", 0.into(), "shadow_steps: must be at least 1"),
        ("led_radius_mm", (-1.0).into(), "led_radius_mm"),
    ];
    for (field, value, needle) in cases {
        let mut bad = json.clone();
        if value.is_null() {
            bad.as_object_mut().unwrap().remove(field);
        } else {
            bad[field] = value;
        }
        std::fs::write(&path, bad.to_string()).unwrap();
        let e = Calibration::load(dir.path()).unwrap_err();
        assert!(e.contains("map.json") && e.contains(needle), "{field}: {e}");
        assert_eq!(e.lines().count(), 1, "{e}");
    }
    json["lights"] = serde_json::json!([]);
    std::fs::write(&path, json.to_string()).unwrap();
    let e = Calibration::load(dir.path()).unwrap_err();
    assert!(e.contains("lights: empty"), "{e}");
}
