//! Tactile datasets on disk: the layout `sparsh generate` writes and the code that writes and
//! reads it. No simulation here.
//!
//! ```text
//! DIR/frames/000000.png      8-bit RGB sensor image per frame
//! DIR/fields/000000.exr      ground-truth fields: f32 (or f16) channels p qx qy ux uy uz contact slip
//! DIR/background.png         the sensor's image with nothing touching
//! DIR/labels.jsonl           one JSON row per frame (see [`Label`])
//! DIR/manifest.json          scene copy, seed, version, counts, sha256 of every file
//! ```
//! Every file is written under a temporary name and renamed into place, and the manifest comes
//! last, so an interrupted run never leaves a file that looks complete but is not.
#![warn(missing_docs)]

mod exr_io;
mod writer;

pub use exr_io::{ExrChannels, read_exr_channels, write_exr_channels};
pub use writer::{DatasetWriter, Label, Manifest, PoseLabel, encode_png, write_atomic};

/// Failures reading or writing a dataset; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// A file system operation failed.
    #[error("{path}: {source}")]
    Io {
        /// File or directory.
        path: std::path::PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
    /// The output directory holds files and `--force` was not given.
    #[error("{path}: output directory is not empty (pass --force to overwrite the dataset in it)")]
    NotEmpty {
        /// Directory.
        path: std::path::PathBuf,
    },
    /// An image or EXR file could not be encoded or decoded.
    #[error("{path}: {message}")]
    Format {
        /// File.
        path: std::path::PathBuf,
        /// What is wrong.
        message: String,
    },
}

/// Attaches a path to an I/O error.
pub(crate) fn io_err(path: &std::path::Path) -> impl FnOnce(std::io::Error) -> DataError + '_ {
    move |source| DataError::Io {
        path: path.to_path_buf(),
        source,
    }
}
