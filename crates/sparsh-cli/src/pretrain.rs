//! `sparsh pretrain`: self-supervised pretraining of a ViT encoder from a recipe.

use std::path::{Path, PathBuf};

use anyhow::Result;
use sparsh_ssl::device::{DeviceKind, Devices};
use sparsh_ssl::recipe::Recipe;
use sparsh_ssl::train::{
    RunOptions, probe_encoders_with_progress, probe_patches_with_progress,
    probe_random_encoders_with_progress, run,
};

use crate::progress::Progress;

/// Runs (or resumes) the recipe `config` on `data`, writing into `out`.
pub fn pretrain(
    config: &Path,
    data: Vec<PathBuf>,
    probe_data: Vec<PathBuf>,
    out: PathBuf,
    resume: bool,
    max_steps: Option<usize>,
    devices: &Devices,
) -> Result<()> {
    let recipe = Recipe::load(config)?;
    let bar = Progress::new("pretrain", "step", recipe.optim.steps as u64);
    let opts = RunOptions {
        data,
        probe_data,
        out: out.clone(),
        resume,
        max_steps,
        devices: devices.clone(),
    };
    let mut probe_msg = String::new();
    let summary = run(&recipe, &opts, &mut |r| {
        if let Some(p) = r.probe {
            probe_msg = format!(
                " probe {:.1} mN (linear {:.1}, mean {:.1}, feature std {:.3}, rank {:.1})",
                p.rmse_mn, p.linear_mn, p.baseline_mn, p.feature_std, p.feature_rank
            );
        }
        if r.loss.is_finite() {
            bar.set_message(format!(
                "loss {:.4} lr {:.2e} {:.2} s/step{probe_msg}",
                r.loss, r.lr, r.step_s
            ));
            bar.set(r.step as u64 + 1);
        }
    })?;
    bar.finish();
    let total = recipe.optim.steps;
    if summary.last_loss.is_nan() {
        println!(
            "{}: already at step {} of {total}; nothing to do",
            out.display(),
            summary.steps
        );
        return Ok(());
    }
    let plural = |n: usize| if n == 1 { "" } else { "s" };
    println!(
        "step {} of {total} (this run: {} step{}, last loss {:.4}, {:.2} s/step, {:.3} s/step waiting for data) → {}",
        summary.steps,
        summary.ran,
        plural(summary.ran),
        summary.last_loss,
        summary.mean_step_s,
        summary.mean_wait_s,
        out.join("encoder.safetensors").display()
    );
    if let (Some(a), Some(b)) = (summary.probe_initial, summary.probe_final) {
        println!(
            "force probe RMSE: random init {:.1} mN, pretrained {:.1} mN (linear read-out {:.1} / {:.1} mN; predicting the mean: {:.1} mN)",
            a.rmse_mn, b.rmse_mn, a.linear_mn, b.linear_mn, b.baseline_mn
        );
    }
    println!("log: {}", out.join("log.csv").display());
    Ok(())
}

/// `sparsh probe`: the recipe's force probes (attentive and ridge, RMSE in mN on held-out
/// sequences) on its random encoder and on `encoder`, one row per probe seed and their mean.
/// `label_fraction` replaces the recipe's `[log] probe_label_fraction`; `patches` adds the
/// attentive probe on the raw input patches; `random_inits` probes that many random encoders
/// (recipe seeds from the recipe's on) and ranks `encoder` among them.
#[allow(clippy::too_many_arguments)]
pub fn probe(
    config: &Path,
    data: &[PathBuf],
    encoder: Option<&Path>,
    seeds: u64,
    label_fraction: Option<f64>,
    patches: bool,
    random_inits: Option<u64>,
    devices: &Devices,
) -> Result<()> {
    let device = devices.main();
    anyhow::ensure!(
        (1..=100).contains(&seeds),
        "--probe-seeds must be 1 to 100, got {seeds}"
    );
    if let Some(k) = random_inits {
        anyhow::ensure!(
            (1..=100).contains(&k),
            "--random-inits must be 1 to 100, got {k}"
        );
    }
    let mut recipe = Recipe::load(config)?;
    if let Some(f) = label_fraction {
        anyhow::ensure!(
            f > 0.0 && f <= 1.0,
            "--label-fraction must be in (0, 1], got {f}"
        );
        recipe.log.probe_label_fraction = f;
    }
    let seeds: Vec<u64> = (0..seeds).collect();
    // one probe fit per seed and encoder (random init, pretrained, other random draws, patches)
    let per_seed =
        1 + u64::from(encoder.is_some()) + random_inits.map_or(0, |k| k - 1) + u64::from(patches);
    let progress = Progress::new("probe", "fit", per_seed * seeds.len() as u64);
    let fitted = || progress.inc(1);
    let rows = probe_encoders_with_progress(&recipe, data, encoder, &seeds, device, &fitted)?;
    // the recipe's own seed is the random encoder of the table; draw the others
    let encoder_seeds: Vec<u64> = (0..random_inits.unwrap_or(0))
        .map(|i| recipe.seed.wrapping_add(i))
        .collect();
    let draws = match random_inits {
        Some(_) => Some(probe_random_encoders_with_progress(
            &recipe,
            data,
            &encoder_seeds[1..],
            &seeds,
            device,
            &fitted,
        )?),
        None => None,
    };
    let patch_scores = match patches {
        true => Some(probe_patches_with_progress(
            &recipe, data, &seeds, device, &fitted,
        )?),
        false => None,
    };
    progress.finish();
    println!("| probe seed | random init: attentive | linear | pretrained: attentive | linear |");
    println!("|---|---|---|---|---|");
    let cell = |s: Option<f64>| s.map_or("–".to_string(), |v| format!("{v:.1}"));
    let mut sums = [0.0; 4];
    for (seed, (random, loaded)) in seeds.iter().zip(&rows) {
        let values = [
            Some(random.rmse_mn),
            Some(random.linear_mn),
            loaded.map(|s| s.rmse_mn),
            loaded.map(|s| s.linear_mn),
        ];
        for (sum, v) in sums.iter_mut().zip(values) {
            *sum += v.unwrap_or(0.0);
        }
        println!(
            "| {seed} | {} | {} | {} | {} |",
            cell(values[0]),
            cell(values[1]),
            cell(values[2]),
            cell(values[3])
        );
    }
    let n = rows.len() as f64;
    let has = encoder.is_some();
    println!(
        "| mean | {:.1} | {:.1} | {} | {} |",
        sums[0] / n,
        sums[1] / n,
        cell(has.then_some(sums[2] / n)),
        cell(has.then_some(sums[3] / n))
    );
    println!(
        "force RMSE in mN; predicting the training mean scores {:.1} mN",
        rows[0].0.baseline_mn
    );
    println!(
        "feature rank (participation ratio of the tokens' frame-to-frame variation, of {}): \
         random init {:.1}, pretrained {}",
        recipe.encoder_config()?.embed_dim,
        rows[0].0.feature_rank,
        cell(rows[0].1.map(|s| s.feature_rank))
    );
    if let (Some(k), Some(draws)) = (random_inits, draws) {
        let means: Vec<f64> = std::iter::once(sums[0] / n)
            .chain(
                draws
                    .iter()
                    .map(|r| r.iter().map(|s| s.rmse_mn).sum::<f64>() / r.len() as f64),
            )
            .collect();
        let spread = Spread::of(&means);
        let list: Vec<String> = means.iter().map(|v| format!("{v:.1}")).collect();
        println!(
            "random inits (recipe seeds {}..={}), attentive probe, mean over probe seeds: {} mN; \
             mean {:.1}, standard deviation {:.1}, range {:.1}–{:.1}",
            encoder_seeds[0],
            encoder_seeds[encoder_seeds.len() - 1],
            list.join(" / "),
            spread.mean,
            spread.std,
            spread.min,
            spread.max
        );
        if encoder.is_some() {
            let pretrained = sums[2] / n;
            let beaten = means.iter().filter(|&&m| pretrained < m).count();
            println!(
                "pretrained {pretrained:.1} mN reads force better than {beaten} of {k} random inits"
            );
        }
    }
    if let Some(scores) = patch_scores {
        let list: Vec<String> = scores.iter().map(|v| format!("{v:.1}")).collect();
        println!(
            "attentive probe on the raw input patches (no encoder), seeds 0..{}: {} mN, mean {:.1}",
            seeds.len() - 1,
            list.join(" / "),
            scores.iter().sum::<f64>() / scores.len() as f64
        );
    }
    Ok(())
}

/// Mean, sample standard deviation and range of a list of scores.
struct Spread {
    mean: f64,
    std: f64,
    min: f64,
    max: f64,
}

impl Spread {
    fn of(values: &[f64]) -> Self {
        let n = values.len() as f64;
        let mean = values.iter().sum::<f64>() / n;
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
        Self {
            mean,
            std: var.sqrt(),
            min: values.iter().copied().fold(f64::INFINITY, f64::min),
            max: values.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        }
    }
}

/// `sparsh devices`: every device of each kind this build and machine have, with the index
/// `--devices` takes.
pub fn devices() -> Result<()> {
    for kind in [DeviceKind::Cpu, DeviceKind::Wgpu, DeviceKind::Cuda] {
        match sparsh_ssl::device::list(kind) {
            Ok(list) if list.is_empty() => println!("{kind}: none on this machine"),
            Ok(list) => {
                for (i, (_, name)) in list.iter().enumerate() {
                    println!("{kind} {i}: {name}");
                }
            }
            Err(_) if kind == DeviceKind::Cuda && !cfg!(feature = "cuda") => {
                println!("cuda: not in this build (rebuild with `--features cuda`)")
            }
            Err(e) => println!("{kind}: {e}"),
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::Spread;

    #[test]
    fn spread_is_the_sample_statistics() {
        let s = Spread::of(&[4.0, 1.0, 3.0, 2.0]);
        assert_eq!((s.mean, s.min, s.max), (2.5, 1.0, 4.0));
        // Σ(x − 2.5)² = 5 over n − 1 = 3
        assert!((s.std - (5.0f64 / 3.0).sqrt()).abs() < 1e-12);
        assert_eq!(Spread::of(&[7.0]).std, 0.0);
    }
}
