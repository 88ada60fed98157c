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
fields = ["uz"]
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
         [baselines]\nrecipe = \"recipe.toml\"\nceiling = true\noracle = true\npixel_size = [32, 24]\nceiling_epochs = 3\n"
    );
    for (kind, data) in tasks {
        s += &format!("[[task]]\nkind = \"{kind}\"\ndata = \"{data}\"\nframe_stride = 2\n");
        if *kind == "slip" {
            // the gels' μ ≤ 1.2 never reach the official cone of 1.6: a lower one gives the
            // slip task both classes
            s += &format!("slip_cone_ratio = {SLIP_CONE_RATIO}\n");
        }
    }
    s
}

/// The slip task's friction-cone ratio in these runs.
const SLIP_CONE_RATIO: f64 = 0.5;

/// Writes the recipe, a weights file of its architecture (seed 5's random draw) and the
/// dataset into `dir`.
fn setup(dir: &Path) -> PathBuf {
    std::fs::write(dir.join("recipe.toml"), RECIPE).unwrap();
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

#[test]
fn tacbench_runs_every_task_and_resumes() {
    let tmp = tempfile::tempdir().unwrap();
    let data = setup(tmp.path());
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
            "ridge",
            "ceiling",
            "floor",
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
    // the constant rows equal the learning-free predictor worked out from labels.jsonl: the
    // recipe stacks frames t − 5 and t, and --quick doubles the frame stride of 2
    let col = |name: &str| header.iter().position(|h| h == name).unwrap();
    let reach = sparsh_ssl::recipe::Recipe::parse(RECIPE)
        .unwrap()
        .frame_offsets()
        .into_iter()
        .max()
        .unwrap();
    for task in ["force", "slip"] {
        for budget in [1.0, 0.1] {
            let metrics = constant_by_hand(&data, task, budget, reach, 4);
            let of: Vec<&csv::StringRecord> = rows
                .iter()
                .filter(|r| &r[0] == task && &r[2] == "constant" && r[3].parse() == Ok(budget))
                .collect();
            assert_eq!(of.len(), metrics.len(), "{task} {budget}: {of:?}");
            for r in of {
                let (hand, counts) = metrics[&r[4]];
                eprintln!(
                    "{task} budget {budget} {}: by hand {hand}, results.csv {}",
                    &r[4], &r[5]
                );
                assert!(
                    (value(r) - hand).abs() <= 1e-9 * hand.abs().max(1.0),
                    "{task} budget {budget} {}: results.csv {} but {hand} by hand",
                    &r[4],
                    &r[5]
                );
                let listed = ["train_sequences", "train_samples", "test_samples"]
                    .map(|c| r[col(c)].parse::<usize>().unwrap());
                assert_eq!(
                    listed, counts,
                    "{task} budget {budget}: sequences and samples"
                );
            }
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
    // --task: only the named tasks run and are reported, each row as in the run of every
    // task; the same run resumed without it adds the rest and reports what that run did
    let by_task_dir = tmp.path().join("run_by_task");
    let by_task = |extra: &[&str]| {
        let mut a = vec![
            "tacbench",
            "--config",
            cfg.to_str().unwrap(),
            "--out",
            by_task_dir.to_str().unwrap(),
            "--quick",
        ];
        a.extend_from_slice(extra);
        sparsh(&a)
    };
    let out = by_task(&["--task", "pose", "--task", "force"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let all = String::from_utf8(csv_before.clone()).unwrap();
    let part = std::fs::read_to_string(by_task_dir.join("results.csv")).unwrap();
    let part_tasks: std::collections::BTreeSet<&str> = part
        .lines()
        .skip(1)
        .map(|l| l.split(',').next().unwrap())
        .collect();
    assert_eq!(
        part_tasks.into_iter().collect::<Vec<_>>(),
        ["force", "pose"]
    );
    for line in part.lines() {
        assert!(
            all.lines().any(|l| l == line),
            "not in the full run: {line}"
        );
    }
    let out = by_task(&["--resume"]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(
        std::fs::read(by_task_dir.join("results.csv")).unwrap(),
        csv_before
    );
    // a task the config does not have
    assert_user_error(&by_task(&["--resume", "--task", "forse"]), "--task forse");
    // other weights under the same name: the recorded units are not theirs
    let recipe = sparsh_ssl::recipe::Recipe::parse(RECIPE).unwrap();
    let other = sparsh_bench::encoders::random_encoder(&recipe, 6).unwrap();
    sparsh_ssl::weights::save_encoder(&other, &tmp.path().join("weights.safetensors")).unwrap();
    assert_user_error(&sparsh(&resumed), "weights file");
}

/// The `constant` rows of the `force` or `slip` task at `budget`, worked out from
/// `data/labels.jsonl` without the library: metric → value, and the training sequences,
/// training samples and test samples. It re-derives
/// - the samples (`tasks::extract`): frames t ≥ `reach` of each sequence, every `stride`-th;
///   slip leaves out frames without contact, and its cone label is ‖F_xy‖ > [`SLIP_CONE_RATIO`]
///   · F_z (the task's `slip_cone_ratio`, applied as the data are loaded in `tacbench::run`);
/// - the splits (`run::TaskRun::new`): the sequences the data mark `test` are held out; of the
///   other sequences with samples, in order, every fifth from the fifth is validation and every
///   fifth from the third is the seen-shape test split (metrics `seen_…`);
/// - the budget (`run::TaskRun::budget_sequences`): m = round(budget · n) of the n training
///   sequences (at least one), the (i n / m)-th for i < m;
/// - the predictor (`report::constant_predictions`): the mean force of the budget's samples,
///   the majority cone label and stick / partial / gross state (a tie to the lower class);
/// - the metrics on the test samples of each split (`tasks::score`): RMSE (mN) over the three
///   axes and per axis; F1 of the slip class (0 without true positives), and balanced accuracies
///   as the mean recall over the classes the test samples hold.
///
/// Each metric comes with the training sequences, training samples and test samples.
fn constant_by_hand(
    data: &Path,
    task: &str,
    budget: f64,
    reach: usize,
    stride: usize,
) -> std::collections::BTreeMap<String, (f64, [usize; 3])> {
    use std::collections::BTreeMap;
    /// One sample: its sequence, whether that is held out, force (N), cone label, and state
    /// (0 stick, 1 partial, 2 gross).
    struct Sample {
        seq: usize,
        test: bool,
        force: [f64; 3],
        cone: bool,
        state: usize,
    }
    let text = std::fs::read_to_string(data.join("labels.jsonl")).unwrap();
    let mut by_seq: BTreeMap<u64, Vec<serde_json::Value>> = BTreeMap::new();
    for line in text.lines().filter(|l| !l.trim().is_empty()) {
        let row: serde_json::Value = serde_json::from_str(line).unwrap();
        by_seq
            .entry(row["sequence"].as_u64().unwrap())
            .or_default()
            .push(row);
    }
    // --quick keeps every sequence of a dataset of at most 20
    assert!(by_seq.len() <= 20, "{} sequences", by_seq.len());
    let mut samples = Vec::new();
    for (s, frames) in by_seq.values_mut().enumerate() {
        frames.sort_by_key(|f| f["frame_in_sequence"].as_u64().unwrap());
        let test = frames[0]["split"] == "test";
        for f in frames.iter().skip(reach).step_by(stride) {
            let force: Vec<f64> = f["force_n"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect();
            let state = match f["slip_state"].as_str().unwrap() {
                "no_contact" if task == "slip" => continue,
                "stick" | "no_contact" => 0,
                "partial" => 1,
                "gross" => 2,
                other => panic!("slip_state {other}"),
            };
            samples.push(Sample {
                seq: s,
                test,
                force: [force[0], force[1], force[2]],
                // `slip_cone_ratio`: the label recomputed as ‖F_xy‖ > ratio · F_z
                cone: force[0].hypot(force[1]) > SLIP_CONE_RATIO * force[2],
                state,
            });
        }
    }
    let mut seqs: Vec<(usize, bool)> = samples.iter().map(|x| (x.seq, x.test)).collect();
    seqs.dedup();
    assert!(
        seqs.iter().any(|x| x.1) && seqs.iter().any(|x| !x.1),
        "both splits"
    );
    let rest: Vec<usize> = seqs.iter().filter(|x| !x.1).map(|x| x.0).collect();
    let train: Vec<usize> = rest
        .iter()
        .enumerate()
        .filter(|(k, _)| k % 5 != 4 && k % 5 != 2)
        .map(|x| *x.1)
        .collect();
    let seen: Vec<usize> = rest.iter().skip(2).step_by(5).copied().collect();
    let n = train.len();
    let m = ((budget * n as f64).round() as usize).clamp(1, n);
    let picked: Vec<usize> = (0..m).map(|i| train[i * n / m]).collect();
    let fit: Vec<&Sample> = samples.iter().filter(|x| picked.contains(&x.seq)).collect();
    let held_out: Vec<&Sample> = samples.iter().filter(|x| x.test).collect();
    let seen: Vec<&Sample> = samples.iter().filter(|x| seen.contains(&x.seq)).collect();
    let mut out = BTreeMap::new();
    for (prefix, test) in [("", held_out), ("seen_", seen)] {
        let mut put = |name: &str, v: f64| {
            out.insert(format!("{prefix}{name}"), (v, [m, fit.len(), test.len()]));
        };
        if task == "force" {
            let mean: Vec<f64> = (0..3)
                .map(|k| fit.iter().map(|x| x.force[k]).sum::<f64>() / fit.len() as f64)
                .collect();
            let se: Vec<f64> = (0..3)
                .map(|k| test.iter().map(|x| (x.force[k] - mean[k]).powi(2)).sum())
                .collect();
            let rmse = |se: f64, axes: usize| 1000.0 * (se / (axes * test.len()) as f64).sqrt();
            put("rmse_mn", rmse(se.iter().sum(), 3));
            for (k, axis) in ["x", "y", "z"].iter().enumerate() {
                put(&format!("rmse_{axis}_mn"), rmse(se[k], 1));
            }
        } else {
            // the majority class of `n` classes among the fitted samples, and the mean recall of
            // the test samples' classes when every one is predicted as it
            let majority = |class: &dyn Fn(&Sample) -> usize, n: usize| {
                let mut counts = vec![0; n];
                fit.iter().for_each(|x| counts[class(x)] += 1);
                let best = (0..n).rev().max_by_key(|&c| counts[c]).unwrap();
                let present: Vec<usize> = (0..n)
                    .filter(|&c| test.iter().any(|x| class(x) == c))
                    .collect();
                let recall = if present.contains(&best) { 1.0 } else { 0.0 };
                (best, recall / present.len() as f64)
            };
            let (cone, balanced) = majority(&|x| usize::from(x.cone), 2);
            let (_, state_balanced) = majority(&|x| x.state, 3);
            let positives = test.iter().filter(|x| x.cone).count() as f64;
            let (tp, fp) = if cone == 1 {
                (positives, test.len() as f64 - positives)
            } else {
                (0.0, 0.0)
            };
            let f1 = if tp > 0.0 {
                2.0 * tp / (2.0 * tp + fp + (positives - tp))
            } else {
                0.0
            };
            put("f1", f1);
            put("balanced_accuracy", balanced);
            put("state_balanced_accuracy", state_balanced);
        }
    }
    out
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
    for name in ["pixels", "ridge-light"] {
        let reserved = config(&[("force", "data")], "[1.0]").replacen(
            "\"weights\"",
            &format!("\"{name}\""),
            1,
        );
        assert_user_error(&run("reserved", &reserved), "encoder[0].name");
    }
    let path = config(&[("force", "data")], "[1.0]").replacen("\"weights\"", "\"../up\"", 1);
    assert_user_error(&run("path", &path), "encoder[0].name");
    let zero = config(&[("force", "data")], "[1.0]").replacen(
        "[baselines]\nrecipe = \"recipe.toml\"\n",
        "[baselines]\nrecipe = \"recipe.toml\"\nend_to_end_epochs = 0\n",
        1,
    );
    assert_user_error(&run("zero_epochs", &zero), "end_to_end_epochs");
    // the pixel read-outs' settings
    for (key, bad) in [
        ("ridge_block", "ridge_block = 0"),
        ("pixel_size", "pixel_size = [8, 8]"),
        ("ceiling_lr", "ceiling_lr = -1.0"),
    ] {
        let text = config(&[("force", "data")], "[1.0]")
            .replacen("pixel_size = [32, 24]\n", "", 1)
            .replacen(
                "[baselines]\nrecipe = \"recipe.toml\"\n",
                &format!("[baselines]\nrecipe = \"recipe.toml\"\n{bad}\n"),
                1,
            );
        assert_user_error(&run(key, &text), &format!("baselines.{key}"));
    }
    // the photometric read-out at a pixel size that is not the contact grid turned
    let photometric = config(&[("force", "data")], "[1.0]").replacen(
        "oracle = true\n",
        "oracle = true\nphotometric = true\n",
        1,
    );
    assert_user_error(&run("photometric", &photometric), "turned to portrait");
    // the floor oracle on data without the indentation field
    let no_uz = tmp.path().join("no_uz");
    let scene = tmp.path().join("no_uz.toml");
    std::fs::write(
        &scene,
        DATA_SCENE.replace("fields = [\"uz\"]", "fields = []"),
    )
    .unwrap();
    let out = sparsh(&[
        "generate",
        scene.to_str().unwrap(),
        "--out",
        no_uz.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_user_error(
        &run("no_uz", &config(&[("force", "no_uz")], "[1.0]")),
        "\"uz\"",
    );
    // light-normalized frames from a dataset that keeps no backgrounds (the official layout)
    let official = tmp.path().join("official");
    let out = sparsh(&[
        "export",
        tmp.path().join("data").to_str().unwrap(),
        "--format",
        "sparsh-pkl",
        "--out",
        official.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let light = config(&[("force", "official")], "[1.0]").replacen(
        "oracle = true\n",
        "light_normalize = true\n",
        1,
    );
    assert_user_error(&run("light", &light), "light_normalize");
    // a task's seeds, and validation on a shape the training split lacks
    let zero_seeds = config(&[("force", "data")], "[1.0]") + "seeds = 0\n";
    assert_user_error(&run("zero_seeds", &zero_seeds), "task[0].seeds");
    let cube = config(&[("force", "data")], "[1.0]") + "validation_shapes = [\"cube\"]\n";
    assert_user_error(&run("cube", &cube), "validation_shapes");
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
/// for every kind of row (pretrained and random encoders, raw patches, end to end, the ridge,
/// the ceiling CNN and the floor oracles): each encoder and head drawn on the CPU under its seed
/// and moved, so the runs differ only by floating-point rounding.
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
    // the random draw, raw patches, end to end, ridge, the ceiling and the two floor oracles
    assert_eq!(units.len(), 7, "7 rows × 1 budget: {units:?}");
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
