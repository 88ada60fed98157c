//! `sparsh`: the command line of the sparsh tactile simulator.

mod ablate;
mod bench_train;
mod dataset;
mod embed;
mod fieldprobe;
mod optics;
mod pretrain;
mod progress;
mod study;
mod tacbench;
mod validate;

use std::path::{Path, PathBuf};
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
    /// No progress on stderr (the bar on a terminal, the periodic lines otherwise); results and
    /// errors are still printed.
    #[arg(long, global = true)]
    quiet: bool,
    /// Seconds between progress lines of `generate`, `pretrain`, `probe` and `embed` when stderr is not
    /// a terminal (a log file or a pipe).
    #[arg(long, global = true, value_name = "SECONDS", default_value_t = 5.0)]
    progress_interval: f64,
    #[command(subcommand)]
    command: Command,
}

/// Where a learning command computes.
#[derive(Debug, clap::Args)]
struct DeviceArgs {
    /// cpu (burn's CPU backend), wgpu (a GPU through Vulkan / Metal / DX12; Mesa's lavapipe is a
    /// software one), cuda (a build with `--features cuda`) or auto (CUDA, else a hardware wgpu
    /// adapter, else the CPU).
    #[arg(long, default_value = "cpu", value_parser = clap::value_parser!(sparsh_ssl::device::DeviceKind))]
    device: sparsh_ssl::device::DeviceKind,
    /// Which devices of the --device kind (indices as `sparsh devices` lists them, e.g. 0,1):
    /// pretrain splits every batch across them (data-parallel) and averages their gradients on
    /// the first; probe computes on the first; tacbench, fieldprobe, embed and ablate take one
    /// index. Default: the kind's first device.
    #[arg(long, value_name = "I,J,…")]
    devices: Option<String>,
}

impl DeviceArgs {
    /// The devices asked for, named on stderr unless they are the one CPU.
    fn choose(&self) -> Result<sparsh_ssl::device::Devices> {
        let devices = self.pick()?;
        Self::announce(&devices);
        Ok(devices)
    }

    /// The one device of a command that computes on one (`command` names it in the error when
    /// --devices lists several).
    fn choose_one(&self, command: &str) -> Result<sparsh_ssl::device::Devices> {
        let devices = self.pick()?;
        anyhow::ensure!(
            devices.devices.len() == 1,
            "--devices: {command} computes on one device; give one index, not {}",
            devices.devices.len()
        );
        Self::announce(&devices);
        Ok(devices)
    }

    fn pick(&self) -> Result<sparsh_ssl::device::Devices> {
        let indices = match &self.devices {
            Some(s) => sparsh_ssl::device::parse_indices(s).map_err(anyhow::Error::msg)?,
            None => Vec::new(),
        };
        Ok(sparsh_ssl::device::Devices::choose(self.device, &indices)?)
    }

    fn announce(devices: &sparsh_ssl::device::Devices) {
        if devices.kind != sparsh_ssl::device::DeviceKind::Cpu || devices.devices.len() > 1 {
            eprintln!("device: {}", devices.names.join(", "));
        }
    }
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Render one frame of a scene to a PNG (and optionally its fields to an EXR).
    Render {
        /// Scene file (TOML).
        scene: PathBuf,
        /// Sequence of a dataset file (from 0).
        #[arg(long, default_value_t = 0)]
        sequence: usize,
        /// Frame index within the sequence (frames before it are simulated too: contact
        /// history matters).
        #[arg(long, default_value_t = 0)]
        frame: usize,
        /// The PNG to write (`--out` is accepted too).
        #[arg(long, alias = "out")]
        png: PathBuf,
        /// Also write the frame's ground-truth fields to this EXR file.
        #[arg(long)]
        fields: Option<PathBuf>,
        /// Where images are formed: `cpu`, `gpu` (wgpu; an error without an adapter) or `auto`
        /// (the GPU if there is one, else the CPU).
        #[arg(long, value_enum, default_value = "cpu")]
        device: dataset::DeviceArg,
    },
    /// Simulate every sequence of a scene or dataset file into a dataset directory.
    Generate {
        /// Scene or dataset file (TOML).
        scene: PathBuf,
        /// Dataset directory (created; must be empty unless --force, --resume or --shard).
        #[arg(long)]
        out: PathBuf,
        /// Replace a dataset already in the directory.
        #[arg(long)]
        force: bool,
        /// Continue an interrupted run: redo only the sequences not yet recorded.
        #[arg(long)]
        resume: bool,
        /// Make only sequences s with s mod N = K (K from 0), into a directory shared by all
        /// shards; the last shard to finish writes the manifest.
        #[arg(long, value_name = "K/N")]
        shard: Option<sparsh_gen::Shard>,
        /// Where images are formed: `cpu`, `gpu` (wgpu; an error without an adapter) or `auto`
        /// (the GPU if there is one, else the CPU).
        #[arg(long, value_enum, default_value = "cpu")]
        device: dataset::DeviceArg,
    },
    /// Measure the whole pipeline's throughput (frames/s and each stage's time per frame) per
    /// solver rung.
    Bench {
        /// Scene file (TOML); its output settings decide what is written.
        scene: PathBuf,
        /// Solver rungs to compare; the first is the baseline of the ratios.
        #[arg(long = "solver", default_values = ["geometric", "halfspace", "layered"], num_args = 1..)]
        solvers: Vec<sparsh_scene::SolverKind>,
        /// Mechanics strides to compare (pixels per contact cell).
        #[arg(long = "stride", default_values = ["1", "2", "4"], num_args = 1..)]
        strides: Vec<usize>,
        /// Where images are formed: `cpu`, `gpu` (wgpu; an error without an adapter) or `auto`
        /// (the GPU if there is one, else the CPU).
        #[arg(long, value_enum, default_value = "cpu")]
        device: dataset::DeviceArg,
    },
    /// Time the image formation per frame: each model, with and without shadows, at 320×240
    /// and 640×480, on 1 and 2 CPU threads (a ball pressed into the GelSight 2017 preset).
    BenchOptics {
        /// Calibration of the calibrated model (default: the checkout's
        /// assets/calib/gelsight).
        #[arg(long)]
        calib: Option<PathBuf>,
        /// Timed frames per configuration (after one warm-up); the median is reported.
        #[arg(long, default_value_t = 15)]
        repeats: usize,
        /// CPU thread counts to time.
        #[arg(long = "threads-list", default_values = ["1", "2"], num_args = 1..)]
        thread_counts: Vec<usize>,
        /// `gpu` or `auto` also time each model on the GPU (`auto`: if there is an adapter).
        #[arg(long, value_enum, default_value = "cpu")]
        device: dataset::DeviceArg,
    },
    /// Time training steps on a device: the reference step (a ViT, a linear pixel head, MSE,
    /// Adam; the step `crates/sparsh-ssl/benches/torch_step.py` takes in PyTorch) and recipes'
    /// own steps, in images/s, with the device's f32 matrix-product rate; `--parity` also
    /// compares one step of each recipe on the CPU and on the device.
    BenchTrain {
        /// Recipe (TOML) whose training step to time, at its batch size unless --batch; repeat
        /// for several.
        #[arg(long = "config")]
        configs: Vec<PathBuf>,
        /// Reference steps to time: ViT sizes tiny (192 wide, 6 blocks), small (384, 12), base
        /// (768, 12), comma-separated.
        #[arg(long, value_delimiter = ',')]
        reference: Vec<String>,
        /// The reference input, HEIGHTxWIDTH in pixels (6 channels; the official input is
        /// 320x240).
        #[arg(long, default_value = "320x240")]
        input: String,
        /// The reference patch side in pixels.
        #[arg(long, default_value_t = 16)]
        patch: usize,
        /// Images per step: the reference's (default 32) and each recipe's in place of its own.
        #[arg(long)]
        batch: Option<usize>,
        /// Untimed steps before the timed ones.
        #[arg(long, default_value_t = 2)]
        warmup: usize,
        /// Timed steps; the median is reported.
        #[arg(long, default_value_t = 5)]
        steps: usize,
        /// Also time an N×N×N f32 matrix product on the device (the rate a step could reach).
        #[arg(long, default_value_t = 0, value_name = "N")]
        gemm: usize,
        /// Also take one step of each recipe on the CPU and on the device from the same weights
        /// and batch (two images per micro-batch) and compare losses, gradients and updated
        /// weights.
        #[arg(long)]
        parity: bool,
        /// Also write the rows as JSON here.
        #[arg(long)]
        json: Option<PathBuf>,
        #[command(flatten)]
        device: DeviceArgs,
    },
    /// Write a dataset in another project's layout.
    Export {
        /// Dataset directory written by `generate`.
        dir: PathBuf,
        /// Target layout: `sparsh-pkl`, what the official Sparsh code's loaders read: force/slip
        /// batch folders, SSL pickles with their backgrounds, and Hydra data configs naming them.
        #[arg(long, value_parser = ["sparsh-pkl"])]
        format: String,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
    },
    /// Fit the calibrated optics on real images of a ball pressed into a sensor (a Taxim pack).
    Calibrate {
        /// Calibration pack (npz: f0, imgs, touch_center, touch_radius).
        #[arg(long)]
        pack: PathBuf,
        /// Ball radius (mm).
        #[arg(long, default_value_t = 2.0)]
        ball_radius_mm: f64,
        /// Pixel pitch of the pack (mm per pixel); default: `sensor.pixmm` of the params.json
        /// beside the pack (Taxim's layout).
        #[arg(long)]
        pixmm: Option<f64>,
        /// Frames to fit on.
        #[arg(long, default_value = "even")]
        frames: sparsh_optics::FrameSet,
        /// Calibration directory to write.
        #[arg(long)]
        out: PathBuf,
        /// Fit the map through the shadows of the sensor's LEDs, their z fitted too (needs
        /// --sensor).
        #[arg(long)]
        shadows: bool,
        /// Shadow-march samples per ray (with --shadows).
        #[arg(long, default_value_t = 32)]
        shadow_steps: u32,
        /// Sensor preset whose LED layout starts the shadow fit (gelsight2017 for the GelSight
        /// pack, gelsight_mini_vga for the Mini).
        #[arg(long)]
        sensor: Option<String>,
        /// The surface under the ball: `hertz` (closed form), or a rung pressed until its contact
        /// circle has the marked radius (`geometric`, `halfspace`, `layered`); fit one map per
        /// rung a scene renders with.
        #[arg(long, default_value = "hertz")]
        mechanics: String,
        /// Gel thickness for `--mechanics geometric|layered` (mm).
        #[arg(long)]
        gel_thickness_mm: Option<f64>,
        /// Poisson ratio for `--mechanics layered`.
        #[arg(long, default_value_t = 0.49)]
        poisson_ratio: f64,
    },
    /// Render a pack's ball indentations with a calibration and score them against the real frames.
    Sim2real {
        /// Calibration pack (npz).
        #[arg(long)]
        pack: PathBuf,
        /// Calibration directory written by `calibrate`.
        #[arg(long)]
        calib: PathBuf,
        /// Ball radius (mm).
        #[arg(long, default_value_t = 2.0)]
        ball_radius_mm: f64,
        /// Pixel pitch of the pack (mm per pixel); default: the calibration's
        /// (`provenance.mm_per_px` of its map.json), which it must equal when given.
        #[arg(long)]
        pixmm: Option<f64>,
        /// Render with cast shadows: of the calibration's fitted LEDs when it was fitted with
        /// --shadows, otherwise of --sensor's.
        #[arg(long)]
        shadows: bool,
        /// Shadow-march samples per ray (default: the calibration's, else 32).
        #[arg(long)]
        shadow_steps: Option<u32>,
        /// Sensor preset for the shadows' shading (default: the one the calibration was fitted
        /// with).
        #[arg(long)]
        sensor: Option<String>,
        /// Frames to score.
        #[arg(long, default_value = "odd")]
        frames: sparsh_optics::FrameSet,
        /// Print JSON (summary and per-frame scores).
        #[arg(long)]
        json: bool,
        /// Also write each rendered frame as DIR/NNN.png.
        #[arg(long)]
        save: Option<PathBuf>,
        /// Also write real | simulated | difference (×4, on grey) of the frame with the median
        /// crop PSNR to this PNG.
        #[arg(long)]
        figure: Option<PathBuf>,
        /// Also fit each scored frame's contact circle by rendering (centre and radius whose
        /// render is closest to the frame, from its mark) and compare the pack's marks to the
        /// fits: how far the marks are from what the images show. About 250 renders a frame
        /// (79 s for Taxim's 24 GelSight frames on two cores with Hertz's surface; under a
        /// rung's mechanics each render also solves the rung).
        #[arg(long)]
        refit: bool,
    },
    /// Check every file of a dataset against the checksums in its manifest; on a dataset still
    /// being generated by shards, say which shards are done, check their files against their
    /// records and name the missing shards.
    Verify {
        /// Dataset directory.
        dir: PathBuf,
        /// Check only the sequences of shard K of N (those s with s mod N = K).
        #[arg(long, value_name = "K/N")]
        shard: Option<sparsh_gen::Shard>,
        /// Also fail when the dataset (or the --shard) is not complete.
        #[arg(long)]
        complete: bool,
    },
    /// Check the contact solvers against analytic solutions; exits 1 if a case misses.
    Validate {
        /// Directory of validation cases (default: the checkout's scenes/validation).
        dir: Option<PathBuf>,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Chart every solver rung's speed against its accuracy on analytic scenes, map where each
    /// one fails, and write the table `solver = "auto"` reads.
    Study {
        /// Output directory (study.csv, stability.csv, solver_table.csv, PNG and SVG charts).
        #[arg(long)]
        out: PathBuf,
        /// Coarse grids and one run per point (about 6 minutes on 2 cores).
        #[arg(long)]
        quick: bool,
        /// Also write the solver table here (assets/solver_table.csv is the one compiled in);
        /// with --sweep, replace the rows of those sweeps in the table already there.
        #[arg(long)]
        table: Option<PathBuf>,
        /// Run only these stability sweeps (comma-separated: depth_over_thickness, press_slide,
        /// sharpness, poisson_ratio, friction, tangential_load, contact_cells) and no accuracy
        /// study: their rows replace theirs in OUT/stability.csv (the other sweeps' rows kept),
        /// and in the --table given; no charts.
        #[arg(long, value_delimiter = ',')]
        sweep: Vec<String>,
        /// Stability points solved at once, each on one thread (the results do not depend on
        /// it; each point's time is its own thread's, so other jobs perturb it a little).
        #[arg(long, default_value_t = 1)]
        jobs: usize,
    },
    /// Print where each solver rung holds at a relative force tolerance (from the study's
    /// compiled-in table): the limits a scene's `validity` policy checks every frame against.
    Limits {
        /// Relative force tolerance, in (0, 1).
        #[arg(long, default_value_t = 0.02)]
        tolerance: f64,
    },
    /// List the devices `pretrain` and `probe` can compute on (`--device KIND --devices I,J`
    /// index this list).
    Devices,
    /// Self-supervised pretraining of a ViT encoder (MAE, DINO, I-JEPA, V-JEPA) from a recipe.
    Pretrain {
        /// Training recipe (TOML), e.g. assets/ssl/mae_tiny_cpu.toml.
        #[arg(long)]
        config: PathBuf,
        /// Dataset: a directory (generated or Sparsh pickles) or a Taxim pack (`dataPack.npz`
        /// or its directory); repeat to pool the sequences of several.
        #[arg(long, required = true)]
        data: Vec<PathBuf>,
        /// Labelled dataset of the online force probe (default: the --data sets); repeat for
        /// several. Probing a fixed labelled set lets runs on different data be compared.
        #[arg(long)]
        probe_data: Vec<PathBuf>,
        /// Run directory (log.csv, checkpoint/, encoder.safetensors).
        #[arg(long)]
        out: PathBuf,
        /// Continue the run in --out from its last checkpoint.
        #[arg(long)]
        resume: bool,
        /// Stop after this many steps in total (the schedule keeps the recipe's length).
        #[arg(long)]
        max_steps: Option<usize>,
        #[command(flatten)]
        device: DeviceArgs,
    },
    /// Force probe of an encoder against the recipe's randomly initialised one, over several
    /// probe seeds.
    Probe {
        /// Recipe (TOML) whose encoder shape, data stacking and `[log]` probe settings apply.
        #[arg(long)]
        config: PathBuf,
        /// Labelled dataset directory; repeat for several.
        #[arg(long, required = true)]
        data: Vec<PathBuf>,
        /// Encoder weights (safetensors, e.g. runs/NAME/encoder.safetensors); without it only
        /// the random encoder is probed.
        #[arg(long)]
        encoder: Option<PathBuf>,
        /// How many probe seeds (0..N) to fit each probe with (`--seeds` is accepted too).
        #[arg(long, alias = "seeds", default_value_t = 3)]
        probe_seeds: u64,
        /// Label budget: fit the probes on this share of the training samples (default: the
        /// recipe's `[log] probe_label_fraction`).
        #[arg(long)]
        label_fraction: Option<f64>,
        /// Also fit the attentive probe on the raw input patches (no encoder): what the
        /// encoders' tokens are up against.
        #[arg(long)]
        patches: bool,
        /// Also probe this many randomly initialised encoders (recipe seeds seed, seed + 1, …)
        /// and rank the pretrained encoder among them: one random draw is a noisy baseline.
        #[arg(long)]
        random_inits: Option<u64>,
        #[command(flatten)]
        device: DeviceArgs,
    },
    /// Features of every frame of a generated dataset from a trained encoder, as its recipe
    /// feeds it (the frame stacking, each frame against its sequence's background); written as
    /// safetensors (`features`, `frame`) or .npy (`features`), by the extension of --out.
    Embed {
        /// Encoder weights (safetensors, e.g. runs/NAME/encoder.safetensors).
        #[arg(long)]
        encoder: PathBuf,
        /// The encoder's recipe (TOML; default: recipe.toml beside the encoder, as a run
        /// directory holds it).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Dataset directory written by `generate`.
        #[arg(long)]
        data: PathBuf,
        /// Output file: .safetensors or .npy; rows in ascending frame number.
        #[arg(long)]
        out: PathBuf,
        /// Features per frame: `mean` of the patch tokens (`[frames, dim]`) or `none`, every
        /// patch token (`[frames, tokens, dim]`).
        #[arg(long, value_enum, default_value = "mean")]
        pool: embed::PoolArg,
        /// Frames per forward pass.
        #[arg(long, default_value_t = 32)]
        batch_size: usize,
        #[command(flatten)]
        device: DeviceArgs,
    },
    /// TacBench: frozen encoders read out by the attentive probe on force, slip, pose,
    /// texture and grasp tasks at label budgets, against random draws of the same
    /// architecture, the probe on raw patches, the same ViT trained end to end, a constant
    /// predictor, a ridge read-out of the frames, a supervised CNN (the ceiling) and the floor
    /// oracles on the true indentation; writes results.csv, results.md and a chart per task.
    Tacbench {
        /// Benchmark config (TOML, e.g. tacbench/cpu_small.toml); its paths are relative to it.
        #[arg(long)]
        config: PathBuf,
        /// Run directory (units/, results.csv, results.md, budget_TASK.png/.svg).
        #[arg(long)]
        out: PathBuf,
        /// Small settings for a smoke run: 2 epochs, 2 random draws, budgets 1 and 0.1, at
        /// most 20 sequences per task.
        #[arg(long)]
        quick: bool,
        /// Continue a run in --out, skipping the units it finished.
        #[arg(long)]
        resume: bool,
        /// Train nothing: rewrite the report of the run in --out from the units it finished.
        #[arg(long, conflicts_with = "resume")]
        report_only: bool,
        /// Run only this task of the config (force, slip, pose, texture or grasp; repeat for
        /// several): a run can be done a few tasks at a time, each later one with --resume.
        /// The report then shows these tasks; --report-only without it shows every finished one.
        #[arg(long = "task", value_name = "KIND")]
        tasks: Vec<String>,
        #[command(flatten)]
        device: DeviceArgs,
    },
    /// Sim-to-real ablation: train on synthetic frames of each simulator variant, score the
    /// contact circle on real frames (ablations/*.toml).
    Ablate {
        /// Ablation file (TOML).
        #[arg(long)]
        config: PathBuf,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Continue a run: skip the variants already recorded.
        #[arg(long)]
        resume: bool,
        /// Small settings for tests: 24 sequences per variant, 2 epochs, one seed, 2 folds.
        #[arg(long)]
        quick: bool,
        #[command(flatten)]
        device: DeviceArgs,
    },
    /// T1A: the normal and shear field decoder (DPT) on a frozen encoder, trained without
    /// field labels, scored against the simulator's ground-truth fields.
    Fieldprobe {
        #[command(subcommand)]
        action: FieldprobeAction,
    },
}

#[derive(Debug, Subcommand)]
enum FieldprobeAction {
    /// Train the self-supervised decoder and the references (supervised ceiling, random
    /// encoders) on the training sequences of a generated dataset; reads no field while
    /// training the self-supervised decoders.
    Train {
        /// Field-probe config (TOML, e.g. tacbench/fields_cpu.toml).
        #[arg(long)]
        config: PathBuf,
        /// Frozen encoder weights (safetensors) of the config's recipe.
        #[arg(long)]
        encoder: PathBuf,
        /// Dataset written by `sparsh generate` (e.g. from scenes/tacbench_fields.toml).
        #[arg(long)]
        data: PathBuf,
        /// Run directory (run.json, decoders/).
        #[arg(long)]
        out: PathBuf,
        /// Smoke run: 3 steps per decoder, one random draw, 24 training pairs.
        #[arg(long)]
        quick: bool,
        /// Continue a run in --out: keep each model already trained there whose encoder, data
        /// and settings are unchanged, train the rest (e.g. a reference added to the config).
        #[arg(long)]
        resume: bool,
        #[command(flatten)]
        device: DeviceArgs,
    },
    /// Check the shear branch's loss: per family, its value for the true lateral motion of the
    /// gel, zero flow and a uniform flow on the training pairs in contact (reads the fields).
    Objective {
        /// Field-probe config (its recipe gives the input size and pair offset, its [loss] the
        /// weights).
        #[arg(long)]
        config: PathBuf,
        /// Dataset with fields.
        #[arg(long)]
        data: PathBuf,
    },
    /// Score a run's decoders, the classical baselines and the markers on the held-out
    /// sequences against the ground-truth fields; writes RUN/eval/fields.csv, fields.md and
    /// fields_examples.png.
    Eval {
        /// Run directory written by `sparsh fieldprobe train`.
        #[arg(long)]
        run: PathBuf,
        /// Dataset with fields (its `test` split is scored).
        #[arg(long)]
        data: PathBuf,
        /// Also score the contact region on a real Taxim calibration pack (dataPack.npz);
        /// may be given several times.
        #[arg(long)]
        pack: Vec<PathBuf>,
        #[command(flatten)]
        device: DeviceArgs,
    },
}

fn main() -> ExitCode {
    end_quietly_on_a_closed_pipe();
    quiet_device_select_without_a_session();
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {}", one_line(&err));
            ExitCode::FAILURE
        }
    }
}

/// A table piped into `head` (or any reader that stops early) ends the command as it ends other
/// Unix tools: by `SIGPIPE`, silently. Rust ignores the signal by default, so the next write to
/// the closed pipe would be an error, and `println!` panics on it.
fn end_quietly_on_a_closed_pipe() {
    #[cfg(unix)]
    // SAFETY: the first thing `main` does, before any other thread exists; restores the
    // signal's default disposition.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// Outside a desktop session (no `XDG_RUNTIME_DIR`: ssh, CI, containers) Mesa's Vulkan
/// device-select layer asks the Wayland library for the session's default GPU whenever wgpu
/// lists adapters, and that library prints `error: XDG_RUNTIME_DIR is invalid or not set in the
/// environment.` on stderr, several times, though nothing failed. The layer only reorders
/// adapters (wgpu chooses its own), so there it is switched off (`NODEVICE_SELECT=1`, Mesa's
/// switch) unless the user set that variable.
fn quiet_device_select_without_a_session() {
    if std::env::var_os("XDG_RUNTIME_DIR").is_none()
        && std::env::var_os("NODEVICE_SELECT").is_none()
    {
        // SAFETY: the first thing `main` does, before any other thread exists.
        unsafe { std::env::set_var("NODEVICE_SELECT", "1") };
    }
}

/// An error and its causes on one line, `outer: cause: …`, leaving out a cause whose text the
/// line already holds (an error that prints its source in its own message and also chains it
/// would otherwise say it twice); a cause written on several lines (some decoders' errors) is
/// joined with spaces.
fn one_line(err: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in err.chain() {
        let text = cause
            .to_string()
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty())
            .collect::<Vec<_>>()
            .join(" ");
        if text.is_empty() || line.contains(&text) {
            continue;
        }
        if !line.is_empty() {
            line.push_str(": ");
        }
        line.push_str(&text);
    }
    line
}

/// A file shipped with the project, for a default: `path` in the checkout this binary was built
/// from (its assets), whatever the working directory; `path` from the working directory only
/// when that checkout is gone.
fn shipped(path: &str) -> PathBuf {
    let checkout = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join(path);
    if checkout.exists() {
        checkout
    } else {
        PathBuf::from(path)
    }
}

fn run(cli: Cli) -> Result<()> {
    anyhow::ensure!(
        cli.progress_interval.is_finite() && cli.progress_interval >= 0.0,
        "--progress-interval must be a number of seconds ≥ 0, got {}",
        cli.progress_interval
    );
    progress::configure(cli.quiet, cli.progress_interval);
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
            sequence,
            frame,
            png,
            fields,
            device,
        } => dataset::render(&scene, sequence, frame, &png, fields.as_deref(), device),
        Command::Generate {
            scene,
            out,
            force,
            resume,
            shard,
            device,
        } => dataset::generate(
            &scene,
            &out,
            sparsh_gen::GenerateOptions {
                force,
                resume,
                shard,
                ..Default::default()
            },
            device,
        )
        .map(drop),
        Command::Bench {
            scene,
            solvers,
            strides,
            device,
        } => dataset::bench(&scene, &solvers, &strides, device),
        Command::BenchOptics {
            calib,
            repeats,
            thread_counts,
            device,
        } => optics::bench(
            &calib.unwrap_or_else(|| shipped("assets/calib/gelsight")),
            repeats,
            &thread_counts,
            device,
        ),
        Command::BenchTrain {
            configs,
            reference,
            input,
            patch,
            batch,
            warmup,
            steps,
            gemm,
            parity,
            json,
            device,
        } => bench_train::bench_train(
            &bench_train::BenchTrain {
                configs: &configs,
                reference: &reference,
                input: bench_train::parse_input(&input).map_err(anyhow::Error::msg)?,
                patch,
                batch,
                warmup,
                steps,
                gemm,
                parity,
                json: json.as_deref(),
            },
            &device.choose_one("bench-train")?,
        ),
        Command::Verify {
            dir,
            shard,
            complete,
        } => dataset::verify(&dir, shard, complete),
        Command::Calibrate {
            pack,
            ball_radius_mm,
            pixmm,
            frames,
            out,
            shadows,
            shadow_steps,
            sensor,
            mechanics,
            gel_thickness_mm,
            poisson_ratio,
        } => optics::calibrate(
            &pack,
            ball_radius_mm,
            pixmm,
            frames,
            &out,
            optics::ShadowOptions {
                shadows,
                steps: Some(shadow_steps),
                sensor: sensor.as_deref(),
            },
            optics::mechanics(&mechanics, gel_thickness_mm, poisson_ratio)?,
        ),
        Command::Sim2real {
            pack,
            calib,
            ball_radius_mm,
            pixmm,
            shadows,
            shadow_steps,
            sensor,
            frames,
            json,
            save,
            figure,
            refit,
        } => optics::sim2real(
            &pack,
            &calib,
            optics::Sim2realOptions {
                ball_radius_mm,
                mm_per_px: pixmm,
                shadows: optics::ShadowOptions {
                    shadows,
                    steps: shadow_steps,
                    sensor: sensor.as_deref(),
                },
                frames,
                json,
                save: save.as_deref(),
                figure: figure.as_deref(),
                refit,
            },
        ),
        Command::Export {
            dir,
            format: _,
            out,
        } => {
            let done = sparsh_data::sparsh_pkl::export(&dir, &out)?;
            eprintln!(
                "{}: {} sequences ({}) in the official Sparsh layouts; data configs \
                 sparsh_ssl.yaml and sparsh_force_slip_<sensor>.yaml",
                out.display(),
                done.sequences,
                done.sensors.join(", ")
            );
            Ok(())
        }
        Command::Validate { dir, json } => {
            validate::validate(&dir.unwrap_or_else(|| shipped("scenes/validation")), json)
        }
        Command::Study {
            out,
            quick,
            table,
            sweep,
            jobs,
        } => study::study(&out, quick, table.as_deref(), sweep, jobs),
        Command::Limits { tolerance } => study::limits(tolerance),
        Command::Devices => pretrain::devices(),
        Command::Pretrain {
            config,
            data,
            probe_data,
            out,
            resume,
            max_steps,
            device,
        } => pretrain::pretrain(
            &config,
            data,
            probe_data,
            out,
            resume,
            max_steps,
            &device.choose()?,
        ),
        Command::Probe {
            config,
            data,
            encoder,
            probe_seeds,
            label_fraction,
            patches,
            random_inits,
            device,
        } => pretrain::probe(
            &config,
            &data,
            encoder.as_deref(),
            probe_seeds,
            label_fraction,
            patches,
            random_inits,
            &device.choose()?,
        ),
        Command::Embed {
            encoder,
            config,
            data,
            out,
            pool,
            batch_size,
            device,
        } => embed::embed(
            &encoder,
            config.as_deref(),
            &data,
            &out,
            pool,
            batch_size,
            &device.choose_one("embed")?,
        ),
        Command::Tacbench {
            config,
            out,
            quick,
            resume,
            report_only,
            tasks,
            device,
        } => tacbench::tacbench(
            &config,
            &out,
            quick,
            resume,
            report_only,
            &tasks,
            &device.choose_one("tacbench")?,
        ),
        Command::Ablate {
            config,
            out,
            resume,
            quick,
            device,
        } => ablate::run(&config, &out, resume, quick, &device.choose_one("ablate")?),
        Command::Fieldprobe { action } => match action {
            FieldprobeAction::Train {
                config,
                encoder,
                data,
                out,
                quick,
                resume,
                device,
            } => fieldprobe::train(
                &config,
                &encoder,
                &data,
                &out,
                quick,
                resume,
                &device.choose_one("fieldprobe")?,
            ),
            FieldprobeAction::Objective { config, data } => fieldprobe::objective(&config, &data),
            FieldprobeAction::Eval {
                run,
                data,
                pack,
                device,
            } => fieldprobe::eval(&run, &data, &pack, &device.choose_one("fieldprobe")?),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An error whose message already holds its source's text is printed once, not twice.
    #[test]
    fn a_cause_already_in_the_message_is_not_repeated() {
        #[derive(Debug)]
        struct Wrapped(std::io::Error);
        impl std::fmt::Display for Wrapped {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                write!(f, "cases: {}", self.0)
            }
        }
        impl std::error::Error for Wrapped {
            fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
                Some(&self.0)
            }
        }
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "No such file");
        let err = anyhow::Error::new(Wrapped(io)).context("validate");
        assert_eq!(one_line(&err), "validate: cases: No such file");
        let chained = anyhow::Error::new(std::io::Error::other("denied")).context("a.png");
        assert_eq!(one_line(&chained), "a.png: denied");
    }

    /// List options take several values after one flag, as the README shows them.
    #[test]
    fn list_options_take_several_values() {
        let cli = Cli::try_parse_from(["sparsh", "bench-optics", "--threads-list", "1", "2"])
            .expect("parses");
        let Command::BenchOptics { thread_counts, .. } = cli.command else {
            panic!("bench-optics");
        };
        assert_eq!(thread_counts, [1, 2]);
        // the global --threads is not shadowed by --threads-list
        let cli =
            Cli::try_parse_from(["sparsh", "bench-optics", "--threads", "2"]).expect("parses");
        assert_eq!(cli.threads, Some(2));
        let cli = Cli::try_parse_from([
            "sparsh",
            "bench",
            "s.toml",
            "--solver",
            "halfspace",
            "layered",
            "--stride",
            "2",
            "4",
        ])
        .expect("parses");
        let Command::Bench {
            solvers, strides, ..
        } = cli.command
        else {
            panic!("bench");
        };
        assert_eq!(
            solvers,
            [
                sparsh_scene::SolverKind::Halfspace,
                sparsh_scene::SolverKind::Layered
            ]
        );
        assert_eq!(strides, [2, 4]);
    }
}
