//! The official Sparsh repository's on-disk layouts (facebookresearch/sparsh): frames as a
//! pickled list of JPEG byte strings per sequence, and force/slip labels as a pickled dictionary
//! `{"in_contact": [...], "trajectories": {"indexes": [...], "forces": [[fx, fy, fz], ...],
//! "slip_label": [...]}}` (`dataset_slip_forces.pkl`).
//!
//! `export` turns a dataset written by `sparsh generate` into
//! ```text
//! OUT/frames/000000/dataset_0.pkl              the sequence's frames, JPEG-encoded, in order
//! OUT/frames/000000/bg_0.jpg                   its background
//! OUT/labels/000000/dataset_slip_forces.pkl    its force and slip labels
//! ```
//! so PyTorch users can train the official code on simulated data.

use std::collections::BTreeMap;
use std::io::Cursor;
use std::path::Path;

use image::RgbImage;
use serde_pickle::{HashableValue, Value};

use crate::{DataError, Label, io_err, write_atomic};

/// Force and slip labels of one sequence in the official layout.
#[derive(Debug, Clone, PartialEq)]
pub struct SlipForces {
    /// Per frame: in contact.
    pub in_contact: Vec<bool>,
    /// Per frame: its index in the sequence's frame list.
    pub indexes: Vec<i64>,
    /// Per frame: [Fx, Fy, Fz] (N).
    pub forces: Vec<[f64; 3]>,
    /// Per frame: 1 where slipping (the friction-cone label), else 0.
    pub slip_label: Vec<i64>,
}

/// JPEG quality of exported frames.
pub const JPEG_QUALITY: u8 = 95;

/// Writes a pickle of JPEG frames (a list of byte strings).
pub fn write_frames_pickle(path: &Path, frames: &[RgbImage]) -> Result<(), DataError> {
    let list = frames
        .iter()
        .map(|f| encode_jpeg(f).map(Value::Bytes))
        .collect::<Result<Vec<_>, String>>()
        .map_err(|message| DataError::Format {
            path: path.to_path_buf(),
            message,
        })?;
    write_pickle(path, &Value::List(list))
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

/// Writes `dataset_slip_forces.pkl`.
pub fn write_slip_forces(path: &Path, labels: &SlipForces) -> Result<(), DataError> {
    let key = |k: &str| HashableValue::String(k.into());
    let ints = |v: &[i64]| Value::List(v.iter().map(|&i| Value::I64(i)).collect());
    let trajectories = BTreeMap::from([
        (key("indexes"), ints(&labels.indexes)),
        (
            key("forces"),
            Value::List(
                labels
                    .forces
                    .iter()
                    .map(|f| Value::List(f.iter().map(|&c| Value::F64(c)).collect()))
                    .collect(),
            ),
        ),
        (key("slip_label"), ints(&labels.slip_label)),
    ]);
    let root = BTreeMap::from([
        (
            key("in_contact"),
            Value::List(labels.in_contact.iter().map(|&b| Value::Bool(b)).collect()),
        ),
        (key("trajectories"), Value::Dict(trajectories)),
    ]);
    write_pickle(path, &Value::Dict(root))
}

/// Reads `dataset_slip_forces.pkl`.
pub fn read_slip_forces(path: &Path) -> Result<SlipForces, DataError> {
    let bad = |message: String| DataError::Format {
        path: path.to_path_buf(),
        message,
    };
    let Value::Dict(root) = read_pickle(path)? else {
        return Err(bad("not a dictionary".into()));
    };
    let get = |d: &BTreeMap<HashableValue, Value>, k: &str| {
        d.get(&HashableValue::String(k.into()))
            .cloned()
            .ok_or_else(|| bad(format!("no `{k}` key")))
    };
    let list = |v: Value, k: &str| match v {
        Value::List(items) | Value::Tuple(items) => Ok(items),
        _ => Err(bad(format!("`{k}` is not a list"))),
    };
    let int = |v: &Value, k: &str| match v {
        Value::I64(i) => Ok(*i),
        Value::Bool(b) => Ok(i64::from(*b)),
        _ => Err(bad(format!("`{k}` holds a non-integer"))),
    };
    let float = |v: &Value| match v {
        Value::F64(f) => Ok(*f),
        Value::I64(i) => Ok(*i as f64),
        _ => Err(bad("`forces` holds a non-number".into())),
    };
    let in_contact = list(get(&root, "in_contact")?, "in_contact")?
        .iter()
        .map(|v| int(v, "in_contact").map(|i| i != 0))
        .collect::<Result<_, _>>()?;
    let Value::Dict(traj) = get(&root, "trajectories")? else {
        return Err(bad("`trajectories` is not a dictionary".into()));
    };
    let indexes = list(get(&traj, "indexes")?, "indexes")?
        .iter()
        .map(|v| int(v, "indexes"))
        .collect::<Result<_, _>>()?;
    let slip_label = list(get(&traj, "slip_label")?, "slip_label")?
        .iter()
        .map(|v| int(v, "slip_label"))
        .collect::<Result<_, _>>()?;
    let forces = list(get(&traj, "forces")?, "forces")?
        .into_iter()
        .map(|row| {
            let row = list(row, "forces")?;
            if row.len() != 3 {
                return Err(bad("`forces` rows must have 3 components".into()));
            }
            Ok([float(&row[0])?, float(&row[1])?, float(&row[2])?])
        })
        .collect::<Result<_, _>>()?;
    Ok(SlipForces {
        in_contact,
        indexes,
        forces,
        slip_label,
    })
}

/// Exports the dataset in `dir` (written by `sparsh generate`) into `out`; returns the number
/// of sequences.
pub fn export(dir: &Path, out: &Path) -> Result<usize, DataError> {
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
    for (sequence, rows) in &sequences {
        let frames_dir = out.join("frames").join(format!("{sequence:06}"));
        let labels_dir = out.join("labels").join(format!("{sequence:06}"));
        for d in [&frames_dir, &labels_dir] {
            std::fs::create_dir_all(d).map_err(io_err(d))?;
        }
        let read = |rel: &str| -> Result<RgbImage, DataError> {
            let path = dir.join(rel);
            image::open(&path)
                .map(|i| i.to_rgb8())
                .map_err(|e| DataError::Format {
                    path: path.clone(),
                    message: e.to_string(),
                })
        };
        let frames = rows
            .iter()
            .map(|r| read(&format!("frames/{:06}.png", r.frame)))
            .collect::<Result<Vec<_>, _>>()?;
        write_frames_pickle(&frames_dir.join("dataset_0.pkl"), &frames)?;
        let bg_path = frames_dir.join("bg_0.jpg");
        let bg = encode_jpeg(&read(&rows[0].background)?).map_err(|message| DataError::Format {
            path: bg_path.clone(),
            message,
        })?;
        write_atomic(&bg_path, &bg)?;
        write_slip_forces(
            &labels_dir.join("dataset_slip_forces.pkl"),
            &SlipForces {
                in_contact: rows.iter().map(|r| r.contact_area_mm2 > 0.0).collect(),
                indexes: rows.iter().map(|r| r.frame_in_sequence as i64).collect(),
                forces: rows.iter().map(|r| r.force_n).collect(),
                slip_label: rows.iter().map(|r| i64::from(r.slip_cone)).collect(),
            },
        )?;
    }
    Ok(sequences.len())
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

fn write_pickle(path: &Path, value: &Value) -> Result<(), DataError> {
    let mut bytes = Vec::new();
    serde_pickle::value_to_writer(&mut bytes, value, serde_pickle::SerOptions::new()).map_err(
        |e| DataError::Format {
            path: path.to_path_buf(),
            message: e.to_string(),
        },
    )?;
    write_atomic(path, &bytes)
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
