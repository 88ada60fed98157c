#![warn(missing_docs)]
//! TacBench (Sparsh, CoRL 2024, §5): frozen tactile encoders read out by a small attentive
//! probe on touch tasks, at shrinking label budgets, against baselines that learn nothing from
//! pretraining — randomly initialised encoders of the same architecture (several draws), the
//! probe on the raw input patches, and the same ViT trained end to end on the budget's labels.
//!
//! - [`labels`]: per-frame labels of generated datasets and the official layouts, one type.
//! - [`tasks`]: the five tasks (force, slip, pose, texture, grasp): samples, targets, heads,
//!   losses and metrics.
//! - [`official`]: the official TacBench pickles (force/slip, pose, textile).
//! - [`config`]: the TOML run description.
//! - [`probe`]: the probe trainer (frozen tokens or end to end), epoch chosen on validation.
//! - [`stats`]: bootstrap intervals over test sequences, spread of random draws.
//! - [`report`]: `results.csv`, the Markdown table and the label-budget charts.
//! - [`run`]: the benchmark loop with resume.
//! - [`fields`]: T1A, the normal and shear field decoder scored against ground-truth fields,
//!   with [`flow`] (Farnebäck optical flow, its classical baseline) and [`fieldfig`] (figures).
//! - [`ablate`]: the sim-to-real ablation — models trained on synthetic frames of simulator
//!   variants, scored on real frames' contact circles.

pub mod ablate;
pub mod config;
pub mod fieldfig;
pub mod fields;
pub mod flow;
pub mod labels;
pub mod official;
pub mod probe;
pub mod report;
pub mod run;
pub mod stats;
pub mod tasks;

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
