//! Training-step benchmark: the reference ViT of `benches/torch_step.py` (6×96×96, patch 8,
//! width 192, 6 blocks, linear pixel head, MSE, Adam, batch 32), then images/s of one step of each
//! CPU recipe's objective. `cargo bench -p sparsh-ssl [-- NAME …]` (release; names `reference`,
//! `reference_small` (the same step with ViT-small: width 384, 12 blocks, 6 heads), `mae`,
//! `dino`, `ijepa`, `vjepa`). Prints medians of 5 steps after 2 warm-up steps, and for the
//! reference the mean CPU time per step.

use std::path::Path;
use std::time::Instant;

use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::optim::AdamConfig;
use burn::prelude::*;
use sparsh_ssl::data::HostBatch;
use sparsh_ssl::recipe::Recipe;
use sparsh_ssl::rng::Rng;
use sparsh_ssl::train::{Trainee, micro_batch_gradients, optimizer};
use sparsh_ssl::vit::{Vit, VitConfig, patchify};

#[derive(Module, Debug)]
struct Reference {
    vit: Vit,
    head: Linear,
}

/// CPU seconds used by this process so far (user + system, from `/proc/self/stat`; 0 where
/// unavailable): on a shared machine CPU time per step is steadier than wall time.
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let fields: Vec<&str> = stat
        .rsplit_once(')')
        .map_or(Vec::new(), |(_, rest)| rest.split_whitespace().collect());
    // after the command name: state is field 3, utime 14 and stime 15 (clock ticks of 10 ms)
    let tick = |i: usize| {
        fields
            .get(i - 3)
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(0.0)
    };
    (tick(14) + tick(15)) / 100.0
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The reference step of a ViT of `width` / `depth` / `heads` with the batch split into `parts`
/// micro-batches ([`micro_batch_gradients`], the trainer's path; 1 = the plain whole-batch step).
fn reference(device: &Device, [width, depth, heads]: [usize; 3], parts: usize) -> (f64, f64) {
    let cfg = VitConfig::new([96, 96], 8)
        .with_embed_dim(width)
        .with_depth(depth)
        .with_num_heads(heads);
    let mut model = Reference {
        vit: cfg.init(device),
        head: LinearConfig::new(width, cfg.patch_dim()).init(device),
    };
    let mut optim = AdamConfig::new().init();
    let x = Tensor::<5>::random(
        [32, 1, 6, 96, 96],
        burn::tensor::Distribution::Default,
        device,
    );
    let target = patchify(x.clone(), 8, 1);
    let mut times = Vec::new();
    let mut cpu = 0.0;
    for i in 0..7 {
        let t0 = Instant::now();
        let c0 = cpu_seconds();
        let (grads, _, _) = micro_batch_gradients(
            &model,
            x.clone(),
            std::slice::from_ref(device),
            parts,
            |m, x, rows| {
                let pred = m.head.forward(m.vit.forward(x, None).patches);
                let loss = (pred - target.clone().slice(rows)).powi_scalar(2).mean();
                (loss, None)
            },
        );
        model = optim.step(1e-4, model, grads);
        if i >= 2 {
            times.push(t0.elapsed().as_secs_f64());
            cpu += cpu_seconds() - c0;
        }
    }
    (median(times), cpu / 5.0)
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
        model = model
            .train_step(&recipe, &mut optim, &batch, std::slice::from_ref(device))
            .0;
        if i >= 2 {
            times.push(t0.elapsed().as_secs_f64());
        }
    }
    (median(times), b)
}

fn main() {
    // `cargo bench -p sparsh-ssl -- reference mae` runs only the named benchmarks
    let only: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let wanted = |name: &str| only.is_empty() || only.iter().any(|o| o == name);
    let device = Device::flex().autodiff();
    // the reference ViT-tiny of torch_step.py, and ViT-small (width 384, 12 blocks, 6 heads)
    for (name, size) in [
        ("reference", [192, 6, 3]),
        ("reference_small", [384, 12, 6]),
    ] {
        if !wanted(name) {
            continue;
        }
        for parts in [1, 2] {
            let (s, cpu) = reference(&device, size, parts);
            println!(
                "{name} (burn flex), {parts} micro-batch(es): {s:.3} s/step, {:.1} images/s, {cpu:.3} CPU s/step",
                32.0 / s
            );
        }
    }
    for name in ["mae", "dino", "ijepa", "vjepa"]
        .into_iter()
        .filter(|n| wanted(n))
    {
        let (s, b) = objective(name, &device);
        println!(
            "{name}_tiny_cpu: {s:.3} s/step at batch {b}, {:.1} images/s",
            b as f64 / s
        );
    }
}
