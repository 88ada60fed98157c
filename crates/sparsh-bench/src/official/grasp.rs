//! Feeling of Success grasp files (T4): `NNN.pkl`, one sequence per grasp and sensor; the
//! layout and how its labels are mapped are in the [module docs](super).

use std::path::Path;

use serde_pickle::Value;
use sparsh_ssl::data::Sequence;

use super::{Img, Want, field_1d, frames_of, get, prepare, read_dict, require};
use crate::Error;
use crate::labels::{FrameLabel, SequenceLabels};

/// Official split of the Feeling of Success files: 0–29 train, 30–35 test.
fn grasp_split(path: &Path) -> Option<bool> {
    let n: u32 = path.file_stem()?.to_str()?.parse().ok()?;
    match n {
        0..=29 => Some(false),
        30..=35 => Some(true),
        _ => None,
    }
}

pub(super) fn load_grasp_file(
    path: &Path,
    size: [usize; 2],
) -> Result<Vec<(Sequence, SequenceLabels)>, Error> {
    let d = read_dict(path)?;
    if get(&d, "is_gripping").is_none() {
        return Err(Error::file(
            path,
            "not a Feeling of Success grasp pickle: no `is_gripping` key",
        ));
    }
    let gripping = field_1d(require(&d, "is_gripping", path, "")?, Want::Flag, None)
        .map_err(|e| Error::file(path, format!("is_gripping: {e}")))?;
    let n = gripping.len();
    let names: Option<Vec<String>> = match get(&d, "object_name") {
        Some(Value::List(items)) if items.len() == n => items
            .iter()
            .map(|v| match v {
                Value::String(s) => Some(s.clone()),
                Value::Bytes(b) => Some(String::from_utf8_lossy(b).into_owned()),
                _ => None,
            })
            .collect(),
        _ => None,
    };
    let test = grasp_split(path);
    let mut out = Vec::with_capacity(2 * n);
    for sensor in ["gelsightA", "gelsightB"] {
        let mut stages = Vec::with_capacity(3);
        for stage in ["before", "during", "after"] {
            let key = format!("{sensor}_{stage}");
            let frames = frames_of(require(&d, &key, path, "")?)
                .map_err(|e| Error::file(path, format!("{key}: {e}")))?;
            if frames.len() != n {
                return Err(Error::file(
                    path,
                    format!("{key}: {} frames but {n} is_gripping labels", frames.len()),
                ));
            }
            stages.push(frames);
        }
        for (g, &grip) in gripping.iter().enumerate() {
            let picked: Vec<&Img> = stages.iter().map(|s| &s[g]).collect();
            let what = format!("{sensor} grasp {g}: ");
            let pre = prepare(&picked, None, size, path, &what)?;
            out.push((
                Sequence {
                    frames: Sequence::decoded(pre),
                    forces: None,
                    rest_frame: None,
                },
                SequenceLabels {
                    test,
                    class: names.as_ref().map(|v| v[g].clone()),
                    indenter: None,
                    outcome: Some(grip != 0.0),
                    frames: vec![FrameLabel::default(); 3],
                },
            ));
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use crate::official::load;
    use crate::official::tests::{SIZE, frames_list, s, write_value};
    use serde_pickle::Value as V;
    use std::collections::BTreeMap;

    #[test]
    fn grasp_files() {
        let tmp = tempfile::tempdir().unwrap();
        let mut d = BTreeMap::new();
        d.insert(s("is_gripping"), V::List(vec![V::Bool(true), V::I64(0)]));
        d.insert(
            s("object_name"),
            V::List(vec![V::String("mug".into()), V::String("ball".into())]),
        );
        for sensor in ["gelsightA", "gelsightB"] {
            for stage in ["before", "during", "after"] {
                d.insert(s(&format!("{sensor}_{stage}")), frames_list(&[1, 2]));
            }
        }
        write_value(&tmp.path().join("031.pkl"), &V::Dict(d));
        let data = load(tmp.path(), SIZE).unwrap();
        assert_eq!(data.labels.len(), 4);
        assert_eq!(data.dataset.num_frames(), 12);
        let outcomes: Vec<_> = data.labels.iter().map(|l| l.outcome).collect();
        assert_eq!(outcomes, [Some(true), Some(false), Some(true), Some(false)]);
        assert!(
            data.labels
                .iter()
                .all(|l| l.test == Some(true) && l.frames.len() == 3)
        );
        assert_eq!(data.labels[1].class.as_deref(), Some("ball"));
    }
}
