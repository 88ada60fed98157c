//! Parity of the encoder's forward pass (burn's graph and the host pass of `sparsh embed`) with an
//! independent NumPy ViT (`tests/numpy_vit.py`) and with the PyTorch module of
//! `scripts/sparsh_torch.py` (when torch imports), weights passed through safetensors under the
//! official key names. Skips, saying so, when
//! `python3` with numpy is unavailable (`pip install numpy`), unless `SPARSH_REQUIRE_PYTHON` is
//! set, when it fails instead.

mod common;

use std::path::Path;

use burn::prelude::*;
use common::{Named, floats, normals, python_ready, run_script, write_safetensors};
use safetensors::SafeTensors;
use sparsh_ssl::embed::Pool;
use sparsh_ssl::host::HostVit;
use sparsh_ssl::rng::Rng;
use sparsh_ssl::vit::VitConfig;
use sparsh_ssl::weights::{load_encoder, save_encoder};

/// Random official-layout weights with the keys and shapes of `template` (its `pos_embed` kept),
/// and a random `input` in a file of its own.
fn randomize(
    template: &Path,
    out: &Path,
    input: &Path,
    input_shape: &[usize],
    seed: u64,
) -> Vec<f32> {
    let bytes = std::fs::read(template).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let mut rng = Rng::new(seed);
    let mut normal = |scale: f64| normals(&mut rng, 1, scale)[0];
    let mut tensors: Vec<Named> = Vec::new();
    for name in st.names() {
        let t = st.tensor(name).unwrap();
        let n: usize = t.shape().iter().product();
        let values: Vec<f32> = if name == "pos_embed" {
            t.data()
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect()
        } else if name.contains("norm") && name.ends_with("weight") {
            (0..n).map(|_| 1.0 + normal(0.2)).collect()
        } else {
            (0..n).map(|_| normal(0.3)).collect()
        };
        tensors.push((name.to_string(), t.shape().to_vec(), values));
    }
    write_safetensors(out, &tensors, None);
    let n: usize = input_shape.iter().product();
    let values: Vec<f32> = (0..n).map(|_| normal(1.0)).collect();
    write_safetensors(
        input,
        &[("input".into(), input_shape.to_vec(), values.clone())],
        None,
    );
    values
}

fn check(cfg: VitConfig, seed: u64) {
    let dir = tempfile::tempdir().unwrap();
    let device = Device::flex();
    let template = dir.path().join("template.safetensors");
    let file = dir.path().join("weights.safetensors");
    let input_file = dir.path().join("input.safetensors");
    save_encoder(&cfg.init(&device), &template).unwrap();
    let [h, w] = cfg.img_size;
    let shape = [2, cfg.num_frames, cfg.in_chans, h, w];
    let input = randomize(&template, &file, &input_file, &shape, seed);

    let vit = load_encoder(cfg.init(&device), &file, None).unwrap();
    let x = Tensor::<1>::from_floats(input.as_slice(), &device).reshape(shape);
    let out = vit.forward(x, None);
    let mut parts = Vec::new();
    if let Some(r) = out.registers {
        parts.push(r);
    }
    parts.push(out.patches);
    let ours = Tensor::cat(parts, 1)
        .into_data()
        .try_to_vec::<f32>()
        .unwrap();

    // save → load → save gives back the same tensors
    let again = dir.path().join("again.safetensors");
    save_encoder(&vit, &again).unwrap();
    let (a, b) = (
        std::fs::read(&file).unwrap(),
        std::fs::read(&again).unwrap(),
    );
    let (sa, sb) = (
        SafeTensors::deserialize(&a).unwrap(),
        SafeTensors::deserialize(&b).unwrap(),
    );
    for name in sb.names() {
        assert_eq!(
            sa.tensor(name).unwrap().data(),
            sb.tensor(name).unwrap().data(),
            "{name}"
        );
    }

    let heads = cfg.num_heads.to_string();
    let reference = run_script(
        "numpy_vit.py",
        &[
            file.to_str().unwrap(),
            input_file.to_str().unwrap(),
            heads.as_str(),
        ],
        "",
    );
    let expect_shape: Vec<usize> = reference["shape"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as usize)
        .collect();
    let r = cfg.num_registers;
    assert_eq!(expect_shape, vec![2, r + cfg.num_patches(), cfg.embed_dim]);
    let refv: Vec<f64> = reference["values"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert_eq!(refv.len(), ours.len());
    let scale = refv.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let err = ours
        .iter()
        .zip(&refv)
        .fold(0.0f64, |m, (a, b)| m.max((*a as f64 - b).abs()));
    eprintln!("max abs difference {err:.3e} (largest value {scale:.3})");
    assert!(err / scale <= 1e-4, "relative error {:.3e}", err / scale);

    // the host pass of `sparsh embed` (patch tokens only) against the same reference
    let host =
        HostVit::new(&vit).embed(&input, [shape[1], shape[2], shape[3], shape[4]], Pool::None);
    let d = cfg.embed_dim;
    let patches = refv
        .chunks((r + cfg.num_patches()) * d)
        .flat_map(|sample| &sample[r * d..]);
    let host_err = host
        .iter()
        .zip(patches)
        .fold(0.0f64, |m, (a, b)| m.max((*a as f64 - b).abs()));
    assert_eq!(host.len(), 2 * cfg.num_patches() * d);
    eprintln!("host pass: max abs difference {host_err:.3e}");
    assert!(
        host_err / scale <= 1e-4,
        "host pass: relative error {:.3e}",
        host_err / scale
    );
    let pos_dev = reference["pos_dev"].as_f64().unwrap();
    assert!(
        pos_dev < 1e-5,
        "position embedding differs from the formula by {pos_dev}"
    );

    // the same weights in PyTorch, in the official layout (scripts/sparsh_torch.py)
    if torch_ready() {
        let torch = run_script(
            "../../../scripts/sparsh_torch.py",
            &[
                file.to_str().unwrap(),
                input_file.to_str().unwrap(),
                "--heads",
                heads.as_str(),
            ],
            "",
        );
        let values = floats(&torch["values"]);
        assert_eq!(torch["shape"], reference["shape"]);
        let torch_err = ours
            .iter()
            .zip(&values)
            .fold(0.0f64, |m, (a, b)| m.max((*a as f64 - b).abs()));
        eprintln!("PyTorch: max abs difference {torch_err:.3e}");
        assert!(
            torch_err / scale <= 1e-4,
            "PyTorch: relative error {:.3e}",
            torch_err / scale
        );
    }
}

/// Whether `python3` imports torch; without it the PyTorch comparison is skipped with a note,
/// unless SPARSH_REQUIRE_TORCH is set, when it fails instead.
fn torch_ready() -> bool {
    let ok = std::process::Command::new("python3")
        .args(["-c", "import torch"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !ok {
        assert!(
            std::env::var_os("SPARSH_REQUIRE_TORCH").is_none(),
            "python3 cannot import torch and SPARSH_REQUIRE_TORCH is set"
        );
        eprintln!("skipping the PyTorch comparison: python3 cannot import torch");
    }
    ok
}

#[test]
fn encoder_matches_numpy_reference() {
    if !python_ready("encoder_matches_numpy_reference") {
        return;
    }
    // image encoder: 6 channels, registers
    check(
        VitConfig::new([16, 12], 4)
            .with_embed_dim(32)
            .with_depth(2)
            .with_num_heads(4)
            .with_num_registers(2),
        1,
    );
    // with layer scale (random gammas, not 1)
    check(
        VitConfig::new([16, 12], 4)
            .with_embed_dim(30)
            .with_depth(2)
            .with_num_heads(3)
            .with_num_registers(1)
            .with_layer_scale(Some(1.0)),
        3,
    );
    // V-JEPA clip encoder: 4 frames of 3 channels, tubelets of 2
    check(
        VitConfig::new([16, 12], 4)
            .with_in_chans(3)
            .with_num_frames(4)
            .with_tubelet_size(2)
            .with_embed_dim(32)
            .with_depth(2)
            .with_num_heads(2),
        2,
    );
}
