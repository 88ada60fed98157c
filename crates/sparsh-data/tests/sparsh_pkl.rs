//! The official Sparsh layouts: our writer against our reader and, when Python is present,
//! against Python's own pickle module (its absence fails the test when `SPARSH_REQUIRE_PYTHON`
//! is set, as in CI).

use image::RgbImage;
use sparsh_data::sparsh_pkl::{
    SlipForces, read_frames_pickle, read_slip_forces, write_frames_pickle, write_slip_forces,
};

fn labels() -> SlipForces {
    SlipForces {
        in_contact: vec![false, true, true],
        indexes: vec![0, 1, 2],
        forces: vec![[0.0, 0.0, 0.0], [0.1, -0.2, 1.5], [0.9, 0.0, 0.5]],
        slip_label: vec![0, 0, 1],
    }
}

fn frames() -> Vec<RgbImage> {
    (0..3)
        .map(|k| {
            RgbImage::from_fn(40, 30, |x, y| {
                image::Rgb([x as u8 * 4, y as u8 * 5, 60 * k])
            })
        })
        .collect()
}

#[test]
fn labels_and_frames_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("dataset_slip_forces.pkl");
    write_slip_forces(&path, &labels()).unwrap();
    assert_eq!(read_slip_forces(&path).unwrap(), labels());
    let path = dir.path().join("dataset_0.pkl");
    write_frames_pickle(&path, &frames()).unwrap();
    let encoded = read_frames_pickle(&path).unwrap();
    assert_eq!(encoded.len(), 3);
    for (jpeg, original) in encoded.iter().zip(frames()) {
        let decoded = image::load_from_memory(jpeg).unwrap().to_rgb8();
        assert_eq!(decoded.dimensions(), original.dimensions());
        let mean_error: f64 = decoded
            .as_raw()
            .iter()
            .zip(original.as_raw())
            .map(|(a, b)| (*a as f64 - *b as f64).abs())
            .sum::<f64>()
            / decoded.as_raw().len() as f64;
        assert!(mean_error < 3.0, "JPEG error {mean_error}");
    }
}

#[test]
fn python_reads_the_pickles() {
    if std::process::Command::new("python3")
        .arg("--version")
        .output()
        .is_err()
    {
        assert!(
            std::env::var_os("SPARSH_REQUIRE_PYTHON").is_none(),
            "SPARSH_REQUIRE_PYTHON is set but python3 is not available"
        );
        eprintln!("python3 not found: skipping the Python cross-check");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let labels_path = dir.path().join("dataset_slip_forces.pkl");
    let frames_path = dir.path().join("dataset_0.pkl");
    write_slip_forces(&labels_path, &labels()).unwrap();
    write_frames_pickle(&frames_path, &frames()).unwrap();
    let script = r#"
import pickle, sys
d = pickle.load(open(sys.argv[1], "rb"))
t = d["trajectories"]
f = pickle.load(open(sys.argv[2], "rb"))
assert all(isinstance(b, bytes) and b[:2] == b"\xff\xd8" for b in f), "JPEG bytes"
print(len(f), d["in_contact"], t["indexes"], t["forces"][1], t["slip_label"])
"#;
    let out = std::process::Command::new("python3")
        .args(["-c", script])
        .arg(&labels_path)
        .arg(&frames_path)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(
        String::from_utf8_lossy(&out.stdout).trim(),
        "3 [False, True, True] [0, 1, 2] [0.1, -0.2, 1.5] [0, 0, 1]"
    );
}

#[test]
fn frames_in_a_dictionary_or_tuple_are_found_and_other_pickles_are_refused() {
    use serde_pickle::{HashableValue, SerOptions, Value};
    let dir = tempfile::tempdir().unwrap();
    let bytes = |k: u8| Value::Bytes(vec![k; 4]);
    let write = |name: &str, v: Value| {
        let path = dir.path().join(name);
        std::fs::write(
            &path,
            serde_pickle::value_to_vec(&v, SerOptions::new()).unwrap(),
        )
        .unwrap();
        path
    };
    // a dictionary: the first non-empty list under the sorted keys
    let dict = Value::Dict(
        [
            (
                HashableValue::String("b_frames".into()),
                Value::List(vec![bytes(1), bytes(2)]),
            ),
            (HashableValue::String("a_empty".into()), Value::List(vec![])),
            (
                HashableValue::String("c_other".into()),
                Value::List(vec![bytes(9)]),
            ),
        ]
        .into_iter()
        .collect(),
    );
    let got = read_frames_pickle(&write("dict.pkl", dict)).unwrap();
    assert_eq!(got, vec![vec![1; 4], vec![2; 4]]);
    let got = read_frames_pickle(&write("tuple.pkl", Value::Tuple(vec![bytes(3)]))).unwrap();
    assert_eq!(got, vec![vec![3; 4]]);
    let err = read_frames_pickle(&write("ints.pkl", Value::List(vec![Value::I64(1)])))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("ints.pkl") && err.contains("encoded frames"),
        "{err}"
    );
}
