//! What the end-to-end tests share: running the built `sparsh`, reading its errors, writing a
//! scene and generating a dataset from it, and a small ViT recipe.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// A ViT of two blocks on the CPU recipes' input.
#[allow(dead_code)] // the learned commands' tests only
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
#[allow(dead_code)] // not every test crate checks errors
pub fn assert_user_error(out: &Output, needle: &str) {
    let err = stderr(out);
    assert!(!out.status.success(), "should fail: {err}");
    assert!(
        !err.contains("panicked") && !err.contains("RUST_BACKTRACE"),
        "{err}"
    );
    assert_eq!(err.trim_end().lines().count(), 1, "one line: {err}");
    assert!(err.contains(needle), "expected `{needle}` in: {err}");
}

/// `args` with device flags the build or the command cannot use (a CUDA device in a build
/// without the feature, several devices for a command that computes on one, an index that is not
/// a number) is refused on one line each time, and `out` is never written.
#[allow(dead_code)] // the learned commands' tests only
pub fn assert_device_refused(args: &[&str], out: &Path) {
    let run = |device: &[&str]| {
        let mut all = args.to_vec();
        all.extend_from_slice(device);
        sparsh(&all)
    };
    #[cfg(not(feature = "cuda"))]
    assert_user_error(&run(&["--device", "cuda"]), "--features cuda");
    assert_user_error(&run(&["--devices", "0,1"]), "one device");
    assert_user_error(&run(&["--devices", "x"]), "not a device index");
    assert!(!out.exists(), "{} was written", out.display());
}

/// Writes `text` as `dir/scene.toml`.
#[allow(dead_code)] // not every test crate writes scenes
pub fn write_scene(dir: &Path, text: &str) -> PathBuf {
    let path = dir.join("scene.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// `sparsh generate SCENE --out OUT EXTRA…`.
#[allow(dead_code)] // not every test crate generates datasets
pub fn generate(scene: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "generate",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    sparsh(&args)
}

/// A 12-frame press-and-slide of a 6 mm sphere on an 80 × 60 DIGIT, geometric rung.
#[allow(dead_code)] // not every test crate uses it
pub const SMALL_SCENE: &str = r#"
seed = 11
solver = "geometric"
[sensor]
preset = "digit"
width_px = 80
height_px = 60
mm_per_px = 0.2
fps = 10.0
[gel]
youngs_modulus_kpa = 300.0
thickness_mm = 3.0
[indenter]
shape = "sphere"
radius_mm = 6.0
[[trajectory]]
time_s = 0.0
position_mm = [-1.0, 0.0, 0.2]
[[trajectory]]
time_s = 0.6
position_mm = [-1.0, 0.0, -0.8]
[[trajectory]]
time_s = 1.2
position_mm = [1.0, 0.0, -0.8]
"#;

/// Six short sequences (two per shard of three) with a pressure field, on a small sensor.
#[allow(dead_code)] // not every test crate uses it
pub const SHARDED_DATASET: &str = r#"
seed = 21
[output]
fields = ["p"]
[[family]]
name = "presses"
sequences = 6
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
[[family.indenters]]
shape = "cylinder"
radius_mm = 1.5
split = "test"
[family.motion]
kind = "press_slide"
depth_mm = [0.3, 0.8]
"#;

/// Whether this machine has a wgpu adapter for `--device wgpu` (Mesa's lavapipe counts). Without
/// one the caller skips, with the reason printed, unless SPARSH_REQUIRE_GPU=1 (CI sets it),
/// where this panics.
#[allow(dead_code)] // the learned commands' tests only
pub fn wgpu_or_skip() -> bool {
    use sparsh_ssl::device::{DeviceKind, Devices};
    match Devices::choose(DeviceKind::Wgpu, &[]) {
        Ok(d) => {
            eprintln!("wgpu device: {}", d.names[0]);
            true
        }
        Err(e) if std::env::var("SPARSH_REQUIRE_GPU").is_ok_and(|v| v == "1") => {
            panic!("SPARSH_REQUIRE_GPU=1 and {e}")
        }
        Err(e) => {
            eprintln!("skipped: {e}");
            false
        }
    }
}

/// Every `*.json` file under `dir`, as paths relative to it, sorted.
#[allow(dead_code)] // the learned commands' tests only
pub fn json_files(dir: &Path) -> Vec<PathBuf> {
    fn walk(root: &Path, dir: &Path, out: &mut Vec<PathBuf>) {
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                walk(root, &path, out);
            } else if path.extension().is_some_and(|e| e == "json") {
                out.push(path.strip_prefix(root).unwrap().to_path_buf());
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort();
    out
}
