//! One training step lowers each objective's loss on a fixed batch (same masks / views, the
//! EMA teacher and the DINO centre held fixed so only the trained weights move), a step split
//! into micro-batches has the whole batch's gradient, and the EMA teachers move by the scheduled
//! momentum.

use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::prelude::*;
use sparsh_ssl::data::HostBatch;
use sparsh_ssl::recipe::Recipe;
use sparsh_ssl::rng::Rng;
use sparsh_ssl::train::{Trainee, optimizer};

fn recipe(objective: &str, extra: &str) -> Recipe {
    Recipe::parse(&format!(
        "objective = \"{objective}\"\nseed = 3\n[encoder]\nimg_size = [32, 24]\npatch_size = 4\n\
         embed_dim = 32\ndepth = 2\nnum_heads = 4\n{extra}\n[optim]\nlr = 1e-3\nwarmup_steps = 0\n\
         steps = 10\nbatch_size = 4\n"
    ))
    .unwrap()
}

fn fixed_batch(recipe: &Recipe) -> HostBatch {
    let enc = recipe.encoder_config().unwrap();
    let shape = [4, enc.num_frames, enc.in_chans, 32, 24];
    let mut rng = Rng::new(11);
    // smooth blobs, so that masked content is predictable from its context
    let (cx, cy) = (rng.range_f64(6.0, 18.0), rng.range_f64(8.0, 24.0));
    let n: usize = shape.iter().product();
    let values = (0..n)
        .map(|i| {
            let x = (i % 24) as f64;
            let y = ((i / 24) % 32) as f64;
            let s = (i / (24 * 32)) as f64;
            (0.5 + 0.4 * (-((x - cx - s).powi(2) + (y - cy).powi(2)) / 30.0).exp()
                + 0.02 * rng.range_f64(-1.0, 1.0)) as f32
        })
        .collect();
    HostBatch {
        step: 0,
        values,
        shape,
        forces: None,
    }
}

fn one_step_lowers_loss(recipe: Recipe) {
    let device = Device::flex().autodiff();
    let model = Trainee::init(&recipe, &device).unwrap();
    let mut optim = optimizer(&recipe);
    let batch = fixed_batch(&recipe);
    let x = || Tensor::<1>::from_floats(batch.values.as_slice(), &device).reshape(batch.shape);
    let before = model.loss(&recipe, x(), 0).0.into_scalar::<f32>();
    let (model, reported) =
        model.train_step(&recipe, &mut optim, &batch, std::slice::from_ref(&device));
    let after = model.loss(&recipe, x(), 0).0.into_scalar::<f32>();
    assert!(
        (reported as f32 - before).abs() <= 1e-4 * before.abs().max(1.0),
        "{reported} vs {before}"
    );
    assert!(before.is_finite() && after.is_finite());
    assert!(
        after < before,
        "{:?}: loss {before} → {after}",
        recipe.objective
    );
}

#[test]
fn mae_step_lowers_loss() {
    one_step_lowers_loss(recipe(
        "mae",
        "[mae]\ndecoder_dim = 32\ndecoder_depth = 1\ndecoder_heads = 4",
    ));
}

#[test]
fn dino_step_lowers_loss() {
    one_step_lowers_loss(recipe(
        "dino",
        "num_registers = 1\n[dino]\nhead_hidden = 64\nhead_bottleneck = 16\nnum_prototypes = 128\n\
         ema = [1.0, 1.0]\ncenter_momentum = 1.0\n[dino.views]\nnum_local = 4",
    ));
}

#[test]
fn dino_step_with_batch_standardized_teacher_lowers_loss() {
    one_step_lowers_loss(recipe(
        "dino",
        "num_registers = 1\n[dino]\nhead_hidden = 64\nhead_bottleneck = 16\nnum_prototypes = 128\n\
         ema = [1.0, 1.0]\ncenter_momentum = 1.0\nteacher_norm = \"batch\"\n\
         teacher_temp = [0.25, 0.25]\n[dino.views]\nnum_local = 4",
    ));
}

#[test]
fn dino_step_with_ibot_masked_patches_lowers_loss() {
    one_step_lowers_loss(recipe(
        "dino",
        "num_registers = 1\n[dino]\nhead_hidden = 64\nhead_bottleneck = 16\nnum_prototypes = 128\n\
         ema = [1.0, 1.0]\nteacher_norm = \"batch\"\nteacher_temp = [0.25, 0.25]\nibot_weight = 1.0\n\
         [dino.views]\nnum_local = 4\nmask_ratio = 0.4",
    ));
}

#[test]
fn ijepa_step_lowers_loss() {
    one_step_lowers_loss(recipe(
        "ijepa",
        "[jepa]\npredictor_dim = 32\npredictor_depth = 1\npredictor_heads = 4\nema = [1.0, 1.0]",
    ));
}

#[test]
fn vjepa_step_with_batch_standardized_targets_lowers_loss() {
    one_step_lowers_loss(recipe(
        "vjepa",
        "[jepa]\npredictor_dim = 32\npredictor_depth = 1\npredictor_heads = 4\nema = [1.0, 1.0]\n\
         target_norm = \"layer_batch\"",
    ));
}

#[test]
fn vjepa_step_lowers_loss() {
    one_step_lowers_loss(recipe(
        "vjepa",
        "[jepa]\npredictor_dim = 32\npredictor_depth = 1\npredictor_heads = 4\nema = [1.0, 1.0]",
    ));
}

/// Every parameter's gradient (`None` where it has none), flattened, in visiting order.
struct Flatten<'a> {
    grads: &'a GradientsParams,
    out: Vec<Option<Vec<f32>>>,
}

impl ModuleVisitor for Flatten<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let g = self.grads.get::<D>(param.id);
        self.out
            .push(g.map(|g| g.into_data().try_to_vec::<f32>().unwrap()));
    }
}

fn flat_gradients(model: &Trainee, grads: &GradientsParams) -> Vec<Option<Vec<f32>>> {
    let mut f = Flatten {
        grads,
        out: Vec::new(),
    };
    model.visit(&mut f);
    f.out
}

/// Every parameter's value, flattened, in visiting order.
struct Weights(Vec<Vec<f32>>);

impl ModuleVisitor for Weights {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        self.0
            .push(param.val().into_data().try_to_vec::<f32>().unwrap());
    }
}

/// Three MAE steps in two micro-batches give the same bits on a pool of one thread and of two:
/// the split is the recipe's, and the micro-batch gradients are summed in order.
#[test]
fn training_gives_the_same_bits_on_one_and_two_threads() {
    let mut recipe = recipe(
        "mae",
        "[mae]\ndecoder_dim = 32\ndecoder_depth = 1\ndecoder_heads = 4",
    );
    recipe.optim.micro_batches = 2;
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let device = Device::flex().autodiff();
            let mut model = Trainee::init(&recipe, &device).unwrap();
            let mut optim = optimizer(&recipe);
            let mut batch = fixed_batch(&recipe);
            let mut losses = Vec::new();
            for step in 0..3 {
                batch.step = step;
                let (next, loss) =
                    model.train_step(&recipe, &mut optim, &batch, std::slice::from_ref(&device));
                model = next;
                losses.push(loss.to_bits());
            }
            let mut w = Weights(Vec::new());
            model.visit(&mut w);
            (losses, w.0)
        })
    };
    let (one, two) = (run(1), run(2));
    assert_eq!(one.0, two.0, "losses");
    assert!(one.1 == two.1, "weights differ");
}

/// The gradient averaged over 2 and 4 micro-batches (each on its own parameter copy, in
/// parallel) equals the plain whole-batch gradient: the losses are means over samples with
/// equal token counts per sample, so splitting the batch only reorders sums.
fn micro_batches_match_whole_batch(mut recipe: Recipe) {
    let device = Device::flex().autodiff();
    let model = Trainee::init(&recipe, &device).unwrap();
    let batch = fixed_batch(&recipe);
    let x = || Tensor::<1>::from_floats(batch.values.as_slice(), &device).reshape(batch.shape);
    recipe.optim.micro_batches = 1;
    let (whole, whole_loss, _) = model.gradients(&recipe, x(), 0, std::slice::from_ref(&device));
    let whole = flat_gradients(&model, &whole);
    assert!(whole.iter().any(Option::is_some));
    for parts in [2, 4] {
        recipe.optim.micro_batches = parts;
        let (split, split_loss, _) =
            model.gradients(&recipe, x(), 0, std::slice::from_ref(&device));
        let split = flat_gradients(&model, &split);
        assert_eq!(split.len(), whole.len(), "{parts} parts: parameter count");
        assert!(
            (split_loss - whole_loss).abs() <= 1e-5 * whole_loss.abs().max(1.0),
            "{parts} parts: loss {split_loss} vs {whole_loss}"
        );
        for (i, (a, b)) in whole.iter().zip(&split).enumerate() {
            let (a, b) = match (a, b) {
                (Some(a), Some(b)) => (a, b),
                (None, None) => continue,
                _ => panic!("{parts} parts, parameter {i}: a gradient on one side only"),
            };
            let scale = a.iter().fold(0f32, |m, v| m.max(v.abs()));
            let err = a.iter().zip(b).fold(0f32, |m, (u, v)| m.max((u - v).abs()));
            assert!(
                err <= 1e-4 * scale + 1e-9,
                "{:?}, {parts} parts, parameter {i}: max error {err} of max |g| {scale}",
                recipe.objective
            );
        }
    }
}

#[test]
fn mae_micro_batches_give_the_whole_batch_gradient() {
    micro_batches_match_whole_batch(recipe(
        "mae",
        "[mae]\ndecoder_dim = 32\ndecoder_depth = 1\ndecoder_heads = 4",
    ));
}

#[test]
fn jepa_micro_batches_give_the_whole_batch_gradient() {
    for objective in ["ijepa", "vjepa"] {
        micro_batches_match_whole_batch(recipe(
            objective,
            "[jepa]\npredictor_dim = 32\npredictor_depth = 1\npredictor_heads = 4",
        ));
    }
}

#[test]
fn dino_micro_batches_give_the_whole_batch_gradient_without_batch_statistics() {
    // without the head's batch norm and KoLeo the DINO loss is a per-sample mean too
    micro_batches_match_whole_batch(recipe(
        "dino",
        "num_registers = 1\n[dino]\nhead_hidden = 64\nhead_bottleneck = 16\n\
         num_prototypes = 128\nhead_batch_norm = false\nkoleo_weight = 0.0\n[dino.views]\nnum_local = 2",
    ));
}

#[test]
fn ema_copies_start_as_the_trained_weights() {
    let device = Device::flex().autodiff();
    let weights = |m: &dyn Fn(&mut Weights)| {
        let mut w = Weights(Vec::new());
        m(&mut w);
        w.0
    };
    let jepa = recipe(
        "ijepa",
        "[jepa]\npredictor_dim = 32\npredictor_depth = 1\npredictor_heads = 4",
    );
    let Trainee::Jepa(j) = Trainee::init(&jepa, &device).unwrap() else {
        panic!("I-JEPA trainee")
    };
    let encoder = weights(&|w| j.encoder.visit(w));
    assert!(!encoder.is_empty());
    assert_eq!(encoder, weights(&|w| j.target_encoder.visit(w)));
    let dino = recipe(
        "dino",
        "num_registers = 1\n[dino]\nhead_hidden = 64\nhead_bottleneck = 16\nnum_prototypes = 128",
    );
    let Trainee::Dino(d) = Trainee::init(&dino, &device).unwrap() else {
        panic!("DINO trainee")
    };
    assert_eq!(
        weights(&|w| d.encoder.visit(w)),
        weights(&|w| d.teacher_encoder.visit(w))
    );
    assert_eq!(
        weights(&|w| d.head.visit(w)),
        weights(&|w| d.teacher_head.visit(w))
    );
}

fn weights_of<M: Module>(m: &M) -> Vec<Vec<f32>> {
    let mut w = Weights(Vec::new());
    m.visit(&mut w);
    w.0
}

/// Asserts `teacher = m · before + (1 − m) · after`, parameter by parameter, to 1e-6 of each
/// parameter's largest value; returns the largest change of the teacher.
fn assert_blend(teacher: &[Vec<f32>], before: &[Vec<f32>], after: &[Vec<f32>], m: f64) -> f64 {
    assert_eq!(teacher.len(), before.len());
    let mut moved = 0f64;
    for ((t, b), a) in teacher.iter().zip(before).zip(after) {
        let scale = b.iter().fold(0f64, |s, v| s.max(v.abs() as f64));
        for ((&t, &b), &a) in t.iter().zip(b).zip(a) {
            let expect = m * b as f64 + (1.0 - m) * a as f64;
            assert!(
                (t as f64 - expect).abs() <= 1e-6 * scale.max(1e-3),
                "teacher {t} vs {expect} (before {b}, student after {a})"
            );
            moved = moved.max((t - b).abs() as f64);
        }
    }
    moved
}

/// A training step with the EMA momentum ramping from 0.9 to 0.99 over 10 steps, at step 3
/// (momentum 0.9 + 0.09 · 3/10 = 0.927): the teacher (I-JEPA target encoder; DINO teacher
/// encoder and head), a copy of the student before the step, becomes 0.927 · the student before
/// + 0.073 · the student after the optimizer step.
#[test]
fn ema_teacher_follows_the_student_by_the_scheduled_momentum() {
    let momentum = 0.927;
    let step_at_3 = |recipe: &Recipe| {
        let device = Device::flex().autodiff();
        let model = Trainee::init(recipe, &device).unwrap();
        let mut optim = optimizer(recipe);
        let mut batch = fixed_batch(recipe);
        batch.step = 3;
        let (after, _) =
            model
                .clone()
                .train_step(recipe, &mut optim, &batch, std::slice::from_ref(&device));
        (model, after)
    };
    let jepa = recipe(
        "ijepa",
        "[jepa]\npredictor_dim = 32\npredictor_depth = 1\npredictor_heads = 4\nema = [0.9, 0.99]",
    );
    let (Trainee::Jepa(before), Trainee::Jepa(after)) = step_at_3(&jepa) else {
        panic!("I-JEPA trainee")
    };
    assert_eq!(
        weights_of(&before.encoder),
        weights_of(&before.target_encoder)
    );
    let moved = assert_blend(
        &weights_of(&after.target_encoder),
        &weights_of(&before.encoder),
        &weights_of(&after.encoder),
        momentum,
    );
    assert!(moved > 1e-6, "the target encoder did not move ({moved})");

    let dino = recipe(
        "dino",
        "num_registers = 1\n[dino]\nhead_hidden = 64\nhead_bottleneck = 16\nnum_prototypes = 128\n\
         ema = [0.9, 0.99]\n[dino.views]\nnum_local = 2",
    );
    let (Trainee::Dino(before), Trainee::Dino(after)) = step_at_3(&dino) else {
        panic!("DINO trainee")
    };
    for (teacher, student_before, student_after) in [
        (
            weights_of(&after.teacher_encoder),
            weights_of(&before.encoder),
            weights_of(&after.encoder),
        ),
        (
            weights_of(&after.teacher_head),
            weights_of(&before.head),
            weights_of(&after.head),
        ),
    ] {
        let moved = assert_blend(&teacher, &student_before, &student_after, momentum);
        assert!(moved > 1e-6, "the DINO teacher did not move ({moved})");
    }
}
