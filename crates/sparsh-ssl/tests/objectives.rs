//! One training step lowers each objective's loss on a fixed batch (same masks / views, the
//! EMA teacher and the DINO centre held fixed so only the trained weights move).

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
    let (model, reported) = model.train_step(&recipe, &mut optim, &batch, &device);
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
fn ijepa_step_lowers_loss() {
    one_step_lowers_loss(recipe(
        "ijepa",
        "[jepa]\npredictor_dim = 32\npredictor_depth = 1\npredictor_heads = 4\nema = [1.0, 1.0]",
    ));
}

#[test]
fn vjepa_step_lowers_loss() {
    one_step_lowers_loss(recipe(
        "vjepa",
        "[jepa]\npredictor_dim = 32\npredictor_depth = 1\npredictor_heads = 4\nema = [1.0, 1.0]",
    ));
}
