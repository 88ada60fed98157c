//! Frames outside their solver rung's validity, end to end: `generate` stops on the first one
//! under `validity = "error"`, and under `warn` counts them in one line and labels each frame.

mod common;
use common::{assert_user_error, generate, stderr, write_scene};

/// A 2 mm sphere pressed 0.1 mm deeper each frame into a frictionless 2 mm gel (frames 0…9) on
/// the layered rung, whose depth limit at the 2 % default tolerance is δ/h = 0.3 (the study's
/// depth sweep).
fn deep_press(policy: &str) -> String {
    deep_press_with(policy, 0.0)
}

/// [`deep_press`] with friction coefficient `friction`.
fn deep_press_with(policy: &str, friction: f64) -> String {
    layered_scene(
        policy,
        friction,
        2.0,
        [0.0, 0.0, 0.0],
        (1.0, [0.0, 0.0, -1.0]),
    )
}

/// A sphere of `radius_mm` on a 2 mm gel with friction `friction`, the layered rung under
/// validity `policy`, moved from `start_mm` at time 0 to `end` = (time s, position mm) on a
/// 64 × 48 grid of 0.12 mm at 10 frames a second.
fn layered_scene(
    policy: &str,
    friction: f64,
    radius_mm: f64,
    start_mm: [f64; 3],
    (end_s, end_mm): (f64, [f64; 3]),
) -> String {
    format!(
        r#"
solver = "layered"
validity = "{policy}"
[sensor]
preset = "digit"
width_px = 64
height_px = 48
mm_per_px = 0.12
fps = 10.0
[gel]
thickness_mm = 2.0
friction = {friction:?}
[indenter]
shape = "sphere"
radius_mm = {radius_mm:?}
[[trajectory]]
time_s = 0.0
position_mm = {start_mm:?}
[[trajectory]]
time_s = {end_s:?}
position_mm = {end_mm:?}
"#
    )
}

#[test]
fn error_policy_stops_on_one_line_naming_the_frame() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), &deep_press("error"));
    let out = generate(&scene, &tmp.path().join("ds"), &["--quiet"]);
    // δ/h = 0.05 k on the grid's deepest cell (a hair shallower): frame 7 is the first past 0.3
    assert_user_error(&out, "frame 7: the layered rung is outside its validity");
    assert!(stderr(&out).contains("indentation depth over gel thickness 0.3"));
    assert!(!tmp.path().join("ds/manifest.json").exists());
    // With friction the rung holds to δ/h = 0.1 only: frame 3 is the first past it.
    let scene = write_scene(tmp.path(), &deep_press_with("error", 1.0));
    let out = generate(&scene, &tmp.path().join("ds_friction"), &["--quiet"]);
    assert_user_error(&out, "frame 3: the layered rung is outside its validity");
    assert!(stderr(&out).contains("past the rung's 0.100"));
}

#[test]
fn warn_policy_counts_and_labels_every_frame() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), &deep_press("warn"));
    let ds = tmp.path().join("ds");
    let out = generate(&scene, &ds, &["--quiet"]);
    let err = stderr(&out);
    assert!(out.status.success(), "{err}");
    let warning: Vec<&str> = err.lines().filter(|l| l.contains("warning")).collect();
    assert_eq!(warning.len(), 1, "{err}");
    assert!(
        warning[0].contains("3 of 10 frames") && warning[0].contains("sequence 0 frame 7"),
        "{err}"
    );
    let labels = std::fs::read_to_string(ds.join("labels.jsonl")).unwrap();
    for (k, line) in labels.lines().enumerate() {
        let row: serde_json::Value = serde_json::from_str(line).unwrap();
        assert_eq!(row["solver"], "layered");
        if k >= 7 {
            assert_eq!(row["validity"], "depth_over_h", "frame {k}");
            let [value, bound] = [0, 1].map(|i| row["validity_value_bound"][i].as_f64().unwrap());
            assert!(
                (value - 0.05 * k as f64).abs() < 1e-3 && bound == 0.3,
                "{row}"
            );
        } else {
            assert_eq!(row["validity"], "ok", "frame {k}");
            assert!(row.get("validity_value_bound").is_none());
        }
    }
}

/// A press and the same press then slid, on the layered rung with μ = 1: the press carries no
/// tangential load and the slide does (`sparsh_sim::loaded_tangentially`, what decides whether
/// a frame is held to the study's press-and-slide rows), and every frame's validity label is
/// the rung's limits read with that flag.
#[test]
fn a_slide_loads_the_contact_tangentially_and_a_press_does_not() {
    use sparsh_scene::auto::SolverTable;
    use sparsh_scene::{RungLimits, SolverKind};
    let limits = RungLimits::of(SolverTable::builtin(), SolverKind::Layered, 0.02, 1.0);
    // 2 mm gel, the sphere pressed 0.15 mm (δ/h 0.075), then slid about 0.8 mm over five frames
    let scene = layered_scene(
        "warn",
        1.0,
        5.0,
        [0.0, 0.0, -0.15],
        (0.6, [1.0, 0.0, -0.15]),
    );
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), &scene);
    let ds = tmp.path().join("ds");
    let out = generate(&scene, &ds, &["--quiet"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let labels = std::fs::read_to_string(ds.join("labels.jsonl")).unwrap();
    let rows: Vec<serde_json::Value> = labels
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(rows.len(), 6);
    let loaded: Vec<bool> = rows
        .iter()
        .map(|row| {
            let f = [0, 1, 2].map(|i| row["force_n"][i].as_f64().unwrap());
            sparsh_sim::loaded_tangentially(f, 1.0)
        })
        .collect();
    assert!(!loaded[0], "the press: {}", rows[0]);
    // a slide of about a contact radius loads every frame after the press
    assert!(loaded[1..].iter().all(|&l| l), "{labels}");
    for (row, &sliding) in rows.iter().zip(&loaded) {
        let a_over_h =
            (row["contact_area_mm2"].as_f64().unwrap() / std::f64::consts::PI).sqrt() / 2.0;
        let expected = limits.check(true, a_over_h, 0.15 / 2.0, sliding);
        assert_eq!(row["validity"], expected.name(), "{row}");
    }
}

#[test]
fn families_read_tolerance_and_validity() {
    let tmp = tempfile::tempdir().unwrap();
    let family = |keys: &str| {
        format!(
            r#"
[[family]]
name = "presses"
sequences = 1
frames_per_sequence = 2
solver = "geometric"
{keys}
[family.sensor]
preset = "digit"
width_px = 40
height_px = 30
mm_per_px = 0.2
[[family.indenters]]
shape = "sphere"
radius_mm = 3.0
[family.motion]
kind = "press_slide"
depth_mm = 0.5
"#
        )
    };
    let scene = write_scene(tmp.path(), &family("validity = \"escalate\""));
    assert_user_error(
        &generate(&scene, &tmp.path().join("a"), &[]),
        "family[0].validity",
    );
    let scene = write_scene(tmp.path(), &family("tolerance = 2.0"));
    assert_user_error(
        &generate(&scene, &tmp.path().join("b"), &[]),
        "family[0].tolerance",
    );
    // the geometric rung makes no force claim: every frame in contact is outside
    let scene = write_scene(
        tmp.path(),
        &family("tolerance = 0.05\nvalidity = \"error\""),
    );
    let out = generate(&scene, &tmp.path().join("c"), &["--quiet"]);
    assert_user_error(&out, "geometric rung is outside its validity");
    assert!(
        stderr(&out).contains(
            "above the tolerance in every studied case (best 100.0 %) at the 5.0 % force tolerance"
        ),
        "{}",
        stderr(&out)
    );
}

/// `sparsh limits` prints each rung's limits as the validity check reads them, and refuses a
/// tolerance outside (0, 1) on one line.
#[test]
fn limits_prints_the_checked_limits() {
    use sparsh_scene::auto::SolverTable;
    use sparsh_scene::{RungLimits, SolverKind};
    let out = common::sparsh(&["limits", "--tolerance", "0.05"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let table = String::from_utf8(out.stdout).unwrap();
    let frictions = SolverTable::builtin().swept_frictions();
    assert!(frictions.len() >= 4, "{frictions:?}");
    for rung in SolverKind::ALL {
        for (k, &mu) in frictions.iter().enumerate() {
            let limits = RungLimits::of(SolverTable::builtin(), rung, 0.05, mu);
            let label = if k + 1 == frictions.len() {
                "any".to_string()
            } else {
                format!("{mu}")
            };
            let row = table
                .lines()
                .find(|l| l.starts_with(&format!("| {} | {label} |", rung.name())))
                .unwrap_or_else(|| panic!("no row for {rung:?} at μ {label}: {table}"));
            let cells: Vec<&str> = row.split('|').map(str::trim).collect();
            match limits.max_a_over_h {
                Some(a) => {
                    assert_eq!(cells[3].parse::<f64>().unwrap(), a, "{row}");
                    assert_eq!(
                        cells[4].parse::<f64>().unwrap(),
                        limits.max_depth_over_h,
                        "{row}"
                    );
                    assert_eq!(
                        cells[5].parse::<f64>().unwrap(),
                        limits.max_sliding_depth_over_h,
                        "{row}"
                    );
                }
                None => assert_eq!(&cells[3..6], ["nowhere"; 3], "{row}"),
            }
        }
    }
    assert_user_error(
        &common::sparsh(&["limits", "--tolerance", "1.5"]),
        "--tolerance: must be a relative force error in (0, 1), got 1.5",
    );
}

/// The quick start's scene, as shipped, gives ground truth its own checks accept: `generate`
/// prints no validity warning and every frame's labels say `ok`, on the rung `solver = "auto"`
/// chose, whose limits (`sparsh limits`) the deepest frame stays inside.
#[test]
fn the_quickstart_is_inside_its_rungs_validity() {
    let tmp = tempfile::tempdir().unwrap();
    let scene =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../scenes/quickstart.toml");
    let ds = tmp.path().join("ds");
    let out = generate(&scene, &ds, &["--quiet"]);
    let err = stderr(&out);
    assert!(out.status.success(), "{err}");
    assert!(!err.contains("warning"), "{err}");
    let labels = std::fs::read_to_string(ds.join("labels.jsonl")).unwrap();
    let rows: Vec<serde_json::Value> = labels
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(rows.len(), 120);
    for row in &rows {
        assert_eq!(row["validity"], "ok", "{row}");
        assert_eq!(row["solver"], rows[0]["solver"], "{row}");
    }
    assert_ne!(
        rows[0]["solver"], "halfspace",
        "a 3 mm gel is no half-space"
    );
}

/// Shipped scenes whose frames leave their rung's validity, and why (the book's "Not done yet"
/// says the same): every other scene and dataset file must not.
const OUTSIDE_VALIDITY: [(&str, &str); 3] = [
    (
        "sim2real_gelsight",
        "the real packs' ball presses reach δ/h 0.15–1 with friction: no rung holds there",
    ),
    ("sim2real_mini", "as sim2real_gelsight"),
    (
        "tacbench_force_slip_randomized",
        "the half-space ablation of the published table",
    ),
];

/// Every other shipped scene and dataset file (scenes/*.toml, scenes/bench, assets/ssl/*_data)
/// gives frames inside its rung's validity: a spot check of about five sequences of each (one
/// shard), which `generate` would warn about; the half-space ablation, which does warn, shows
/// the check sees a warning when there is one. The quick start has its own test above, and the
/// finite-element deep press (19 frames of about 5 s each) is left out for time.
#[test]
fn shipped_scenes_are_inside_their_rungs_validity() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../");
    let mut files: Vec<std::path::PathBuf> = Vec::new();
    for dir in ["scenes", "scenes/bench", "assets/ssl"] {
        for entry in std::fs::read_dir(root.join(dir)).unwrap() {
            let path = entry.unwrap().path();
            let stem = path.file_stem().unwrap().to_string_lossy().into_owned();
            let is_scene = path.extension().is_some_and(|e| e == "toml")
                && (dir != "assets/ssl" || stem.ends_with("_data"));
            if is_scene && !["quickstart", "deep_press"].contains(&stem.as_str()) {
                files.push(path);
            }
        }
    }
    files.sort();
    assert!(files.len() >= 12, "{files:?}");
    let tmp = tempfile::tempdir().unwrap();
    for path in &files {
        let stem = path.file_stem().unwrap().to_string_lossy().into_owned();
        let control = stem == "tacbench_force_slip_randomized";
        if let Some((_, why)) = OUTSIDE_VALIDITY.iter().find(|(name, _)| *name == stem)
            && !control
        {
            eprintln!("{stem}: left out ({why})");
            continue;
        }
        let sequences = sparsh_scene::DatasetSpec::load(path)
            .unwrap_or_else(|e| panic!("{e}"))
            .sequence_count();
        let shard = format!("0/{}", (sequences / 5).max(1));
        let out = generate(
            path,
            &tmp.path().join(&stem),
            &["--quiet", "--shard", &shard],
        );
        let err = stderr(&out);
        assert!(out.status.success(), "{stem}: {err}");
        let warned = err.contains("outside their solver rung's validity");
        if control {
            assert!(warned, "the half-space ablation warns: {err}");
        } else {
            assert!(!warned, "{stem}: {err}");
        }
    }
}
