//! Training-step benchmark: the reference ViT of `benches/torch_step.py` (6×96×96, patch 8,
//! width 192, 6 blocks, linear pixel head, MSE, Adam, batch 32), then images/s of one step of each
//! CPU recipe's objective. `cargo bench -p sparsh-ssl` (release). Prints medians of 5 steps after
//! 2 warm-up steps.

use std::path::Path;
use std::time::Instant;

use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::optim::{AdamConfig, GradientsParams};
use burn::prelude::*;
use sparsh_ssl::data::HostBatch;
use sparsh_ssl::recipe::Recipe;
use sparsh_ssl::rng::Rng;
use sparsh_ssl::train::{Trainee, optimizer};
use sparsh_ssl::vit::{Vit, VitConfig, patchify};

#[derive(Module, Debug)]
struct Reference {
    vit: Vit,
    head: Linear,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn reference(device: &Device) -> f64 {
    let cfg = VitConfig::new([96, 96], 8).with_depth(6);
    let mut model = Reference {
        vit: cfg.init(device),
        head: LinearConfig::new(192, cfg.patch_dim()).init(device),
    };
    let mut optim = AdamConfig::new().init();
    let x = Tensor::<5>::random(
        [32, 1, 6, 96, 96],
        burn::tensor::Distribution::Default,
        device,
    );
    let target = patchify(x.clone(), 8, 1);
    let mut times = Vec::new();
    for i in 0..7 {
        let t0 = Instant::now();
        let pred = model
            .head
            .forward(model.vit.forward(x.clone(), None).patches);
        let loss = (pred - target.clone()).powi_scalar(2).mean();
        let _ = loss.clone().into_scalar::<f32>();
        let grads = GradientsParams::from_grads(loss.backward(), &model);
        model = optim.step(1e-4, model, grads);
        if i >= 2 {
            times.push(t0.elapsed().as_secs_f64());
        }
    }
    median(times)
}

fn objective(name: &str, device: &Device) -> (f64, usize) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/ssl");
    let recipe = Recipe::load(&dir.join(format!("{name}_tiny_cpu.toml"))).unwrap();
    let enc = recipe.encoder_config().unwrap();
    let b = recipe.optim.batch_size;
    let shape = [
        b,
        enc.num_frames,
        enc.in_chans,
        enc.img_size[0],
        enc.img_size[1],
    ];
    let mut rng = Rng::new(1);
    let values = (0..shape.iter().product::<usize>())
        .map(|_| rng.uniform() as f32)
        .collect();
    let mut batch = HostBatch {
        step: 0,
        values,
        shape,
        forces: None,
    };
    let mut model = Trainee::init(&recipe, device).unwrap();
    let mut optim = optimizer(&recipe);
    let mut times = Vec::new();
    for i in 0..7 {
        batch.step = i;
        let t0 = Instant::now();
        model = model.train_step(&recipe, &mut optim, &batch, device).0;
        if i >= 2 {
            times.push(t0.elapsed().as_secs_f64());
        }
    }
    (median(times), b)
}

fn main() {
    let device = Device::flex().autodiff();
    let s = reference(&device);
    println!(
        "reference ViT (burn flex): {s:.3} s/step, {:.1} images/s",
        32.0 / s
    );
    for name in ["mae", "dino", "ijepa", "vjepa"] {
        let (s, b) = objective(name, &device);
        println!(
            "{name}_tiny_cpu: {s:.3} s/step at batch {b}, {:.1} images/s",
            b as f64 / s
        );
    }
}
