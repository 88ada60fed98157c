//! `sparsh`: the command line of the sparsh tactile simulator.

mod dataset;

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};

/// Physics-based simulator of vision-based tactile sensors (DIGIT, GelSight) with ground truth.
#[derive(Debug, Parser)]
#[command(name = "sparsh", version, about)]
struct Cli {
    /// Worker threads (default: all cores); results do not depend on it.
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Render one frame of a scene to a PNG (and optionally its fields to an EXR).
    Render {
        /// Scene file (TOML).
        scene: PathBuf,
        /// Frame index (frames before it are simulated too: contact history matters).
        #[arg(long, default_value_t = 0)]
        frame: usize,
        /// Output PNG.
        #[arg(long)]
        out: PathBuf,
        /// Also write the frame's ground-truth fields to this EXR file.
        #[arg(long)]
        fields: Option<PathBuf>,
    },
    /// Simulate every frame of a scene into a dataset directory.
    Generate {
        /// Scene file (TOML).
        scene: PathBuf,
        /// Dataset directory (created; must be empty unless --force).
        #[arg(long)]
        out: PathBuf,
        /// Replace a dataset already in the directory.
        #[arg(long)]
        force: bool,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    if let Some(threads) = cli.threads {
        anyhow::ensure!(threads > 0, "--threads must be at least 1");
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build_global()
            .context("cannot start the thread pool")?;
    }
    match cli.command {
        Command::Render {
            scene,
            frame,
            out,
            fields,
        } => dataset::render(&scene, frame, &out, fields.as_deref()),
        Command::Generate { scene, out, force } => dataset::generate(&scene, &out, force),
    }
}
