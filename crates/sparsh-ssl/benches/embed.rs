//! Encoder forward benchmark: frames/s of the frozen encoder (host input → mean-pooled features on
//! the host) for ViT-tiny, ViT-small and the CPU recipes' 6-block ViT-tiny, at the CPU recipes'
//! input (96×72, patch 8) and the official 224×224 at patch 16, 6 channels, on 1 and 2 threads,
//! at batch 1 (latency) and 16 (throughput): "ours" is the host pass of `sparsh embed` on the CPU
//! ([`sparsh_ssl::host::HostVit`]), "burn graph" the same encoder as burn ops
//! ([`sparsh_ssl::embed::encode`], the path of every other device). Each configuration also runs
//! `benches/torch_embed.py` (the same encoder in PyTorch) when python3 can import torch, and the
//! table gives ours / torch.
//! `cargo bench -p sparsh-ssl --bench embed [-- NAME …]` (release; names `tiny`, `small`,
//! `tiny6`, `recipe`, `official`). Medians of the timed passes after a warm-up (at least 3
//! passes and 1 s).

mod common;

use common::torch_version;

use std::path::Path;
use std::process::Command;
use std::time::Instant;

use burn::prelude::*;
use sparsh_ssl::embed::{Pool, encode};
use sparsh_ssl::host::HostVit;
use sparsh_ssl::vit::VitConfig;

/// The 1-, 5- and 15-minute load averages (the machine's other work).
fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "unknown".into())
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Median seconds of `pass` after a warm-up (at least 3 passes and 1 s, at most 50).
fn seconds<T>(pass: impl Fn() -> T) -> f64 {
    pass();
    let start = Instant::now();
    let mut times = Vec::new();
    while times.len() < 3 || (start.elapsed().as_secs_f64() < 1.0 && times.len() < 50) {
        let t0 = Instant::now();
        std::hint::black_box(pass());
        times.push(t0.elapsed().as_secs_f64());
    }
    median(times)
}

/// Frames/s of the forward pass of `cfg` at `batch` on the current thread pool: the host pass
/// ([`HostVit`], what `sparsh embed` runs on the CPU) and burn's graph ([`encode`]).
fn ours(cfg: &VitConfig, batch: usize) -> (f64, f64) {
    let device = Device::flex();
    let vit = cfg.init(&device);
    let host = HostVit::new(&vit);
    let [h, w] = cfg.img_size;
    let shape = [1, cfg.in_chans, h, w];
    let input: Vec<f32> = (0..batch * cfg.in_chans * h * w)
        .map(|i| (i % 251) as f32 / 251.0)
        .collect();
    let graph = || {
        let x = Tensor::<1>::from_floats(input.as_slice(), &device).reshape([
            batch,
            1,
            cfg.in_chans,
            h,
            w,
        ]);
        encode(&vit, x, Pool::Mean)
    };
    let batch = batch as f64;
    (
        batch / seconds(|| host.embed(&input, shape, Pool::Mean)),
        batch / seconds(graph),
    )
}

/// Frames/s of the PyTorch encoder, `None` without python3 and torch.
fn torch(size: &str, [h, w, p]: [usize; 3], threads: usize, batch: usize) -> Option<f64> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/torch_embed.py");
    let out = Command::new("python3")
        .arg(script)
        .args([size, &h.to_string(), &w.to_string(), &p.to_string()])
        .args([threads.to_string(), batch.to_string()])
        .output()
        .ok()?;
    let text = String::from_utf8_lossy(&out.stdout);
    text.split_once("frames/s ")?.1.trim().parse().ok()
}

fn main() {
    // `cargo bench -p sparsh-ssl --bench embed -- tiny recipe` runs only the named encoders
    // (all without one) at the named inputs (all without one)
    let only: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let named = |names: &[&str], name: &str| {
        only.iter().any(|o| o == name) || !only.iter().any(|o| names.contains(&o.as_str()))
    };
    // (name, width, blocks, heads)
    let models = [
        ("tiny", 192, 12, 3),
        ("small", 384, 12, 6),
        ("tiny6", 192, 6, 3),
    ];
    let inputs = [("recipe", [96, 72, 8]), ("official", [224, 224, 16])];
    let model_names = models.map(|m| m.0);
    let input_names = inputs.map(|i| i.0);
    // names of the other benchmark (`cargo bench -p sparsh-ssl -- reference`) select none here
    if !only.is_empty()
        && !only
            .iter()
            .any(|o| model_names.contains(&o.as_str()) || input_names.contains(&o.as_str()))
    {
        return;
    }
    let version = torch_version();
    println!(
        "load average at start: {}; torch: {}",
        load_average(),
        version
            .as_deref()
            .unwrap_or("not importable (no comparison)")
    );
    println!(
        "| encoder | input | threads | batch | ours frames/s | burn graph frames/s | torch frames/s | ours / torch |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for (name, width, depth, heads) in models.into_iter().filter(|m| named(&model_names, m.0)) {
        for (input, [h, w, p]) in inputs.into_iter().filter(|i| named(&input_names, i.0)) {
            // the CPU recipes' encoder only at the CPU recipes' input
            if name == "tiny6" && input == "official" {
                continue;
            }
            let cfg = VitConfig::new([h, w], p)
                .with_embed_dim(width)
                .with_depth(depth)
                .with_num_heads(heads);
            for threads in [1, 2] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .expect("thread pool");
                for batch in [1, 16] {
                    let (fps, graph) = pool.install(|| ours(&cfg, batch));
                    let reference = version
                        .as_ref()
                        .and_then(|_| torch(name, [h, w, p], threads, batch));
                    let (t, ratio) = reference.map_or(("–".into(), "–".into()), |t| {
                        (format!("{t:.1}"), format!("{:.2}", fps / t))
                    });
                    println!(
                        "| {name} ({width}×{depth}) | {h}×{w}/{p} | {threads} | {batch} | {fps:.1} | {graph:.1} | {t} | {ratio} |"
                    );
                }
            }
        }
    }
    println!("load average at end: {}", load_average());
}
