//! `sparsh render`, `sparsh generate` and `sparsh verify`: the simulator joined to the dataset
//! writer.

use std::path::Path;
use std::str::FromStr;
use std::sync::Mutex;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use rayon::prelude::*;
use sparsh_contact::Fields;
use sparsh_data::{
    Dataset, Identity, Label, Manifest, OpenMode, PoseLabel, SequencePart, encode_png, write_atomic,
};
use sparsh_optics::GpuContext;
use sparsh_scene::{
    DatasetSpec, FieldName, OutputSpec, Precision, Scene, SequenceScene, SolverKind, Validity,
};
use sparsh_sim::{Frame, Simulator};

use crate::progress::Progress;

/// `--shard K/N`: this run makes the sequences s with s mod N = K (K from 0).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    index: usize,
    count: usize,
}

impl Shard {
    /// Whether sequence `s` belongs to this shard.
    fn has(self, s: usize) -> bool {
        s % self.count == self.index
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

impl FromStr for Shard {
    type Err = String;

    fn from_str(s: &str) -> Result<Shard, String> {
        let (k, n) = s
            .split_once('/')
            .ok_or_else(|| format!("`{s}` is not K/N"))?;
        let parse = |v: &str| {
            v.trim()
                .parse::<usize>()
                .map_err(|_| format!("`{s}` is not K/N with whole numbers"))
        };
        let (index, count) = (parse(k)?, parse(n)?);
        if count == 0 || index >= count {
            return Err(format!("`{s}`: K must be in 0..N and N at least 1"));
        }
        Ok(Shard { index, count })
    }
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
    announce_auto(scene_path, &scene);
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
        write_atomic(path, &exr_bytes(&frame.fields, &spec)?)?;
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

/// One line on stderr saying what `solver = "auto"` chose, and a warning when no studied rung
/// is predicted to meet the tolerance (the most accurate one is used then).
fn announce_auto(scene_path: &Path, scene: &Scene) {
    let Some(choice) = &scene.auto else { return };
    eprintln!(
        "{}: solver = \"auto\" chose {} at mechanics_stride {} (contact radius ≈ {:.3} mm, \
         a/h ≈ {:.3}; predicted force error {:.2} %, tolerance {:.2} %; {:.1} ms/frame in the study)",
        scene_path.display(),
        choice.solver.name(),
        choice.mechanics_stride,
        choice.contact_radius_mm,
        choice.a_over_h,
        100.0 * choice.predicted_rel_error,
        100.0 * choice.tolerance,
        choice.predicted_ms_per_frame,
    );
    if !choice.meets_tolerance() {
        eprintln!(
            "{}: warning: no studied rung and grid is predicted to meet tolerance = {}; \
             using the most accurate one",
            scene_path.display(),
            choice.tolerance
        );
    }
}

/// What `generate` is asked to do.
#[derive(Debug, Clone, Copy)]
pub struct GenerateOptions {
    /// Replace a dataset already in the directory.
    pub force: bool,
    /// Continue an interrupted run.
    pub resume: bool,
    /// Make only this shard's sequences.
    pub shard: Option<Shard>,
    /// Use this solver rung instead of the scene's (benchmarks).
    pub solver: Option<SolverKind>,
    /// Use this mechanics stride instead of the scene's (benchmarks).
    pub mechanics_stride: Option<usize>,
    /// Where images are formed.
    pub device: DeviceArg,
}

/// What a `generate` run did.
#[derive(Debug, Clone, Copy)]
pub struct GenerateReport {
    /// Frames simulated by this run.
    pub frames: usize,
    /// Wall-clock seconds.
    pub wall_s: f64,
    /// Seconds per stage, summed over frames.
    pub stages: StageTotals,
}

/// Seconds per pipeline stage, summed over frames, and the frames outside their rung's validity.
#[derive(Debug, Default, Clone, Copy)]
pub struct StageTotals {
    /// Gap-field ray casting.
    pub gap_s: f64,
    /// Contact solve.
    pub contact_s: f64,
    /// Image formation.
    pub optics_s: f64,
    /// PNG and EXR encoding and writing.
    pub writing_s: f64,
    /// Frames outside their rung's validity.
    pub outside_validity: OutsideValidity,
}

/// Frames outside their rung's validity: how many, and the first (lowest sequence, then frame).
#[derive(Debug, Default, Clone, Copy)]
pub struct OutsideValidity {
    /// How many.
    pub frames: usize,
    /// The first: sequence, frame in the sequence, rung, what it passed, the scene's tolerance.
    pub first: Option<(usize, usize, SolverKind, Validity, f64)>,
}

impl OutsideValidity {
    fn note(&mut self, sequence: usize, frame: &Frame, tolerance: f64) {
        let here = (
            sequence,
            frame.target.index,
            frame.solver,
            frame.validity,
            tolerance,
        );
        self.merge(&OutsideValidity {
            frames: 1,
            first: Some(here),
        });
    }

    fn merge(&mut self, other: &OutsideValidity) {
        self.frames += other.frames;
        if let Some(o) = other.first
            && self.first.is_none_or(|f| (f.0, f.1) > (o.0, o.1))
        {
            self.first = Some(o);
        }
    }

    /// One warning line for a run of `frames` frames, or `None` if every frame was within its
    /// rung's validity.
    pub fn warning(&self, frames: usize) -> Option<String> {
        let (sequence, frame, rung, validity, tolerance) = self.first?;
        Some(format!(
            "warning: {} of {frames} frames are outside their solver rung's validity at the \
             {:.1} % force tolerance (first: sequence {sequence} frame {frame} on {}: {validity}); \
             see `validity` in labels.jsonl",
            self.frames,
            100.0 * tolerance,
            rung.name()
        ))
    }
}

impl StageTotals {
    /// Each stage's time per frame in milliseconds: [gap, contact, optics, writing]. The stages
    /// overlap (a frame's image forms while the next frame's contact is solved, and frames are
    /// written on a thread of their own), so the wall time per frame is less than their sum;
    /// the slowest path bounds it.
    pub fn ms_per_frame(&self, frames: usize) -> [f64; 4] {
        let parts = [self.gap_s, self.contact_s, self.optics_s, self.writing_s];
        parts.map(|v| 1e3 * v / frames.max(1) as f64)
    }
}

/// Simulates the sequences of `scene_path` (this shard's, not yet recorded) into `out`.
pub fn generate(scene_path: &Path, out: &Path, options: GenerateOptions) -> Result<GenerateReport> {
    if options.force && options.resume {
        bail!("--force and --resume contradict each other: pick one");
    }
    let spec = DatasetSpec::load(scene_path)?;
    let gpu = options.device.context()?;
    let identity = Identity {
        format: "sparsh-dataset/1".into(),
        sparsh_version: env!("CARGO_PKG_VERSION").into(),
        scene_file: spec
            .path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
        scene: spec.source.clone(),
        seed: spec.seed,
        sequences: spec.sequence_count(),
        frames: spec.frame_count(),
    };
    let mode = if options.resume || options.shard.is_some() {
        OpenMode::Join
    } else {
        OpenMode::Fresh {
            force: options.force,
        }
    };
    let dataset = Dataset::open(out, &identity, mode)?;
    if let Some(shard) = options.shard {
        dataset.record_shard_layout(shard.count)?;
    }
    let mine: Vec<usize> = (0..identity.sequences)
        .filter(|&s| options.shard.is_none_or(|sh| sh.has(s)))
        .collect();
    let mut todo: Vec<usize> = mine
        .iter()
        .copied()
        .filter(|&s| !dataset.has_part(s))
        .collect();
    if options.resume {
        todo.extend(damaged_sequences(&dataset, &mine, out)?);
        todo.sort_unstable();
    }
    let mut sequences: Vec<SequenceScene> = todo
        .iter()
        .map(|&s| spec.sequence(s))
        .collect::<Result<_, _>>()?;
    if options.solver.is_none()
        && let Some(seq) = sequences.first()
    {
        announce_auto(scene_path, &seq.scene);
    }
    for seq in &mut sequences {
        let scene = &mut seq.scene;
        scene.solver = options.solver.unwrap_or(scene.solver);
        let stride = options.mechanics_stride.unwrap_or(scene.mechanics_stride);
        let (w, h) = (scene.sensor.width_px, scene.sensor.height_px);
        if stride == 0 || !w.is_multiple_of(stride) || !h.is_multiple_of(stride) {
            bail!("mechanics stride {stride} must be ≥ 1 and divide the image size {w}×{h}");
        }
        scene.mechanics_stride = stride;
    }
    let frames: usize = sequences.iter().map(|s| s.scene.frames().len()).sum();
    let progress = Progress::new("generate", "frame", frames as u64);
    let totals = Mutex::new(StageTotals::default());
    let start = Instant::now();
    sequences
        .into_par_iter()
        .try_for_each(|seq| write_sequence(&dataset, seq, gpu.as_ref(), &progress, &totals))?;
    progress.finish();
    let wall_s = start.elapsed().as_secs_f64();
    let stages = *totals.lock().expect("no poisoned lock");
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
        let [gap, contact, optics, writing] = stages.ms_per_frame(frames);
        eprintln!(
            "{frames} frames in {wall_s:.2} s: {:.1} frames/s (per frame: gap {gap:.1} ms, contact {contact:.1} ms, optics {optics:.1} ms, writing {writing:.1} ms; the stages overlap)",
            frames as f64 / wall_s,
        );
    }
    if let Some(warning) = stages.outside_validity.warning(frames) {
        eprintln!("{}: {warning}", out.display());
    }
    let complete = dataset
        .finish_if_complete(identity.sequences, manifest(&spec, identity))
        .with_context(|| format!("cannot finish the dataset in {}", out.display()))?;
    if !complete {
        eprintln!(
            "{}: shard done; the manifest is written when every shard has run",
            out.display()
        );
    }
    Ok(GenerateReport {
        frames,
        wall_s,
        stages,
    })
}

/// A recorded sequence's check: files checked and the problems found.
type PartCheck = (usize, Vec<sparsh_data::Problem>);

/// The recorded sequences among `sequences` whose files (or record) `verify` would flag, each
/// named on stderr with its first problem: a resumed run renders them again.
fn damaged_sequences(dataset: &Dataset, sequences: &[usize], out: &Path) -> Result<Vec<usize>> {
    // a manifest that cannot be read is rewritten when the run finishes
    let manifest = sparsh_data::read_manifest(out).ok().flatten();
    let checks: Vec<Option<PartCheck>> = sequences
        .par_iter()
        .map(|&s| dataset.check_part(s, manifest.as_ref()))
        .collect();
    let mut damaged = Vec::new();
    for (&s, check) in sequences.iter().zip(checks) {
        let Some((_, problems)) = check else { continue };
        let Some(first) = problems.first() else {
            continue;
        };
        let more = match problems.len() {
            1 => String::new(),
            n => format!(" and {} more", n - 1),
        };
        eprintln!(
            "{}: {}{more}; rendering sequence {s} again",
            out.join(&first.file).display(),
            first.what
        );
        damaged.push(s);
    }
    Ok(damaged)
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
                force: false,
                resume: false,
                shard: None,
                solver: Some(solver),
                mechanics_stride: Some(stride),
                device,
            },
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

/// Simulates one sequence, writes its frames, fields and background, then its record.
///
/// Frames are encoded and written on a thread of their own while the simulator goes on with
/// the next ones (at most two frames wait between them), in frame order, so the files and the
/// record are the same as writing each frame before simulating the next. The writer never uses
/// the rayon pool: a pool worker simulating a sequence blocks when its writer falls behind.
fn write_sequence(
    dataset: &Dataset,
    seq: SequenceScene,
    gpu: Option<&GpuContext>,
    progress: &Progress,
    totals: &Mutex<StageTotals>,
) -> Result<()> {
    let SequenceScene {
        sequence,
        family,
        split,
        first_frame,
        scene,
    } = seq;
    let about = SequenceAbout {
        sequence,
        family,
        split: split.name(),
        first_frame,
        output: scene.output.clone(),
        mm_per_px: scene.sensor.mm_per_px,
        tolerance: scene.tolerance,
    };
    let mut sim = Simulator::on_device(scene, gpu)?;
    let background = format!("backgrounds/{sequence:06}.png");
    let background_sha = dataset.write_png(&background, &sim.background())?;
    let (frames, received) = std::sync::mpsc::sync_channel::<Frame>(2);
    let (mut part, local) = std::thread::scope(|scope| {
        let writer = scope.spawn(|| write_frames(dataset, &about, &background, received, progress));
        let mut failure = None;
        while let Some(frame) = sim.next_frame() {
            match frame {
                // a closed channel means the writer failed: its error is reported below
                Ok(frame) => {
                    if frames.send(frame).is_err() {
                        break;
                    }
                }
                Err(e) => {
                    failure = Some(e);
                    break;
                }
            }
        }
        drop(frames);
        let written = writer
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        match failure {
            Some(e) => {
                Err(anyhow::Error::new(e)
                    .context(format!("sequence {sequence} ({})", about.family)))
            }
            None => written,
        }
    })?;
    part.files.insert(background, background_sha);
    dataset.write_part(&part)?;
    let mut t = totals.lock().expect("no poisoned lock");
    t.gap_s += local.gap_s;
    t.contact_s += local.contact_s;
    t.optics_s += local.optics_s;
    t.writing_s += local.writing_s;
    t.outside_validity.merge(&local.outside_validity);
    Ok(())
}

/// What the writer needs to know of a sequence besides its frames.
struct SequenceAbout {
    sequence: usize,
    family: String,
    split: &'static str,
    first_frame: usize,
    output: OutputSpec,
    mm_per_px: f64,
    tolerance: f64,
}

/// The writer's side of [`write_sequence`]: each frame's PNG, fields and label as it arrives.
/// Returns the sequence's record (without its background) and its stage times.
fn write_frames(
    dataset: &Dataset,
    seq: &SequenceAbout,
    background: &str,
    frames: std::sync::mpsc::Receiver<Frame>,
    progress: &Progress,
) -> Result<(SequencePart, StageTotals)> {
    let output = &seq.output;
    let mut part = SequencePart {
        sequence: seq.sequence,
        files: Default::default(),
        labels: Vec::new(),
    };
    let mut local = StageTotals::default();
    let mut previous: Option<Frame> = None;
    let mut forces: Vec<[f64; 3]> = Vec::new();
    for frame in frames {
        let t0 = Instant::now();
        let index = seq.first_frame + frame.target.index;
        let name = format!("{index:06}");
        if output.frames {
            let rel = format!("frames/{name}.png");
            part.files
                .insert(rel.clone(), dataset.write_png(&rel, &frame.image)?);
        }
        if !output.fields.is_empty() {
            let rel = format!("fields/{name}.exr");
            let bytes = exr_bytes(&frame.fields, output)?;
            part.files
                .insert(rel.clone(), dataset.write_file(&rel, &bytes)?);
        }
        forces.push(frame.fields.force_n);
        let k = frame.target.index;
        let before = forces[k.saturating_sub(5)];
        let force = frame.fields.force_n;
        let [fx, fy, fz] = force;
        let (dp, dr) = previous.as_ref().map_or(([0.0; 3], [0.0; 3]), |p| {
            (
                (frame.pose.position_mm - p.pose.position_mm).to_array(),
                (frame.pose.rotation_deg - p.pose.rotation_deg).to_array(),
            )
        });
        part.labels.push(Label {
            frame: index,
            sequence: seq.sequence,
            frame_in_sequence: k,
            family: seq.family.clone(),
            split: seq.split.into(),
            time_s: frame.target.time_s,
            force_n: force,
            delta_force_n: std::array::from_fn(|c| force[c] - before[c]),
            slip_state: frame.slip_state.name().into(),
            slip_cone: fx.hypot(fy) > output.slip_cone_ratio * fz,
            pose: PoseLabel {
                position_mm: frame.pose.position_mm.to_array(),
                rotation_deg: frame.pose.rotation_deg.to_array(),
            },
            pose_change_se2: [dp[0], dp[1], dr[2]],
            contact_area_mm2: frame.contact_area_mm2,
            solver: Some(frame.solver.name().into()),
            validity: Some(frame.validity.name().into()),
            validity_value_bound: match frame.validity {
                Validity::Ok => None,
                Validity::Outside { value, bound, .. } => Some([value, bound]),
            },
            mm_per_px: Some(seq.mm_per_px),
            markers_px: frame.markers_px.clone(),
            background: background.to_string(),
        });
        if !frame.validity.is_ok() {
            local
                .outside_validity
                .note(seq.sequence, &frame, seq.tolerance);
        }
        local.gap_s += frame.timings.gap_s;
        local.contact_s += frame.timings.contact_s;
        local.optics_s += frame.timings.optics_s;
        local.writing_s += t0.elapsed().as_secs_f64();
        previous = Some(frame);
        progress.inc(1);
    }
    Ok((part, local))
}

/// `sparsh verify DIR`: checks every checksum in the manifest of a complete dataset; on a
/// dataset still being generated (no manifest yet) or with `--shard`, checks the files of every
/// recorded sequence against its record, says which shards are done and names the missing ones.
/// Fails on a missing or corrupt file, and, with `complete`, when anything asked for is not done.
pub fn verify(dir: &Path, shard: Option<Shard>, complete: bool) -> Result<()> {
    let manifest = sparsh_data::read_manifest(dir)?;
    if manifest.is_some() && shard.is_none() {
        let (checked, problems) = sparsh_data::verify(dir)?;
        report_problems(dir, &problems, checked)?;
        println!("{}: all {checked} files match the manifest", dir.display());
        return Ok(());
    }
    let identity = sparsh_data::read_identity(dir)?;
    let sequences = identity.sequences;
    let layout = match shard {
        Some(shard) => Some(shard),
        None => sparsh_data::read_shard_layout(dir)?.map(|l| Shard {
            index: 0,
            count: l.count,
        }),
    };
    let wanted: Vec<usize> = (0..sequences)
        .filter(|&s| shard.is_none_or(|sh| sh.has(s)))
        .collect();
    let checks: Vec<Option<PartCheck>> = wanted
        .par_iter()
        .map(|&s| sparsh_data::check_part(dir, s, manifest.as_ref()))
        .collect();
    let done: Vec<usize> = wanted
        .iter()
        .zip(&checks)
        .filter(|(_, c)| c.is_some())
        .map(|(&s, _)| s)
        .collect();
    let (checked, problems) =
        checks
            .into_iter()
            .flatten()
            .fold((0, Vec::new()), |(n, mut all), (k, p)| {
                all.extend(p);
                (n + k, all)
            });
    let missing_what = match (shard, layout) {
        (Some(shard), _) => {
            let state = if done.len() == wanted.len() {
                "done"
            } else if done.is_empty() {
                "not run"
            } else {
                "partly done"
            };
            println!(
                "{}: shard {shard}: {state} ({} of {} sequences recorded)",
                dir.display(),
                done.len(),
                wanted.len()
            );
            (done.len() < wanted.len()).then(|| format!("shard {shard}"))
        }
        (None, Some(layout)) => {
            let n = layout.count;
            let recorded = |k: usize| done.iter().filter(|&&s| s % n == k).count();
            let of_shard = |k: usize| (0..sequences).filter(|&s| s % n == k).count();
            let (mut full, mut partly, mut none) = (Vec::new(), Vec::new(), Vec::new());
            for k in 0..n {
                match (recorded(k), of_shard(k)) {
                    (r, all) if r == all => full.push(k),
                    (0, _) => none.push(k),
                    (r, all) => partly.push(format!("{k} ({r} of {all} sequences)")),
                }
            }
            println!(
                "{}: {} of {n} shards done: {}",
                dir.display(),
                full.len(),
                list_or_none(&ranges(&full))
            );
            if !partly.is_empty() {
                println!(
                    "{}: shards partly done: {}",
                    dir.display(),
                    partly.join(", ")
                );
            }
            if !none.is_empty() {
                println!(
                    "{}: missing shards (of {n}): {}",
                    dir.display(),
                    ranges(&none)
                );
            }
            (!none.is_empty() || !partly.is_empty())
                .then(|| format!("{} of {n} shards", n - full.len()))
        }
        (None, None) => {
            let missing: Vec<usize> = (0..sequences).filter(|s| !done.contains(s)).collect();
            println!(
                "{}: {} of {sequences} sequences done",
                dir.display(),
                done.len()
            );
            if !missing.is_empty() {
                println!("{}: missing sequences: {}", dir.display(), ranges(&missing));
            }
            (!missing.is_empty()).then(|| format!("{} of {sequences} sequences", missing.len()))
        }
    };
    report_problems(dir, &problems, checked)?;
    if done.is_empty() {
        println!(
            "{}: no sequence recorded yet: no file to check",
            dir.display()
        );
    } else {
        println!(
            "{}: all {checked} files of the done sequences match their records{}",
            dir.display(),
            if manifest.is_some() {
                " and the manifest"
            } else {
                ""
            }
        );
    }
    if let Some(what) = missing_what
        && complete
    {
        bail!("{}: not complete: {what} missing", dir.display());
    }
    Ok(())
}

/// Prints each problem on stdout; fails when there is one.
fn report_problems(dir: &Path, problems: &[sparsh_data::Problem], checked: usize) -> Result<()> {
    for p in problems {
        println!("{}: {}", dir.join(&p.file).display(), p.what);
    }
    if !problems.is_empty() {
        bail!(
            "{}: {} of {checked} files missing or corrupt",
            dir.display(),
            problems.len()
        );
    }
    Ok(())
}

/// `0-2, 5, 7-9`: sorted indices as ranges.
fn ranges(indices: &[usize]) -> String {
    let mut parts: Vec<String> = Vec::new();
    let mut i = 0;
    while i < indices.len() {
        let mut j = i;
        while j + 1 < indices.len() && indices[j + 1] == indices[j] + 1 {
            j += 1;
        }
        parts.push(if j == i {
            indices[i].to_string()
        } else {
            format!("{}-{}", indices[i], indices[j])
        });
        i = j + 1;
    }
    parts.join(", ")
}

fn list_or_none(text: &str) -> &str {
    if text.is_empty() { "none" } else { text }
}

fn manifest(spec: &DatasetSpec, identity: Identity) -> Manifest {
    let mut notes = Vec::new();
    if spec.solvers().contains(&SolverKind::Geometric) {
        notes.push(
            "geometric rung: no tangential mechanics, so qx, qy, ux, uy and slip are zero".into(),
        );
    }
    Manifest {
        identity,
        fields: spec
            .output
            .fields
            .iter()
            .map(|f| f.channel().to_string())
            .collect(),
        field_precision: match spec.output.field_precision {
            Precision::F32 => "f32",
            Precision::F16 => "f16",
        }
        .into(),
        notes,
        files: Default::default(),
    }
}

/// The fields the output spec keeps, as an EXR file.
fn exr_bytes(fields: &Fields, output: &OutputSpec) -> Result<Vec<u8>> {
    let as_f32 = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
    let mask = |v: &[bool]| {
        v.iter()
            .map(|&b| f32::from(u8::from(b)))
            .collect::<Vec<f32>>()
    };
    let channels: Vec<(&str, Vec<f32>)> = output
        .fields
        .iter()
        .map(|&f| {
            let data = match f {
                FieldName::P => as_f32(&fields.pressure_kpa),
                FieldName::Qx => as_f32(&fields.traction_x_kpa),
                FieldName::Qy => as_f32(&fields.traction_y_kpa),
                FieldName::Ux => as_f32(&fields.ux_mm),
                FieldName::Uy => as_f32(&fields.uy_mm),
                FieldName::Uz => as_f32(&fields.uz_mm),
                FieldName::Contact => mask(&fields.contact),
                FieldName::Slip => mask(&fields.slip),
            };
            (f.channel(), data)
        })
        .collect();
    sparsh_data::write_exr_channels(
        fields.grid.nx,
        fields.grid.ny,
        &channels,
        output.field_precision,
    )
    .map_err(anyhow::Error::msg)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn indices_print_as_ranges() {
        assert_eq!(ranges(&[0, 1, 2, 5, 7, 8, 9]), "0-2, 5, 7-9");
        assert_eq!(ranges(&[3]), "3");
        assert_eq!(ranges(&[]), "");
    }
}
