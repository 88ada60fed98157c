//! `sparsh tacbench` end to end on a small generated dataset: every task, every kind of
//! encoder row, the report files, resume, one-line errors for bad configs and devices, and the
//! same units on wgpu as on the CPU.

use std::path::{Path, PathBuf};

mod common;
use common::{
    RECIPE, assert_device_refused, assert_user_error, json_files, sparsh, stderr, wgpu_or_skip,
};

/// Two families (the texture task's two classes), press-and-slide and twist, with held-out
/// cylinders: force, slip, pose and grasp labels on every frame.
const DATA_SCENE: &str = r#"
seed = 7
[output]
fields = []
[[family]]
name = "slide"
sequences = 12
frames_per_sequence = 14
solver = "halfspace"
mechanics_stride = 4
mechanics_margin_mm = 3.0
[family.sensor]
preset = "digit"
width_px = 160
height_px = 120
mm_per_px = 0.125
[family.gel]
friction = [0.3, 1.2]
[[family.indenters]]
shape = "sphere"
radius_mm = [3.0, 6.0]
[[family.indenters]]
shape = "cylinder"
radius_mm = [1.5, 2.5]
split = "test"
[family.motion]
kind = "press_slide"
depth_mm = [0.3, 0.8]
slide_mm = [0.5, 2.5]
[[family]]
name = "twist"
sequences = 8
frames_per_sequence = 14
solver = "halfspace"
mechanics_stride = 4
mechanics_margin_mm = 3.0
[family.sensor]
preset = "digit"
width_px = 160
height_px = 120
mm_per_px = 0.125
[[family.indenters]]
shape = "sphere"
radius_mm = [3.0, 6.0]
[[family.indenters]]
shape = "cylinder"
radius_mm = [1.5, 2.5]
split = "test"
[family.motion]
kind = "twist"
depth_mm = [0.3, 0.8]
"#;

fn config(tasks: &[(&str, &str)], budgets: &str) -> String {
    let mut s = format!(
        "seed = 3\nbudgets = {budgets}\nbootstrap = 50\n[probe]\nepochs = 2\n\
         [[encoder]]\nname = \"weights\"\nrecipe = \"recipe.toml\"\nweights = \"weights.safetensors\"\n\
         [[random]]\nname = \"random\"\nrecipe = \"recipe.toml\"\ndraws = 2\n\
         [baselines]\nrecipe = \"recipe.toml\"\n"
    );
    for (kind, data) in tasks {
        s += &format!("[[task]]\nkind = \"{kind}\"\ndata = \"{data}\"\nframe_stride = 2\n");
    }
    s
}

/// Writes the recipe, a weights file of its architecture (seed 5's random draw) and the
/// dataset into `dir`.
fn setup(dir: &Path) -> PathBuf {
    std::fs::write(dir.join("recipe.toml"), RECIPE).unwrap();
    let recipe = sparsh_ssl::recipe::Recipe::parse(RECIPE).unwrap();
    let vit = sparsh_bench::run::random_encoder(&recipe, 5).unwrap();
    sparsh_ssl::weights::save_encoder(&vit, &dir.join("weights.safetensors")).unwrap();
    let scene = dir.join("data.toml");
    std::fs::write(&scene, DATA_SCENE).unwrap();
    let data = dir.join("data");
    let out = sparsh(&[
        "generate",
        scene.to_str().unwrap(),
        "--out",
        data.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    data
}

#[test]
fn tacbench_runs_every_task_and_resumes() {
    let tmp = tempfile::tempdir().unwrap();
    setup(tmp.path());
    let tasks = ["force", "slip", "pose", "texture", "grasp"];
    let cfg = tmp.path().join("bench.toml");
    let pairs: Vec<(&str, &str)> = tasks.iter().map(|&t| (t, "data")).collect();
    std::fs::write(&cfg, config(&pairs, "[1.0, 0.33, 0.1, 0.01]")).unwrap();
    let out_dir = tmp.path().join("run");
    let args = [
        "tacbench",
        "--config",
        cfg.to_str().unwrap(),
        "--out",
        out_dir.to_str().unwrap(),
        "--quick",
    ];
    let out = sparsh(&args);
    assert!(out.status.success(), "{}", stderr(&out));

    // results.csv: plain CSV, header first, every task × kind of row
    let mut reader = csv::Reader::from_path(out_dir.join("results.csv")).unwrap();
    let header: Vec<String> = reader.headers().unwrap().iter().map(String::from).collect();
    assert_eq!(
        &header[..6],
        ["task", "encoder", "kind", "budget", "metric", "value"]
    );
    let rows: Vec<csv::StringRecord> = reader.records().map(|r| r.unwrap()).collect();
    for task in tasks {
        for kind in [
            "pretrained",
            "random",
            "random_draws",
            "pixels",
            "end_to_end",
            "constant",
        ] {
            assert!(
                rows.iter().any(|r| &r[0] == task && &r[2] == kind),
                "no {kind} row for {task}"
            );
        }
        for ext in ["png", "svg"] {
            assert!(
                out_dir.join(format!("budget_{task}.{ext}")).is_file(),
                "{task} chart"
            );
        }
    }
    // quick runs budgets 1 and 0.1
    let budgets: std::collections::BTreeSet<&str> =
        rows.iter().map(|r| r.get(3).unwrap()).collect();
    assert_eq!(budgets.into_iter().collect::<Vec<_>>(), ["0.1", "1.0"]);
    // the pretrained rows are ranked among the 2 random draws of their architecture
    let ranked = rows.iter().find(|r| &r[2] == "pretrained").unwrap();
    let rank_of = header.iter().position(|h| h == "rank_of").unwrap();
    assert_eq!(&ranked[rank_of], "3");
    // accuracies and F1 lie in [0, 1], RMSEs are positive
    let value = |r: &csv::StringRecord| r[5].parse::<f64>().unwrap();
    for r in &rows {
        let v = value(r);
        if r[4].starts_with("accuracy") || &r[4] == "f1" || r[4].ends_with("balanced_accuracy") {
            assert!((0.0..=1.0).contains(&v), "{r:?}");
        } else {
            assert!(v >= 0.0 && v.is_finite(), "{r:?}");
        }
    }
    let md = std::fs::read_to_string(out_dir.join("results.md")).unwrap();
    for task in tasks {
        assert!(md.contains(&format!("**{task}**")), "{md}");
    }

    // again without --resume: refused; with it: nothing new, the same table
    let again = sparsh(&args);
    assert_user_error(&again, "--resume");
    let csv_before = std::fs::read(out_dir.join("results.csv")).unwrap();
    let mut resumed: Vec<&str> = args.to_vec();
    resumed.push("--resume");
    let out = sparsh(&resumed);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(String::from_utf8_lossy(&out.stdout).contains("(0 new)"));
    assert_eq!(
        std::fs::read(out_dir.join("results.csv")).unwrap(),
        csv_before
    );
    // --report-only trains nothing and rewrites the same report
    let mut report_only: Vec<&str> = args.to_vec();
    report_only.push("--report-only");
    std::fs::remove_file(out_dir.join("results.csv")).unwrap();
    let out = sparsh(&report_only);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(String::from_utf8_lossy(&out.stdout).contains("(0 new)"));
    assert_eq!(
        std::fs::read(out_dir.join("results.csv")).unwrap(),
        csv_before
    );
    // other weights under the same name: the recorded units are not theirs
    let recipe = sparsh_ssl::recipe::Recipe::parse(RECIPE).unwrap();
    let other = sparsh_bench::run::random_encoder(&recipe, 6).unwrap();
    sparsh_ssl::weights::save_encoder(&other, &tmp.path().join("weights.safetensors")).unwrap();
    assert_user_error(&sparsh(&resumed), "weights file");
}

#[test]
fn bad_tacbench_configs_fail_on_one_line() {
    let tmp = tempfile::tempdir().unwrap();
    setup(tmp.path());
    let run = |name: &str, text: &str| {
        let cfg = tmp.path().join(format!("{name}.toml"));
        std::fs::write(&cfg, text).unwrap();
        let out_dir = tmp.path().join(format!("run_{name}"));
        sparsh(&[
            "tacbench",
            "--config",
            cfg.to_str().unwrap(),
            "--out",
            out_dir.to_str().unwrap(),
            "--quick",
        ])
    };
    // label budgets outside (0, 1]
    assert_user_error(
        &run("zero", &config(&[("force", "data")], "[1.0, 0.0]")),
        "budgets",
    );
    assert_user_error(
        &run("over", &config(&[("force", "data")], "[1.5]")),
        "budgets",
    );
    // a task whose labels the data lack: one family is one texture class
    let one_family = tmp.path().join("one_family");
    std::fs::create_dir_all(&one_family).unwrap();
    let scene = tmp.path().join("one.toml");
    let first_family = DATA_SCENE
        .split("[[family]]\nname = \"twist\"")
        .next()
        .unwrap();
    std::fs::write(&scene, first_family).unwrap();
    let out = sparsh(&[
        "generate",
        scene.to_str().unwrap(),
        "--out",
        one_family.to_str().unwrap(),
        "--force",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_user_error(
        &run("texture", &config(&[("texture", "one_family")], "[1.0]")),
        "at least two classes",
    );
    // an encoder file of another architecture: the recipe asks for three blocks
    let deeper = tmp.path().join("deeper.toml");
    std::fs::write(&deeper, RECIPE.replace("depth = 2", "depth = 3")).unwrap();
    let text = config(&[("force", "data")], "[1.0]").replacen(
        "recipe = \"recipe.toml\"",
        "recipe = \"deeper.toml\"",
        1,
    );
    assert_user_error(&run("arch", &text), "encoder[0].weights");
    // a budget twice, a task kind twice, a name the baselines use, a name that is a path
    assert_user_error(
        &run("twice", &config(&[("force", "data")], "[1.0, 1.0]")),
        "twice",
    );
    assert_user_error(
        &run(
            "kind",
            &config(&[("force", "data"), ("force", "data")], "[1.0]"),
        ),
        "task[1].kind",
    );
    let reserved = config(&[("force", "data")], "[1.0]").replacen("\"weights\"", "\"pixels\"", 1);
    assert_user_error(&run("reserved", &reserved), "encoder[0].name");
    let path = config(&[("force", "data")], "[1.0]").replacen("\"weights\"", "\"../up\"", 1);
    assert_user_error(&run("path", &path), "encoder[0].name");
    let zero = config(&[("force", "data")], "[1.0]").replacen(
        "[baselines]\nrecipe = \"recipe.toml\"\n",
        "[baselines]\nrecipe = \"recipe.toml\"\nend_to_end_epochs = 0\n",
        1,
    );
    assert_user_error(&run("zero_epochs", &zero), "end_to_end_epochs");
    // unknown keys and missing data
    assert_user_error(
        &run(
            "typo",
            &(config(&[("force", "data")], "[1.0]") + "epochz = 3\n"),
        ),
        "epochz",
    );
    assert_user_error(
        &run("nodata", &config(&[("force", "nowhere")], "[1.0]")),
        "nowhere",
    );
}

/// Numbers of a JSON value, depth first.
fn numbers(v: &serde_json::Value, out: &mut Vec<f64>) {
    match v {
        serde_json::Value::Number(n) => out.push(n.as_f64().unwrap()),
        serde_json::Value::Array(a) => a.iter().for_each(|x| numbers(x, out)),
        serde_json::Value::Object(o) => o.values().for_each(|x| numbers(x, out)),
        _ => {}
    }
}

/// The largest |a − b| of two equally shaped lists of numbers.
fn worst(a: &serde_json::Value, b: &serde_json::Value) -> f64 {
    let (mut x, mut y) = (Vec::new(), Vec::new());
    numbers(a, &mut x);
    numbers(b, &mut y);
    assert_eq!(x.len(), y.len());
    x.iter().zip(&y).fold(0.0, |m, (u, v)| m.max((u - v).abs()))
}

/// `--device wgpu` (Mesa's lavapipe here, a software Vulkan driver) records the CPU's units
/// for every kind of row (pretrained and random encoders, raw patches, end to end): each
/// encoder and head drawn on the CPU under its seed and moved, so the runs differ only by
/// floating-point rounding.
#[test]
fn tacbench_on_wgpu_records_the_cpu_units() {
    if !wgpu_or_skip() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    setup(tmp.path());
    // one random draw (a pretrained encoder takes the same path), the raw patches and the ViT
    // trained end to end, on a sample every 8 frames: lavapipe is some 10× slower than the CPU
    let cfg = tmp.path().join("bench.toml");
    let text = config(&[("force", "data")], "[1.0]")
        .replacen(
            "[[encoder]]\nname = \"weights\"\nrecipe = \"recipe.toml\"\nweights = \"weights.safetensors\"\n",
            "",
            1,
        )
        .replace("draws = 2", "draws = 1")
        .replace("frame_stride = 2", "frame_stride = 8");
    assert!(!text.contains("[[encoder]]"));
    std::fs::write(&cfg, text).unwrap();
    let run_on = |device: &str| {
        let out_dir = tmp.path().join(device);
        let t0 = std::time::Instant::now();
        let out = sparsh(&[
            "tacbench",
            "--config",
            cfg.to_str().unwrap(),
            "--out",
            out_dir.to_str().unwrap(),
            "--device",
            device,
        ]);
        assert!(out.status.success(), "{device}: {}", stderr(&out));
        eprintln!("{device}: {:.1} s", t0.elapsed().as_secs_f64());
        out_dir
    };
    let (cpu, gpu) = (run_on("cpu"), run_on("wgpu"));
    let units = json_files(&cpu.join("units"));
    assert_eq!(units, json_files(&gpu.join("units")));
    assert_eq!(units.len(), 3, "3 encoders × 1 budget: {units:?}");
    let read = |dir: &Path, unit: &Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(dir.join("units").join(unit)).unwrap())
            .unwrap()
    };
    let (mut preds, mut curves) = (0f64, 0f64);
    for unit in &units {
        let (a, b) = (read(&cpu, unit), read(&gpu, unit));
        let name = unit.display();
        assert_eq!(a["best_epoch"], b["best_epoch"], "{name}: epoch chosen");
        let p = worst(&a["test_preds"], &b["test_preds"]);
        let c = worst(&a["val_curve"], &b["val_curve"]);
        eprintln!("{name}: predictions differ by up to {p:.2e} N, validation RMSE {c:.2e} mN");
        (preds, curves) = (preds.max(p), curves.max(c));
    }
    assert!(preds <= PRED_TOL_N, "predictions differ by {preds:.2e} N");
    assert!(
        curves <= CURVE_TOL_MN,
        "validation RMSE differs by {curves:.2e} mN"
    );
}

/// Tolerances of [`tacbench_on_wgpu_records_the_cpu_units`]. Predicted forces are a few newtons
/// and their validation RMSE hundreds to thousands of mN; two epochs of training carry the
/// backends' rounding (sums in another order) to 1.9 mN in a prediction and 0.25 mN in a
/// validation RMSE here (2.7 and 1.7 mN in a `--quick` run of two tasks; lavapipe), so 10 mN and
/// 5 mN bound rounding, not another model.
const PRED_TOL_N: f64 = 1e-2;
const CURVE_TOL_MN: f64 = 5.0;

/// A device the build or the machine lacks, or several devices for a command that computes on
/// one, is refused on one line before anything is read or written.
#[test]
fn a_device_tacbench_cannot_use_is_a_one_line_error() {
    let tmp = tempfile::tempdir().unwrap();
    let out_dir = tmp.path().join("run");
    let args = [
        "tacbench",
        "--config",
        "missing.toml",
        "--out",
        out_dir.to_str().unwrap(),
    ];
    assert_device_refused(&args, &out_dir);
    // no ninth adapter here; a machine without any says so instead; still one line outside a
    // desktop session, where Mesa's device-select layer would print complaints of its own
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_sparsh"))
        .args(args)
        .args(["--device", "wgpu", "--devices", "9"])
        .env_remove("XDG_RUNTIME_DIR")
        .env_remove("NODEVICE_SELECT")
        .output()
        .unwrap();
    let err = stderr(&out);
    assert!(
        err.contains("device 9 does not exist") || err.contains("no wgpu adapter"),
        "{err}"
    );
    assert_user_error(&out, "--device");
    assert!(!out_dir.exists());
}
