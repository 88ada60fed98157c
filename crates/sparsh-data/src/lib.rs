//! Tactile datasets on disk: the layout `sparsh generate` writes and the code that writes and
//! reads it. No simulation here.
//!
//! ```text
//! DIR/dataset.json           what the dataset is made from (scene copy, seed, version, counts)
//! DIR/frames/000000.png      8-bit RGB sensor image per frame (dataset-wide frame index)
//! DIR/fields/000000.exr      ground-truth fields: f32 (or f16) channels p qx qy ux uy uz contact slip
//! DIR/backgrounds/000000.png each sequence's no-contact image
//! DIR/parts/000000.json      record of a finished sequence: its files' sha256 and label rows
//! DIR/labels.jsonl           one JSON row per frame (see [`Label`]), all sequences in order
//! DIR/manifest.json          identity, notes and the sha256 of every file; written last
//! DIR/shards.json            while shards (`--shard K/N`) are running: N; removed at the end
//! ```
//! Every file is written under a temporary name and renamed into place; a sequence's record is
//! written after its files, and the manifest after every record, so an interrupted run never
//! leaves a file that looks complete but is not, and a resumed run redoes only unrecorded
//! sequences.
#![warn(missing_docs)]

mod exr_io;
mod official;
pub mod sparsh_pkl;
mod writer;

pub use exr_io::{ExrChannels, MAX_EXR_SAMPLES, read_exr_channels, write_exr_channels};
pub use official::{official_crop, official_resize, preprocess, subtract_background};
pub use writer::{
    Dataset, Identity, Label, Manifest, OpenMode, PoseLabel, Problem, SequencePart, ShardLayout,
    check_part, encode_png, read_identity, read_manifest, read_shard_layout, verify, write_atomic,
};

/// Failures reading or writing a dataset; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// A file system operation failed (the reason is the error's source).
    #[error("{path}")]
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
    /// The directory holds a different dataset (another scene or seed).
    #[error("{path}: {message}")]
    Refused {
        /// Directory.
        path: std::path::PathBuf,
        /// Why.
        message: String,
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
