//! The official Sparsh repository's on-disk layouts (facebookresearch/sparsh), written so that
//! its own loaders read them unchanged.
//!
//! `export` turns a dataset written by `sparsh generate` into
//! ```text
//! OUT/force_slip/<sensor>/<split>/<family>/batch_<seq>/dataset_<sensor>_00.pkl
//!         the sequence's background, then its frames: a list of JPEG byte strings
//! OUT/force_slip/<sensor>/<split>/<family>/batch_<seq>/dataset_slip_forces.pkl
//!         {"in_contact": array, "trajectories": {0: {"indexes", "forces", "slip_label"}}}
//! OUT/ssl/<sensor>/<family>_<seq>/dataset_0.pkl     the sequence's frames (JPEG byte strings)
//! OUT/ssl/<sensor>/bgs/bg_<family>_<seq>.jpg         its background
//! OUT/ssl/<sensor>/bgs/bg_gs.jpg                     the background, where every sequence shares one
//! OUT/sparsh_force_slip_<sensor>.yaml, OUT/sparsh_ssl.yaml   Hydra data configs naming all of it
//! ```
//! What the official code does with each file (`tactile_ssl/data/digit/utils.py`,
//! `vision_based_forces_slip_probes.py`, `vision_tactile.py`, `train.py`, `train_task.py`):
//! - the force/slip loader globs a batch folder for `dataset_{sensor}*` (frames concatenated in
//!   sorted file order) and reads `dataset_slip_forces.pkl`; `trajectories[t]["indexes"]` index
//!   that frame list, `forces` (N×3, N) and `slip_label` are numpy arrays (it subtracts rows and
//!   indexes with arrays), and the background is the frame at `np.where(in_contact == 0)[0][0]`
//!   — here the sequence's own no-contact image, frame 0 of the list, which no trajectory uses;
//! - the SSL loader reads `<path_dataset>/<object>/dataset_<id>.pkl` and, for DIGIT, the
//!   background `bg_<DIGIT_BGS_OBJECTS[object]>.jpg` from a hard-coded table (the one-line patch
//!   the book gives makes it fall back to `bg_<object>.jpg`); for GelSight Mini, `bg_gs.jpg`.
//!
//! Every sequence is its own batch and its own SSL object because generated sequences draw
//! their own LED intensities, so each has its own background.

use std::collections::BTreeMap;
use std::io::Cursor;
use std::path::Path;

use image::RgbImage;
use serde_pickle::{HashableValue, Value};

use crate::{DataError, Identity, Label, io_err, write_atomic};

/// A Python value, as far as the official layouts need: what [`to_pickle`] writes.
#[derive(Debug, Clone, PartialEq)]
pub enum Py {
    /// `True` / `False`.
    Bool(bool),
    /// `int`.
    Int(i64),
    /// `float`.
    Float(f64),
    /// `str`.
    Str(String),
    /// `bytes`.
    Bytes(Vec<u8>),
    /// `list`.
    List(Vec<Py>),
    /// `dict`, keys in the given order.
    Dict(Vec<(Py, Py)>),
    /// A C-ordered `numpy.ndarray`.
    Array(NdArray),
}

/// A numpy array: its dtype (`<f8`, `<i8` or `|b1`), shape and little-endian element bytes.
#[derive(Debug, Clone, PartialEq)]
pub struct NdArray {
    dtype: &'static str,
    shape: Vec<usize>,
    data: Vec<u8>,
}

impl NdArray {
    /// A `float64` array of `shape` (C order).
    pub fn f64(shape: Vec<usize>, values: &[f64]) -> Self {
        assert_eq!(shape.iter().product::<usize>(), values.len());
        let data = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        Self {
            dtype: "<f8",
            shape,
            data,
        }
    }

    /// A one-dimensional `int64` array.
    pub fn i64(values: &[i64]) -> Self {
        let data = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        Self {
            dtype: "<i8",
            shape: vec![values.len()],
            data,
        }
    }

    /// A one-dimensional `bool` array.
    pub fn bool(values: &[bool]) -> Self {
        Self {
            dtype: "|b1",
            shape: vec![values.len()],
            data: values.iter().map(|&b| u8::from(b)).collect(),
        }
    }
}

/// Serialises `value` as a protocol-3 pickle (Python ≥ 3.0). Arrays are written as numpy
/// pickles them, `numpy.core.multiarray._reconstruct` then `BUILD` with
/// `(1, shape, dtype, False, bytes)`, the module name numpy 1.x has and numpy 2 still loads.
pub fn to_pickle(value: &Py) -> Vec<u8> {
    let mut out = vec![0x80, 3];
    write_value(&mut out, value);
    out.push(b'.');
    out
}

fn write_int(out: &mut Vec<u8>, i: i64) {
    if let Ok(small) = i32::try_from(i) {
        out.push(b'J'); // BININT
        out.extend(small.to_le_bytes());
    } else {
        out.extend([0x8a, 8]); // LONG1, eight bytes of two's complement
        out.extend(i.to_le_bytes());
    }
}

fn write_str(out: &mut Vec<u8>, s: &str) {
    out.push(b'X'); // BINUNICODE
    out.extend((s.len() as u32).to_le_bytes());
    out.extend(s.as_bytes());
}

fn write_bytes(out: &mut Vec<u8>, b: &[u8]) {
    let len = u32::try_from(b.len()).expect("a byte string under 4 GiB");
    out.push(b'B'); // BINBYTES
    out.extend(len.to_le_bytes());
    out.extend(b);
}

fn write_value(out: &mut Vec<u8>, value: &Py) {
    match value {
        Py::Bool(b) => out.push(if *b { 0x88 } else { 0x89 }),
        Py::Int(i) => write_int(out, *i),
        Py::Float(f) => {
            out.push(b'G'); // BINFLOAT, big-endian
            out.extend(f.to_be_bytes());
        }
        Py::Str(s) => write_str(out, s),
        Py::Bytes(b) => write_bytes(out, b),
        Py::List(items) => {
            out.push(b']'); // EMPTY_LIST
            if !items.is_empty() {
                out.push(b'('); // MARK
                items.iter().for_each(|v| write_value(out, v));
                out.push(b'e'); // APPENDS
            }
        }
        Py::Dict(entries) => {
            out.push(b'}'); // EMPTY_DICT
            if !entries.is_empty() {
                out.push(b'(');
                for (k, v) in entries {
                    write_value(out, k);
                    write_value(out, v);
                }
                out.push(b'u'); // SETITEMS
            }
        }
        Py::Array(a) => {
            out.extend(b"cnumpy.core.multiarray\n_reconstruct\n"); // GLOBAL
            out.extend(b"cnumpy\nndarray\n");
            write_int(out, 0);
            out.push(0x85); // TUPLE1: shape (0,)
            write_bytes(out, b"b");
            out.push(0x87); // TUPLE3
            out.push(b'R'); // REDUCE
            out.push(b'('); // the state: (1, shape, dtype, False, data)
            write_int(out, 1);
            out.push(b'(');
            a.shape.iter().for_each(|&d| write_int(out, d as i64));
            out.push(b't'); // TUPLE
            out.extend(b"cnumpy\ndtype\n");
            write_str(out, &a.dtype[1..]);
            out.extend([0x89, 0x88, 0x87, b'R']); // (name, False, True) → dtype
            out.push(b'('); // dtype state: (3, byte order, None, None, None, -1, -1, 0)
            write_int(out, 3);
            write_str(out, &a.dtype[..1]);
            out.extend(b"NNN");
            write_int(out, -1);
            write_int(out, -1);
            write_int(out, 0);
            out.extend(b"tb"); // TUPLE, BUILD
            out.push(0x89); // not Fortran-ordered
            write_bytes(out, &a.data);
            out.extend(b"tb");
        }
    }
}

/// One trajectory of a force/slip batch.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    /// Per sample: its index in the batch's frame list.
    pub indexes: Vec<i64>,
    /// Per sample: [Fx, Fy, Fz] (N).
    pub forces: Vec<[f64; 3]>,
    /// Per sample: 1 where slipping (the friction-cone label), else 0.
    pub slip_label: Vec<i64>,
}

/// `dataset_slip_forces.pkl` of one batch folder.
#[derive(Debug, Clone, PartialEq)]
pub struct SlipForces {
    /// Per frame of the batch's frame list: in contact.
    pub in_contact: Vec<bool>,
    /// The trajectories, keyed 0, 1, … in order.
    pub trajectories: Vec<Trajectory>,
}

/// JPEG quality of exported frames.
pub const JPEG_QUALITY: u8 = 95;

/// Writes a pickle of JPEG frames (a list of byte strings).
pub fn write_frames_pickle(path: &Path, frames: &[RgbImage]) -> Result<(), DataError> {
    let list = frames
        .iter()
        .map(|f| encode_jpeg(f).map(Py::Bytes))
        .collect::<Result<Vec<_>, String>>()
        .map_err(|message| DataError::Format {
            path: path.to_path_buf(),
            message,
        })?;
    write_atomic(path, &to_pickle(&Py::List(list)))
}

/// Reads a pickle of encoded frames: a list (or tuple) of byte strings, or a dictionary whose
/// first non-empty list value (keys in sorted order) is one, as the official datasets store them.
pub fn read_frames_pickle(path: &Path) -> Result<Vec<Vec<u8>>, DataError> {
    let as_bytes = |items: Vec<Value>| {
        items
            .into_iter()
            .map(|v| match v {
                Value::Bytes(b) => Some(b),
                _ => None,
            })
            .collect::<Option<Vec<_>>>()
    };
    let frames = match read_pickle(path)? {
        Value::List(items) | Value::Tuple(items) => as_bytes(items),
        Value::Dict(map) => {
            let mut entries: Vec<(HashableValue, Value)> = map.into_iter().collect();
            entries.sort_by(|a, b| format!("{:?}", a.0).cmp(&format!("{:?}", b.0)));
            entries.into_iter().find_map(|(_, v)| match v {
                Value::List(items) | Value::Tuple(items) if !items.is_empty() => as_bytes(items),
                _ => None,
            })
        }
        _ => None,
    };
    frames.ok_or_else(|| DataError::Format {
        path: path.to_path_buf(),
        message: "expected a list of encoded frames (bytes)".into(),
    })
}

/// Writes `dataset_slip_forces.pkl` with numpy arrays, as the official loader indexes them.
pub fn write_slip_forces(path: &Path, labels: &SlipForces) -> Result<(), DataError> {
    let key = |k: &str| Py::Str(k.into());
    let trajectories = labels
        .trajectories
        .iter()
        .enumerate()
        .map(|(t, traj)| {
            let forces: Vec<f64> = traj.forces.iter().flatten().copied().collect();
            let entry = Py::Dict(vec![
                (key("indexes"), Py::Array(NdArray::i64(&traj.indexes))),
                (
                    key("forces"),
                    Py::Array(NdArray::f64(vec![traj.forces.len(), 3], &forces)),
                ),
                (key("slip_label"), Py::Array(NdArray::i64(&traj.slip_label))),
            ]);
            (Py::Int(t as i64), entry)
        })
        .collect();
    let root = Py::Dict(vec![
        (
            key("in_contact"),
            Py::Array(NdArray::bool(&labels.in_contact)),
        ),
        (key("trajectories"), Py::Dict(trajectories)),
    ]);
    write_atomic(path, &to_pickle(&root))
}

/// The official code's name of a sensor preset: `digit`, `gelsight` (GelSight 2017) or
/// `gelsight_mini`.
pub fn official_sensor(preset: &str) -> Option<&'static str> {
    if preset.starts_with("digit") {
        Some("digit")
    } else if preset.starts_with("gelsight_mini") {
        Some("gelsight_mini")
    } else if preset.starts_with("gelsight") {
        Some("gelsight")
    } else {
        None
    }
}

/// The sensor preset of each family in a dataset's scene (`""` keys the families of a
/// single-scene file, whose `[sensor]` applies to every sequence).
fn family_presets(dir: &Path) -> Result<BTreeMap<String, String>, DataError> {
    let path = dir.join("dataset.json");
    let text = std::fs::read_to_string(&path).map_err(io_err(&path))?;
    let bad = |message: String| DataError::Format {
        path: path.clone(),
        message,
    };
    let identity: Identity = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
    let scene: toml::Table =
        toml::from_str(&identity.scene).map_err(|e| bad(format!("scene: {}", e.message())))?;
    let preset = |t: &toml::Table| {
        t.get("sensor")
            .and_then(|s| s.get("preset"))
            .and_then(|p| p.as_str())
            .map(str::to_string)
    };
    let mut presets = BTreeMap::new();
    match scene.get("family").and_then(|f| f.as_array()) {
        Some(families) => {
            for f in families.iter().filter_map(|f| f.as_table()) {
                let name = f.get("name").and_then(|n| n.as_str()).unwrap_or_default();
                let p = preset(f)
                    .ok_or_else(|| bad(format!("scene: family `{name}` has no sensor.preset")))?;
                presets.insert(name.to_string(), p);
            }
        }
        None => {
            let p = preset(&scene).ok_or_else(|| bad("scene: no sensor.preset".into()))?;
            presets.insert(String::new(), p);
        }
    }
    Ok(presets)
}

/// What [`export`] wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct Exported {
    /// Sequences written.
    pub sequences: usize,
    /// The official sensor names present, in order.
    pub sensors: Vec<&'static str>,
}

/// One sequence on its way out.
struct Out {
    sequence: usize,
    family: String,
    test: bool,
    sensor: &'static str,
    background: String,
}

impl Out {
    /// The SSL object name (no `/`: the official code takes the background's table key from the
    /// dataset name's first component).
    fn object(&self) -> String {
        format!("{}_{:06}", self.family, self.sequence)
    }

    /// The force/slip batch, relative to `force_slip/<sensor>/`.
    fn batch(&self) -> String {
        let split = if self.test { "test" } else { "train" };
        format!("{split}/{}/batch_{:06}", self.family, self.sequence)
    }
}

/// Exports the dataset in `dir` (written by `sparsh generate`) into `out` in the official
/// layouts (see the module docs).
pub fn export(dir: &Path, out: &Path) -> Result<Exported, DataError> {
    let labels_path = dir.join("labels.jsonl");
    let text = std::fs::read_to_string(&labels_path).map_err(io_err(&labels_path))?;
    let mut sequences: BTreeMap<usize, Vec<Label>> = BTreeMap::new();
    for (k, line) in text.lines().enumerate() {
        let row: Label = serde_json::from_str(line).map_err(|e| DataError::Format {
            path: labels_path.clone(),
            message: format!("line {}: {e}", k + 1),
        })?;
        sequences.entry(row.sequence).or_default().push(row);
    }
    let presets = family_presets(dir)?;
    let single = presets.get("").cloned();
    // the data configs name absolute paths, so they work from the official repository
    std::fs::create_dir_all(out).map_err(io_err(out))?;
    let out = &out.canonicalize().map_err(io_err(out))?;
    let mut outs = Vec::new();
    for (&sequence, rows) in &sequences {
        let family = &rows[0].family;
        let preset = presets
            .get(family)
            .or(single.as_ref())
            .ok_or_else(|| DataError::Format {
                path: labels_path.clone(),
                message: format!("sequence {sequence}: family `{family}` is not in the scene"),
            })?;
        let sensor = official_sensor(preset).ok_or_else(|| DataError::Format {
            path: dir.join("dataset.json"),
            message: format!("sensor preset `{preset}` has no official Sparsh name"),
        })?;
        let out_seq = Out {
            sequence,
            family: if family.is_empty() {
                "scene".into()
            } else {
                family.replace('/', "_")
            },
            test: rows[0].split == "test",
            sensor,
            background: rows[0].background.clone(),
        };
        export_sequence(dir, out, &out_seq, rows)?;
        outs.push(out_seq);
    }
    let mut sensors: Vec<&'static str> = outs.iter().map(|o| o.sensor).collect();
    sensors.sort_unstable();
    sensors.dedup();
    for &sensor in &sensors {
        let of_sensor: Vec<&Out> = outs.iter().filter(|o| o.sensor == sensor).collect();
        // one shared background: also where the official GelSight Mini loader looks for it
        let first = std::fs::read(dir.join(&of_sensor[0].background))
            .map_err(io_err(&dir.join(&of_sensor[0].background)))?;
        let mut shared = true;
        for o in &of_sensor[1..] {
            let path = dir.join(&o.background);
            shared &= std::fs::read(&path).map_err(io_err(&path))? == first;
        }
        if shared {
            let bgs = out.join("ssl").join(sensor).join("bgs");
            std::fs::copy(
                bgs.join(format!("bg_{}.jpg", of_sensor[0].object())),
                bgs.join("bg_gs.jpg"),
            )
            .map_err(io_err(&bgs.join("bg_gs.jpg")))?;
        }
        let path = out.join(format!("sparsh_force_slip_{sensor}.yaml"));
        write_atomic(&path, force_slip_config(out, sensor, &of_sensor).as_bytes())?;
    }
    let path = out.join("sparsh_ssl.yaml");
    write_atomic(&path, ssl_config(out, &sensors, &outs).as_bytes())?;
    Ok(Exported {
        sequences: outs.len(),
        sensors,
    })
}

fn export_sequence(dir: &Path, out: &Path, seq: &Out, rows: &[Label]) -> Result<(), DataError> {
    let read = |rel: &str| -> Result<RgbImage, DataError> {
        let path = dir.join(rel);
        image::open(&path)
            .map(|i| i.to_rgb8())
            .map_err(|e| DataError::Format {
                path: path.clone(),
                message: e.to_string(),
            })
    };
    let jpeg = |img: &RgbImage, path: &Path| {
        encode_jpeg(img).map_err(|message| DataError::Format {
            path: path.to_path_buf(),
            message,
        })
    };
    let batch = out.join("force_slip").join(seq.sensor).join(seq.batch());
    let bg = jpeg(&read(&seq.background)?, &batch)?;
    let frames = rows
        .iter()
        .map(|r| jpeg(&read(&format!("frames/{:06}.png", r.frame))?, &batch))
        .collect::<Result<Vec<_>, _>>()?;

    // force/slip: frame 0 of the batch is the background, the only frame out of contact that
    // the official loader's `np.where(in_contact == 0)[0][0]` can pick
    std::fs::create_dir_all(&batch).map_err(io_err(&batch))?;
    let with_bg = std::iter::once(&bg)
        .chain(&frames)
        .map(|b| Py::Bytes(b.clone()))
        .collect();
    write_atomic(
        &batch.join(format!("dataset_{}_00.pkl", seq.sensor)),
        &to_pickle(&Py::List(with_bg)),
    )?;
    let in_contact = std::iter::once(false)
        .chain(rows.iter().map(|r| r.contact_area_mm2 > 0.0))
        .collect();
    write_slip_forces(
        &batch.join("dataset_slip_forces.pkl"),
        &SlipForces {
            in_contact,
            trajectories: vec![Trajectory {
                indexes: (1..=rows.len() as i64).collect(),
                forces: rows.iter().map(|r| r.force_n).collect(),
                slip_label: rows.iter().map(|r| i64::from(r.slip_cone)).collect(),
            }],
        },
    )?;

    // SSL: the frames alone, the background beside the others
    let ssl = out.join("ssl").join(seq.sensor);
    let object = ssl.join(seq.object());
    let bgs = ssl.join("bgs");
    for d in [&object, &bgs] {
        std::fs::create_dir_all(d).map_err(io_err(d))?;
    }
    let frames = Py::List(frames.into_iter().map(Py::Bytes).collect());
    write_atomic(&object.join("dataset_0.pkl"), &to_pickle(&frames))?;
    write_atomic(&bgs.join(format!("bg_{}.jpg", seq.object())), &bg)
}

/// A YAML list of quoted names.
fn yaml_list(names: impl Iterator<Item = String>) -> String {
    let items: Vec<String> = names.map(|n| format!("\"{n}\"")).collect();
    format!("[{}]", items.join(", "))
}

/// The Hydra data config of one sensor's force/slip batches, in the shape of the official
/// `config/data/digit_force.yaml` (test batches under `test/`, read with `look_in_folder`).
fn force_slip_config(out: &Path, sensor: &str, seqs: &[&Out]) -> String {
    let families = |test: bool| {
        let f: std::collections::BTreeSet<String> = seqs
            .iter()
            .filter(|s| s.test == test)
            .map(|s| format!("{}/{}", if test { "test" } else { "train" }, s.family))
            .collect();
        yaml_list(f.into_iter())
    };
    // the official scales (config/data/{digit,gelsight}_force.yaml)
    let scale = if sensor == "digit" {
        "[4.0, 4.0, 5.0]"
    } else {
        "[1.5, 1.5, 2.0]"
    };
    format!(
        "# Written by `sparsh export --format sparsh-pkl`: the force/slip batches of the {sensor} \
         sequences,\n# for facebookresearch/sparsh's config/data/ (in place of {sensor}_force.yaml).\n\
         train_val_split: ~\ntrain_data_budget: 1.0\nval_data_budget: 1.0\nmax_train_data: ~\n\
         sensor: {sensor}\n\ndataset:\n  _target_: \
         tactile_ssl.data.vision_based_forces_slip_probes.VisionForceSlipDataset\n  config:\n    \
         sensor: ${{data.sensor}}\n    remove_bg: true\n    out_format: \"concat_ch_img\"\n    \
         num_frames: 2\n    frame_stride: 5\n\n    path_dataset: \"{path}/\"\n    \
         list_datasets: {train}\n    list_datasets_test: {test}\n    look_in_folder: true\n\n    \
         slip_horizon: 0\n    max_abs_forceXYZ: {scale}\n    \
         max_delta_forceXYZ: [0.25, 0.25, 0.15]\n\n    transforms:\n      resize: [320, 240]\n\n\
         train_dataloader:\n  batch_size: 100\n  num_workers: 8\n  drop_last: True\n  \
         pin_memory: True\n  persistent_workers: True\n  shuffle: True\n\nval_dataloader:\n  \
         batch_size: 100\n  num_workers: 8\n  drop_last: True\n  pin_memory: True\n  \
         persistent_workers: True\n",
        path = out.join("force_slip").join(sensor).display(),
        train = families(false),
        test = families(true),
    )
}

/// The Hydra data config of every sensor's SSL objects, in the shape of the official
/// `config/data/vision_based.yaml`: per sensor, one entry of training objects (`dataset_0` as
/// training data) and one of test objects (`dataset_0` as validation data).
fn ssl_config(out: &Path, sensors: &[&str], outs: &[Out]) -> String {
    let mut text = String::from(
        "# Written by `sparsh export --format sparsh-pkl`: every sequence as one SSL object,\n\
         # for facebookresearch/sparsh's config/data/ (in place of vision_based.yaml). DIGIT \
         backgrounds\n# need the one-line patch of get_bg_img the sparsh book gives.\n\
         train_dataloader:\n  batch_size: 64\n  num_workers: 8\n  shuffle: True\n  \
         drop_last: True\n  pin_memory: True\n  persistent_workers: True\n\nval_dataloader:\n  \
         batch_size: 64\n  num_workers: 8\n  shuffle: True\n  drop_last: True\n  \
         pin_memory: True\n  persistent_workers: True\n\nremove_bg: true\n\nsensor:\n",
    );
    for &sensor in sensors {
        let path = out.join("ssl").join(sensor);
        for test in [false, true] {
            let objects: Vec<String> = outs
                .iter()
                .filter(|o| o.sensor == sensor && o.test == test)
                .map(Out::object)
                .collect();
            if objects.is_empty() {
                continue;
            }
            let (train_ids, val_ids) = if test { ("[]", "[0]") } else { ("[0]", "[]") };
            // the official GelSight (2017) entry lists each object's files and subtracts no
            // background; the DIGIT and Mini entries take the ids and the backgrounds
            let kind = if sensor == "gelsight" {
                "gelsight"
            } else {
                sensor
            };
            text.push_str(&format!(
                "  - type: {kind}\n    dataset:\n      _target_: \
                 tactile_ssl.data.vision_tactile.VisionTactileBackboneDataset\n      config:\n        \
                 sensor: {kind}\n        remove_bg: {remove_bg}\n        out_format: ${{data_out_format}}\n        \
                 num_frames: ${{num_frames}}\n        frame_stride: ${{frame_stride}}\n\n        \
                 dataset_ids_train: {train_ids}\n        dataset_ids_val: {val_ids}\n        \
                 train_val_split: {split}\n        path_dataset: \"{path}/\"\n        \
                 path_bgs: \"{path}/bgs/\"\n        list_datasets: {objects}\n\n        \
                 transforms:\n          with_augmentation: true\n          resize: [320, 240]\n          \
                 p_flip: 0.5\n          p_crop: 0.2\n          p_rot: 0.2\n\n",
                remove_bg = if sensor == "gelsight" {
                    "false"
                } else {
                    "${data.remove_bg}"
                },
                split = if test { "0.0" } else { "1.0" },
                path = path.display(),
                objects = yaml_list(objects.into_iter()),
            ));
        }
    }
    text
}

fn encode_jpeg(image: &RgbImage) -> Result<Vec<u8>, String> {
    let mut bytes = Vec::new();
    image
        .write_with_encoder(image::codecs::jpeg::JpegEncoder::new_with_quality(
            &mut bytes,
            JPEG_QUALITY,
        ))
        .map_err(|e| e.to_string())?;
    Ok(bytes)
}

/// Reads a whole pickle file. Memory is bounded by the file's size: a length prefix reaching past
/// the end of the file is refused before its bytes are allocated, and each memo entry is
/// expanded at most as many times as the file refers to it.
fn read_pickle(path: &Path) -> Result<Value, DataError> {
    let bytes = std::fs::read(path).map_err(io_err(path))?;
    serde_pickle::value_from_reader(
        Cursor::new(bytes),
        serde_pickle::DeOptions::new().replace_unresolved_globals(),
    )
    .map_err(|e| DataError::Format {
        path: path.to_path_buf(),
        message: format!("not a readable pickle: {e}"),
    })
}
