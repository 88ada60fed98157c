//! Writes a dataset directory: atomic files, labels, and a manifest with their checksums.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use image::RgbImage;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::{DataError, io_err};

/// Indenter pose in a label row.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PoseLabel {
    /// Position of the indenter's tip in the camera frame (mm).
    pub position_mm: [f64; 3],
    /// X, Y, Z Euler angles (degrees).
    pub rotation_deg: [f64; 3],
}

/// One row of `labels.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Label {
    /// Frame index in the dataset (names `frames/NNNNNN.png`).
    pub frame: usize,
    /// Sequence the frame belongs to.
    pub sequence: usize,
    /// Index within its sequence.
    pub frame_in_sequence: usize,
    /// Time since the sequence started (s).
    pub time_s: f64,
    /// Total contact force on the gel [Fx, Fy, Fz] (N); Fz > 0 presses.
    pub force_n: [f64; 3],
    /// Indenter pose.
    pub pose: PoseLabel,
    /// `no_contact`, `stick`, `partial` or `gross`.
    pub slip_state: String,
    /// Contact area (mm²).
    pub contact_area_mm2: f64,
}

/// `manifest.json`: what made the dataset and the checksum of every file in it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Layout version, `sparsh-dataset/1`.
    pub format: String,
    /// Version of sparsh that wrote it.
    pub sparsh_version: String,
    /// File name of the scene.
    pub scene_file: String,
    /// The scene file's text.
    pub scene: String,
    /// Scene seed.
    pub seed: u64,
    /// Contact solver rung.
    pub solver: String,
    /// Number of frames.
    pub frames: usize,
    /// Field channels written per frame.
    pub fields: Vec<String>,
    /// `f32` or `f16`.
    pub field_precision: String,
    /// What a user should know about the data (e.g. channels a rung leaves zero).
    pub notes: Vec<String>,
    /// sha256 (hex) of every file, by path relative to the dataset directory.
    pub files: BTreeMap<String, String>,
}

/// Entries of a dataset directory that `--force` replaces.
const DATASET_ENTRIES: [&str; 5] = [
    "frames",
    "fields",
    "labels.jsonl",
    "manifest.json",
    "background.png",
];

/// Writes a dataset directory file by file.
#[derive(Debug)]
pub struct DatasetWriter {
    dir: PathBuf,
    files: BTreeMap<String, String>,
    labels: Vec<u8>,
}

impl DatasetWriter {
    /// Prepares `dir`: it must be empty or absent, unless `force`, which removes a previous
    /// dataset's entries (and nothing else) first.
    pub fn create(dir: &Path, force: bool) -> Result<DatasetWriter, DataError> {
        if dir.exists() {
            let mut entries = std::fs::read_dir(dir).map_err(io_err(dir))?;
            if entries.next().is_some() {
                if !force {
                    return Err(DataError::NotEmpty {
                        path: dir.to_path_buf(),
                    });
                }
                for name in DATASET_ENTRIES {
                    let path = dir.join(name);
                    if path.is_dir() {
                        std::fs::remove_dir_all(&path).map_err(io_err(&path))?;
                    } else if path.exists() {
                        std::fs::remove_file(&path).map_err(io_err(&path))?;
                    }
                }
            }
        }
        for sub in ["frames", "fields"] {
            let path = dir.join(sub);
            std::fs::create_dir_all(&path).map_err(io_err(&path))?;
        }
        Ok(DatasetWriter {
            dir: dir.to_path_buf(),
            files: BTreeMap::new(),
            labels: Vec::new(),
        })
    }

    /// Writes `bytes` to `rel` (relative to the dataset directory) atomically and records its
    /// checksum.
    pub fn write_file(&mut self, rel: &str, bytes: &[u8]) -> Result<(), DataError> {
        write_atomic(&self.dir.join(rel), bytes)?;
        self.files
            .insert(rel.to_string(), hex(&Sha256::digest(bytes)));
        Ok(())
    }

    /// Writes an 8-bit RGB PNG.
    pub fn write_png(&mut self, rel: &str, image: &RgbImage) -> Result<(), DataError> {
        let bytes = encode_png(image).map_err(|message| DataError::Format {
            path: self.dir.join(rel),
            message,
        })?;
        self.write_file(rel, &bytes)
    }

    /// Appends a row to the labels.
    pub fn push_label(&mut self, label: &Label) {
        serde_json::to_writer(&mut self.labels, label).expect("labels serialise");
        self.labels.push(b'\n');
    }

    /// Writes `labels.jsonl`, then the manifest with every file's checksum: the dataset is
    /// complete once `manifest.json` exists.
    pub fn finish(mut self, mut manifest: Manifest) -> Result<(), DataError> {
        let labels = std::mem::take(&mut self.labels);
        self.write_file("labels.jsonl", &labels)?;
        manifest.files = std::mem::take(&mut self.files);
        let mut json = serde_json::to_vec_pretty(&manifest).expect("manifest serialises");
        json.push(b'\n');
        write_atomic(&self.dir.join("manifest.json"), &json)
    }
}

/// Encodes an RGB image as PNG bytes.
pub fn encode_png(image: &RgbImage) -> Result<Vec<u8>, String> {
    let mut bytes = Vec::new();
    image
        .write_with_encoder(image::codecs::png::PngEncoder::new(&mut bytes))
        .map_err(|e| e.to_string())?;
    Ok(bytes)
}

/// Writes `bytes` to a temporary file beside `path`, then renames it into place, so `path` is
/// either absent or complete.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), DataError> {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.tmp"));
    std::fs::write(&tmp, bytes).map_err(io_err(path))?;
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        io_err(path)(e)
    })
}

fn hex(digest: &[u8]) -> String {
    digest.iter().map(|b| format!("{b:02x}")).collect()
}
