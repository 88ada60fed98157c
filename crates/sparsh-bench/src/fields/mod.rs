//! T1A: Sparsh's normal and shear field decoder on a frozen encoder, trained without field
//! labels and scored against the simulator's ground-truth fields.
//!
//! - [`geometry`]: frame pixels → encoder input pixels (rotation, crop, resize).
//! - [`data`]: frame pairs (never the fields) for training; ground truth and markers for scoring.
//! - [`dpt`]: the DPT decoder with its normal and shear branches.
//! - [`loss`]: the self-supervised photometric losses and the warp.
//! - [`objective`]: whether the shear loss scores the true flow below zero and uniform flows.
//! - [`train`]: training on hooked tokens, self-supervised or supervised (the ceiling).
//! - [`ceiling`]: the supervised U-Net at the input's resolution, which reads no encoder.
//! - [`metrics`]: correlation, IoU, end-point and angular error per frame pair.
//! - [`run`]: `sparsh fieldprobe train` and `eval`: decoders, references, tables, figures.
//! - [`flow`]: Farnebäck dense optical flow, the classical shear baseline.
//! - [`figures`]: normal colour map + shear quiver figures.

pub mod ceiling;
pub mod data;
pub mod dpt;
pub mod figures;
pub mod flow;
pub mod geometry;
pub mod loss;
pub mod metrics;
pub mod objective;
pub mod run;
pub mod train;
