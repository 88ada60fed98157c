//! `sparsh embed` end to end: a tiny generated dataset, a tiny pretrained encoder, features of
//! every frame read back with the npyz and safetensors readers and checked against the library
//! call on frames decoded here.

use std::path::{Path, PathBuf};

use sparsh_ssl::embed::{FrozenEncoder, Pool};
use sparsh_ssl::recipe::Recipe;

mod common;
use common::{
    RECIPE, assert_device_refused, assert_user_error, generate, sparsh, stderr, wgpu_or_skip,
    write_scene,
};

/// Two sequences of eight frames on a small sensor.
const SCENE: &str = r#"
seed = 3
[[family]]
name = "presses"
sequences = 2
frames_per_sequence = 8
solver = "geometric"
[family.sensor]
preset = "digit"
width_px = 80
height_px = 60
mm_per_px = 0.2
[[family.indenters]]
shape = "sphere"
radius_mm = [3.0, 6.0]
[family.motion]
kind = "press_slide"
depth_mm = [0.3, 0.8]
"#;

/// The dataset, the run directory of a tiny encoder pretrained for one step, and the tempdir.
fn fixture() -> (tempfile::TempDir, PathBuf, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let scene = write_scene(tmp.path(), SCENE);
    let ds = tmp.path().join("ds");
    let out = generate(&scene, &ds, &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let recipe = tmp.path().join("recipe.toml");
    std::fs::write(&recipe, format!("{RECIPE}[log]\nprobe_every = 0\n")).unwrap();
    let run = tmp.path().join("run");
    let out = sparsh(&[
        "--quiet",
        "pretrain",
        "--config",
        recipe.to_str().unwrap(),
        "--data",
        ds.to_str().unwrap(),
        "--out",
        run.to_str().unwrap(),
        "--max-steps",
        "1",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    (tmp, ds, run)
}

fn rgb(path: &Path) -> image::RgbImage {
    image::open(path).unwrap().to_rgb8()
}

/// Frame number → (sequence, frame in sequence, background file) from `labels.jsonl`.
fn labels(ds: &Path) -> Vec<(usize, usize, PathBuf)> {
    let text = std::fs::read_to_string(ds.join("labels.jsonl")).unwrap();
    let mut rows: Vec<(usize, usize, usize, PathBuf)> = text
        .lines()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            let bg = v["background"]
                .as_str()
                .map_or(ds.join("background.png"), |b| ds.join(b));
            let n = |k: &str| v[k].as_u64().unwrap() as usize;
            (n("frame"), n("sequence"), n("frame_in_sequence"), bg)
        })
        .collect();
    rows.sort_by_key(|r| r.0);
    rows.into_iter()
        .enumerate()
        .map(|(i, (f, s, t, bg))| {
            assert_eq!(f, i, "frames numbered 0..N");
            (s, t, bg)
        })
        .collect()
}

#[test]
fn features_of_every_frame_match_the_library_call_on_decoded_frames() {
    let (tmp, ds, run) = fixture();
    let weights = run.join("encoder.safetensors");
    let npy = tmp.path().join("pooled.npy");
    // the recipe is found beside the encoder, in the run directory
    let out = sparsh(&[
        "--progress-interval",
        "0",
        "embed",
        "--encoder",
        weights.to_str().unwrap(),
        "--data",
        ds.to_str().unwrap(),
        "--out",
        npy.to_str().unwrap(),
        "--batch-size",
        "5",
    ]);
    let err = stderr(&out);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("embed: 16/16 frames (100 %)"), "{err}");
    assert!(!npy.with_extension("tmp-write").exists());

    let bytes = std::fs::read(&npy).unwrap();
    let array = npyz::NpyFile::new(&bytes[..]).unwrap();
    assert_eq!(array.shape(), [16, 192]);
    let pooled: Vec<f32> = array.into_vec().unwrap();
    assert!(pooled.iter().all(|v| v.is_finite()));

    // every token, as safetensors, with --quiet: no progress
    let st = tmp.path().join("tokens.safetensors");
    let out = sparsh(&[
        "--quiet",
        "embed",
        "--encoder",
        weights.to_str().unwrap(),
        "--config",
        run.join("recipe.toml").to_str().unwrap(),
        "--data",
        ds.to_str().unwrap(),
        "--out",
        st.to_str().unwrap(),
        "--pool",
        "none",
    ]);
    let err = stderr(&out);
    assert!(out.status.success(), "{err}");
    assert!(!err.contains("embed: "), "{err}");
    let bytes = std::fs::read(&st).unwrap();
    let file = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let features = file.tensor("features").unwrap();
    // 96×72 at patch 8: 12 × 9 tokens
    assert_eq!(features.shape(), [16, 108, 192]);
    assert_eq!(features.dtype(), safetensors::Dtype::F32);
    let tokens: Vec<f32> = features
        .data()
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    assert!(tokens.iter().all(|v| v.is_finite()));
    let frame = file.tensor("frame").unwrap();
    let ids: Vec<i64> = frame
        .data()
        .chunks_exact(8)
        .map(|c| i64::from_le_bytes(c.try_into().unwrap()))
        .collect();
    assert_eq!(ids, (0..16).collect::<Vec<i64>>());
    // the mean of the tokens is the pooled feature
    for f in 0..16 {
        for d in 0..192 {
            let mean = (0..108)
                .map(|t| tokens[(f * 108 + t) * 192 + d])
                .sum::<f32>()
                / 108.0;
            assert!((mean - pooled[f * 192 + d]).abs() < 1e-4, "frame {f}");
        }
    }
    // frames carry the encoder's content: not all rows alike
    assert!((0..192).any(|d| (pooled[d] - pooled[7 * 192 + d]).abs() > 1e-3));

    // the library call on frames decoded here: I_t ⊕ I_{t−5}, and before t = 5 the no-contact
    // frame (the background itself)
    let recipe = Recipe::load(&run.join("recipe.toml")).unwrap();
    let encoder = FrozenEncoder::load(&recipe, &weights).unwrap();
    assert_eq!(encoder.frame_offsets(), [0, 5]);
    let rows = labels(&ds);
    let frame_png = |i: usize| ds.join("frames").join(format!("{i:06}.png"));
    for f in [2, 7, 15] {
        let (seq, t, bg_path) = &rows[f];
        let bg = rgb(bg_path);
        let now = rgb(&frame_png(f));
        let before = if *t >= 5 {
            let g = rows
                .iter()
                .position(|(s, u, _)| s == seq && *u == t - 5)
                .unwrap();
            rgb(&frame_png(g))
        } else {
            bg.clone()
        };
        let lib = encoder
            .embed_frames(&[&now, &before], &bg, Pool::Mean)
            .unwrap();
        assert_eq!(lib.len(), 192);
        let row = &pooled[f * 192..(f + 1) * 192];
        let worst = lib
            .iter()
            .zip(row)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(worst < 1e-5, "frame {f}: differs by {worst}");
    }
}

#[test]
fn bad_input_fails_on_one_line_naming_the_file() {
    let (tmp, ds, run) = fixture();
    let weights = run.join("encoder.safetensors");
    let (w, d) = (weights.to_str().unwrap(), ds.to_str().unwrap());
    let out_npy = tmp.path().join("f.npy");
    let o = out_npy.to_str().unwrap();
    let embed = |args: &[&str]| sparsh(&[&["embed"], args].concat());

    let missing = tmp.path().join("none.safetensors");
    let out = embed(&[
        "--encoder",
        missing.to_str().unwrap(),
        "--data",
        d,
        "--out",
        o,
    ]);
    assert_user_error(&out, "none.safetensors");

    // weights of a 2-block encoder read with a 6-block recipe
    let deeper = tmp.path().join("deeper.toml");
    std::fs::write(&deeper, RECIPE.replace("depth = 2", "depth = 6")).unwrap();
    let config = deeper.to_str().unwrap();
    let out = embed(&["--encoder", w, "--config", config, "--data", d, "--out", o]);
    assert_user_error(&out, "encoder.safetensors");
    assert!(
        stderr(&out).contains("missing tensor `blocks.2."),
        "{}",
        stderr(&out)
    );

    let not_data = tmp.path().join("empty");
    std::fs::create_dir(&not_data).unwrap();
    let out = embed(&[
        "--encoder",
        w,
        "--data",
        not_data.to_str().unwrap(),
        "--out",
        o,
    ]);
    assert_user_error(&out, "no labels.jsonl");

    let txt = tmp.path().join("f.txt");
    let out = embed(&["--encoder", w, "--data", d, "--out", txt.to_str().unwrap()]);
    assert_user_error(&out, "unknown output format `.txt`");
    assert!(!txt.exists() && !out_npy.exists());

    // weights outside a run directory need their recipe named
    let alone = tmp.path().join("alone").join("encoder.safetensors");
    std::fs::create_dir(alone.parent().unwrap()).unwrap();
    std::fs::copy(&weights, &alone).unwrap();
    let out = embed(&[
        "--encoder",
        alone.to_str().unwrap(),
        "--data",
        d,
        "--out",
        o,
    ]);
    assert_user_error(&out, "--config");
}

/// The features of a `.npy` file written by `sparsh embed`: its shape and values.
fn read_npy(path: &Path) -> (Vec<u64>, Vec<f32>) {
    let bytes = std::fs::read(path).unwrap();
    let array = npyz::NpyFile::new(&bytes[..]).unwrap();
    (array.shape().to_vec(), array.into_vec().unwrap())
}

/// `--device wgpu` (Mesa's lavapipe here, a software Vulkan driver) writes the CPU's features:
/// the encoder is loaded on the CPU and moved, so every token differs only by floating-point
/// rounding (sums in another order).
#[test]
fn embed_on_wgpu_writes_the_cpu_features() {
    if !wgpu_or_skip() {
        return;
    }
    let (tmp, ds, run) = fixture();
    let weights = run.join("encoder.safetensors");
    let embed_on = |device: &str| {
        let out_file = tmp.path().join(format!("{device}.npy"));
        let t0 = std::time::Instant::now();
        // every token, in batches of 5 (the last one short)
        let out = sparsh(&[
            "--quiet",
            "embed",
            "--encoder",
            weights.to_str().unwrap(),
            "--data",
            ds.to_str().unwrap(),
            "--out",
            out_file.to_str().unwrap(),
            "--pool",
            "none",
            "--batch-size",
            "5",
            "--device",
            device,
        ]);
        assert!(out.status.success(), "{device}: {}", stderr(&out));
        eprintln!("{device}: {:.1} s", t0.elapsed().as_secs_f64());
        read_npy(&out_file)
    };
    let (cpu, gpu) = (embed_on("cpu"), embed_on("wgpu"));
    assert_eq!(cpu.0, [16, 108, 192]);
    assert_eq!(gpu.0, cpu.0);
    assert!(gpu.1.iter().all(|v| v.is_finite()));
    let scale = cpu.1.iter().fold(0f32, |m, v| m.max(v.abs()));
    let diff = cpu
        .1
        .iter()
        .zip(&gpu.1)
        .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    eprintln!(
        "features up to {scale:.3} in magnitude differ by up to {diff:.2e} ({:.2e} relative)",
        diff / scale
    );
    assert!(
        diff <= REL_TOL * scale,
        "features differ by {diff:.2e} (scale {scale:.3})"
    );
}

/// Tolerance of [`embed_on_wgpu_writes_the_cpu_features`], relative to the largest feature:
/// two blocks of a ViT in f32 on two backends round differently in the last bits only.
const REL_TOL: f32 = 1e-4;

/// A device the build or the machine lacks, or several devices, is refused on one line before
/// any file is written.
#[test]
fn a_device_embed_cannot_use_is_a_one_line_error() {
    let tmp = tempfile::tempdir().unwrap();
    let out_npy = tmp.path().join("f.npy");
    let args = [
        "embed",
        "--encoder",
        "missing.safetensors",
        "--data",
        "missing",
        "--out",
        out_npy.to_str().unwrap(),
    ];
    assert_device_refused(&args, &out_npy);
}
