//! The objectives' losses, the DINO centre, the EMA teacher update and the schedules on fixed
//! small inputs against independent NumPy references written from the papers and the official
//! code (`tests/numpy_losses.py`). Skips, saying so, when `python3` with numpy is unavailable
//! (`pip install numpy`), unless `SPARSH_REQUIRE_PYTHON` is set, when it fails instead.

mod common;

use burn::module::{Module, ModuleVisitor, Param};
use burn::prelude::*;
use serde_json::{Value, json};
use sparsh_ssl::device::seeded_module;
use sparsh_ssl::dino::{
    TeacherNorm, cross_entropy, dino_cross_entropy, koleo, teacher_targets, updated_center,
};
use sparsh_ssl::ema::{ema_update, momentum_at};
use sparsh_ssl::jepa::{JepaLoss, TargetNorm, latent_loss, regression_targets};
use sparsh_ssl::mae::masked_mse;
use sparsh_ssl::recipe::{DinoSection, OptimSection};
use sparsh_ssl::rng::Rng;
use sparsh_ssl::vit::VitConfig;

/// Relative tolerance of an f32 result against the float64 reference.
const F32_TOL: f64 = 1e-5;

/// The reference's answer to `case`, or `None` (a skip) without python3 + numpy.
fn reference(case: Value) -> Option<Value> {
    common::python_ready("numpy_losses")
        .then(|| common::run_script("numpy_losses.py", &[], &case.to_string()))
}

fn normal(rng: &mut Rng, n: usize, mean: f64, std: f64) -> Vec<f32> {
    (0..n)
        .map(|_| {
            let u = rng.uniform().max(1e-12);
            let v = rng.uniform();
            (mean + std * (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()) as f32
        })
        .collect()
}

fn tensor<const D: usize>(values: &[f32], shape: [usize; D]) -> Tensor<D> {
    Tensor::<1>::from_floats(values, &Device::flex()).reshape(shape)
}

fn array<const D: usize>(values: &[f32], shape: [usize; D]) -> Value {
    json!({ "shape": shape.to_vec(), "data": values })
}

fn values<const D: usize>(t: Tensor<D>) -> Vec<f64> {
    t.into_data()
        .try_to_vec::<f32>()
        .unwrap()
        .into_iter()
        .map(f64::from)
        .collect()
}

fn scalar(t: Tensor<1>) -> f64 {
    t.into_scalar::<f32>() as f64
}

fn reference_values(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

/// Largest |ours − reference| over the largest |reference|; asserts it is at most `tol`.
fn assert_close(what: &str, ours: &[f64], reference: &[f64], tol: f64) -> f64 {
    assert_eq!(ours.len(), reference.len(), "{what}: length");
    let scale = reference.iter().fold(0f64, |m, v| m.max(v.abs()));
    let err = ours
        .iter()
        .zip(reference)
        .fold(0f64, |m, (a, b)| m.max((a - b).abs()));
    let rel = err / scale.max(1e-30);
    eprintln!("{what}: relative difference {rel:.2e}");
    assert!(
        rel <= tol,
        "{what}: relative difference {rel:.3e} > {tol:e}"
    );
    rel
}

#[test]
fn mae_masked_mse_matches_numpy() {
    let (b, n, d) = (3, 8, 12);
    let mut rng = Rng::new(1);
    // pixel patches with their own brightness and contrast, so that norm_pix_loss matters
    let mut target = Vec::with_capacity(b * n * d);
    for _ in 0..b * n {
        let (offset, gain) = (rng.range_f64(0.2, 0.8), rng.range_f64(0.05, 0.3));
        target.extend(
            normal(&mut rng, d, 0.0, 1.0)
                .iter()
                .map(|v| (offset + gain * *v as f64) as f32),
        );
    }
    let masked: Vec<Vec<bool>> = (0..b)
        .map(|i| (0..n).map(|j| (j + i) % 3 != 0).collect())
        .collect();
    // far-off predictions on the visible patches: counting them would change the loss
    let mut pred = normal(&mut rng, b * n * d, 0.3, 0.5);
    for (i, row) in masked.iter().enumerate() {
        for (j, &m) in row.iter().enumerate() {
            if !m {
                let s = (i * n + j) * d;
                pred[s..s + d].iter_mut().for_each(|v| *v += 5.0);
            }
        }
    }
    let Some(r) = reference(json!({
        "case": "mae",
        "pred": array(&pred, [b, n, d]),
        "target": array(&target, [b, n, d]),
        "mask": masked,
    })) else {
        return;
    };
    for (key, norm_pix) in [("plain", false), ("norm_pix", true)] {
        let ours = scalar(masked_mse(
            tensor(&pred, [b, n, d]),
            tensor(&target, [b, n, d]),
            &masked,
            norm_pix,
        ));
        assert_close(
            &format!("MAE {key}"),
            &[ours],
            &[r[key].as_f64().unwrap()],
            F32_TOL,
        );
    }
}

#[test]
fn dino_loss_centre_and_teacher_targets_match_numpy() {
    // 2 global and 3 local views of 4 samples, 16 prototypes
    let (b, g, views, k) = (4, 2, 5, 16);
    let mut rng = Rng::new(2);
    let t = normal(&mut rng, g * b * k, 0.0, 0.5);
    let s = normal(&mut rng, views * b * k, 0.0, 0.5);
    let center = normal(&mut rng, k, 0.0, 0.2);
    let (tt, ts, m) = (0.04, 0.1, 0.9);
    let Some(r) = reference(json!({
        "case": "dino",
        "batch": b,
        "teacher": array(&t, [g * b, k]),
        "student": array(&s, [views * b, k]),
        "center": array(&center, [1, k]),
        "teacher_temp": tt,
        "student_temp": ts,
        "center_momentum": m,
    })) else {
        return;
    };
    let t_prob = teacher_targets(
        tensor(&t, [g * b, k]),
        tensor(&center, [1, k]),
        TeacherNorm::Center,
        tt,
    );
    let loss = scalar(dino_cross_entropy(
        t_prob,
        tensor(&s, [views * b, k]),
        b,
        ts,
    ));
    assert_close(
        "DINO loss",
        &[loss],
        &[r["loss"].as_f64().unwrap()],
        F32_TOL,
    );
    let c = updated_center(
        tensor(&center, [1, k]),
        tensor(&t, [g * b, k]).mean_dim(0),
        m,
    );
    assert_close(
        "DINO centre",
        &values(c),
        &reference_values(&r["center"]),
        F32_TOL,
    );
    let batch = teacher_targets(
        tensor(&t, [g * b, k]),
        tensor(&center, [1, k]),
        TeacherNorm::Batch,
        tt,
    );
    assert_close(
        "DINO batch-standardized teacher",
        &values(batch),
        &reference_values(&r["teacher_batch"]),
        F32_TOL,
    );
}

#[test]
fn ibot_patch_loss_matches_numpy() {
    // 4 view rows of 6 tokens, 2 masked in each, 16 prototypes
    let (rows, tokens, k) = (4, 6, 16);
    let masks: Vec<Vec<bool>> = (0..rows)
        .map(|i| {
            (0..tokens)
                .map(|j| j == i || j == (i + 3) % tokens)
                .collect()
        })
        .collect();
    let n = rows * 2;
    let mut rng = Rng::new(3);
    let t = normal(&mut rng, n * k, 0.1, 0.4);
    let s = normal(&mut rng, n * k, 0.0, 0.5);
    let (tt, ts) = (0.25, 0.1);
    let Some(r) = reference(json!({
        "case": "ibot",
        "teacher": array(&t, [n, k]),
        "student": array(&s, [n, k]),
        "masks": masks,
        "teacher_temp": tt,
        "student_temp": ts,
    })) else {
        return;
    };
    let t_prob = teacher_targets(
        tensor(&t, [n, k]),
        Tensor::zeros([1, k], &Device::flex()),
        TeacherNorm::Batch,
        tt,
    );
    let loss = scalar(cross_entropy(t_prob, tensor(&s, [n, k]), ts));
    assert_close(
        "iBOT loss",
        &[loss],
        &[r["loss"].as_f64().unwrap()],
        F32_TOL,
    );
}

#[test]
fn koleo_matches_numpy() {
    let (n, d) = (6, 5);
    let mut rng = Rng::new(4);
    let mut x = normal(&mut rng, n * d, 0.0, 1.0);
    // a near-duplicate pair, the case the term is there for
    let noise = normal(&mut rng, d, 0.0, 1e-2);
    for j in 0..d {
        x[(n - 1) * d + j] = 2.0 * x[j] + noise[j];
    }
    let Some(r) = reference(json!({ "case": "koleo", "x": array(&x, [n, d]) })) else {
        return;
    };
    let ours = scalar(koleo(tensor(&x, [n, d])));
    assert_close("KoLeo", &[ours], &[r["loss"].as_f64().unwrap()], F32_TOL);
}

fn jepa_case(kind: JepaLoss, shapes: &[[usize; 3]], seed: u64) {
    let mut rng = Rng::new(seed);
    let sets: Vec<(Vec<f32>, Vec<f32>)> = shapes
        .iter()
        .map(|s| {
            let n = s.iter().product();
            // raw target-encoder features off-centre and off-scale; predictions spread so
            // that both branches of smooth L1 are taken
            (normal(&mut rng, n, 0.0, 1.5), normal(&mut rng, n, 0.7, 3.0))
        })
        .collect();
    let name = match kind {
        JepaLoss::L1 => "l1",
        JepaLoss::SmoothL1 => "smooth_l1",
    };
    let Some(r) = reference(json!({
        "case": "jepa",
        "loss": name,
        "preds": shapes.iter().zip(&sets).map(|(s, (p, _))| array(p, *s)).collect::<Vec<_>>(),
        "features": shapes.iter().zip(&sets).map(|(s, (_, h))| array(h, *s)).collect::<Vec<_>>(),
    })) else {
        return;
    };
    let mut pairs = Vec::new();
    for (i, (s, (p, h))) in shapes.iter().zip(&sets).enumerate() {
        let target = regression_targets(tensor(h, *s), TargetNorm::Layer);
        assert_close(
            &format!("JEPA {name} layer-normed targets, set {i}"),
            &values(target.clone()),
            &reference_values(&r["targets"][i]),
            F32_TOL,
        );
        pairs.push((tensor(p, *s), target));
    }
    let ours = scalar(latent_loss(pairs, kind));
    assert_close(
        &format!("JEPA {name} loss"),
        &[ours],
        &[r["loss"].as_f64().unwrap()],
        F32_TOL,
    );
}

#[test]
fn ijepa_smooth_l1_matches_numpy() {
    jepa_case(JepaLoss::SmoothL1, &[[3, 5, 8]], 5);
}

#[test]
fn vjepa_l1_over_mask_sets_matches_numpy() {
    jepa_case(JepaLoss::L1, &[[3, 5, 8], [6, 2, 8]], 6);
}

/// Every parameter's values in traversal order.
struct Params(Vec<Vec<f32>>);

impl ModuleVisitor for Params {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        self.0
            .push(param.val().into_data().try_to_vec::<f32>().unwrap());
    }
}

fn params<M: Module>(m: &M) -> Vec<Vec<f32>> {
    let mut p = Params(Vec::new());
    m.visit(&mut p);
    p.0
}

#[test]
fn ema_update_matches_numpy() {
    let device = Device::flex();
    let cfg = VitConfig::new([8, 8], 4)
        .with_in_chans(3)
        .with_embed_dim(16)
        .with_depth(1)
        .with_num_heads(2)
        .with_num_registers(1);
    let target = seeded_module(&device, 7, || cfg.init(&device));
    let source = seeded_module(&device, 8, || cfg.init(&device));
    let (t, s) = (params(&target), params(&source));
    assert!(t.len() > 5 && t != s);
    for m in [0.9, 0.996] {
        let Some(r) = reference(json!({
            "case": "ema",
            "momentum": m,
            "target": t,
            "source": s,
        })) else {
            return;
        };
        let ours: Vec<f64> = params(&ema_update(target.clone(), &source, m))
            .into_iter()
            .flatten()
            .map(f64::from)
            .collect();
        let expect: Vec<f64> = r["params"]
            .as_array()
            .unwrap()
            .iter()
            .flat_map(reference_values)
            .collect();
        assert_close(&format!("EMA at {m}"), &ours, &expect, 1e-6);
    }
}

#[test]
fn schedules_match_numpy() {
    let steps = [0usize, 1, 2, 9, 10, 11, 29, 30, 31, 50, 98, 99];
    let total = 100;
    let optim = OptimSection {
        steps: total,
        warmup_steps: 10,
        lr: 1e-3,
        min_lr: 1e-6,
        ..Default::default()
    };
    let dino = DinoSection {
        teacher_temp: [0.04, 0.07],
        teacher_temp_warmup_steps: 30,
        ..Default::default()
    };
    let ema = [0.996, 1.0];
    let Some(r) = reference(json!({
        "case": "schedules",
        "steps": steps,
        "total": total,
        "ema": ema,
        "teacher_temp": dino.teacher_temp,
        "teacher_temp_warmup": dino.teacher_temp_warmup_steps,
        "lr": optim.lr,
        "min_lr": optim.min_lr,
        "warmup": optim.warmup_steps,
    })) else {
        return;
    };
    let of = |f: &dyn Fn(usize) -> f64| steps.iter().map(|&s| f(s)).collect::<Vec<_>>();
    assert_close(
        "EMA momentum schedule",
        &of(&|s| momentum_at(ema[0], ema[1], s, total)),
        &reference_values(&r["momentum"]),
        1e-12,
    );
    assert_close(
        "teacher temperature schedule",
        &of(&|s| dino.teacher_temp_at(s)),
        &reference_values(&r["teacher_temp"]),
        1e-12,
    );
    assert_close(
        "learning-rate schedule",
        &of(&|s| optim.lr_at(s)),
        &reference_values(&r["lr"]),
        1e-12,
    );
}
