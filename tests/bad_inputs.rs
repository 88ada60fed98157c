//! The corpus of bad inputs in tests/bad_inputs (see its README.md): every file there is refused
//! with exactly the one line its `.expected` file holds. Scene files (and the meshes and
//! backgrounds they name) go through the `sparsh` binary, run in the corpus folder so paths in
//! errors are relative to it; EXR fields, frame pickles and safetensors encoders, which no
//! command reads on its own, go through their library readers.

use std::path::Path;
use std::process::Command;

#[path = "common/encoder.rs"]
mod encoder;

/// `sparsh render NAME`, in `dir`: its error line, or what is wrong with how it failed.
fn render_error(dir: &Path, name: &str, out: &Path) -> String {
    let run = Command::new(env!("CARGO_BIN_EXE_sparsh"))
        .current_dir(dir)
        .args(["render", name, "--png"])
        .arg(out)
        .output()
        .expect("sparsh runs");
    let stderr = String::from_utf8_lossy(&run.stderr).into_owned();
    if run.status.success() {
        return format!("(accepted; stderr: {stderr})");
    }
    if run.status.code() != Some(1) || stderr.trim_end().lines().count() != 1 {
        return format!("(exit {:?}, not one line: {stderr})", run.status.code());
    }
    match stderr.trim_end().strip_prefix("error: ") {
        Some(line) => line.to_string(),
        None => format!("(no `error: ` prefix: {stderr})"),
    }
}

/// The library reader's error for `dir/name`, with `dir/` taken off the paths in it.
fn library_error(dir: &Path, name: &str) -> String {
    let path = dir.join(name);
    let result = match path.extension().and_then(|e| e.to_str()) {
        Some("exr") => sparsh_data::read_exr_channels(&path)
            .map(|_| ())
            .map_err(|e| e.to_string()),
        Some("pkl") => sparsh_ssl::data::load_pickle(&path, [32, 24])
            .map(|_| ())
            .map_err(|e| e.to_string()),
        Some("safetensors") => {
            sparsh_ssl::weights::load_encoder(encoder::tiny_encoder(), &path, None)
                .map(|_| ())
                .map_err(|e| e.to_string())
        }
        _ => panic!("{name}: no reader for this extension"),
    };
    match result {
        Ok(()) => "(accepted)".into(),
        Err(e) => e.replace(&format!("{}/", dir.display()), ""),
    }
}

#[test]
fn every_bad_input_gives_its_error_line() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/bad_inputs");
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("frame.png");
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_file())
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .filter(|n| !n.ends_with(".expected") && n != "README.md")
        .collect();
    names.sort();
    let mut failures = Vec::new();
    let mut expected_files = 0;
    for name in &names {
        let stem = Path::new(name).file_stem().unwrap().to_string_lossy();
        let expected_path = dir.join(format!("{stem}.expected"));
        let Ok(expected) = std::fs::read_to_string(&expected_path) else {
            failures.push(format!("{name}: no {stem}.expected"));
            continue;
        };
        expected_files += 1;
        let got = if name.ends_with(".toml") {
            render_error(&dir, name, &out)
        } else {
            library_error(&dir, name)
        };
        if got != expected.trim_end() {
            failures.push(format!(
                "{name}\n  expected: {}\n  got:      {got}",
                expected.trim_end()
            ));
        }
    }
    let all_expected = std::fs::read_dir(&dir)
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .path()
                .extension()
                .is_some_and(|x| x == "expected")
        })
        .count();
    assert_eq!(
        all_expected, expected_files,
        "an .expected file without its input"
    );
    assert!(!out.exists(), "a bad input rendered a frame");
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
