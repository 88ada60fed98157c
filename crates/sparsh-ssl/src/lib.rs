#![warn(missing_docs)]
//! Self-supervised touch representations (Sparsh) in burn.
//!
//! - [`vit`]: the ViT encoder (no `[cls]`, fixed sinusoidal positions, optional registers and
//!   layer scale); [`pos_embed`]: the official sinusoidal table and its resampling.
//! - [`masks`]: the masking and view samplers of the four objectives.
//! - [`mae`], [`dino`], [`jepa`]: MAE, DINO, I-JEPA and V-JEPA.
//! - [`data`]: official preprocessing, datasets (generated, Sparsh pickles, Taxim packs), the
//!   batch loader.
//! - [`weights`]: safetensors with the official checkpoints' key names.
//! - [`embed`]: a trained encoder as a frozen feature extractor of tactile frames.
//! - [`recipe`], [`train`], [`probe`]: training recipes, the training loop, the online force probe.
//! - [`kernels`]: the exact GELU and layer norm, one vectorised pass each way on the CPU backend.
//! - [`bench`]: training-step throughput and cross-device parity (`sparsh bench-train`).
//! - [`device`]: the CPU, wgpu or CUDA devices a run computes on (data-parallel over several).

pub mod bench;
pub mod data;
pub mod device;
pub mod dino;
pub mod ema;
pub mod embed;
pub mod host;
pub mod jepa;
pub mod kernels;
pub mod mae;
pub mod masks;
pub mod pos_embed;
pub mod probe;
pub mod recipe;
pub mod rng;
pub mod train;
pub mod vit;
pub mod weights;

/// Errors of this crate; each message names the file or field at fault.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// An invalid configuration value.
    #[error("config: {0}")]
    Config(String),
    /// A file that cannot be read or parsed.
    #[error("{path}: {msg}")]
    File {
        /// The file.
        path: String,
        /// What is wrong with it.
        msg: String,
    },
    /// Anything else in the data.
    #[error("data: {0}")]
    Data(String),
}

impl Error {
    /// A [`Error::File`] for `path`.
    pub fn file(path: impl AsRef<std::path::Path>, msg: impl std::fmt::Display) -> Self {
        Error::File {
            path: path.as_ref().display().to_string(),
            msg: msg.to_string(),
        }
    }
}
