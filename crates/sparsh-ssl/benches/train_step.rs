//! Training-step benchmark, in one run: the CPU's clock and peak FLOP/s, the reference step of
//! `benches/torch_step.py` (6×96×96, patch 8, a ViT, linear pixel head, MSE, Adam, batch 32) at
//! ViT-tiny (width 192, 6 blocks, 3 heads), ViT-small (384, 12, 6) and ViT-base (768, 12, 12)
//! with burn — whole batch and 2 micro-batches, the trainer's path — and right after it the same
//! step in PyTorch (`python3 benches/torch_step.py`, skipped with a note when python3 cannot
//! import torch), then images/s of one training step of each CPU recipe (`*_tiny_cpu.toml`) and
//! of the paper's ViT-base recipes (`*_base.toml`) at batch 4.
//!
//! `cargo bench -p sparsh-ssl --bench train_step [-- NAME …]` (release). Names: `reference`
//! (all three sizes) or `tiny`, `small`, `base`; `recipes` (the four CPU recipes) or `mae`,
//! `dino`, `ijepa`, `vjepa`; `base_recipes` (the five ViT-base recipes) or `mae_base`, `dino_base`,
//! `dinov2_base`, `ijepa_base`, `vjepa_base`; `wgpu`, only when named: the four CPU recipes on the
//! first wgpu adapter (one warm-up and one timed step each). No name runs everything but `wgpu`.
//!
//! FLOPs are counted as 2·M·N·K for every matrix product of the forward pass (the patch
//! embedding, q/k/v, qkᵀ, attention · v, the output projection, the two MLP layers, the head;
//! element-wise ops, norms and softmax not counted) and three times that for a training step
//! (forward, and the two products of each backward), PyTorch's and burn's alike. The peak is
//! measured on one core and multiplied by the rayon threads: the clock by a chain of dependent
//! integer adds (one cycle each), and the FLOP/s by independent 256-bit fused multiply-adds,
//! which on Zen 4 (two 256-bit FMA pipes; 512-bit FMAs run as two halves) approach
//! clock × 32 per core.

mod common;

use common::torch_version;

use std::path::Path;
use std::process::Command;
use std::time::Instant;

use burn::prelude::*;
use sparsh_ssl::bench::{ReferenceStep, time_recipe};
use sparsh_ssl::device::{DeviceKind, Devices};
use sparsh_ssl::recipe::Recipe;

/// Images per step of the reference step.
const BATCH: usize = 32;

/// The 1-, 5- and 15-minute load averages (the machine's other work).
fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "unknown".into())
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

/// Iterations per second of `work` on the calling thread, the best of 5 rounds of 5·10⁷
/// iterations (the best is the least disturbed by other work on a shared machine).
#[cfg(target_arch = "x86_64")]
fn rate(work: fn(u64)) -> f64 {
    const ITERS: u64 = 50_000_000;
    (0..5)
        .map(|_| {
            let t0 = Instant::now();
            work(ITERS);
            ITERS as f64 / t0.elapsed().as_secs_f64()
        })
        .fold(0.0, f64::max)
}

/// `n` iterations of 8 dependent 64-bit adds (8 cycles per iteration: integer add has a latency
/// of one cycle; the loop counter runs beside the chain).
#[cfg(target_arch = "x86_64")]
fn add_chain(n: u64) {
    let mut x = 0u64;
    // SAFETY: register-only arithmetic on the two operands, no memory or stack access
    unsafe {
        std::arch::asm!(
            "2:",
            "add {x}, 1", "add {x}, 1", "add {x}, 1", "add {x}, 1",
            "add {x}, 1", "add {x}, 1", "add {x}, 1", "add {x}, 1",
            "dec {n}",
            "jnz 2b",
            x = inout(reg) x,
            n = inout(reg) n => _,
            options(nomem, nostack),
        );
    }
    std::hint::black_box(x);
}

/// `n` iterations of 10 independent 256-bit f32 FMAs (160 FLOPs; ten accumulators cover the
/// FMA latency on two pipes). Only called where `fma` and `avx` are detected.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx,fma")]
fn fma_block(n: u64) {
    // SAFETY: register-only arithmetic (accumulators start and stay at zero), no memory access;
    // the caller checked that the CPU has AVX and FMA
    unsafe {
        std::arch::asm!(
            "vxorps ymm10, ymm10, ymm10",
            "vxorps ymm11, ymm11, ymm11",
            "vxorps ymm0, ymm0, ymm0", "vxorps ymm1, ymm1, ymm1", "vxorps ymm2, ymm2, ymm2",
            "vxorps ymm3, ymm3, ymm3", "vxorps ymm4, ymm4, ymm4", "vxorps ymm5, ymm5, ymm5",
            "vxorps ymm6, ymm6, ymm6", "vxorps ymm7, ymm7, ymm7", "vxorps ymm8, ymm8, ymm8",
            "vxorps ymm9, ymm9, ymm9",
            "2:",
            "vfmadd231ps ymm0, ymm10, ymm11", "vfmadd231ps ymm1, ymm10, ymm11",
            "vfmadd231ps ymm2, ymm10, ymm11", "vfmadd231ps ymm3, ymm10, ymm11",
            "vfmadd231ps ymm4, ymm10, ymm11", "vfmadd231ps ymm5, ymm10, ymm11",
            "vfmadd231ps ymm6, ymm10, ymm11", "vfmadd231ps ymm7, ymm10, ymm11",
            "vfmadd231ps ymm8, ymm10, ymm11", "vfmadd231ps ymm9, ymm10, ymm11",
            "dec {n}",
            "jnz 2b",
            n = inout(reg) n => _,
            out("ymm0") _, out("ymm1") _, out("ymm2") _, out("ymm3") _, out("ymm4") _,
            out("ymm5") _, out("ymm6") _, out("ymm7") _, out("ymm8") _, out("ymm9") _,
            out("ymm10") _, out("ymm11") _,
            options(nomem, nostack),
        );
    }
}

/// The measured clock (Hz) and f32 FMA FLOP/s of one core, times `threads` for the peak of all
/// cores (one core is measured because a shared machine seldom leaves them all idle at once);
/// `None` off x86-64 or without FMA.
fn peak(threads: usize) -> Option<(f64, f64)> {
    #[cfg(target_arch = "x86_64")]
    {
        if !(std::arch::is_x86_feature_detected!("avx")
            && std::arch::is_x86_feature_detected!("fma"))
        {
            return None;
        }
        let clock = 8.0 * rate(add_chain);
        // SAFETY: AVX and FMA were detected above
        let fma = |n| unsafe { fma_block(n) };
        let flops = 160.0 * rate(fma) * threads as f64;
        Some((clock, flops))
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = threads;
        None
    }
}

/// GFLOP/s of burn's f32 matrix product at 2048 × 2048 × 2048 (median of 5 after a warm-up).
fn gemm_gflops(device: &Device) -> f64 {
    let n: usize = 2048;
    let a = Tensor::<2>::random([n, n], burn::tensor::Distribution::Default, device);
    let b = Tensor::<2>::random([n, n], burn::tensor::Distribution::Default, device);
    let _ = a.clone().matmul(b.clone()).into_data();
    let times = (0..5)
        .map(|_| {
            let t0 = Instant::now();
            let _ = a.clone().matmul(b.clone()).into_data();
            t0.elapsed().as_secs_f64()
        })
        .collect();
    2.0 * (n * n * n) as f64 / median(times) / 1e9
}

/// The reference step (`sparsh_ssl::bench::ReferenceStep`: 6×96×96, patch 8, batch 32) of
/// the ViT `size` names.
fn reference_step(size: &str) -> ReferenceStep {
    ReferenceStep::new(size, [96, 96], 8, BATCH).unwrap()
}

/// The reference step with the batch split into `parts` micro-batches (1 = the plain whole-batch
/// step): median s/step of `timed` steps after `warmup`, and the mean CPU s/step.
fn reference(
    device: &Device,
    size: &str,
    parts: usize,
    (warmup, timed): (usize, usize),
) -> (f64, f64) {
    let mut c0 = cpu_seconds();
    let t = reference_step(size).time(device, parts, (warmup, timed), |i, _| {
        if i + 1 == warmup {
            c0 = cpu_seconds();
        }
    });
    (t.seconds, (cpu_seconds() - c0) / timed as f64)
}

/// The same step in PyTorch on `threads` threads: (s/step, CPU s/step), `None` when the script
/// fails (no torch).
fn torch_reference(
    size: &str,
    threads: usize,
    (warmup, timed): (usize, usize),
) -> Option<(f64, f64)> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/torch_step.py");
    let out = Command::new("python3")
        .arg(script)
        .arg(threads.to_string())
        .arg(size)
        .args([warmup, timed].map(|v| v.to_string()))
        .output()
        .ok()?;
    // "torch 2.x tiny threads 2: 0.505 s/step, 63.4 images/s, 0.980 CPU s/step"
    let text = String::from_utf8_lossy(&out.stdout);
    let (_, tail) = text.split_once(": ")?;
    let mut numbers = tail
        .split(", ")
        .filter_map(|f| f.split_whitespace().next()?.parse::<f64>().ok());
    let step = numbers.next()?;
    let _images = numbers.next()?;
    Some((step, numbers.next()?))
}

/// Median s/step of `timed` steps of the recipe `file` (`assets/ssl/{file}.toml`) on `device`
/// after `warmup` steps, at the batch size and micro-batches `resize` when given (else the
/// recipe's); returns (s/step, batch, micro-batches).
fn objective(
    file: &str,
    device: &Device,
    resize: Option<(usize, usize)>,
    steps: (usize, usize),
) -> (f64, usize, usize) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/ssl");
    let mut recipe = Recipe::load(&dir.join(format!("{file}.toml"))).unwrap();
    if let Some((batch, parts)) = resize {
        recipe.optim.batch_size = batch;
        recipe.optim.micro_batches = parts;
    }
    let t = time_recipe(&recipe, device, steps, |_, _| {}).unwrap();
    (t.seconds, t.batch, recipe.optim.micro_batches)
}

fn main() {
    // `cargo bench -p sparsh-ssl -- base mae` runs only the named benchmarks
    let only: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let wanted = |name: &str, group: &str| {
        (only.is_empty() && name != "wgpu") || only.iter().any(|o| o == name || o == group)
    };
    let threads = rayon::current_num_threads();
    let device = Device::flex().autodiff();
    println!(
        "rayon threads: {threads}; load average at start: {}",
        load_average()
    );
    let sizes = [
        ("tiny", (2, 5), (3, 10)),
        ("small", (2, 5), (2, 5)),
        ("base", (1, 3), (1, 3)),
    ];
    if sizes.iter().any(|s| wanted(s.0, "reference")) {
        let peak = peak(threads);
        let peak_flops = peak.map(|(clock, flops)| {
            println!(
                "clock {:.2} GHz; FMA peak of {threads} cores {:.1} GFLOP/s ({:.1} FLOP per cycle \
                 per core); burn f32 GEMM 2048³: {:.1} GFLOP/s",
                clock / 1e9,
                flops / 1e9,
                flops / clock / threads as f64,
                gemm_gflops(&Device::flex())
            );
            flops
        });
        let version = torch_version();
        println!(
            "torch: {}",
            version
                .as_deref()
                .unwrap_or("python3 cannot import torch: no PyTorch column")
        );
        println!(
            "| ViT | GFLOP/step | burn whole batch | burn 2 micro-batches | PyTorch | burn (2) / PyTorch | burn (2) of peak | PyTorch of peak |"
        );
        println!("|---|---|---|---|---|---|---|---|");
        for (name, steps, torch_steps) in sizes {
            if !wanted(name, "reference") {
                continue;
            }
            let step = reference_step(name);
            let flops = step.flops();
            let cell = |s: f64, cpu: f64| {
                format!(
                    "{s:.3} s/step, {:.1} images/s ({cpu:.2} CPU s)",
                    BATCH as f64 / s
                )
            };
            let share = |s: f64| {
                peak_flops.map_or("–".into(), |p| format!("{:.0} %", 100.0 * flops / s / p))
            };
            let (whole, whole_cpu) = reference(&device, name, 1, steps);
            let (split, split_cpu) = reference(&device, name, 2, steps);
            let torch = version
                .as_ref()
                .and_then(|_| torch_reference(name, threads, torch_steps));
            let (torch_cell, ratio, torch_share) = torch
                .map_or(("–".into(), "–".into(), "–".into()), |(s, cpu)| {
                    (cell(s, cpu), format!("{:.2}", s / split), share(s))
                });
            println!(
                "| {name} ({}×{}) | {:.0} | {} | {} | {torch_cell} | {ratio} | {} | {torch_share} |",
                step.vit[0],
                step.vit[1],
                flops / 1e9,
                cell(whole, whole_cpu),
                cell(split, split_cpu),
                share(split),
            );
        }
        // a GPU's images/s estimated the same way: utilisation × peak FLOP/s / FLOPs per image
        let base = reference_step("base").flops() / BATCH as f64;
        println!(
            "estimate, not a measurement: an A100 at 40 % of its 312 TFLOP/s bf16 peak would take \
             the base step at 0.4 × 312e12 / {:.1e} = {:.0} images/s",
            base,
            0.4 * 312e12 / base
        );
    }
    let recipes = ["mae", "dino", "ijepa", "vjepa"];
    let cpu_recipes: Vec<&str> = recipes
        .into_iter()
        .filter(|n| wanted(n, "recipes"))
        .collect();
    let base_recipes: Vec<&str> = ["mae", "dino", "dinov2", "ijepa", "vjepa"]
        .into_iter()
        .filter(|n| wanted(&format!("{n}_base"), "base_recipes"))
        .collect();
    if !cpu_recipes.is_empty() || !base_recipes.is_empty() {
        println!("| recipe | device | batch | micro-batches | s/step | images/s |");
        println!("|---|---|---|---|---|---|");
    }
    let row = |file: &str, device: &str, (s, b, parts): (f64, usize, usize)| {
        println!(
            "| `{file}` | {device} | {b} | {parts} | {s:.3} | {:.1} |",
            b as f64 / s
        );
    };
    for name in cpu_recipes {
        let file = format!("{name}_tiny_cpu");
        row(&file, "cpu", objective(&file, &device, None, (2, 5)));
    }
    for name in base_recipes {
        // batch 4 (the paper's 100–150 would take minutes a step here); DINO's batch statistics
        // keep it whole, the others run the CPU recipes' two micro-batches
        let parts = if name.starts_with("dino") { 1 } else { 2 };
        let file = format!("{name}_base");
        row(
            &file,
            "cpu",
            objective(&file, &device, Some((4, parts)), (1, 2)),
        );
    }
    if wanted("wgpu", "wgpu") {
        match Devices::choose(DeviceKind::Wgpu, &[]) {
            Ok(d) => {
                let gpu = d.main().clone().autodiff();
                for name in recipes {
                    let file = format!("{name}_tiny_cpu");
                    row(&file, &d.names[0], objective(&file, &gpu, None, (1, 1)));
                }
            }
            Err(e) => println!("wgpu: {e}"),
        }
    }
    println!("load average at end: {}", load_average());
}
