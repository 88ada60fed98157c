//! `sparsh fieldprobe train | eval | objective`: T1A on a frozen encoder (`sparsh_bench::fields`).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Result, bail};
use sparsh_ssl::device::Devices;

fn log(line: &str) {
    eprintln!("{line}");
}

/// Trains the decoders of a run into `out` (a new or empty directory, or with `resume` an
/// earlier run's), on `device`.
pub fn train(
    config: &Path,
    encoder: &Path,
    data: &Path,
    out: &Path,
    quick: bool,
    resume: bool,
    device: &Devices,
) -> Result<()> {
    if out.join("run.json").exists() && !resume {
        bail!(
            "{}: holds a field-probe run already (choose another --out, or continue it with --resume)",
            out.display()
        );
    }
    let start = Instant::now();
    let record = sparsh_bench::fields::run::train_run(
        config,
        encoder,
        data,
        out,
        quick,
        resume,
        device.main(),
        &log,
    )?;
    println!(
        "{}: {} decoders trained on {} pairs in {:.0} s; score them with: sparsh fieldprobe eval --run {} --data {}",
        out.display(),
        record.decoders.len(),
        record.train_pairs,
        start.elapsed().as_secs_f64(),
        out.display(),
        data.display()
    );
    Ok(())
}

/// Scores a run on `device` and prints the Markdown report.
pub fn eval(run: &Path, data: &Path, packs: &[PathBuf], device: &Devices) -> Result<()> {
    let start = Instant::now();
    let summary = sparsh_bench::fields::run::eval_run(run, data, packs, device.main(), &log)?;
    println!("{}", summary.markdown);
    eprintln!(
        "{}: scored in {:.0} s",
        run.join("eval").display(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Prints, per family, the shear objective of the true, zero and uniform flows on the training
/// pairs in contact.
pub fn objective(config: &Path, data: &Path) -> Result<()> {
    let rows = sparsh_bench::fields::run::objective_run(config, data)?;
    print!("{}", sparsh_bench::fields::objective::markdown(&rows));
    Ok(())
}
