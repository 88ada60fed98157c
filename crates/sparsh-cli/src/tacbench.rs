//! `sparsh tacbench`: the TacBench run of a config (`sparsh_bench`), generating any task
//! dataset that is missing from its scene, then the results table and charts.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use sha2::{Digest, Sha256};
use sparsh_bench::tacbench::config::{BenchConfig, TaskConfig};
use sparsh_bench::tacbench::run::{RunOptions, run};
use sparsh_bench::tacbench::tasks::TaskKind;
use sparsh_ssl::device::Devices;

use crate::dataset::{DeviceArg, generate};
use sparsh_gen::GenerateOptions;

/// Runs (or resumes) the benchmark of `config` into `out`, its encoders and heads on `device`.
pub fn tacbench(
    config: &Path,
    out: &Path,
    quick: bool,
    resume: bool,
    report_only: bool,
    tasks: &[String],
    device: &Devices,
) -> Result<()> {
    let cfg = BenchConfig::load(config)?;
    let tasks = chosen_tasks(&cfg, config, tasks)?;
    // the pretrained encoders load and fit their recipes before anything is written
    sparsh_bench::tacbench::run::encoders(&cfg, Some(0))?;
    let text = std::fs::read_to_string(config).with_context(|| config.display().to_string())?;
    // what the units depend on: the config, --quick, every recipe and weights file
    let mut inputs = serde_json::Map::new();
    let files = cfg.encoder.iter().flat_map(|e| [&e.recipe, &e.weights]);
    let files = files.chain(cfg.random.iter().map(|r| &r.recipe));
    let files = files.chain(cfg.baselines.iter().map(|b| &b.recipe));
    for f in files {
        let bytes = std::fs::read(f).with_context(|| f.display().to_string())?;
        let digest: String = Sha256::digest(&bytes)
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        inputs.insert(f.display().to_string(), digest.into());
    }
    let identity =
        serde_json::json!({ "config": text, "quick": quick, "sha256": inputs }).to_string();
    let stamp = out.join("run.json");
    if stamp.is_file() {
        let old = std::fs::read_to_string(&stamp).with_context(|| stamp.display().to_string())?;
        if !resume && !report_only {
            bail!(
                "{}: holds a TacBench run already (pass --resume to continue it, or choose another --out)",
                out.display()
            );
        }
        if old != identity {
            bail!(
                "{}: was run with another config, --quick setting, recipe or weights file; --resume continues only the same run",
                stamp.display()
            );
        }
    } else if report_only {
        bail!("{}: holds no TacBench run to report", out.display());
    } else {
        if out.is_dir() && std::fs::read_dir(out)?.next().is_some() {
            bail!("{}: output directory is not empty", out.display());
        }
        std::fs::create_dir_all(out)
            .with_context(|| format!("{}: cannot create", out.display()))?;
        sparsh_data::write_atomic(&stamp, identity.as_bytes())?;
    }
    let start = Instant::now();
    let mut ensure = |task: &TaskConfig| -> Result<(), sparsh_bench::Error> {
        let complete = task.data.join("manifest.json").is_file() || official_layout(&task.data);
        if complete {
            return Ok(());
        }
        let Some(scene) = &task.scene else {
            return Err(sparsh_bench::Error::file(
                &task.data,
                format!(
                    "no dataset here and task `{}` names no scene to generate it from",
                    task.kind.name()
                ),
            ));
        };
        eprintln!(
            "generating {} from {}",
            task.data.display(),
            scene.display()
        );
        generate(
            scene,
            &task.data,
            GenerateOptions {
                resume: true,
                ..GenerateOptions::default()
            },
            DeviceArg::Cpu,
        )
        .map(drop)
        .map_err(|e| sparsh_bench::Error::file(scene, format!("{e:#}")))
    };
    let mut done = 0usize;
    let mut progress = |line: &str| {
        done += 1;
        eprintln!("[{:>6.0} s] {line}", start.elapsed().as_secs_f64());
    };
    let opts = RunOptions {
        out: out.to_path_buf(),
        resume,
        quick,
        report_only,
        tasks,
        device: device.main().clone(),
    };
    let budgets = if quick {
        vec![1.0, 0.1]
    } else {
        cfg.budgets.clone()
    };
    let draws = if quick { 200 } else { cfg.bootstrap };
    let mut report = |runs: &_, units: &[_]| {
        let rows = sparsh_bench::tacbench::report::rows(runs, units, &budgets, draws, cfg.seed);
        sparsh_bench::tacbench::report::write(out, &rows, &budgets)
    };
    let (runs, units) = run(&cfg, &opts, &mut ensure, &mut progress, &mut report)?;
    let rows = sparsh_bench::tacbench::report::rows(&runs, &units, &budgets, draws, cfg.seed);
    println!(
        "tacbench: {} units ({done} new) in {:.0} s → {}",
        units.len(),
        start.elapsed().as_secs_f64(),
        out.join("results.csv").display()
    );
    print!(
        "{}",
        sparsh_bench::tacbench::report::markdown(&rows, &budgets)
    );
    Ok(())
}

/// The config's tasks that `--task` names (`None` when it names none); a name the config has
/// no task of is a one-line error.
fn chosen_tasks(
    cfg: &BenchConfig,
    config: &Path,
    names: &[String],
) -> Result<Option<Vec<TaskKind>>> {
    if names.is_empty() {
        return Ok(None);
    }
    let mut chosen = Vec::new();
    for name in names {
        let Some(task) = cfg.task.iter().find(|t| t.kind.name() == name) else {
            let have: Vec<&str> = cfg.task.iter().map(|t| t.kind.name()).collect();
            bail!(
                "{}: --task {name}: the config has no such task (it has: {})",
                config.display(),
                have.join(", ")
            );
        };
        chosen.push(task.kind);
    }
    Ok(Some(chosen))
}

/// Whether `dir` holds a dataset not written by `sparsh generate` (an official layout).
fn official_layout(dir: &Path) -> bool {
    dir.exists() && !dir.join("labels.jsonl").exists() && !dir.join("dataset.json").exists()
}
