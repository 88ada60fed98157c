//! The official TacBench datasets of facebookresearch/sparsh, read in their published layouts so
//! the benchmark runs on the real data.
//!
//! [`load`] takes the path the user gave (a file, one dataset directory, or a directory above
//! several of one kind), finds the layout by the files present ([`detect`]) and maps what each
//! records into [`FrameLabel`](crate::labels::FrameLabel)/
//! [`SequenceLabels`](crate::labels::SequenceLabels):
//!
//! - **Force / slip (T1, T2)**, [`force_slip`] —
//!   `tactile_ssl/data/vision_based_forces_slip_probes.py`,
//!   `tactile_ssl/data/digit/utils.py::load_dataset_forces_digit_gelsight`,
//!   `config/data/{digit,gelsight}_force.yaml`, `config/task/t2_slip_detection.yaml`. A batch
//!   directory (`<indenter>/batch_<k>/`) holds `dataset_<sensor>_NN.pkl` (lists of JPEG byte
//!   strings, concatenated in sorted file order into one frame list) and
//!   `dataset_slip_forces.pkl` = `{"in_contact": [per frame of that list],
//!   "trajectories": {key: {"indexes": [frame-list index], "forces": N×3 (N), "slip_label": N}}}`.
//!   Each trajectory is one sequence (in key order); `force_n` is its force row, `slip_cone` its
//!   `slip_label != 0`, `delta_force_n` the force minus the force 5 samples earlier (clipped to
//!   the first sample, as the official `_get_force_slip_labels`). The background of every frame
//!   of a batch is its first frame with `in_contact == 0` (`remove_bg: true`). `class` is the
//!   batch's `<indenter>/<batch>`; `test` is true for the official test batches `flat/batch_1`
//!   (force), `*/batch_test` (slip) and batches under a `test` directory (`sparsh export`'s
//!   `test/<family>/batch_<seq>`), false for the other batches. A `trajectories` that is itself
//!   `{"indexes", "forces", "slip_label"}` (what earlier `sparsh export` versions wrote) is read
//!   as one trajectory.
//! - **Pose (T3)**, [`pose`] — `tactile_ssl/data/vision_based_pose_probes.py`,
//!   `digit/utils.py::load_dataset_poses`, `config/data/digit_pose.yaml`. Each
//!   `{train,test}/<object>/bag_NN.pkl` is one sequence: the ring finger's frames `digit_ring`
//!   and `object_ring_rel_pose_n5`, per frame the 4×4 transform of the object's pose change over
//!   the last 5 samples (both cut to the shorter, as the official loader does). The official
//!   targets are `tx` = `translation[1]`, `ty` = `translation[0]` and yaw = the z angle of the
//!   rotation's extrinsic `xyz` Euler angles in degrees. The units are not stated anywhere; the
//!   official bins (±0.1…5) only make sense in millimetres, so the translations are taken as mm
//!   unchanged. The labels are changes over a 5-sample window, not absolute poses and not
//!   per-frame changes; `pose_change_se2` receives per-frame changes `[tx, ty, yaw]` whose sum
//!   over every 5 consecutive frames (frames before the first counted as still) equals the
//!   official window label exactly ([`pose::per_frame_from_window`]). The background is
//!   `bgs/digit_ring.png` of an enclosing directory (`path_bgs_fingers`), else the bag's first
//!   frame. `test` comes from the `train`/`test` directory, `class` is the object directory.
//! - **Textile (T5)**, [`textile`] — `tactile_ssl/data/vision_based_textile_probes.py`,
//!   `digit/utils.py::load_textile_dataset`, `config/data/gelsight_textile.yaml`. Each clip
//!   directory `{train,test}/<textile>/<clip>/` with `dataset_gelsight.pkl` (a list of JPEG byte
//!   strings) and `metadata.txt` (`label: <int>` then `class_name: <name>`) is one sequence;
//!   `class` is the class name (20 classes). No background is subtracted (`remove_bg: false`).
//! - **Grasp (T4, Feeling of Success)**, [`grasp`] —
//!   `tactile_ssl/data/vision_based_grasp_probes.py`,
//!   `scripts/download_datasets_scratch/compress_feeling_success.py`,
//!   `config/data/gelsight_grasp.yaml`. Each `NNN.pkl` is a dictionary of lists, one entry per
//!   grasp: `is_gripping` and the JPEG frames `gelsight{A,B}_{before,during,after}`. Each grasp
//!   and sensor is one sequence of 3 frames (before, during, after) with `outcome` =
//!   `is_gripping` and `class` = `object_name` when present; files 000–029 are the official
//!   training set, 030–035 the test set, others unassigned. No background is subtracted.
//!
//! Frames without a background follow the official raw input: they go through
//! [`sparsh_ssl::data::preprocess`] against a uniform grey of 127, which leaves every pixel
//! unchanged. Frames may also be stored as `H×W×3` `uint8` numpy arrays instead of JPEG bytes.
//!
//! Numeric fields may be Python lists or numpy arrays (the official files hold numpy arrays):
//! arrays pickled with protocols 2–5 are decoded from their raw buffer, the element type taken
//! from the pickled dtype when `serde-pickle` keeps it, else from the field's expected kind and
//! the item size (8 bytes read as `f64` for forces and poses, `i64` for indexes; flags are
//! "any byte non-zero", which is right whatever the type). Not supported: big-integer and
//! half-precision fields, structured dtypes, and arrays pickled out of band.

pub mod force_slip;
pub mod grasp;
pub mod pose;
pub mod textile;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use image::RgbImage;
use rayon::prelude::*;
use serde_pickle::{HashableValue, Value};
use sparsh_ssl::data::{Dataset, Frame, preprocess};

use crate::Error;
use crate::labels::LabelledData;

/// Force/slip labels of one batch directory (`dataset_slip_forces.pkl`).
pub const FORCE_LABELS: &str = "dataset_slip_forces.pkl";
/// Frames of one textile clip (`dataset_gelsight.pkl`).
pub const TEXTILE_FRAMES: &str = "dataset_gelsight.pkl";
/// Label of one textile clip (`metadata.txt`).
pub const TEXTILE_METADATA: &str = "metadata.txt";
/// Grey level whose subtraction leaves a frame unchanged (no background).
const NO_BG_GREY: u8 = 127;
/// How deep below the given directory datasets are searched.
const MAX_DEPTH: usize = 6;

/// One official dataset unit found on disk.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub enum Layout {
    /// A force/slip batch directory (holds `dataset_slip_forces.pkl`).
    ForceSlip(PathBuf),
    /// A pose bag (`bag_NN.pkl`).
    Pose(PathBuf),
    /// A textile clip directory (holds `dataset_gelsight.pkl`).
    Textile(PathBuf),
    /// A Feeling of Success grasp file (`NNN.pkl`).
    Grasp(PathBuf),
}

impl Layout {
    fn kind(&self) -> &'static str {
        match self {
            Layout::ForceSlip(_) => "force/slip batches (dataset_slip_forces.pkl)",
            Layout::Pose(_) => "pose bags (bag_NN.pkl)",
            Layout::Textile(_) => "textile clips (dataset_gelsight.pkl)",
            Layout::Grasp(_) => "grasp files (NNN.pkl)",
        }
    }
}

const EXPECTED: &str = "expected an official TacBench layout: a directory with \
    dataset_slip_forces.pkl and dataset_<sensor>_NN.pkl (force/slip), bag_NN.pkl (pose), \
    dataset_gelsight.pkl and metadata.txt (textile) or NNN.pkl (grasp), or a directory above \
    such files";

/// Loads an official TacBench dataset at frame size `size` (`[height, width]`); see the module
/// docs for the layouts and how their labels are mapped.
pub fn load(path: &Path, size: [usize; 2]) -> Result<LabelledData, Error> {
    let found = detect(path)?;
    let mut parts = Vec::with_capacity(found.len());
    for unit in &found {
        match unit {
            Layout::ForceSlip(dir) => parts.extend(force_slip::load_force_batch(dir, size)?),
            Layout::Pose(file) => parts.push(pose::load_pose_bag(file, size)?),
            Layout::Textile(dir) => parts.push(textile::load_textile_clip(dir, size)?),
            Layout::Grasp(file) => parts.extend(grasp::load_grasp_file(file, size)?),
        }
    }
    if parts.is_empty() {
        return Err(Error::file(path, "the dataset holds no sequences"));
    }
    let (sequences, labels): (Vec<_>, Vec<_>) = parts.into_iter().unzip();
    Ok(LabelledData {
        source: path.to_path_buf(),
        dataset: Dataset { sequences, size },
        labels,
    })
}

/// The official dataset units at `path`, sorted; an error naming `path` and the expected files
/// when there are none, or when they are of several kinds.
pub fn detect(path: &Path) -> Result<Vec<Layout>, Error> {
    let mut found = Vec::new();
    if path.is_file() {
        let name = file_name(path);
        let parent = path.parent().unwrap_or(Path::new("."));
        if name == FORCE_LABELS {
            found.push(Layout::ForceSlip(parent.to_path_buf()));
        } else if name == TEXTILE_FRAMES || name == TEXTILE_METADATA {
            found.push(Layout::Textile(parent.to_path_buf()));
        } else if let Some(unit) = classify_file(path) {
            found.push(unit);
        } else if name.ends_with(".pkl") && parent.join(FORCE_LABELS).is_file() {
            // A frame pickle of a force/slip batch.
            found.push(Layout::ForceSlip(parent.to_path_buf()));
        }
    } else if path.is_dir() {
        visit(path, 0, &mut found)?;
    } else {
        return Err(Error::file(path, "no such file or directory"));
    }
    if found.is_empty() {
        return Err(Error::file(path, EXPECTED));
    }
    found.sort();
    let mut kinds: Vec<&str> = found.iter().map(Layout::kind).collect();
    kinds.dedup();
    if kinds.len() > 1 {
        return Err(Error::file(
            path,
            format!(
                "holds several official layouts ({}); give the directory of one task",
                kinds.join(", ")
            ),
        ));
    }
    Ok(found)
}

fn file_name(path: &Path) -> &str {
    path.file_name().and_then(|n| n.to_str()).unwrap_or("")
}

/// A pose bag or grasp file by its name.
fn classify_file(path: &Path) -> Option<Layout> {
    let name = file_name(path);
    let stem = name.strip_suffix(".pkl")?;
    if stem.starts_with("bag_") {
        Some(Layout::Pose(path.to_path_buf()))
    } else if !stem.is_empty() && stem.bytes().all(|b| b.is_ascii_digit()) {
        Some(Layout::Grasp(path.to_path_buf()))
    } else {
        None
    }
}

fn visit(dir: &Path, depth: usize, found: &mut Vec<Layout>) -> Result<(), Error> {
    if dir.join(FORCE_LABELS).is_file() {
        found.push(Layout::ForceSlip(dir.to_path_buf()));
        return Ok(());
    }
    if dir.join(TEXTILE_FRAMES).is_file() {
        found.push(Layout::Textile(dir.to_path_buf()));
        return Ok(());
    }
    let mut entries = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| Error::file(dir, e))? {
        entries.push(entry.map_err(|e| Error::file(dir, e))?.path());
    }
    entries.sort();
    for p in entries {
        if file_name(&p).starts_with('.') {
            continue;
        }
        if p.is_dir() {
            if depth < MAX_DEPTH {
                visit(&p, depth + 1, found)?;
            }
        } else if let Some(unit) = classify_file(&p) {
            found.push(unit);
        }
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Pickles and numpy arrays.

fn one_line(msg: impl std::fmt::Display) -> String {
    msg.to_string().replace(['\n', '\r'], " ")
}

fn read_pickle(path: &Path) -> Result<Value, Error> {
    let bytes = std::fs::read(path).map_err(|e| Error::file(path, e))?;
    serde_pickle::value_from_slice(
        &bytes,
        serde_pickle::DeOptions::new()
            .replace_unresolved_globals()
            .keep_restore_state(),
    )
    .map_err(|e| Error::file(path, format!("not a readable pickle: {}", one_line(e))))
}

fn read_dict(path: &Path) -> Result<BTreeMap<HashableValue, Value>, Error> {
    match read_pickle(path)? {
        Value::Dict(d) => Ok(d),
        other => Err(Error::file(
            path,
            format!("expected a dictionary, found {}", type_name(&other)),
        )),
    }
}

fn type_name(v: &Value) -> &'static str {
    match v {
        Value::None => "None",
        Value::Bool(_) => "a bool",
        Value::I64(_) | Value::Int(_) => "an integer",
        Value::F64(_) => "a float",
        Value::Bytes(_) => "bytes",
        Value::String(_) => "a string",
        Value::List(_) => "a list",
        Value::Tuple(_) => "a tuple",
        Value::Set(_) | Value::FrozenSet(_) => "a set",
        Value::Dict(_) => "a dictionary",
    }
}

/// `d[key]`, the key a string or (Python 2 pickles) bytes.
fn get<'a>(d: &'a BTreeMap<HashableValue, Value>, key: &str) -> Option<&'a Value> {
    d.get(&HashableValue::String(key.into()))
        .or_else(|| d.get(&HashableValue::Bytes(key.as_bytes().to_vec())))
}

fn require<'a>(
    d: &'a BTreeMap<HashableValue, Value>,
    key: &str,
    path: &Path,
    ctx: &str,
) -> Result<&'a Value, Error> {
    get(d, key).ok_or_else(|| {
        let keys: Vec<String> = d.keys().take(12).map(key_name).collect();
        Error::file(
            path,
            format!("{ctx}no `{key}` key (keys: {})", keys.join(", ")),
        )
    })
}

fn key_name(k: &HashableValue) -> String {
    match k {
        HashableValue::String(s) => s.clone(),
        HashableValue::Bytes(b) => String::from_utf8_lossy(b).into_owned(),
        HashableValue::I64(i) => i.to_string(),
        other => format!("{other:?}"),
    }
}

/// What a numeric field holds, for arrays whose dtype the pickle does not keep.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Want {
    Float,
    Int,
    /// Zero or not.
    Flag,
}

/// A numeric array in C order.
#[derive(Debug, Clone, PartialEq)]
struct Nd {
    shape: Vec<usize>,
    data: Vec<f64>,
}

/// What is known of a pickled numpy dtype.
#[derive(Debug, Clone, Copy, Default)]
struct DType {
    kind: Option<u8>,
    size: Option<usize>,
    big_endian: bool,
}

fn dtype_of(v: &Value) -> DType {
    let Value::Tuple(t) = v else {
        return DType::default();
    };
    match t.first() {
        // The `numpy.dtype` constructor arguments: ("f8", False, True).
        Some(Value::String(s)) => {
            let big_endian = s.starts_with('>');
            let s = s.trim_start_matches(['<', '>', '|', '=']);
            if s == "?" {
                return DType {
                    kind: Some(b'b'),
                    size: Some(1),
                    big_endian,
                };
            }
            let kind = s.bytes().next();
            let size = s.get(1..).and_then(|n| n.parse().ok());
            DType {
                kind,
                size,
                big_endian,
            }
        }
        // The dtype state: (3, "<", None, None, None, -1, -1, 0).
        Some(Value::I64(_)) => DType {
            big_endian: matches!(t.get(1), Some(Value::String(o)) if o == ">"),
            ..DType::default()
        },
        _ => DType::default(),
    }
}

fn is_dtype(v: &Value) -> bool {
    match v {
        Value::None => true,
        Value::Tuple(t) => matches!(
            (t.first(), t.get(1)),
            (Some(Value::String(_)), _) | (Some(Value::I64(_)), Some(Value::String(_)))
        ),
        _ => false,
    }
}

/// A pickled numpy array as `serde-pickle` leaves it: `(shape, dtype, fortran, data)`.
struct RawArray<'a> {
    shape: Vec<usize>,
    dtype: DType,
    fortran: bool,
    data: &'a Value,
}

fn shape_of(v: &Value) -> Option<Vec<usize>> {
    match v {
        Value::Tuple(t) | Value::List(t) => t
            .iter()
            .map(|d| match d {
                Value::I64(n) if *n >= 0 => Some(*n as usize),
                _ => None,
            })
            .collect(),
        _ => None,
    }
}

fn as_array(v: &Value) -> Option<RawArray<'_>> {
    let Value::Tuple(t) = v else { return None };
    match t.as_slice() {
        // `ndarray.__setstate__` state (protocols 2–4): (1, shape, dtype, is_fortran, data).
        [
            Value::I64(_),
            shape,
            dtype,
            Value::Bool(fortran),
            data @ (Value::Bytes(_) | Value::List(_)),
        ] if is_dtype(dtype) => Some(RawArray {
            shape: shape_of(shape)?,
            dtype: dtype_of(dtype),
            fortran: *fortran,
            data,
        }),
        // `numpy.core.numeric._frombuffer` arguments (protocol 5): (buffer, dtype, shape, order).
        [data @ Value::Bytes(_), dtype, shape, Value::String(order)] if is_dtype(dtype) => {
            Some(RawArray {
                shape: shape_of(shape)?,
                dtype: dtype_of(dtype),
                fortran: order == "F",
                data,
            })
        }
        // `numpy.core.multiarray.scalar` arguments: (dtype, bytes).
        [dtype, data @ Value::Bytes(_)] if is_dtype(dtype) => Some(RawArray {
            shape: Vec::new(),
            dtype: dtype_of(dtype),
            fortran: false,
            data,
        }),
        _ => None,
    }
}

fn decode_element(b: &[u8], kind: u8, big: bool, want: Want) -> Result<f64, String> {
    if want == Want::Flag {
        return Ok(if b.iter().any(|&x| x != 0) { 1.0 } else { 0.0 });
    }
    let mut le = b.to_vec();
    if big {
        le.reverse();
    }
    let v = match (kind, le.len()) {
        (b'f', 4) => f32::from_le_bytes(le[..].try_into().unwrap_or_default()) as f64,
        (b'f', 8) => f64::from_le_bytes(le[..].try_into().unwrap_or_default()),
        (b'i', 1) => le[0] as i8 as f64,
        (b'i', 2) => i16::from_le_bytes([le[0], le[1]]) as f64,
        (b'i', 4) => i32::from_le_bytes(le[..].try_into().unwrap_or_default()) as f64,
        (b'i', 8) => i64::from_le_bytes(le[..].try_into().unwrap_or_default()) as f64,
        (b'u' | b'b', 1) => le[0] as f64,
        (b'u', 2) => u16::from_le_bytes([le[0], le[1]]) as f64,
        (b'u', 4) => u32::from_le_bytes(le[..].try_into().unwrap_or_default()) as f64,
        (b'u', 8) => u64::from_le_bytes(le[..].try_into().unwrap_or_default()) as f64,
        (k, n) => {
            return Err(format!("unsupported numpy element type `{}{n}`", k as char));
        }
    };
    Ok(v)
}

fn decode_array(a: &RawArray<'_>, want: Want) -> Result<Nd, String> {
    let count = element_count(&a.shape).ok_or("numpy array too large")?;
    let mut data = match a.data {
        Value::List(items) => {
            // An object array: its elements one by one.
            if items.len() != count {
                return Err(format!(
                    "numpy array of shape {:?} holds {} objects",
                    a.shape,
                    items.len()
                ));
            }
            let mut out = Vec::with_capacity(count);
            for item in items {
                let n = to_nd(item, want)?;
                if !n.shape.is_empty() {
                    return Err("numpy object array of arrays".into());
                }
                out.extend(n.data);
            }
            out
        }
        Value::Bytes(raw) => {
            if count == 0 {
                Vec::new()
            } else {
                if raw.len() % count != 0 {
                    return Err(format!(
                        "numpy array of shape {:?} has {} data bytes",
                        a.shape,
                        raw.len()
                    ));
                }
                let size = raw.len() / count;
                if a.dtype.size.is_some_and(|s| s != size) {
                    return Err(format!(
                        "numpy array of shape {:?}: {}-byte elements but a {}-byte dtype",
                        a.shape,
                        size,
                        a.dtype.size.unwrap_or(0)
                    ));
                }
                let kind = match a.dtype.kind {
                    Some(k) => k,
                    None => match (want, size) {
                        (_, 1) => b'u',
                        (Want::Float, _) => b'f',
                        _ => b'i',
                    },
                };
                if want != Want::Flag && !matches!(kind, b'f' | b'i' | b'u' | b'b') {
                    return Err(format!("unsupported numpy dtype kind `{}`", kind as char));
                }
                raw.chunks_exact(size)
                    .map(|c| decode_element(c, kind, a.dtype.big_endian, want))
                    .collect::<Result<Vec<_>, _>>()?
            }
        }
        _ => return Err("numpy array without data".into()),
    };
    if a.fortran && a.shape.len() > 1 {
        data = fortran_to_c(&data, &a.shape);
    }
    Ok(Nd {
        shape: a.shape.clone(),
        data,
    })
}

/// The number of elements of `shape`, `None` on overflow.
fn element_count(shape: &[usize]) -> Option<usize> {
    shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d))
}

fn fortran_to_c(data: &[f64], shape: &[usize]) -> Vec<f64> {
    let n = shape.len();
    let mut stride_f = vec![1usize; n];
    for k in 1..n {
        stride_f[k] = stride_f[k - 1] * shape[k - 1];
    }
    let mut idx = vec![0usize; n];
    let mut out = Vec::with_capacity(data.len());
    for _ in 0..data.len() {
        let src: usize = idx.iter().zip(&stride_f).map(|(i, s)| i * s).sum();
        out.push(data[src]);
        for k in (0..n).rev() {
            idx[k] += 1;
            if idx[k] < shape[k] {
                break;
            }
            idx[k] = 0;
        }
    }
    out
}

/// A number, a (nested) list of numbers or a numpy array/scalar as an [`Nd`].
fn to_nd(v: &Value, want: Want) -> Result<Nd, String> {
    let scalar = |x: f64| {
        Ok(Nd {
            shape: Vec::new(),
            data: vec![x],
        })
    };
    match v {
        Value::Bool(b) => scalar(f64::from(u8::from(*b))),
        Value::I64(i) => scalar(*i as f64),
        Value::F64(f) if want == Want::Flag => scalar(if *f != 0.0 { 1.0 } else { 0.0 }),
        Value::F64(f) => scalar(*f),
        Value::Int(_) => Err("integer too large".into()),
        Value::Tuple(_) if as_array(v).is_some() => {
            decode_array(&as_array(v).expect("checked"), want)
        }
        Value::List(items) | Value::Tuple(items) => {
            let mut inner: Option<Vec<usize>> = None;
            let mut data = Vec::new();
            for (k, item) in items.iter().enumerate() {
                let n = to_nd(item, want).map_err(|e| format!("item {k}: {e}"))?;
                match &inner {
                    None => inner = Some(n.shape),
                    Some(s) if *s != n.shape => {
                        return Err(format!(
                            "item {k}: shape {:?} differs from the first item's {s:?}",
                            n.shape
                        ));
                    }
                    Some(_) => {}
                }
                data.extend(n.data);
            }
            let mut shape = vec![items.len()];
            shape.extend(inner.unwrap_or_default());
            Ok(Nd { shape, data })
        }
        other => Err(format!("expected numbers, found {}", type_name(other))),
    }
}

/// A field as a 1-D array of `n` numbers (`n = None`: any length).
fn field_1d(v: &Value, want: Want, n: Option<usize>) -> Result<Vec<f64>, String> {
    let a = to_nd(v, want)?;
    if a.shape.len() != 1 {
        return Err(format!("expected a 1-D array, found shape {:?}", a.shape));
    }
    if let Some(n) = n
        && a.data.len() != n
    {
        return Err(format!("expected {n} values, found {}", a.data.len()));
    }
    Ok(a.data)
}

/// One stored frame: encoded bytes or a raw `H×W×3` array.
#[derive(Debug, Clone)]
enum Img {
    Encoded(Vec<u8>),
    Raw(RgbImage),
}

impl Img {
    fn decode(&self) -> Result<RgbImage, String> {
        match self {
            Img::Encoded(bytes) => image::load_from_memory(bytes)
                .map(|i| i.to_rgb8())
                .map_err(|e| format!("cannot decode image: {}", one_line(e))),
            Img::Raw(img) => Ok(img.clone()),
        }
    }
}

fn raw_image(shape: &[usize], bytes: &[u8]) -> Option<RgbImage> {
    match shape {
        [h, w, 3] if *h > 0 && *w > 0 && element_count(&[*h, *w, 3]) == Some(bytes.len()) => {
            RgbImage::from_raw(*w as u32, *h as u32, bytes.to_vec())
        }
        _ => None,
    }
}

/// The frames of a field: a list of encoded images (bytes) or of `H×W×3` `uint8` arrays, a
/// numpy object array of those, or one `N×H×W×3` `uint8` array.
fn frames_of(v: &Value) -> Result<Vec<Img>, String> {
    if let Some(a) = as_array(v) {
        return match (a.data, a.shape.as_slice()) {
            (Value::List(items), _) => frames_of(&Value::List(items.clone())),
            (Value::Bytes(raw), [n, h, w, 3])
                if !a.fortran
                    && *n > 0
                    && *h > 0
                    && *w > 0
                    && element_count(&a.shape) == Some(raw.len()) =>
            {
                Ok(raw
                    .chunks_exact(h * w * 3)
                    .filter_map(|c| raw_image(&[*h, *w, 3], c).map(Img::Raw))
                    .collect())
            }
            _ => Err(format!(
                "expected a list of frames, found a numpy array of shape {:?}",
                a.shape
            )),
        };
    }
    let (Value::List(items) | Value::Tuple(items)) = v else {
        return Err(format!("expected a list of frames, found {}", type_name(v)));
    };
    items
        .iter()
        .enumerate()
        .map(|(k, item)| match item {
            Value::Bytes(b) => Ok(Img::Encoded(b.clone())),
            other => as_array(other)
                .and_then(|a| match a.data {
                    Value::Bytes(raw) if !a.fortran => raw_image(&a.shape, raw),
                    _ => None,
                })
                .map(Img::Raw)
                .ok_or_else(|| {
                    format!(
                        "frame {k}: expected encoded image bytes or an H×W×3 uint8 array, \
                         found {}",
                        type_name(other)
                    )
                }),
        })
        .collect()
}

/// Preprocesses `frames` against `bg` (`None`: no background subtraction), in parallel.
fn prepare(
    frames: &[&Img],
    bg: Option<&RgbImage>,
    size: [usize; 2],
    path: &Path,
    what: &str,
) -> Result<Vec<Frame>, Error> {
    frames
        .par_iter()
        .enumerate()
        .map(|(k, img)| {
            let img = img
                .decode()
                .map_err(|e| Error::file(path, format!("{what}frame {k}: {e}")))?;
            let grey;
            let bg = match bg {
                Some(bg) => bg,
                None => {
                    grey = RgbImage::from_pixel(
                        img.width(),
                        img.height(),
                        image::Rgb([NO_BG_GREY; 3]),
                    );
                    &grey
                }
            };
            preprocess(&img, bg, size)
                .map(Arc::new)
                .map_err(|e| Error::file(path, format!("{what}frame {k}: {e}")))
        })
        .collect()
}

/// The split named by the nearest `train`/`test` directory among `path`'s last `levels`
/// components.
fn split_of(path: &Path, levels: usize) -> Option<bool> {
    path.components()
        .rev()
        .take(levels)
        .find_map(|c| match c.as_os_str().to_str() {
            Some("test") => Some(true),
            Some("train") => Some(false),
            _ => None,
        })
}
#[cfg(test)]
mod tests {
    use super::*;
    use serde_pickle::{HashableValue as H, Value as V};

    pub(super) const SIZE: [usize; 2] = [8, 6];
    pub(super) const W: u32 = 12;
    pub(super) const H_: u32 = 16;

    fn image(seed: u8) -> RgbImage {
        RgbImage::from_fn(W, H_, |x, y| {
            image::Rgb([
                seed.wrapping_mul(37).wrapping_add(x as u8 * 9),
                seed.wrapping_mul(11).wrapping_add(y as u8 * 7),
                seed.wrapping_mul(5),
            ])
        })
    }

    fn encode(img: &RgbImage, format: image::ImageFormat) -> Vec<u8> {
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, format).unwrap();
        out.into_inner()
    }

    pub(super) fn jpeg(seed: u8) -> Vec<u8> {
        encode(&image(seed), image::ImageFormat::Jpeg)
    }

    pub(super) fn png_uniform(v: u8) -> Vec<u8> {
        let img = RgbImage::from_pixel(W, H_, image::Rgb([v; 3]));
        encode(&img, image::ImageFormat::Png)
    }

    pub(super) fn s(k: &str) -> H {
        H::String(k.into())
    }

    pub(super) fn write_value(path: &Path, v: &V) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        let mut bytes = Vec::new();
        serde_pickle::value_to_writer(&mut bytes, v, serde_pickle::SerOptions::new()).unwrap();
        std::fs::write(path, bytes).unwrap();
    }

    pub(super) fn frames_list(seeds: &[u8]) -> V {
        V::List(seeds.iter().map(|&k| V::Bytes(jpeg(k))).collect())
    }

    /// A Python object to pickle the way CPython and numpy do (protocol 3), numpy arrays
    /// included, which `serde-pickle` cannot write.
    pub(super) enum P {
        Dict(Vec<(P, P)>),
        List(Vec<P>),
        Str(&'static str),
        Int(i64),
        Float(f64),
        Bool(bool),
        /// A numpy array: dtype string (`f8`, `i8`, `u1`, …), shape, raw little-endian data.
        Nd(&'static str, Vec<usize>, Vec<u8>),
    }

    pub(super) fn f8(shape: &[usize], v: &[f64]) -> P {
        P::Nd(
            "f8",
            shape.to_vec(),
            v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        )
    }

    fn i8a(v: &[i64]) -> P {
        P::Nd(
            "i8",
            vec![v.len()],
            v.iter().flat_map(|x| x.to_le_bytes()).collect(),
        )
    }

    #[derive(Default)]
    pub(super) struct Pickler {
        pub(super) out: Vec<u8>,
        memo: u8,
        dtypes: BTreeMap<&'static str, u8>,
    }

    impl Pickler {
        fn put(&mut self) -> u8 {
            let id = self.memo;
            self.out.extend([b'q', id]);
            self.memo += 1;
            id
        }

        pub(super) fn str(&mut self, s: &str) {
            self.out.push(b'X');
            self.out.extend((s.len() as u32).to_le_bytes());
            self.out.extend(s.as_bytes());
        }

        fn int(&mut self, i: i64) {
            self.out.push(b'J');
            self.out.extend((i as i32).to_le_bytes());
        }

        fn global(&mut self, module: &str, name: &str) {
            self.out.push(b'c');
            self.out.extend(format!("{module}\n{name}\n").as_bytes());
        }

        fn dtype(&mut self, descr: &'static str) {
            if let Some(&id) = self.dtypes.get(descr) {
                // numpy dtypes are singletons: later arrays reference the memo.
                self.out.extend([b'h', id]);
                return;
            }
            self.global("numpy", "dtype");
            self.str(descr);
            self.out.extend([0x89, 0x88, 0x87, b'R']);
            let id = self.put();
            self.dtypes.insert(descr, id);
            self.out.push(b'(');
            self.int(3);
            self.str(if descr.starts_with('u') { "|" } else { "<" });
            self.out.extend([b'N', b'N', b'N']);
            self.int(-1);
            self.int(-1);
            self.int(0);
            self.out.extend([b't', b'b']);
        }

        pub(super) fn obj(&mut self, p: &P) {
            match p {
                P::Dict(items) => {
                    self.out.push(b'}');
                    self.out.push(b'(');
                    for (k, v) in items {
                        self.obj(k);
                        self.obj(v);
                    }
                    self.out.push(b'u');
                }
                P::List(items) => {
                    self.out.push(b']');
                    self.out.push(b'(');
                    for v in items {
                        self.obj(v);
                    }
                    self.out.push(b'e');
                }
                P::Str(s) => self.str(s),
                P::Int(i) => self.int(*i),
                P::Float(f) => {
                    self.out.push(b'G');
                    self.out.extend(f.to_be_bytes());
                }
                P::Bool(b) => self.out.push(if *b { 0x88 } else { 0x89 }),
                P::Nd(descr, shape, raw) => {
                    self.global("numpy.core.multiarray", "_reconstruct");
                    self.global("numpy", "ndarray");
                    self.int(0);
                    self.out.push(0x85);
                    self.out.extend([b'C', 1, b'b']);
                    self.out.extend([0x87, b'R']);
                    self.put();
                    self.out.push(b'(');
                    self.int(1);
                    self.out.push(b'(');
                    for &d in shape {
                        self.int(d as i64);
                    }
                    self.out.push(b't');
                    self.dtype(descr);
                    self.out.push(0x89);
                    self.out.push(b'B');
                    self.out.extend((raw.len() as u32).to_le_bytes());
                    self.out.extend(raw);
                    self.out.extend([b't', b'b']);
                }
            }
        }
    }

    pub(super) fn write_p(path: &Path, p: &P) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        let mut w = Pickler::default();
        w.out.extend([0x80, 3]);
        w.obj(p);
        w.out.push(b'.');
        std::fs::write(path, w.out).unwrap();
    }

    fn message(r: Result<LabelledData, Error>) -> String {
        let e = r.expect_err("expected an error");
        let m = e.to_string();
        assert!(!m.contains('\n'), "not one line: {m}");
        m
    }

    /// A force batch: 6 frames in two pickles, frame 0 without contact; trajectory 0 (numpy)
    /// frames 1..=3, trajectory 1 (lists) frames 0, 4, 5.
    pub(super) fn write_force_batch(dir: &Path) {
        write_value(&dir.join("dataset_digit_00.pkl"), &frames_list(&[0, 1, 2]));
        write_value(&dir.join("dataset_digit_01.pkl"), &frames_list(&[3, 4, 5]));
        let forces0 = [0.1, 0.2, 1.0, 0.3, -0.2, 1.5, 2.0, 0.0, 1.0];
        let labels = P::Dict(vec![
            (
                P::Str("in_contact"),
                P::Nd(
                    "i8",
                    vec![6],
                    [0i64, 1, 1, 1, 1, 1]
                        .iter()
                        .flat_map(|x| x.to_le_bytes())
                        .collect(),
                ),
            ),
            (
                P::Str("trajectories"),
                P::Dict(vec![
                    (
                        P::Int(0),
                        P::Dict(vec![
                            (P::Str("indexes"), i8a(&[1, 2, 3])),
                            (P::Str("forces"), f8(&[3, 3], &forces0)),
                            (P::Str("slip_label"), f8(&[3], &[0.0, 0.0, 1.0])),
                        ]),
                    ),
                    (
                        P::Int(1),
                        P::Dict(vec![
                            (
                                P::Str("indexes"),
                                P::List(vec![P::Int(0), P::Int(4), P::Int(5)]),
                            ),
                            (
                                P::Str("forces"),
                                P::List(vec![
                                    P::List(vec![P::Float(0.0), P::Float(0.0), P::Float(0.0)]),
                                    P::List(vec![P::Float(0.5), P::Float(0.5), P::Float(2.0)]),
                                    P::List(vec![P::Float(1.0), P::Int(1), P::Float(0.5)]),
                                ]),
                            ),
                            (
                                P::Str("slip_label"),
                                P::List(vec![P::Bool(false), P::Bool(false), P::Bool(true)]),
                            ),
                        ]),
                    ),
                ]),
            ),
        ]);
        write_p(&dir.join(FORCE_LABELS), &labels);
    }

    #[test]
    fn missing_label_files() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("flat/batch_1");
        write_value(&dir.join("dataset_digit_00.pkl"), &frames_list(&[0, 1]));
        let m = message(load(tmp.path(), SIZE));
        assert!(m.starts_with(&tmp.path().display().to_string()), "{m}");
        assert!(m.contains(FORCE_LABELS) && m.contains("bag_NN.pkl"), "{m}");

        let clip = tmp.path().join("textile/train/wool/c0");
        write_value(&clip.join(TEXTILE_FRAMES), &frames_list(&[0]));
        let m = message(load(&tmp.path().join("textile"), SIZE));
        assert!(
            m.contains(&clip.join(TEXTILE_METADATA).display().to_string()),
            "{m}"
        );

        let m = message(load(&tmp.path().join("nowhere"), SIZE));
        assert!(m.contains("nowhere") && m.contains("no such file"), "{m}");
    }

    #[test]
    fn label_counts_not_matching_frames() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("b");
        write_value(&dir.join("dataset_digit_00.pkl"), &frames_list(&[0, 1, 2]));
        let labels = |indexes: P, forces: P| {
            P::Dict(vec![
                (
                    P::Str("in_contact"),
                    P::List(vec![P::Int(0), P::Int(1), P::Int(1)]),
                ),
                (
                    P::Str("trajectories"),
                    P::Dict(vec![(
                        P::Int(0),
                        P::Dict(vec![
                            (P::Str("indexes"), indexes),
                            (P::Str("forces"), forces),
                            (P::Str("slip_label"), f8(&[2], &[0.0, 1.0])),
                        ]),
                    )]),
                ),
            ])
        };
        let file = dir.join(FORCE_LABELS).display().to_string();
        // Three force rows for two indexes.
        write_p(
            &dir.join(FORCE_LABELS),
            &labels(i8a(&[1, 2]), f8(&[3, 3], &[0.0; 9])),
        );
        let m = message(load(&dir, SIZE));
        assert!(m.starts_with(&file) && m.contains("forces"), "{m}");
        // An index past the 3 frames.
        write_p(
            &dir.join(FORCE_LABELS),
            &labels(i8a(&[1, 3]), f8(&[2, 3], &[0.0; 6])),
        );
        let m = message(load(&dir, SIZE));
        assert!(m.starts_with(&file) && m.contains("indexes[1]"), "{m}");

        let mut d = BTreeMap::new();
        d.insert(
            s("is_gripping"),
            V::List(vec![V::Bool(true), V::Bool(false)]),
        );
        for sensor in ["gelsightA", "gelsightB"] {
            for stage in ["before", "during", "after"] {
                d.insert(s(&format!("{sensor}_{stage}")), frames_list(&[1]));
            }
        }
        let grasp = tmp.path().join("g/002.pkl");
        write_value(&grasp, &V::Dict(d));
        let m = message(load(&grasp, SIZE));
        assert!(
            m.starts_with(&grasp.display().to_string()) && m.contains("gelsightA_before"),
            "{m}"
        );
    }

    #[test]
    fn wrong_types() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("b");
        write_value(&dir.join("dataset_digit_00.pkl"), &frames_list(&[0, 1, 2]));
        let file = dir.join(FORCE_LABELS);
        let labels = P::Dict(vec![
            (
                P::Str("in_contact"),
                P::List(vec![P::Int(0), P::Int(1), P::Int(1)]),
            ),
            (
                P::Str("trajectories"),
                P::Dict(vec![(
                    P::Int(0),
                    P::Dict(vec![
                        (P::Str("indexes"), P::List(vec![P::Int(1)])),
                        (
                            P::Str("forces"),
                            P::List(vec![P::List(vec![
                                P::Float(0.0),
                                P::Str("x"),
                                P::Float(0.0),
                            ])]),
                        ),
                        (P::Str("slip_label"), P::List(vec![P::Int(0)])),
                    ]),
                )]),
            ),
        ]);
        write_p(&file, &labels);
        let m = message(load(&dir, SIZE));
        assert!(
            m.starts_with(&file.display().to_string()) && m.contains("forces"),
            "{m}"
        );

        write_p(
            &file,
            &P::Dict(vec![
                (P::Str("in_contact"), P::Str("yes")),
                (P::Str("trajectories"), P::Dict(vec![])),
            ]),
        );
        let m = message(load(&dir, SIZE));
        assert!(m.contains("in_contact"), "{m}");

        std::fs::write(&file, b"not a pickle").unwrap();
        let m = message(load(&dir, SIZE));
        assert!(
            m.starts_with(&file.display().to_string()) && m.contains("pickle"),
            "{m}"
        );

        // A frame that is not an image.
        write_value(&dir.join("dataset_digit_00.pkl"), &V::List(vec![V::I64(3)]));
        write_p(&file, &labels);
        let m = message(load(&dir, SIZE));
        assert!(
            m.contains("dataset_digit_00.pkl") && m.contains("frame 0"),
            "{m}"
        );

        let clip = tmp.path().join("t/train/wool/c0");
        write_value(&clip.join(TEXTILE_FRAMES), &frames_list(&[0]));
        std::fs::write(clip.join(TEXTILE_METADATA), "label: wool\n").unwrap();
        let m = message(load(&clip, SIZE));
        assert!(
            m.contains(&clip.join(TEXTILE_METADATA).display().to_string()) && m.contains("integer"),
            "{m}"
        );

        let bag = tmp.path().join("p/bag_01.pkl");
        let mut d = BTreeMap::new();
        d.insert(s("digit_ring"), frames_list(&[0]));
        d.insert(s("object_ring_rel_pose_n5"), V::List(vec![V::F64(1.0)]));
        write_value(&bag, &V::Dict(d));
        let m = message(load(&bag, SIZE));
        assert!(
            m.starts_with(&bag.display().to_string()) && m.contains("4×4"),
            "{m}"
        );
    }

    #[test]
    fn mixed_layouts_are_refused() {
        let tmp = tempfile::tempdir().unwrap();
        write_force_batch(&tmp.path().join("force/flat/batch_1"));
        let clip = tmp.path().join("textile/c0");
        write_value(&clip.join(TEXTILE_FRAMES), &frames_list(&[0]));
        let m = message(load(tmp.path(), SIZE));
        assert!(m.contains("several official layouts"), "{m}");
    }
}
