//! What the benchmarks share: the PyTorch beside them.

use std::process::Command;

/// The version of PyTorch `python3` imports, or `None` without one (the torch columns are then
/// left out).
pub fn torch_version() -> Option<String> {
    let out = Command::new("python3")
        .args(["-c", "import torch; print(torch.__version__)"])
        .output()
        .ok()?;
    out.status
        .success()
        .then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
}
