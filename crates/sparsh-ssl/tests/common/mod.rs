//! Helpers shared by the NumPy reference tests: whether python3 with NumPy is here (required
//! when `SPARSH_REQUIRE_PYTHON` is set), safetensors writing, running the scripts.

#![allow(dead_code)] // each test crate uses its own subset

use std::collections::HashMap;
use std::io::Write;
use std::path::Path;
use std::process::{Command, Stdio};

use safetensors::{Dtype, tensor::TensorView};
use sparsh_ssl::rng::Rng;

/// True when `python3` with numpy runs. Without it the caller skips, saying so, unless the
/// environment variable `SPARSH_REQUIRE_PYTHON` is set, which makes a missing NumPy a failure.
pub fn python_ready(test: &str) -> bool {
    let ok = Command::new("python3")
        .args(["-c", "import numpy"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !ok {
        assert!(
            std::env::var_os("SPARSH_REQUIRE_PYTHON").is_none(),
            "{test}: python3 with numpy not found and SPARSH_REQUIRE_PYTHON is set"
        );
        eprintln!("skipping {test}: python3 with numpy not found (pip install numpy)");
    }
    ok
}

/// A named f32 tensor.
pub type Named = (String, Vec<usize>, Vec<f32>);

/// Writes f32 tensors (and optional metadata) as safetensors.
pub fn write_safetensors(
    path: &Path,
    tensors: &[Named],
    metadata: Option<HashMap<String, String>>,
) {
    let raw: Vec<Vec<u8>> = tensors
        .iter()
        .map(|(_, _, v)| v.iter().flat_map(|x| x.to_le_bytes()).collect())
        .collect();
    let views: Vec<(String, TensorView)> = tensors
        .iter()
        .zip(&raw)
        .map(|((name, shape, _), b)| {
            (
                name.clone(),
                TensorView::new(Dtype::F32, shape.clone(), b).unwrap(),
            )
        })
        .collect();
    std::fs::write(path, safetensors::serialize(views, metadata).unwrap()).unwrap();
}

/// Standard normal samples times `scale` (Box–Muller on the crate's generator).
pub fn normals(rng: &mut Rng, n: usize, scale: f64) -> Vec<f32> {
    (0..n)
        .map(|_| {
            let u = rng.uniform().max(1e-12);
            let v = rng.uniform();
            ((-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos() * scale) as f32
        })
        .collect()
}

/// Runs `tests/SCRIPT` with `args` and `stdin`, returns its JSON output.
pub fn run_script(script: &str, args: &[&str], stdin: &str) -> serde_json::Value {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests")
        .join(script);
    let mut child = Command::new("python3")
        .arg(&path)
        .args(args)
        // numpy_vit.py imports numpy_pos_embed.py: no __pycache__ in the source tree
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    child
        .stdin
        .take()
        .unwrap()
        .write_all(stdin.as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "{script} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// The floats of a JSON array.
pub fn floats(v: &serde_json::Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

/// Largest absolute difference.
pub fn max_abs_diff(a: &[f32], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len(), "lengths differ");
    a.iter()
        .zip(b)
        .fold(0.0f64, |m, (x, y)| m.max((*x as f64 - y).abs()))
}
