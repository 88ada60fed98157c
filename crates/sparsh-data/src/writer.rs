//! Writes a dataset directory sequence by sequence: atomic files, a record per finished
//! sequence (so killed runs resume and shards share a directory), and, once every sequence is
//! there, `labels.jsonl` and a manifest with the checksum of every file.

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
    /// Family the sequence was drawn from.
    pub family: String,
    /// `train` or `test`.
    pub split: String,
    /// The sequence's indenter: a mesh's file stem, a textured plate's pattern, else the shape
    /// (`sphere`, `cylinder`, `cone`, `box`); absent in datasets written before it was recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub indenter: Option<String>,
    /// Time since the sequence started (s).
    pub time_s: f64,
    /// Total contact force on the gel [Fx, Fy, Fz] (N); Fz > 0 presses.
    pub force_n: [f64; 3],
    /// Change of `force_n` since frame t − 5 of the sequence (since its first frame before that).
    pub delta_force_n: [f64; 3],
    /// Mechanical stick/slip state: `no_contact`, `stick`, `partial` or `gross`.
    pub slip_state: String,
    /// The official Sparsh slip label: ‖(Fx, Fy)‖ > ratio · Fz, the ratio set in `[output]`.
    pub slip_cone: bool,
    /// Indenter pose.
    pub pose: PoseLabel,
    /// SE(2) motion of the indenter relative to the sensor since the previous frame:
    /// [Δx (mm), Δy (mm), Δθ (deg) about the sensor normal]; zero on a sequence's first frame.
    pub pose_change_se2: [f64; 3],
    /// Contact area (mm²).
    pub contact_area_mm2: f64,
    /// The solver rung that solved the frame; absent in datasets written before it was recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub solver: Option<String>,
    /// `ok` where the frame lies within its rung's validity at the scene's force tolerance, else
    /// the limit it passed: `a_over_h` (contact radius over gel thickness), `depth_over_h`
    /// (indentation depth over gel thickness) or `rung` (the rung meets the tolerance nowhere in
    /// the study); absent in datasets written before it was recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub validity: Option<String>,
    /// The frame's value of the limit passed, and the rung's bound (for `rung`: the rung's best
    /// studied relative force error and the tolerance); absent when `validity` is `ok`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub validity_value_bound: Option<[f64; 2]>,
    /// Pixel pitch of the frame (mm per pixel): converts the fields' displacements (mm) to
    /// image motion; absent in datasets written before it was recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mm_per_px: Option<f64>,
    /// Centres of the gel's printed markers in this frame (pixels: x = column, y = row, pixel
    /// (0, 0)'s centre at the origin), row by row; absent for a markerless gel.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub markers_px: Vec<[f64; 2]>,
    /// The sequence's no-contact image, relative to the dataset directory.
    pub background: String,
}

/// `dataset.json`: what a dataset is made from; a resumed run or another shard must match it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Identity {
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
    /// Number of sequences.
    pub sequences: usize,
    /// Number of frames.
    pub frames: usize,
}

/// `manifest.json`: the identity, notes, and the sha256 of every file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// What made the dataset.
    #[serde(flatten)]
    pub identity: Identity,
    /// Field channels written per frame.
    pub fields: Vec<String>,
    /// `f32` or `f16`.
    pub field_precision: String,
    /// What a user should know about the data (e.g. channels a rung leaves zero).
    pub notes: Vec<String>,
    /// sha256 (hex) of every file, by path relative to the dataset directory.
    pub files: BTreeMap<String, String>,
}

/// The record of one finished sequence: its files' checksums and its label rows.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SequencePart {
    /// Sequence index.
    pub sequence: usize,
    /// sha256 of each file it wrote.
    pub files: BTreeMap<String, String>,
    /// Its label rows, in frame order.
    pub labels: Vec<Label>,
}

/// Entries of a dataset directory, which `--force` replaces.
const DATASET_ENTRIES: [&str; 8] = [
    "frames",
    "fields",
    "backgrounds",
    "parts",
    "labels.jsonl",
    "manifest.json",
    "dataset.json",
    SHARDS_FILE,
];

/// The shard layout of a dataset still being generated by shards (`--shard K/N`), so `verify`
/// can say which shards are done; removed when the dataset is complete (it is not part of the
/// dataset: every shard layout yields the same files).
const SHARDS_FILE: &str = "shards.json";

/// `shards.json`: the number of shards the last sharded run split the sequences into.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ShardLayout {
    /// N of `--shard K/N`.
    pub count: usize,
}

/// How to open a dataset directory.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OpenMode {
    /// A new dataset: the directory must be empty or absent, unless `force`, which removes a
    /// previous dataset's entries (and nothing else).
    Fresh {
        /// Replace a dataset already there.
        force: bool,
    },
    /// Continue a dataset made from the same scene and seed (`--resume`), or add a shard to it.
    Join,
}

/// A dataset directory being written. Safe to share between threads.
#[derive(Debug)]
pub struct Dataset {
    dir: PathBuf,
}

impl Dataset {
    /// Opens `dir` for writing the dataset described by `identity`.
    pub fn open(dir: &Path, identity: &Identity, mode: OpenMode) -> Result<Dataset, DataError> {
        let has_entries = dir.is_dir()
            && std::fs::read_dir(dir)
                .map_err(io_err(dir))?
                .next()
                .is_some();
        let id_path = dir.join("dataset.json");
        match mode {
            OpenMode::Fresh { force } if has_entries => {
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
            OpenMode::Join if has_entries => {
                let text = std::fs::read(&id_path).map_err(|_| DataError::Refused {
                    path: dir.to_path_buf(),
                    message: "holds files but no dataset.json: not a sparsh dataset to resume"
                        .into(),
                })?;
                let found: Identity =
                    serde_json::from_slice(&text).map_err(|e| DataError::Format {
                        path: id_path.clone(),
                        message: e.to_string(),
                    })?;
                if let Some(why) = mismatch(&found, identity) {
                    return Err(DataError::Refused {
                        path: dir.to_path_buf(),
                        message: format!("was made from {why}; refusing to mix datasets"),
                    });
                }
            }
            _ => {}
        }
        for sub in ["frames", "fields", "backgrounds", "parts"] {
            let path = dir.join(sub);
            std::fs::create_dir_all(&path).map_err(io_err(&path))?;
        }
        let dataset = Dataset {
            dir: dir.to_path_buf(),
        };
        if !id_path.exists() {
            dataset.write_file("dataset.json", &pretty_json(identity))?;
        }
        Ok(dataset)
    }

    /// The dataset directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Writes `bytes` to `rel` atomically; returns its sha256 (hex).
    pub fn write_file(&self, rel: &str, bytes: &[u8]) -> Result<String, DataError> {
        write_atomic(&self.dir.join(rel), bytes)?;
        Ok(sha256_hex(bytes))
    }

    /// Writes an 8-bit RGB PNG; returns its sha256.
    pub fn write_png(&self, rel: &str, image: &RgbImage) -> Result<String, DataError> {
        let bytes = encode_png(image).map_err(|message| DataError::Format {
            path: self.dir.join(rel),
            message,
        })?;
        self.write_file(rel, &bytes)
    }

    fn part_path(sequence: usize) -> String {
        format!("parts/{sequence:06}.json")
    }

    /// Whether sequence `sequence` was finished by this or an earlier run.
    pub fn has_part(&self, sequence: usize) -> bool {
        self.dir.join(Self::part_path(sequence)).is_file()
    }

    /// Records that shards of `count` are writing into the directory (see [`ShardLayout`]).
    pub fn record_shard_layout(&self, count: usize) -> Result<(), DataError> {
        self.write_file(SHARDS_FILE, &pretty_json(&ShardLayout { count }))
            .map(drop)
    }

    /// Checks the files of sequence `sequence` against its record (and the record against
    /// `manifest`, when there is one): `None` when the sequence is not recorded, else the files
    /// checked and the problems found. A record that cannot be read is itself a problem.
    pub fn check_part(
        &self,
        sequence: usize,
        manifest: Option<&Manifest>,
    ) -> Option<(usize, Vec<Problem>)> {
        check_part(&self.dir, sequence, manifest)
    }

    /// Records a finished sequence (after all its files are written).
    pub fn write_part(&self, part: &SequencePart) -> Result<(), DataError> {
        self.write_file(&Self::part_path(part.sequence), &pretty_json(part))
            .map(drop)
    }

    /// When every one of `sequences` is recorded, writes `labels.jsonl` and then the manifest
    /// (so a dataset with a manifest is complete), removes temporary files left by killed runs,
    /// and returns true; otherwise returns false.
    pub fn finish_if_complete(
        &self,
        sequences: usize,
        mut manifest: Manifest,
    ) -> Result<bool, DataError> {
        if !(0..sequences).all(|s| self.has_part(s)) {
            return Ok(false);
        }
        let mut labels = Vec::new();
        let mut files = BTreeMap::new();
        for s in 0..sequences {
            let rel = Self::part_path(s);
            let path = self.dir.join(&rel);
            let bytes = std::fs::read(&path).map_err(io_err(&path))?;
            let part: SequencePart =
                serde_json::from_slice(&bytes).map_err(|e| DataError::Format {
                    path: path.clone(),
                    message: e.to_string(),
                })?;
            for row in &part.labels {
                serde_json::to_writer(&mut labels, row).expect("labels serialise");
                labels.push(b'\n');
            }
            files.extend(part.files);
            files.insert(rel, sha256_hex(&bytes));
        }
        files.insert(
            "labels.jsonl".into(),
            self.write_file("labels.jsonl", &labels)?,
        );
        let id_path = self.dir.join("dataset.json");
        let id = std::fs::read(&id_path).map_err(io_err(&id_path))?;
        files.insert("dataset.json".into(), sha256_hex(&id));
        remove_temporaries(&self.dir)?;
        manifest.files = files;
        write_atomic(&self.dir.join("manifest.json"), &pretty_json(&manifest))?;
        let layout = self.dir.join(SHARDS_FILE);
        match std::fs::remove_file(&layout) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(io_err(&layout)(e)),
            _ => {}
        }
        Ok(true)
    }
}

/// What differs between the identity on disk and the one asked for.
fn mismatch(found: &Identity, wanted: &Identity) -> Option<String> {
    if found.seed != wanted.seed {
        Some(format!("seed {} (this run: {})", found.seed, wanted.seed))
    } else if found.scene != wanted.scene {
        Some(format!("another scene ({})", found.scene_file))
    } else if found.format != wanted.format || found.sparsh_version != wanted.sparsh_version {
        Some(format!(
            "{} by sparsh {} (this is {} by sparsh {})",
            found.format, found.sparsh_version, wanted.format, wanted.sparsh_version
        ))
    } else {
        None
    }
}

/// A problem `verify` found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Problem {
    /// File, relative to the dataset directory.
    pub file: String,
    /// `missing`, `corrupt (sha256 mismatch)` or, for a sequence's record, `unreadable record`.
    pub what: &'static str,
}

/// Checks every checksum in `dir/manifest.json`; returns the files that are missing or differ.
pub fn verify(dir: &Path) -> Result<(usize, Vec<Problem>), DataError> {
    let path = dir.join("manifest.json");
    let bytes = std::fs::read(&path).map_err(io_err(&path))?;
    let manifest = parse_manifest(&path, &bytes)?;
    let mut problems = Vec::new();
    for (rel, sum) in &manifest.files {
        if let Some(what) = check_file(dir, rel, sum) {
            problems.push(Problem {
                file: rel.clone(),
                what,
            });
        }
    }
    Ok((manifest.files.len(), problems))
}

/// The manifest of a complete dataset; `None` when `dir` has no `manifest.json` (a dataset
/// still being generated).
pub fn read_manifest(dir: &Path) -> Result<Option<Manifest>, DataError> {
    let path = dir.join("manifest.json");
    match std::fs::read(&path) {
        Ok(bytes) => parse_manifest(&path, &bytes).map(Some),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(io_err(&path)(e)),
    }
}

/// The identity (`dataset.json`) of a dataset directory, complete or not.
pub fn read_identity(dir: &Path) -> Result<Identity, DataError> {
    let path = dir.join("dataset.json");
    let bytes = std::fs::read(&path).map_err(|e| {
        if e.kind() == std::io::ErrorKind::NotFound {
            DataError::Refused {
                path: dir.to_path_buf(),
                message: "has neither manifest.json nor dataset.json: not a sparsh dataset".into(),
            }
        } else {
            io_err(&path)(e)
        }
    })?;
    serde_json::from_slice(&bytes).map_err(|e| DataError::Format {
        path: path.clone(),
        message: e.to_string(),
    })
}

/// The shard layout recorded by sharded runs of a dataset still being generated, if any.
pub fn read_shard_layout(dir: &Path) -> Result<Option<ShardLayout>, DataError> {
    let path = dir.join(SHARDS_FILE);
    let bytes = match std::fs::read(&path) {
        Ok(bytes) => bytes,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(io_err(&path)(e)),
    };
    let layout: ShardLayout = serde_json::from_slice(&bytes).map_err(|e| DataError::Format {
        path: path.clone(),
        message: e.to_string(),
    })?;
    if layout.count == 0 {
        return Err(DataError::Format {
            path,
            message: "count: must be at least 1".into(),
        });
    }
    Ok(Some(layout))
}

/// Checks the files of sequence `sequence` of the dataset in `dir` against its record (and the
/// record against `manifest`, when given): `None` when the sequence is not recorded, else the
/// number of files checked (the record included) and the problems found.
pub fn check_part(
    dir: &Path,
    sequence: usize,
    manifest: Option<&Manifest>,
) -> Option<(usize, Vec<Problem>)> {
    let rel = Dataset::part_path(sequence);
    let bytes = std::fs::read(dir.join(&rel)).ok()?;
    let mut problems = Vec::new();
    let record_problem = |what: &'static str| Problem {
        file: rel.clone(),
        what,
    };
    if let Some(sum) = manifest.and_then(|m| m.files.get(&rel))
        && &sha256_hex(&bytes) != sum
    {
        problems.push(record_problem("corrupt (sha256 mismatch)"));
        return Some((1, problems));
    }
    let part = match serde_json::from_slice::<SequencePart>(&bytes) {
        Ok(part) if part.sequence == sequence => part,
        _ => return Some((1, vec![record_problem("unreadable record")])),
    };
    for (file, sum) in &part.files {
        if let Some(what) = check_file(dir, file, sum) {
            problems.push(Problem {
                file: file.clone(),
                what,
            });
        }
    }
    Some((1 + part.files.len(), problems))
}

/// `None` when `dir/rel` has sha256 `sum`, else what is wrong with it.
fn check_file(dir: &Path, rel: &str, sum: &str) -> Option<&'static str> {
    match std::fs::read(dir.join(rel)) {
        Err(_) => Some("missing"),
        Ok(data) if sha256_hex(&data) != sum => Some("corrupt (sha256 mismatch)"),
        Ok(_) => None,
    }
}

fn parse_manifest(path: &Path, bytes: &[u8]) -> Result<Manifest, DataError> {
    serde_json::from_slice(bytes).map_err(|e| DataError::Format {
        path: path.to_path_buf(),
        message: e.to_string(),
    })
}

fn remove_temporaries(dir: &Path) -> Result<(), DataError> {
    for entry in std::fs::read_dir(dir).map_err(io_err(dir))? {
        let path = entry.map_err(io_err(dir))?.path();
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
        if path.is_dir() {
            remove_temporaries(&path)?;
        } else if name.is_some_and(|n| n.starts_with('.') && n.ends_with(".tmp")) {
            std::fs::remove_file(&path).map_err(io_err(&path))?;
        }
    }
    Ok(())
}

fn pretty_json<T: Serialize>(value: &T) -> Vec<u8> {
    let mut json = serde_json::to_vec_pretty(value).expect("serialises");
    json.push(b'\n');
    json
}

/// Encodes an RGB image as PNG bytes.
pub fn encode_png(image: &RgbImage) -> Result<Vec<u8>, String> {
    let mut bytes = Vec::new();
    image
        .write_with_encoder(image::codecs::png::PngEncoder::new(&mut bytes))
        .map_err(|e| e.to_string())?;
    Ok(bytes)
}

/// Writes `bytes` to a temporary file beside `path` (named after the process, so concurrent
/// writers never share one), then renames it into place: `path` is either absent or complete.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), DataError> {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.{}.tmp", std::process::id()));
    std::fs::write(&tmp, bytes).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        io_err(path)(e)
    })?;
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        io_err(path)(e)
    })
}

fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}
