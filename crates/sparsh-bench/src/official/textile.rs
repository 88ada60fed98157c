//! Textile clips (T5): `{train,test}/<textile>/<clip>/` directories with `dataset_gelsight.pkl`
//! and `metadata.txt`, one sequence each; the layout and how its labels are mapped are in the
//! [module docs](super).

use std::path::Path;

use sparsh_ssl::data::Sequence;

use super::{Img, TEXTILE_FRAMES, TEXTILE_METADATA, frames_of, prepare, read_pickle, split_of};
use crate::Error;
use crate::labels::{FrameLabel, SequenceLabels};

/// `(label, class_name)` of a textile `metadata.txt`: `label: <int>` then `class_name: <name>`.
fn parse_metadata(text: &str) -> Result<(i64, Option<String>), String> {
    let mut lines = text.lines();
    let first = lines.next().unwrap_or("");
    let label = first
        .split("label:")
        .nth(1)
        .ok_or_else(|| format!("line 1: expected `label: <int>`, found {first:?}"))?
        .trim();
    let label = label
        .parse()
        .map_err(|_| format!("line 1: label: expected an integer, found {label:?}"))?;
    let name = lines
        .next()
        .and_then(|l| l.split("class_name:").nth(1))
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty());
    Ok((label, name))
}

pub(super) fn load_textile_clip(
    dir: &Path,
    size: [usize; 2],
) -> Result<(Sequence, SequenceLabels), Error> {
    let meta_path = dir.join(TEXTILE_METADATA);
    let text = std::fs::read_to_string(&meta_path).map_err(|e| Error::file(&meta_path, e))?;
    let (label, name) = parse_metadata(&text).map_err(|e| Error::file(&meta_path, e))?;
    let frames_path = dir.join(TEXTILE_FRAMES);
    let frames =
        frames_of(&read_pickle(&frames_path)?).map_err(|e| Error::file(&frames_path, e))?;
    if frames.is_empty() {
        return Err(Error::file(&frames_path, "the pickle holds no frames"));
    }
    let picked: Vec<&Img> = frames.iter().collect();
    let pre = prepare(&picked, None, size, &frames_path, "")?;
    let class = name.unwrap_or_else(|| label.to_string());
    Ok((
        Sequence {
            frames: Sequence::decoded(pre),
            forces: None,
            rest_frame: None,
        },
        SequenceLabels {
            test: split_of(dir, 4),
            class: Some(class),
            indenter: None,
            outcome: None,
            frames: vec![FrameLabel::default(); picked.len()],
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::official::load;
    use crate::official::tests::{H_, P, SIZE, W, png_uniform, write_p, write_value};
    use serde_pickle::Value as V;

    #[test]
    fn textile_clips() {
        let tmp = tempfile::tempdir().unwrap();
        let a = tmp.path().join("train/cotton/clip_0");
        write_value(
            &a.join(TEXTILE_FRAMES),
            &V::List((0..4).map(|_| V::Bytes(png_uniform(200))).collect()),
        );
        std::fs::write(a.join(TEXTILE_METADATA), "label: 0\nclass_name: cotton\n").unwrap();
        // Frames as one N×H×W×3 uint8 numpy array.
        let b = tmp.path().join("test/broadcloth/clip_3");
        write_p(
            &b.join(TEXTILE_FRAMES),
            &P::Nd(
                "u1",
                vec![2, H_ as usize, W as usize, 3],
                vec![40; 2 * (W * H_ * 3) as usize],
            ),
        );
        std::fs::write(
            b.join(TEXTILE_METADATA),
            "label: 5\nclass_name: broad cloth\n",
        )
        .unwrap();
        let data = load(tmp.path(), SIZE).unwrap();
        assert_eq!(data.labels.len(), 2);
        assert_eq!(data.labels[0].class.as_deref(), Some("broad cloth"));
        assert_eq!(data.labels[0].test, Some(true));
        assert_eq!(data.labels[0].frames.len(), 2);
        assert_eq!(data.labels[1].class.as_deref(), Some("cotton"));
        assert_eq!(data.labels[1].test, Some(false));
        assert_eq!(data.labels[1].frames, vec![FrameLabel::default(); 4]);
        // No background: the raw image.
        assert!(
            data.dataset.sequences[1].frames[0]
                .decoded()
                .unwrap()
                .iter()
                .all(|&v| v == 200.0 / 255.0)
        );
        assert!(
            data.dataset.sequences[0].frames[1]
                .decoded()
                .unwrap()
                .iter()
                .all(|&v| v == 40.0 / 255.0)
        );
    }
}
