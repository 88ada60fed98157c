//! Read-outs that need no encoder, on a task's frames at a resolution of their own (160×120 by
//! default, 2.8× the CPU recipes' 96×72 along each side): the classical ridge regression on
//! block means of the background-subtracted frame, and a small CNN trained on the task's labels —
//! the supervised ceiling a frozen encoder's probe is judged against.
//!
//! Both read one input per sample: the frame minus its background (3 channels) and minus the
//! frame five before it (3), the official I_t ⊕ I_{t−5} pair as differences.
//!
//! The same CNN and ridge on the simulator's true indentation −u_z at t and t − 5 instead of the
//! frames are the **floor oracles**: they are given everything the frames could show of the gel's
//! surface and nothing they cannot (the gel's stiffness and friction, where a slide began), so
//! each one's error bounds from above the task's identifiability floor — the error of the best
//! predictor the input allows. (With one gel a layer's normal force is a linear functional of
//! u_z over the whole surface, which the ridge can represent.)

use std::collections::BTreeMap;
use std::path::Path;

use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{Linear, LinearConfig, PaddingConfig2d};
use burn::prelude::*;
use burn::tensor::activation::relu;
use faer::Mat;
use faer::linalg::solvers::Solve;
use rayon::prelude::*;
use sparsh_ssl::data::Dataset;
use sparsh_ssl::device::seeded_module;

use super::photometric::{Integrator, SlopeLookup, slopes};
use super::probe::{Fit, FitOptions, Split, Standardizer, fit, force_bias, statistics_rows};
use super::tasks::{Head, Metric, Sample, Target, TaskKind, score};
use crate::Error;

/// Frames between the two frames of a pair (the official t − 5).
pub const PAIR_OFFSET: usize = 5;

/// Distinct frames of a [`PixelInputs`].
enum Frames {
    /// `[3, h, w]` 8-bit levels of (I − bg)/255 + 0.5: frames preprocessed as the encoders'
    /// inputs (background-subtracted, portrait, the official crop).
    Levels(Vec<Vec<u8>>),
    /// `[h, w]` indentation −u_z (mm) on the contact grid.
    Indentation(Vec<Vec<f32>>),
}

/// What every sample of a task reads, once per distinct frame: its frames, or its true
/// indentation (the floor oracle's input).
pub struct PixelInputs {
    /// `[height, width]`.
    pub size: [usize; 2],
    /// Distinct frames.
    frames: Frames,
    /// Per sample: its frame and the frame [`PAIR_OFFSET`] before it (indices into `frames`).
    pairs: Vec<(usize, usize)>,
    /// Per distinct frame, its sequence's light level per colour channel: the mean of the
    /// sequence's background over the mean of every background (the scenes draw each LED's
    /// intensity per sequence, and I − bg scales with it); empty where the dataset keeps no
    /// backgrounds (official layouts) or for the indentation.
    gains: Vec<[f64; 3]>,
    /// Whether [`PixelInputs::input`] divides the frames by their light level (`gains`).
    light_normalized: bool,
}

impl PixelInputs {
    /// Reads the frames of `samples` from the dataset in `dir` at `size`. `origin` maps the
    /// samples' sequence indices to the dataset's (identity unless a run keeps a subset).
    /// With `light_normalized`, [`PixelInputs::input`] divides each frame by its sequence's
    /// light level; a dataset without backgrounds (the official layouts) is refused then.
    pub fn load(
        dir: &Path,
        samples: &[Sample],
        origin: &[usize],
        size: [usize; 2],
        light_normalized: bool,
    ) -> Result<Self, Error> {
        let dataset = if dir.join("labels.jsonl").is_file() {
            Dataset::load_generated(dir, size)?
        } else {
            crate::official::load(dir, size)?.dataset
        };
        let (wanted, order) = distinct_frames(samples, origin);
        let frames = order
            .par_iter()
            .map(|&(s, t)| {
                let seq = dataset.sequences.get(s).ok_or_else(|| {
                    Error::file(dir, format!("no sequence {s} (the labels name it)"))
                })?;
                let src = seq
                    .frames
                    .get(t)
                    .ok_or_else(|| Error::file(dir, format!("sequence {s} has no frame {t}")))?;
                let f = src.read(size)?;
                Ok(f.iter()
                    .map(|&v| (v * 255.0).round().clamp(0.0, 255.0) as u8)
                    .collect())
            })
            .collect::<Result<Vec<Vec<u8>>, Error>>()?;
        let gains = light_levels(dir, &order)?;
        if light_normalized && gains.is_empty() {
            return Err(Error::file(
                dir,
                "light_normalize needs each sequence's background (a generated dataset); \
                 this layout keeps none",
            ));
        }
        Ok(Self {
            size,
            frames: Frames::Levels(frames),
            pairs: pairs_of(samples, origin, &wanted),
            gains,
            light_normalized,
        })
    }

    /// Checks, before anything trains, that the dataset `dir` keeps the indentation the floor
    /// oracles read: its first frame's field file has a `uz` channel. Returns the contact
    /// grid's `[rows, columns]`.
    pub fn check_indentation(dir: &Path) -> Result<[usize; 2], Error> {
        let sequences = sparsh_ssl::data::generated_sequences(dir)?;
        let id = sequences
            .first()
            .and_then(|q| q.frame_ids.first())
            .ok_or_else(|| Error::file(dir, "no frames"))?;
        let path = dir.join("fields").join(format!("{id:06}.exr"));
        uz_channel(&path).map(|(size, _)| size)
    }

    /// Reads the true indentation −u_z of `samples`' frames from the `fields/NNNNNN.exr` of the
    /// dataset `dir` written by `sparsh generate` with `uz` among its fields (one-line errors
    /// name the file otherwise), on the contact grid.
    pub fn load_indentation(
        dir: &Path,
        samples: &[Sample],
        origin: &[usize],
    ) -> Result<Self, Error> {
        let sequences = sparsh_ssl::data::generated_sequences(dir)?;
        let (wanted, order) = distinct_frames(samples, origin);
        let grids = order
            .par_iter()
            .map(|&(s, t)| {
                let id = sequences
                    .get(s)
                    .and_then(|q| q.frame_ids.get(t))
                    .ok_or_else(|| Error::file(dir, format!("sequence {s} has no frame {t}")))?;
                uz_channel(&dir.join("fields").join(format!("{id:06}.exr")))
            })
            .collect::<Result<Vec<_>, Error>>()?;
        let size = grids.first().map_or([0, 0], |g| g.0);
        if let Some(k) = grids.iter().position(|g| g.0 != size) {
            let (s, t) = order[k];
            return Err(Error::file(
                dir,
                format!(
                    "sequence {s} frame {t}: a {:?} contact grid where the first frame has \
                     {size:?} (the floor oracle needs one grid)",
                    grids[k].0
                ),
            ));
        }
        Ok(Self {
            size,
            frames: Frames::Indentation(grids.into_iter().map(|g| g.1).collect()),
            pairs: pairs_of(samples, origin, &wanted),
            gains: Vec::new(),
            light_normalized: false,
        })
    }

    /// Channels of an input: 6 for frames (I_t − bg and I_t − I_{t−5}, RGB), 2 for the
    /// indentation (−u_z at t and its change since t − 5).
    pub fn channels(&self) -> usize {
        match self.frames {
            Frames::Levels(_) => 6,
            Frames::Indentation(_) => 2,
        }
    }

    /// Samples held.
    pub fn len(&self) -> usize {
        self.pairs.len()
    }

    /// Whether no sample is held.
    pub fn is_empty(&self) -> bool {
        self.pairs.is_empty()
    }

    /// Sample `i`'s input, `[channels, h, w]`: (I_t − bg)/255 and (I_t − I_{t−5})/255, each
    /// colour channel divided by the sequence's light level where the inputs are
    /// light-normalized, or −u_z(t) and −u_z(t) + u_z(t − 5) in units of 0.1 mm (about the
    /// frames' scale).
    pub fn input(&self, i: usize, out: &mut Vec<f32>) {
        let (now, before) = self.pairs[i];
        match &self.frames {
            Frames::Levels(f) => {
                let (a, b) = (&f[now], &f[before]);
                let plane = self.size[0] * self.size[1];
                // Divided, not multiplied by a reciprocal: plain inputs are (v − 127.5) / 255 exactly.
                let divisor: [f32; 3] = match self.gains.get(now) {
                    Some(g) if self.light_normalized => {
                        std::array::from_fn(|c| (255.0 * g[c]) as f32)
                    }
                    _ => [255.0; 3],
                };
                out.extend(
                    a.iter()
                        .enumerate()
                        .map(|(k, &v)| (v as f32 - 127.5) / divisor[k / plane]),
                );
                out.extend(
                    a.iter()
                        .zip(b)
                        .enumerate()
                        .map(|(k, (&x, &y))| (x as f32 - y as f32) / divisor[k / plane]),
                );
            }
            Frames::Indentation(f) => {
                let (a, b) = (&f[now], &f[before]);
                out.extend(a.iter().map(|x| 10.0 * x));
                out.extend(a.iter().zip(b).map(|(x, y)| 10.0 * (x - y)));
            }
        }
    }

    /// The ridge features of sample `i`: per `block` × `block` cell, the mean of each input
    /// channel and of the absolute value of each of its two parts (the frame against the
    /// background and against the earlier frame, summed over RGB): `(channels + 2) · ⌈h/block⌉
    /// · ⌈w/block⌉` values.
    pub fn block_features(&self, i: usize, block: usize) -> Vec<f64> {
        let [h, w] = self.size;
        let channels = self.channels();
        let (bh, bw) = (h.div_ceil(block), w.div_ceil(block));
        let mut x = Vec::with_capacity(channels * h * w);
        self.input(i, &mut x);
        let mut out = vec![0.0; (channels + 2) * bh * bw];
        let mut count = vec![0.0; bh * bw];
        for y in 0..h {
            for xx in 0..w {
                let cell = (y / block) * bw + xx / block;
                count[cell] += 1.0;
                for c in 0..channels {
                    let v = x[(c * h + y) * w + xx] as f64;
                    out[c * bh * bw + cell] += v;
                    out[(channels + 2 * c / channels) * bh * bw + cell] += v.abs();
                }
            }
        }
        for (k, v) in out.iter_mut().enumerate() {
            *v /= count[k % (bh * bw)];
        }
        out
    }
}

impl PixelInputs {
    /// The classical height read-out's input ([`super::photometric`]): the indentation these
    /// frames show, estimated by a slope lookup calibrated on the frames of the samples `train`
    /// against `truth` (the same samples' true indentation), integrated to a height map on the
    /// contact grid. The frames are portrait (the official turn), the contact grid landscape:
    /// `pixel_size` must be the grid turned, `[columns, rows]`.
    pub fn photometric(&self, truth: &PixelInputs, train: &[usize]) -> Result<PixelInputs, String> {
        let (Frames::Levels(levels), Frames::Indentation(depth)) = (&self.frames, &truth.frames)
        else {
            return Err("the photometric read-out needs frames and the true indentation".into());
        };
        let [h, w] = self.size;
        let [rows, cols] = truth.size;
        if (h, w) != (cols, rows) {
            return Err(format!(
                "pixel_size {:?} must be the contact grid {:?} turned to portrait, [{cols}, {rows}] \
                 (the photometric read-out matches each frame pixel to a contact cell)",
                self.size, truth.size
            ));
        }
        if self.pairs != truth.pairs {
            return Err("frames and indentation of different samples".into());
        }
        // the colour change at landscape cell (r, c): portrait pixel (c, rows − 1 − r)
        // divided by the frame's light level, where the dataset keeps its backgrounds, with
        // the cell's position in [−1, 1]²
        let colour = |k: usize, r: usize, c: usize| -> ([f64; 3], [f64; 2]) {
            let (y, x) = (c, rows - 1 - r);
            let gain = self.gains.get(k).copied().unwrap_or([1.0; 3]);
            let change = std::array::from_fn(|ch| {
                (levels[k][(ch * h + y) * w + x] as f64 - 127.5) / 255.0 / gain[ch]
            });
            let position = [
                2.0 * c as f64 / cols as f64 - 1.0,
                2.0 * r as f64 / rows as f64 - 1.0,
            ];
            (change, position)
        };
        // calibration: both frames of the training samples, at most 600 of them, every second
        // cell each way
        let mut frames: Vec<usize> = train
            .iter()
            .flat_map(|&i| [self.pairs[i].0, self.pairs[i].1])
            .collect();
        frames.sort_unstable();
        frames.dedup();
        let step = frames.len().div_ceil(600).max(1);
        let chosen: Vec<usize> = frames.into_iter().step_by(step).collect();
        type Calibration = (([f64; 3], [f64; 2]), [f64; 2]);
        let samples: Vec<Vec<Calibration>> = chosen
            .par_iter()
            .map(|&f| {
                let (gx, gy) = slopes(&depth[f], rows, cols);
                (0..rows)
                    .step_by(2)
                    .flat_map(|r| (0..cols).step_by(2).map(move |c| (r, c)))
                    .map(|(r, c)| (colour(f, r, c), [gx[r * cols + c], gy[r * cols + c]]))
                    .collect()
            })
            .collect();
        let lookup = SlopeLookup::fit(samples.into_iter().flatten());
        let integrator = Integrator::new(rows, cols);
        let estimated = (0..levels.len())
            .into_par_iter()
            .map(|k| {
                let mut gx = vec![0.0; rows * cols];
                let mut gy = vec![0.0; rows * cols];
                for r in 0..rows {
                    for c in 0..cols {
                        let (change, position) = colour(k, r, c);
                        [gx[r * cols + c], gy[r * cols + c]] = lookup.slope(change, position);
                    }
                }
                integrator.integrate(&gx, &gy)
            })
            .collect();
        Ok(PixelInputs {
            size: truth.size,
            frames: Frames::Indentation(estimated),
            pairs: self.pairs.clone(),
            gains: Vec::new(),
            light_normalized: false,
        })
    }
}

/// Each distinct frame's light level per channel (see [`PixelInputs`]'s `gains`): the mean of
/// its sequence's background over the mean of all the sequences' backgrounds; empty for a
/// dataset without background files (the official layouts).
fn light_levels(dir: &Path, order: &[(usize, usize)]) -> Result<Vec<[f64; 3]>, Error> {
    if !dir.join("labels.jsonl").is_file() {
        return Ok(Vec::new());
    }
    let sequences = sparsh_ssl::data::generated_sequences(dir)?;
    let means = sequences
        .par_iter()
        .map(|q| {
            let bg = sparsh_ssl::data::read_image(&q.background)?;
            let n = (bg.width() * bg.height()) as f64;
            let mut m = [0.0; 3];
            for p in bg.pixels() {
                (0..3).for_each(|c| m[c] += p.0[c] as f64 / n);
            }
            Ok(m)
        })
        .collect::<Result<Vec<[f64; 3]>, Error>>()?;
    let all: [f64; 3] = std::array::from_fn(|c| {
        means.iter().map(|m| m[c]).sum::<f64>() / means.len().max(1) as f64
    });
    order
        .iter()
        .map(|&(s, _)| {
            let m = means
                .get(s)
                .ok_or_else(|| Error::file(dir, format!("no sequence {s} (the labels name it)")))?;
            Ok(std::array::from_fn(|c| (m[c] / all[c].max(1e-9)).max(1e-3)))
        })
        .collect()
}

/// The indentation −u_z of one field file and its `[height, width]`; a file without the
/// channel is a one-line error saying how to keep it.
fn uz_channel(path: &Path) -> Result<([usize; 2], Vec<f32>), Error> {
    if !path.is_file() {
        return Err(Error::file(
            path,
            "no such field file (the floor oracles read the indentation: keep \"uz\" in the \
             scene's [output] fields and regenerate)",
        ));
    }
    let c = sparsh_data::read_exr_channels(path).map_err(|e| Error::file(path, e))?;
    let uz = c.get("uz").ok_or_else(|| {
        Error::file(
            path,
            "no channel \"uz\" (the floor oracles read the indentation: add \"uz\" to the \
             scene's [output] fields and regenerate)",
        )
    })?;
    Ok(([c.height, c.width], uz.iter().map(|v| -v).collect()))
}

/// The distinct (sequence, frame) pairs `samples` read, numbered in first-use order, and that
/// order.
type FrameIndex = (BTreeMap<(usize, usize), usize>, Vec<(usize, usize)>);

fn distinct_frames(samples: &[Sample], origin: &[usize]) -> FrameIndex {
    let mut wanted = BTreeMap::new();
    let mut order = Vec::new();
    for s in samples {
        for t in [s.frame, s.frame.saturating_sub(PAIR_OFFSET)] {
            let key = (origin[s.sequence], t);
            if let std::collections::btree_map::Entry::Vacant(e) = wanted.entry(key) {
                e.insert(order.len());
                order.push(key);
            }
        }
    }
    (wanted, order)
}

/// Each sample's (frame, frame five before) as indices into the distinct frames.
fn pairs_of(
    samples: &[Sample],
    origin: &[usize],
    wanted: &BTreeMap<(usize, usize), usize>,
) -> Vec<(usize, usize)> {
    samples
        .iter()
        .map(|s| {
            let o = origin[s.sequence];
            (
                wanted[&(o, s.frame)],
                wanted[&(o, s.frame.saturating_sub(PAIR_OFFSET))],
            )
        })
        .collect()
}

/// The ridge read-out's target row of a sample: the force in N, else the head's encoded row
/// (class-weighted one-hot rows; ΔF scaled), whose argmax per head is the class.
fn ridge_target(head: &Head, target: &Target, classes: usize) -> Vec<f64> {
    match target {
        Target::Force(f) => f.to_vec(),
        t => head.encode(t, classes).iter().map(|&v| v as f64).collect(),
    }
}

/// A prediction from a ridge output row (see [`ridge_target`]).
fn ridge_decode(head: &Head, out: &[f64]) -> Vec<f64> {
    match head.kind {
        TaskKind::Force => out.to_vec(),
        _ => head.decode(&out.iter().map(|&v| v as f32).collect::<Vec<_>>()),
    }
}

/// Ridge penalties tried, relative to the mean diagonal of the standardized Gram matrix.
pub const RIDGE_LAMBDAS: [f64; 7] = [1e-4, 1e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0];

/// The classical read-out: ridge regression of the task's targets on [`block_features`]
/// (standardized on the training rows, with an intercept), its penalty chosen among
/// [`RIDGE_LAMBDAS`] on the validation rows by the task's first metric. `best_epoch` is the
/// chosen penalty's index (from 1) and `val_curve` the validation metric per penalty.
///
/// [`block_features`]: PixelInputs::block_features
pub fn fit_ridge(
    inputs: &PixelInputs,
    block: usize,
    samples: &[Sample],
    head: &Head,
    classes: usize,
    split: &Split,
) -> Fit {
    let features: Vec<Vec<f64>> = (0..inputs.len())
        .into_par_iter()
        .map(|i| inputs.block_features(i, block))
        .collect();
    let d = features[0].len();
    let n = split.train.len();
    let mut mean = vec![0.0; d];
    let mut sd = vec![0.0; d];
    for &i in &split.train {
        for (m, v) in mean.iter_mut().zip(&features[i]) {
            *m += v / n as f64;
        }
    }
    for &i in &split.train {
        for ((s, v), m) in sd.iter_mut().zip(&features[i]).zip(&mean) {
            *s += (v - m).powi(2) / n as f64;
        }
    }
    let sd: Vec<f64> = sd.iter().map(|v| v.sqrt().max(1e-9)).collect();
    let z = |i: usize, j: usize| (features[i][j] - mean[j]) / sd[j];
    let targets: Vec<Vec<f64>> = samples
        .iter()
        .map(|s| ridge_target(head, &s.target, classes))
        .collect();
    let k = targets[0].len();
    let mut ymean = vec![0.0; k];
    for &i in &split.train {
        for (m, v) in ymean.iter_mut().zip(&targets[i]) {
            *m += v / n as f64;
        }
    }
    let x = Mat::<f64>::from_fn(n, d, |r, j| z(split.train[r], j));
    let y = Mat::<f64>::from_fn(n, k, |r, c| targets[split.train[r]][c] - ymean[c]);
    let gram = x.transpose() * &x;
    let xty = x.transpose() * &y;
    let scale = (0..d).map(|j| gram[(j, j)]).sum::<f64>() / d as f64;
    let predict = |w: &Mat<f64>, rows: &[usize]| -> Vec<Vec<f64>> {
        rows.iter()
            .map(|&i| {
                let out: Vec<f64> = (0..k)
                    .map(|c| ymean[c] + (0..d).map(|j| z(i, j) * w[(j, c)]).sum::<f64>())
                    .collect();
                ridge_decode(head, &out)
            })
            .collect()
    };
    let metric: Metric = head.kind.metrics()[0];
    let mut val_curve = Vec::new();
    let mut best: Option<(f64, usize, Mat<f64>)> = None;
    for (li, &lambda) in RIDGE_LAMBDAS.iter().enumerate() {
        let mut a = gram.clone();
        for j in 0..d {
            a[(j, j)] += lambda * scale.max(1e-12);
        }
        let w = match a.llt(faer::Side::Lower) {
            Ok(llt) => llt.solve(&xty),
            Err(_) => {
                val_curve.push(f64::NAN);
                continue;
            }
        };
        let mut preds = vec![Vec::new(); samples.len()];
        for (&i, p) in split.val.iter().zip(predict(&w, &split.val)) {
            preds[i] = p;
        }
        let value = score(metric, &split.val, &preds, samples);
        val_curve.push(value);
        let better = match &best {
            None => value.is_finite(),
            Some((b, _, _)) => {
                value.is_finite()
                    && if metric.higher_is_better() {
                        value > *b
                    } else {
                        value < *b
                    }
            }
        };
        if better {
            best = Some((value, li + 1, w));
        }
    }
    // every penalty failed: the training mean
    let (best_epoch, w) = best.map_or((0, Mat::zeros(d, k)), |(_, e, w)| (e, w));
    Fit {
        best_epoch,
        val_curve,
        test_preds: predict(&w, &split.test),
        seen_preds: predict(&w, &split.seen),
    }
}

/// Channels and strides of the ceiling CNN's 3 × 3 convolutions.
const CNN_LAYERS: [(usize, usize); 5] = [(16, 2), (32, 2), (64, 2), (64, 1), (64, 2)];

/// The supervised ceiling: a small fully convolutional network (≈ 0.1 M parameters) — five
/// 3 × 3 convolutions with ReLU, four of stride 2 (a receptive field of 47 input pixels, about a
/// gel thickness at 160×120), then a head. For force, a 1 × 1 convolution to the outputs at
/// every cell, averaged over the image: sums of local evidence, as a force is the integral of
/// its traction over the contact, a model that cannot key on a training shape's outline. For the
/// classification tasks (slip, pose, texture, grasp) the last features' mean and maximum over
/// the image, then a linear layer: a class — the slip cone's ratio of two integrals — is not a
/// sum of local evidence.
#[derive(Module, Debug)]
pub struct CeilingCnn {
    /// Convolutions.
    pub convs: Vec<Conv2d>,
    /// The force head: the 1 × 1 convolution to the outputs, averaged.
    pub out: Option<Conv2d>,
    /// The classification head: mean- and max-pooled features to the outputs.
    pub pooled: Option<Linear>,
}

impl CeilingCnn {
    /// A fresh network reading `channels` input channels, with `outputs` outputs, summing local
    /// evidence (`additive`, for force) or pooling features.
    pub fn new(channels: usize, outputs: usize, additive: bool, device: &Device) -> Self {
        let mut convs = Vec::new();
        let mut cin = channels;
        for (c, stride) in CNN_LAYERS {
            convs.push(
                Conv2dConfig::new([cin, c], [3, 3])
                    .with_stride([stride, stride])
                    .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
                    .init(device),
            );
            cin = c;
        }
        let (out, pooled) = if additive {
            (
                Some(Conv2dConfig::new([cin, outputs], [1, 1]).init(device)),
                None,
            )
        } else {
            (None, Some(LinearConfig::new(2 * cin, outputs).init(device)))
        };
        Self { convs, out, pooled }
    }

    /// `[n, channels, h, w]` inputs → `[n, outputs]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<2> {
        let mut x = x * 4.0;
        for conv in &self.convs {
            x = relu(conv.forward(x));
        }
        let [n, c, h, w] = x.dims();
        if let Some(linear) = &self.pooled {
            let cells = x.reshape([n, c, h * w]);
            let mean = cells.clone().mean_dim(2).reshape([n, c]);
            let max = cells.max_dim(2).reshape([n, c]);
            return linear.forward(Tensor::cat(vec![mean, max], 1));
        }
        let y = self.out.as_ref().expect("a head").forward(x);
        let [n, k, h, w] = y.dims();
        y.reshape([n, k, h * w]).mean_dim(2).reshape([n, k])
    }
}

/// Trains the ceiling CNN (or, on the indentation, the floor oracle) on the training rows'
/// inputs, each channel standardized on them ([`Standardizer`]), and labels (AdamW,
/// half-cosine), the epoch scored on test chosen on validation; the
/// network is drawn on the CPU under `opts.seed`, its force outputs starting at the training
/// mean ([`Head::force_bias`]).
pub fn fit_ceiling(
    inputs: &PixelInputs,
    samples: &[Sample],
    head: &Head,
    classes: usize,
    split: &Split,
    opts: FitOptions,
    device: &Device,
) -> Fit {
    let cpu = Device::flex().autodiff();
    let mut model = seeded_module(&cpu, opts.seed, || {
        let additive = head.kind == TaskKind::Force;
        CeilingCnn::new(inputs.channels(), head.outputs(classes), additive, &cpu)
    });
    if let (Some(bias), Some(out)) = (force_bias(head, &cpu), model.out.as_mut()) {
        out.bias = Some(bias);
    }
    let ([h, w], c) = (inputs.size, inputs.channels());
    let standardizer = Standardizer::fit(
        c,
        h * w,
        statistics_rows(&split.train).into_iter().map(|i| {
            let mut x = Vec::with_capacity(c * h * w);
            inputs.input(i, &mut x);
            x
        }),
    );
    let input = |rows: &[usize], device: &Device| {
        let mut x = Vec::with_capacity(rows.len() * c * h * w);
        for &i in rows {
            inputs.input(i, &mut x);
        }
        standardizer.apply(&mut x);
        Tensor::<1>::from_floats(x.as_slice(), device).reshape([rows.len(), 1, c * h * w])
    };
    let forward = move |m: &CeilingCnn, x: Tensor<3>| {
        let [n, _, _] = x.dims();
        m.forward(x.reshape([n, c, h, w]))
    };
    fit(
        model, &input, &forward, samples, head, classes, split, opts, device,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use sparsh_ssl::rng::Rng;

    /// `n` indentation maps of `size` holding one disc each (random centre, radius and depth),
    /// their force a known function of the map: `[0, 0, k · volume]`, the integral of the
    /// indentation (as a layer's normal force is, to first order, linear in it).
    fn discs(n: usize, size: [usize; 2], seed: u64) -> (PixelInputs, Vec<Sample>) {
        let mut rng = Rng::new(seed);
        let [h, w] = size;
        let mut grids = Vec::with_capacity(n);
        let mut samples = Vec::with_capacity(n);
        for i in 0..n {
            let (cy, cx) = (
                rng.range_f64(6.0, h as f64 - 6.0),
                rng.range_f64(6.0, w as f64 - 6.0),
            );
            let (r, depth) = (rng.range_f64(1.5, 5.0), rng.range_f64(0.1, 0.8));
            let g: Vec<f32> = (0..h * w)
                .map(|k| {
                    let (y, x) = ((k / w) as f64 + 0.5, (k % w) as f64 + 0.5);
                    let d2 = (y - cy).powi(2) + (x - cx).powi(2);
                    (depth * (1.0 - d2 / (r * r)).max(0.0)) as f32
                })
                .collect();
            let volume: f64 = g.iter().map(|&v| v as f64).sum();
            grids.push(g);
            samples.push(Sample {
                sequence: i / 4,
                frame: i % 4,
                target: Target::Force([0.0, 0.0, 0.05 * volume]),
            });
        }
        let inputs = PixelInputs {
            size,
            frames: Frames::Indentation(grids),
            pairs: (0..n).map(|i| (i, i)).collect(),
            gains: Vec::new(),
            light_normalized: false,
        };
        (inputs, samples)
    }

    fn split(n: usize) -> Split {
        let rows: Vec<usize> = (0..n).collect();
        Split {
            train: rows.iter().copied().filter(|i| i % 5 < 3).collect(),
            val: rows.iter().copied().filter(|i| i % 5 == 3).collect(),
            test: rows.iter().copied().filter(|i| i % 5 == 4).collect(),
            seen: Vec::new(),
        }
    }

    fn rmse(fit: &Fit, samples: &[Sample], split: &Split) -> f64 {
        let mut preds = vec![Vec::new(); samples.len()];
        for (&i, p) in split.test.iter().zip(&fit.test_preds) {
            preds[i] = p.clone();
        }
        score(Metric::RmseMn, &split.test, &preds, samples)
    }

    /// The training mean's test RMSE (what learns nothing).
    fn constant_rmse(samples: &[Sample], split: &Split) -> f64 {
        let mut m = [0.0; 3];
        for &i in &split.train {
            if let Target::Force(f) = samples[i].target {
                (0..3).for_each(|k| m[k] += f[k] / split.train.len() as f64);
            }
        }
        let preds = vec![m.to_vec(); samples.len()];
        score(Metric::RmseMn, &split.test, &preds, samples)
    }

    #[test]
    fn ridge_recovers_a_force_linear_in_the_block_means() {
        // the volume is the sum of the block means times the block area: exactly linear in the
        // features, so the ridge's error is the penalty's bias alone
        let (inputs, samples) = discs(300, [24, 32], 1);
        let split = split(samples.len());
        let refs: Vec<&Sample> = split.train.iter().map(|&i| &samples[i]).collect();
        let head = Head::new(TaskKind::Force, 0, [4.0, 4.0, 5.0], &refs);
        let fit = fit_ridge(&inputs, 8, &samples, &head, 0, &split);
        let (read, mean) = (
            rmse(&fit, &samples, &split),
            constant_rmse(&samples, &split),
        );
        assert!(read < 0.05 * mean, "ridge {read} mN vs the mean's {mean}");
        // the chosen penalty is the best on validation
        let best = fit.val_curve.iter().copied().fold(f64::INFINITY, f64::min);
        assert_eq!(fit.val_curve[fit.best_epoch - 1], best);
        assert_eq!(fit.val_curve.len(), RIDGE_LAMBDAS.len());
    }

    /// Frames shaded from the indentation maps' slopes by a known linear lookup, 8-bit and
    /// turned to portrait clockwise as the official preprocessing turns them: the photometric
    /// read-out's height must be the true one, and its ridge must read the force as the floor
    /// ridge does (a wrong turn or a swapped slope would leave a map unrelated to the truth).
    #[test]
    fn photometric_heights_recover_the_indentation_a_shading_shows() {
        let (truth, samples) = discs(300, [24, 32], 5);
        let [rows, cols] = truth.size;
        let Frames::Indentation(grids) = &truth.frames else {
            unreachable!()
        };
        let levels: Vec<Vec<u8>> = grids
            .iter()
            .map(|g| {
                let (gx, gy) = slopes(g, rows, cols);
                let mut f = vec![0u8; 3 * cols * rows];
                // landscape (r, c) is portrait (y = c, x = rows − 1 − r) after a clockwise turn
                for r in 0..rows {
                    for c in 0..cols {
                        let (sx, sy) = (gx[r * cols + c], gy[r * cols + c]);
                        let shade = [
                            0.3 * sx + 0.1 * sy,
                            -0.2 * sx + 0.25 * sy,
                            0.05 * sx - 0.3 * sy,
                        ];
                        for (ch, v) in shade.iter().enumerate() {
                            let (y, x) = (c, rows - 1 - r);
                            f[(ch * cols + y) * rows + x] =
                                (127.5 + 255.0 * v).round().clamp(0.0, 255.0) as u8;
                        }
                    }
                }
                f
            })
            .collect();
        let frames = PixelInputs {
            size: [cols, rows],
            frames: Frames::Levels(levels),
            pairs: truth.pairs.clone(),
            gains: Vec::new(),
            light_normalized: false,
        };
        let split = split(samples.len());
        let Ok(estimated) = frames.photometric(&truth, &split.train) else {
            panic!("the frames are the grid turned")
        };
        let Frames::Indentation(heights) = &estimated.frames else {
            unreachable!()
        };
        let (mut err, mut norm) = (0.0, 0.0);
        for (e, t) in heights.iter().zip(grids) {
            for (a, b) in e.iter().zip(t) {
                err += ((a - b) as f64).powi(2);
                norm += (*b as f64).powi(2);
            }
        }
        let relative = (err / norm).sqrt();
        assert!(
            relative < 0.2,
            "height error {relative} of the true indentation's norm"
        );
        let refs: Vec<&Sample> = split.train.iter().map(|&i| &samples[i]).collect();
        let head = Head::new(TaskKind::Force, 0, [4.0, 4.0, 5.0], &refs);
        let fit = fit_ridge(&estimated, 8, &samples, &head, 0, &split);
        let (read, mean) = (
            rmse(&fit, &samples, &split),
            constant_rmse(&samples, &split),
        );
        assert!(
            read < 0.15 * mean,
            "photometric ridge {read} mN vs the mean's {mean}"
        );
        // the frames must be the contact grid turned
        let unturned = PixelInputs {
            size: [rows, cols],
            ..frames
        };
        let Err(err) = unturned.photometric(&truth, &split.train) else {
            panic!("frames not turned must be refused")
        };
        assert!(err.contains("turned to portrait"), "{err}");
    }

    #[test]
    fn the_ceiling_cnn_learns_a_force_from_indentation_maps() {
        // the maps as they are, and faint on an offset (a thousandth of their depth on a level
        // 50 times that), as a shallow press shows in background-subtracted frames: the
        // standardized input makes both the same problem
        for (gain, offset) in [(1.0f32, 0.0f32), (1e-3, 0.05)] {
            let (mut inputs, samples) = discs(400, [24, 32], 2);
            if let Frames::Indentation(grids) = &mut inputs.frames {
                grids
                    .iter_mut()
                    .flatten()
                    .for_each(|v| *v = offset + gain * *v);
            }
            let split = split(samples.len());
            let refs: Vec<&Sample> = split.train.iter().map(|&i| &samples[i]).collect();
            let head = Head::new(TaskKind::Force, 0, [4.0, 4.0, 5.0], &refs);
            let opts = FitOptions {
                epochs: 30,
                batch_size: 16,
                lr: 3e-3,
                seed: 4,
                patience: 0,
            };
            let fit = fit_ceiling(&inputs, &samples, &head, 0, &split, opts, &Device::flex());
            let (read, mean) = (
                rmse(&fit, &samples, &split),
                constant_rmse(&samples, &split),
            );
            assert!(
                read < 0.35 * mean,
                "gain {gain}: CNN {read} mN vs the mean's {mean}"
            );
            let best = fit.val_curve.iter().copied().fold(f64::INFINITY, f64::min);
            assert_eq!(fit.val_curve[fit.best_epoch - 1], best);
        }
    }

    #[test]
    fn patience_stops_a_fit_that_no_longer_improves() {
        // labels that are noise: validation stops improving early, and the fit stops
        // `patience` epochs after its best
        let (inputs, mut samples) = discs(100, [16, 16], 3);
        let mut rng = Rng::new(9);
        for s in &mut samples {
            s.target = Target::Force([0.0, 0.0, rng.range_f64(0.0, 2.0)]);
        }
        let split = split(samples.len());
        let refs: Vec<&Sample> = split.train.iter().map(|&i| &samples[i]).collect();
        let head = Head::new(TaskKind::Force, 0, [4.0, 4.0, 5.0], &refs);
        let opts = FitOptions {
            epochs: 60,
            batch_size: 16,
            lr: 3e-3,
            seed: 1,
            patience: 3,
        };
        let fit = fit_ceiling(&inputs, &samples, &head, 0, &split, opts, &Device::flex());
        assert_eq!(
            fit.val_curve.len(),
            fit.best_epoch + 3,
            "{:?}",
            fit.val_curve
        );
    }

    #[test]
    fn block_features_average_each_channel_and_its_magnitude() {
        // one 2 × 4 indentation map, blocks of 2: cells [[1, -3], [2, 2]] and [[0, 4], [0, 0]]
        let inputs = PixelInputs {
            size: [2, 4],
            frames: Frames::Indentation(vec![vec![1.0, -3.0, 0.0, 4.0, 2.0, 2.0, 0.0, 0.0]]),
            pairs: vec![(0, 0)],
            gains: Vec::new(),
            light_normalized: false,
        };
        let f = inputs.block_features(0, 2);
        // channel 0 (the map in 0.1 mm), channel 1 (its change: 0), |channel 0|, |channel 1|
        assert_eq!(f, vec![5.0, 10.0, 0.0, 0.0, 20.0, 10.0, 0.0, 0.0]);
    }

    #[test]
    fn light_normalized_inputs_undo_a_sequences_led_gain() {
        // one shading (I − bg in levels, per channel) seen under two sequences' lights: the
        // second's LEDs at 1.25 / 0.8 / 1 of the first's, so its change in every channel scales
        // by that gain; the earlier frame of each pair is the background (change 0)
        let change: [f32; 3] = [40.0, -24.0, 16.0];
        let frame = |gain: [f32; 3]| -> Vec<u8> {
            (0..3)
                .flat_map(|c| std::iter::repeat_n((127.5 + change[c] * gain[c]).round() as u8, 2))
                .collect()
        };
        let background = vec![128u8; 6];
        let inputs = |light_normalized| PixelInputs {
            size: [1, 2],
            frames: Frames::Levels(vec![
                frame([1.0; 3]),
                background.clone(),
                frame([1.25, 0.8, 1.0]),
                background.clone(),
            ]),
            pairs: vec![(0, 1), (2, 3)],
            gains: vec![[1.0; 3], [1.0; 3], [1.25, 0.8, 1.0], [1.25, 0.8, 1.0]],
            light_normalized,
        };
        let read = |p: &PixelInputs, i| {
            let mut x = Vec::new();
            p.input(i, &mut x);
            x
        };
        let plain = inputs(false);
        let (a, b) = (read(&plain, 0), read(&plain, 1));
        assert!((b[0] / a[0] - 1.25).abs() < 0.02, "{a:?} {b:?}");
        let normalized = inputs(true);
        let (a, b) = (read(&normalized, 0), read(&normalized, 1));
        for (k, (x, y)) in a.iter().zip(&b).enumerate() {
            // each frame rounded to whole levels: half a level, and half a level over the gain
            assert!(
                (x - y).abs() <= (0.5 + 0.5 / 0.8) / 255.0 + 1e-6,
                "value {k}: {x} vs {y}"
            );
        }
        assert!(
            (a[0] - change[0] / 255.0).abs() < 0.5 / 255.0 + 1e-6,
            "{a:?}"
        );
    }
}
