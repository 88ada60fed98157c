//! Taxim calibration packs (`dataPack.npz`, from the `taxim` 1.4.1 package on PyPI, MIT licence):
//! real frames of a ball pressed into the gel, with the hand-marked contact circle of each frame.
//!
//! Arrays read: `f0` (H×W×3 uint8, BGR: the no-contact frame), `imgs` (N×H×W×3 uint8, BGR),
//! `touch_center` (N×2, x = column, y = row, pixels; any integer or float dtype) and
//! `touch_radius` (N, contact radius in pixels; any integer or float dtype). Other arrays are
//! ignored. Images are converted to RGB on load.

use std::path::{Path, PathBuf};

use image::RgbImage;

/// A selection of a pack's frames: calibrations fit on the even ones and are scored on the odd
/// ones, so no scored frame was seen by the fit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FrameSet {
    /// Frames 0, 2, 4, …
    Even,
    /// Frames 1, 3, 5, …
    Odd,
    /// Every frame.
    All,
}

impl FrameSet {
    /// The selected indices among `count` frames.
    pub fn indices(self, count: usize) -> Vec<usize> {
        (0..count)
            .filter(|k| match self {
                FrameSet::Even => k % 2 == 0,
                FrameSet::Odd => k % 2 == 1,
                FrameSet::All => true,
            })
            .collect()
    }
}

impl std::str::FromStr for FrameSet {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "even" => Ok(FrameSet::Even),
            "odd" => Ok(FrameSet::Odd),
            "all" => Ok(FrameSet::All),
            _ => Err(format!("`{s}` is not a frame set (even, odd or all)")),
        }
    }
}

/// A pack that cannot be used: one line naming the file, the array and what is wrong.
#[derive(Debug, thiserror::Error)]
#[error("{}: {field}: {message}", path.display())]
pub struct PackError {
    /// The npz file.
    pub path: PathBuf,
    /// The array (or `file` for the archive itself).
    pub field: String,
    /// What is wrong.
    pub message: String,
}

/// A contact circle in a pack's pixels.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Circle {
    /// Centre (pixels: x = column, y = row).
    pub centre_px: [f64; 2],
    /// Radius (pixels).
    pub radius_px: f64,
}

/// A calibration pack in memory (images in RGB).
#[derive(Debug, Clone)]
pub struct CalibrationPack {
    /// The no-contact frame.
    pub background: RgbImage,
    /// The contact frames.
    pub frames: Vec<RgbImage>,
    /// Contact centre of each frame (pixels: x = column, y = row).
    pub centers_px: Vec<[f64; 2]>,
    /// Contact radius of each frame (pixels).
    pub radii_px: Vec<f64>,
}

impl CalibrationPack {
    /// Reads a Taxim pack; every array is checked for presence, dtype and shape, and every
    /// contact circle for a centre inside the image and a positive radius.
    pub fn read(path: &Path) -> Result<CalibrationPack, PackError> {
        let err = |field: &str, message: String| PackError {
            path: path.to_path_buf(),
            field: field.into(),
            message,
        };
        let mut npz = npyz::npz::NpzArchive::open(path)
            .map_err(|e| err("file", format!("cannot open as npz: {e}")))?;
        let (f0_shape, f0) = read_u8(&mut npz, "f0", &err)?;
        let [h, w, c] = f0_shape[..] else {
            return Err(err("f0", format!("expected H×W×3, shape is {f0_shape:?}")));
        };
        if c != 3 || h == 0 || w == 0 {
            return Err(err("f0", format!("expected H×W×3, shape is {f0_shape:?}")));
        }
        let (imgs_shape, imgs) = read_u8(&mut npz, "imgs", &err)?;
        if imgs_shape.len() != 4 || imgs_shape[1..] != f0_shape[..] {
            return Err(err(
                "imgs",
                format!("expected N×{h}×{w}×3 like f0, shape is {imgs_shape:?}"),
            ));
        }
        let n = imgs_shape[0];
        let (c_shape, centers) = read_f64(&mut npz, "touch_center", &err)?;
        if c_shape != [n, 2] {
            return Err(err(
                "touch_center",
                format!("expected {n}×2 (one x, y per frame), shape is {c_shape:?}"),
            ));
        }
        let (r_shape, radii) = read_f64(&mut npz, "touch_radius", &err)?;
        if r_shape != [n] {
            return Err(err(
                "touch_radius",
                format!("expected {n} values (one per frame), shape is {r_shape:?}"),
            ));
        }
        let centers_px: Vec<[f64; 2]> = centers.chunks_exact(2).map(|p| [p[0], p[1]]).collect();
        for (k, p) in centers_px.iter().enumerate() {
            let inside = (0.0..w as f64).contains(&p[0]) && (0.0..h as f64).contains(&p[1]);
            if !inside {
                return Err(err(
                    "touch_center",
                    format!(
                        "frame {k}: centre ({}, {}) is outside the {w}×{h} image",
                        p[0], p[1]
                    ),
                ));
            }
        }
        for (k, r) in radii.iter().enumerate() {
            if !(r.is_finite() && *r > 0.0) {
                return Err(err(
                    "touch_radius",
                    format!("frame {k}: radius must be > 0, got {r}"),
                ));
            }
        }
        let to_rgb = |bgr: &[u8]| {
            let rgb: Vec<u8> = bgr
                .chunks_exact(3)
                .flat_map(|p| [p[2], p[1], p[0]])
                .collect();
            RgbImage::from_raw(w as u32, h as u32, rgb).expect("size checked above")
        };
        let frame_len = h * w * 3;
        Ok(CalibrationPack {
            background: to_rgb(&f0),
            frames: imgs.chunks_exact(frame_len).map(to_rgb).collect(),
            centers_px,
            radii_px: radii,
        })
    }

    /// Image width and height (pixels).
    pub fn size_px(&self) -> (usize, usize) {
        (
            self.background.width() as usize,
            self.background.height() as usize,
        )
    }

    /// The contact circle the pack marks on frame `k`.
    pub fn marked_circle(&self, k: usize) -> Circle {
        Circle {
            centre_px: self.centers_px[k],
            radius_px: self.radii_px[k],
        }
    }
}

type ErrFn<'a> = dyn Fn(&str, String) -> PackError + 'a;

fn open_array<'a, R: std::io::Read + std::io::Seek>(
    npz: &'a mut npyz::npz::NpzArchive<R>,
    name: &str,
    err: &ErrFn,
) -> Result<npyz::NpyFile<impl std::io::Read + 'a>, PackError> {
    match npz.by_name(name) {
        Ok(Some(a)) => Ok(a),
        Ok(None) => Err(err(name, "array is missing".into())),
        Err(e) => Err(err(name, format!("cannot read: {e}"))),
    }
}

fn shape_of<R: std::io::Read>(a: &npyz::NpyFile<R>) -> Vec<usize> {
    a.shape().iter().map(|&s| s as usize).collect()
}

/// Largest array a calibration pack may hold (bytes): Taxim's largest, 48 frames of 640×480×3,
/// is 44 MB. A header claiming more is refused before anything is allocated.
pub const MAX_PACK_ARRAY_BYTES: u64 = 1 << 30;

/// Refuses an array whose header claims more than [`MAX_PACK_ARRAY_BYTES`].
fn check_size<R: std::io::Read>(
    a: &npyz::NpyFile<R>,
    name: &str,
    item_bytes: u64,
    err: &ErrFn,
) -> Result<(), PackError> {
    let bytes = a.len().saturating_mul(item_bytes);
    if bytes > MAX_PACK_ARRAY_BYTES {
        return Err(err(
            name,
            format!(
                "its header claims {:?} ({bytes} bytes), more than the {MAX_PACK_ARRAY_BYTES} a \
                 pack array may hold",
                a.shape()
            ),
        ));
    }
    Ok(())
}

fn read_u8<R: std::io::Read + std::io::Seek>(
    npz: &mut npyz::npz::NpzArchive<R>,
    name: &str,
    err: &ErrFn,
) -> Result<(Vec<usize>, Vec<u8>), PackError> {
    let a = open_array(npz, name, err)?;
    let shape = shape_of(&a);
    if a.order() != npyz::Order::C {
        return Err(err(name, "Fortran-ordered arrays are not supported".into()));
    }
    let dtype = a.dtype().descr();
    if !matches!(dtype.trim_matches('\''), "|u1" | "<u1" | ">u1") {
        return Err(err(name, format!("expected uint8, dtype is {dtype}")));
    }
    check_size(&a, name, 1, err)?;
    let data = a.into_vec::<u8>().map_err(|e| {
        err(
            name,
            format!("the data ends before the {shape:?} its header declares ({e})"),
        )
    })?;
    Ok((shape, data))
}

/// Reads a numeric array of any integer or float dtype as f64.
fn read_f64<R: std::io::Read + std::io::Seek>(
    npz: &mut npyz::npz::NpzArchive<R>,
    name: &str,
    err: &ErrFn,
) -> Result<(Vec<usize>, Vec<f64>), PackError> {
    use npyz::TypeChar;
    let a = open_array(npz, name, err)?;
    let shape = shape_of(&a);
    if a.order() != npyz::Order::C && shape.len() > 1 {
        return Err(err(name, "Fortran-ordered arrays are not supported".into()));
    }
    let dtype = a.dtype();
    let descr = dtype.descr();
    let bad = |e: std::io::Error| err(name, format!("cannot read {descr}: {e}"));
    let unsupported = || err(name, format!("expected a numeric dtype, got {descr}"));
    let npyz::DType::Plain(ts) = &dtype else {
        return Err(unsupported());
    };
    check_size(&a, name, ts.size_field(), err)?;
    let data: Vec<f64> = match (ts.type_char(), ts.size_field()) {
        (TypeChar::Float, 8) => a.into_vec::<f64>().map_err(bad)?,
        (TypeChar::Float, 4) => conv(a.into_vec::<f32>().map_err(bad)?),
        (TypeChar::Int, 8) => a
            .into_vec::<i64>()
            .map_err(bad)?
            .iter()
            .map(|&v| v as f64)
            .collect(),
        (TypeChar::Int, 4) => conv(a.into_vec::<i32>().map_err(bad)?),
        (TypeChar::Int, 2) => conv(a.into_vec::<i16>().map_err(bad)?),
        (TypeChar::Int, 1) => conv(a.into_vec::<i8>().map_err(bad)?),
        (TypeChar::Uint, 8) => a
            .into_vec::<u64>()
            .map_err(bad)?
            .iter()
            .map(|&v| v as f64)
            .collect(),
        (TypeChar::Uint, 4) => conv(a.into_vec::<u32>().map_err(bad)?),
        (TypeChar::Uint, 2) => conv(a.into_vec::<u16>().map_err(bad)?),
        (TypeChar::Uint, 1) => conv(a.into_vec::<u8>().map_err(bad)?),
        _ => return Err(unsupported()),
    };
    if data.iter().any(|v| !v.is_finite()) {
        return Err(err(name, "contains a non-finite value".into()));
    }
    Ok((shape, data))
}

fn conv<T: Into<f64> + Copy>(v: Vec<T>) -> Vec<f64> {
    v.iter().map(|&x| x.into()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A zip of `.npy` entries, each a header with `descr` and `shape` and `data` after it.
    fn npz(entries: &[(&str, &str, &str, &[u8])]) -> Vec<u8> {
        use std::io::Write;
        let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
        for (name, descr, shape, data) in entries {
            let mut header =
                format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
            while (10 + header.len() + 1) % 64 != 0 {
                header.push(' ');
            }
            header.push('\n');
            zip.start_file(*name, zip::write::FileOptions::default())
                .unwrap();
            zip.write_all(b"\x93NUMPY\x01\x00").unwrap();
            zip.write_all(&(header.len() as u16).to_le_bytes()).unwrap();
            zip.write_all(header.as_bytes()).unwrap();
            zip.write_all(data).unwrap();
        }
        zip.finish().unwrap().into_inner()
    }

    /// Headers claiming 92 GB, a wrong dtype or more data than follows are refused on one
    /// line naming the array, before anything is allocated.
    #[test]
    fn bad_array_headers_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let cases: [(&str, &str, &str, &[u8], &str); 3] = [
            (
                "huge",
                "|u1",
                "(100000, 480, 640, 3)",
                &[0; 16],
                "more than the",
            ),
            (
                "float",
                "<f4",
                "(2, 2, 3)",
                &[0; 48],
                "expected uint8, dtype is '<f4'",
            ),
            (
                "short",
                "|u1",
                "(2, 2, 3)",
                &[0; 5],
                "the data ends before the [2, 2, 3]",
            ),
        ];
        for (label, descr, shape, data, needle) in cases {
            let path = dir.path().join(format!("{label}.npz"));
            std::fs::write(&path, npz(&[("f0.npy", descr, shape, data)])).unwrap();
            let line = CalibrationPack::read(&path).unwrap_err().to_string();
            assert!(
                line.contains(&format!("{label}.npz"))
                    && line.contains("f0")
                    && line.contains(needle),
                "{label}: {line}"
            );
            assert!(!line.contains('\n'), "{line}");
        }
    }

    #[test]
    fn frame_sets_pick_indices_and_parse() {
        assert_eq!(FrameSet::Odd.indices(5), vec![1, 3]);
        assert_eq!(FrameSet::Even.indices(5), vec![0, 2, 4]);
        assert_eq!(FrameSet::All.indices(2), vec![0, 1]);
        assert_eq!("odd".parse::<FrameSet>(), Ok(FrameSet::Odd));
        assert!(
            "evens"
                .parse::<FrameSet>()
                .unwrap_err()
                .contains("even, odd or all")
        );
    }
}
