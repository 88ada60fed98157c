//! `sparsh._native`, the compiled half of the Python package `sparsh`: scene files, the
//! simulator frame by frame, dataset generation and verification, the contact validation and the
//! official input preprocessing, with images and fields as NumPy arrays. The Python half
//! (`python/sparsh/`) builds the dataset classes on it.
//!
//! Every call that computes releases the GIL and runs on a rayon pool of its own, made for the
//! call (or, for a [`Simulator`], for the object) and dropped with it: nothing starts rayon's
//! global pool, so a process that forks (PyTorch's DataLoader workers) after using the module
//! leaves no dead pool behind in its children.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use image::RgbImage;
use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::create_exception;
use pyo3::exceptions::PyException;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use sparsh_contact::Fields;
use sparsh_gen::{GenerateOptions, Labeller, Observer, Shard};
use sparsh_scene::{DatasetSpec, FieldName};

create_exception!(
    sparsh,
    SparshError,
    PyException,
    "A scene, dataset or solver problem; the message names the file and what is wrong."
);

/// The error as one line: its context chain joined by ": ".
fn error(e: impl Into<anyhow::Error>) -> PyErr {
    SparshError::new_err(format!("{:#}", e.into()))
}

/// A rayon pool of `threads` workers (all cores when `None`).
fn pool(threads: Option<usize>) -> PyResult<rayon::ThreadPool> {
    if threads == Some(0) {
        return Err(error(anyhow::anyhow!("threads must be at least 1")));
    }
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads.unwrap_or(0))
        .build()
        .map_err(error)
}

/// A JSON value as the Python object `json.loads` would give.
fn json_to_py(py: Python<'_>, value: &serde_json::Value) -> PyResult<Py<PyAny>> {
    use serde_json::Value;
    Ok(match value {
        Value::Null => py.None(),
        Value::Bool(b) => b.into_pyobject(py)?.to_owned().into_any().unbind(),
        Value::Number(n) => match n.as_i64() {
            Some(i) => i.into_pyobject(py)?.into_any().unbind(),
            None => n
                .as_f64()
                .unwrap_or(f64::NAN)
                .into_pyobject(py)?
                .into_any()
                .unbind(),
        },
        Value::String(s) => s.into_pyobject(py)?.into_any().unbind(),
        Value::Array(items) => {
            let list = PyList::empty(py);
            for item in items {
                list.append(json_to_py(py, item)?)?;
            }
            list.into_any().unbind()
        }
        Value::Object(map) => {
            let dict = PyDict::new(py);
            for (k, v) in map {
                dict.set_item(k, json_to_py(py, v)?)?;
            }
            dict.into_any().unbind()
        }
    })
}

/// A serializable value (a label row, a report) as Python dicts and lists.
fn to_py(py: Python<'_>, value: &impl serde::Serialize) -> PyResult<Py<PyAny>> {
    json_to_py(py, &serde_json::to_value(value).map_err(error)?)
}

/// An RGB image as a `(height, width, 3)` uint8 array.
fn image_array<'py>(py: Python<'py>, img: &RgbImage) -> PyResult<Bound<'py, PyAny>> {
    let (w, h) = (img.width() as usize, img.height() as usize);
    let flat = PyArray1::from_slice(py, img.as_raw());
    Ok(flat.reshape([h, w, 3])?.into_any())
}

/// A `(height, width, 3)` uint8 array as an RGB image; `what` names it in the error.
fn array_image(array: &PyReadonlyArray3<'_, u8>, what: &str) -> PyResult<RgbImage> {
    let shape = array.shape();
    if shape[2] != 3 {
        return Err(error(anyhow::anyhow!(
            "{what}: expected a (height, width, 3) uint8 RGB array, got shape {shape:?}"
        )));
    }
    let pixels: Vec<u8> = array.as_array().iter().copied().collect();
    RgbImage::from_raw(shape[1] as u32, shape[0] as u32, pixels).ok_or_else(|| {
        error(anyhow::anyhow!(
            "{what}: array of shape {shape:?} is not an image"
        ))
    })
}

/// The fields of a frame as `{channel: (ny, nx) array}` under the EXR channel names of
/// `fields/*.exr` (`p qx qy` kPa, `ux uy uz` mm as float64, `contact slip` as bool).
fn fields_dict<'py>(py: Python<'py>, fields: &Fields) -> PyResult<Bound<'py, PyDict>> {
    let shape = [fields.grid.ny, fields.grid.nx];
    let dict = PyDict::new(py);
    for name in FieldName::ALL {
        let array = match name {
            FieldName::P => PyArray1::from_slice(py, &fields.pressure_kpa).reshape(shape)?,
            FieldName::Qx => PyArray1::from_slice(py, &fields.traction_x_kpa).reshape(shape)?,
            FieldName::Qy => PyArray1::from_slice(py, &fields.traction_y_kpa).reshape(shape)?,
            FieldName::Ux => PyArray1::from_slice(py, &fields.ux_mm).reshape(shape)?,
            FieldName::Uy => PyArray1::from_slice(py, &fields.uy_mm).reshape(shape)?,
            FieldName::Uz => PyArray1::from_slice(py, &fields.uz_mm).reshape(shape)?,
            FieldName::Contact => {
                let mask = PyArray1::from_slice(py, &fields.contact).reshape(shape)?;
                dict.set_item(name.channel(), mask)?;
                continue;
            }
            FieldName::Slip => {
                let mask = PyArray1::from_slice(py, &fields.slip).reshape(shape)?;
                dict.set_item(name.channel(), mask)?;
                continue;
            }
        };
        dict.set_item(name.channel(), array)?;
    }
    Ok(dict)
}

/// A scene or dataset file: one scene, or `[[family]]` tables drawing many sequences.
#[pyclass(frozen, module = "sparsh")]
struct Scene {
    spec: DatasetSpec,
}

#[pymethods]
impl Scene {
    /// Reads and checks the file at `path`.
    #[new]
    fn new(path: PathBuf) -> PyResult<Self> {
        DatasetSpec::load(&path)
            .map(|spec| Scene { spec })
            .map_err(error)
    }

    /// The file.
    #[getter]
    fn path(&self) -> PathBuf {
        self.spec.path.clone()
    }

    /// The dataset seed.
    #[getter]
    fn seed(&self) -> u64 {
        self.spec.seed
    }

    /// How many sequences the file draws (1 for a single scene).
    #[getter]
    fn sequences(&self) -> usize {
        self.spec.sequence_count()
    }

    /// How many frames all sequences hold together.
    #[getter]
    fn frames(&self) -> usize {
        self.spec.frame_count()
    }

    /// What sequence `index` is: family, split, frame count, sensor size, solver rung.
    fn sequence<'py>(&self, py: Python<'py>, index: usize) -> PyResult<Bound<'py, PyDict>> {
        let seq = self.sequence_scene(index)?;
        let d = PyDict::new(py);
        d.set_item("sequence", seq.sequence)?;
        d.set_item("family", &seq.family)?;
        d.set_item("split", seq.split.name())?;
        d.set_item("frames", seq.scene.frames().len())?;
        d.set_item("width_px", seq.scene.sensor.width_px)?;
        d.set_item("height_px", seq.scene.sensor.height_px)?;
        d.set_item("mm_per_px", seq.scene.sensor.mm_per_px)?;
        d.set_item("solver", seq.scene.solver.name())?;
        Ok(d)
    }

    /// A simulator of sequence `sequence`, its frames computed on `threads` workers (all cores
    /// when `None`); the frames are the same bits whatever the thread count.
    #[pyo3(signature = (sequence = 0, *, threads = None))]
    fn simulate(
        &self,
        py: Python<'_>,
        sequence: usize,
        threads: Option<usize>,
    ) -> PyResult<Simulator> {
        let seq = self.sequence_scene(sequence)?;
        let pool = pool(threads)?;
        let background_file = format!("backgrounds/{sequence:06}.png");
        let labeller = Labeller::new(&seq, &background_file);
        let frames = seq.scene.frames().len();
        // the background is formed on the rayon pool too: on this object's
        let (sim, background) = py
            .detach(|| {
                pool.install(|| {
                    sparsh_sim::Simulator::new(seq.scene).map(|sim| {
                        let background = sim.background();
                        (sim, background)
                    })
                })
            })
            .map_err(error)?;
        Ok(Simulator {
            state: Mutex::new(Running {
                background,
                sim,
                labeller,
            }),
            pool,
            frames,
        })
    }

    fn __repr__(&self) -> String {
        format!(
            "Scene({:?}, sequences={}, frames={})",
            self.spec.path,
            self.spec.sequence_count(),
            self.spec.frame_count()
        )
    }
}

impl Scene {
    fn sequence_scene(&self, index: usize) -> PyResult<sparsh_scene::SequenceScene> {
        let count = self.spec.sequence_count();
        if index >= count {
            return Err(error(anyhow::anyhow!(
                "{}: sequence {index} asked for, the file draws {count}",
                self.spec.path.display()
            )));
        }
        self.spec.sequence(index).map_err(error)
    }
}

struct Running {
    sim: sparsh_sim::Simulator,
    labeller: Labeller,
    background: RgbImage,
}

/// One sequence's frames, in order: iterate it, or call `next()`. Each frame is a dict with the
/// sensor image, every ground-truth field and the label row `labels.jsonl` would hold.
#[pyclass(module = "sparsh")]
struct Simulator {
    state: Mutex<Running>,
    pool: rayon::ThreadPool,
    frames: usize,
}

#[pymethods]
impl Simulator {
    /// The sensor's image with nothing touching, `(height, width, 3)` uint8.
    #[getter]
    fn background<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let state = self.state.lock().expect("no poisoned lock");
        image_array(py, &state.background)
    }

    /// Frames in the sequence.
    fn __len__(&self) -> usize {
        self.frames
    }

    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    /// The next frame: `{"image", "fields", "label"}`; `StopIteration` after the last. A
    /// frame whose contact solve fails raises `SparshError`.
    fn __next__<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let mut state = self.state.lock().expect("no poisoned lock");
        let sim = &mut state.sim;
        let frame = py.detach(|| self.pool.install(|| sim.next_frame()));
        let Some(frame) = frame else {
            return Ok(None);
        };
        let frame = frame.map_err(error)?;
        let label = state.labeller.label(&frame);
        let d = PyDict::new(py);
        d.set_item("image", image_array(py, &frame.image)?)?;
        d.set_item("fields", fields_dict(py, &frame.fields)?)?;
        d.set_item("cell_mm", frame.fields.grid.cell_mm)?;
        d.set_item("label", to_py(py, &label)?)?;
        Ok(Some(d))
    }
}

/// Collects what a generate run has to say.
#[derive(Default)]
struct Notes(Mutex<Vec<String>>);

impl Observer for Notes {
    fn note(&self, line: &str) {
        self.0
            .lock()
            .expect("no poisoned lock")
            .push(line.to_string());
    }
}

/// Parses `"K/N"`.
fn shard(value: Option<&str>) -> PyResult<Option<Shard>> {
    value
        .map(|s| s.parse::<Shard>())
        .transpose()
        .map_err(|e| error(anyhow::anyhow!("shard: {e}")))
}

/// `sparsh generate`: simulates the sequences of `scene` (this shard's) into `out`. Returns the
/// run's report: frames simulated, wall seconds, whether the dataset is complete, the frames
/// outside their rung's validity and the notes (the `auto` choice, a validity warning).
#[pyfunction]
#[pyo3(signature = (scene, out, *, force = false, resume = false, shard = None, threads = None))]
fn generate<'py>(
    py: Python<'py>,
    scene: PathBuf,
    out: PathBuf,
    force: bool,
    resume: bool,
    shard: Option<&str>,
    threads: Option<usize>,
) -> PyResult<Bound<'py, PyDict>> {
    let options = GenerateOptions {
        force,
        resume,
        shard: self::shard(shard)?,
        ..GenerateOptions::default()
    };
    let pool = pool(threads)?;
    let notes = Notes::default();
    let report = py
        .detach(|| pool.install(|| sparsh_gen::generate(&scene, &out, options, None, &notes)))
        .map_err(error)?;
    let mut lines = notes.0.into_inner().expect("no poisoned lock");
    let outside = report.stages.outside_validity;
    lines.extend(outside.warning(report.frames));
    let d = PyDict::new(py);
    d.set_item("frames", report.frames)?;
    d.set_item("wall_s", report.wall_s)?;
    d.set_item("complete", report.complete)?;
    d.set_item("outside_validity", outside.frames)?;
    d.set_item("notes", lines)?;
    Ok(d)
}

/// `sparsh verify`: checks the dataset in `dir` against its manifest (or, while shards run,
/// each recorded sequence against its record). Returns what it found, a line at a time; raises
/// `SparshError` (naming each missing or corrupt file) on a missing or corrupt file, and with
/// `complete`, on anything not yet done.
#[pyfunction]
#[pyo3(signature = (dir, *, shard = None, complete = false))]
fn verify(
    py: Python<'_>,
    dir: PathBuf,
    shard: Option<&str>,
    complete: bool,
) -> PyResult<Vec<String>> {
    let shard = self::shard(shard)?;
    let mut lines = Vec::new();
    let pool = pool(None)?;
    let verified = py.detach(|| {
        pool.install(|| sparsh_gen::verify(&dir, shard, complete, &mut |line| lines.push(line)))
    });
    match verified {
        Ok(()) => Ok(lines),
        Err(e) if lines.is_empty() => Err(error(e)),
        // the verdict, then the problems found
        Err(e) => Err(SparshError::new_err(format!("{e:#}: {}", lines.join("; ")))),
    }
}

/// `sparsh validate`: the contact solvers against the analytic solutions of the cases in
/// `cases` (a directory like `scenes/validation/`). Returns `{"rows": [...], "convergence":
/// [...], "passed": bool}`; each row has `case`, `quantity`, `analytic`, `simulated`,
/// `rel_error`, `tolerance` (None: reported, not graded) and `ms`.
#[pyfunction]
#[pyo3(signature = (cases, *, threads = None))]
fn validate<'py>(
    py: Python<'py>,
    cases: PathBuf,
    threads: Option<usize>,
) -> PyResult<Bound<'py, PyAny>> {
    let pool = pool(threads)?;
    let report = py
        .detach(|| pool.install(|| sparsh_contact::validation::run_cases(&cases)))
        .map_err(error)?;
    let d = to_py(py, &report)?.into_bound(py);
    d.set_item("passed", report.passed())?;
    Ok(d)
}

/// Reads a PNG or JPEG file as a `(height, width, 3)` uint8 array.
#[pyfunction]
fn read_image<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyAny>> {
    let img = py.detach(|| decode(&path)).map_err(error)?;
    image_array(py, &img)
}

fn decode(path: &Path) -> anyhow::Result<RgbImage> {
    let bytes = std::fs::read(path).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    let img = image::load_from_memory(&bytes)
        .map_err(|e| anyhow::anyhow!("{}: cannot decode image: {e}", path.display()))?;
    Ok(img.to_rgb8())
}

/// Reads a fields file (`fields/NNNNNN.exr`) as `{channel: (ny, nx) float32 array}`.
#[pyfunction]
fn read_fields<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyDict>> {
    let exr = py
        .detach(|| sparsh_data::read_exr_channels(&path))
        .map_err(error)?;
    let d = PyDict::new(py);
    for (name, values) in &exr.channels {
        let array = PyArray1::from_slice(py, values).reshape([exr.height, exr.width])?;
        d.set_item(name, array)?;
    }
    Ok(d)
}

/// The official Sparsh preprocessing of `image` (`(h, w, 3)` uint8): minus `background`
/// (`clip((I − bg)/255 + 0.5, 0, 1)` in 8 bits; skipped when `None`), turned clockwise to
/// portrait, the official 4:3 crop, resized to `size` = `(height, width)`, scaled to `[0, 1]`.
/// Returns a `(3, height, width)` float32 array.
#[pyfunction]
#[pyo3(signature = (image, background = None, size = (320, 240)))]
fn preprocess<'py>(
    py: Python<'py>,
    image: PyReadonlyArray3<'py, u8>,
    background: Option<PyReadonlyArray3<'py, u8>>,
    size: (usize, usize),
) -> PyResult<Bound<'py, PyAny>> {
    if size.0 == 0 || size.1 == 0 {
        return Err(error(anyhow::anyhow!("size: {size:?} must be positive")));
    }
    let img = array_image(&image, "image")?;
    let bg = background
        .as_ref()
        .map(|b| array_image(b, "background"))
        .transpose()?;
    let out = py
        .detach(|| -> Result<Vec<f32>, String> {
            let diff = match &bg {
                Some(bg) => sparsh_data::subtract_background(&img, bg)?,
                None => img,
            };
            Ok(sparsh_data::official_resize(&diff, [size.0, size.1]))
        })
        .map_err(|e| error(anyhow::anyhow!("background: {e}")))?;
    Ok(PyArray1::from_vec(py, out)
        .reshape([3, size.0, size.1])?
        .into_any())
}

/// The compiled half of the `sparsh` package.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("SparshError", m.py().get_type::<SparshError>())?;
    m.add_class::<Scene>()?;
    m.add_class::<Simulator>()?;
    m.add_function(wrap_pyfunction!(generate, m)?)?;
    m.add_function(wrap_pyfunction!(verify, m)?)?;
    m.add_function(wrap_pyfunction!(validate, m)?)?;
    m.add_function(wrap_pyfunction!(read_image, m)?)?;
    m.add_function(wrap_pyfunction!(read_fields, m)?)?;
    m.add_function(wrap_pyfunction!(preprocess, m)?)?;
    Ok(())
}
