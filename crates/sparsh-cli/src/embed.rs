//! `sparsh embed`: features of every frame of a generated dataset from a trained encoder.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use safetensors::{Dtype, tensor::TensorView};
use sparsh_ssl::data::generated_sequences;
use sparsh_ssl::device::Devices;
use sparsh_ssl::embed::{Embeddings, FrozenEncoder, Pool};
use sparsh_ssl::recipe::Recipe;
use sparsh_ssl::weights::write_atomic;

use crate::progress::Progress;

/// `--pool`: what one frame's features are.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum PoolArg {
    /// The mean of the patch tokens, `[dim]` per frame.
    Mean,
    /// Every patch token, `[tokens, dim]` per frame.
    None,
}

/// The output formats, by the extension of `--out`.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Format {
    Safetensors,
    Npy,
}

fn format_of(out: &Path) -> Result<Format> {
    match out.extension().and_then(|e| e.to_str()) {
        Some("safetensors") => Ok(Format::Safetensors),
        Some("npy") => Ok(Format::Npy),
        other => bail!(
            "{}: unknown output format{}: use .safetensors or .npy",
            out.display(),
            other.map_or(String::new(), |e| format!(" `.{e}`"))
        ),
    }
}

/// Embeds every frame of the dataset `data` with the encoder `weights` of the recipe `config`
/// (default: the `recipe.toml` of the run directory holding the weights) into `out`, computing
/// on `device` (the encoder is loaded on the CPU and moved there).
pub fn embed(
    weights: &Path,
    config: Option<&Path>,
    data: &Path,
    out: &Path,
    pool: PoolArg,
    batch: usize,
    device: &Devices,
) -> Result<()> {
    let format = format_of(out)?;
    anyhow::ensure!(batch > 0, "--batch-size must be at least 1");
    if !weights.is_file() {
        bail!("{}: no such encoder file", weights.display());
    }
    let config: PathBuf = match config {
        Some(c) => c.to_path_buf(),
        None => {
            let beside = weights.with_file_name("recipe.toml");
            anyhow::ensure!(
                beside.is_file(),
                "{}: no recipe.toml beside the encoder; name its recipe with --config",
                weights.display()
            );
            beside
        }
    };
    let recipe = Recipe::load(&config)?;
    let encoder = FrozenEncoder::load(&recipe, weights)
        .with_context(|| format!("encoder of the recipe {}", config.display()))?
        .to_device(device.main());
    let sequences = generated_sequences(data)?;
    let total: usize = sequences.iter().map(|s| s.frames.len()).sum();
    let pool = match pool {
        PoolArg::Mean => Pool::Mean,
        PoolArg::None => Pool::None,
    };
    let progress = Progress::new("embed", "frame", total as u64);
    let start = std::time::Instant::now();
    let embeddings =
        encoder.embed_sequences(&sequences, pool, batch, &|n| progress.inc(n as u64))?;
    progress.finish();
    let seconds = start.elapsed().as_secs_f64();
    let bytes = match format {
        Format::Safetensors => safetensors_bytes(&embeddings, out)?,
        Format::Npy => npy_bytes(&embeddings)?,
    };
    write_atomic(out, &bytes)?;
    eprintln!(
        "{}: {total} frames, features {:?} ({:.1} frames/s)",
        out.display(),
        embeddings.shape,
        total as f64 / seconds.max(1e-9)
    );
    Ok(())
}

/// `features` (f32) and `frame` (i64, the frame number of each row).
fn safetensors_bytes(e: &Embeddings, out: &Path) -> Result<Vec<u8>> {
    let values: Vec<u8> = e.values.iter().flat_map(|v| v.to_le_bytes()).collect();
    let frames: Vec<u8> = e
        .frame_ids
        .iter()
        .flat_map(|&f| (f as i64).to_le_bytes())
        .collect();
    let views = vec![
        (
            "features",
            TensorView::new(Dtype::F32, e.shape.clone(), &values)?,
        ),
        (
            "frame",
            TensorView::new(Dtype::I64, vec![e.frame_ids.len()], &frames)?,
        ),
    ];
    safetensors::serialize(views, None).with_context(|| out.display().to_string())
}

/// The features alone as one f32 array (rows in ascending frame number).
fn npy_bytes(e: &Embeddings) -> Result<Vec<u8>> {
    use npyz::WriterBuilder;
    let shape: Vec<u64> = e.shape.iter().map(|&d| d as u64).collect();
    let mut bytes = Vec::new();
    let mut writer = npyz::WriteOptions::new()
        .default_dtype()
        .shape(&shape)
        .writer(&mut bytes)
        .begin_nd()?;
    writer.extend(e.values.iter().copied())?;
    writer.finish()?;
    Ok(bytes)
}
