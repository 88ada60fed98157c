//! Calibration on synthetic packs whose answer is known: frames rendered from a known
//! gradient→colour map over a known background, written as Taxim-style npz files.

use std::path::Path;

use npyz::WriterBuilder;
use sparsh_optics::ball::BallMechanics;
use sparsh_optics::sim2real::{
    BallSetup, FitOptions, calibrate_pack, fit_circle, refit_frame, render_and_score, summarize,
    summarize_refits,
};
use sparsh_optics::{Calibration, CalibrationPack, Circle, Surface};

const W: usize = 96;
const H: usize = 72;
const SETUP: BallSetup = BallSetup {
    ball_radius_mm: 2.0,
    mm_per_px: 0.05,
    mechanics: BallMechanics::Hertz,
};

/// The known map: colour change affine in the normal's lateral components, with a position
/// term, as the calibrated model can represent exactly.
fn true_delta(n: [f64; 2], x: f64, y: f64) -> [f64; 3] {
    [
        60.0 * n[0] - 20.0 * n[1] + 30.0 * x * n[0],
        -40.0 * n[0] + 50.0 * n[1] + 20.0 * y * n[1],
        25.0 * n[0] + 35.0 * n[1],
    ]
}

fn background() -> Vec<[f64; 3]> {
    (0..W * H)
        .map(|c| {
            let (i, j) = ((c % W) as f64, (c / W) as f64);
            [100.0 + 0.5 * i, 120.0 + 0.3 * j, 90.0 + 0.2 * (i + j)]
        })
        .collect()
}

/// Renders the truth for one contact (pixel centre and radius), in RGB.
fn true_frame(centre_px: [f64; 2], radius_px: f64) -> Vec<u8> {
    let grid = sparsh_scene::Grid {
        nx: W,
        ny: H,
        cell_mm: SETUP.mm_per_px,
    };
    let centre_mm = [
        (centre_px[0] + 0.5 - W as f64 / 2.0) * SETUP.mm_per_px,
        (centre_px[1] + 0.5 - H as f64 / 2.0) * SETUP.mm_per_px,
    ];
    let uz = sparsh_optics::ball::ball_press_uz_mm(
        grid,
        centre_mm,
        radius_px * SETUP.mm_per_px,
        SETUP.ball_radius_mm,
    )
    .unwrap();
    let bg = background();
    (0..W * H)
        .flat_map(|c| {
            let (i, j) = (c % W, c / W);
            // numpy.gradient-style differences, written out independently of the crate.
            let at = |ii: usize, jj: usize| uz[jj * W + ii];
            let (il, ir) = (i.saturating_sub(1), (i + 1).min(W - 1));
            let (ju, jd) = (j.saturating_sub(1), (j + 1).min(H - 1));
            let gx = (at(ir, j) - at(il, j)) / ((ir - il) as f64 * SETUP.mm_per_px);
            let gy = (at(i, jd) - at(i, ju)) / ((jd - ju) as f64 * SETUP.mm_per_px);
            let norm = (1.0 + gx * gx + gy * gy).sqrt();
            let x = (i as f64 + 0.5) / W as f64 - 0.5;
            let y = (j as f64 + 0.5) / H as f64 - 0.5;
            let d = true_delta([gx / norm, gy / norm], x, y);
            std::array::from_fn::<u8, 3, _>(|ch| {
                (bg[c][ch] + d[ch]).round().clamp(0.0, 255.0) as u8
            })
        })
        .collect()
}

fn contacts() -> Vec<([f64; 2], f64)> {
    (0..10)
        .map(|k| {
            let t = k as f64;
            (
                [
                    (30.0 + 4.0 * t + (t * 1.3).sin() * 6.0).round(),
                    28.0 + 2.0 * t,
                ],
                7.0 + (k % 4) as f64 * 1.5,
            )
        })
        .collect()
}

/// Writes a pack in Taxim's layout (BGR images, uint16 centres, float64 radii); `skip` leaves
/// one array out, `radius_override` replaces every radius, `centre_x_override` every centre's x.
fn write_pack(
    path: &Path,
    skip: Option<&str>,
    radius_override: Option<f64>,
    centre_x_override: Option<u16>,
) {
    let contacts = contacts();
    let rgb_to_bgr =
        |v: Vec<u8>| -> Vec<u8> { v.chunks(3).flat_map(|p| [p[2], p[1], p[0]]).collect() };
    let f0: Vec<u8> = background()
        .iter()
        .flat_map(|p| p.map(|v| v.round() as u8))
        .collect();
    let mut imgs = Vec::new();
    for (c, r) in &contacts {
        imgs.extend(rgb_to_bgr(true_frame(*c, *r)));
    }
    let n = contacts.len() as u64;
    let mut npz = npyz::npz::NpzWriter::create(path).unwrap();
    let opts = || npyz::zip::write::FileOptions::default();
    if skip != Some("f0") {
        let mut w = npz
            .array::<u8>("f0", opts())
            .unwrap()
            .default_dtype()
            .shape(&[H as u64, W as u64, 3])
            .begin_nd()
            .unwrap();
        w.extend(rgb_to_bgr(f0)).unwrap();
        w.finish().unwrap();
    }
    if skip != Some("imgs") {
        let mut w = npz
            .array::<u8>("imgs", opts())
            .unwrap()
            .default_dtype()
            .shape(&[n, H as u64, W as u64, 3])
            .begin_nd()
            .unwrap();
        w.extend(imgs).unwrap();
        w.finish().unwrap();
    }
    if skip != Some("touch_center") {
        // uint16, like the GelSight Mini pack.
        let mut w = npz
            .array::<u16>("touch_center", opts())
            .unwrap()
            .default_dtype()
            .shape(&[n, 2])
            .begin_nd()
            .unwrap();
        w.extend(
            contacts
                .iter()
                .flat_map(|(c, _)| [centre_x_override.unwrap_or(c[0] as u16), c[1] as u16]),
        )
        .unwrap();
        w.finish().unwrap();
    }
    if skip != Some("touch_radius") {
        // float64 radii.
        let mut w = npz
            .array::<f64>("touch_radius", opts())
            .unwrap()
            .default_dtype()
            .shape(&[n])
            .begin_nd()
            .unwrap();
        w.extend(contacts.iter().map(|(_, r)| radius_override.unwrap_or(*r)))
            .unwrap();
        w.finish().unwrap();
    }
}

fn pack_path(dir: &tempfile::TempDir) -> std::path::PathBuf {
    dir.path().join("dataPack.npz")
}

#[test]
fn reading_converts_bgr_to_rgb_and_any_numeric_dtype() {
    let dir = tempfile::tempdir().unwrap();
    write_pack(&pack_path(&dir), None, None, None);
    let pack = CalibrationPack::read(&pack_path(&dir)).unwrap();
    let contacts = contacts();
    assert_eq!(pack.frames.len(), contacts.len());
    assert_eq!(pack.size_px(), (W, H));
    assert_eq!(
        pack.frames[3].as_raw(),
        &true_frame(contacts[3].0, contacts[3].1)
    );
    assert_eq!(pack.centers_px[3], contacts[3].0);
    assert_eq!(pack.radii_px[3], contacts[3].1);
    let bg = background();
    assert_eq!(
        pack.background.get_pixel(5, 7).0[2],
        bg[7 * W + 5][2].round() as u8
    );
}

#[test]
fn calibration_recovers_a_known_map_on_held_out_frames() {
    let dir = tempfile::tempdir().unwrap();
    write_pack(&pack_path(&dir), None, None, None);
    let pack = CalibrationPack::read(&pack_path(&dir)).unwrap();
    let n = pack.frames.len();
    let even: Vec<usize> = (0..n).step_by(2).collect();
    let cal = calibrate_pack(&pack, &even, SETUP, FitOptions::default()).unwrap();
    // Far from the contacts the Hertz skirt's slopes are below 0.01: the re-estimated
    // background stays within a level of f0.
    let bg_err = cal
        .background
        .as_raw()
        .iter()
        .zip(pack.background.as_raw())
        .map(|(a, b)| (*a as i32 - *b as i32).abs())
        .max()
        .unwrap();
    assert!(bg_err <= 1, "background off by {bg_err}");
    let mut scores = Vec::new();
    for k in (1..n).step_by(2) {
        let (sim, score) = render_and_score(
            &sparsh_optics::sim2real::pack_renderer(&cal, &pack, SETUP, None),
            &pack,
            k,
            SETUP,
        )
        .unwrap();
        let worst = sim
            .as_raw()
            .iter()
            .zip(pack.frames[k].as_raw())
            .map(|(a, b)| (*a as i32 - *b as i32).abs())
            .max()
            .unwrap();
        assert!(worst <= 3, "frame {k}: max abs error {worst}");
        scores.push(score);
    }
    let summary = summarize(&scores);
    assert!(summary.crop_mean.mae < 0.6, "{summary:?}");
    assert!(summary.crop_mean.ssim > 0.99, "{summary:?}");
}

/// A circle off the pixel grid, drawn by the independent renderer above, is found by rendering
/// with the map fitted on other frames, from a start 3.6 px and 1.25 px of radius away; and a
/// pack whose marks were moved is refitted back to where its images were drawn.
#[test]
fn the_circle_fit_finds_the_drawn_circle_from_a_wrong_mark() {
    let dir = tempfile::tempdir().unwrap();
    write_pack(&pack_path(&dir), None, None, None);
    let mut pack = CalibrationPack::read(&pack_path(&dir)).unwrap();
    let even: Vec<usize> = (0..pack.frames.len()).step_by(2).collect();
    let cal = calibrate_pack(&pack, &even, SETUP, FitOptions::default()).unwrap();
    let renderer = sparsh_optics::sim2real::pack_renderer(&cal, &pack, SETUP, None);
    let truth = Circle {
        centre_px: [41.3, 35.6],
        radius_px: 9.25,
    };
    let image = image::RgbImage::from_raw(
        W as u32,
        H as u32,
        true_frame(truth.centre_px, truth.radius_px),
    )
    .unwrap();
    let start = Circle {
        centre_px: [44.3, 33.6],
        radius_px: 10.5,
    };
    let fit = fit_circle(&renderer, &image, start, SETUP).unwrap();
    let dx = fit.fitted.centre_px[0] - truth.centre_px[0];
    let dy = fit.fitted.centre_px[1] - truth.centre_px[1];
    assert!(dx.hypot(dy) < 0.2, "{fit:?}");
    assert!(
        (fit.fitted.radius_px - truth.radius_px).abs() < 0.2,
        "{fit:?}"
    );
    assert!(fit.rms_fitted < 0.5 * fit.rms_start, "{fit:?}");
    // Marks moved by (+3, −2) px and +1.5 px of radius on two held-out frames.
    let moved = [1, 3];
    let drawn: Vec<Circle> = moved.iter().map(|&k| pack.marked_circle(k)).collect();
    for &k in &moved {
        pack.centers_px[k][0] += 3.0;
        pack.centers_px[k][1] -= 2.0;
        pack.radii_px[k] += 1.5;
    }
    let refits: Vec<_> = moved
        .iter()
        .map(|&k| refit_frame(&renderer, &pack, k, SETUP).unwrap())
        .collect();
    for (r, d) in refits.iter().zip(&drawn) {
        let e = (r.fit.fitted.centre_px[0] - d.centre_px[0])
            .hypot(r.fit.fitted.centre_px[1] - d.centre_px[1]);
        assert!(e < 0.2, "{r:?}");
        assert!((r.fit.fitted.radius_px - d.radius_px).abs() < 0.2, "{r:?}");
    }
    let summary = summarize_refits(&refits);
    // The marks are 13^½ px and 1.5 px off what the images show, the same way on both frames.
    assert!(
        (summary.centre_median_px - 13f64.sqrt()).abs() < 0.2,
        "{summary:?}"
    );
    assert!(
        (summary.centre_mean_offset_px[0] + 3.0).abs() < 0.2,
        "{summary:?}"
    );
    assert!(
        (summary.centre_mean_offset_px[1] - 2.0).abs() < 0.2,
        "{summary:?}"
    );
    assert!(summary.centre_median_about_offset_px < 0.2, "{summary:?}");
    assert!(
        (summary.radius_mean_offset_px + 1.5).abs() < 0.2,
        "{summary:?}"
    );
    assert!(summary.check_centre_median_px < 0.2, "{summary:?}");
}

#[test]
fn a_flat_surface_renders_the_background() {
    let dir = tempfile::tempdir().unwrap();
    write_pack(&pack_path(&dir), None, None, None);
    let pack = CalibrationPack::read(&pack_path(&dir)).unwrap();
    let cal = calibrate_pack(&pack, &[0, 2, 4, 6, 8], SETUP, FitOptions::default()).unwrap();
    let renderer = sparsh_optics::CalibratedRenderer::new(&cal, W, H);
    let zeros = vec![0.0; W * H];
    let grid = sparsh_scene::Grid {
        nx: W,
        ny: H,
        cell_mm: SETUP.mm_per_px,
    };
    let img = renderer.render(&Surface {
        grid,
        ux_mm: &zeros,
        uy_mm: &zeros,
        uz_mm: &zeros,
    });
    // The true map gives no change at zero slope, wherever the pixel is.
    for (a, b) in img.pixels().zip(pack.background.pixels()) {
        let d: Vec<i32> = (0..3).map(|c| a.0[c] as i32 - b.0[c] as i32).collect();
        assert!(d.iter().all(|v| v.abs() <= 1), "{d:?}");
    }
}

#[test]
fn calibration_survives_a_save_and_load() {
    let dir = tempfile::tempdir().unwrap();
    write_pack(&pack_path(&dir), None, None, None);
    let pack = CalibrationPack::read(&pack_path(&dir)).unwrap();
    let cal = calibrate_pack(&pack, &[0, 2, 4], SETUP, FitOptions::default()).unwrap();
    let out = dir.path().join("calib");
    cal.save(&out).unwrap();
    let back = Calibration::load(&out).unwrap();
    assert_eq!(back.map, cal.map);
    assert_eq!(back.background, cal.background);
    // A damaged map names the file and the field.
    let text = std::fs::read_to_string(out.join("map.json")).unwrap();
    let damaged = text.replacen("\"nodes\":17", "\"nodes\":5", 1);
    assert_ne!(text, damaged);
    std::fs::write(out.join("map.json"), damaged).unwrap();
    let e = Calibration::load(&out).unwrap_err();
    assert!(e.contains("map.json") && e.contains("coef"), "{e}");
}

fn read_error(skip: Option<&str>, radius: Option<f64>, centre_x: Option<u16>) -> String {
    let dir = tempfile::tempdir().unwrap();
    write_pack(&pack_path(&dir), skip, radius, centre_x);
    CalibrationPack::read(&pack_path(&dir))
        .map(|_| String::new())
        .unwrap_or_else(|e| e.to_string())
}

#[test]
fn bad_packs_get_one_line_errors_naming_file_and_array() {
    let e = read_error(Some("imgs"), None, None);
    assert!(
        e.contains("dataPack.npz") && e.contains("imgs") && e.contains("missing"),
        "{e}"
    );
    let e = read_error(Some("touch_radius"), None, None);
    assert!(e.contains("touch_radius") && e.contains("missing"), "{e}");
    let e = read_error(None, None, Some(W as u16 + 4));
    assert!(e.contains("touch_center") && e.contains("outside"), "{e}");
    let e = read_error(None, Some(-3.0), None);
    assert!(e.contains("touch_radius") && e.contains("> 0"), "{e}");
    for e in [
        read_error(Some("imgs"), None, None),
        read_error(None, None, Some(500)),
    ] {
        assert_eq!(e.lines().count(), 1, "{e}");
    }
    // A radius larger than the ball is caught when the surface is built.
    let dir = tempfile::tempdir().unwrap();
    write_pack(&pack_path(&dir), None, Some(50.0), None);
    let pack = CalibrationPack::read(&pack_path(&dir)).unwrap();
    let e = calibrate_pack(&pack, &[0], SETUP, FitOptions::default()).unwrap_err();
    assert!(
        e.contains("touch_radius") && e.contains("ball radius"),
        "{e}"
    );
    // Not an npz at all.
    let junk = dir.path().join("junk.npz");
    std::fs::write(&junk, b"not a zip").unwrap();
    let e = CalibrationPack::read(&junk).unwrap_err().to_string();
    assert!(e.contains("junk.npz") && e.contains("npz"), "{e}");
}

#[test]
fn wrong_dtype_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let path = pack_path(&dir);
    let mut npz = npyz::npz::NpzWriter::create(&path).unwrap();
    let mut w = npz
        .array::<f32>("f0", Default::default())
        .unwrap()
        .default_dtype()
        .shape(&[4, 4, 3])
        .begin_nd()
        .unwrap();
    w.extend(vec![0.0f32; 48]).unwrap();
    w.finish().unwrap();
    drop(npz);
    let e = CalibrationPack::read(&path).unwrap_err().to_string();
    assert!(e.contains("f0") && e.contains("uint8"), "{e}");
}

/// Arrays of the wrong shape are named with the shape expected and the shape found.
#[test]
fn wrong_shapes_are_named() {
    let write = |path: &Path, imgs_h: u64, centre_cols: u64| {
        let mut npz = npyz::npz::NpzWriter::create(path).unwrap();
        let opts = || npyz::zip::write::FileOptions::default();
        let mut put_u8 = |name: &str, shape: &[u64]| {
            let len: u64 = shape.iter().product();
            let mut w = npz
                .array::<u8>(name, opts())
                .unwrap()
                .default_dtype()
                .shape(shape)
                .begin_nd()
                .unwrap();
            w.extend(vec![100u8; len as usize]).unwrap();
            w.finish().unwrap();
        };
        put_u8("f0", &[8, 10, 3]);
        put_u8("imgs", &[1, imgs_h, 10, 3]);
        let mut put_f64 = |name: &str, shape: &[u64], v: f64| {
            let len: u64 = shape.iter().product();
            let mut w = npz
                .array::<f64>(name, opts())
                .unwrap()
                .default_dtype()
                .shape(shape)
                .begin_nd()
                .unwrap();
            w.extend(vec![v; len as usize]).unwrap();
            w.finish().unwrap();
        };
        put_f64("touch_center", &[1, centre_cols], 4.0);
        put_f64("touch_radius", &[1], 2.0);
    };
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("shapes.npz");
    write(&path, 9, 2);
    let e = CalibrationPack::read(&path).unwrap_err().to_string();
    assert!(
        e.contains("shapes.npz") && e.contains("imgs") && e.contains("[1, 9, 10, 3]"),
        "{e}"
    );
    write(&path, 8, 3);
    let e = CalibrationPack::read(&path).unwrap_err().to_string();
    assert!(e.contains("touch_center") && e.contains("[1, 3]"), "{e}");
    assert_eq!(e.lines().count(), 1, "{e}");
    write(&path, 8, 2);
    assert!(
        CalibrationPack::read(&path).is_ok(),
        "the well-formed pack reads"
    );
}
