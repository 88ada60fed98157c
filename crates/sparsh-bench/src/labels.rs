//! Per-frame labels of a tactile dataset, whatever its layout: a directory written by
//! `sparsh generate` (`labels.jsonl`) or the official TacBench pickles ([`crate::official`]).
//! The frames themselves are loaded by `sparsh_ssl::data`, sequence for sequence in the same
//! order, so `LabelledData::labels[s]` labels `LabelledData::dataset.sequences[s]`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use sparsh_ssl::data::Dataset;

use crate::Error;

/// Mechanical stick/slip state of a frame (the contact solver's, from the share of the contact
/// area that slips).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum SlipState {
    /// Nothing touches the gel.
    NoContact,
    /// The whole contact sticks.
    Stick,
    /// Part of the contact slips (Cattaneo–Mindlin annulus).
    Partial,
    /// The whole contact slides.
    Gross,
}

impl SlipState {
    /// Parses a label's `slip_state`.
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "no_contact" => Some(Self::NoContact),
            "stick" => Some(Self::Stick),
            "partial" => Some(Self::Partial),
            "gross" => Some(Self::Gross),
            _ => None,
        }
    }
}

/// What is known of one frame; a layout fills what it records.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FrameLabel {
    /// Total contact force `[Fx, Fy, Fz]` (N), Fz > 0 pressing.
    pub force_n: Option<[f64; 3]>,
    /// Change of the force since frame t − 5 (N).
    pub delta_force_n: Option<[f64; 3]>,
    /// Mechanical stick/slip state.
    pub slip_state: Option<SlipState>,
    /// The official slip label: ‖(Fx, Fy)‖ > 1.6 Fz (or the dataset's own slip flag).
    pub slip_cone: Option<bool>,
    /// SE(2) motion of the object relative to the sensor since the previous frame:
    /// `[Δx mm, Δy mm, Δθ deg]`.
    pub pose_change_se2: Option<[f64; 3]>,
    /// Position of the indenter's tip in the sensor plane (mm).
    pub position_mm: Option<[f64; 2]>,
}

/// The labels of one sequence.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SequenceLabels {
    /// The split the data assign it to: `Some(true)` held out for testing (e.g. an indenter
    /// shape never trained on), `Some(false)` training, `None` unassigned.
    pub test: Option<bool>,
    /// Its class (the family name of a generated sequence, the textile of the official set).
    pub class: Option<String>,
    /// Its indenter's name, where the data record it (see [`sparsh_data::Label::indenter`]).
    pub indenter: Option<String>,
    /// The outcome of the whole sequence, when the layout records one (a grasp's success).
    pub outcome: Option<bool>,
    /// One entry per frame.
    pub frames: Vec<FrameLabel>,
}

/// Frames and labels of one dataset.
#[derive(Debug, Clone)]
pub struct LabelledData {
    /// Where it was read from.
    pub source: PathBuf,
    /// The preprocessed frames.
    pub dataset: Dataset,
    /// The labels, one entry per sequence of `dataset`.
    pub labels: Vec<SequenceLabels>,
}

/// Loads a dataset and its labels at frame size `size` (`[height, width]`): a directory
/// written by `sparsh generate` (it has `labels.jsonl`), else an official TacBench layout.
pub fn load(path: &Path, size: [usize; 2]) -> Result<LabelledData, Error> {
    if path.join("labels.jsonl").is_file() {
        return load_generated(path, size);
    }
    crate::official::load(path, size)
}

/// Loads a directory written by `sparsh generate`.
pub fn load_generated(dir: &Path, size: [usize; 2]) -> Result<LabelledData, Error> {
    let labels = read_generated_labels(dir)?;
    let dataset = Dataset::load_generated(dir, size)?.into_decoded()?;
    if dataset.sequences.len() != labels.len() {
        return Err(Error::file(
            dir.join("labels.jsonl"),
            format!(
                "{} sequences of labels but {} of frames",
                labels.len(),
                dataset.sequences.len()
            ),
        ));
    }
    Ok(LabelledData {
        source: dir.to_path_buf(),
        dataset,
        labels,
    })
}

/// The rows of `dir/labels.jsonl` as written, one list per sequence in ascending sequence order,
/// each sorted by frame (the order `sparsh_ssl::data::Dataset::load_generated` reads frames in);
/// never empty.
pub fn read_label_rows(dir: &Path) -> Result<Vec<Vec<sparsh_data::Label>>, Error> {
    let path = dir.join("labels.jsonl");
    let text = std::fs::read_to_string(&path).map_err(|e| Error::file(&path, e))?;
    let mut by_seq: BTreeMap<usize, Vec<sparsh_data::Label>> = BTreeMap::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let row: sparsh_data::Label = serde_json::from_str(line)
            .map_err(|e| Error::file(&path, format!("line {}: {e}", i + 1)))?;
        by_seq.entry(row.sequence).or_default().push(row);
    }
    if by_seq.is_empty() {
        return Err(Error::file(&path, "no frames"));
    }
    Ok(by_seq
        .into_values()
        .map(|mut rows| {
            rows.sort_by_key(|r| r.frame_in_sequence);
            rows
        })
        .collect())
}

/// The label rows of `dir/labels.jsonl`, grouped by sequence in ascending sequence order and by
/// frame within each (the order `sparsh_ssl::data::Dataset::load_generated` reads frames in).
pub fn read_generated_labels(dir: &Path) -> Result<Vec<SequenceLabels>, Error> {
    let path = dir.join("labels.jsonl");
    read_label_rows(dir)?
        .into_iter()
        .map(|rows| {
            let first = &rows[0];
            let test = match first.split.as_str() {
                "train" => false,
                "test" => true,
                other => {
                    return Err(Error::file(
                        &path,
                        format!(
                            "frame {}: split: expected train or test, got {other:?}",
                            first.frame
                        ),
                    ));
                }
            };
            let frames = rows
                .iter()
                .map(|r| {
                    let state = SlipState::parse(&r.slip_state).ok_or_else(|| {
                        Error::file(
                            &path,
                            format!(
                                "frame {}: slip_state: unknown state {:?}",
                                r.frame, r.slip_state
                            ),
                        )
                    })?;
                    Ok(FrameLabel {
                        force_n: Some(r.force_n),
                        delta_force_n: Some(r.delta_force_n),
                        slip_state: Some(state),
                        slip_cone: Some(r.slip_cone),
                        pose_change_se2: Some(r.pose_change_se2),
                        position_mm: Some([r.pose.position_mm[0], r.pose.position_mm[1]]),
                    })
                })
                .collect::<Result<Vec<_>, Error>>()?;
            Ok(SequenceLabels {
                test: Some(test),
                class: Some(first.family.clone()),
                indenter: first.indenter.clone(),
                outcome: None,
                frames,
            })
        })
        .collect()
}
