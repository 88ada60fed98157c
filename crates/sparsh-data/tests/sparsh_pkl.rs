//! The official Sparsh layouts: the pickle writer against our reader and, when Python is
//! present, against Python's own pickle module and numpy (their absence fails the test when
//! `SPARSH_REQUIRE_PYTHON` is set, as in CI).

use image::RgbImage;
use sparsh_data::sparsh_pkl::{
    NdArray, Py, SlipForces, Trajectory, read_frames_pickle, to_pickle, write_frames_pickle,
    write_slip_forces,
};

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
fn frames_round_trip() {
    let dir = tempfile::tempdir().unwrap();
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

/// Runs a Python script with the given arguments; `None` where Python or numpy is missing and
/// `SPARSH_REQUIRE_PYTHON` is not set.
fn python(script: &str, args: &[&std::path::Path]) -> Option<String> {
    let has_numpy = std::process::Command::new("python3")
        .args(["-c", "import numpy"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !has_numpy {
        assert!(
            std::env::var_os("SPARSH_REQUIRE_PYTHON").is_none(),
            "SPARSH_REQUIRE_PYTHON is set but python3 with numpy is not available"
        );
        eprintln!("python3 with numpy not found: skipping the Python cross-check");
        return None;
    }
    let out = std::process::Command::new("python3")
        .args(["-c", script])
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    Some(String::from_utf8_lossy(&out.stdout).trim().to_string())
}

/// Every kind of value the writer knows, read back by Python's unpickler: numpy arrays come back
/// as arrays of the right dtype and shape, with the warnings of a deprecated module path turned
/// into errors.
#[test]
fn python_and_numpy_read_every_value() {
    let value = Py::Dict(vec![
        (Py::Str("t".into()), Py::Bool(true)),
        (Py::Int(7), Py::Int(-3_000_000_000)),
        (Py::Str("f".into()), Py::Float(-0.1)),
        (
            Py::Str("l".into()),
            Py::List(vec![
                Py::Bytes(vec![0, 255]),
                Py::List(vec![]),
                Py::Dict(vec![]),
            ]),
        ),
        (
            Py::Str("a".into()),
            Py::Array(NdArray::f64(
                vec![2, 3],
                &[0.5, 1.0, -2.0, 3.25, 4.0, 1e-300],
            )),
        ),
        (
            Py::Str("i".into()),
            Py::Array(NdArray::i64(&[1, -2, 1 << 40])),
        ),
        (
            Py::Str("b".into()),
            Py::Array(NdArray::bool(&[true, false])),
        ),
        (Py::Str("e".into()), Py::Array(NdArray::i64(&[]))),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("v.pkl");
    std::fs::write(&path, to_pickle(&value)).unwrap();
    let script = r#"
import pickle, sys, warnings
import numpy as np
warnings.simplefilter("error")
d = pickle.load(open(sys.argv[1], "rb"))
a, i, b, e = d["a"], d["i"], d["b"], d["e"]
assert isinstance(a, np.ndarray) and a.dtype == np.float64 and a.shape == (2, 3), a
assert i.dtype == np.int64 and b.dtype == np.bool_ and e.shape == (0,) and e.dtype == np.int64
print(d["t"], d[7], d["f"], d["l"], a.tolist(), i.tolist(), b.tolist(), (a[1] - a[0]).tolist())
"#;
    let Some(said) = python(script, &[&path]) else {
        return;
    };
    assert_eq!(
        said,
        "True -3000000000 -0.1 [b'\\x00\\xff', [], {}] [[0.5, 1.0, -2.0], [3.25, 4.0, 1e-300]] \
         [1, -2, 1099511627776] [True, False] [2.75, 3.0, 2.0]"
    );
}

/// `dataset_slip_forces.pkl` as the official force/slip loader indexes it: numpy arrays
/// (`np.where(in_contact == 0)`, `forces[i] - forces[j]`, `slip_label[array]`).
#[test]
fn python_indexes_the_slip_forces_as_the_official_loader_does() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("dataset_slip_forces.pkl");
    write_slip_forces(
        &path,
        &SlipForces {
            in_contact: vec![false, true, true, true],
            trajectories: vec![Trajectory {
                indexes: vec![1, 2, 3],
                forces: vec![[0.1, -0.2, 1.5], [0.9, 0.0, 0.5], [0.0, 0.25, 2.0]],
                slip_label: vec![0, 1, 0],
            }],
        },
    )
    .unwrap();
    let script = r#"
import pickle, sys
import numpy as np
d = pickle.load(open(sys.argv[1], "rb"))
t = d["trajectories"][0]
print(np.where(d["in_contact"] == 0)[0][0], t["indexes"][2], (t["forces"][2] - t["forces"][0]).tolist(),
      t["slip_label"][np.clip(np.arange(0, 3), 0, 2)].astype(int).tolist())
"#;
    if let Some(said) = python(script, &[&path]) {
        assert_eq!(said, "0 3 [-0.1, 0.45, 0.5] [0, 1, 0]");
    }
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
