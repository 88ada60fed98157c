//! End-to-end runs of the commands that measure and learn, on the smallest inputs they take:
//! `validate` on two shipped cases, `bench`, `bench-optics`, `pretrain` then `probe` on a tiny
//! generated dataset, and `calibrate` then `sim2real` on Taxim's real GelSight pack. Each checks
//! what it prints or writes against what its inputs imply.
//!
//! The Taxim runs skip, saying so, when `data/taxim/calib` is absent, unless
//! `SPARSH_REQUIRE_TAXIM` is set (CI), which makes that a failure.

use std::path::{Path, PathBuf};
use std::process::Output;

mod common;
use common::{RECIPE, SHARDED_DATASET, SMALL_SCENE, generate, sparsh, stderr, write_scene};

fn checkout(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join(path)
}

fn stdout(out: &Output) -> String {
    assert!(out.status.success(), "{}", stderr(out));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// The cells of the markdown table rows of `text` that start with `| first`, trimmed.
fn table_rows(text: &str) -> Vec<Vec<String>> {
    text.lines()
        .filter(|l| l.starts_with("| ") && !l.starts_with("|---"))
        .skip(1) // the header
        .map(|l| {
            l.trim_matches('|')
                .split('|')
                .map(|c| c.trim().to_string())
                .collect()
        })
        .collect()
}

fn number(cell: &str) -> f64 {
    cell.parse()
        .unwrap_or_else(|_| panic!("not a number: {cell}"))
}

/// `validate` on a directory holding two of the shipped cases: a Hertz sphere and Lubkin's
/// stuck torsion. The JSON rows carry the closed-form values computed here from the cases'
/// parameters, and the solver within each case's tolerance.
#[test]
fn validate_runs_the_cases_of_a_directory() {
    let tmp = tempfile::tempdir().unwrap();
    for case in ["hertz.toml", "torsion_stuck.toml"] {
        std::fs::copy(
            checkout("scenes/validation").join(case),
            tmp.path().join(case),
        )
        .unwrap();
    }
    let dir = tmp.path().to_str().unwrap();
    let report: serde_json::Value =
        serde_json::from_str(&stdout(&sparsh(&["validate", dir, "--json"]))).unwrap();
    let rows = report["rows"].as_array().unwrap();
    let row = |case: &str, quantity: &str| {
        rows.iter()
            .find(|r| r["case"] == case && r["quantity"] == quantity)
            .unwrap_or_else(|| panic!("no {case} {quantity} in {rows:?}"))
    };
    // Hertz: R = 100 mm, δ = 0.01 mm, E = 300 kPa, ν = 0.48: P = (4/3) E* √R δ^(3/2).
    let e_star = 300.0 / (1.0 - 0.48 * 0.48);
    let force = 4.0 / 3.0 * e_star * 10.0 * 0.01f64.powf(1.5) * 1e-3;
    // Torsion: G = E/3 = 100 kPa, a = √(Rδ) = 1 mm, β = 0.005°: M = 16Ga³β/3.
    let moment = 16.0 / 3.0 * 100.0 * 0.005f64.to_radians() * 1e-3;
    for (case, quantity, analytic, tolerance) in [
        ("hertz", "force (N)", force, 0.01),
        ("torsion_stuck", "moment (N·mm)", moment, 0.02),
    ] {
        let r = row(case, quantity);
        let (a, s) = (
            r["analytic"].as_f64().unwrap(),
            r["simulated"].as_f64().unwrap(),
        );
        assert!(
            (a - analytic).abs() < 1e-9 * analytic,
            "{case}: {a} vs {analytic}"
        );
        assert!(
            (s - analytic).abs() < tolerance * analytic,
            "{case}: {s} vs {analytic}"
        );
        assert_eq!(r["tolerance"].as_f64(), Some(tolerance));
    }
    // Hertz's refinement study: three cell sizes, the force error shrinking with each.
    let study = report["convergence"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["case"] == "hertz" && c["quantity"] == "force (N)")
        .expect("a convergence study");
    let errors: Vec<f64> = study["rel_error"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e.as_f64().unwrap().abs())
        .collect();
    assert_eq!(errors.len(), 3);
    assert!(errors[0] > errors[1] && errors[1] > errors[2], "{errors:?}");
    // The table says the same: every graded row ok.
    let table = stdout(&sparsh(&["validate", dir]));
    let graded: Vec<&str> = table
        .lines()
        .take_while(|l| !l.is_empty()) // the case table, before the convergence study
        .filter(|l| l.starts_with("hertz ") || l.starts_with("torsion_stuck "))
        .collect();
    assert_eq!(graded.len(), 4, "{table}");
    assert!(graded.iter().all(|l| l.ends_with("ok")), "{table}");
}

/// `bench` with two rungs and two strides: one row each, in order, every one of the scene's
/// 1.2 s × 10 fps = 12 frames, the ratio column the frames/s over the first row's, and each
/// path's stage times within the wall time per frame: the contact solves run one after the
/// other frame by frame (the gap casts too, beside them), the images one after the other, the
/// writing on one thread.
#[test]
fn bench_times_every_rung_and_stride() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), SMALL_SCENE);
    let out = sparsh(&[
        "bench",
        scene.to_str().unwrap(),
        "--solver",
        "geometric",
        "halfspace",
        "--stride",
        "2",
        "4",
    ]);
    let text = stdout(&out);
    let rows = table_rows(&text);
    let runs: Vec<(&str, &str)> = rows
        .iter()
        .map(|r| (r[0].as_str(), r[1].as_str()))
        .collect();
    assert_eq!(
        runs,
        [
            ("geometric", "2"),
            ("geometric", "4"),
            ("halfspace", "2"),
            ("halfspace", "4")
        ],
        "{text}"
    );
    let first_fps = number(&rows[0][3]);
    for r in &rows {
        assert_eq!(r[2], "12", "{text}");
        let fps = number(&r[3]);
        assert!(fps.is_finite() && fps > 0.0, "{text}");
        // frames/s printed to 0.1, the ratio to 0.01
        let ratio = number(&r[4]);
        let (lo, hi) = (
            (fps - 0.05) / (first_fps + 0.05),
            (fps + 0.05) / (first_fps - 0.05),
        );
        assert!(ratio >= lo - 0.005 && ratio <= hi + 0.005, "{text}");
        let [gap, contact, optics, writing] = [5, 6, 7, 8].map(|c| number(&r[c]));
        let wall_ms = 1e3 / (fps - 0.05);
        assert!(
            [gap, contact, optics, writing].iter().all(|&v| v >= 0.0),
            "{text}"
        );
        // printed to 0.01 ms
        assert!(gap <= wall_ms + 0.005, "{text}");
        assert!(contact <= wall_ms + 0.005, "{text}");
        assert!(optics <= wall_ms + 0.005, "{text}");
        assert!(writing <= wall_ms + 0.005, "{text}");
        assert!(contact > 0.0 && writing > 0.0, "{text}");
    }
    assert_eq!(rows[0][4], "1.00");
}

/// `bench-optics` with one timed frame on one thread: both models, both sizes, with and without
/// shadows; at Taxim's 640 × 480 each row's speed-up is Taxim's time from the footer over the
/// row's time, to the printed rounding, and at 320 × 240 there is none.
#[test]
fn bench_optics_rows_agree_with_taxims_times() {
    let text = stdout(&sparsh(&[
        "bench-optics",
        "--repeats",
        "1",
        "--threads-list",
        "1",
    ]));
    let rows = table_rows(&text);
    assert_eq!(rows.len(), 8, "{text}");
    let footer = text.lines().last().unwrap();
    let taxim: Vec<f64> = footer
        .split(|c: char| !(c.is_ascii_digit() || c == '.'))
        .filter_map(|w| w.parse().ok())
        .filter(|&v: &f64| v > 100.0 && v != 640.0 && v != 480.0)
        .collect();
    let [with_shadows, without] = taxim[..] else {
        panic!("two Taxim times in: {footer}");
    };
    for model in ["photometric", "calibrated"] {
        for size in ["320×240", "640×480"] {
            for shadows in ["no", "yes"] {
                let r = rows
                    .iter()
                    .find(|r| r[0] == model && r[1] == size && r[2] == shadows)
                    .unwrap_or_else(|| panic!("no {model} {size} {shadows} row in {text}"));
                assert_eq!((r[3].as_str(), r[4].as_str()), ("cpu", "1"));
                let ms = number(&r[5]);
                assert!(ms > 0.05, "{text}");
                let taxim_ms = if shadows == "yes" {
                    with_shadows
                } else {
                    without
                };
                if size == "320×240" {
                    assert_eq!(r[6], "–", "{text}");
                    continue;
                }
                let speedup = number(&r[6]);
                let (lo, hi) = (taxim_ms / (ms + 0.05) - 0.05, taxim_ms / (ms - 0.05) + 0.05);
                assert!(
                    speedup >= lo && speedup <= hi,
                    "{model} {size} {shadows}: {text}"
                );
            }
        }
    }
}

/// The safetensors header of `path` (a little-endian u64 length, then that much JSON) and the
/// length of the tensor data after it.
fn safetensors_header(path: &Path) -> (serde_json::Value, usize) {
    let bytes = std::fs::read(path).unwrap();
    let len = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    assert!(
        8 + len <= bytes.len(),
        "header past the end of {}",
        path.display()
    );
    let header = serde_json::from_slice(&bytes[8..8 + len]).unwrap();
    (header, bytes.len() - 8 - len)
}

/// `pretrain --max-steps 2` on a tiny generated dataset writes a log of two steps with finite
/// losses, the encoder's weights (a safetensors file whose tensors fill it exactly, with the
/// recipe's 8-pixel patch embedding) and a checkpoint; `probe` then reads that encoder and
/// reports finite force errors, and a predict-the-mean baseline no larger than the spread of the
/// dataset's force labels allows.
#[test]
fn pretrain_smoke_run_then_probe_its_encoder() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), SHARDED_DATASET);
    let ds = tmp.path().join("ds");
    let out = generate(&scene, &ds, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let recipe = tmp.path().join("recipe.toml");
    std::fs::write(
        &recipe,
        format!("{RECIPE}[log]\nprobe_every = 0\nprobe_epochs = 1\nprobe_max_samples = 40\n"),
    )
    .unwrap();
    let run = tmp.path().join("run");
    let (r, d) = (recipe.to_str().unwrap(), ds.to_str().unwrap());
    let text = stdout(&sparsh(&[
        "--quiet",
        "pretrain",
        "--config",
        r,
        "--data",
        d,
        "--out",
        run.to_str().unwrap(),
        "--max-steps",
        "2",
    ]));
    assert!(text.contains("step 2 of 10 (this run: 2 steps"), "{text}");

    let log = std::fs::read_to_string(run.join("log.csv")).unwrap();
    let mut lines = log.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let steps: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(steps.len(), 2, "{log}");
    for (k, s) in steps.iter().enumerate() {
        assert_eq!(s[col("step")], k.to_string(), "{log}");
        let loss = number(s[col("loss")]);
        assert!(loss.is_finite() && loss > 0.0, "{log}");
        let lr = number(s[col("lr")]);
        assert!(lr.is_finite() && lr >= 0.0, "{log}");
    }

    let weights = run.join("encoder.safetensors");
    let (header, data_len) = safetensors_header(&weights);
    let mut data_end = 0;
    let mut patch_kernels = Vec::new();
    for (name, t) in header.as_object().unwrap() {
        if name == "__metadata__" {
            continue;
        }
        let offsets = t["data_offsets"].as_array().unwrap();
        data_end = data_end.max(offsets[1].as_u64().unwrap() as usize);
        let shape: Vec<u64> = t["shape"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap())
            .collect();
        if shape.len() == 4 {
            patch_kernels.push(shape[2..].to_vec());
        }
    }
    assert_eq!(data_end, data_len, "the tensors fill the file");
    assert_eq!(patch_kernels, [vec![8, 8]], "one 8 × 8 patch embedding");
    assert!(run.join("checkpoint").is_dir());

    let text = stdout(&sparsh(&[
        "--quiet",
        "probe",
        "--config",
        r,
        "--data",
        d,
        "--encoder",
        weights.to_str().unwrap(),
        "--seeds",
        "1",
    ]));
    let rows = table_rows(&text);
    assert_eq!(rows.len(), 2, "seed 0 and the mean: {text}");
    for cell in &rows[0][1..] {
        let rmse = number(cell);
        assert!(rmse.is_finite() && rmse > 0.0, "{text}");
    }
    let baseline = text
        .lines()
        .find_map(|l| l.strip_prefix("force RMSE in mN; predicting the training mean scores "))
        .and_then(|rest| rest.strip_suffix(" mN"))
        .map(number)
        .unwrap_or_else(|| panic!("no baseline in {text}"));
    // Predicting a mean of training labels misses a held-out label by at most the labels' range.
    let labels = std::fs::read_to_string(ds.join("labels.jsonl")).unwrap();
    let forces: Vec<[f64; 3]> = labels
        .lines()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            std::array::from_fn(|k| v["force_n"][k].as_f64().unwrap())
        })
        .collect();
    let widest_mn = (0..3)
        .map(|k| {
            let (lo, hi) = forces
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |m, f| {
                    (m.0.min(f[k]), m.1.max(f[k]))
                });
            1000.0 * (hi - lo)
        })
        .fold(0.0, f64::max);
    assert!(
        baseline > 0.0 && baseline <= widest_mn + 0.05,
        "{baseline} vs {widest_mn}"
    );
}

/// Taxim's GelSight pack, or `None` (with a message) when it is absent and not required.
fn taxim_gelsight_pack() -> Option<PathBuf> {
    let path = match std::env::var_os("SPARSH_TAXIM_CALIB") {
        Some(dir) => PathBuf::from(dir),
        None => checkout("data/taxim/calib"),
    }
    .join("gelsight/dataPack.npz");
    if path.is_file() {
        return Some(path);
    }
    assert!(
        std::env::var_os("SPARSH_REQUIRE_TAXIM").is_none(),
        "{} is missing and SPARSH_REQUIRE_TAXIM is set",
        path.display()
    );
    eprintln!(
        "SKIPPED: {} not found (pip download taxim==1.4.1 --no-deps; unzip its taxim/calib/* \
         into data/, or set SPARSH_TAXIM_CALIB)",
        path.display()
    );
    None
}

/// `calibrate` on the pack's even frames writes a map recording the pitch it was given and a
/// background of the pack's frame size; `sim2real` with it scores the 24 odd frames, every
/// score in range and the crop PSNR above Taxim's own 31.65 dB on that pack, and writes the
/// frames and the real | simulated | difference figure at the pack's size.
#[test]
fn calibrate_then_sim2real_on_taxims_pack() {
    let Some(pack) = taxim_gelsight_pack() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let calib = tmp.path().join("calib");
    let p = pack.to_str().unwrap();
    let out = sparsh(&[
        "calibrate",
        "--pack",
        p,
        "--pixmm",
        "0.0295",
        "--out",
        calib.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("calibrated on 24 frames"),
        "{}",
        stderr(&out)
    );
    let map: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(calib.join("map.json")).unwrap()).unwrap();
    assert_eq!(map["provenance"]["mm_per_px"].as_f64(), Some(0.0295));
    let fitted: Vec<u64> = map["provenance"]["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|k| k.as_u64().unwrap())
        .collect();
    assert_eq!(fitted, (0..24).map(|k| 2 * k).collect::<Vec<u64>>());
    let coef = map["coef"].as_array().unwrap();
    assert!(!coef.is_empty());
    assert!(
        coef.iter()
            .flat_map(|c| c.as_array().unwrap())
            .all(|v| v.as_f64().unwrap().is_finite())
    );
    let background = image::open(calib.join("background.png")).unwrap();
    let (w, h) = (background.width(), background.height());

    let saved = tmp.path().join("frames");
    let figure = tmp.path().join("figure.png");
    let report: serde_json::Value = serde_json::from_str(&stdout(&sparsh(&[
        "sim2real",
        "--pack",
        p,
        "--calib",
        calib.to_str().unwrap(),
        "--json",
        "--save",
        saved.to_str().unwrap(),
        "--figure",
        figure.to_str().unwrap(),
        "--refit",
    ])))
    .unwrap();
    let frames = report["frames"].as_array().unwrap();
    let indices: Vec<u64> = frames
        .iter()
        .map(|f| f["frame"].as_u64().unwrap())
        .collect();
    assert_eq!(indices, (0..24).map(|k| 2 * k + 1).collect::<Vec<u64>>());
    for f in frames {
        for region in ["full", "crop"] {
            let s = &f[region];
            let (psnr, ssim, mae) = (
                s["psnr_db"].as_f64().unwrap(),
                s["ssim"].as_f64().unwrap(),
                s["mae"].as_f64().unwrap(),
            );
            assert!(psnr.is_finite() && psnr > 0.0, "{f}");
            assert!(ssim > 0.0 && ssim <= 1.0, "{f}");
            assert!((0.0..=255.0).contains(&mae), "{f}");
        }
    }
    assert_eq!(report["summary"]["frames"].as_u64(), Some(24));
    let crop = report["summary"]["crop_mean"]["psnr_db"].as_f64().unwrap();
    assert!(crop > 31.65, "crop PSNR {crop}");
    for k in indices {
        let img = image::open(saved.join(format!("{k:03}.png"))).unwrap();
        assert_eq!((img.width(), img.height()), (w, h));
    }
    let fig = image::open(&figure).unwrap();
    assert_eq!((fig.width(), fig.height()), (3 * w, h));
    // --refit: each frame's circle fitted by rendering, from its mark. A fit never ends worse
    // than its start; on frames rendered at its own circles (with noise) it finds them again to
    // a fraction of a pixel; the summary's median distance is the frames' own.
    let refit = &report["refit"];
    let mut distances: Vec<f64> = refit["frames"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| {
            let (start, fitted) = (&f["fit"]["start"], &f["fit"]["fitted"]);
            assert!(
                f["fit"]["rms_fitted"].as_f64() <= f["fit"]["rms_start"].as_f64(),
                "{f}"
            );
            let c = |v: &serde_json::Value, i: usize| v["centre_px"][i].as_f64().unwrap();
            (c(fitted, 0) - c(start, 0)).hypot(c(fitted, 1) - c(start, 1))
        })
        .collect();
    assert_eq!(distances.len(), 24);
    distances.sort_by(f64::total_cmp);
    let median = (distances[11] + distances[12]) / 2.0;
    let summary = &refit["summary"];
    assert!(
        (summary["centre_median_px"].as_f64().unwrap() - median).abs() < 1e-9,
        "{summary}"
    );
    assert!(median < 10.0, "{summary}");
    assert!(
        summary["check_centre_median_px"].as_f64().unwrap() < 0.25,
        "{summary}"
    );

    // Fitted under the layered rung's surface (3 mm gel), the map records it and sim2real
    // renders with it: still above Taxim's own crop PSNR on the held-out frames.
    let layered = tmp.path().join("layered");
    let out = sparsh(&[
        "calibrate",
        "--pack",
        p,
        "--pixmm",
        "0.0295",
        "--mechanics",
        "layered",
        "--gel-thickness-mm",
        "3",
        "--out",
        layered.to_str().unwrap(),
    ]);
    assert!(
        stderr(&out).contains("under layered (3 mm"),
        "{}",
        stderr(&out)
    );
    let map: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(layered.join("map.json")).unwrap()).unwrap();
    assert_eq!(map["provenance"]["mechanics"]["model"], "layered");
    let report: serde_json::Value = serde_json::from_str(&stdout(&sparsh(&[
        "sim2real",
        "--pack",
        p,
        "--calib",
        layered.to_str().unwrap(),
        "--json",
    ])))
    .unwrap();
    let crop = report["summary"]["crop_mean"]["psnr_db"].as_f64().unwrap();
    assert!(crop > 31.65, "layered crop PSNR {crop}");
}

/// FLOPs of one reference training step, enumerated matrix product by matrix product (2·M·N·K
/// each, × 3 for forward and backward) for `tokens` tokens of `patch_values` values per image,
/// width `d`, `blocks` blocks, `batch` images: a count written apart from
/// `sparsh_ssl::bench::ReferenceStep::flops`.
fn enumerated_step_flops(tokens: f64, patch_values: f64, d: f64, blocks: f64, batch: f64) -> f64 {
    let product = |m: f64, n: f64, k: f64| 2.0 * m * n * k;
    let embed = product(tokens, d, patch_values);
    let head = product(tokens, patch_values, d);
    let block = 3.0 * product(tokens, d, d) // q, k, v
        + product(tokens, tokens, d) // q kᵀ, all heads together
        + product(tokens, d, tokens) // attention · v
        + product(tokens, d, d) // output projection
        + product(tokens, 4.0 * d, d) // MLP up
        + product(tokens, d, 4.0 * d); // MLP down
    3.0 * batch * (embed + head + blocks * block)
}

/// `bench-train` on the CPU: the reference step's FLOPs equal an enumeration of its matrix
/// products, every time is positive, and a step compared with itself on the same device is the
/// same bit for bit; on wgpu (lavapipe here) the recipe's step agrees with the CPU's to the
/// tolerances of the device tests. Bad input is refused on one line, with nothing written.
#[test]
fn bench_train_times_steps_and_compares_devices() {
    let tmp = tempfile::tempdir().unwrap();
    let recipe = tmp.path().join("recipe.toml");
    std::fs::write(
        &recipe,
        RECIPE.replace("batch_size = 8", "batch_size = 8\nmicro_batches = 2"),
    )
    .unwrap();
    let recipe = recipe.to_str().unwrap();
    let json = tmp.path().join("bench.json");
    let run = |device: &str| {
        let out = sparsh(&[
            "--quiet",
            "bench-train",
            "--reference",
            "tiny",
            "--input",
            "32x24",
            "--patch",
            "8",
            "--batch",
            "2",
            "--warmup",
            "0",
            "--steps",
            "1",
            "--config",
            recipe,
            "--gemm",
            "64",
            "--parity",
            "--device",
            device,
            "--json",
            json.to_str().unwrap(),
        ]);
        stdout(&out);
        let report: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
        report
    };
    let report = run("cpu");
    let rows = report["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 3, "{report}");
    for row in rows {
        assert!(row["seconds_per_step"].as_f64().unwrap() > 0.0, "{row}");
    }
    let row = |prefix: &str| {
        rows.iter()
            .find(|r| r["what"].as_str().unwrap().starts_with(prefix))
            .unwrap_or_else(|| panic!("no row '{prefix}…': {report}"))
    };
    // tiny: 192 wide, 6 blocks; 32×24 at patch 8 is 4 × 3 = 12 tokens of 6·8·8 values
    let expected = enumerated_step_flops(12.0, 384.0, 192.0, 6.0, 2.0) / 1e9;
    let reference = row("reference");
    assert_eq!(reference["batch"], 2, "{reference}");
    let gflop = reference["gflop_per_step"].as_f64().unwrap();
    assert!(
        (gflop - expected).abs() <= 1e-9 * expected,
        "{gflop} vs {expected}"
    );
    let recipe_row = row(recipe);
    assert_eq!(recipe_row["batch"], 2, "{recipe_row}");
    assert!(
        recipe_row["gflop_per_step"].is_null(),
        "a recipe's FLOPs are not counted"
    );
    // a 64³ product is 2 · 64³ multiply-adds counted as two FLOPs each
    let product = row("f32 matrix product 64×64×64");
    assert_eq!(
        product["gflop_per_step"].as_f64(),
        Some(2.0 * 64f64.powi(3) / 1e9)
    );
    let parity = &report["parity"][0];
    assert_eq!(parity["batch"], 4, "two images per micro-batch: {parity}");
    for key in ["loss_relative", "gradient_relative", "weight_abs"] {
        assert_eq!(
            parity[key].as_f64(),
            Some(0.0),
            "CPU against CPU, {key}: {parity}"
        );
    }
    if common::wgpu_or_skip() {
        let report = run("wgpu");
        let p = &report["parity"][0];
        assert!(p["loss_relative"].as_f64().unwrap() <= 1e-5, "{p}");
        assert!(p["gradient_relative"].as_f64().unwrap() <= 1e-3, "{p}");
        assert!(p["weight_abs"].as_f64().unwrap() <= 2e-5, "{p}");
        assert!(
            p["undetermined_weight_abs"].as_f64().unwrap() <= 2.2e-3,
            "{p}"
        );
    }

    let missing = tmp.path().join("refused.json");
    let refused = |extra: &[&str], needle: &str| {
        let mut args = vec!["bench-train", "--json", missing.to_str().unwrap()];
        args.extend_from_slice(extra);
        common::assert_user_error(&sparsh(&args), needle);
    };
    refused(&[], "nothing to time");
    refused(&["--reference", "huge"], "expected tiny, small or base");
    refused(
        &["--reference", "tiny", "--input", "32"],
        "expected HEIGHTxWIDTH",
    );
    refused(
        &["--reference", "tiny", "--input", "30x24", "--patch", "8"],
        "30",
    );
    refused(&["--reference", "tiny", "--steps", "0"], "--steps");
    refused(&["--config", recipe, "--batch", "3"], "micro-batches");
    common::assert_device_refused(
        &[
            "bench-train",
            "--reference",
            "tiny",
            "--json",
            missing.to_str().unwrap(),
        ],
        &missing,
    );
}

/// `scripts/gpu-check.sh run` at its toy sizes (`GPU_CHECK_QUICK=1`) on this machine's wgpu
/// adapter (lavapipe here), with the binary under test: every stage that has what it needs exits
/// 0, the rendered frame on the GPU equals the CPU's to one level, the four objectives' steps
/// agree with the CPU's to the device tests' tolerances, and the probe ran. Skips without an
/// adapter (unless SPARSH_REQUIRE_GPU=1) or without NumPy and Pillow (unless
/// SPARSH_REQUIRE_PYTHON=1).
#[test]
fn the_gpu_check_runs_end_to_end_at_toy_sizes() {
    if !common::wgpu_or_skip() {
        return;
    }
    let python = std::process::Command::new("python3")
        .args(["-c", "import numpy, PIL"])
        .status()
        .is_ok_and(|s| s.success());
    if !python {
        assert!(
            std::env::var("SPARSH_REQUIRE_PYTHON").is_err(),
            "SPARSH_REQUIRE_PYTHON is set and python3 cannot import numpy and PIL"
        );
        eprintln!("skipped: python3 cannot import numpy and PIL");
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let run = std::process::Command::new("bash")
        .arg(checkout("scripts/gpu-check.sh"))
        .args(["run", out.to_str().unwrap()])
        .env("GPU_CHECK_QUICK", "1")
        .env("GPU_CHECK_SPARSH", env!("CARGO_BIN_EXE_sparsh"))
        .env("GPU_CHECK_WORK", tmp.path().join("work"))
        // the suite's other tests share the cores: time limits with room to spare
        .env("GPU_CHECK_SECONDS", "3000")
        .env("GPU_CHECK_STAGE_FACTOR", "5")
        .output()
        .expect("bash runs");
    assert!(run.status.success(), "{}", stderr(&run));
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("gpu-check.json")).unwrap())
            .unwrap();
    for stage in report["stages"].as_array().unwrap() {
        let name = stage["stage"].as_str().unwrap();
        // nvidia-smi and PyTorch are the GPU machine's; elsewhere they may be missing
        if name == "nvidia_smi" || name.starts_with("torch") {
            continue;
        }
        assert_eq!(stage["exit"], "0", "{stage}");
    }
    let render = &report["render_parity"];
    assert!(
        render["max_abs_levels"].as_f64().unwrap() <= 1.0,
        "{render}"
    );
    let parity = report["step_parity"]["parity"].as_array().unwrap();
    assert_eq!(parity.len(), 4, "the four objectives");
    for p in parity {
        assert!(p["loss_relative"].as_f64().unwrap() <= 1e-5, "{p}");
        assert!(p["weight_abs"].as_f64().unwrap() <= 2e-5, "{p}");
    }
    let probe = report["probe"].as_str().unwrap();
    assert!(probe.contains("random inits"), "{probe}");
    assert!(out.join("gpu-check.md").is_file() && out.join("gpu-check.log").is_file());
}
