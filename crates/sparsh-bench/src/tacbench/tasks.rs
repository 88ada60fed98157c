//! The TacBench tasks on labelled sequences: which frames are samples, their targets, the
//! probe head's outputs and loss, and the metrics, after the official downstream tasks
//! (facebookresearch/sparsh, `tactile_ssl/downstream_task/`):
//!
//! - **force** (T1): `[Fx, Fy, Fz]`; tanh on Fx, Fy and a sigmoid on Fz, each scaled by the
//!   sensor's force range (DIGIT 4, 4, 5 N); smooth-L1 (β = 0.02) on the scaled targets. Scored
//!   by the true root mean square error in mN, per axis and over the three (the official code
//!   reports a mean absolute error under that name).
//! - **slip** (T2): the friction-cone label ‖F_xy‖ > 1.6 F_z (class weights 0.1, 1 as the
//!   official head), the contact solver's stick / partial / gross state (inverse-frequency
//!   weights), and the official auxiliary head on ΔF (the force change since t − 5); F1 of the
//!   cone label and balanced accuracy of both.
//! - **pose** (T3): the SE(2) change over 5 frames, `tx`, `ty` (mm) and yaw (deg), each as 11
//!   classes with the official bin edges; accuracy per head and the RMSE of the bin centres.
//! - **texture** (T5): the sequence's surface texture; accuracy.
//! - **grasp** (T4): whether a press followed by a tangential ramp ends in gross slip, from
//!   frames before the ramp passes half its final displacement; accuracy and F1.

use burn::prelude::*;
use burn::tensor::activation::{log_softmax, sigmoid, tanh};
use serde::{Deserialize, Serialize};

use crate::labels::{SequenceLabels, SlipState};

/// A TacBench task.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TaskKind {
    /// T1: 3-axis force.
    Force,
    /// T2: slip (friction-cone label and stick/partial/gross state).
    Slip,
    /// T3: SE(2) pose change over 5 frames.
    Pose,
    /// T5: surface texture class.
    Texture,
    /// T4: grasp outcome (stick or gross slip at the end of a tangential ramp).
    Grasp,
}

impl TaskKind {
    /// The name in configs, files and tables.
    pub fn name(self) -> &'static str {
        match self {
            TaskKind::Force => "force",
            TaskKind::Slip => "slip",
            TaskKind::Pose => "pose",
            TaskKind::Texture => "texture",
            TaskKind::Grasp => "grasp",
        }
    }

    /// The metrics reported, the first being the one epochs are chosen on and charts show.
    pub fn metrics(self) -> &'static [Metric] {
        match self {
            TaskKind::Force => &[
                Metric::RmseMn,
                Metric::RmseXMn,
                Metric::RmseYMn,
                Metric::RmseZMn,
            ],
            TaskKind::Slip => &[
                Metric::F1,
                Metric::BalancedAccuracy,
                Metric::StateBalancedAccuracy,
            ],
            TaskKind::Pose => &[
                Metric::Accuracy,
                Metric::AccuracyX,
                Metric::AccuracyY,
                Metric::AccuracyYaw,
                Metric::RmseXyMm,
                Metric::RmseYawDeg,
            ],
            TaskKind::Texture => &[Metric::Accuracy],
            TaskKind::Grasp => &[Metric::Accuracy, Metric::F1],
        }
    }
}

/// A score of a task.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Metric {
    /// Root mean square force error over the three axes (mN).
    RmseMn,
    /// RMSE of Fx (mN).
    RmseXMn,
    /// RMSE of Fy (mN).
    RmseYMn,
    /// RMSE of Fz (mN).
    RmseZMn,
    /// F1 of the positive class (slip; gross-slip outcome).
    F1,
    /// Balanced accuracy of the binary label (mean recall of the two classes).
    BalancedAccuracy,
    /// Balanced accuracy of the stick / partial / gross state.
    StateBalancedAccuracy,
    /// Share of correct classes (pose: mean over the three heads).
    Accuracy,
    /// Pose: accuracy of the tx head.
    AccuracyX,
    /// Pose: accuracy of the ty head.
    AccuracyY,
    /// Pose: accuracy of the yaw head.
    AccuracyYaw,
    /// Pose: RMSE of the bin-centre estimate of (tx, ty) over both axes (mm).
    RmseXyMm,
    /// Pose: RMSE of the bin-centre estimate of yaw (deg).
    RmseYawDeg,
}

impl Metric {
    /// The name in files and tables.
    pub fn name(self) -> &'static str {
        match self {
            Metric::RmseMn => "rmse_mn",
            Metric::RmseXMn => "rmse_x_mn",
            Metric::RmseYMn => "rmse_y_mn",
            Metric::RmseZMn => "rmse_z_mn",
            Metric::F1 => "f1",
            Metric::BalancedAccuracy => "balanced_accuracy",
            Metric::StateBalancedAccuracy => "state_balanced_accuracy",
            Metric::Accuracy => "accuracy",
            Metric::AccuracyX => "accuracy_x",
            Metric::AccuracyY => "accuracy_y",
            Metric::AccuracyYaw => "accuracy_yaw",
            Metric::RmseXyMm => "rmse_xy_mm",
            Metric::RmseYawDeg => "rmse_yaw_deg",
        }
    }

    /// Whether a larger value is better.
    pub fn higher_is_better(self) -> bool {
        !matches!(
            self,
            Metric::RmseMn
                | Metric::RmseXMn
                | Metric::RmseYMn
                | Metric::RmseZMn
                | Metric::RmseXyMm
                | Metric::RmseYawDeg
        )
    }
}

/// Official translation bin edges of the pose task (mm): 11 classes.
pub const POSE_EDGES_MM: [f64; 10] = [-5.0, -2.0, -1.0, -0.5, -0.1, 0.1, 0.5, 1.0, 2.0, 5.0];
/// Official yaw bin edges of the pose task (deg): 11 classes.
pub const POSE_EDGES_DEG: [f64; 10] = [-2.0, -1.0, -0.5, -0.2, -0.03, 0.03, 0.2, 0.5, 1.0, 2.0];
/// Frames the pose change spans.
pub const POSE_SPAN: usize = 5;
/// The friction-cone ratio of the official slip label.
pub const SLIP_CONE_RATIO: f64 = 1.6;
/// Smooth-L1 transition of the official force head (on scaled targets).
pub const SMOOTH_L1_BETA: f64 = 0.02;

/// The bin of `value` among ascending `edges`: the number of edges below it (a value on an
/// edge falls in the lower bin).
pub fn bin_of(value: f64, edges: &[f64]) -> usize {
    edges.iter().filter(|&&e| value > e).count()
}

/// The centre of bin `k` of ascending `edges`: the midpoint of an inner bin; an open end bin
/// sits half its neighbour's width beyond the last edge (−6.5 and 6.5 mm for translation).
pub fn bin_centre(k: usize, edges: &[f64]) -> f64 {
    let n = edges.len();
    match k {
        0 => edges[0] - 0.5 * (edges[1] - edges[0]),
        k if k == n => edges[n - 1] + 0.5 * (edges[n - 1] - edges[n - 2]),
        k => 0.5 * (edges[k - 1] + edges[k]),
    }
}

/// The target of one sample.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Target {
    /// Force `[Fx, Fy, Fz]` (N).
    Force([f64; 3]),
    /// Slip: the cone label, the state (0 stick, 1 partial, 2 gross) and ΔF (N).
    Slip {
        /// ‖F_xy‖ > 1.6 F_z.
        cone: bool,
        /// Stick / partial / gross (0, 1, 2); `None` when the data record no mechanical state
        /// (the official datasets), which leaves the state head out of the loss and metric.
        state: Option<usize>,
        /// Force change since t − 5 (N).
        delta_n: [f64; 3],
    },
    /// Pose change over [`POSE_SPAN`] frames `[tx mm, ty mm, yaw deg]`.
    Pose([f64; 3]),
    /// A class index.
    Class(usize),
}

/// One sample: frame `frame` of sequence `sequence`, and its target.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    /// Sequence index in the dataset.
    pub sequence: usize,
    /// Frame index in the sequence (the current frame t).
    pub frame: usize,
    /// What the probe must read.
    pub target: Target,
}

/// A task's samples on one dataset.
#[derive(Debug, Clone)]
pub struct TaskSamples {
    /// The task.
    pub kind: TaskKind,
    /// Samples in sequence and frame order.
    pub samples: Vec<Sample>,
    /// Class names (texture; grasp: `held`, `slipped`), empty for regression tasks.
    pub classes: Vec<String>,
    /// Class of each sequence for stratified budgets (texture, grasp), `None` otherwise.
    pub sequence_class: Vec<Option<usize>>,
}

/// The class a generated sequence's family name stands for: the name up to a `__` suffix
/// (`ribs_fine__mini` → `ribs_fine`), so one texture under several sensors is one class.
pub fn class_name(family: &str) -> &str {
    family.split("__").next().unwrap_or(family)
}

/// The samples of `kind` in `labels`: frames `t ≥ reach` (every offset of the encoders'
/// frame stacking inside the sequence), every `stride`-th, that carry what the task needs.
/// Errors (naming the label) when no sequence carries it.
pub fn extract(
    kind: TaskKind,
    labels: &[SequenceLabels],
    reach: usize,
    stride: usize,
) -> Result<TaskSamples, String> {
    let stride = stride.max(1);
    let mut samples = Vec::new();
    let mut classes: Vec<String> = Vec::new();
    let mut sequence_class = vec![None; labels.len()];
    let reach = match kind {
        TaskKind::Pose => reach.max(POSE_SPAN),
        _ => reach,
    };
    let missing = |what: &str| {
        format!(
            "the {} task needs `{what}` labels, which the data lack",
            kind.name()
        )
    };
    match kind {
        TaskKind::Texture => {
            let mut names: Vec<String> = labels
                .iter()
                .filter_map(|s| s.class.as_deref().map(|c| class_name(c).to_string()))
                .collect();
            names.sort();
            names.dedup();
            if names.len() < 2 {
                return Err(format!(
                    "the texture task needs at least two classes (family names), found {}",
                    names.len()
                ));
            }
            classes = names;
        }
        TaskKind::Grasp => classes = vec!["held".into(), "slipped".into()],
        _ => {}
    }
    for (s, seq) in labels.iter().enumerate() {
        let n = seq.frames.len();
        let in_contact = |t: usize| {
            seq.frames[t]
                .slip_state
                .is_none_or(|st| st != SlipState::NoContact)
        };
        match kind {
            TaskKind::Force => {
                for t in (reach..n).step_by(stride) {
                    if let Some(f) = seq.frames[t].force_n {
                        samples.push(Sample {
                            sequence: s,
                            frame: t,
                            target: Target::Force(f),
                        });
                    }
                }
            }
            TaskKind::Slip => {
                for t in (reach..n).step_by(stride) {
                    let f = &seq.frames[t];
                    let (Some(cone), Some(delta)) = (f.slip_cone, f.delta_force_n) else {
                        continue;
                    };
                    let state = match f.slip_state {
                        Some(SlipState::Stick) => Some(0),
                        Some(SlipState::Partial) => Some(1),
                        Some(SlipState::Gross) => Some(2),
                        Some(SlipState::NoContact) => continue,
                        None => None,
                    };
                    samples.push(Sample {
                        sequence: s,
                        frame: t,
                        target: Target::Slip {
                            cone,
                            state,
                            delta_n: delta,
                        },
                    });
                }
            }
            TaskKind::Pose => {
                for t in (reach..n).step_by(stride) {
                    let mut change = [0.0; 3];
                    let mut known = true;
                    for f in &seq.frames[t + 1 - POSE_SPAN..=t] {
                        match f.pose_change_se2 {
                            Some(d) => (0..3).for_each(|k| change[k] += d[k]),
                            None => known = false,
                        }
                    }
                    if known && in_contact(t) {
                        samples.push(Sample {
                            sequence: s,
                            frame: t,
                            target: Target::Pose(change),
                        });
                    }
                }
            }
            TaskKind::Texture => {
                let Some(name) = seq.class.as_deref() else {
                    continue;
                };
                let c = classes
                    .iter()
                    .position(|x| x == class_name(name))
                    .expect("classes hold every name");
                sequence_class[s] = Some(c);
                for t in (reach..n).step_by(stride) {
                    if in_contact(t) {
                        samples.push(Sample {
                            sequence: s,
                            frame: t,
                            target: Target::Class(c),
                        });
                    }
                }
            }
            TaskKind::Grasp => {
                let Some(outcome) = grasp_outcome(seq) else {
                    continue;
                };
                let c = usize::from(outcome);
                sequence_class[s] = Some(c);
                for t in grasp_frames(seq)
                    .into_iter()
                    .filter(|&t| t >= reach)
                    .step_by(stride)
                {
                    samples.push(Sample {
                        sequence: s,
                        frame: t,
                        target: Target::Class(c),
                    });
                }
            }
        }
    }
    if samples.is_empty() {
        return Err(match kind {
            TaskKind::Force => missing("force_n"),
            TaskKind::Slip => missing("slip_cone, slip_state and delta_force_n"),
            TaskKind::Pose => missing("pose_change_se2"),
            TaskKind::Texture => missing("family (class)"),
            TaskKind::Grasp => missing("slip_state and pose"),
        } + &format!(" (or no sequence has frames past the first {reach})"));
    }
    Ok(TaskSamples {
        kind,
        samples,
        classes,
        sequence_class,
    })
}

/// Whether a grasp sequence ends in slip: the recorded outcome (a grasp that did not hold),
/// else whether its last frame slips grossly.
pub fn grasp_outcome(seq: &SequenceLabels) -> Option<bool> {
    seq.outcome
        .map(|held| !held)
        .or_else(|| seq.frames.last()?.slip_state.map(|s| s == SlipState::Gross))
}

/// The frames a grasp outcome is predicted from: in contact, and before the tangential motion
/// has passed half of its final displacement (all contact frames when nothing moves or the
/// positions are unknown).
pub fn grasp_frames(seq: &SequenceLabels) -> Vec<usize> {
    let pos: Option<Vec<[f64; 2]>> = seq.frames.iter().map(|f| f.position_mm).collect();
    let shift = |p: &[[f64; 2]], t: usize| (p[t][0] - p[0][0]).hypot(p[t][1] - p[0][1]);
    (0..seq.frames.len())
        .filter(|&t| {
            let contact = seq.frames[t]
                .slip_state
                .is_none_or(|s| s != SlipState::NoContact);
            let early = match &pos {
                Some(p) => shift(p, t) <= 0.5 * shift(p, p.len() - 1),
                None => true,
            };
            contact && early
        })
        .collect()
}

/// The probe head of a task: its outputs, how targets are encoded for the loss, the loss, and
/// how outputs decode into predictions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Head {
    /// The task.
    pub kind: TaskKind,
    /// Force range per axis (N) that tanh/sigmoid outputs are scaled by (force, ΔF).
    pub force_scale_n: [f64; 3],
    /// Class weights of each classification head, from the training samples.
    pub class_weights: Vec<Vec<f64>>,
    /// Output biases that make the force head start at the training samples' mean force
    /// (atanh of the scaled mean for Fx, Fy, its logit for Fz); `None` for other tasks.
    pub force_bias: Option<[f64; 3]>,
}

impl Head {
    /// A head for `kind` with class weights from the `train` samples: the official [0.1, 1]
    /// for the slip cone label, inverse class frequency (normalized to mean 1) elsewhere.
    pub fn new(kind: TaskKind, classes: usize, force_scale_n: [f64; 3], train: &[&Sample]) -> Self {
        let inverse = |counts: Vec<f64>| -> Vec<f64> {
            let present = counts.iter().filter(|&&c| c > 0.0).count().max(1) as f64;
            let total: f64 = counts.iter().sum();
            counts
                .iter()
                .map(|&c| if c > 0.0 { total / (present * c) } else { 0.0 })
                .collect()
        };
        let count = |n: usize, f: &dyn Fn(&Target) -> usize| {
            let mut c = vec![0.0; n];
            for s in train {
                c[f(&s.target)] += 1.0;
            }
            c
        };
        let class_weights = match kind {
            TaskKind::Force | TaskKind::Pose => Vec::new(),
            TaskKind::Slip => vec![
                vec![0.1, 1.0],
                inverse(
                    count(4, &|t| match t {
                        Target::Slip {
                            state: Some(state), ..
                        } => *state,
                        _ => 3,
                    })[..3]
                        .to_vec(),
                ),
            ],
            TaskKind::Texture | TaskKind::Grasp => vec![inverse(count(classes, &|t| match t {
                Target::Class(c) => *c,
                _ => 0,
            }))],
        };
        // The sigmoid on Fz starts at half the range (2.5 N for DIGIT): with AdamW's steps of
        // about the learning rate, a short probe would spend its whole schedule walking the bias
        // to the mean, so the head starts there instead.
        let force_bias = (kind == TaskKind::Force && !train.is_empty()).then(|| {
            let mut mean = [0.0; 3];
            for s in train {
                if let Target::Force(f) = s.target {
                    (0..3).for_each(|k| mean[k] += f[k] / force_scale_n[k] / train.len() as f64);
                }
            }
            let squash = |v: f64, lo: f64| v.clamp(lo + 1e-3, 1.0 - 1e-3);
            [
                squash(mean[0], -1.0).atanh(),
                squash(mean[1], -1.0).atanh(),
                {
                    let p = squash(mean[2], 0.0);
                    (p / (1.0 - p)).ln()
                },
            ]
        });
        Self {
            kind,
            force_scale_n,
            class_weights,
            force_bias,
        }
    }

    /// Outputs of the probe.
    pub fn outputs(&self, classes: usize) -> usize {
        match self.kind {
            TaskKind::Force => 3,
            TaskKind::Slip => 2 + 3 + 3,
            TaskKind::Pose => 3 * 11,
            TaskKind::Texture | TaskKind::Grasp => classes,
        }
    }

    /// Width of an encoded target row (see [`Head::encode`]).
    pub fn target_width(&self, classes: usize) -> usize {
        match self.kind {
            TaskKind::Force => 3,
            TaskKind::Slip => 2 + 3 + 3,
            TaskKind::Pose => 3 * 11,
            TaskKind::Texture | TaskKind::Grasp => classes,
        }
    }

    /// The target as the loss reads it: scaled forces, and for each classification head the
    /// one-hot row times the class's weight.
    pub fn encode(&self, target: &Target, classes: usize) -> Vec<f32> {
        let s = self.force_scale_n;
        let weighted = |k: usize, n: usize, w: &[f64]| -> Vec<f32> {
            (0..n)
                .map(|j| if j == k { w[k] as f32 } else { 0.0 })
                .collect()
        };
        match (self.kind, target) {
            (TaskKind::Force, Target::Force(f)) => (0..3).map(|k| (f[k] / s[k]) as f32).collect(),
            (
                TaskKind::Slip,
                Target::Slip {
                    cone,
                    state,
                    delta_n,
                },
            ) => {
                let mut row = weighted(usize::from(*cone), 2, &self.class_weights[0]);
                match state {
                    Some(k) => row.extend(weighted(*k, 3, &self.class_weights[1])),
                    None => row.extend([0.0; 3]),
                }
                row.extend((0..3).map(|k| (delta_n[k] / s[k]) as f32));
                row
            }
            (TaskKind::Pose, Target::Pose(p)) => {
                let mut row = weighted(bin_of(p[0], &POSE_EDGES_MM), 11, &[1.0; 11]);
                row.extend(weighted(bin_of(p[1], &POSE_EDGES_MM), 11, &[1.0; 11]));
                row.extend(weighted(bin_of(p[2], &POSE_EDGES_DEG), 11, &[1.0; 11]));
                row
            }
            (TaskKind::Texture | TaskKind::Grasp, Target::Class(c)) => {
                weighted(*c, classes, &self.class_weights[0])
            }
            (kind, t) => unreachable!("a {kind:?} head got a {t:?} target"),
        }
    }

    /// The training loss of `out` (`[batch, outputs]`) against encoded targets `[batch, width]`.
    pub fn loss(&self, out: Tensor<2>, target: Tensor<2>) -> Tensor<1> {
        let [b, _] = out.dims();
        let part = |x: &Tensor<2>, from: usize, n: usize| x.clone().narrow(1, from, n);
        match self.kind {
            TaskKind::Force => {
                let pred = bounded_force(out);
                smooth_l1(pred - target, SMOOTH_L1_BETA)
            }
            TaskKind::Slip => {
                let cone = weighted_cross_entropy(part(&out, 0, 2), part(&target, 0, 2));
                let state = weighted_cross_entropy(part(&out, 2, 3), part(&target, 2, 3));
                let delta = smooth_l1(tanh(part(&out, 5, 3)) - part(&target, 5, 3), SMOOTH_L1_BETA);
                cone + state + delta
            }
            TaskKind::Pose => (0..3)
                .map(|h| weighted_cross_entropy(part(&out, 11 * h, 11), part(&target, 11 * h, 11)))
                .reduce(|a, b| a + b)
                .unwrap_or_else(|| Tensor::zeros([1], &out.device())),
            TaskKind::Texture | TaskKind::Grasp => {
                let [_, c] = out.dims();
                weighted_cross_entropy(out, target.narrow(1, 0, c))
            }
        }
        .reshape([1])
        .mul_scalar(if b > 0 { 1.0 } else { 0.0 })
    }

    /// Decodes one sample's outputs into a prediction: force `[Fx, Fy, Fz]` (N); slip
    /// `[cone, state]`; pose `[bin x, bin y, bin yaw]`; class `[class]`.
    pub fn decode(&self, out: &[f32]) -> Vec<f64> {
        let argmax = |v: &[f32]| {
            v.iter()
                .enumerate()
                .fold((0, f32::NEG_INFINITY), |best, (i, &x)| {
                    if x > best.1 { (i, x) } else { best }
                })
                .0 as f64
        };
        let s = self.force_scale_n;
        match self.kind {
            TaskKind::Force => vec![
                s[0] * (out[0] as f64).tanh(),
                s[1] * (out[1] as f64).tanh(),
                s[2] / (1.0 + (-(out[2] as f64)).exp()),
            ],
            TaskKind::Slip => vec![argmax(&out[0..2]), argmax(&out[2..5])],
            TaskKind::Pose => (0..3).map(|h| argmax(&out[11 * h..11 * (h + 1)])).collect(),
            TaskKind::Texture | TaskKind::Grasp => vec![argmax(out)],
        }
    }
}

/// The official force head's bounded outputs: tanh on Fx, Fy and a sigmoid on Fz.
fn bounded_force(out: Tensor<2>) -> Tensor<2> {
    let xy = tanh(out.clone().narrow(1, 0, 2));
    let z = sigmoid(out.narrow(1, 2, 1));
    Tensor::cat(vec![xy, z], 1)
}

/// Smooth-L1 (Huber / β) of a residual, averaged: 0.5 r²/β below β, |r| − β/2 above.
fn smooth_l1(r: Tensor<2>, beta: f64) -> Tensor<1> {
    let a = r.abs();
    let quad = a.clone().powi_scalar(2).mul_scalar(0.5 / beta);
    let lin = a.clone().sub_scalar(0.5 * beta);
    let small = a.lower_elem(beta);
    lin.mask_where(small, quad).mean()
}

/// Cross-entropy with class weights baked into the one-hot targets (`target` = w_c at the
/// true class c, 0 elsewhere): Σ −w_c log p_c / Σ w_c, PyTorch's weighted mean.
fn weighted_cross_entropy(logits: Tensor<2>, target: Tensor<2>) -> Tensor<1> {
    let logp = log_softmax(logits, 1);
    let num = (logp * target.clone()).sum().neg();
    num / target.sum().clamp_min(1e-12)
}

/// The value of `metric` over the samples `rows` from their predictions (see
/// [`Head::decode`]) and targets.
pub fn score(metric: Metric, rows: &[usize], preds: &[Vec<f64>], samples: &[Sample]) -> f64 {
    let n = rows.len().max(1) as f64;
    let rmse_axes = |axes: &[usize]| -> f64 {
        let mut se = 0.0;
        for &i in rows {
            if let Target::Force(f) = samples[i].target {
                for &k in axes {
                    se += (preds[i][k] - f[k]).powi(2);
                }
            }
        }
        1000.0 * (se / (n * axes.len() as f64)).sqrt()
    };
    let binary = |pos: &dyn Fn(usize) -> (bool, bool)| -> (f64, f64) {
        // (F1 of the positive class, balanced accuracy)
        let (mut tp, mut fp, mut tn, mut fneg) = (0.0, 0.0, 0.0, 0.0);
        for &i in rows {
            match pos(i) {
                (true, true) => tp += 1.0,
                (false, true) => fp += 1.0,
                (false, false) => tn += 1.0,
                (true, false) => fneg += 1.0,
            }
        }
        let f1 = if tp > 0.0 {
            2.0 * tp / (2.0 * tp + fp + fneg)
        } else {
            0.0
        };
        (f1, balanced(&[(tp, tp + fneg), (tn, tn + fp)]))
    };
    let pose_head = |h: usize| -> f64 {
        let edges: &[f64] = if h == 2 {
            &POSE_EDGES_DEG
        } else {
            &POSE_EDGES_MM
        };
        rows.iter()
            .filter(|&&i| match samples[i].target {
                Target::Pose(p) => preds[i][h] as usize == bin_of(p[h], edges),
                _ => false,
            })
            .count() as f64
            / n
    };
    let pose_rmse = |heads: &[usize]| -> f64 {
        let mut se = 0.0;
        for &i in rows {
            if let Target::Pose(p) = samples[i].target {
                for &h in heads {
                    let edges: &[f64] = if h == 2 {
                        &POSE_EDGES_DEG
                    } else {
                        &POSE_EDGES_MM
                    };
                    se += (bin_centre(preds[i][h] as usize, edges) - p[h]).powi(2);
                }
            }
        }
        (se / (n * heads.len() as f64)).sqrt()
    };
    let class_of = |i: usize| match samples[i].target {
        Target::Class(c) => c,
        Target::Slip { cone, .. } => usize::from(cone),
        _ => 0,
    };
    match metric {
        Metric::RmseMn => rmse_axes(&[0, 1, 2]),
        Metric::RmseXMn => rmse_axes(&[0]),
        Metric::RmseYMn => rmse_axes(&[1]),
        Metric::RmseZMn => rmse_axes(&[2]),
        Metric::F1 => binary(&|i| (class_of(i) == 1, preds[i][0] as usize == 1)).0,
        Metric::BalancedAccuracy => binary(&|i| (class_of(i) == 1, preds[i][0] as usize == 1)).1,
        Metric::StateBalancedAccuracy => {
            let mut per = [(0.0, 0.0); 3];
            for &i in rows {
                if let Target::Slip {
                    state: Some(state), ..
                } = samples[i].target
                {
                    per[state].1 += 1.0;
                    if preds[i][1] as usize == state {
                        per[state].0 += 1.0;
                    }
                }
            }
            balanced(&per)
        }
        Metric::Accuracy => match samples.first().map(|s| s.target) {
            Some(Target::Pose(_)) => (pose_head(0) + pose_head(1) + pose_head(2)) / 3.0,
            _ => {
                rows.iter()
                    .filter(|&&i| preds[i][0] as usize == class_of(i))
                    .count() as f64
                    / n
            }
        },
        Metric::AccuracyX => pose_head(0),
        Metric::AccuracyY => pose_head(1),
        Metric::AccuracyYaw => pose_head(2),
        Metric::RmseXyMm => pose_rmse(&[0, 1]),
        Metric::RmseYawDeg => pose_rmse(&[2]),
    }
}

/// Mean recall over the classes present: `(correct, total)` per class; NaN when no sample
/// carries the label (a metric that does not apply, as the state of the official slip data).
fn balanced(per_class: &[(f64, f64)]) -> f64 {
    let present: Vec<f64> = per_class
        .iter()
        .filter(|(_, total)| *total > 0.0)
        .map(|(ok, total)| ok / total)
        .collect();
    if present.is_empty() {
        f64::NAN
    } else {
        present.iter().sum::<f64>() / present.len() as f64
    }
}
