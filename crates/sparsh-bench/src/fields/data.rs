//! Frame pairs for the field decoders, and their ground truth.
//!
//! [`FramePairs`] holds what training sees: the preprocessed frames of a dataset written by
//! `sparsh generate` and the pairs `(I_t, I_{t−k})`. Building it never opens `fields/`: the
//! self-supervised decoders cannot read a field label. [`GroundTruth`] reads the EXR fields of
//! chosen pairs, mapped into the input geometry, for scoring and for the supervised ceiling.

use std::path::{Path, PathBuf};

use sparsh_ssl::data::{Dataset, Frame};

use super::geometry::InputGeometry;
use crate::Error;

/// One frame pair: frame `t` of sequence `sequence` and frame `t − offset`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pair {
    /// Sequence index (into [`FramePairs::sequences`]).
    pub sequence: usize,
    /// Frame index within the sequence.
    pub t: usize,
}

/// What is known of a sequence without its fields.
#[derive(Debug, Clone)]
pub struct SequenceInfo {
    /// Held out for testing (its indenter shape is never trained on).
    pub test: bool,
    /// Held out for the in-distribution test: a sequence of a training shape that no model
    /// trains or validates on.
    pub seen_test: bool,
    /// Family name.
    pub family: String,
    /// Dataset frame index of each frame (names `frames/` and `fields/` files).
    pub frame_index: Vec<usize>,
    /// Pixel pitch (mm per frame pixel).
    pub mm_per_px: Option<f64>,
    /// Marker centres per frame (frame pixels), empty for markerless gels.
    pub markers_px: Vec<Vec<[f64; 2]>>,
    /// Map from frame pixels to input pixels.
    pub geometry: InputGeometry,
}

impl SequenceInfo {
    /// Whether the gel prints markers.
    pub fn has_markers(&self) -> bool {
        self.markers_px.first().is_some_and(|m| !m.is_empty())
    }
}

/// Preprocessed frames and the pairs drawn from them.
#[derive(Debug, Clone)]
pub struct FramePairs {
    /// The dataset directory.
    pub dir: PathBuf,
    /// Frames, background-subtracted and resized (`sparsh_ssl::data`).
    pub dataset: Dataset,
    /// Per sequence, in the order of `dataset.sequences`.
    pub sequences: Vec<SequenceInfo>,
    /// Frames back from `t` to the pair's earlier frame.
    pub offset: usize,
    /// Training pairs (sequences of the `train` split).
    pub train: Vec<Pair>,
    /// Held-out pairs (sequences of the `test` split).
    pub test: Vec<Pair>,
    /// Held-out pairs of the training shapes (every `seen_test_period`-th sequence of the
    /// `train` split; empty without one).
    pub seen: Vec<Pair>,
}

impl FramePairs {
    /// Loads `dir` at input size `size` (`[height, width]`) and takes every `frame_stride`-th
    /// frame `t ≥ offset` of each sequence as a pair `(t, t − offset)`. With
    /// `seen_test_period` n ≥ 2, the training split's sequences n/2, n/2 + n, n/2 + 2n, … (in
    /// dataset order) are held out as the in-distribution test ([`FramePairs::seen`]); 0: none.
    /// Reads `labels.jsonl`, `frames/` and `backgrounds/` only.
    pub fn load(
        dir: &Path,
        size: [usize; 2],
        offset: usize,
        frame_stride: usize,
        seen_test_period: usize,
    ) -> Result<Self, Error> {
        let labels_path = dir.join("labels.jsonl");
        if !labels_path.is_file() {
            return Err(Error::file(
                dir,
                "not a dataset written by sparsh generate (no labels.jsonl)",
            ));
        }
        let label_rows = crate::labels::read_label_rows(dir)?;
        let dataset = Dataset::load_generated(dir, size)?.into_decoded()?;
        let mut sequences = Vec::with_capacity(label_rows.len());
        for rows in label_rows {
            let first = &rows[0];
            let frame_png = dir.join("frames").join(format!("{:06}.png", first.frame));
            let (fw, fh) =
                image::image_dimensions(&frame_png).map_err(|e| Error::file(&frame_png, e))?;
            sequences.push(SequenceInfo {
                test: first.split == "test",
                seen_test: false,
                family: first.family.clone(),
                frame_index: rows.iter().map(|r| r.frame).collect(),
                mm_per_px: first.mm_per_px,
                markers_px: rows.iter().map(|r| r.markers_px.clone()).collect(),
                geometry: InputGeometry::new(fw as usize, fh as usize, size),
            });
        }
        if sequences.len() != dataset.sequences.len() {
            return Err(Error::file(
                &labels_path,
                format!(
                    "{} sequences of labels but {} of frames",
                    sequences.len(),
                    dataset.sequences.len()
                ),
            ));
        }
        if seen_test_period >= 2 {
            for (rank, info) in sequences.iter_mut().filter(|s| !s.test).enumerate() {
                info.seen_test = rank % seen_test_period == seen_test_period / 2;
            }
        }
        let (mut train, mut test, mut seen) = (Vec::new(), Vec::new(), Vec::new());
        for (s, info) in sequences.iter().enumerate() {
            let n = dataset.sequences[s].frames.len();
            for t in (offset..n).step_by(frame_stride.max(1)) {
                let pair = Pair { sequence: s, t };
                if info.test {
                    test.push(pair);
                } else if info.seen_test {
                    seen.push(pair);
                } else {
                    train.push(pair);
                }
            }
        }
        if train.is_empty() || test.is_empty() {
            return Err(Error::file(
                &labels_path,
                format!(
                    "the field probe needs sequences of both splits longer than {offset} frames \
                     ({} train pairs, {} test pairs)",
                    train.len(),
                    test.len()
                ),
            ));
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            dataset,
            sequences,
            offset,
            train,
            test,
            seen,
        })
    }

    /// `[height, width]` of the input.
    pub fn size(&self) -> [usize; 2] {
        self.dataset.size
    }

    /// The inputs `I_t ⊕ I_{t−k}` of `rows` of `list`, `[PAIR_CHANNELS, height, width]` each,
    /// concatenated.
    pub fn pair_inputs(&self, list: &[Pair], rows: &[usize]) -> Vec<f32> {
        rows.iter()
            .flat_map(|&i| {
                let (now, before) = self.frames(list[i]);
                now.iter().chain(before.iter()).copied()
            })
            .collect()
    }

    /// Frames `t` and `t − offset` of a pair, `[3, height, width]` each.
    pub fn frames(&self, p: Pair) -> (&Frame, &Frame) {
        let seq = &self.dataset.sequences[p.sequence];
        let frame = |t: usize| {
            seq.frames[t]
                .decoded()
                .expect("FramePairs::load decodes every frame")
        };
        (frame(p.t), frame(p.t - self.offset))
    }
}

/// The ground truth of one pair in input pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct PairTruth {
    /// Pressure at frame t (kPa).
    pub pressure_kpa: Vec<f32>,
    /// Indentation −u_z at frame t (mm; positive where the gel is pushed in).
    pub indentation_mm: Vec<f32>,
    /// Contact at frame t (1 inside).
    pub contact: Vec<bool>,
    /// |q| at frame t (kPa).
    pub shear_traction_kpa: Vec<f32>,
    /// Lateral displacement change from t − k to t, `[dx, dy]` per pixel (input pixels).
    pub flow_px: Vec<[f32; 2]>,
}

impl PairTruth {
    /// Whether frame t is in contact anywhere.
    pub fn in_contact(&self) -> bool {
        self.contact.iter().any(|&c| c)
    }
}

/// Reads the ground truth of pairs on demand.
#[derive(Debug)]
pub struct GroundTruth<'a> {
    data: &'a FramePairs,
}

impl<'a> GroundTruth<'a> {
    /// Ground truth for the pairs of `data`.
    pub fn new(data: &'a FramePairs) -> Self {
        Self { data }
    }

    fn channels(&self, frame: usize) -> Result<sparsh_data::ExrChannels, Error> {
        let path = self.data.dir.join("fields").join(format!("{frame:06}.exr"));
        if !path.is_file() {
            return Err(Error::file(
                &path,
                "no such field file (generate the data with the fields p, qx, qy, ux, uy, uz \
                 and contact kept in [output] fields)",
            ));
        }
        sparsh_data::read_exr_channels(&path).map_err(|e| Error::file(&path, e))
    }

    /// The truth of pair `p`: fields of frames t and t − k, resampled to the input pixels,
    /// displacements converted with the sequence's pixel pitch and turned with the frame.
    pub fn pair(&self, p: Pair) -> Result<PairTruth, Error> {
        let info = &self.data.sequences[p.sequence];
        let now = info.frame_index[p.t];
        let before = info.frame_index[p.t - self.data.offset];
        let mm_per_px = info.mm_per_px.ok_or_else(|| {
            Error::file(
                self.data.dir.join("labels.jsonl"),
                format!("frame {now}: mm_per_px: absent (the dataset predates it; regenerate it)"),
            )
        })?;
        let (a, b) = (self.channels(now)?, self.channels(before)?);
        let path = |f: usize| self.data.dir.join("fields").join(format!("{f:06}.exr"));
        let get = |c: &'_ sparsh_data::ExrChannels, f: usize, name: &str| {
            c.get(name).map(|v| v.to_vec()).ok_or_else(|| {
                Error::file(
                    path(f),
                    format!("no channel {name:?} (needed by the field probe)"),
                )
            })
        };
        let g = &info.geometry;
        let (nx, ny) = (a.width, a.height);
        let on_input = |v: Vec<f32>| g.resample(&v, nx, ny);
        let pressure_kpa = on_input(get(&a, now, "p")?);
        let indentation_mm = on_input(get(&a, now, "uz")?.iter().map(|v| -v).collect());
        let contact = on_input(get(&a, now, "contact")?)
            .iter()
            .map(|&c| c > 0.5)
            .collect();
        let (qx, qy) = (get(&a, now, "qx")?, get(&a, now, "qy")?);
        let shear_traction_kpa = on_input(qx.iter().zip(&qy).map(|(x, y)| x.hypot(*y)).collect());
        let du = |name: &str| -> Result<Vec<f32>, Error> {
            let (u1, u0) = (get(&a, now, name)?, get(&b, before, name)?);
            Ok(on_input(
                u1.iter()
                    .zip(&u0)
                    .map(|(x, y)| (x - y) / mm_per_px as f32)
                    .collect(),
            ))
        };
        let (dx, dy) = (du("ux")?, du("uy")?);
        let flow_px = dx
            .iter()
            .zip(&dy)
            .map(|(&x, &y)| {
                let v = g.vector_to_input([x as f64, y as f64]);
                [v[0] as f32, v[1] as f32]
            })
            .collect();
        Ok(PairTruth {
            pressure_kpa,
            indentation_mm,
            contact,
            shear_traction_kpa,
            flow_px,
        })
    }
}

/// The marker baseline: the printed markers' motion from t − k to t (`markers_px` of the labels),
/// spread to every input pixel by Nadaraya–Watson interpolation with a Gaussian kernel as wide as
/// the median spacing of neighbouring markers. `None` for a markerless sensor.
pub fn marker_flow(data: &FramePairs, p: Pair) -> Option<Vec<[f32; 2]>> {
    let info = &data.sequences[p.sequence];
    let (now, before) = (&info.markers_px[p.t], &info.markers_px[p.t - data.offset]);
    if now.is_empty() || now.len() != before.len() {
        return None;
    }
    let g = &info.geometry;
    let sites: Vec<([f64; 2], [f64; 2])> = before
        .iter()
        .zip(now)
        .map(|(b, a)| {
            (
                g.point_to_input(*b),
                g.vector_to_input([a[0] - b[0], a[1] - b[1]]),
            )
        })
        .collect();
    let mut nearest: Vec<f64> = sites
        .iter()
        .map(|(p, _)| {
            sites
                .iter()
                .map(|(q, _)| (p[0] - q[0]).hypot(p[1] - q[1]))
                .filter(|&d| d > 0.0)
                .fold(f64::INFINITY, f64::min)
        })
        .filter(|d| d.is_finite())
        .collect();
    nearest.sort_by(f64::total_cmp);
    let sigma = nearest
        .get(nearest.len() / 2)
        .copied()
        .unwrap_or(1.0)
        .max(0.5);
    let [h, w] = data.size();
    let mut out = vec![[0.0f32; 2]; h * w];
    for y in 0..h {
        for x in 0..w {
            let (mut sw, mut sx, mut sy) = (0.0, 0.0, 0.0);
            for (q, v) in &sites {
                let d2 = (x as f64 - q[0]).powi(2) + (y as f64 - q[1]).powi(2);
                let k = (-0.5 * d2 / (sigma * sigma)).exp();
                sw += k;
                sx += k * v[0];
                sy += k * v[1];
            }
            if sw > 1e-12 {
                out[y * w + x] = [(sx / sw) as f32, (sy / sw) as f32];
            }
        }
    }
    Some(out)
}
