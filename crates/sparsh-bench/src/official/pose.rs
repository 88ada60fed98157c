//! Pose bags (T3): `{train,test}/<object>/bag_NN.pkl`, one sequence each; the layout and how
//! its labels are mapped are in the [module docs](super).

use std::path::{Path, PathBuf};

use sparsh_ssl::data::Sequence;

use super::{
    Img, Want, file_name, frames_of, one_line, prepare, read_dict, require, split_of, to_nd,
};
use crate::Error;
use crate::labels::{FrameLabel, SequenceLabels};

/// The finger whose frames and poses the official pose task uses (`finger_type: ring`).
pub const POSE_FINGER: &str = "ring";
/// The window of the official pose labels, in samples (`rel_pose_t_window: 5`).
pub const POSE_WINDOW: usize = 5;

/// Per-frame changes `d` whose sum over every `w` consecutive frames `t−w+1..=t` (frames before
/// the first counted as still) equals `window[t]`: `d[t] = window[t] − window[t−1] + d[t−w]`.
pub fn per_frame_from_window(window: &[[f64; 3]], w: usize) -> Vec<[f64; 3]> {
    let mut d: Vec<[f64; 3]> = Vec::with_capacity(window.len());
    for t in 0..window.len() {
        let prev = if t > 0 { window[t - 1] } else { [0.0; 3] };
        let back = if w > 0 && t >= w { d[t - w] } else { [0.0; 3] };
        d.push(std::array::from_fn(|c| window[t][c] - prev[c] + back[c]));
    }
    d
}

/// The official `[tx, ty, yaw°]` of a 4×4 transform (row-major): `translation[1]`,
/// `translation[0]`, and the z angle of its extrinsic `xyz` Euler angles.
fn pose_target(m: &[f64]) -> [f64; 3] {
    let yaw = m[4].atan2(m[0]).to_degrees();
    [m[7], m[3], yaw]
}

fn pose_background(bag: &Path) -> Option<PathBuf> {
    bag.ancestors()
        .skip(1)
        .take(5)
        .map(|a| a.join("bgs").join(format!("digit_{POSE_FINGER}.png")))
        .find(|p| p.is_file())
}

pub(super) fn load_pose_bag(
    path: &Path,
    size: [usize; 2],
) -> Result<(Sequence, SequenceLabels), Error> {
    let d = read_dict(path)?;
    let frames_key = format!("digit_{POSE_FINGER}");
    let pose_key = format!("object_{POSE_FINGER}_rel_pose_n{POSE_WINDOW}");
    let frames = frames_of(require(&d, &frames_key, path, "")?)
        .map_err(|e| Error::file(path, format!("{frames_key}: {e}")))?;
    let poses = to_nd(require(&d, &pose_key, path, "")?, Want::Float)
        .map_err(|e| Error::file(path, format!("{pose_key}: {e}")))?;
    if poses.shape.len() != 3 || poses.shape[1..] != [4, 4] {
        return Err(Error::file(
            path,
            format!(
                "{pose_key}: expected N×4×4 transforms, found shape {:?}",
                poses.shape
            ),
        ));
    }
    // The official loader cuts both to the shorter.
    let n = frames.len().min(poses.shape[0]);
    if n == 0 {
        return Err(Error::file(path, "the bag holds no labelled frames"));
    }
    let window: Vec<[f64; 3]> = poses
        .data
        .chunks_exact(16)
        .take(n)
        .map(pose_target)
        .collect();
    let changes = per_frame_from_window(&window, POSE_WINDOW);
    let bg = match pose_background(path) {
        Some(p) => image::open(&p)
            .map(|i| i.to_rgb8())
            .map_err(|e| Error::file(&p, format!("cannot read background: {}", one_line(e))))?,
        None => frames[0]
            .decode()
            .map_err(|e| Error::file(path, format!("{frames_key}: frame 0: {e}")))?,
    };
    let picked: Vec<&Img> = frames.iter().take(n).collect();
    let pre = prepare(&picked, Some(&bg), size, path, &format!("{frames_key}: "))?;
    let class = path
        .parent()
        .map(|p| file_name(p).to_string())
        .filter(|c| !c.is_empty());
    Ok((
        Sequence {
            frames: Sequence::decoded(pre),
            forces: None,
            rest_frame: None,
        },
        SequenceLabels {
            test: split_of(path, 4),
            class,
            indenter: None,
            outcome: None,
            frames: changes
                .into_iter()
                .map(|c| FrameLabel {
                    pose_change_se2: Some(c),
                    ..FrameLabel::default()
                })
                .collect(),
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::official::load;
    use crate::official::tests::{Pickler, SIZE, f8, jpeg, png_uniform};

    /// A homogeneous transform (row-major) rotating `yaw` degrees about z and moving by `t`.
    fn transform(t: [f64; 3], yaw: f64) -> Vec<f64> {
        let (s, c) = yaw.to_radians().sin_cos();
        vec![
            c, -s, 0.0, t[0], s, c, 0.0, t[1], 0.0, 0.0, 1.0, t[2], 0.0, 0.0, 0.0, 1.0,
        ]
    }

    #[test]
    fn pose_bags() {
        let tmp = tempfile::tempdir().unwrap();
        // True per-frame changes [tx, ty, yaw] (tx is the official translation[1]).
        let truth: Vec<[f64; 3]> = (0..6)
            .map(|t| [0.1 * t as f64, -0.05 * t as f64, 0.02 * (t as f64 - 2.0)])
            .collect();
        let window: Vec<[f64; 3]> = (0..6usize)
            .map(|t| {
                let lo = t.saturating_sub(POSE_WINDOW - 1);
                std::array::from_fn(|c| truth[lo..=t].iter().map(|d| d[c]).sum())
            })
            .collect();
        let mats: Vec<f64> = window
            .iter()
            .flat_map(|w| transform([w[1], w[0], 0.3], w[2]))
            .collect();
        let bag = tmp.path().join("test/sugar/bag_00.pkl");

        // Frames as a plain list of JPEG bytes, written beside the numpy poses.
        let mut w = Pickler::default();
        w.out.extend([0x80, 3, b'}', b'(']);
        w.str("digit_ring");
        w.out.extend([b']', b'(']);
        for k in 0..7u8 {
            let b = jpeg(k);
            w.out.push(b'B');
            w.out.extend((b.len() as u32).to_le_bytes());
            w.out.extend(b);
        }
        w.out.push(b'e');
        w.str(&format!("object_ring_rel_pose_n{POSE_WINDOW}"));
        w.obj(&f8(&[6, 4, 4], &mats));
        w.str("object_index_rel_pose_n5");
        w.obj(&f8(&[1, 4, 4], &transform([0.0; 3], 0.0)));
        w.out.extend([b'u', b'.']);
        std::fs::create_dir_all(bag.parent().unwrap()).unwrap();
        std::fs::write(&bag, w.out).unwrap();
        let bg = tmp.path().join("bgs/digit_ring.png");
        std::fs::create_dir_all(bg.parent().unwrap()).unwrap();
        std::fs::write(&bg, png_uniform(90)).unwrap();

        let data = load(tmp.path(), SIZE).unwrap();
        assert_eq!(data.labels.len(), 1);
        let l = &data.labels[0];
        assert_eq!(l.test, Some(true));
        assert_eq!(l.class.as_deref(), Some("sugar"));
        // 7 frames, 6 poses: cut to 6 as the official loader does.
        assert_eq!(l.frames.len(), 6);
        assert_eq!(data.dataset.sequences[0].frames.len(), 6);
        for (t, f) in l.frames.iter().enumerate() {
            let d = f.pose_change_se2.unwrap();
            for c in 0..3 {
                assert!(
                    (d[c] - truth[t][c]).abs() < 1e-9,
                    "frame {t}: {d:?} vs {:?}",
                    truth[t]
                );
            }
        }
        // Summed over the last 5 frames, the official window label.
        let sum: f64 = l.frames[1..6]
            .iter()
            .map(|f| f.pose_change_se2.unwrap()[0])
            .sum();
        assert!((sum - window[5][0]).abs() < 1e-9);
        // the pose task's 5-frame change is the official label
        let pose = crate::tacbench::tasks::extract(
            crate::tacbench::tasks::TaskKind::Pose,
            &data.labels,
            0,
            1,
        )
        .unwrap();
        assert_eq!(pose.samples[0].frame, 5);
        let crate::tacbench::tasks::Target::Pose(p) = pose.samples[0].target else {
            panic!("a pose target");
        };
        for c in 0..3 {
            assert!(
                (p[c] - window[5][c]).abs() < 1e-9,
                "{p:?} vs {:?}",
                window[5]
            );
        }
    }

    #[test]
    fn window_decomposition() {
        let window = [
            [1.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [3.0, 1.0, 0.0],
            [3.0, 1.0, 0.0],
        ];
        let d = per_frame_from_window(&window, 2);
        for t in 0..window.len() {
            let s: f64 = d[t.saturating_sub(1)..=t].iter().map(|x| x[0]).sum();
            assert_eq!(s, window[t][0]);
        }
        assert_eq!(d[0], [1.0, 0.0, 0.0]);
    }
}
