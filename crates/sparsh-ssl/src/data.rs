//! Tactile datasets for pretraining: official preprocessing, the dataset layouts, augmentation
//! and a prefetching batch loader that streams frames from disk.
//!
//! Preprocessing is the official code's ([`preprocess`], from `sparsh-data`): background
//! subtraction, a clockwise turn to portrait, the official crop and a resize.
//!
//! Layouts read here:
//! - a directory written by `sparsh generate`: `labels.jsonl` (rows with `frame`, `sequence`,
//!   `frame_in_sequence`, `force_n` and optionally `background`, the sequence's no-contact image
//!   relative to the directory), `frames/NNNNNN.png`; without a `background` field,
//!   `background.png`, else the first frame of each sequence, is the background;
//! - the official Sparsh pickles (YCB-Slide / Touch-Slide / Touch-and-Go style): each `*.pkl`
//!   holds a list of JPEG (or PNG) byte strings — one sequence — either at the top level or as the
//!   first list value of a dictionary; the background is a `bg*.jpg`/`bg*.png` beside the pickle,
//!   else the sequence's first frame;
//! - a Taxim calibration pack (`dataPack.npz`, or a directory holding one): `f0` is the
//!   background, and each of `imgs` (separate presses of a ball, not a time series) is a sequence
//!   of one frame seen from rest: frame offsets before it read the no-contact frame, and it has
//!   no force label.
//!
//! Loading reads the labels and each sequence's background, not the frames: a generated
//! dataset's frames are read and preprocessed from their PNG files, a pickle's from its encoded
//! bytes (held in memory, as compressed as the file), when a batch needs them, on the rayon
//! workers. A [`Sampler`] keeps decoded frames up to a memory cap (`[data] cache_mb`), so a
//! dataset larger than memory trains with bounded memory, and one that fits is decoded once.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, sync_channel};
use std::sync::{Arc, Mutex};

use image::RgbImage;
use rayon::prelude::*;
pub use sparsh_data::{official_crop, preprocess};

use crate::Error;
use crate::rng::Rng;

/// One preprocessed frame: `[3, height, width]` in `[0, 1]`.
pub type Frame = Arc<Vec<f32>>;

/// Where one frame of a sequence comes from.
#[derive(Debug, Clone)]
pub enum FrameSource {
    /// Preprocessed, in memory.
    Decoded(Frame),
    /// An image file, preprocessed against `background` when read.
    File {
        /// The image.
        path: PathBuf,
        /// The sequence's no-contact image.
        background: Arc<RgbImage>,
    },
    /// Encoded image bytes (JPEG or PNG, one entry of an official pickle), preprocessed against
    /// `background` when read.
    Encoded {
        /// The encoded image.
        bytes: Arc<Vec<u8>>,
        /// The sequence's no-contact image.
        background: Arc<RgbImage>,
        /// The file the bytes came from and their index in it, for errors.
        origin: Arc<PathBuf>,
        /// Index of the frame in `origin`.
        index: usize,
    },
}

impl FrameSource {
    /// The preprocessed frame at `size` (`[height, width]`): decoded and preprocessed now unless
    /// it is in memory. Errors name the file.
    pub fn read(&self, size: [usize; 2]) -> Result<Frame, Error> {
        match self {
            FrameSource::Decoded(f) => Ok(f.clone()),
            FrameSource::File { path, background } => {
                preprocess(&read_image(path)?, background, size)
                    .map(Arc::new)
                    .map_err(|e| Error::file(path, e))
            }
            FrameSource::Encoded {
                bytes,
                background,
                origin,
                index,
            } => preprocess(&decode(bytes, origin)?, background, size)
                .map(Arc::new)
                .map_err(|e| Error::file(origin.as_path(), format!("frame {index}: {e}"))),
        }
    }

    /// The frame when it is held preprocessed in memory.
    pub fn decoded(&self) -> Option<&Frame> {
        match self {
            FrameSource::Decoded(f) => Some(f),
            _ => None,
        }
    }
}

/// One tactile sequence.
#[derive(Debug, Clone)]
pub struct Sequence {
    /// Frames in time order.
    pub frames: Vec<FrameSource>,
    /// Total force per frame `[fx, fy, fz]` in N, when labelled.
    pub forces: Option<Vec<[f32; 3]>>,
    /// The no-contact frame (the background preprocessed against itself), read by frame
    /// offsets that reach before the first frame; without it, samples stay inside the sequence.
    pub rest_frame: Option<Frame>,
}

impl Sequence {
    /// Frames held in memory, in time order.
    pub fn decoded(frames: Vec<Frame>) -> Vec<FrameSource> {
        frames.into_iter().map(FrameSource::Decoded).collect()
    }
}

/// Preprocessed sequences at one image size.
#[derive(Debug, Clone)]
pub struct Dataset {
    /// The sequences.
    pub sequences: Vec<Sequence>,
    /// `[height, width]` of every frame.
    pub size: [usize; 2],
}

/// Decodes a PNG or JPEG frame under the `image` crate's default limits: a header whose image
/// would take more than 512 MiB is refused before the pixels are allocated. The decoder's error
/// (the JPEG decoder's can span lines) is given on one line.
fn decode(bytes: &[u8], what: &Path) -> Result<RgbImage, Error> {
    image::load_from_memory(bytes)
        .map(|i| i.to_rgb8())
        .map_err(|e| {
            let reason: Vec<String> = e
                .to_string()
                .lines()
                .map(|l| l.trim().to_string())
                .collect();
            Error::file(what, format!("cannot decode image: {}", reason.join(" ")))
        })
}

/// Reads an image file as RGB; the error names the file.
pub fn read_image(path: &Path) -> Result<RgbImage, Error> {
    let bytes = std::fs::read(path).map_err(|e| Error::file(path, e))?;
    decode(&bytes, path)
}

#[derive(serde::Deserialize)]
struct LabelRow {
    frame: usize,
    sequence: usize,
    frame_in_sequence: usize,
    #[serde(default)]
    force_n: Option<[f32; 3]>,
    #[serde(default)]
    background: Option<String>,
}

/// One sequence of a dataset written by `sparsh generate`, as its files.
#[derive(Debug, Clone)]
pub struct GeneratedSequence {
    /// Dataset-wide frame numbers (`frames/NNNNNN.png`) in time order.
    pub frame_ids: Vec<usize>,
    /// The frame files, in time order.
    pub frames: Vec<PathBuf>,
    /// The no-contact image the frames are preprocessed against: the rows' `background`, else
    /// the dataset's `background.png`, else the sequence's first frame.
    pub background: PathBuf,
    /// Total force per frame `[fx, fy, fz]` in N, when every frame is labelled.
    pub forces: Option<Vec<[f32; 3]>>,
}

/// The sequences of a dataset written by `sparsh generate`, in sequence order, read from its
/// `labels.jsonl`.
pub fn generated_sequences(dir: &Path) -> Result<Vec<GeneratedSequence>, Error> {
    if !dir.is_dir() {
        return Err(Error::file(dir, "no such directory"));
    }
    let labels = dir.join("labels.jsonl");
    if !labels.is_file() {
        return Err(Error::file(
            dir,
            "not a dataset written by `sparsh generate` (no labels.jsonl)",
        ));
    }
    let text = std::fs::read_to_string(&labels).map_err(|e| Error::file(&labels, e))?;
    let mut by_seq: BTreeMap<usize, Vec<LabelRow>> = BTreeMap::new();
    for (i, line) in text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
    {
        let row: LabelRow = serde_json::from_str(line)
            .map_err(|e| Error::file(&labels, format!("line {}: {e}", i + 1)))?;
        by_seq.entry(row.sequence).or_default().push(row);
    }
    if by_seq.is_empty() {
        return Err(Error::file(&labels, "no frames"));
    }
    let shared_bg = dir.join("background.png");
    let frame_path = |i: usize| dir.join("frames").join(format!("{i:06}.png"));
    Ok(by_seq
        .into_values()
        .map(|mut rows| {
            rows.sort_by_key(|r| r.frame_in_sequence);
            let background = match &rows[0].background {
                Some(rel) => dir.join(rel),
                None if shared_bg.is_file() => shared_bg.clone(),
                None => frame_path(rows[0].frame),
            };
            GeneratedSequence {
                frame_ids: rows.iter().map(|r| r.frame).collect(),
                frames: rows.iter().map(|r| frame_path(r.frame)).collect(),
                background,
                forces: rows.iter().map(|r| r.force_n).collect(),
            }
        })
        .collect())
}

impl Dataset {
    /// Loads a Taxim pack (an `.npz` file, or a directory with `dataPack.npz`), else a
    /// directory: a generated dataset when it has `labels.jsonl`, else every `*.pkl` below it
    /// (one level of sub-directories).
    pub fn load(path: &Path, size: [usize; 2]) -> Result<Self, Error> {
        if path.is_file() {
            if path.extension().is_some_and(|e| e == "npz") {
                return Self::load_taxim_pack(path, size);
            }
            return Err(Error::file(
                path,
                "neither a dataset directory nor a Taxim pack (.npz)",
            ));
        }
        if !path.is_dir() {
            return Err(Error::file(path, "no such file or directory"));
        }
        if path.join("labels.jsonl").is_file() {
            return Self::load_generated(path, size);
        }
        if path.join(TAXIM_PACK).is_file() {
            return Self::load_taxim_pack(&path.join(TAXIM_PACK), size);
        }
        let mut pickles = Vec::new();
        for entry in std::fs::read_dir(path).map_err(|e| Error::file(path, e))? {
            let p = entry.map_err(|e| Error::file(path, e))?.path();
            if p.is_dir() {
                for sub in std::fs::read_dir(&p).map_err(|e| Error::file(&p, e))? {
                    let q = sub.map_err(|e| Error::file(&p, e))?.path();
                    if q.extension().is_some_and(|e| e == "pkl") {
                        pickles.push(q);
                    }
                }
            } else if p.extension().is_some_and(|e| e == "pkl") {
                pickles.push(p);
            }
        }
        if pickles.is_empty() {
            return Err(Error::file(
                path,
                format!("no frames: neither labels.jsonl, {TAXIM_PACK} nor *.pkl files"),
            ));
        }
        pickles.sort();
        let sequences = pickles
            .par_iter()
            .map(|p| load_pickle(p, size))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self { sequences, size })
    }

    /// Opens a dataset written by `sparsh generate`: reads its labels and backgrounds and checks
    /// that every frame file exists; frames are read when a batch needs them.
    pub fn load_generated(dir: &Path, size: [usize; 2]) -> Result<Self, Error> {
        let sequences = generated_sequences(dir)?
            .into_par_iter()
            .map(|seq| {
                let background = Arc::new(read_image(&seq.background)?);
                if let Some(missing) = seq.frames.iter().find(|p| !p.is_file()) {
                    return Err(Error::file(missing, "no such frame file"));
                }
                Ok(Sequence {
                    frames: seq
                        .frames
                        .into_iter()
                        .map(|path| FrameSource::File {
                            path,
                            background: background.clone(),
                        })
                        .collect(),
                    forces: seq.forces,
                    rest_frame: None,
                })
            })
            .collect::<Result<Vec<_>, Error>>()?;
        Ok(Self { sequences, size })
    }

    /// Loads a Taxim calibration pack: one unlabelled sequence per frame of `imgs`, each with
    /// `f0` as background and as rest frame.
    pub fn load_taxim_pack(path: &Path, size: [usize; 2]) -> Result<Self, Error> {
        let pack = sparsh_optics::pack::CalibrationPack::read(path)
            .map_err(|e| Error::file(path, format!("{}: {}", e.field, e.message)))?;
        if pack.frames.is_empty() {
            return Err(Error::file(path, "imgs: the pack holds no frames"));
        }
        let bg = &pack.background;
        let rest = Arc::new(preprocess(bg, bg, size).map_err(|e| Error::file(path, e))?);
        let sequences = pack
            .frames
            .par_iter()
            .enumerate()
            .map(|(k, img)| {
                let frame = preprocess(img, bg, size)
                    .map_err(|e| Error::file(path, format!("imgs: frame {k}: {e}")))?;
                Ok(Sequence {
                    frames: vec![FrameSource::Decoded(Arc::new(frame))],
                    forces: None,
                    rest_frame: Some(rest.clone()),
                })
            })
            .collect::<Result<Vec<_>, Error>>()?;
        Ok(Self { sequences, size })
    }

    /// Reads and preprocesses every frame now, on the rayon workers: for callers that index
    /// frames directly (small evaluation sets); training streams through a [`Sampler`].
    pub fn into_decoded(mut self) -> Result<Self, Error> {
        let size = self.size;
        for seq in &mut self.sequences {
            seq.frames = seq
                .frames
                .par_iter()
                .map(|f| f.read(size).map(FrameSource::Decoded))
                .collect::<Result<_, _>>()?;
        }
        Ok(self)
    }

    /// Number of frames in all sequences.
    pub fn num_frames(&self) -> usize {
        self.sequences.iter().map(|s| s.frames.len()).sum()
    }
}

/// Opens one official Sparsh pickle (a list of encoded frames) as one sequence: the encoded
/// frames stay in memory and are decoded when a batch needs them. The background (a `bg*` image
/// beside it, else the first frame) and the first frame are decoded now, so a file that is not
/// images fails here.
pub fn load_pickle(path: &Path, size: [usize; 2]) -> Result<Sequence, Error> {
    let frames = sparsh_data::sparsh_pkl::read_frames_pickle(path).map_err(|e| match e {
        sparsh_data::DataError::Format { message, .. } => Error::file(path, message),
        sparsh_data::DataError::Io { source, .. } => Error::file(path, source),
        other => Error::file(path, other),
    })?;
    if frames.is_empty() {
        return Err(Error::file(path, "the pickle holds no frames"));
    }
    let background = Arc::new(match background_beside(path) {
        Some(p) => read_image(&p)?,
        None => decode(&frames[0], path)?,
    });
    let origin = Arc::new(path.to_path_buf());
    let frames: Vec<FrameSource> = frames
        .into_iter()
        .enumerate()
        .map(|(index, bytes)| FrameSource::Encoded {
            bytes: Arc::new(bytes),
            background: background.clone(),
            origin: origin.clone(),
            index,
        })
        .collect();
    frames[0].read(size)?;
    Ok(Sequence {
        frames,
        forces: None,
        rest_frame: None,
    })
}

/// The file name of a Taxim calibration pack.
const TAXIM_PACK: &str = "dataPack.npz";

fn background_beside(path: &Path) -> Option<PathBuf> {
    let dir = path.parent()?;
    let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
            name.starts_with("bg") && (name.ends_with(".jpg") || name.ends_with(".png"))
        })
        .collect();
    found.sort();
    found.into_iter().next()
}

/// How the frames of one sample are stacked.
#[derive(Debug, Clone, PartialEq)]
pub enum Stacking {
    /// Frames at these offsets back in time concatenated on channels, one clip frame
    /// (`[0, 5]`: I_t ⊕ I_{t−5}, 6 channels).
    Channels(Vec<usize>),
    /// Frames at these offsets as clip frames of 3 channels (`[0, 2, 4, 6]` for V-JEPA).
    Frames(Vec<usize>),
}

impl Stacking {
    fn offsets(&self) -> &[usize] {
        match self {
            Stacking::Channels(o) | Stacking::Frames(o) => o,
        }
    }

    /// `[frames, channels]` of one sample.
    pub fn shape(&self) -> [usize; 2] {
        match self {
            Stacking::Channels(o) => [1, 3 * o.len()],
            Stacking::Frames(o) => [o.len(), 3],
        }
    }
}

/// Augmentation settings (official pretraining: flip 0.5, crop 0.2, rotation 0.2 at ±15°).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AugmentConfig {
    /// Probability of a horizontal flip.
    pub flip_p: f64,
    /// Probability of a random crop (resized back).
    pub crop_p: f64,
    /// Area fraction range of the crop.
    pub crop_scale: [f64; 2],
    /// Probability of a rotation.
    pub rotate_p: f64,
    /// Largest rotation in degrees.
    pub rotate_deg: f64,
}

impl Default for AugmentConfig {
    fn default() -> Self {
        Self {
            flip_p: 0.5,
            crop_p: 0.2,
            crop_scale: [0.5, 1.0],
            rotate_p: 0.2,
            rotate_deg: 15.0,
        }
    }
}

impl AugmentConfig {
    /// No augmentation.
    pub fn none() -> Self {
        Self {
            flip_p: 0.0,
            crop_p: 0.0,
            crop_scale: [1.0, 1.0],
            rotate_p: 0.0,
            rotate_deg: 0.0,
        }
    }
}

/// One sample's geometric transform: output pixel → source pixel.
#[derive(Debug, Clone, Copy)]
struct Warp {
    flip: bool,
    scale: f64,
    shift: [f64; 2],
    angle: f64,
}

impl Warp {
    fn sample(rng: &mut Rng, cfg: &AugmentConfig) -> Self {
        let flip = rng.chance(cfg.flip_p);
        let (scale, shift) = if rng.chance(cfg.crop_p) {
            let s = rng.range_f64(cfg.crop_scale[0], cfg.crop_scale[1]).sqrt();
            let room = 1.0 - s;
            (
                s,
                [
                    rng.range_f64(-room, room) * 0.5,
                    rng.range_f64(-room, room) * 0.5,
                ],
            )
        } else {
            (1.0, [0.0, 0.0])
        };
        let angle = if rng.chance(cfg.rotate_p) {
            rng.range_f64(-cfg.rotate_deg, cfg.rotate_deg).to_radians()
        } else {
            0.0
        };
        Self {
            flip,
            scale,
            shift,
            angle,
        }
    }

    fn is_identity(&self) -> bool {
        !self.flip && self.scale == 1.0 && self.angle == 0.0
    }

    /// Applies the warp to a `[3, h, w]` frame (bilinear, outside filled with 0.5, the
    /// no-change grey of a difference image).
    fn apply(&self, src: &[f32], h: usize, w: usize, out: &mut [f32]) {
        if self.is_identity() {
            out.copy_from_slice(src);
            return;
        }
        let (cy, cx) = ((h as f64 - 1.0) / 2.0, (w as f64 - 1.0) / 2.0);
        let (sin, cos) = self.angle.sin_cos();
        for y in 0..h {
            for x in 0..w {
                let mut u = (x as f64 - cx) * self.scale;
                let v = (y as f64 - cy) * self.scale;
                if self.flip {
                    u = -u;
                }
                let sx = cos * u - sin * v + cx + self.shift[0] * w as f64;
                let sy = sin * u + cos * v + cy + self.shift[1] * h as f64;
                let (x0, y0) = (sx.floor(), sy.floor());
                let (fx, fy) = ((sx - x0) as f32, (sy - y0) as f32);
                for c in 0..3 {
                    let at = |yy: f64, xx: f64| {
                        if yy < 0.0 || xx < 0.0 || yy >= h as f64 || xx >= w as f64 {
                            0.5
                        } else {
                            src[(c * h + yy as usize) * w + xx as usize]
                        }
                    };
                    let top = at(y0, x0) * (1.0 - fx) + at(y0, x0 + 1.0) * fx;
                    let bot = at(y0 + 1.0, x0) * (1.0 - fx) + at(y0 + 1.0, x0 + 1.0) * fx;
                    out[(c * h + y) * w + x] = top * (1.0 - fy) + bot * fy;
                }
            }
        }
    }
}

/// A batch on the host, ready to become a tensor.
#[derive(Debug, Clone)]
pub struct HostBatch {
    /// The training step it belongs to.
    pub step: usize,
    /// Values of `[batch, frames, channels, height, width]`.
    pub values: Vec<f32>,
    /// The shape.
    pub shape: [usize; 5],
    /// Force labels per sample, when every sample has one.
    pub forces: Option<Vec<[f32; 3]>>,
}

/// Decoded frames kept by a [`Sampler`], up to a byte cap: frames are kept as they are first
/// read until the cap is reached, then read from their source each time (under uniform random
/// sampling no eviction policy keeps more of the reads in memory, and this one never moves a
/// frame). What is cached changes the time, not the values.
#[derive(Debug)]
struct FrameCache {
    cap_bytes: usize,
    held: Mutex<Held>,
}

/// Bytes held, and the frames by `(sequence, frame)`.
type Held = (usize, std::collections::HashMap<(usize, usize), Frame>);

impl FrameCache {
    fn new(cap_bytes: usize) -> Self {
        Self {
            cap_bytes,
            held: Mutex::new((0, Default::default())),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Held> {
        // a panic while holding the lock leaves the map consistent (only inserts happen)
        self.held.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Samples `(sequence, frame)` of a dataset under a stacking, and batch assembly.
#[derive(Debug, Clone)]
pub struct Sampler {
    data: Arc<Dataset>,
    stacking: Stacking,
    cache: Arc<FrameCache>,
    /// The valid `(sequence, frame)` pairs: every offset inside the sequence, or reaching back
    /// to its rest frame.
    pub samples: Vec<(usize, usize)>,
}

/// The default cap of a [`Sampler`]'s decoded frames (`[data] cache_mb`).
pub const DEFAULT_CACHE_MB: usize = 4096;

impl Sampler {
    /// All samples of `data` whose offsets stay within their sequence; every frame of a
    /// sequence with a rest frame. Keeps up to [`DEFAULT_CACHE_MB`] of decoded frames.
    pub fn new(data: Arc<Dataset>, stacking: Stacking) -> Result<Self, Error> {
        let reach = stacking.offsets().iter().copied().max().unwrap_or(0);
        let samples: Vec<(usize, usize)> = data
            .sequences
            .iter()
            .enumerate()
            .flat_map(|(s, seq)| {
                let first = if seq.rest_frame.is_some() { 0 } else { reach };
                (first..seq.frames.len()).map(move |t| (s, t))
            })
            .collect();
        if samples.is_empty() {
            return Err(Error::Data(format!(
                "no sequence is longer than {reach} frames, the reach of the frame stacking"
            )));
        }
        Ok(Self {
            data,
            stacking,
            cache: Arc::new(FrameCache::new(DEFAULT_CACHE_MB << 20)),
            samples,
        })
    }

    /// The same sampler keeping at most `mb` MiB of decoded frames (frames held in memory by the
    /// dataset itself are not counted).
    pub fn with_cache_mb(mut self, mb: usize) -> Self {
        self.cache = Arc::new(FrameCache::new(mb.saturating_mul(1 << 20)));
        self
    }

    /// Bytes of decoded frames the sampler holds now.
    pub fn cached_bytes(&self) -> usize {
        self.cache.lock().0
    }

    /// The dataset.
    pub fn data(&self) -> &Dataset {
        &self.data
    }

    /// The preprocessed frame `back` steps before frame `t` of sequence `s`: the rest frame
    /// before the sequence start.
    fn frame_back(&self, s: usize, t: usize, back: usize) -> Result<Frame, Error> {
        let seq = &self.data.sequences[s];
        let Some(i) = t.checked_sub(back) else {
            return Ok(seq
                .rest_frame
                .clone()
                .expect("Sampler::new admits only samples whose offsets resolve"));
        };
        let source = &seq.frames[i];
        if let Some(f) = source.decoded() {
            return Ok(f.clone());
        }
        if let Some(f) = self.cache.lock().1.get(&(s, i)) {
            return Ok(f.clone());
        }
        let frame = source.read(self.data.size)?;
        let bytes = frame.len() * size_of::<f32>();
        let mut held = self.cache.lock();
        if held.0 + bytes <= self.cache.cap_bytes && !held.1.contains_key(&(s, i)) {
            held.0 += bytes;
            held.1.insert((s, i), frame.clone());
        }
        Ok(frame)
    }

    /// Assembles the samples `picks` (indices into [`Self::samples`]) with per-sample warps
    /// drawn from `(seed, step)`, reading frames on the rayon workers. Errors name a frame file
    /// that cannot be read.
    pub fn batch(
        &self,
        picks: &[usize],
        aug: &AugmentConfig,
        seed: u64,
        step: usize,
    ) -> Result<HostBatch, Error> {
        let [h, w] = self.data.size;
        let [frames, chans] = self.stacking.shape();
        let per = frames * chans * h * w;
        let mut values = vec![0.0; picks.len() * per];
        values
            .par_chunks_mut(per)
            .zip(picks.par_iter().enumerate())
            .try_for_each(|(out, (i, &pick))| {
                let (s, t) = self.samples[pick];
                let warp =
                    Warp::sample(&mut Rng::for_step(seed, step as u64, 1000 + i as u64), aug);
                for (k, &off) in self.stacking.offsets().iter().enumerate() {
                    let frame = self.frame_back(s, t, off)?;
                    warp.apply(&frame, h, w, &mut out[k * 3 * h * w..(k + 1) * 3 * h * w]);
                }
                Ok::<(), Error>(())
            })?;
        let forces = picks
            .iter()
            .map(|&p| {
                let (s, t) = self.samples[p];
                self.data.sequences[s].forces.as_ref().map(|f| f[t])
            })
            .collect();
        Ok(HostBatch {
            step,
            values,
            shape: [picks.len(), frames, chans, h, w],
            forces,
        })
    }

    /// The sample indices of training step `step`: consecutive slices of a per-epoch permutation
    /// drawn from `(seed, epoch)`.
    pub fn picks(&self, seed: u64, step: usize, batch: usize) -> Vec<usize> {
        let n = self.samples.len();
        let mut out = Vec::with_capacity(batch);
        let mut cached: Option<(usize, Vec<usize>)> = None;
        for pos in step * batch..(step + 1) * batch {
            let epoch = pos / n;
            if cached.as_ref().is_none_or(|(e, _)| *e != epoch) {
                cached = Some((epoch, Rng::for_step(seed, epoch as u64, 7).permutation(n)));
            }
            out.push(cached.as_ref().expect("set above").1[pos % n]);
        }
        out
    }

    /// Starts a thread that assembles the batches of steps `start..end` ahead of the trainer
    /// (up to `prefetch` waiting); reading and augmentation run on the rayon pool. The thread
    /// stops after the first error, which it passes on.
    pub fn prefetch(
        &self,
        aug: AugmentConfig,
        seed: u64,
        batch: usize,
        start: usize,
        end: usize,
        prefetch: usize,
    ) -> Receiver<Result<HostBatch, Error>> {
        let (tx, rx) = sync_channel(prefetch.max(1));
        let me = self.clone();
        std::thread::spawn(move || {
            for step in start..end {
                let picks = me.picks(seed, step, batch);
                let batch = me.batch(&picks, &aug, seed, step);
                let failed = batch.is_err();
                if tx.send(batch).is_err() || failed {
                    break;
                }
            }
        });
        rx
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn toy(seqs: usize, len: usize) -> Arc<Dataset> {
        let size = [8, 6];
        Arc::new(Dataset {
            size,
            sequences: (0..seqs)
                .map(|s| Sequence {
                    frames: Sequence::decoded(
                        (0..len)
                            .map(|t| Arc::new(vec![(s * 100 + t) as f32; 3 * 48]))
                            .collect(),
                    ),
                    forces: Some((0..len).map(|t| [t as f32, 0.0, 1.0]).collect()),
                    rest_frame: None,
                })
                .collect(),
        })
    }

    #[test]
    fn pairs_stay_in_sequence_and_epochs_cover_all_samples() {
        let sampler = Sampler::new(toy(3, 8), Stacking::Channels(vec![0, 5])).unwrap();
        assert_eq!(sampler.samples.len(), 3 * 3);
        let b = sampler
            .batch(&[0, 4], &AugmentConfig::none(), 1, 0)
            .unwrap();
        assert_eq!(b.shape, [2, 1, 6, 8, 6]);
        // sample 0 = (seq 0, t 5): channels 0..3 from frame 5, 3..6 from frame 0
        assert_eq!(b.values[0], 5.0);
        assert_eq!(b.values[3 * 48], 0.0);
        // sample 4 = (seq 1, t 6)
        assert_eq!(b.values[6 * 48], 106.0);
        assert_eq!(b.values[6 * 48 + 3 * 48], 101.0);
        let mut seen: Vec<usize> = (0..3).flat_map(|s| sampler.picks(9, s, 3)).collect();
        seen.sort_unstable();
        assert_eq!(seen, (0..9).collect::<Vec<_>>());
        assert!(Sampler::new(toy(2, 5), Stacking::Channels(vec![0, 5])).is_err());
    }

    #[test]
    fn offsets_before_the_start_read_the_rest_frame_where_there_is_one() {
        let mut data = Arc::unwrap_or_clone(toy(2, 7));
        data.sequences[0].frames.truncate(3);
        data.sequences[0].rest_frame = Some(Arc::new(vec![-1.0; 3 * 48]));
        let sampler = Sampler::new(Arc::new(data), Stacking::Frames(vec![0, 2, 4])).unwrap();
        // every frame of the sequence with a rest frame; only t ≥ 4 of the one without
        assert_eq!(
            sampler.samples,
            vec![(0, 0), (0, 1), (0, 2), (1, 4), (1, 5), (1, 6)]
        );
        let b = sampler
            .batch(&[2, 3], &AugmentConfig::none(), 0, 0)
            .unwrap();
        let clip = 3 * 3 * 48;
        let first = |k: usize, f: usize| b.values[k * clip + f * 3 * 48];
        // (seq 0, t 2): frames 2 and 0, then the rest frame
        assert_eq!([first(0, 0), first(0, 1), first(0, 2)], [2.0, 0.0, -1.0]);
        // (seq 1, t 4): frames 4, 2, 0
        assert_eq!(
            [first(1, 0), first(1, 1), first(1, 2)],
            [104.0, 102.0, 100.0]
        );
    }

    #[test]
    fn augmentation_is_deterministic_and_flip_mirrors() {
        let mut v = vec![0.0f32; 3 * 48];
        for y in 0..8 {
            for x in 0..6 {
                for c in 0..3 {
                    v[(c * 8 + y) * 6 + x] = x as f32;
                }
            }
        }
        let flip = Warp {
            flip: true,
            scale: 1.0,
            shift: [0.0, 0.0],
            angle: 0.0,
        };
        let mut out = vec![0.0; 3 * 48];
        flip.apply(&v, 8, 6, &mut out);
        for (x, v) in out.iter().take(6).enumerate() {
            assert!((v - (5 - x) as f32).abs() < 1e-5);
        }
        let data = Arc::new(Dataset {
            size: [8, 6],
            sequences: vec![Sequence {
                frames: Sequence::decoded((0..6).map(|_| Arc::new(v.clone())).collect()),
                forces: None,
                rest_frame: None,
            }],
        });
        let s = Sampler::new(data, Stacking::Frames(vec![0, 2, 4])).unwrap();
        let a = s
            .batch(&[0, 1, 0], &AugmentConfig::default(), 5, 3)
            .unwrap();
        let b = s
            .batch(&[0, 1, 0], &AugmentConfig::default(), 5, 3)
            .unwrap();
        assert_eq!(a.values, b.values);
        assert_eq!(a.shape, [3, 3, 3, 8, 6]);
    }
}
