//! What the end-to-end tests of learned commands share: running the built `sparsh`, reading its
//! errors, and a small ViT recipe.

use std::process::{Command, Output};

/// A ViT of two blocks on the CPU recipes' input.
pub const RECIPE: &str = r#"
objective = "mae"
seed = 0
[encoder]
size = "tiny"
img_size = [96, 72]
patch_size = 8
depth = 2
[optim]
steps = 10
batch_size = 8
"#;

/// Runs the built `sparsh` with `args`.
pub fn sparsh(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sparsh"))
        .args(args)
        .output()
        .expect("sparsh runs")
}

/// Its standard error.
pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// A user error: non-zero exit, one line on stderr naming what is wrong, no panic.
pub fn assert_user_error(out: &Output, needle: &str) {
    let err = stderr(out);
    assert!(!out.status.success(), "should fail: {err}");
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(err.trim_end().lines().count(), 1, "one line: {err}");
    assert!(err.contains(needle), "expected `{needle}` in: {err}");
}
