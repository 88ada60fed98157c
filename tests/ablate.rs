//! `sparsh ablate` end to end with quick settings on Taxim's GelSight pack: every row of the
//! table (references, CNN, probes on a pretrained and a random encoder, the real ceiling, the
//! marks' noise), the report files, `--resume`, and one-line errors for bad ablation files.
//!
//! Skips with a message when the pack is absent, unless `SPARSH_REQUIRE_TAXIM` is set (CI).

use std::path::{Path, PathBuf};

mod common;
use common::{RECIPE, assert_device_refused, assert_user_error, sparsh, stderr};

fn checkout() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn pack() -> Option<PathBuf> {
    let dir = match std::env::var_os("SPARSH_TAXIM_CALIB") {
        Some(dir) => PathBuf::from(dir),
        None => checkout().join("data/taxim/calib"),
    };
    let path = dir.join("gelsight/dataPack.npz");
    if path.is_file() {
        return Some(path);
    }
    assert!(
        std::env::var_os("SPARSH_REQUIRE_TAXIM").is_none(),
        "{} is missing and SPARSH_REQUIRE_TAXIM is set",
        path.display()
    );
    eprintln!(
        "SKIPPED: {} not found (pip download taxim==1.4.1 --no-deps; see README)",
        path.display()
    );
    None
}

/// The ablation file: the shipped GelSight scene and pack, a base variant with the probes and a
/// photometric one.
fn config(dir: &Path, pack: &Path, extra: &str) -> PathBuf {
    std::fs::write(dir.join("recipe.toml"), RECIPE).unwrap();
    let recipe = sparsh_ssl::recipe::Recipe::parse(RECIPE).unwrap();
    let vit = sparsh_bench::encoders::random_encoder(&recipe, 5).unwrap();
    sparsh_ssl::weights::save_encoder(&vit, &dir.join("weights.safetensors")).unwrap();
    let text = format!(
        r#"scene = "{scene}"
pack = "{pack}"
pack_mm_per_px = 0.0295
seeds = 3
bootstrap = 200
[cnn]
epochs = 3
batch_size = 16
lr = 2e-3
[probe]
recipe = "recipe.toml"
weights = "weights.safetensors"
train = {{ epochs = 3, batch_size = 16, lr = 1e-3 }}
[real]
folds = 4
train = {{ epochs = 3, batch_size = 16, lr = 2e-3 }}
marks_calibration = "{calib}"
[[variant]]
name = "base"
probe = true
[[variant]]
name = "photometric optics"
set = {{ "optics.model" = "photometric" }}
remove = ["optics.calibration"]
{extra}"#,
        scene = checkout().join("scenes/sim2real_gelsight.toml").display(),
        pack = pack.display(),
        calib = checkout().join("assets/calib/gelsight").display(),
    );
    let path = dir.join("ablation.toml");
    std::fs::write(&path, text).unwrap();
    path
}

fn rows(out: &Path) -> Vec<csv::StringRecord> {
    let mut r = csv::Reader::from_path(out.join("ablation.csv")).unwrap();
    r.records().map(|x| x.unwrap()).collect()
}

#[test]
fn ablate_trains_on_synthetic_frames_scores_real_ones_and_resumes() {
    let Some(pack) = pack() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let cfg = config(tmp.path(), &pack, "");
    let out = tmp.path().join("run");
    let (c, o) = (cfg.to_str().unwrap(), out.to_str().unwrap());
    let run = sparsh(&["ablate", "--config", c, "--out", o, "--quick"]);
    assert!(run.status.success(), "{}", stderr(&run));
    let table = rows(&out);
    let names: Vec<(String, String)> = table
        .iter()
        .map(|r| (r[0].to_string(), r[1].to_string()))
        .collect();
    let expect = [
        ("base", "constant"),
        ("base", "classical"),
        ("base", "cnn"),
        ("base", "probe (pretrained)"),
        ("base", "probe (random)"),
        ("photometric optics", "cnn"),
        ("real frames", "constant"),
        ("real frames", "cnn"),
        ("real frames", "calibrated optics fit"),
    ];
    assert_eq!(
        names,
        expect.map(|(a, b)| (a.to_string(), b.to_string())).to_vec()
    );
    for r in &table {
        let v = |k: usize| -> f64 { r[k].parse().unwrap() };
        // medians inside their intervals, shares in [0, 1], 90th percentiles above medians
        assert!(v(7) <= v(6) + 1e-9 && v(6) <= v(8) + 1e-9, "{r:?}");
        assert!(v(13) <= v(12) + 1e-9 && v(12) <= v(14) + 1e-9, "{r:?}");
        assert!(v(9) >= v(6) && v(15) >= v(12), "{r:?}");
        assert!(
            (0.0..=1.0).contains(&v(16)) && v(17) >= v(16) && v(17) <= 1.0,
            "{r:?}"
        );
        // quick: one seed for every learned row
        assert_eq!(&r[4], "1", "{r:?}");
    }
    // the constant circle misses the 24 odd frames' centres, spread over most of the frame,
    // by tens of pixels
    assert!(table[0][6].parse::<f64>().unwrap() > 30.0, "{:?}", table[0]);
    // the circles the calibrated optics fit to the frames sit within a few pixels of the marks
    // (the marks' noise; the constant of the unscored real frames misses by tens of pixels)
    let (noise, real_constant) = (&table[8], &table[6]);
    let centre = |r: &csv::StringRecord| r[6].parse::<f64>().unwrap();
    assert!(
        centre(noise) < 10.0 && centre(noise) < centre(real_constant) / 5.0,
        "{noise:?}"
    );
    assert!(
        stderr(&run).contains("label noise: fitted circles against the marks"),
        "{}",
        stderr(&run)
    );
    // every row of ablation.csv is its recorded predictions scored against the pack's marks
    // (pooled seeds and frames: median centre error, median radius error in %, the share within
    // 3 px and 5 %), recomputed here
    let marks = sparsh_optics::CalibrationPack::read(&pack).unwrap();
    let mut checked = 0;
    for (file, variant) in [
        ("variants/base/predictions.csv", "base"),
        (
            "variants/photometric_optics/predictions.csv",
            "photometric optics",
        ),
        ("real/predictions.csv", "real frames"),
        ("real/marks_predictions.csv", "real frames"),
    ] {
        let mut errors: std::collections::BTreeMap<String, Vec<(f64, f64)>> = Default::default();
        for r in csv::Reader::from_path(out.join(file)).unwrap().records() {
            let r = r.unwrap();
            let k: usize = r[2].parse().unwrap();
            assert_eq!(k % 2, 1, "{r:?}: only odd frames are scored");
            let v = |i: usize| -> f64 { r[i].parse().unwrap() };
            let [mx, my] = marks.centers_px[k];
            let mr = marks.radii_px[k];
            errors
                .entry(r[0].to_string())
                .or_default()
                .push(((v(3) - mx).hypot(v(4) - my), 100.0 * (v(5) - mr).abs() / mr));
        }
        for (model, errs) in errors {
            let median = |mut v: Vec<f64>| {
                v.sort_by(f64::total_cmp);
                let n = v.len();
                (v[(n - 1) / 2] + v[n / 2]) / 2.0
            };
            let within =
                errs.iter().filter(|e| e.0 <= 3.0 && e.1 <= 5.0).count() as f64 / errs.len() as f64;
            let row = table
                .iter()
                .find(|r| &r[0] == variant && r[1] == model)
                .unwrap_or_else(|| panic!("{file}: {model} has no row"));
            let csv = |i: usize| -> f64 { row[i].parse().unwrap() };
            assert_eq!(errs.len(), 24 * csv(4) as usize, "{row:?}");
            assert!(
                (median(errs.iter().map(|e| e.0).collect()) - csv(6)).abs() < 1e-4,
                "{row:?}"
            );
            assert!(
                (median(errs.iter().map(|e| e.1).collect()) - csv(12)).abs() < 1e-4,
                "{row:?}"
            );
            assert!((within - csv(16)).abs() < 1e-4, "{row:?}");
            checked += 1;
        }
    }
    // constant, classical, cnn, two probes; cnn; ceiling; the marks' fit
    assert_eq!(checked, 8);
    for f in [
        "ablation.md",
        "ablation.png",
        "ablation.svg",
        "ablation.toml",
    ] {
        assert!(out.join(f).is_file(), "{f}");
    }
    // datasets are removed once scored; the scenes stay
    assert!(out.join("variants/base/scene.toml").is_file());
    assert!(!out.join("variants/base/data").exists());
    // a second run without --resume refuses; with it, every variant is kept as recorded
    assert_user_error(
        &sparsh(&["ablate", "--config", c, "--out", o, "--quick"]),
        "--resume",
    );
    let before = std::fs::read(out.join("ablation.csv")).unwrap();
    let again = sparsh(&["ablate", "--config", c, "--out", o, "--quick", "--resume"]);
    assert!(again.status.success(), "{}", stderr(&again));
    assert!(stderr(&again).contains("recorded, kept"));
    assert_eq!(before, std::fs::read(out.join("ablation.csv")).unwrap());
}

#[test]
fn bad_ablation_files_get_one_line_errors() {
    let Some(pack) = pack() else { return };
    let tmp = tempfile::tempdir().unwrap();
    // an ablation file with `extra` appended (and `from` replaced by `to`), and its output folder
    let edited = |extra: &str, replace: Option<(&str, &str)>| {
        let dir = tempfile::tempdir_in(tmp.path()).unwrap().keep();
        let cfg = config(&dir, &pack, extra);
        if let Some((from, to)) = replace {
            let text = std::fs::read_to_string(&cfg).unwrap().replace(from, to);
            std::fs::write(&cfg, text).unwrap();
        }
        (cfg, dir.join("run"))
    };
    let ablate = |(cfg, out): &(PathBuf, PathBuf), quick: bool| {
        let (c, o) = (cfg.to_str().unwrap(), out.to_str().unwrap());
        let mut args = vec!["ablate", "--config", c, "--out", o];
        if quick {
            args.push("--quick");
        }
        sparsh(&args)
    };
    for (extra, needle) in [
        ("colour = 1\n", "colour"),
        (
            "[[variant]]\nname = \"no such key\"\nremove = [\"gel.hardness\"]\n",
            "gel.hardness",
        ),
        ("[[variant]]\nname = \"Base\"\n", "variant[2].name"),
    ] {
        assert_user_error(&ablate(&edited(extra, None), true), needle);
    }
    // a calibration that is not there is refused before anything runs
    let missing = edited(
        "",
        Some((
            "marks_calibration = \"",
            "marks_calibration = \"/no/such/calibration",
        )),
    );
    assert_user_error(&ablate(&missing, true), "real.marks_calibration");
    assert!(!missing.1.join("ablation.toml").exists());
    let no_weights = edited(
        "",
        Some((
            "weights = \"weights.safetensors\"",
            "weights = \"missing.safetensors\"",
        )),
    );
    let refused = ablate(&no_weights, false);
    assert_user_error(&refused, "probe.weights");
    // the hint is a command that runs as given (pretrain needs its data)
    assert_user_error(&refused, "--data DATASET --out RUN");
    // nothing that a re-run would have to --resume
    assert!(
        !no_weights.1.join("ablation.toml").exists(),
        "a refused config left its record behind"
    );
}

/// A device the build lacks, or several devices, is refused on one line before the ablation
/// file is read or anything is written.
#[test]
fn a_device_ablate_cannot_use_is_a_one_line_error() {
    let tmp = tempfile::tempdir().unwrap();
    let out_dir = tmp.path().join("run");
    let out = out_dir.to_str().unwrap();
    assert_device_refused(
        &["ablate", "--config", "missing.toml", "--out", out],
        &out_dir,
    );
}
