//! Textured plates (`shape = "texture"`): the relief patterns, the gap field against the closed
//! form, oblique rays, the keys' one-line errors, and their ranges in dataset families.

use std::path::Path;

use glam::DVec3;
use sparsh_scene::{
    DatasetSpec, GapField, Grid, Indenter, Pattern, Pose, Scene, SceneError, TexturedPlate,
};

const PATTERNS: [Pattern; 4] = [Pattern::Ribs, Pattern::Weave, Pattern::Knurl, Pattern::Dots];

const GRID: Grid = Grid {
    nx: 96,
    ny: 72,
    cell_mm: 0.1,
};

fn plate(pattern: Pattern, crown_radius_mm: Option<f64>) -> TexturedPlate {
    TexturedPlate {
        pattern,
        pitch_mm: 1.3,
        depth_mm: 0.25,
        size_mm: [8.0, 6.0, 3.0],
        crown_radius_mm,
    }
}

#[test]
fn patterns_are_periodic_with_a_crest_at_the_origin() {
    let s2 = std::f64::consts::SQRT_2;
    // (pattern, periods along x and along y, in pitches)
    for (pattern, px, py) in [
        (Pattern::Ribs, 1.0, f64::NAN),
        (Pattern::Weave, 2.0, 2.0),
        (Pattern::Knurl, s2, s2),
        (Pattern::Dots, 1.0, 1.0),
    ] {
        assert_eq!(
            pattern.profile(0.0, 0.0),
            1.0,
            "{pattern:?}: crest at the origin"
        );
        let mut lo = f64::INFINITY;
        for k in 0..400 {
            let (u, v) = (0.037 * k as f64 - 7.1, 0.053 * k as f64 - 9.3);
            let tau = pattern.profile(u, v);
            assert!(
                (0.0..=1.0).contains(&tau),
                "{pattern:?}: τ({u}, {v}) = {tau}"
            );
            lo = lo.min(tau);
            let along_x = pattern.profile(u + px, v);
            assert!((along_x - tau).abs() < 1e-9, "{pattern:?} at ({u}, {v})");
            if py.is_nan() {
                // Ribs run along y.
                assert!((pattern.profile(u, v + 0.37) - tau).abs() < 1e-12);
            } else {
                assert!((pattern.profile(u, v + py) - tau).abs() < 1e-9);
            }
        }
        assert!(lo < 0.25, "{pattern:?} has troughs (lowest τ {lo})");
    }
    // Plain weave: the warp (along y) is on top at even crossings, the weft at odd ones.
    let w = |u: f64, v: f64| Pattern::Weave.profile(u, v);
    assert!(w(0.0, 0.3) > w(0.3, 0.0) + 0.4, "warp on top at (0, 0)");
    assert!(w(1.3, 0.0) > w(1.0, 0.3) + 0.4, "weft on top at (1, 0)");
}

/// The slope bound holds: finite differences of τ never exceed it.
#[test]
fn pattern_slopes_stay_within_their_bound() {
    let h = 1e-6;
    for pattern in PATTERNS {
        let bound = pattern.max_slope();
        let mut steepest: f64 = 0.0;
        for k in 0..20_000 {
            let (u, v) = (0.00731 * k as f64 - 3.0, 0.01177 * k as f64 - 5.0);
            let gx = (pattern.profile(u + h, v) - pattern.profile(u - h, v)) / (2.0 * h);
            let gy = (pattern.profile(u, v + h) - pattern.profile(u, v - h)) / (2.0 * h);
            steepest = steepest.max(gx.hypot(gy));
        }
        assert!(
            steepest <= bound * 1.001,
            "{pattern:?}: {steepest} > {bound}"
        );
        assert!(
            steepest > 0.5 * bound,
            "{pattern:?}: bound {bound} is loose ({steepest})"
        );
    }
}

/// Along the sensor normal (any turn about z) the gap is the pose's z plus the underside
/// height at the cell's local coordinates; outside the footprint nothing is hit.
#[test]
fn gap_matches_the_underside_for_turned_and_shifted_poses() {
    for pattern in PATTERNS {
        for crown in [None, Some(12.0)] {
            let p = plate(pattern, crown);
            let indenter = Indenter::Texture(p);
            for pose in [
                Pose {
                    position_mm: DVec3::new(0.0, 0.0, -0.4),
                    rotation_deg: DVec3::ZERO,
                },
                Pose {
                    position_mm: DVec3::new(0.7, -0.45, -0.2),
                    rotation_deg: DVec3::new(0.0, 0.0, 33.0),
                },
            ] {
                let gap = GapField::cast(&indenter, &pose, GRID);
                for j in 0..GRID.ny {
                    for i in 0..GRID.nx {
                        let world = DVec3::new(GRID.x_mm(i), GRID.y_mm(j), 0.0);
                        let local = pose.inverse_apply(world);
                        let inside = local.x.abs() <= 4.0 && local.y.abs() <= 3.0;
                        let s = p.underside_mm(local.x, local.y);
                        let got = gap.gap_mm[j * GRID.nx + i];
                        if inside && s <= 3.0 {
                            let want = pose.position_mm.z + s;
                            assert!(
                                (got - want).abs() < 1e-9,
                                "{pattern:?} {crown:?} cell {i},{j}: {got} vs {want}"
                            );
                        } else if !inside {
                            assert!(got.is_infinite(), "{pattern:?} cell {i},{j}: {got}");
                        }
                    }
                }
                assert!(
                    (gap.max_penetration_mm() + pose.position_mm.z).abs() < 0.05,
                    "{pattern:?}: the tip reaches the pose's depth"
                );
            }
        }
    }
}

/// A tilted plate is marched: every hit lies on the plate's surface, and no point of the ray
/// before it is inside the plate.
#[test]
fn oblique_rays_enter_at_the_first_crossing() {
    for pattern in PATTERNS {
        let p = plate(pattern, Some(15.0));
        let indenter = Indenter::Texture(p);
        let pose = Pose {
            position_mm: DVec3::new(0.3, -0.2, -0.5),
            rotation_deg: DVec3::new(12.0, -8.0, 20.0),
        };
        let inside = |q: DVec3| {
            q.x.abs() <= 4.0
                && q.y.abs() <= 3.0
                && q.z <= 3.0
                && q.z >= p.underside_mm(q.x, q.y) - 1e-12
        };
        let gap = GapField::cast(&indenter, &pose, GRID);
        let mut hits = 0;
        for c in 0..GRID.len() {
            let g = gap.gap_mm[c];
            let (x, y) = (GRID.x_mm(c % GRID.nx), GRID.y_mm(c / GRID.nx));
            if !g.is_finite() {
                // A miss: the vertical through the cell never enters the plate.
                for k in 0..400 {
                    let z = -1.0 + 5.0 * k as f64 / 400.0;
                    let q = pose.inverse_apply(DVec3::new(x, y, z));
                    assert!(
                        !inside(q),
                        "{pattern:?} cell {c}: missed the plate at z {z}"
                    );
                }
                continue;
            }
            hits += 1;
            let hit = pose.inverse_apply(DVec3::new(x, y, g));
            let on_side = (hit.x.abs() - 4.0).abs() < 1e-6 || (hit.y.abs() - 3.0).abs() < 1e-6;
            let on_underside = (hit.z - p.underside_mm(hit.x, hit.y)).abs() < 1e-6;
            assert!(on_side || on_underside, "{pattern:?} cell {c}: hit {hit}");
            for k in 1..200 {
                let z = g - 0.002 * k as f64;
                let q = pose.inverse_apply(DVec3::new(x, y, z));
                assert!(
                    !inside(q),
                    "{pattern:?} cell {c}: inside below the hit at z {z}"
                );
            }
        }
        assert!(
            hits > 2000,
            "{pattern:?}: only {hits} cells under the plate"
        );
    }
}

const BASE: &str = r#"
[sensor]
preset = "digit"
width_px = 64
height_px = 48
[indenter]
shape = "texture"
pattern = "knurl"
pitch_mm = 1.2
depth_mm = 0.2
crown_radius_mm = 20.0
[[trajectory]]
time_s = 0.0
position_mm = [0.0, 0.0, 0.3]
[[trajectory]]
time_s = 0.5
position_mm = [0.0, 0.0, -0.5]
"#;

fn parse(text: &str) -> Result<Scene, SceneError> {
    Scene::parse(Path::new("scenes/test.toml"), text.to_string())
}

fn error_of(text: &str) -> String {
    let line = parse(text)
        .expect_err("scene should be rejected")
        .to_string();
    assert!(!line.contains('\n'), "error spans lines: {line}");
    assert!(line.starts_with("scenes/test.toml"), "{line}");
    line
}

#[test]
fn texture_scene_loads_with_the_default_plate() {
    let scene = parse(BASE).unwrap();
    match scene.indenter {
        Indenter::Texture(p) => {
            assert_eq!(p.pattern, Pattern::Knurl);
            assert_eq!((p.pitch_mm, p.depth_mm), (1.2, 0.2));
            assert_eq!(p.size_mm, TexturedPlate::DEFAULT_SIZE_MM);
            assert_eq!(p.crown_radius_mm, Some(20.0));
        }
        other => panic!("expected a texture, got {other:?}"),
    }
    let flat = parse(&BASE.replace("crown_radius_mm = 20.0\n", "")).unwrap();
    assert!(matches!(flat.indenter, Indenter::Texture(p) if p.crown_radius_mm.is_none()));
}

#[test]
fn bad_texture_keys_are_named_on_one_line() {
    for (from, to, field, words) in [
        ("pattern = \"knurl\"\n", "", "indenter.pattern", "required"),
        (
            "pitch_mm = 1.2",
            "pitch_mm = 0.0",
            "indenter.pitch_mm",
            "> 0",
        ),
        (
            "pitch_mm = 1.2",
            "pitch_mm = nan",
            "indenter.pitch_mm",
            "> 0",
        ),
        ("pitch_mm = 1.2\n", "", "indenter.pitch_mm", "required"),
        (
            "depth_mm = 0.2",
            "depth_mm = -0.1",
            "indenter.depth_mm",
            "> 0",
        ),
        (
            "crown_radius_mm = 20.0",
            "crown_radius_mm = 0.0",
            "indenter.crown_radius_mm",
            "> 0",
        ),
        (
            "depth_mm = 0.2",
            "depth_mm = 0.2\nsize_mm = [10.0, 10.0, -1.0]",
            "indenter.size_mm",
            "> 0",
        ),
        (
            "depth_mm = 0.2",
            "depth_mm = 2.0\nsize_mm = [10.0, 10.0, 1.5]",
            "indenter.size_mm",
            "exceed depth_mm",
        ),
        (
            "depth_mm = 0.2",
            "depth_mm = 0.2\nradius_mm = 3.0",
            "indenter.radius_mm",
            "does not apply",
        ),
    ] {
        let line = error_of(&BASE.replace(from, to));
        assert!(
            line.contains(field) && line.contains(words),
            "{to:?}: {line}"
        );
    }
    // A texture key on another shape, and an unknown pattern.
    let sphere = BASE.replace("shape = \"texture\"", "shape = \"sphere\"\nradius_mm = 3.0");
    let line = error_of(&sphere);
    assert!(
        line.contains("indenter.pattern") && line.contains("does not apply"),
        "{line}"
    );
    let line = error_of(&BASE.replace("\"knurl\"", "\"waffle\""));
    assert!(line.contains("waffle") && line.contains("knurl"), "{line}");
}

const FAMILIES: &str = r#"
seed = 9
[output]
fields = []
[[family]]
name = "ribs"
sequences = 6
frames_per_sequence = 4
[family.sensor]
preset = "digit"
width_px = 64
height_px = 48
[[family.indenters]]
shape = "texture"
pattern = "ribs"
pitch_mm = [1.0, 1.4]
depth_mm = [0.1, 0.2]
crown_radius_mm = [15.0, 25.0]
size_mm = [12.0, 12.0, 4.0]
[[family.indenters]]
shape = "texture"
pattern = "ribs"
pitch_mm = [1.5, 1.6]
depth_mm = 0.3
split = "test"
[family.motion]
kind = "press_slide"
[[family]]
name = "ribs"
sequences = 5
frames_per_sequence = 4
[family.sensor]
preset = "gelsight_mini"
width_px = 64
height_px = 48
[[family.indenters]]
shape = "texture"
pattern = "ribs"
pitch_mm = [1.0, 1.4]
depth_mm = [0.1, 0.2]
[family.motion]
kind = "random_walk"
"#;

fn load_families(text: &str) -> Result<DatasetSpec, SceneError> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("families.toml");
    std::fs::write(&path, text).unwrap();
    DatasetSpec::load(&path)
}

/// Texture keys take ranges in families, drawn per sequence; two families may share a name
/// (one class seen through two sensors), and each indenter entry keeps its own split.
#[test]
fn families_draw_texture_ranges_and_may_share_a_name() {
    let spec = load_families(FAMILIES).unwrap();
    assert_eq!(spec.sequence_count(), 11);
    let mut pitches = Vec::new();
    for k in 0..spec.sequence_count() {
        let seq = spec.sequence(k).unwrap();
        assert_eq!(seq.family, "ribs");
        let Indenter::Texture(p) = seq.scene.indenter else {
            panic!("sequence {k}: not a texture");
        };
        assert_eq!(p.pattern, Pattern::Ribs);
        let test = seq.split == sparsh_scene::Split::Test;
        if test {
            assert!((1.5..=1.6).contains(&p.pitch_mm) && p.depth_mm == 0.3);
        } else {
            assert!((1.0..=1.4).contains(&p.pitch_mm), "{}", p.pitch_mm);
            assert!((0.1..=0.2).contains(&p.depth_mm), "{}", p.depth_mm);
        }
        if k < 6 && !test {
            let r = p.crown_radius_mm.unwrap();
            assert!((15.0..=25.0).contains(&r), "{r}");
            assert_eq!(p.size_mm, [12.0, 12.0, 4.0]);
        }
        assert_eq!(
            seq.scene.sensor.name,
            if k < 6 { "digit" } else { "gelsight_mini" }
        );
        pitches.push(p.pitch_mm);
    }
    pitches.dedup();
    assert!(
        pitches.len() > 5,
        "pitch is drawn per sequence: {pitches:?}"
    );
    // Both ends of a range are checked at load.
    let err =
        load_families(&FAMILIES.replacen("pitch_mm = [1.0, 1.4]", "pitch_mm = [0.0, 1.4]", 1))
            .unwrap_err()
            .to_string();
    assert!(err.contains("family[0].indenters[0].pitch_mm"), "{err}");
}
