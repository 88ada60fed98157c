//! Datasets from scene files: the simulator (`sparsh-sim`) joined to the dataset writer
//! (`sparsh-data`). [`generate`] makes a scene's sequences (every family, or one shard), resumes
//! an interrupted run and renders damaged sequences again; [`verify`] checks a dataset, whole or
//! shard by shard; [`Labeller`] makes the label rows of a sequence's frames. Nothing here prints:
//! what a run has to say goes to its [`Observer`].

use std::path::Path;
use std::str::FromStr;
use std::sync::Mutex;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use rayon::prelude::*;
use sparsh_contact::Fields;
use sparsh_data::{Dataset, Identity, Label, Manifest, OpenMode, PoseLabel, SequencePart};
use sparsh_optics::GpuContext;
use sparsh_scene::{
    DatasetSpec, FieldName, OutputSpec, Pose, Precision, Scene, SequenceScene, SolverKind, Validity,
};
use sparsh_sim::{Frame, Simulator};

/// What a run tells its caller while it works; each method does nothing unless overridden.
pub trait Observer: Sync {
    /// The run will simulate `frames` frames.
    fn start(&self, _frames: usize) {}
    /// One more frame is written.
    fn frame_done(&self) {}
    /// A line for the user: a choice made for them, a damaged sequence rendered again.
    fn note(&self, _line: &str) {}
}

/// An observer that hears nothing.
#[derive(Debug, Clone, Copy, Default)]
pub struct Silent;

impl Observer for Silent {}

/// What `solver = "auto"` chose for `scene` and why, and a warning when no studied rung is
/// predicted to meet the tolerance (the most accurate one is used then); empty for a named rung.
pub fn auto_notes(scene_path: &Path, scene: &Scene) -> Vec<String> {
    let Some(choice) = &scene.auto else {
        return Vec::new();
    };
    let mut lines = vec![format!(
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
    )];
    if !choice.meets_tolerance() {
        lines.push(format!(
            "{}: warning: no studied rung and grid is predicted to meet tolerance = {}; \
             using the most accurate one",
            scene_path.display(),
            choice.tolerance
        ));
    }
    lines
}

/// A shard (`--shard K/N`): the sequences s with s mod N = K (K from 0).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    index: usize,
    count: usize,
}

impl Shard {
    /// Shard `index` of `count` (an error unless `index < count`).
    pub fn new(index: usize, count: usize) -> Result<Shard, String> {
        if count == 0 || index >= count {
            return Err(format!(
                "`{index}/{count}`: K must be in 0..N and N at least 1"
            ));
        }
        Ok(Shard { index, count })
    }

    /// The number of shards.
    pub fn count(self) -> usize {
        self.count
    }

    /// Whether sequence `s` belongs to this shard.
    pub fn has(self, s: usize) -> bool {
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
        Shard::new(index, count).map_err(|_| format!("`{s}`: K must be in 0..N and N at least 1"))
    }
}

/// What `generate` is asked to do.
#[derive(Debug, Clone, Copy, Default)]
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
    /// Whether every sequence of the dataset is now written (and the manifest with them).
    pub complete: bool,
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

/// Simulates the sequences of `scene_path` (this shard's, not yet recorded) into `out`, forming
/// images on `gpu` when given; `observer` hears of the frames as they are written.
pub fn generate(
    scene_path: &Path,
    out: &Path,
    options: GenerateOptions,
    gpu: Option<&GpuContext>,
    observer: &dyn Observer,
) -> Result<GenerateReport> {
    if options.force && options.resume {
        bail!("--force and --resume contradict each other: pick one");
    }
    let spec = DatasetSpec::load(scene_path)?;
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
        todo.extend(damaged_sequences(&dataset, &mine, out, observer)?);
        todo.sort_unstable();
    }
    let mut sequences: Vec<SequenceScene> = todo
        .iter()
        .map(|&s| spec.sequence(s))
        .collect::<Result<_, _>>()?;
    if options.solver.is_none()
        && let Some(seq) = sequences.first()
    {
        auto_notes(scene_path, &seq.scene)
            .iter()
            .for_each(|line| observer.note(line));
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
    observer.start(frames);
    let totals = Mutex::new(StageTotals::default());
    let start = Instant::now();
    sequences
        .into_par_iter()
        .try_for_each(|seq| write_sequence(&dataset, seq, gpu, observer, &totals))?;
    let wall_s = start.elapsed().as_secs_f64();
    let stages = *totals.lock().expect("no poisoned lock");
    let complete = dataset
        .finish_if_complete(identity.sequences, manifest(&spec, identity))
        .with_context(|| format!("cannot finish the dataset in {}", out.display()))?;
    Ok(GenerateReport {
        frames,
        wall_s,
        stages,
        complete,
    })
}

/// A recorded sequence's check: files checked and the problems found.
type PartCheck = (usize, Vec<sparsh_data::Problem>);

/// The recorded sequences among `sequences` whose files (or record) `verify` would flag, each
/// named to the observer with its first problem: a resumed run renders them again.
fn damaged_sequences(
    dataset: &Dataset,
    sequences: &[usize],
    out: &Path,
    observer: &dyn Observer,
) -> Result<Vec<usize>> {
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
        observer.note(&format!(
            "{}: {}{more}; rendering sequence {s} again",
            out.join(&first.file).display(),
            first.what
        ));
        damaged.push(s);
    }
    Ok(damaged)
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
    observer: &dyn Observer,
    totals: &Mutex<StageTotals>,
) -> Result<()> {
    let sequence = seq.sequence;
    let family = seq.family.clone();
    let background = format!("backgrounds/{sequence:06}.png");
    let about = SequenceAbout {
        sequence,
        output: seq.scene.output.clone(),
        tolerance: seq.scene.tolerance,
        labeller: Labeller::new(&seq, &background),
    };
    let mut sim = Simulator::on_device(seq.scene, gpu)?;
    let background_sha = dataset.write_png(&background, &sim.background())?;
    let (frames, received) = std::sync::mpsc::sync_channel::<Frame>(2);
    let (mut part, local) = std::thread::scope(|scope| {
        let writer = scope.spawn(|| write_frames(dataset, about, received, observer));
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
                Err(anyhow::Error::new(e).context(format!("sequence {sequence} ({family})")))
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
    output: OutputSpec,
    tolerance: f64,
    labeller: Labeller,
}

/// The label rows of one sequence's frames, made in frame order: the force change over the last
/// 5 frames and the pose change since the previous frame need the frames before.
#[derive(Debug, Clone)]
pub struct Labeller {
    sequence: usize,
    family: String,
    split: &'static str,
    indenter: String,
    first_frame: usize,
    slip_cone_ratio: f64,
    mm_per_px: f64,
    background: String,
    forces: Vec<[f64; 3]>,
    previous_pose: Option<Pose>,
}

impl Labeller {
    /// The labeller of sequence `seq`, whose no-contact image is `background` (a path relative
    /// to the dataset directory).
    pub fn new(seq: &SequenceScene, background: &str) -> Self {
        Labeller {
            sequence: seq.sequence,
            family: seq.family.clone(),
            split: seq.split.name(),
            indenter: seq.scene.indenter_spec.name(),
            first_frame: seq.first_frame,
            slip_cone_ratio: seq.scene.output.slip_cone_ratio,
            mm_per_px: seq.scene.sensor.mm_per_px,
            background: background.to_string(),
            forces: Vec::new(),
            previous_pose: None,
        }
    }

    /// The label row of the sequence's next frame.
    pub fn label(&mut self, frame: &Frame) -> Label {
        self.forces.push(frame.fields.force_n);
        let k = frame.target.index;
        let before = self.forces[k.saturating_sub(5)];
        let force = frame.fields.force_n;
        let [fx, fy, fz] = force;
        let (dp, dr) = self.previous_pose.map_or(([0.0; 3], [0.0; 3]), |p| {
            (
                (frame.pose.position_mm - p.position_mm).to_array(),
                (frame.pose.rotation_deg - p.rotation_deg).to_array(),
            )
        });
        self.previous_pose = Some(frame.pose);
        Label {
            frame: self.first_frame + k,
            sequence: self.sequence,
            frame_in_sequence: k,
            family: self.family.clone(),
            split: self.split.into(),
            indenter: Some(self.indenter.clone()),
            time_s: frame.target.time_s,
            force_n: force,
            delta_force_n: std::array::from_fn(|c| force[c] - before[c]),
            slip_state: frame.slip_state.name().into(),
            slip_cone: fx.hypot(fy) > self.slip_cone_ratio * fz,
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
            mm_per_px: Some(self.mm_per_px),
            markers_px: frame.markers_px.clone(),
            background: self.background.clone(),
        }
    }
}

/// The writer's side of [`write_sequence`]: each frame's PNG, fields and label as it arrives.
/// Returns the sequence's record (without its background) and its stage times.
fn write_frames(
    dataset: &Dataset,
    mut seq: SequenceAbout,
    frames: std::sync::mpsc::Receiver<Frame>,
    observer: &dyn Observer,
) -> Result<(SequencePart, StageTotals)> {
    let mut part = SequencePart {
        sequence: seq.sequence,
        files: Default::default(),
        labels: Vec::new(),
    };
    let mut local = StageTotals::default();
    for frame in frames {
        let t0 = Instant::now();
        let label = seq.labeller.label(&frame);
        let name = format!("{:06}", label.frame);
        if seq.output.frames {
            let rel = format!("frames/{name}.png");
            part.files
                .insert(rel.clone(), dataset.write_png(&rel, &frame.image)?);
        }
        if !seq.output.fields.is_empty() {
            let rel = format!("fields/{name}.exr");
            let bytes = fields_exr(&frame.fields, &seq.output)?;
            part.files
                .insert(rel.clone(), dataset.write_file(&rel, &bytes)?);
        }
        part.labels.push(label);
        if !frame.validity.is_ok() {
            local
                .outside_validity
                .note(seq.sequence, &frame, seq.tolerance);
        }
        local.gap_s += frame.timings.gap_s;
        local.contact_s += frame.timings.contact_s;
        local.optics_s += frame.timings.optics_s;
        local.writing_s += t0.elapsed().as_secs_f64();
        observer.frame_done();
    }
    Ok((part, local))
}

/// Checks every checksum in the manifest of a complete dataset; on a
/// dataset still being generated (no manifest yet) or with `--shard`, checks the files of every
/// recorded sequence against its record, says which shards are done and names the missing ones.
/// Fails on a missing or corrupt file, and, with `complete`, when anything asked for is not done.
/// What it finds goes to `say`, a line at a time.
pub fn verify(
    dir: &Path,
    shard: Option<Shard>,
    complete: bool,
    say: &mut dyn FnMut(String),
) -> Result<()> {
    let manifest = sparsh_data::read_manifest(dir)?;
    if manifest.is_some() && shard.is_none() {
        let (checked, problems) = sparsh_data::verify(dir)?;
        report_problems(dir, &problems, checked, say)?;
        say(format!(
            "{}: all {checked} files match the manifest",
            dir.display()
        ));
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
            say(format!(
                "{}: shard {shard}: {state} ({} of {} sequences recorded)",
                dir.display(),
                done.len(),
                wanted.len()
            ));
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
            say(format!(
                "{}: {} of {n} shards done: {}",
                dir.display(),
                full.len(),
                list_or_none(&ranges(&full))
            ));
            if !partly.is_empty() {
                say(format!(
                    "{}: shards partly done: {}",
                    dir.display(),
                    partly.join(", ")
                ));
            }
            if !none.is_empty() {
                say(format!(
                    "{}: missing shards (of {n}): {}",
                    dir.display(),
                    ranges(&none)
                ));
            }
            (!none.is_empty() || !partly.is_empty())
                .then(|| format!("{} of {n} shards", n - full.len()))
        }
        (None, None) => {
            let missing: Vec<usize> = (0..sequences).filter(|s| !done.contains(s)).collect();
            say(format!(
                "{}: {} of {sequences} sequences done",
                dir.display(),
                done.len()
            ));
            if !missing.is_empty() {
                say(format!(
                    "{}: missing sequences: {}",
                    dir.display(),
                    ranges(&missing)
                ));
            }
            (!missing.is_empty()).then(|| format!("{} of {sequences} sequences", missing.len()))
        }
    };
    report_problems(dir, &problems, checked, say)?;
    if done.is_empty() {
        say(format!(
            "{}: no sequence recorded yet: no file to check",
            dir.display()
        ));
    } else {
        say(format!(
            "{}: all {checked} files of the done sequences match their records{}",
            dir.display(),
            if manifest.is_some() {
                " and the manifest"
            } else {
                ""
            }
        ));
    }
    if let Some(what) = missing_what
        && complete
    {
        bail!("{}: not complete: {what} missing", dir.display());
    }
    Ok(())
}

/// Prints each problem on stdout; fails when there is one.
fn report_problems(
    dir: &Path,
    problems: &[sparsh_data::Problem],
    checked: usize,
    say: &mut dyn FnMut(String),
) -> Result<()> {
    for p in problems {
        say(format!("{}: {}", dir.join(&p.file).display(), p.what));
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

/// The manifest of a dataset made from `spec`, before its files' checksums are added.
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
pub fn fields_exr(fields: &Fields, output: &OutputSpec) -> Result<Vec<u8>> {
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
