//! Label extraction and metrics of the five TacBench tasks against hand-computed values.

use burn::prelude::*;
use sparsh_bench::labels::{FrameLabel, SequenceLabels, SlipState};
use sparsh_bench::tacbench::tasks::{
    Head, Metric, POSE_EDGES_DEG, POSE_EDGES_MM, Sample, Target, TaskKind, bin_centre, bin_of,
    class_name, extract, grasp_frames, grasp_outcome, score,
};

fn frame(force: [f64; 3], state: SlipState) -> FrameLabel {
    FrameLabel {
        force_n: Some(force),
        delta_force_n: Some([0.0, 0.0, 0.1]),
        slip_state: Some(state),
        slip_cone: Some(force[0].hypot(force[1]) > 1.6 * force[2]),
        pose_change_se2: Some([0.1, -0.2, 0.5]),
        position_mm: Some([0.0, 0.0]),
    }
}

fn sequence(n: usize, state: SlipState) -> SequenceLabels {
    SequenceLabels {
        test: Some(false),
        class: Some("ribs__digit".into()),
        indenter: None,
        outcome: None,
        frames: (0..n)
            .map(|t| frame([0.01 * t as f64, 0.0, 0.5], state))
            .collect(),
    }
}

#[test]
fn force_samples_skip_the_reach_and_take_the_stride() {
    let labels = vec![
        sequence(12, SlipState::Stick),
        sequence(4, SlipState::Stick),
    ];
    let s = extract(TaskKind::Force, &labels, 5, 3).expect("force labels");
    // sequence 0: t = 5, 8, 11; sequence 1 is shorter than the reach
    let at: Vec<(usize, usize)> = s.samples.iter().map(|x| (x.sequence, x.frame)).collect();
    assert_eq!(at, [(0, 5), (0, 8), (0, 11)]);
    assert_eq!(s.samples[1].target, Target::Force([0.08, 0.0, 0.5]));
}

#[test]
fn force_rmse_is_a_root_mean_square_in_millinewtons() {
    let samples: Vec<Sample> = [[1.0, 0.0, 2.0], [0.0, -1.0, 1.0]]
        .iter()
        .enumerate()
        .map(|(i, &f)| Sample {
            sequence: i,
            frame: 0,
            target: Target::Force(f),
        })
        .collect();
    // errors: sample 0 (0.1, 0, −0.2), sample 1 (0, 0.3, 0.4)
    let preds = vec![vec![1.1, 0.0, 1.8], vec![0.0, -0.7, 1.4]];
    let rows = [0, 1];
    let rmse = |m| score(m, &rows, &preds, &samples);
    let all = ((0.01 + 0.04 + 0.09 + 0.16) / 6.0f64).sqrt() * 1000.0;
    assert!((rmse(Metric::RmseMn) - all).abs() < 1e-9);
    assert!((rmse(Metric::RmseXMn) - (0.01f64 / 2.0).sqrt() * 1000.0).abs() < 1e-9);
    assert!((rmse(Metric::RmseYMn) - (0.09f64 / 2.0).sqrt() * 1000.0).abs() < 1e-9);
    assert!((rmse(Metric::RmseZMn) - (0.2f64 / 2.0).sqrt() * 1000.0).abs() < 1e-9);
    // not the official mean absolute error: (0.1 + 0.2 + 0.3 + 0.4)/6 = 0.1667 N
    assert!((rmse(Metric::RmseMn) - 166.7).abs() > 10.0);
}

#[test]
fn slip_keeps_contact_frames_and_scores_f1_and_balanced_accuracy() {
    let mut seq = sequence(8, SlipState::Partial);
    seq.frames[6].slip_state = Some(SlipState::NoContact);
    seq.frames[7].force_n = Some([1.0, 0.0, 0.5]); // 1.0 > 1.6 · 0.5: slips
    seq.frames[7].slip_cone = Some(true);
    seq.frames[7].slip_state = Some(SlipState::Gross);
    let s = extract(TaskKind::Slip, &[seq], 5, 1).expect("slip labels");
    let at: Vec<usize> = s.samples.iter().map(|x| x.frame).collect();
    assert_eq!(at, [5, 7], "the no-contact frame 6 is not a slip sample");
    assert_eq!(
        s.samples[1].target,
        Target::Slip {
            cone: true,
            state: Some(2),
            delta_n: [0.0, 0.0, 0.1]
        }
    );
    // eight samples: cone truth 1 1 1 0 0 0 0 0, predictions 1 0 1 1 0 0 0 0
    let truth = [true, true, true, false, false, false, false, false];
    let pred = [1.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0];
    let states = [2, 2, 1, 0, 0, 1, 1, 0];
    let pstates = [2.0, 1.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0];
    let samples: Vec<Sample> = (0..8)
        .map(|i| Sample {
            sequence: i,
            frame: 0,
            target: Target::Slip {
                cone: truth[i],
                state: Some(states[i]),
                delta_n: [0.0; 3],
            },
        })
        .collect();
    let preds: Vec<Vec<f64>> = (0..8).map(|i| vec![pred[i], pstates[i]]).collect();
    let rows: Vec<usize> = (0..8).collect();
    // tp 2, fp 1, fn 1: F1 = 4/6; recall of slip 2/3, of no slip 4/5
    assert!((score(Metric::F1, &rows, &preds, &samples) - 4.0 / 6.0).abs() < 1e-12);
    let bal = (2.0 / 3.0 + 4.0 / 5.0) / 2.0;
    assert!((score(Metric::BalancedAccuracy, &rows, &preds, &samples) - bal).abs() < 1e-12);
    // states: stick 3 of 3 right, partial 2 of 3, gross 1 of 2
    let state_bal = (1.0 + 2.0 / 3.0 + 0.5) / 3.0;
    assert!(
        (score(Metric::StateBalancedAccuracy, &rows, &preds, &samples) - state_bal).abs() < 1e-12
    );
}

#[test]
fn pose_bins_follow_the_official_edges() {
    assert_eq!(bin_of(-7.0, &POSE_EDGES_MM), 0);
    assert_eq!(
        bin_of(-5.0, &POSE_EDGES_MM),
        0,
        "a value on an edge falls in the lower bin"
    );
    assert_eq!(bin_of(0.0, &POSE_EDGES_MM), 5);
    assert_eq!(bin_of(0.3, &POSE_EDGES_MM), 6);
    assert_eq!(bin_of(6.0, &POSE_EDGES_MM), 10);
    assert_eq!(bin_of(0.1, &POSE_EDGES_DEG), 6);
    assert_eq!(bin_centre(5, &POSE_EDGES_MM), 0.0);
    assert_eq!(bin_centre(6, &POSE_EDGES_MM), 0.3);
    assert_eq!(bin_centre(0, &POSE_EDGES_MM), -6.5);
    assert_eq!(bin_centre(10, &POSE_EDGES_DEG), 2.5);
}

#[test]
fn pose_change_sums_five_frames_and_scores_bins() {
    let seq = sequence(7, SlipState::Stick);
    let s = extract(TaskKind::Pose, &[seq], 0, 1).expect("pose labels");
    // the change over 5 frames needs frames t−4 … t: samples from t = 5 (reach 5)
    assert_eq!(s.samples[0].frame, 5);
    match s.samples[0].target {
        Target::Pose(p) => {
            assert!((p[0] - 0.5).abs() < 1e-12 && (p[1] + 1.0).abs() < 1e-12);
            assert!((p[2] - 2.5).abs() < 1e-12);
        }
        t => panic!("{t:?}"),
    }
    // two samples; predictions: x right twice, y right once, yaw wrong once
    let samples = vec![
        Sample {
            sequence: 0,
            frame: 5,
            target: Target::Pose([0.3, -1.5, 0.1]),
        },
        Sample {
            sequence: 1,
            frame: 5,
            target: Target::Pose([0.0, 0.0, -3.0]),
        },
    ];
    let preds = vec![vec![6.0, 2.0, 6.0], vec![5.0, 6.0, 5.0]];
    let rows = [0, 1];
    assert_eq!(score(Metric::AccuracyX, &rows, &preds, &samples), 1.0);
    assert_eq!(score(Metric::AccuracyY, &rows, &preds, &samples), 0.5);
    assert_eq!(score(Metric::AccuracyYaw, &rows, &preds, &samples), 0.5);
    assert!((score(Metric::Accuracy, &rows, &preds, &samples) - 2.0 / 3.0).abs() < 1e-12);
    // bin centres: x 0.3 and 0.0 (exact); y −1.5 and 0.3 (errors 0, 0.3)
    let xy = ((0.0 + 0.0 + 0.0 + 0.09) / 4.0f64).sqrt();
    assert!((score(Metric::RmseXyMm, &rows, &preds, &samples) - xy).abs() < 1e-12);
    // yaw centres: bin 6 → 0.115 (error 0.015), bin 5 → 0 (error 3)
    let yaw = ((0.015f64.powi(2) + 9.0) / 2.0).sqrt();
    assert!((score(Metric::RmseYawDeg, &rows, &preds, &samples) - yaw).abs() < 1e-12);
}

#[test]
fn texture_classes_are_family_names_without_the_sensor_suffix() {
    assert_eq!(class_name("knurl_fine__mini"), "knurl_fine");
    assert_eq!(class_name("dots"), "dots");
    let mut a = sequence(7, SlipState::Stick);
    a.class = Some("weave__mini".into());
    let mut b = sequence(7, SlipState::Stick);
    b.class = Some("dots__digit".into());
    let mut c = sequence(7, SlipState::Stick);
    c.class = Some("weave__digit".into());
    let s = extract(TaskKind::Texture, &[a, b, c], 5, 1).expect("classes");
    assert_eq!(s.classes, ["dots", "weave"]);
    assert_eq!(s.sequence_class, [Some(1), Some(0), Some(1)]);
    let one_class = vec![sequence(7, SlipState::Stick)];
    let err = extract(TaskKind::Texture, &one_class, 5, 1).unwrap_err();
    assert!(err.contains("at least two classes"), "{err}");
}

#[test]
fn grasp_outcome_and_frames_before_half_the_ramp() {
    let mut seq = sequence(10, SlipState::Stick);
    seq.frames[0].slip_state = Some(SlipState::NoContact);
    // still for frames 0–3, then 0.5 mm a frame: final shift 3.0 mm, half at frame 6
    for (t, f) in seq.frames.iter_mut().enumerate() {
        f.position_mm = Some([0.5 * t.saturating_sub(3) as f64, 0.0]);
    }
    assert_eq!(grasp_outcome(&seq), Some(false));
    assert_eq!(grasp_frames(&seq), [1, 2, 3, 4, 5, 6]);
    seq.frames[9].slip_state = Some(SlipState::Gross);
    assert_eq!(grasp_outcome(&seq), Some(true));
    seq.outcome = Some(true);
    assert_eq!(
        grasp_outcome(&seq),
        Some(false),
        "a recorded outcome (the grasp held) wins"
    );
    let s = extract(TaskKind::Grasp, &[seq], 5, 1).expect("grasp");
    let at: Vec<usize> = s.samples.iter().map(|x| x.frame).collect();
    assert_eq!(at, [5, 6]);
    assert_eq!(s.samples[0].target, Target::Class(0));
}

#[test]
fn missing_labels_name_what_the_task_needs() {
    let mut seq = sequence(8, SlipState::Stick);
    for f in &mut seq.frames {
        f.pose_change_se2 = None;
    }
    let err = extract(TaskKind::Pose, &[seq], 5, 1).unwrap_err();
    assert!(err.contains("pose_change_se2"), "{err}");
}

#[test]
fn heads_decode_and_weight_as_the_official_ones() {
    let device = Device::flex();
    let force = Head::new(TaskKind::Force, 0, [4.0, 4.0, 5.0], &[]);
    // tanh(0) · 4 = 0, sigmoid(0) · 5 = 2.5
    assert_eq!(force.decode(&[0.0, 0.0, 0.0]), vec![0.0, 0.0, 2.5]);
    assert_eq!(
        force.encode(&Target::Force([2.0, -1.0, 2.5]), 0),
        vec![0.5, -0.25, 0.5]
    );
    // smooth-L1 with β = 0.02 on bounded outputs: outputs 0 → (0, 0, 0.5); targets
    // (0.01, 0, 0.5) and (0.5, 0, 0.5): residuals 0.01 (quadratic: 0.5·1e-4/0.02 = 0.0025) and
    // 0.5 (linear: 0.49), mean over 6 entries
    let out = Tensor::<2>::zeros([2, 3], &device);
    let target = Tensor::<2>::from_floats([[0.01, 0.0, 0.5], [0.5, 0.0, 0.5]], &device);
    let loss: f32 = force.loss(out, target).into_scalar();
    assert!((loss as f64 - (0.0025 + 0.49) / 6.0).abs() < 1e-6, "{loss}");
    // slip weights: the official [0.1, 1] on the cone label
    let train = [Sample {
        sequence: 0,
        frame: 0,
        target: Target::Slip {
            cone: false,
            state: Some(0),
            delta_n: [0.0; 3],
        },
    }];
    let refs: Vec<&Sample> = train.iter().collect();
    let slip = Head::new(TaskKind::Slip, 0, [4.0, 4.0, 5.0], &refs);
    assert_eq!(slip.class_weights[0], [0.1, 1.0]);
    // weighted cross-entropy of two samples of a 2-class head with weights (1, 3): uniform
    // logits give −log ½ whatever the weights
    let mut texture = Head::new(TaskKind::Texture, 2, [1.0; 3], &[]);
    texture.class_weights = vec![vec![1.0, 3.0]];
    let t0 = texture.encode(&Target::Class(0), 2);
    let t1 = texture.encode(&Target::Class(1), 2);
    assert_eq!((t0.clone(), t1.clone()), (vec![1.0, 0.0], vec![0.0, 3.0]));
    let target = Tensor::<1>::from_floats([t0, t1].concat().as_slice(), &device).reshape([2, 2]);
    let uniform: f32 = texture
        .loss(Tensor::zeros([2, 2], &device), target.clone())
        .into_scalar();
    assert!((uniform as f64 - std::f64::consts::LN_2).abs() < 1e-6);
    // logits favouring class 0 by 1 on both samples: −(1·log σ(1) + 3·log σ(−1)) / 4
    let logits = Tensor::<2>::from_floats([[1.0, 0.0], [1.0, 0.0]], &device);
    let got: f32 = texture.loss(logits, target).into_scalar();
    let sig = |x: f64| 1.0 / (1.0 + (-x).exp());
    let want = -(sig(1.0).ln() + 3.0 * sig(-1.0).ln()) / 4.0;
    assert!((got as f64 - want).abs() < 1e-6, "{got} vs {want}");
}

#[test]
fn slip_without_a_mechanical_state_leaves_the_state_head_out() {
    // the official force/slip data record the cone label but no stick/partial/gross state
    let mut seq = sequence(7, SlipState::Stick);
    for f in &mut seq.frames {
        f.slip_state = None;
    }
    let s = extract(TaskKind::Slip, &[seq], 5, 1).expect("slip labels");
    assert_eq!(
        s.samples[0].target,
        Target::Slip {
            cone: false,
            state: None,
            delta_n: [0.0, 0.0, 0.1]
        }
    );
    let refs: Vec<&Sample> = s.samples.iter().collect();
    let head = Head::new(TaskKind::Slip, 0, [4.0, 4.0, 5.0], &refs);
    let row = head.encode(&s.samples[0].target, 0);
    assert_eq!(&row[2..5], &[0.0, 0.0, 0.0], "no weight on the state head");
    let preds = vec![vec![0.0, 1.0]; s.samples.len()];
    let rows: Vec<usize> = (0..s.samples.len()).collect();
    assert!(
        score(Metric::StateBalancedAccuracy, &rows, &preds, &s.samples).is_nan(),
        "a metric that does not apply is not a score of 0"
    );
    assert_eq!(
        score(Metric::BalancedAccuracy, &rows, &preds, &s.samples),
        1.0
    );
}

#[test]
fn the_force_head_starts_at_the_training_mean() {
    let train: Vec<Sample> = [[0.4, -0.8, 1.0], [1.2, 0.0, 2.0]]
        .iter()
        .map(|&f| Sample {
            sequence: 0,
            frame: 0,
            target: Target::Force(f),
        })
        .collect();
    let refs: Vec<&Sample> = train.iter().collect();
    let head = Head::new(TaskKind::Force, 0, [4.0, 4.0, 5.0], &refs);
    let bias = head.force_bias.expect("a force head has a starting bias");
    let start = head.decode(&bias.map(|b| b as f32));
    for (got, want) in start.iter().zip([0.8, -0.4, 1.5]) {
        assert!((got - want).abs() < 1e-6, "{start:?}");
    }
    assert!(
        Head::new(TaskKind::Pose, 0, [4.0; 3], &refs)
            .force_bias
            .is_none()
    );
}

/// 30 sequences of a force task: indenters cycle sphere, box, capsule, cylinder, and every
/// sixth sequence is a held-out torus; `recorded`: the labels name them.
fn shaped_run(
    validation_shapes: &[&str],
    recorded: bool,
) -> Result<sparsh_bench::tacbench::run::TaskRun, String> {
    use sparsh_bench::labels::LabelledData;
    use std::sync::Arc;
    let labels: Vec<SequenceLabels> = (0..30)
        .map(|s| SequenceLabels {
            test: Some(s % 6 == 5),
            indenter: recorded.then(|| {
                if s % 6 == 5 {
                    "torus"
                } else {
                    ["sphere", "box", "capsule", "cylinder"][s % 4]
                }
                .into()
            }),
            ..sequence(1, SlipState::Stick)
        })
        .collect();
    let samples = sparsh_bench::tacbench::tasks::TaskSamples {
        kind: TaskKind::Force,
        samples: (0..30)
            .map(|s| Sample {
                sequence: s,
                frame: 0,
                target: Target::Force([0.0, 0.0, 0.5]),
            })
            .collect(),
        classes: Vec::new(),
        sequence_class: vec![None; 30],
    };
    let data = Arc::new(LabelledData {
        source: "shaped".into(),
        dataset: sparsh_ssl::data::Dataset {
            sequences: Vec::new(),
            size: [1, 1],
        },
        labels,
    });
    let shapes: Vec<String> = validation_shapes.iter().map(|s| s.to_string()).collect();
    sparsh_bench::tacbench::run::TaskRun::new(data, samples, &shapes)
}

#[test]
fn validation_by_shape_holds_every_sequence_of_that_shape_and_none_other() {
    let shape_of = |s: usize| {
        if s % 6 == 5 {
            "torus"
        } else {
            ["sphere", "box", "capsule", "cylinder"][s % 4]
        }
    };
    let run = shaped_run(&["box"], true).expect("a split");
    let seqs = |rows: &[usize]| -> Vec<usize> {
        let mut s: Vec<usize> = rows
            .iter()
            .map(|&r| run.samples.samples[r].sequence)
            .collect();
        s.dedup();
        s
    };
    let boxes: Vec<usize> = (0..30).filter(|&s| shape_of(s) == "box").collect();
    assert_eq!(seqs(&run.val), boxes);
    assert_eq!(seqs(&run.test), [5, 11, 17, 23, 29]);
    // the seen-shape test split and training hold the other training shapes only
    for &s in seqs(&run.seen).iter().chain(&run.train_sequences) {
        assert!(
            shape_of(s) != "box" && shape_of(s) != "torus",
            "sequence {s}"
        );
    }
    let mut all: Vec<usize> = [seqs(&run.val), seqs(&run.test), seqs(&run.seen)].concat();
    all.extend(&run.train_sequences);
    all.sort_unstable();
    assert_eq!(all, (0..30).collect::<Vec<_>>());
    // without it, validation is every fifth training sequence, whatever its shape
    let by_sequence = shaped_run(&[], true).expect("a split");
    assert!(seqs(&by_sequence.val).iter().any(|&s| shape_of(s) != "box"));
}

#[test]
fn validation_by_an_untrained_or_unrecorded_shape_is_refused() {
    let err = shaped_run(&["torus"], true).map(|_| ()).unwrap_err();
    assert!(
        err.contains("\"torus\"") && err.contains("box, capsule, cylinder, sphere"),
        "{err}"
    );
    let err = shaped_run(&["cube"], true).map(|_| ()).unwrap_err();
    assert!(err.contains("validation_shapes"), "{err}");
    let err = shaped_run(&["box"], false).map(|_| ()).unwrap_err();
    assert!(err.contains("regenerate"), "{err}");
}
