//! `sparsh fieldprobe train | eval | objective` end to end on a small generated dataset with fields: the
//! decoders, the references, the report files; training reads no field; one-line errors; the
//! same run on wgpu as on the CPU.

use std::path::{Path, PathBuf};
use std::process::Output;

mod common;
use common::{RECIPE, assert_user_error, sparsh, stderr, wgpu_or_skip};

/// DIGIT (markerless) and GelSight 2017 (markers) presses and slides at 160 × 120 with every
/// field at stride 2; held-out cylinders.
const DATA_SCENE: &str = r#"
seed = 9
[output]
fields = ["p", "qx", "qy", "ux", "uy", "uz", "contact", "slip"]
[[family]]
name = "digit_slide"
sequences = 6
frames_per_sequence = 10
solver = "halfspace"
mechanics_stride = 2
mechanics_margin_mm = 3.0
[family.sensor]
preset = "digit"
width_px = 160
height_px = 120
mm_per_px = 0.1064
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
slide_mm = [0.5, 2.0]
[[family]]
name = "gs2017_slide"
sequences = 4
frames_per_sequence = 10
solver = "halfspace"
mechanics_stride = 2
mechanics_margin_mm = 3.0
[family.sensor]
preset = "gelsight2017"
width_px = 160
height_px = 120
mm_per_px = 0.118
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
slide_mm = [0.5, 2.0]
"#;

const CONFIG: &str = r#"
recipe = "recipe.toml"
bootstrap = 50
seen_test_period = 3
[decoder]
channels = 8
[references]
supervised = true
random_draws = 2
[ceiling]
cnn = true
channels = 4
"#;

/// Writes the recipe, weights of its architecture, the config and the dataset into `dir`.
fn setup(dir: &Path) -> PathBuf {
    std::fs::write(dir.join("recipe.toml"), RECIPE).unwrap();
    std::fs::write(dir.join("fields.toml"), CONFIG).unwrap();
    let recipe = sparsh_ssl::recipe::Recipe::parse(RECIPE).unwrap();
    let vit = sparsh_bench::encoders::random_encoder(&recipe, 5).unwrap();
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

fn train(dir: &Path, config: &str, data: &Path, out: &str) -> Output {
    train_on(dir, config, data, out, "cpu")
}

fn train_args(dir: &Path, config: &str, data: &Path, out: &str, device: &str) -> Vec<String> {
    [
        "fieldprobe",
        "train",
        "--config",
        dir.join(config).to_str().unwrap(),
        "--encoder",
        dir.join("weights.safetensors").to_str().unwrap(),
        "--data",
        data.to_str().unwrap(),
        "--out",
        dir.join(out).to_str().unwrap(),
        "--quick",
        "--device",
        device,
    ]
    .map(String::from)
    .to_vec()
}

fn train_on(dir: &Path, config: &str, data: &Path, out: &str, device: &str) -> Output {
    let args = train_args(dir, config, data, out, device);
    sparsh(&args.iter().map(String::as_str).collect::<Vec<_>>())
}

#[test]
fn fieldprobe_trains_without_fields_and_scores_against_them() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let data = setup(dir);

    // the shear objective's check: a row per family, every training pair in contact scored
    let out = sparsh(&[
        "fieldprobe",
        "objective",
        "--config",
        dir.join("fields.toml").to_str().unwrap(),
        "--data",
        data.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let table = String::from_utf8_lossy(&out.stdout).to_string();
    let families: Vec<&str> = table
        .lines()
        .skip(2)
        .map(|l| l.split('|').nth(1).unwrap().trim())
        .collect();
    assert_eq!(families, ["digit_slide", "gs2017_slide"], "{table}");
    for line in table.lines().skip(2) {
        let pairs: usize = line.split('|').nth(2).unwrap().trim().parse().unwrap();
        assert!(pairs > 0, "{line}");
    }

    let out = train(dir, "fields.toml", &data, "run");
    assert!(out.status.success(), "{}", stderr(&out));
    let run = dir.join("run");
    for name in ["self-supervised", "supervised", "random-0"] {
        assert!(
            run.join("decoders").join(format!("{name}.bpk")).is_file(),
            "{name}"
        );
        assert!(
            run.join("decoders")
                .join(format!("{name}.stats.json"))
                .is_file()
        );
    }
    // a second train into the same run is refused
    assert_user_error(
        &train(dir, "fields.toml", &data, "run"),
        "holds a field-probe run",
    );

    let out = sparsh(&[
        "fieldprobe",
        "eval",
        "--run",
        run.to_str().unwrap(),
        "--data",
        data.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let md = String::from_utf8_lossy(&out.stdout);
    // every third training sequence is held out as the in-distribution split, scored apart
    let log = stderr(&out);
    let seen_sequences: usize = log
        .split(" sequences of training shapes")
        .next()
        .and_then(|head| head.rsplit(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no in-distribution count: {log}"));
    assert!(seen_sequences >= 1, "{log}");
    assert!(
        md.contains("Held-out sequences of the training shapes"),
        "{md}"
    );
    for method in [
        "self-supervised",
        "supervised",
        "random-0",
        sparsh_bench::fields::run::CEILING,
        "zero flow",
        "classical",
        "markers",
        sparsh_bench::fields::run::ORACLE,
    ] {
        assert!(
            md.contains(&format!("| {method} |")),
            "no {method} row: {md}"
        );
    }
    // fields.csv: plain CSV, header first, values where they apply and in range
    let mut reader = csv::Reader::from_path(run.join("eval/fields.csv")).unwrap();
    let header: Vec<String> = reader.headers().unwrap().iter().map(String::from).collect();
    assert_eq!(
        header,
        [
            "subset",
            "method",
            "metric",
            "mean",
            "ci_low",
            "ci_high",
            "sequences"
        ]
    );
    let rows: Vec<csv::StringRecord> = reader.records().map(|r| r.unwrap()).collect();
    for r in &rows {
        let v: f64 = r[3].parse().unwrap();
        assert!(v.is_finite(), "{r:?}");
        if r[2].starts_with("pearson") || r[2].starts_with("spearman") {
            assert!((-1.0..=1.0).contains(&v), "{r:?}");
        }
        if &r[2] == "contact_iou" {
            assert!((0.0..=1.0).contains(&v), "{r:?}");
        }
    }
    // the oracle row reads the true fields: correlations 1 and flow errors 0 by construction,
    // through the per-sequence means and the bootstrap
    let oracle = |metric: &str| -> [f64; 3] {
        let row = rows
            .iter()
            .find(|r| {
                &r[0] == "all" && &r[1] == sparsh_bench::fields::run::ORACLE && &r[2] == metric
            })
            .unwrap_or_else(|| panic!("no oracle {metric} row"));
        [3, 4, 5].map(|c| row[c].parse().unwrap())
    };
    for metric in ["pearson_p", "spearman_p"] {
        assert!(
            oracle(metric).iter().all(|v| (v - 1.0).abs() < 1e-6),
            "{metric}"
        );
    }
    for metric in ["epe_contact_px", "epe_all_px"] {
        assert_eq!(oracle(metric), [0.0; 3], "{metric}");
    }
    for metric in ["angular_contact_deg", "angular_all_deg"] {
        assert!(oracle(metric).iter().all(|v| *v < 1e-3), "{metric}");
    }
    assert!(oracle("contact_iou")[0] > 0.5);
    // the in-distribution rows are scored against their own truth too (the oracle's r is 1),
    // and the markers, a held-out-shape reference, have none
    let seen_oracle = rows
        .iter()
        .find(|r| {
            &r[0] == "seen_shapes"
                && &r[1] == sparsh_bench::fields::run::ORACLE
                && &r[2] == "pearson_p"
        })
        .expect("an in-distribution oracle row");
    assert!((seen_oracle[3].parse::<f64>().unwrap() - 1.0).abs() < 1e-6);
    assert!(
        !rows
            .iter()
            .any(|r| &r[0] == "seen_shapes" && &r[1] == "markers")
    );
    // the markers score only the sensor that prints them, and only the flow
    assert!(
        rows.iter()
            .any(|r| &r[0] == "markers" && &r[1] == "markers")
    );
    assert!(!rows.iter().any(|r| &r[0] == "all" && &r[1] == "markers"));
    assert!(
        !rows
            .iter()
            .any(|r| &r[1] == "markers" && r[2].contains("pearson_p"))
    );
    assert!(run.join("eval/fields_examples.png").is_file());

    // --resume keeps the models whose settings did not change: a new loss weight of the
    // contact retrains the supervised decoder and the ceiling only
    let weighted = CONFIG.replace("random_draws = 2", "random_draws = 2\ncontact_weight = 3.0");
    std::fs::write(dir.join("weighted.toml"), weighted).unwrap();
    let before = std::fs::read(run.join("decoders/self-supervised.bpk")).unwrap();
    let mut args = train_args(dir, "weighted.toml", &data, "run", "cpu");
    args.push("--resume".into());
    let out = sparsh(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(out.status.success(), "{}", stderr(&out));
    let log = stderr(&out);
    for name in ["self-supervised", "random-0"] {
        assert!(
            log.contains(&format!("  {name}: kept from the earlier run")),
            "{log}"
        );
    }
    assert!(log.contains("  supervised: step 1/3"), "{log}");
    assert!(log.contains("ceiling CNN: step 3/3"), "{log}");
    assert_eq!(
        std::fs::read(run.join("decoders/self-supervised.bpk")).unwrap(),
        before
    );
    let record = sparsh_bench::fields::run::read_run(&run).unwrap();
    assert_eq!(record.config.references.contact_weight, 3.0);
    assert_eq!(record.decoders.len(), 3);
    assert_eq!(record.ceiling.as_ref().unwrap().best_step, 3);

    // training reads no field: without fields/ the self-supervised decoders still train, the
    // supervised ceiling is a one-line error naming the missing file
    let bare = dir.join("bare");
    copy_dir(&data, &bare, "fields");
    let selfsup = CONFIG
        .replace("supervised = true", "supervised = false")
        .replace("cnn = true", "cnn = false");
    std::fs::write(dir.join("selfsup.toml"), selfsup).unwrap();
    let out = train(dir, "selfsup.toml", &bare, "run_bare");
    assert!(out.status.success(), "{}", stderr(&out));
    assert_user_error(
        &train(dir, "fields.toml", &bare, "run_bare_supervised"),
        "no such field file",
    );
}

/// Copies `from` to `to`, leaving out the entry `skip`.
fn copy_dir(from: &Path, to: &Path, skip: &str) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let (src, name) = (entry.path(), entry.file_name());
        if name == skip {
            continue;
        }
        if src.is_dir() {
            copy_dir(&src, &to.join(&name), skip);
        } else {
            std::fs::copy(&src, to.join(&name)).unwrap();
        }
    }
}

#[test]
fn bad_field_probe_inputs_are_one_line_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    std::fs::write(dir.join("recipe.toml"), RECIPE).unwrap();
    let recipe = sparsh_ssl::recipe::Recipe::parse(RECIPE).unwrap();
    let vit = sparsh_bench::encoders::random_encoder(&recipe, 5).unwrap();
    sparsh_ssl::weights::save_encoder(&vit, &dir.join("weights.safetensors")).unwrap();
    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let cases = [
        ("unknown = 1\n", "unknown field"),
        ("[train]\nsteps = 0\n", "train.steps"),
        ("[decoder]\nchannels = 3\n", "decoder.channels"),
        ("[loss]\nssim = 1.5\n", "loss.ssim"),
        (
            "[references]\ncontact_weight = -1.0\n",
            "references.contact_weight",
        ),
        (
            "[ceiling]\nvalidation_period = 1\n",
            "ceiling.validation_period",
        ),
        ("[ceiling]\nlr = 0.0\n", "ceiling.lr"),
        ("seen_test_period = 1\n", "seen_test_period"),
        ("[train]\nshear_pairs = \"gel\"\n", "unknown variant `gel`"),
    ];
    for (extra, needle) in cases {
        std::fs::write(
            dir.join("bad.toml"),
            format!("recipe = \"recipe.toml\"\n{extra}"),
        )
        .unwrap();
        assert_user_error(&train(dir, "bad.toml", &empty, "r"), needle);
    }
    // a clip recipe (V-JEPA's stacking) cannot feed an image-pair decoder
    let clips = RECIPE.replace("objective = \"mae\"", "objective = \"vjepa\"");
    std::fs::write(dir.join("clips.toml"), clips).unwrap();
    std::fs::write(dir.join("c.toml"), "recipe = \"clips.toml\"\n").unwrap();
    assert_user_error(&train(dir, "c.toml", &empty, "r"), "image pairs");
    // weights of another architecture
    std::fs::write(dir.join("ok.toml"), "recipe = \"recipe.toml\"\n").unwrap();
    let deeper = RECIPE.replace("depth = 2", "depth = 3");
    let other = sparsh_ssl::recipe::Recipe::parse(&deeper).unwrap();
    let vit = sparsh_bench::encoders::random_encoder(&other, 0).unwrap();
    sparsh_ssl::weights::save_encoder(&vit, &dir.join("weights.safetensors")).unwrap();
    assert_user_error(&train(dir, "ok.toml", &empty, "r"), "does not fit");
    // eval of a directory that holds no run
    let out = sparsh(&[
        "fieldprobe",
        "eval",
        "--run",
        empty.to_str().unwrap(),
        "--data",
        empty.to_str().unwrap(),
    ]);
    assert_user_error(&out, "run.json");
    // the objective check on a directory that is no dataset
    let out = sparsh(&[
        "fieldprobe",
        "objective",
        "--config",
        dir.join("ok.toml").to_str().unwrap(),
        "--data",
        empty.to_str().unwrap(),
    ]);
    assert_user_error(&out, "labels.jsonl");
}

/// `fieldprobe train` and `eval` with `--device wgpu` (Mesa's lavapipe here, a software Vulkan
/// driver) give the CPU's run: every decoder's first and last training loss, and every score
/// of the report, differ only by floating-point rounding (the models are drawn on the CPU
/// under the seed and moved).
#[test]
fn fieldprobe_on_wgpu_matches_the_cpu() {
    if !wgpu_or_skip() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let data = setup(dir);
    // the self-supervised decoder and the supervised ceiling (a random draw takes the first's
    // path): lavapipe is some 10× slower than the CPU
    let config = CONFIG.replace("random_draws = 2", "random_draws = 0");
    std::fs::write(dir.join("devices.toml"), config).unwrap();
    let run_on = |device: &str| {
        let t0 = std::time::Instant::now();
        let name = format!("run_{device}");
        let out = train_on(dir, "devices.toml", &data, &name, device);
        assert!(out.status.success(), "{device}: {}", stderr(&out));
        let run = dir.join(&name);
        let out = sparsh(&[
            "fieldprobe",
            "eval",
            "--run",
            run.to_str().unwrap(),
            "--data",
            data.to_str().unwrap(),
            "--device",
            device,
        ]);
        assert!(out.status.success(), "{device}: {}", stderr(&out));
        eprintln!("{device}: {:.1} s", t0.elapsed().as_secs_f64());
        run
    };
    let (cpu, gpu) = (run_on("cpu"), run_on("wgpu"));
    let losses = |run: &Path| -> Vec<(String, f64, f64)> {
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(run.join("run.json")).unwrap()).unwrap();
        v["decoders"]
            .as_array()
            .unwrap()
            .iter()
            .map(|d| {
                let l = d["loss_first_last"].as_array().unwrap();
                (
                    d["name"].as_str().unwrap().to_string(),
                    l[0].as_f64().unwrap(),
                    l[1].as_f64().unwrap(),
                )
            })
            .collect()
    };
    let mut worst_loss = 0f64;
    for (a, b) in losses(&cpu).iter().zip(losses(&gpu)) {
        assert_eq!(a.0, b.0);
        let rel = ((a.1 - b.1).abs() / a.1.abs()).max((a.2 - b.2).abs() / a.2.abs());
        eprintln!(
            "{}: loss {:.6} → {:.6} on the CPU, {:.6} → {:.6} on wgpu ({rel:.1e})",
            a.0, a.1, a.2, b.1, b.2
        );
        worst_loss = worst_loss.max(rel);
    }
    let scores = |run: &Path| -> Vec<(String, f64)> {
        let mut reader = csv::Reader::from_path(run.join("eval/fields.csv")).unwrap();
        reader
            .records()
            .map(|r| {
                let r = r.unwrap();
                (
                    format!("{} {} {}", &r[0], &r[1], &r[2]),
                    r[3].parse().unwrap(),
                )
            })
            .collect()
    };
    let (a, b) = (scores(&cpu), scores(&gpu));
    assert_eq!(a.len(), b.len());
    // each score's difference over its tolerance
    let mut worst_score = (0f64, String::new());
    for ((key, u), (other, v)) in a.iter().zip(&b) {
        assert_eq!(key, other);
        let d = (u - v).abs() / (SCORE_TOL * u.abs().max(1.0));
        assert!(d.is_finite(), "{key}: {u} vs {v}");
        if d > worst_score.0 {
            worst_score = (d, format!("{key}: {u} vs {v}"));
        }
    }
    eprintln!(
        "scores: {} rows, the largest difference {:.2} of its tolerance ({})",
        a.len(),
        worst_score.0,
        worst_score.1
    );
    assert!(worst_loss <= LOSS_TOL, "losses differ by {worst_loss:.1e}");
    assert!(worst_score.0 <= 1.0, "{}", worst_score.1);
}

/// Tolerances of [`fieldprobe_on_wgpu_matches_the_cpu`]: training losses to 1e-4 relative
/// (measured: 1e-6); the report's scores to 5e-3, absolute for those within ±1 (correlations,
/// IoUs), relative for larger ones (angles in degrees, end-point errors in pixels). After three
/// steps the maps are nearly flat, so a correlation near 0 carries rounding further (measured:
/// 8e-4 on a Pearson r of 0.02), and a contact IoU counts thresholded pixels, so rounding that
/// moves a pixel across the threshold moves it by a step (measured: 4e-4 on an IoU of 0.04).
const LOSS_TOL: f64 = 1e-4;
const SCORE_TOL: f64 = 5e-3;

/// A device the build lacks is a one-line error of train and eval alike, before anything is
/// read or written.
#[test]
fn a_device_fieldprobe_cannot_use_is_a_one_line_error() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let empty = dir.join("empty");
    let eval = |device: &[&str]| {
        let mut args = vec![
            "fieldprobe",
            "eval",
            "--run",
            empty.to_str().unwrap(),
            "--data",
            empty.to_str().unwrap(),
        ];
        args.extend_from_slice(device);
        sparsh(&args)
    };
    #[cfg(not(feature = "cuda"))]
    {
        assert_user_error(
            &train_on(dir, "f.toml", &empty, "r", "cuda"),
            "--features cuda",
        );
        assert_user_error(&eval(&["--device", "cuda"]), "--features cuda");
    }
    assert_user_error(&eval(&["--devices", "0,1"]), "one device");
    assert!(!dir.join("r").exists());
}
