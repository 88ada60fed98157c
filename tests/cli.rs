//! End-to-end tests of the `sparsh` command: scene file in, dataset out.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Output};
use std::time::{Duration, Instant};

use sha2::{Digest, Sha256};

mod common;
use common::{SMALL_SCENE, assert_user_error, generate, sparsh, stderr, write_scene};

fn files_under(dir: &Path) -> Vec<PathBuf> {
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            files.extend(files_under(&path));
        } else {
            files.push(path);
        }
    }
    files.sort();
    files
}

#[test]
fn generate_writes_frames_fields_labels_and_a_checked_manifest() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), SMALL_SCENE);
    let out_dir = tmp.path().join("ds");
    let out = generate(&scene, &out_dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));

    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out_dir.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(manifest["frames"], 12, "1.2 s at 10 fps");
    assert_eq!(manifest["scene"], SMALL_SCENE);
    assert_eq!(manifest["seed"], 11);
    let files = manifest["files"].as_object().unwrap();
    // 12 frames + 12 fields + background + sequence record + labels + identity, each with a
    // correct checksum.
    assert_eq!(files.len(), 28);
    for (rel, sum) in files {
        let bytes = std::fs::read(out_dir.join(rel)).unwrap();
        let hex: String = Sha256::digest(&bytes)
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        assert_eq!(&hex, sum, "{rel}");
    }
    let on_disk = files_under(&out_dir).len();
    assert_eq!(on_disk, files.len() + 1, "no stray or temporary files");

    let frame = image::open(out_dir.join("frames/000011.png"))
        .unwrap()
        .to_rgb8();
    assert_eq!(frame.dimensions(), (80, 60));

    let labels = std::fs::read_to_string(out_dir.join("labels.jsonl")).unwrap();
    let rows: Vec<serde_json::Value> = labels
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(rows.len(), 12);
    assert_eq!(rows[0]["force_n"][2], 0.0, "tip starts above the gel");
    assert!(
        rows[6]["force_n"][2].as_f64().unwrap() > 0.0,
        "pressed at 0.6 s"
    );
    assert_eq!(rows[6]["pose"]["position_mm"][2], -0.8);

    // Fields: eight named channels; the pressure integrates to the labelled normal force.
    let exr = sparsh_data::read_exr_channels(&out_dir.join("fields/000006.exr")).unwrap();
    let mut names: Vec<&str> = exr.channels.iter().map(|(n, _)| n.as_str()).collect();
    names.sort();
    assert_eq!(
        names,
        ["contact", "p", "qx", "qy", "slip", "ux", "uy", "uz"]
    );
    let cell_area_mm2 = 0.2 * 0.2;
    let fz: f64 =
        exr.get("p").unwrap().iter().map(|&p| p as f64).sum::<f64>() * cell_area_mm2 * 1e-3;
    let label_fz = rows[6]["force_n"][2].as_f64().unwrap();
    assert!(
        (fz - label_fz).abs() < 1e-4 * label_fz,
        "{fz} vs {label_fz}"
    );
}

#[test]
fn same_scene_and_seed_give_identical_bytes_with_one_or_two_threads() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), SMALL_SCENE);
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    assert!(generate(&scene, &a, &["--threads", "1"]).status.success());
    assert!(generate(&scene, &b, &["--threads", "2"]).status.success());
    let (fa, fb) = (files_under(&a), files_under(&b));
    assert_eq!(fa.len(), fb.len());
    for (x, y) in fa.iter().zip(&fb) {
        assert_eq!(x.strip_prefix(&a).unwrap(), y.strip_prefix(&b).unwrap());
        assert!(
            std::fs::read(x).unwrap() == std::fs::read(y).unwrap(),
            "{} differs",
            x.display()
        );
    }
}

#[test]
fn indenter_that_never_touches_gives_zero_fields() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), &SMALL_SCENE.replace("-0.8]", "2.0]"));
    let out_dir = tmp.path().join("ds");
    let out = generate(&scene, &out_dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let exr = sparsh_data::read_exr_channels(&out_dir.join("fields/000008.exr")).unwrap();
    for (name, data) in &exr.channels {
        assert!(data.iter().all(|&v| v == 0.0), "channel {name} not zero");
    }
    let background = std::fs::read(out_dir.join("backgrounds/000000.png")).unwrap();
    let frame = std::fs::read(out_dir.join("frames/000008.png")).unwrap();
    assert!(
        background == frame,
        "an untouched gel looks like its background"
    );
}

#[test]
fn target_normal_force_is_met() {
    let tmp = tempfile::tempdir().unwrap();
    let text = SMALL_SCENE
        .replace(
            "position_mm = [-1.0, 0.0, -0.8]\n",
            "position_mm = [-1.0, 0.0, 0.0]\nnormal_force_n = 1.5\n",
        )
        .replace(
            "position_mm = [1.0, 0.0, -0.8]\n",
            "position_mm = [1.0, 0.0, 0.0]\nnormal_force_n = 1.5\n",
        );
    let scene = write_scene(tmp.path(), &text);
    let out_dir = tmp.path().join("ds");
    let out = generate(&scene, &out_dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let labels = std::fs::read_to_string(out_dir.join("labels.jsonl")).unwrap();
    for line in labels.lines().skip(6) {
        let row: serde_json::Value = serde_json::from_str(line).unwrap();
        let fz = row["force_n"][2].as_f64().unwrap();
        assert!((fz - 1.5).abs() < 1e-6, "{fz}");
        assert!(
            row["pose"]["position_mm"][2].as_f64().unwrap() < 0.0,
            "pressed in"
        );
    }
}

#[test]
fn render_writes_one_frame_and_its_fields() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), SMALL_SCENE);
    let (png, exr) = (tmp.path().join("f.png"), tmp.path().join("f.exr"));
    let out = sparsh(&[
        "render",
        scene.to_str().unwrap(),
        "--frame",
        "7",
        "--png",
        png.to_str().unwrap(),
        "--fields",
        exr.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    // one line saying what was written
    let said = stderr(&out);
    assert_eq!(said.trim_end().lines().count(), 1, "{said}");
    assert!(
        said.contains("f.png: frame 7") && said.contains("f.exr"),
        "{said}"
    );
    // The same frame as `generate` writes.
    let ds = tmp.path().join("ds");
    assert!(generate(&scene, &ds, &[]).status.success());
    assert!(std::fs::read(&png).unwrap() == std::fs::read(ds.join("frames/000007.png")).unwrap());
    assert!(std::fs::read(&exr).unwrap() == std::fs::read(ds.join("fields/000007.exr")).unwrap());

    let out = sparsh(&[
        "render",
        scene.to_str().unwrap(),
        "--frame",
        "12",
        "--out", // the older name of --png
        png.to_str().unwrap(),
    ]);
    assert_user_error(&out, "out of range");
}

#[test]
fn non_empty_output_directory_needs_force() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), SMALL_SCENE);
    let out_dir = tmp.path().join("ds");
    std::fs::create_dir(&out_dir).unwrap();
    std::fs::write(out_dir.join("notes.txt"), "keep me").unwrap();
    assert_user_error(&generate(&scene, &out_dir, &[]), "not empty");
    assert!(!out_dir.join("frames").exists(), "nothing written");
    let out = generate(&scene, &out_dir, &["--force"]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(
        out_dir.join("notes.txt").exists(),
        "--force replaces only the dataset"
    );
}

#[test]
fn bad_scenes_fail_with_one_line() {
    let tmp = tempfile::tempdir().unwrap();
    let out_dir = tmp.path().join("ds");
    for (bad, needle) in [
        (
            SMALL_SCENE.replace("radius_mm = 6.0", "radius_mm = 6.0 ]"),
            "scene.toml:15:17:",
        ),
        (
            SMALL_SCENE.replace("thickness_mm = 3.0", "thicknes_mm = 3.0"),
            "thicknes_mm",
        ),
        (
            SMALL_SCENE.replace("thickness_mm = 3.0", "thickness_mm = 0.0"),
            "gel.thickness_mm",
        ),
        (
            SMALL_SCENE.replace("youngs_modulus_kpa = 300.0", "youngs_modulus_kpa = -1.0"),
            "gel.youngs_modulus_kpa",
        ),
        (
            SMALL_SCENE.replace("thickness_mm = 3.0", "poisson_ratio = 0.7"),
            "gel.poisson_ratio",
        ),
        (
            SMALL_SCENE.replace(
                "shape = \"sphere\"\nradius_mm = 6.0",
                "shape = \"mesh\"\nmesh = \"gone.obj\"",
            ),
            "gone.obj",
        ),
    ] {
        let scene = write_scene(tmp.path(), &bad);
        assert_user_error(&generate(&scene, &out_dir, &[]), needle);
        assert!(!out_dir.exists(), "nothing written for a bad scene");
    }
    let missing = tmp.path().join("missing.toml");
    assert_user_error(&generate(&missing, &out_dir, &[]), "missing.toml");
}

const FAMILY_SCENE: &str = r#"
seed = 5
[output]
fields = ["p", "uz"]

[[family]]
name = "spheres"
sequences = 10
frames_per_sequence = 16
solver = "geometric"
[family.sensor]
preset = "digit"
width_px = 160
height_px = 120
mm_per_px = 0.1
[family.gel]
youngs_modulus_kpa = [200.0, 400.0]
[family.randomize]
led_intensity = [0.8, 1.2]
[[family.indenters]]
shape = "sphere"
radius_mm = [3.0, 6.0]
[[family.indenters]]
shape = "cylinder"
radius_mm = 1.5
split = "test"
[family.motion]
kind = "press_slide"
depth_mm = [0.3, 0.8]

[[family]]
name = "cones"
sequences = 6
frames_per_sequence = 12
[family.sensor]
preset = "gelsight_mini"
width_px = 120
height_px = 90
mm_per_px = 0.12
[[family.indenters]]
shape = "cone"
half_angle_deg = [60.0, 75.0]
[family.motion]
kind = "twist"
"#;

fn assert_same_tree(a: &Path, b: &Path) {
    let (fa, fb) = (files_under(a), files_under(b));
    let rel = |files: &[PathBuf], root: &Path| -> Vec<PathBuf> {
        files
            .iter()
            .map(|f| f.strip_prefix(root).unwrap().to_path_buf())
            .collect()
    };
    assert_eq!(rel(&fa, a), rel(&fb, b));
    for (x, y) in fa.iter().zip(&fb) {
        assert!(
            std::fs::read(x).unwrap() == std::fs::read(y).unwrap(),
            "{} differs",
            x.display()
        );
    }
}

#[test]
fn families_draw_sequences_with_labels_for_tacbench() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), FAMILY_SCENE);
    let out_dir = tmp.path().join("ds");
    let out = generate(&scene, &out_dir, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let labels = std::fs::read_to_string(out_dir.join("labels.jsonl")).unwrap();
    let rows: Vec<serde_json::Value> = labels
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(rows.len(), 10 * 16 + 6 * 12);
    for (k, row) in rows.iter().enumerate() {
        assert_eq!(row["frame"], k, "frames numbered across sequences");
        let seq = row["sequence"].as_u64().unwrap() as usize;
        let family = if seq < 10 { "spheres" } else { "cones" };
        assert_eq!(row["family"], family);
        // Δforce is the change since five frames earlier in the same sequence.
        let i = row["frame_in_sequence"].as_u64().unwrap() as usize;
        let back = &rows[k - i.min(5)];
        let dfz = row["force_n"][2].as_f64().unwrap() - back["force_n"][2].as_f64().unwrap();
        assert!((row["delta_force_n"][2].as_f64().unwrap() - dfz).abs() < 1e-12);
        // The SE(2) change is the pose difference since the previous frame.
        if i > 0 {
            let prev = &rows[k - 1];
            let dx = row["pose"]["position_mm"][0].as_f64().unwrap()
                - prev["pose"]["position_mm"][0].as_f64().unwrap();
            assert!((row["pose_change_se2"][0].as_f64().unwrap() - dx).abs() < 1e-12);
        }
    }
    let splits: Vec<&str> = rows.iter().map(|r| r["split"].as_str().unwrap()).collect();
    assert!(splits.contains(&"test") && splits.contains(&"train"));
    let twist_end = &rows[10 * 16 + 11];
    assert_ne!(twist_end["pose"]["rotation_deg"][2], 0.0, "twist turns");
    let frame = image::open(out_dir.join("frames/000170.png")).unwrap();
    assert_eq!(
        (frame.width(), frame.height()),
        (120, 90),
        "cones family's sensor"
    );
    let out = sparsh(&["verify", out_dir.to_str().unwrap()]);
    assert!(out.status.success(), "{}", stderr(&out));
}

#[test]
fn every_shard_layout_yields_the_same_dataset() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), FAMILY_SCENE);
    let whole = tmp.path().join("whole");
    assert!(generate(&scene, &whole, &[]).status.success());
    let sharded = tmp.path().join("sharded");
    for k in [2, 0, 1] {
        let shard = format!("{k}/3");
        let out = generate(&scene, &sharded, &["--shard", &shard]);
        assert!(out.status.success(), "{}", stderr(&out));
        assert_eq!(
            sharded.join("manifest.json").exists(),
            k == 1,
            "after shard {k}"
        );
    }
    assert_same_tree(&whole, &sharded);
}

/// Waits for `child` until `deadline`; a child still running then is killed and fails the test
/// (a hung run must not hang the suite).
fn wait_until(child: &mut Child, deadline: Instant, what: &str) -> ExitStatus {
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status;
        }
        if Instant::now() > deadline {
            child.kill().unwrap();
            child.wait().unwrap();
            panic!("{what}: still running after its time limit, killed");
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}

#[test]
fn killed_run_resumes_to_identical_bytes() {
    // Each run takes about a second in release; a minute is ample on a loaded machine.
    let limit = Duration::from_secs(60);
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), FAMILY_SCENE);
    let whole = tmp.path().join("whole");
    assert!(generate(&scene, &whole, &[]).status.success());

    let killed = tmp.path().join("killed");
    let run = |extra: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_sparsh"))
            .args([
                "--threads",
                "1",
                "generate",
                scene.to_str().unwrap(),
                "--out",
                killed.to_str().unwrap(),
            ])
            .args(extra)
            .spawn()
            .unwrap()
    };
    let mut child = run(&[]);
    let first_part = killed.join("parts/000000.json");
    let deadline = Instant::now() + limit;
    while !first_part.exists() {
        assert!(
            child.try_wait().unwrap().is_none(),
            "the run ended before recording a sequence"
        );
        if Instant::now() > deadline {
            child.kill().unwrap();
            child.wait().unwrap();
            panic!("no sequence recorded within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    assert!(
        !killed.join("manifest.json").exists(),
        "the run must be killed before it completes"
    );
    let mut resumed = run(&["--resume"]);
    let status = wait_until(&mut resumed, Instant::now() + limit, "generate --resume");
    assert!(status.success(), "{status}");
    assert_same_tree(&whole, &killed);
}

#[test]
fn resume_refuses_a_dataset_of_another_scene_or_seed() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), FAMILY_SCENE);
    let out_dir = tmp.path().join("ds");
    assert!(generate(&scene, &out_dir, &[]).status.success());
    let other_seed = write_scene(tmp.path(), &FAMILY_SCENE.replace("seed = 5", "seed = 6"));
    assert_user_error(&generate(&other_seed, &out_dir, &["--resume"]), "seed 5");
    let other = write_scene(tmp.path(), &SMALL_SCENE.replace("seed = 11", "seed = 5"));
    assert_user_error(&generate(&other, &out_dir, &["--resume"]), "another scene");
    let not_dataset = tmp.path().join("notes");
    std::fs::create_dir(&not_dataset).unwrap();
    std::fs::write(not_dataset.join("a.txt"), "x").unwrap();
    assert_user_error(
        &generate(&other, &not_dataset, &["--resume"]),
        "not a sparsh dataset",
    );
}

#[test]
fn verify_names_missing_and_corrupt_files() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), SMALL_SCENE);
    let out_dir = tmp.path().join("ds");
    assert!(generate(&scene, &out_dir, &[]).status.success());
    std::fs::remove_file(out_dir.join("frames/000003.png")).unwrap();
    std::fs::write(out_dir.join("fields/000004.exr"), b"not an exr").unwrap();
    let out = sparsh(&["verify", out_dir.to_str().unwrap()]);
    assert!(!out.status.success());
    let report = String::from_utf8_lossy(&out.stdout);
    assert!(report.contains("frames/000003.png: missing"), "{report}");
    assert!(report.contains("fields/000004.exr: corrupt"), "{report}");
    assert_user_error(&out, "2 of 28 files missing or corrupt");
}

#[test]
fn bad_generate_options_fail_with_one_line() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), FAMILY_SCENE);
    let out_dir = tmp.path().join("ds");
    for shard in ["3/3", "1/0", "a/2", "2"] {
        let out = generate(&scene, &out_dir, &["--shard", shard]);
        assert!(!out.status.success(), "--shard {shard} accepted");
        assert!(stderr(&out).contains("--shard"), "{}", stderr(&out));
    }
    let missing_mesh = FAMILY_SCENE.replace(
        "shape = \"cylinder\"\nradius_mm = 1.5",
        "shape = \"mesh\"\nmesh = \"meshes/lost.obj\"",
    );
    let scene = write_scene(tmp.path(), &missing_mesh);
    // The mesh entry is drawn by some sequences only; loading checks every entry up front.
    assert_user_error(&generate(&scene, &out_dir, &[]), "lost.obj");
    let blocked = tmp.path().join("file-not-dir");
    std::fs::write(&blocked, "x").unwrap();
    let scene = write_scene(tmp.path(), SMALL_SCENE);
    assert_user_error(&generate(&scene, &blocked.join("ds"), &[]), "file-not-dir");
}

/// Whether python3 can import the given modules; without them the test skips, unless
/// `SPARSH_REQUIRE_PYTHON` is set (CI), where it fails.
fn python_with(modules: &str) -> bool {
    let ok = std::process::Command::new("python3")
        .args(["-c", &format!("import {modules}")])
        .output()
        .is_ok_and(|o| o.status.success());
    assert!(
        ok || std::env::var_os("SPARSH_REQUIRE_PYTHON").is_none(),
        "SPARSH_REQUIRE_PYTHON is set but python3 cannot import {modules}"
    );
    ok
}

#[test]
fn export_writes_the_official_sparsh_layout() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), FAMILY_SCENE);
    let ds = tmp.path().join("ds");
    assert!(generate(&scene, &ds, &[]).status.success());
    let out_dir = tmp.path().join("pkl");
    let out = sparsh(&[
        "export",
        ds.to_str().unwrap(),
        "--format",
        "sparsh-pkl",
        "--out",
        out_dir.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    // one line saying what was written
    let said = stderr(&out);
    assert_eq!(said.trim_end().lines().count(), 1, "{said}");
    assert!(
        said.contains("pkl: 16 sequences (digit, gelsight_mini) in the official Sparsh layouts"),
        "{said}"
    );
    let labels = std::fs::read_to_string(ds.join("labels.jsonl")).unwrap();
    let rows: Vec<serde_json::Value> = labels
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let row = |sequence: usize, k: usize| {
        rows.iter()
            .find(|r| r["sequence"] == sequence && r["frame_in_sequence"] == k)
            .unwrap()
    };
    let force = |r: &serde_json::Value| -> [f64; 3] {
        std::array::from_fn(|c| r["force_n"][c].as_f64().unwrap())
    };

    // Our reader of the official datasets, on each batch: every frame, its force and split.
    let first_of = |family: &str, split: &str| {
        rows.iter()
            .find(|r| r["family"] == family && r["split"] == split)
            .map(|r| r["sequence"].as_u64().unwrap() as usize)
            .unwrap()
    };
    let (spheres, cones) = (first_of("spheres", "train"), first_of("cones", "train"));
    for (family, sequence, sensor, length) in [
        ("spheres", spheres, "digit", 16),
        ("cones", cones, "gelsight_mini", 12),
    ] {
        let batch = format!("force_slip/{sensor}/train/{family}/batch_{sequence:06}");
        let data = sparsh_bench::official::load(&out_dir.join(batch), [32, 24]).unwrap();
        assert_eq!(data.labels.len(), 1);
        let frames = &data.labels[0].frames;
        assert_eq!(frames.len(), length);
        for (k, f) in frames.iter().enumerate() {
            assert_eq!(f.force_n, Some(force(row(sequence, k))));
            assert_eq!(f.slip_cone, row(sequence, k)["slip_cone"].as_bool());
        }
        assert_eq!(data.labels[0].test, Some(false));
    }
    let test_batches: Vec<usize> = rows
        .iter()
        .filter(|r| r["split"] == "test" && r["frame_in_sequence"] == 0)
        .map(|r| r["sequence"].as_u64().unwrap() as usize)
        .collect();
    assert!(!test_batches.is_empty());
    let dir = out_dir.join(format!(
        "force_slip/digit/test/spheres/batch_{:06}",
        test_batches[0]
    ));
    assert_eq!(
        sparsh_bench::official::load(&dir, [32, 24]).unwrap().labels[0].test,
        Some(true)
    );

    // The official loaders, transcribed (tests/official_loaders.py).
    if python_with("numpy, PIL, yaml") {
        let (report, image) = (tmp.path().join("report.json"), tmp.path().join("input.f32"));
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/official_loaders.py");
        let run = std::process::Command::new("python3")
            .arg(&script)
            .args([&out_dir, &report, &image])
            .output()
            .unwrap();
        assert!(
            run.status.success(),
            "{}",
            String::from_utf8_lossy(&run.stderr)
        );
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
        let items = report["force"].as_array().unwrap();
        // every sequence, less the 5 trailing samples the official index map leaves out
        assert_eq!(items.len(), 10 * (16 - 5) + 6 * (12 - 5));
        for item in items {
            let batch = item["batch"].as_str().unwrap();
            let sequence: usize = batch.rsplit("batch_").next().unwrap().parse().unwrap();
            let sample = item["sample"].as_u64().unwrap() as usize;
            let r = row(sequence, sample);
            assert_eq!(item["split"], r["split"], "{batch}");
            let got: [f64; 3] = std::array::from_fn(|c| item["force_n"][c].as_f64().unwrap());
            assert_eq!(got, force(r), "{batch} sample {sample}");
            assert_eq!(item["slip_label"] == 1, r["slip_cone"].as_bool().unwrap());
            // the official delta: force now minus 5 samples before (clipped), over its scale
            let scale = [0.25, 0.25, 0.15];
            for c in 0..3 {
                let want = (r["delta_force_n"][c].as_f64().unwrap() / scale[c]).clamp(-1.0, 1.0);
                let delta = item["delta_force"][c].as_f64().unwrap();
                assert!(
                    (delta - want).abs() < 1e-9,
                    "{batch} {sample}: {delta} vs {want}"
                );
            }
        }
        let ssl = &report["ssl"];
        assert_eq!(
            ssl["train"].as_object().unwrap().len() + ssl["val"].as_object().unwrap().len(),
            16
        );
        assert_eq!(ssl["train"][format!("spheres_{spheres:06}/dataset_0")], 16);
        assert_eq!(ssl["train"][format!("cones_{cones:06}/dataset_0")], 12);
        assert_eq!(
            ssl["val"][format!("spheres_{:06}/dataset_0", test_batches[0])],
            16
        );
        assert_eq!(
            ssl["input_shapes"],
            serde_json::json!(["(120, 90, 3)", "(160, 120, 3)"])
        );

        // The official input of the most pressed sample is our preprocessing of the same PNG
        // (up to the JPEG of the export), not its 180° turn.
        let strongest = &report["strongest"];
        let batch = strongest["batch"].as_str().unwrap();
        let sequence: usize = batch.rsplit("batch_").next().unwrap().parse().unwrap();
        let sample = strongest["sample"].as_u64().unwrap() as usize;
        let r = row(sequence, sample);
        let png = |rel: &str| image::open(ds.join(rel)).unwrap().to_rgb8();
        let frame = png(&format!("frames/{:06}.png", r["frame"].as_u64().unwrap()));
        let bg = png(r["background"].as_str().unwrap());
        let size = [frame.width() as usize, frame.height() as usize];
        let ours = sparsh_ssl::data::preprocess(&frame, &bg, size).unwrap();
        let bytes = std::fs::read(&image).unwrap();
        let official: Vec<f32> = bytes
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .take(ours.len())
            .collect();
        let mean_abs = |a: &[f32], b: &mut dyn Iterator<Item = f32>| {
            a.iter()
                .zip(b)
                .map(|(x, y)| (x - y).abs() as f64)
                .sum::<f64>()
                / a.len() as f64
        };
        let plane = size[0] * size[1];
        let same = mean_abs(&ours, &mut official.iter().copied());
        let turned = mean_abs(
            &ours,
            &mut (0..3).flat_map(|c| official[c * plane..(c + 1) * plane].iter().rev().copied()),
        );
        eprintln!("official input: mean |Δ| {same:.5} from ours, {turned:.5} from its 180° turn");
        assert!(same < 0.005, "official input differs from ours by {same}");
        assert!(
            turned > 5.0 * same,
            "a 180° turn is as close: {turned} vs {same}"
        );
    }

    let out = sparsh(&[
        "export",
        tmp.path().join("nowhere").to_str().unwrap(),
        "--format",
        "sparsh-pkl",
        "--out",
        out_dir.to_str().unwrap(),
    ]);
    assert_user_error(&out, "labels.jsonl");
}

#[test]
fn calibration_commands_reject_bad_input_on_one_line() {
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("missing.npz");
    let out = tmp.path().join("calib");
    let run = |extra: &[&str]| {
        let mut args = vec!["calibrate", "--pack", missing.to_str().unwrap()];
        args.extend_from_slice(extra);
        args.extend_from_slice(&["--out", out.to_str().unwrap()]);
        sparsh(&args)
    };
    assert_user_error(&run(&["--pixmm", "0.03"]), "missing.npz");
    assert_user_error(&run(&["--pixmm=-1"]), "--pixmm");
    assert_user_error(
        &run(&["--pixmm", "0.03", "--ball-radius-mm", "0"]),
        "--ball-radius-mm",
    );
    assert_user_error(&run(&["--pixmm", "0.03", "--shadows"]), "--sensor");
    assert_user_error(
        &run(&["--pixmm", "0.03", "--shadows", "--sensor", "nope"]),
        "unknown preset nope",
    );
    // The surface under the ball: a known model, with the gel it needs.
    assert_user_error(
        &run(&["--pixmm", "0.03", "--mechanics", "soft"]),
        "--mechanics: unknown model \"soft\"",
    );
    assert_user_error(
        &run(&["--pixmm", "0.03", "--mechanics", "layered"]),
        "--mechanics layered needs --gel-thickness-mm",
    );
    assert_user_error(
        &run(&[
            "--pixmm",
            "0.03",
            "--mechanics",
            "geometric",
            "--gel-thickness-mm",
            "0",
        ]),
        "--gel-thickness-mm must be > 0, got 0",
    );
    assert_user_error(
        &run(&["--pixmm", "0.03", "--gel-thickness-mm", "3"]),
        "--gel-thickness-mm is used only with --mechanics geometric or layered",
    );
    assert_user_error(
        &run(&[
            "--pixmm",
            "0.03",
            "--mechanics",
            "layered",
            "--gel-thickness-mm",
            "3",
            "--poisson-ratio",
            "0.7",
        ]),
        "--poisson-ratio must be in (−1, 0.5], got 0.7",
    );
    // Without --pixmm the pitch is the params.json's beside the pack (Taxim's layout).
    assert_user_error(
        &run(&[]),
        "--pixmm not given and no params.json beside the pack",
    );
    let params = tmp.path().join("params.json");
    std::fs::write(&params, r#"{"sensor": {"pixmm": -1}}"#).unwrap();
    assert_user_error(&run(&[]), "params.json: sensor.pixmm must be > 0, got -1");
    std::fs::write(&params, r#"{"sensor": {"pixmm": 0.03}}"#).unwrap();
    let res = run(&[]);
    let err = stderr(&res);
    assert!(!res.status.success(), "{err}");
    let lines: Vec<&str> = err.lines().collect();
    assert!(
        lines.len() == 2
            && lines[0].ends_with("params.json: pixel pitch 0.03 mm/px")
            && lines[1].contains("missing.npz"),
        "{err}"
    );
    let not_npz = tmp.path().join("pack.npz");
    std::fs::write(&not_npz, b"not a zip").unwrap();
    let shipped = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/calib/gelsight");
    let res = sparsh(&[
        "sim2real",
        "--pack",
        not_npz.to_str().unwrap(),
        "--calib",
        shipped.to_str().unwrap(),
    ]);
    assert_user_error(&res, "pack.npz");
    assert!(!out.exists(), "nothing written on bad input");
}

/// `sim2real` takes the pixel pitch from the calibration's map.json: a `--pixmm` that
/// contradicts it, a missing calibration directory, and a pitch recorded nowhere each fail on
/// one line naming what is wrong.
#[test]
fn sim2real_takes_the_pitch_from_the_calibration() {
    let tmp = tempfile::tempdir().unwrap();
    let pack = tmp.path().join("missing.npz");
    let shipped = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/calib/gelsight");
    let run = |calib: &Path, extra: &[&str]| {
        let mut args = vec![
            "sim2real",
            "--pack",
            pack.to_str().unwrap(),
            "--calib",
            calib.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        sparsh(&args)
    };
    let out = run(&shipped, &["--pixmm", "0.03"]);
    assert_user_error(&out, "map.json");
    let err = stderr(&out);
    assert!(
        err.contains("mm_per_px") && err.contains("0.0295") && err.contains("0.03"),
        "{err}"
    );
    // The same pitch given twice is fine: the run gets as far as the (missing) pack.
    assert_user_error(&run(&shipped, &["--pixmm", "0.0295"]), "missing.npz");
    assert_user_error(&run(&shipped, &[]), "missing.npz");
    let nowhere = tmp.path().join("no_calibration");
    let out = run(&nowhere, &[]);
    assert_user_error(&out, "no_calibration");
    assert!(stderr(&out).contains("map.json"), "{}", stderr(&out));
    // A calibration that records no pitch needs --pixmm.
    let bare = tmp.path().join("bare");
    std::fs::create_dir(&bare).unwrap();
    std::fs::copy(shipped.join("background.png"), bare.join("background.png")).unwrap();
    let mut map: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(shipped.join("map.json")).unwrap()).unwrap();
    map.as_object_mut().unwrap().remove("provenance");
    std::fs::write(bare.join("map.json"), map.to_string()).unwrap();
    assert_user_error(&run(&bare, &[]), "--pixmm");
    assert_user_error(&run(&bare, &["--pixmm", "0.0295"]), "missing.npz");
    // The mechanics a map was fitted under are read back from it, and refused when malformed.
    for (mechanics, expect) in [
        (
            serde_json::json!({"model": "layered", "thickness_mm": -1.0, "poisson_ratio": 0.49}),
            "provenance.mechanics: thickness_mm must be > 0, got -1",
        ),
        (
            serde_json::json!({"model": "soft"}),
            "provenance.mechanics: unknown variant `soft`",
        ),
    ] {
        let odd = tmp.path().join("odd_mechanics");
        std::fs::create_dir_all(&odd).unwrap();
        std::fs::copy(shipped.join("background.png"), odd.join("background.png")).unwrap();
        let mut map: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(shipped.join("map.json")).unwrap())
                .unwrap();
        map["provenance"]["mechanics"] = mechanics;
        std::fs::write(odd.join("map.json"), map.to_string()).unwrap();
        let out = run(&odd, &[]);
        assert_user_error(&out, expect);
        assert!(stderr(&out).contains("map.json"), "{}", stderr(&out));
    }
    // Shadows without a fitted calibration need a sensor to cast them from.
    assert_user_error(&run(&shipped, &["--shadows"]), "--sensor");
    assert_user_error(&run(&shipped, &["--sensor", "gelsight2017"]), "--shadows");
}

fn render_on(scene: &Path, png: &Path, device: &str, backend: Option<&str>) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_sparsh"));
    cmd.args([
        "render",
        scene.to_str().unwrap(),
        "--frame",
        "7",
        "--png",
        png.to_str().unwrap(),
        "--device",
        device,
    ]);
    if let Some(b) = backend {
        cmd.env("WGPU_BACKEND", b);
    }
    cmd.output().expect("sparsh runs")
}

#[test]
fn device_without_an_adapter_fails_or_falls_back_on_one_line() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), SMALL_SCENE);
    let (cpu, auto) = (tmp.path().join("cpu.png"), tmp.path().join("auto.png"));
    // Only DirectX 12, which Linux does not have: wgpu finds no adapter.
    let out = render_on(&scene, &tmp.path().join("gpu.png"), "gpu", Some("dx12"));
    assert_user_error(&out, "no GPU adapter");
    assert!(!tmp.path().join("gpu.png").exists());
    // `wgpu`, the learning commands' name for the same device, is taken too
    let out = render_on(&scene, &tmp.path().join("gpu.png"), "wgpu", Some("dx12"));
    assert_user_error(&out, "no GPU adapter");
    let out = render_on(&scene, &auto, "auto", Some("dx12"));
    assert!(out.status.success(), "{}", stderr(&out));
    // one line on the fallback, then render's line on what it wrote
    let err = stderr(&out);
    let lines: Vec<&str> = err.trim_end().lines().collect();
    assert_eq!(lines.len(), 2, "{err}");
    assert!(
        lines[0].contains("no GPU adapter") && lines[0].contains("CPU"),
        "{err}"
    );
    assert!(lines[1].contains("auto.png: frame 7"), "{err}");
    assert!(
        render_on(&scene, &cpu, "cpu", Some("dx12"))
            .status
            .success()
    );
    assert!(std::fs::read(&cpu).unwrap() == std::fs::read(&auto).unwrap());
}

#[test]
fn render_on_the_gpu_matches_the_cpu_within_a_level() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), SMALL_SCENE);
    let (cpu, gpu) = (tmp.path().join("cpu.png"), tmp.path().join("gpu.png"));
    let out = render_on(&scene, &gpu, "gpu", None);
    if !out.status.success() && std::env::var("SPARSH_REQUIRE_GPU").as_deref() != Ok("1") {
        eprintln!("skipped: {}", stderr(&out));
        return;
    }
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(render_on(&scene, &cpu, "cpu", None).status.success());
    let (a, b) = (
        image::open(&cpu).unwrap().to_rgb8(),
        image::open(&gpu).unwrap().to_rgb8(),
    );
    let worst = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(x, y)| x.abs_diff(*y))
        .max()
        .unwrap();
    assert!(worst <= 1, "CPU and GPU frames differ by {worst}");
}

#[test]
fn quick_study_writes_tables_and_charts() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("study");
    let table = tmp.path().join("table.csv");
    let out = sparsh(&[
        "study",
        "--quick",
        "--out",
        dir.to_str().unwrap(),
        "--table",
        table.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let read = |name: &str| std::fs::read_to_string(dir.join(name)).unwrap();
    assert!(read("study.csv").starts_with("scene,rung,a_over_cell,"));
    assert!(read("stability.csv").starts_with("sweep,value,friction,rung,"));
    let written = read("solver_table.csv");
    assert_eq!(std::fs::read_to_string(&table).unwrap(), written);
    // every CSV starts with its header row; provenance is in a JSON sidecar
    for name in ["study.csv", "stability.csv", "solver_table.csv"] {
        assert!(!read(name).starts_with('#'), "{name}");
    }
    for sidecar in [dir.join("solver_table.json"), table.with_extension("json")] {
        let json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&sidecar).unwrap()).unwrap();
        assert!(
            json["written_by"]
                .as_str()
                .unwrap()
                .contains("study --quick")
        );
    }
    let parsed = sparsh_scene::auto::SolverTable::parse(&written).unwrap();
    assert!(!parsed.rows.is_empty());
    for (stem, size, needle) in [
        ("error_vs_time", (1100, 760), "Pareto front"),
        ("error_vs_time_layers", (1100, 760), "Pareto front"),
        ("stability_geometric", (1300, 860), "Stability map"),
        ("stability_halfspace", (1300, 860), "Stability map"),
        // the depth sweep a row per friction coefficient
        ("stability_layered", (1300, 860), "depth/thickness, μ 1"),
    ] {
        let png = image::open(dir.join(format!("{stem}.png"))).unwrap();
        assert_eq!((png.width(), png.height()), size, "{stem}");
        let svg = read(&format!("{stem}.svg"));
        assert!(svg.starts_with("<svg") && svg.contains(needle), "{stem}");
    }

    // An output path that is a file is refused on one line.
    let file = tmp.path().join("file");
    std::fs::write(&file, "x").unwrap();
    let out = sparsh(&["study", "--quick", "--out", file.to_str().unwrap()]);
    assert_user_error(&out, "cannot create");
}

#[test]
fn study_runs_named_sweeps_alone() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("sweep");
    let out = sparsh(&[
        "study",
        "--quick",
        "--sweep",
        "poisson_ratio",
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let csv = std::fs::read_to_string(dir.join("stability.csv")).unwrap();
    let rows: Vec<&str> = csv.lines().skip(1).collect();
    // seven Poisson ratios, each on every rung
    assert_eq!(rows.len(), 7 * sparsh_scene::SolverKind::ALL.len());
    assert!(
        rows.iter().all(|r| r.starts_with("poisson_ratio,")),
        "{csv}"
    );
    // no accuracy study, and no solver table that would miss rows
    assert!(!dir.join("study.csv").exists() && !dir.join("solver_table.csv").exists());
    // Run again over a study's file, its points on two threads: the sweep's rows are replaced
    // by the same rows in the same order, the other sweeps' kept.
    let other = "sharpness,\"cone 10°\",0,layered,0.1,\"Sneddon\",1e0,1e0,0e0,ok,\"\"";
    std::fs::write(dir.join("stability.csv"), format!("{csv}{other}\n")).unwrap();
    let out = sparsh(&[
        "study",
        "--quick",
        "--sweep",
        "poisson_ratio",
        "--jobs",
        "2",
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let merged = std::fs::read_to_string(dir.join("stability.csv")).unwrap();
    let mut lines: Vec<&str> = merged.lines().collect();
    assert_eq!(lines.remove(0), csv.lines().next().unwrap());
    assert_eq!(lines.remove(0), other);
    assert_eq!(lines, rows);
    let no_jobs = sparsh(&[
        "study",
        "--sweep",
        "poisson_ratio",
        "--jobs",
        "0",
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert_user_error(&no_jobs, "--jobs: must be at least 1");

    let out = sparsh(&[
        "study",
        "--sweep",
        "press_slid",
        "--out",
        dir.to_str().unwrap(),
    ]);
    assert_user_error(&out, "no sweep named \"press_slid\"");
    // A table is updated only by the sweeps it has rows of, and only when it can be read,
    // before any solving.
    let table = tmp.path().join("table.csv");
    let sweep_into_table = |sweep: &str| {
        sparsh(&[
            "study",
            "--sweep",
            sweep,
            "--table",
            table.to_str().unwrap(),
            "--out",
            dir.to_str().unwrap(),
        ])
    };
    assert_user_error(
        &sweep_into_table("poisson_ratio"),
        "--table: the poisson_ratio sweep has no rows in the solver table",
    );
    assert_user_error(
        &sweep_into_table("press_slide"),
        "table.csv: cannot read the solver table",
    );
    std::fs::write(&table, "rung,a_over_cell\n").unwrap();
    assert_user_error(
        &sweep_into_table("press_slide"),
        "table.csv: not a solver table",
    );
    assert_eq!(
        std::fs::read_to_string(&table).unwrap(),
        "rung,a_over_cell\n"
    );
}

#[test]
fn auto_solver_scene_renders() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(
        tmp.path(),
        &SMALL_SCENE.replace(
            "solver = \"geometric\"",
            "solver = \"auto\"\ntolerance = 0.2",
        ),
    );
    let png = tmp.path().join("f.png");
    let out = render_on(&scene, &png, "cpu", None);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(png.exists());
    let said = stderr(&out);
    assert!(
        said.contains("solver = \"auto\" chose") && said.contains("mechanics_stride"),
        "auto's choice is not reported: {said}"
    );
}

/// The calibrated model as a scene option, with shadows, printed markers and seeded noise:
/// byte-identical with one or two threads, and the labels carry every dot's centre (the
/// printed grid itself while nothing touches).
#[test]
fn calibrated_model_with_markers_and_noise_is_deterministic() {
    let calib = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/calib/gelsight");
    let text = SMALL_SCENE.replace("preset = \"digit\"", "preset = \"gelsight2017\"")
        + &format!(
            "[optics]\nmodel = \"calibrated\"\ncalibration = {:?}\nshadows = true\n\
             noise_std = 2.0\nbackground_variation = 0.05\nexposure = 1.1\n",
            calib.canonicalize().unwrap()
        );
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), &text);
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    let out = generate(&scene, &a, &["--threads", "1"]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(generate(&scene, &b, &["--threads", "2"]).status.success());
    assert_same_tree(&a, &b);
    let labels = std::fs::read_to_string(a.join("labels.jsonl")).unwrap();
    let first: serde_json::Value = serde_json::from_str(labels.lines().next().unwrap()).unwrap();
    let markers = first["markers_px"].as_array().unwrap();
    assert_eq!(markers.len(), 15 * 11);
    // Dot (0, 0) printed at (−7·1.2, −5·1.2) mm; pixel (0, 0)'s centre is at (−7.9, −5.9) mm.
    let x = markers[0][0].as_f64().unwrap();
    let y = markers[0][1].as_f64().unwrap();
    assert!((x - (-8.4 + 7.9) / 0.2).abs() < 1e-9, "{x}");
    assert!((y - (-6.0 + 5.9) / 0.2).abs() < 1e-9, "{y}");
}

#[test]
fn probe_refuses_a_label_budget_or_random_init_count_out_of_range() {
    let tmp = tempfile::tempdir().unwrap();
    let recipe = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/ssl/mae_tiny_cpu.toml");
    let bad = [
        ("--label-fraction", "0"),
        ("--label-fraction", "1.5"),
        ("--label-fraction", "-0.1"),
        ("--random-inits", "0"),
        ("--random-inits", "101"),
    ];
    for (flag, value) in bad {
        let out = sparsh(&[
            "probe",
            "--config",
            recipe.to_str().unwrap(),
            "--data",
            tmp.path().to_str().unwrap(),
            &format!("{flag}={value}"),
        ]);
        assert_user_error(&out, flag);
    }
}

/// `validate` and `bench-optics` find the cases and the calibration they ship with from any
/// working directory; a missing directory is named once, on one line.
#[test]
fn shipped_defaults_work_from_any_directory() {
    let tmp = tempfile::tempdir().unwrap();
    let run = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_sparsh"))
            .args(args)
            .current_dir(tmp.path())
            .output()
            .expect("sparsh runs")
    };
    let out = run(&["validate", "--json"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(!report["rows"].as_array().unwrap().is_empty());
    let out = run(&["bench-optics", "--repeats", "1", "--threads-list", "1"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let missing = tmp.path().join("no_cases");
    let out = run(&["validate", missing.to_str().unwrap()]);
    assert_user_error(&out, "no_cases");
    let err = stderr(&out);
    assert_eq!(err.matches("No such file").count(), 1, "{err}");
}

/// A table read by something that stops early (`sparsh limits | head -1`) ends the command
/// quietly, as `SIGPIPE` ends other Unix tools, not with a panic on the closed pipe.
#[test]
fn a_closed_pipe_ends_a_table_without_a_panic() {
    let mut child = Command::new(env!("CARGO_BIN_EXE_sparsh"))
        .arg("limits")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("sparsh runs");
    // The reader goes before the command has printed (it has not yet loaded).
    drop(child.stdout.take());
    let out = child.wait_with_output().expect("sparsh ends");
    let err = stderr(&out);
    assert!(!err.contains("panicked"), "{err}");
    #[cfg(unix)]
    {
        use std::os::unix::process::ExitStatusExt;
        assert!(
            out.status.success() || out.status.signal() == Some(libc::SIGPIPE),
            "{:?}: {err}",
            out.status
        );
    }
}
