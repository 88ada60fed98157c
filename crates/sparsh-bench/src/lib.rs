#![warn(missing_docs)]
//! The learning benchmarks of Sparsh's simulated touch, one folder per benchmark, with the
//! modules several of them share at the top level.
//!
//! - [`tacbench`]: TacBench (Sparsh, CoRL 2024, §5) — frozen tactile encoders read out by a
//!   small attentive probe on touch tasks at shrinking label budgets, against baselines that
//!   learn nothing from pretraining: tasks, config, probe trainer, report and the loop with
//!   resume.
//! - [`official`]: the official TacBench pickles, one file per layout (force/slip, pose,
//!   textile, grasp).
//! - [`fields`]: T1A, the normal and shear field decoder scored against ground-truth fields,
//!   with Farnebäck optical flow (its classical baseline) and the figures.
//! - [`ablate`]: the sim-to-real ablation — models trained on synthetic frames of simulator
//!   variants, scored on real frames' contact circles.
//!
//! Shared:
//!
//! - [`labels`]: per-frame labels of generated datasets and the official layouts, one type.
//! - [`stats`]: bootstrap intervals over test sequences, spread of random draws, quantiles.
//! - [`encoders`]: a recipe's random initialisation under a seed, missing weights named.
//! - `io`: atomic writes, TOML configs, the charts' font.

pub mod ablate;
pub mod encoders;
pub mod fields;
mod io;
pub mod labels;
pub mod official;
pub mod stats;
pub mod tacbench;

/// Errors of TacBench; each message names the file or field at fault.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// An invalid value in a TacBench config.
    #[error("{path}: {field}: {msg}")]
    Config {
        /// The config file.
        path: String,
        /// The key at fault.
        field: String,
        /// What is wrong.
        msg: String,
    },
    /// A file that cannot be read or parsed.
    #[error("{path}: {msg}")]
    File {
        /// The file.
        path: String,
        /// What is wrong with it.
        msg: String,
    },
    /// An error of the encoder stack.
    #[error(transparent)]
    Ssl(#[from] sparsh_ssl::Error),
}

impl Error {
    /// A [`Error::File`] for `path`.
    pub fn file(path: impl AsRef<std::path::Path>, msg: impl std::fmt::Display) -> Self {
        Error::File {
            path: path.as_ref().display().to_string(),
            msg: msg.to_string(),
        }
    }

    /// A [`Error::Config`] for `field` of `path`.
    pub fn config(
        path: impl AsRef<std::path::Path>,
        field: impl std::fmt::Display,
        msg: impl std::fmt::Display,
    ) -> Self {
        Error::Config {
            path: path.as_ref().display().to_string(),
            field: field.to_string(),
            msg: msg.to_string(),
        }
    }
}
