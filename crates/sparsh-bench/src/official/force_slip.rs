//! Force / slip batches (T1, T2): `<indenter>/batch_<k>/` directories of frame pickles and
//! `dataset_slip_forces.pkl`; the layout and how its labels are mapped are in the
//! [module docs](super).

use std::collections::BTreeMap;
use std::path::Path;

use serde_pickle::{HashableValue, Value};
use sparsh_ssl::data::Sequence;

use super::{
    FORCE_LABELS, Want, field_1d, file_name, frames_of, get, key_name, prepare, read_dict,
    read_pickle, require, split_of, to_nd, type_name,
};
use crate::Error;
use crate::labels::{FrameLabel, SequenceLabels};

/// The frame offset of the official force change (`frame_stride: 5`).
pub const FORCE_DELTA: usize = 5;

/// Official test batches: `flat/batch_1` (T1 force), `*/batch_test` (T2 slip).
fn force_test_batch(indenter: &str, batch: &str) -> bool {
    (indenter == "flat" && batch == "batch_1") || batch == "batch_test"
}

pub(super) fn load_force_batch(
    dir: &Path,
    size: [usize; 2],
) -> Result<Vec<(Sequence, SequenceLabels)>, Error> {
    let label_path = dir.join(FORCE_LABELS);
    let mut pickles = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| Error::file(dir, e))? {
        let p = entry.map_err(|e| Error::file(dir, e))?.path();
        let name = file_name(&p);
        if name.starts_with("dataset_") && name.ends_with(".pkl") && name != FORCE_LABELS {
            pickles.push(p);
        }
    }
    pickles.sort();
    if pickles.is_empty() {
        return Err(Error::file(
            dir,
            format!("no frame pickles dataset_<sensor>_NN.pkl beside {FORCE_LABELS}"),
        ));
    }
    let mut frames = Vec::new();
    for p in &pickles {
        let v = read_pickle(p)?;
        frames.extend(frames_of(&v).map_err(|e| Error::file(p, e))?);
    }
    let root = read_dict(&label_path)?;
    let bad = |msg: String| Error::file(&label_path, msg);
    let in_contact = field_1d(
        require(&root, "in_contact", &label_path, "")?,
        Want::Flag,
        None,
    )
    .map_err(|e| bad(format!("in_contact: {e}")))?;
    let bg_index = in_contact
        .iter()
        .position(|&c| c == 0.0)
        .ok_or_else(|| bad("in_contact: no frame without contact to take as background".into()))?;
    let bg_img = frames
        .get(bg_index)
        .ok_or_else(|| {
            bad(format!(
                "in_contact: background frame {bg_index} beyond the {} frames of the \
                 dataset_*.pkl files",
                frames.len()
            ))
        })?
        .decode()
        .map_err(|e| bad(format!("background frame {bg_index}: {e}")))?;

    let trajectories: Vec<(String, &BTreeMap<HashableValue, Value>)> =
        match require(&root, "trajectories", &label_path, "")? {
            Value::Dict(d) if get(d, "indexes").is_some() => vec![("0".into(), d)],
            Value::Dict(d) => d
                .iter()
                .map(|(k, v)| match v {
                    Value::Dict(t) => Ok((key_name(k), t)),
                    other => Err(bad(format!(
                        "trajectories[{}]: expected a dictionary, found {}",
                        key_name(k),
                        type_name(other)
                    ))),
                })
                .collect::<Result<_, _>>()?,
            Value::List(items) => items
                .iter()
                .enumerate()
                .map(|(k, v)| match v {
                    Value::Dict(t) => Ok((k.to_string(), t)),
                    other => Err(bad(format!(
                        "trajectories[{k}]: expected a dictionary, found {}",
                        type_name(other)
                    ))),
                })
                .collect::<Result<_, _>>()?,
            other => {
                return Err(bad(format!(
                    "trajectories: expected a dictionary, found {}",
                    type_name(other)
                )));
            }
        };

    let batch = file_name(dir).to_string();
    let indenter = dir
        .parent()
        .map(|p| file_name(p).to_string())
        .unwrap_or_default();
    let class = if indenter.is_empty() {
        batch.clone()
    } else {
        format!("{indenter}/{batch}")
    };
    let test = force_test_batch(&indenter, &batch) || split_of(dir, 3) == Some(true);

    let mut out = Vec::with_capacity(trajectories.len());
    for (key, traj) in trajectories {
        let ctx = format!("trajectories[{key}]: ");
        let indexes = field_1d(
            require(traj, "indexes", &label_path, &ctx)?,
            Want::Int,
            None,
        )
        .map_err(|e| bad(format!("{ctx}indexes: {e}")))?;
        let n = indexes.len();
        let forces = to_nd(require(traj, "forces", &label_path, &ctx)?, Want::Float)
            .map_err(|e| bad(format!("{ctx}forces: {e}")))?;
        if forces.shape != [n, 3] {
            return Err(bad(format!(
                "{ctx}forces: expected {n}×3 values (one row per index), found shape {:?}",
                forces.shape
            )));
        }
        let slip = field_1d(
            require(traj, "slip_label", &label_path, &ctx)?,
            Want::Flag,
            Some(n),
        )
        .map_err(|e| bad(format!("{ctx}slip_label: {e}")))?;
        let mut picked = Vec::with_capacity(n);
        for (k, &i) in indexes.iter().enumerate() {
            if i < 0.0 || i.fract() != 0.0 || i as usize >= frames.len() {
                return Err(bad(format!(
                    "{ctx}indexes[{k}] = {i} is not a frame of the {} frames of the \
                     dataset_*.pkl files",
                    frames.len()
                )));
            }
            picked.push(&frames[i as usize]);
        }
        let rows: Vec<[f64; 3]> = forces
            .data
            .chunks_exact(3)
            .map(|r| [r[0], r[1], r[2]])
            .collect();
        let frame_labels = (0..n)
            .map(|t| {
                let prev = rows[t.saturating_sub(FORCE_DELTA)];
                FrameLabel {
                    force_n: Some(rows[t]),
                    delta_force_n: Some(std::array::from_fn(|c| rows[t][c] - prev[c])),
                    slip_cone: Some(slip[t] != 0.0),
                    ..FrameLabel::default()
                }
            })
            .collect();
        let pre = prepare(&picked, Some(&bg_img), size, &label_path, &ctx)?;
        out.push((
            Sequence {
                frames: Sequence::decoded(pre),
                forces: Some(rows.iter().map(|r| r.map(|c| c as f32)).collect()),
                rest_frame: None,
            },
            SequenceLabels {
                test: Some(test),
                class: Some(class.clone()),
                indenter: None,
                outcome: None,
                frames: frame_labels,
            },
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::official::load;
    use crate::official::tests::{SIZE, frames_list, write_force_batch, write_value};

    #[test]
    fn force_slip_batches() {
        let tmp = tempfile::tempdir().unwrap();
        write_force_batch(&tmp.path().join("flat/batch_1"));
        write_force_batch(&tmp.path().join("sphere/batch_2"));
        let data = load(tmp.path(), SIZE).unwrap();
        assert_eq!(data.labels.len(), 4);
        assert_eq!(data.dataset.sequences.len(), 4);
        assert_eq!(data.dataset.num_frames(), 12);
        let classes: Vec<_> = data
            .labels
            .iter()
            .map(|l| l.class.clone().unwrap())
            .collect();
        assert_eq!(
            classes,
            [
                "flat/batch_1",
                "flat/batch_1",
                "sphere/batch_2",
                "sphere/batch_2"
            ]
        );
        let tests: Vec<_> = data.labels.iter().map(|l| l.test).collect();
        assert_eq!(tests, [Some(true), Some(true), Some(false), Some(false)]);
        let t0 = &data.labels[0].frames;
        assert_eq!(t0.len(), 3);
        assert_eq!(t0[1].force_n, Some([0.3, -0.2, 1.5]));
        assert_eq!(t0[2].force_n, Some([2.0, 0.0, 1.0]));
        let slips: Vec<_> = t0.iter().map(|f| f.slip_cone.unwrap()).collect();
        assert_eq!(slips, [false, false, true]);
        // ΔF over 5 samples, clipped to the first sample.
        let d = t0[2].delta_force_n.unwrap();
        assert!((d[0] - 1.9).abs() < 1e-12 && (d[1] + 0.2).abs() < 1e-12 && d[2].abs() < 1e-12);
        let t1 = &data.labels[1].frames;
        assert_eq!(t1[2].force_n, Some([1.0, 1.0, 0.5]));
        assert_eq!(
            t1.iter().map(|f| f.slip_cone.unwrap()).collect::<Vec<_>>(),
            [false, false, true]
        );
        assert_eq!(t1[0].pose_change_se2, None);
        let seq = &data.dataset.sequences[0];
        assert_eq!(seq.forces.as_ref().unwrap()[1], [0.3, -0.2, 1.5]);
        assert_eq!(
            seq.frames[0].decoded().unwrap().len(),
            3 * SIZE[0] * SIZE[1]
        );
        // Trajectory 1 starts with frame 0, the background: a uniform 0.5 difference.
        let first = data.dataset.sequences[1].frames[0].decoded().unwrap();
        assert!(first.iter().all(|&v| v == 127.0 / 255.0));
        assert!(
            data.dataset.sequences[0].frames[0]
                .decoded()
                .unwrap()
                .iter()
                .any(|&v| v != 127.0 / 255.0)
        );
        // The label file itself selects its batch.
        let one = load(&tmp.path().join("sphere/batch_2").join(FORCE_LABELS), SIZE).unwrap();
        assert_eq!(one.labels.len(), 2);
        assert_eq!(one.labels[0].test, Some(false));
        let frame_file = tmp.path().join("sphere/batch_2/dataset_digit_01.pkl");
        assert_eq!(load(&frame_file, SIZE).unwrap().labels, one.labels);
        // the TacBench tasks read these labels: force and slip (the cone label only), not pose
        use crate::tacbench::tasks::{Target, TaskKind, extract};
        let force = extract(TaskKind::Force, &data.labels, 0, 1).unwrap();
        assert_eq!(force.samples.len(), 12);
        assert_eq!(force.samples[1].target, Target::Force([0.3, -0.2, 1.5]));
        let slip = extract(TaskKind::Slip, &data.labels, 0, 1).unwrap();
        assert!(matches!(
            slip.samples[2].target,
            Target::Slip {
                cone: true,
                state: None,
                ..
            }
        ));
        let err = extract(TaskKind::Pose, &data.labels, 0, 1).unwrap_err();
        assert!(err.contains("pose_change_se2"), "{err}");
    }

    #[test]
    fn force_batch_as_sparsh_export_writes_it() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("sim/batch_test");
        write_value(&dir.join("dataset_0.pkl"), &frames_list(&[7, 8, 9]));
        sparsh_data::sparsh_pkl::write_slip_forces(
            &dir.join(FORCE_LABELS),
            &sparsh_data::sparsh_pkl::SlipForces {
                in_contact: vec![false, true, true],
                trajectories: vec![sparsh_data::sparsh_pkl::Trajectory {
                    indexes: vec![0, 1, 2],
                    forces: vec![[0.0; 3], [0.1, 0.0, 1.0], [2.0, 0.0, 1.0]],
                    slip_label: vec![0, 0, 1],
                }],
            },
        )
        .unwrap();
        let data = load(&dir, SIZE).unwrap();
        assert_eq!(data.labels.len(), 1);
        assert_eq!(data.labels[0].test, Some(true));
        assert_eq!(data.labels[0].class.as_deref(), Some("sim/batch_test"));
        let f = &data.labels[0].frames;
        assert_eq!(f.len(), 3);
        assert_eq!(f[1].force_n, Some([0.1, 0.0, 1.0]));
        assert_eq!(f[2].slip_cone, Some(true));
    }
}
