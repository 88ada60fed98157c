//! `sparsh pretrain`: self-supervised pretraining of a ViT encoder from a recipe.

use std::path::{Path, PathBuf};

use anyhow::Result;
use indicatif::{ProgressBar, ProgressStyle};
use sparsh_ssl::recipe::Recipe;
use sparsh_ssl::train::{RunOptions, run};

/// Runs (or resumes) the recipe `config` on `data`, writing into `out`.
pub fn pretrain(
    config: &Path,
    data: Vec<PathBuf>,
    out: PathBuf,
    resume: bool,
    max_steps: Option<usize>,
) -> Result<()> {
    let recipe = Recipe::load(config)?;
    let bar = ProgressBar::new(recipe.optim.steps as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "{bar:30} {pos}/{len} [{elapsed_precise}<{eta_precise}] {msg}",
        )
        .expect("valid template"),
    );
    let opts = RunOptions {
        data,
        out: out.clone(),
        resume,
        max_steps,
    };
    let mut probe_msg = String::new();
    let summary = run(&recipe, &opts, &mut |r| {
        if let Some(p) = r.probe {
            probe_msg = format!(
                " probe {:.1} mN (linear {:.1}, mean {:.1}, feature std {:.3})",
                p.rmse_mn, p.linear_mn, p.baseline_mn, p.feature_std
            );
        }
        if r.loss.is_finite() {
            bar.set_position(r.step as u64 + 1);
            bar.set_message(format!(
                "loss {:.4} lr {:.2e} {:.2} s/step{probe_msg}",
                r.loss, r.lr, r.step_s
            ));
        }
    })?;
    bar.finish();
    println!(
        "{} steps, last loss {:.4}, {:.2} s/step ({:.3} s waiting for data)",
        summary.steps, summary.last_loss, summary.mean_step_s, summary.mean_wait_s
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
