//! TacBench (Sparsh, CoRL 2024, §5): frozen tactile encoders read out by a small attentive
//! probe on touch tasks, at shrinking label budgets, against baselines that learn nothing from
//! pretraining — randomly initialised encoders of the same architecture (several draws), the
//! probe on the raw input patches, and the same ViT trained end to end on the budget's labels.
//! It reads generated datasets or the official layouts ([`crate::official`]), both as
//! [`crate::labels`], and draws its intervals from [`crate::stats`].
//!
//! - [`tasks`]: the five tasks (force, slip, pose, texture, grasp): samples, targets, heads,
//!   losses and metrics.
//! - [`config`]: the TOML run description.
//! - [`pixels`]: read-outs without an encoder at the frames' own resolution: the classical
//!   ridge and the supervised-ceiling CNN.
//! - [`probe`]: the probe trainer (frozen tokens or end to end), epoch chosen on validation.
//! - [`report`]: `results.csv`, the Markdown table and the label-budget charts.
//! - [`run`]: the benchmark loop with resume.

pub mod config;
pub mod photometric;
pub mod pixels;
pub mod probe;
pub mod report;
pub mod run;
pub mod tasks;
