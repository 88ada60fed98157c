//! `sparsh bench-train`: images/s of training steps on a device — the reference step that
//! `crates/sparsh-ssl/benches/torch_step.py` takes in PyTorch, and recipes' own steps — with the
//! device's f32 matrix-product rate and, with `--parity`, one step of each recipe on the CPU and
//! on the device compared.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use burn::prelude::*;
use serde::Serialize;
use sparsh_ssl::bench::{ReferenceStep, StepTime, step_parity, time_recipe};
use sparsh_ssl::device::Devices;
use sparsh_ssl::recipe::Recipe;

/// What `sparsh bench-train` times.
pub struct BenchTrain<'a> {
    /// Recipes whose training steps are timed.
    pub configs: &'a [PathBuf],
    /// Reference sizes (tiny, small, base).
    pub reference: &'a [String],
    /// The reference input `[height, width]`.
    pub input: [usize; 2],
    /// The reference patch side.
    pub patch: usize,
    /// Images per step (the reference's; each recipe's in place of its own when given).
    pub batch: Option<usize>,
    /// Untimed steps first.
    pub warmup: usize,
    /// Timed steps (their median is reported).
    pub steps: usize,
    /// Side of the square f32 matrix product timed first (0: none).
    pub gemm: usize,
    /// Also compare one step of each recipe on the CPU and on the device.
    pub parity: bool,
    /// Where the rows go as JSON too.
    pub json: Option<&'a Path>,
}

/// One timed row.
#[derive(Debug, Serialize)]
struct Row {
    what: String,
    device: String,
    batch: usize,
    input: String,
    seconds_per_step: f64,
    images_per_second: Option<f64>,
    /// FLOPs of one step (matrix products only; the reference step and the product).
    gflop_per_step: Option<f64>,
    tflops: Option<f64>,
}

/// One parity row (see `sparsh_ssl::bench::StepParity`).
#[derive(Debug, Serialize)]
struct Parity {
    recipe: String,
    against: String,
    batch: usize,
    loss_relative: f64,
    gradient_relative: f32,
    gradient_worst_scale: f32,
    weight_abs: f32,
    undetermined_weight_abs: f32,
    undetermined: usize,
    weights: usize,
}

#[derive(Debug, Serialize)]
struct Report {
    device: String,
    rows: Vec<Row>,
    parity: Vec<Parity>,
}

/// Parses `HxW` (e.g. `320x240`).
pub fn parse_input(s: &str) -> Result<[usize; 2], String> {
    let bad = || format!("--input '{s}': expected HEIGHTxWIDTH in pixels, e.g. 320x240");
    let (h, w) = s.split_once(['x', '×']).ok_or_else(bad)?;
    let h: usize = h.trim().parse().map_err(|_| bad())?;
    let w: usize = w.trim().parse().map_err(|_| bad())?;
    if h == 0 || w == 0 {
        return Err(bad());
    }
    Ok([h, w])
}

/// Seconds of one `n`³ f32 matrix product on `device`: the median over 5 timings of a chain of
/// [`GEMM_CHAIN`] products, each taking the last one's result as its left operand, ended by
/// reading back one number that depends on every product, divided by the chain's length. A
/// product whose result is read back on its own is not a measure on wgpu: on the H100 and on
/// Mesa's lavapipe alike it returned in under 0.1 ms (2 300 and 52 TFLOP/s), before the product
/// had run.
fn gemm_seconds(device: &Device, n: usize) -> f64 {
    let a = Tensor::<2>::random([n, n], burn::tensor::Distribution::Default, device);
    // b / n keeps every product's entries near 1/2 however long the chain
    let b = Tensor::<2>::random([n, n], burn::tensor::Distribution::Default, device)
        .div_scalar(n as f32);
    let chain = |start: Tensor<2>| {
        let mut x = start;
        for _ in 0..GEMM_CHAIN {
            x = x.matmul(b.clone());
        }
        x.sum().into_scalar::<f32>()
    };
    let _ = chain(a.clone());
    let mut times: Vec<f64> = (0..5)
        .map(|i| {
            let start = a.clone().add_scalar(i as f32);
            let _ = start.clone().sum().into_scalar::<f32>();
            let t0 = Instant::now();
            let _ = chain(start);
            t0.elapsed().as_secs_f64() / GEMM_CHAIN as f64
        })
        .collect();
    times.sort_by(f64::total_cmp);
    times[2]
}

/// Products in each timed chain of [`gemm_seconds`].
const GEMM_CHAIN: usize = 8;

/// Runs the benchmark on `devices`' first device and prints a Markdown table.
pub fn bench_train(b: &BenchTrain, devices: &Devices) -> Result<()> {
    anyhow::ensure!(
        !b.configs.is_empty() || !b.reference.is_empty() || b.gemm > 0,
        "nothing to time: give --config RECIPE, --reference tiny,small,base or --gemm N"
    );
    anyhow::ensure!(b.steps > 0, "--steps: must be at least 1");
    // every input checked before anything is timed
    let references = b
        .reference
        .iter()
        .map(|size| {
            ReferenceStep::new(size, b.input, b.patch, b.batch.unwrap_or(32))
                .with_context(|| format!("--reference {size}"))
        })
        .collect::<Result<Vec<_>>>()?;
    let mut recipes = Vec::new();
    for path in b.configs {
        let mut recipe = Recipe::load(path)?;
        if let Some(batch) = b.batch {
            anyhow::ensure!(
                batch > 0 && batch.is_multiple_of(recipe.optim.micro_batches),
                "--batch {batch}: {} splits each batch into {} micro-batches; give a multiple",
                path.display(),
                recipe.optim.micro_batches
            );
            recipe.optim.batch_size = batch;
        }
        recipe.encoder_config()?;
        recipes.push((path, recipe));
    }

    let device = devices.main().clone();
    let name = devices.names[0].clone();
    let progress = |what: &str| {
        let what = what.to_string();
        move |i: usize, s: f64| {
            if !crate::progress::quiet() {
                eprintln!("{what}: step {i}: {s:.3} s");
            }
        }
    };
    let mut rows = Vec::new();
    if b.gemm > 0 {
        let s = gemm_seconds(&device, b.gemm);
        let flops = 2.0 * (b.gemm as f64).powi(3);
        rows.push(Row {
            what: format!("f32 matrix product {0}×{0}×{0}", b.gemm),
            device: name.clone(),
            batch: 1,
            input: String::new(),
            seconds_per_step: s,
            images_per_second: None,
            gflop_per_step: Some(flops / 1e9),
            tflops: Some(flops / s / 1e12),
        });
    }
    let autodiff = device.clone().autodiff();
    for r in &references {
        let what = format!("reference ViT {}×{}×{}", r.vit[0], r.vit[1], r.vit[2]);
        let t = r.time(&autodiff, 1, (b.warmup, b.steps), progress(&what));
        rows.push(row(&what, &name, r.img_size, t, Some(r.flops())));
    }
    for (path, recipe) in &recipes {
        let what = path.display().to_string();
        let t = time_recipe(recipe, &autodiff, (b.warmup, b.steps), progress(&what))?;
        let enc = recipe.encoder_config()?;
        rows.push(row(&what, &name, enc.img_size, t, None));
    }
    let mut parity = Vec::new();
    if b.parity {
        let cpu = Device::flex().autodiff();
        for (path, recipe) in &recipes {
            // two images per micro-batch: the CPU's half of the comparison stays quick
            let batch = 2 * recipe.optim.micro_batches;
            let mut small = recipe.clone();
            small.optim.batch_size = batch;
            let p = step_parity(&small, batch, &cpu, &autodiff)?;
            parity.push(Parity {
                recipe: path.display().to_string(),
                against: "cpu".into(),
                batch,
                loss_relative: p.loss_relative,
                gradient_relative: p.gradient_relative,
                gradient_worst_scale: p.gradient_worst_scale,
                weight_abs: p.weight_abs,
                undetermined_weight_abs: p.undetermined_weight_abs,
                undetermined: p.undetermined,
                weights: p.weights,
            });
        }
    }

    println!("| what | device | batch | input | s/step | images/s | GFLOP/step | TFLOP/s |");
    println!("|---|---|---|---|---|---|---|---|");
    for r in &rows {
        let opt =
            |v: Option<f64>, digits: usize| v.map_or("–".into(), |v| format!("{v:.digits$}"));
        println!(
            "| {} | {} | {} | {} | {:.4} | {} | {} | {} |",
            r.what,
            r.device,
            r.batch,
            r.input,
            r.seconds_per_step,
            opt(r.images_per_second, 1),
            opt(r.gflop_per_step, 1),
            opt(r.tflops, 2)
        );
    }
    if !parity.is_empty() {
        println!();
        println!(
            "| recipe | batch | loss (relative) | gradients (of each parameter's largest) | that parameter's scale (of the largest gradient) | updated weights | weights with an undetermined sign: largest move |"
        );
        println!("|---|---|---|---|---|---|---|");
        for p in &parity {
            println!(
                "| {} | {} | {:.1e} | {:.1e} | {:.1e} | {:.1e} | {} of {}: {:.1e} |",
                p.recipe,
                p.batch,
                p.loss_relative,
                p.gradient_relative,
                p.gradient_worst_scale,
                p.weight_abs,
                p.undetermined,
                p.weights,
                p.undetermined_weight_abs
            );
        }
    }
    if let Some(path) = b.json {
        let report = Report {
            device: name,
            rows,
            parity,
        };
        let text = serde_json::to_string_pretty(&report)?;
        sparsh_ssl::weights::write_atomic(path, text.as_bytes())?;
    }
    Ok(())
}

fn row(what: &str, device: &str, [h, w]: [usize; 2], t: StepTime, flops: Option<f64>) -> Row {
    Row {
        what: what.to_string(),
        device: device.to_string(),
        batch: t.batch,
        input: format!("{h}×{w}"),
        seconds_per_step: t.seconds,
        images_per_second: Some(t.images_per_second()),
        gflop_per_step: flops.map(|f| f / 1e9),
        tflops: flops.map(|f| f / t.seconds / 1e12),
    }
}
