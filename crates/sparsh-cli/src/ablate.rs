//! `sparsh ablate`: the sim-to-real ablation (`sparsh_bench::ablate`), its progress on the
//! terminal.

use std::path::Path;
use std::time::Instant;

use anyhow::Result;
use sparsh_bench::ablate::{self, RunOptions, config::AblationConfig};
use sparsh_ssl::device::Devices;

use crate::dataset::Terminal;

/// Runs the ablation of `config` into `out` and prints the table; the CNNs, the probes and the
/// frozen encoder compute on `device` (the simulator's images are formed on the CPU).
pub fn run(config: &Path, out: &Path, resume: bool, quick: bool, device: &Devices) -> Result<()> {
    let start = Instant::now();
    let cfg = AblationConfig::load(config)?;
    let log = |line: &str| eprintln!("{line}");
    let opts = RunOptions {
        resume,
        quick,
        device: device.main().clone(),
    };
    let terminal = Terminal::default();
    let rows = ablate::run(&cfg, out, opts, &terminal, &log);
    terminal.finish();
    let rows = rows?;
    let refs: Vec<&ablate::Row> = rows.iter().collect();
    println!("{}", ablate::report::markdown(&refs));
    eprintln!(
        "{}: {} rows in {:.0} s (ablation.csv, ablation.md, ablation.png, ablation.svg)",
        out.display(),
        rows.len(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}
