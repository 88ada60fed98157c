//! `sparsh render`, `sparsh generate`, `sparsh verify` and `sparsh bench`: the dataset pipeline
//! (`sparsh-gen`) with its progress and messages on the terminal.

use std::path::Path;
use std::sync::Mutex;

use anyhow::{Context, Result, bail};
use sparsh_data::{encode_png, write_atomic};
use sparsh_gen::{GenerateOptions, GenerateReport, Observer, Shard};
use sparsh_optics::GpuContext;
use sparsh_scene::{DatasetSpec, FieldName, OutputSpec, SolverKind, Validity};
use sparsh_sim::Simulator;

use crate::progress::Progress;

/// A run's progress (a bar or periodic lines) and its notes, on stderr; each run that starts
/// (an ablation generates one dataset per variant) gets a progress display of its own.
#[derive(Debug, Default)]
pub struct Terminal {
    progress: Mutex<Option<Progress>>,
}

impl Observer for Terminal {
    fn start(&self, frames: usize) {
        let mut slot = self.progress.lock().expect("no poisoned lock");
        if let Some(p) = slot.take() {
            p.finish();
        }
        *slot = Some(Progress::new("generate", "frame", frames as u64));
    }

    fn frame_done(&self) {
        if let Some(p) = self.progress.lock().expect("no poisoned lock").as_ref() {
            p.inc(1);
        }
    }

    fn note(&self, line: &str) {
        eprintln!("{line}");
    }
}

impl Terminal {
    /// Ends the progress display.
    pub fn finish(&self) {
        if let Some(p) = self.progress.lock().expect("no poisoned lock").take() {
            p.finish();
        }
    }
}

/// `sparsh generate`: simulates the sequences of `scene_path` (this shard's, not yet recorded)
/// into `out`, with progress and a summary on stderr.
pub fn generate(
    scene_path: &Path,
    out: &Path,
    options: GenerateOptions,
    device: DeviceArg,
) -> Result<GenerateReport> {
    let gpu = device.context()?;
    let terminal = Terminal::default();
    let report = sparsh_gen::generate(scene_path, out, options, gpu.as_ref(), &terminal);
    terminal.finish();
    let report = report?;
    let frames = report.frames;
    if frames == 0 {
        eprintln!(
            "{}: every sequence{} is written and checks out; nothing to render",
            out.display(),
            if options.shard.is_some() {
                " of this shard"
            } else {
                ""
            }
        );
    } else {
        let [gap, contact, optics, writing] = report.stages.ms_per_frame(frames);
        eprintln!(
            "{frames} frames in {:.2} s: {:.1} frames/s (per frame: gap {gap:.1} ms, contact {contact:.1} ms, optics {optics:.1} ms, writing {writing:.1} ms; the stages overlap)",
            report.wall_s,
            frames as f64 / report.wall_s,
        );
    }
    if let Some(warning) = report.stages.outside_validity.warning(frames) {
        eprintln!("{}: {warning}", out.display());
    }
    if !report.complete {
        eprintln!(
            "{}: shard done; the manifest is written when every shard has run",
            out.display()
        );
    }
    Ok(report)
}

/// `sparsh verify DIR`: [`sparsh_gen::verify`], its findings on stdout.
pub fn verify(dir: &Path, shard: Option<Shard>, complete: bool) -> Result<()> {
    sparsh_gen::verify(dir, shard, complete, &mut |line| println!("{line}"))
}

/// `--device`: where images are formed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum DeviceArg {
    /// The CPU.
    Cpu,
    /// A GPU adapter (wgpu; `wgpu`, the learning commands' name, is taken too); an error if
    /// there is none.
    #[value(alias = "wgpu")]
    Gpu,
    /// A GPU adapter if there is one, else the CPU.
    Auto,
}

impl DeviceArg {
    /// The GPU context asked for: none for `cpu`; for `auto` without an adapter, one line on
    /// stderr and none.
    pub fn context(self) -> Result<Option<GpuContext>> {
        if self == DeviceArg::Cpu {
            return Ok(None);
        }
        match (self, GpuContext::shared()) {
            (_, Ok(ctx)) => {
                eprintln!("images formed with wgpu on {}", ctx.adapter());
                Ok(Some(ctx))
            }
            (DeviceArg::Gpu, Err(e)) => Err(anyhow::anyhow!("--device gpu: {e}")),
            (_, Err(e)) => {
                eprintln!("--device auto: {e}; images formed on the CPU");
                Ok(None)
            }
        }
    }
}

/// Renders frame `index` of sequence `sequence` to `out` (PNG), and optionally its fields.
pub fn render(
    scene_path: &Path,
    sequence: usize,
    index: usize,
    out: &Path,
    fields: Option<&Path>,
    device: DeviceArg,
) -> Result<()> {
    let spec = DatasetSpec::load(scene_path)?;
    let sequences = spec.sequence_count();
    if sequence >= sequences {
        bail!(
            "{}: --sequence {sequence} is out of range: the scene has {sequences} sequences",
            scene_path.display()
        );
    }
    let gpu = device.context()?;
    let scene = spec.sequence(sequence)?.scene;
    sparsh_gen::auto_notes(scene_path, &scene)
        .iter()
        .for_each(|line| eprintln!("{line}"));
    let mut sim = Simulator::on_device(scene, gpu.as_ref())?;
    let count = sim.frame_count();
    if index >= count {
        bail!(
            "{}: --frame {index} is out of range: the sequence has {count} frames",
            scene_path.display()
        );
    }
    let mut frame = None;
    for _ in 0..=index {
        frame = sim.next_frame().transpose()?;
    }
    let frame = frame.expect("index < frame count");
    let png = encode_png(&frame.image).map_err(anyhow::Error::msg)?;
    write_atomic(out, &png)?;
    if let Some(path) = fields {
        let spec = OutputSpec {
            fields: FieldName::ALL.to_vec(),
            ..spec.output.clone()
        };
        write_atomic(path, &sparsh_gen::fields_exr(&frame.fields, &spec)?)?;
    }
    let [fx, fy, fz] = frame.fields.force_n;
    let validity = match frame.validity {
        Validity::Ok => String::new(),
        outside => format!(
            "; warning: the {} rung is outside its validity: {outside}",
            frame.solver.name()
        ),
    };
    eprintln!(
        "{}: frame {index} ({}×{}), force [{fx:.3}, {fy:.3}, {fz:.3}] N, slip {}{}{validity}",
        out.display(),
        frame.image.width(),
        frame.image.height(),
        frame.slip_state.name(),
        fields.map_or(String::new(), |p| format!("; fields {}", p.display()))
    );
    Ok(())
}

/// `sparsh bench SCENE`: generates the scene once per solver rung and mechanics stride into a
/// scratch directory and prints frames/s, the ratio to the first run, and each stage's time per
/// frame.
pub fn bench(
    scene_path: &Path,
    solvers: &[SolverKind],
    strides: &[usize],
    device: DeviceArg,
) -> Result<()> {
    println!(
        "| solver | stride | frames | frames/s | × first | gap ms | contact ms | optics ms | writing ms |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    let mut first_fps = None;
    for (&solver, &stride) in solvers
        .iter()
        .flat_map(|s| strides.iter().map(move |k| (s, k)))
    {
        let scratch = tempfile::tempdir().context("cannot make a scratch directory")?;
        let report = generate(
            scene_path,
            &scratch.path().join("ds"),
            GenerateOptions {
                solver: Some(solver),
                mechanics_stride: Some(stride),
                ..GenerateOptions::default()
            },
            device,
        )?;
        let fps = report.frames as f64 / report.wall_s;
        let base = *first_fps.get_or_insert(fps);
        let [gap, contact, optics, writing] = report.stages.ms_per_frame(report.frames);
        println!(
            "| {} | {stride} | {} | {fps:.1} | {:.2} | {gap:.2} | {contact:.2} | {optics:.2} | {writing:.2} |",
            solver.name(),
            report.frames,
            fps / base,
        );
    }
    Ok(())
}
