//! Encoder weights in safetensors under the official Sparsh (PyTorch) key names
//! (`tactile_ssl/model/vision_transformer.py`, `VisionTransformer.state_dict()`).
//!
//! | official key (PyTorch layout) | here |
//! |---|---|
//! | `patch_embed.proj.weight` `[D, C, p, p]` (`[D, C, t, p, p]` for tubelets) | `patch_embed.weight` `[C·t·p·p, D]` (reshaped, transposed) |
//! | `patch_embed.proj.bias` `[D]` | `patch_embed.bias` |
//! | `pos_embed.frequency_bands` `[A, ⌈D/2A⌉]` (sinusoidal, A = 2 images / 3 clips) | `pos_embed` computed from these bands on this encoder's grid ([`crate::pos_embed::sincos_from_bands`]) |
//! | `pos_embed` `[1, N, D]` (learned: official V-JEPA pretraining; or a table written here) | `pos_embed`, resampled when its grid differs |
//! | `register_tokens` `[1, R, D]` | `register_tokens` |
//! | `blocks.i.norm1.{weight,bias}` | `blocks.i.norm1.{gamma,beta}` |
//! | `blocks.i.attn.qkv.{weight,bias}` `[3D, D]` | `blocks.i.attn.qkv` `[D, 3D]` (transposed) |
//! | `blocks.i.attn.proj.{weight,bias}` | `blocks.i.attn.proj` (transposed) |
//! | `blocks.i.ls1.gamma` `[D]` | `blocks.i.ls1` |
//! | `blocks.i.norm2.{weight,bias}` | `blocks.i.norm2.{gamma,beta}` |
//! | `blocks.i.mlp.fc1/fc2.{weight,bias}` | `blocks.i.mlp.fc1/fc2` (transposed) |
//! | `blocks.i.ls2.gamma` `[D]` | `blocks.i.ls2` |
//! | `norm.{weight,bias}` | `norm.{gamma,beta}` |
//!
//! Rules of [`load_encoder`]:
//! - **Prefix.** A file may hold the encoder bare or inside a training module. The caller may
//!   name the prefix; otherwise the candidates are the prefixes `P` with a `P` +
//!   `patch_embed.proj.weight` key: one candidate is taken, several are resolved by
//!   [`PREFERRED_PREFIXES`] (the encoder the official downstream code loads), and anything else
//!   is an error listing them.
//! - **Every tensor under the prefix is used**: a missing or unexpected one is a one-line error
//!   naming the key (other sub-models — heads, decoders, predictors, the other encoder copy —
//!   lie outside the prefix and are ignored).
//! - **Layer scale** follows the file: with `ls1`/`ls2` gammas they are loaded (and created if
//!   this encoder was configured without); without them (files written before layer scale, or
//!   by a recipe without it) an encoder configured with layer scale gets `γ = 1`, which is the
//!   block without layer scale exactly.
//! - **Position embedding**: see the table; a stored table whose grid differs from this
//!   encoder's is resampled as the official `interpolate_pos_encoding` intends (bicubic for
//!   images, trilinear for clips, [`crate::pos_embed::Resample`]), from the grid recorded in the
//!   file's metadata `pos_embed_grid` (written by [`save_encoder`]) or, for a file without it,
//!   the official 320×240 training grid when the token count matches it.

use std::collections::{HashMap, HashSet};
use std::path::Path;

use burn::module::Param;
use burn::nn::{LayerNorm, Linear};
use burn::prelude::*;
use safetensors::{Dtype, SafeTensors, tensor::TensorView};

use crate::Error;
use crate::pos_embed::{Resample, resample, sincos_from_bands};
use crate::vit::Vit;

/// Metadata key of the position-embedding grid in files written by [`save_encoder`]
/// (comma-separated axes, e.g. `20,15` or `2,20,15`).
pub const POS_GRID_METADATA: &str = "pos_embed_grid";

/// Prefixes preferred, in this order, when a file holds several encoders: the bare encoder, then
/// the encoder the official downstream code loads (`tactile_ssl/downstream_task/sl_module.py`,
/// `load_encoder`): DINO / DINOv2's teacher `teacher_encoder.backbone.` (the student is
/// `student_encoder.backbone.`), V-JEPA's target `target_encoder.backbone.` (`MultiMaskWrapper`
/// adds `.backbone`; context `context_encoder.backbone.`), I-JEPA's target `target_encoder.`
/// (context `context_encoder.`), and MAE's `encoder.`.
pub const PREFERRED_PREFIXES: [&str; 5] = [
    "",
    "teacher_encoder.backbone.",
    "target_encoder.backbone.",
    "target_encoder.",
    "encoder.",
];

/// Position grid of the published checkpoints, trained at 320×240 with 16-pixel patches
/// (`config/experiment/*_vit.yaml`), and 4-frame clips in tubelets of 2 for V-JEPA.
const OFFICIAL_IMAGE_GRID: [usize; 2] = [20, 15];
const OFFICIAL_CLIP_GRID: [usize; 3] = [2, 20, 15];

/// One named host tensor in official layout.
struct Named {
    name: String,
    shape: Vec<usize>,
    values: Vec<f32>,
}

fn host<const D: usize>(t: &Tensor<D>) -> Vec<f32> {
    t.to_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .expect("f32 tensor")
}

fn linear_out(prefix: &str, l: &Linear, out: &mut Vec<Named>) {
    let w = l.weight.val();
    let [din, dout] = w.dims();
    out.push(Named {
        name: format!("{prefix}.weight"),
        shape: vec![dout, din],
        values: host(&w.transpose()),
    });
    if let Some(b) = &l.bias {
        out.push(Named {
            name: format!("{prefix}.bias"),
            shape: vec![dout],
            values: host(&b.val()),
        });
    }
}

fn norm_out(prefix: &str, n: &LayerNorm, out: &mut Vec<Named>) {
    out.push(Named {
        name: format!("{prefix}.weight"),
        shape: n.gamma.dims().to_vec(),
        values: host(&n.gamma.val()),
    });
    if let Some(b) = &n.beta {
        out.push(Named {
            name: format!("{prefix}.bias"),
            shape: b.dims().to_vec(),
            values: host(&b.val()),
        });
    }
}

/// Official-layout shape of the patch-embedding weight.
fn patch_weight_shape(vit: &Vit) -> Vec<usize> {
    let [pd, d] = vit.patch_embed.weight.dims();
    let (p, t) = (vit.patch_size, vit.tubelet_size);
    let c = pd / (p * p * t);
    if t == 1 {
        vec![d, c, p, p]
    } else {
        vec![d, c, t, p, p]
    }
}

fn named_tensors(vit: &Vit) -> Vec<Named> {
    let mut out = Vec::new();
    let w = vit.patch_embed.weight.val();
    out.push(Named {
        name: "patch_embed.proj.weight".into(),
        shape: patch_weight_shape(vit),
        values: host(&w.transpose()),
    });
    if let Some(b) = &vit.patch_embed.bias {
        out.push(Named {
            name: "patch_embed.proj.bias".into(),
            shape: b.dims().to_vec(),
            values: host(&b.val()),
        });
    }
    out.push(Named {
        name: "pos_embed".into(),
        shape: vit.pos_embed.dims().to_vec(),
        values: host(&vit.pos_embed),
    });
    if let Some(r) = &vit.register_tokens {
        out.push(Named {
            name: "register_tokens".into(),
            shape: r.dims().to_vec(),
            values: host(&r.val()),
        });
    }
    for (i, b) in vit.blocks.iter().enumerate() {
        norm_out(&format!("blocks.{i}.norm1"), &b.norm1, &mut out);
        linear_out(&format!("blocks.{i}.attn.qkv"), &b.attn.qkv, &mut out);
        linear_out(&format!("blocks.{i}.attn.proj"), &b.attn.proj, &mut out);
        norm_out(&format!("blocks.{i}.norm2"), &b.norm2, &mut out);
        linear_out(&format!("blocks.{i}.mlp.fc1"), &b.mlp.fc1, &mut out);
        linear_out(&format!("blocks.{i}.mlp.fc2"), &b.mlp.fc2, &mut out);
        for (name, gamma) in [("ls1", &b.ls1), ("ls2", &b.ls2)] {
            if let Some(g) = gamma {
                out.push(Named {
                    name: format!("blocks.{i}.{name}.gamma"),
                    shape: g.dims().to_vec(),
                    values: host(&g.val()),
                });
            }
        }
    }
    norm_out("norm", &vit.norm, &mut out);
    out
}

/// Writes the encoder to `path` in safetensors (f32, official key names, the position table as
/// `pos_embed` with its grid in the metadata [`POS_GRID_METADATA`]), atomically.
pub fn save_encoder(vit: &Vit, path: &Path) -> Result<(), Error> {
    let named = named_tensors(vit);
    let bytes: Vec<Vec<u8>> = named
        .iter()
        .map(|n| n.values.iter().flat_map(|v| v.to_le_bytes()).collect())
        .collect();
    let views = named
        .iter()
        .zip(&bytes)
        .map(|(n, b)| {
            TensorView::new(Dtype::F32, n.shape.clone(), b)
                .map(|v| (n.name.clone(), v))
                .map_err(|e| Error::file(path, format!("{}: {e}", n.name)))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let grid = vit
        .pos_grid
        .iter()
        .map(usize::to_string)
        .collect::<Vec<_>>();
    let metadata = HashMap::from([(POS_GRID_METADATA.to_string(), grid.join(","))]);
    let data = safetensors::serialize(views, Some(metadata)).map_err(|e| Error::file(path, e))?;
    write_atomic(path, &data)
}

/// Reads official-layout tensors under `prefix` and maps them onto the encoder.
struct Source<'a> {
    st: SafeTensors<'a>,
    prefix: String,
    path: &'a Path,
    used: HashSet<String>,
}

impl Source<'_> {
    fn full(&self, key: &str) -> String {
        format!("{}{key}", self.prefix)
    }

    /// Shape of `key` under the prefix, `None` when the file has no such tensor.
    fn shape(&self, key: &str) -> Option<Vec<usize>> {
        self.st
            .tensor(&self.full(key))
            .ok()
            .map(|t| t.shape().to_vec())
    }

    fn get(&mut self, key: &str, shape: &[usize]) -> Result<Vec<f32>, Error> {
        let full = self.full(key);
        let t = self
            .st
            .tensor(&full)
            .map_err(|_| Error::file(self.path, format!("missing tensor `{full}`")))?;
        if t.shape() != shape {
            return Err(Error::file(
                self.path,
                format!(
                    "`{full}` has shape {:?}, this encoder needs {shape:?} (another architecture?)",
                    t.shape()
                ),
            ));
        }
        let data = t.data();
        let values = match t.dtype() {
            Dtype::F32 => data
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect(),
            Dtype::F16 => data
                .chunks_exact(2)
                .map(|c| half_to_f32(u16::from_le_bytes([c[0], c[1]]), false))
                .collect(),
            Dtype::BF16 => data
                .chunks_exact(2)
                .map(|c| half_to_f32(u16::from_le_bytes([c[0], c[1]]), true))
                .collect(),
            other => {
                return Err(Error::file(
                    self.path,
                    format!("`{full}` has dtype {other:?}; f32, f16 and bf16 are supported"),
                ));
            }
        };
        self.used.insert(full);
        Ok(values)
    }
}

/// IEEE half (or bfloat16) bits to f32.
fn half_to_f32(bits: u16, bf16: bool) -> f32 {
    if bf16 {
        return f32::from_bits((bits as u32) << 16);
    }
    let sign = ((bits >> 15) as u32) << 31;
    let exp = ((bits >> 10) & 0x1f) as i32;
    let frac = (bits & 0x3ff) as u32;
    let v = match exp {
        0 => (frac as f32) * 2f32.powi(-24),
        31 => {
            if frac == 0 {
                f32::INFINITY
            } else {
                f32::NAN
            }
        }
        _ => f32::from_bits(((exp - 15 + 127) as u32) << 23 | frac << 13),
    };
    f32::from_bits(v.to_bits() | sign)
}

fn set<const D: usize>(
    p: Param<Tensor<D>>,
    values: Vec<f32>,
    shape: [usize; D],
) -> Param<Tensor<D>> {
    p.map(|old| Tensor::from_data(TensorData::new(values, shape), &old.device()))
}

fn load_linear(src: &mut Source, key: &str, mut l: Linear) -> Result<Linear, Error> {
    let [din, dout] = l.weight.dims();
    let w = src.get(&format!("{key}.weight"), &[dout, din])?;
    // official [out, in] → ours [in, out]
    let mut t = vec![0.0; w.len()];
    for o in 0..dout {
        for i in 0..din {
            t[i * dout + o] = w[o * din + i];
        }
    }
    l.weight = set(l.weight, t, [din, dout]);
    if let Some(b) = l.bias.take() {
        let v = src.get(&format!("{key}.bias"), &[dout])?;
        l.bias = Some(set(b, v, [dout]));
    }
    Ok(l)
}

fn load_norm(src: &mut Source, key: &str, mut n: LayerNorm) -> Result<LayerNorm, Error> {
    let [d] = n.gamma.dims();
    let g = src.get(&format!("{key}.weight"), &[d])?;
    n.gamma = set(n.gamma, g, [d]);
    if let Some(b) = n.beta.take() {
        let v = src.get(&format!("{key}.bias"), &[d])?;
        n.beta = Some(set(b, v, [d]));
    }
    Ok(n)
}

/// The layer-scale vector `key` (`[dim]`) from the file, or `γ = 1` when the file has no layer
/// scale (`in_file` false) and the encoder has one.
fn load_gamma(
    src: &mut Source,
    key: &str,
    in_file: bool,
    gamma: Option<Param<Tensor<1>>>,
    dim: usize,
    device: &Device,
) -> Result<Option<Param<Tensor<1>>>, Error> {
    if !in_file {
        return Ok(gamma.map(|g| g.map(|old| Tensor::ones([dim], &old.device()))));
    }
    let v = src.get(key, &[dim])?;
    Ok(Some(match gamma {
        Some(g) => set(g, v, [dim]),
        None => Param::from_tensor(Tensor::from_data(TensorData::new(v, [dim]), device)),
    }))
}

/// The encoder's prefix in a file with the keys `names` (sorted); see the module docs.
fn choose_prefix(names: &[String], given: Option<&str>, path: &Path) -> Result<String, Error> {
    let key = "patch_embed.proj.weight";
    let found: Vec<&str> = names.iter().filter_map(|n| n.strip_suffix(key)).collect();
    let list = || {
        found
            .iter()
            .map(|p| format!("`{p}`"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    if let Some(p) = given {
        return if found.contains(&p) {
            Ok(p.to_string())
        } else {
            Err(Error::file(
                path,
                format!(
                    "no encoder under prefix `{p}` (no `{p}{key}`; encoders at: {})",
                    list()
                ),
            ))
        };
    }
    match found.as_slice() {
        [] => Err(Error::file(
            path,
            format!("no `{key}`: not a ViT encoder checkpoint"),
        )),
        [one] => Ok(one.to_string()),
        _ => PREFERRED_PREFIXES
            .iter()
            .find(|p| found.contains(p))
            .map(|p| p.to_string())
            .ok_or_else(|| {
                Error::file(
                    path,
                    format!(
                        "several encoders ({}) and none of them is preferred; name the prefix",
                        list()
                    ),
                )
            }),
    }
}

/// Grid of a stored position table with `tokens` tokens: the file's metadata, else this
/// encoder's grid when the count matches, else the official training grid when it matches.
fn stored_grid(
    metadata: Option<&String>,
    tokens: usize,
    target: &[usize],
    path: &Path,
    key: &str,
) -> Result<Vec<usize>, Error> {
    if let Some(text) = metadata {
        let grid = text
            .split(',')
            .map(|v| v.trim().parse::<usize>())
            .collect::<Result<Vec<_>, _>>()
            .ok()
            .filter(|g| g.iter().product::<usize>() == tokens && !g.contains(&0))
            .ok_or_else(|| {
                Error::file(
                    path,
                    format!("metadata `{POS_GRID_METADATA}` = `{text}` is not a grid of the {tokens} tokens of `{key}`"),
                )
            })?;
        return Ok(grid);
    }
    let official: &[usize] = if target.len() == 3 {
        &OFFICIAL_CLIP_GRID
    } else {
        &OFFICIAL_IMAGE_GRID
    };
    [target, official]
        .into_iter()
        .find(|g| g.iter().product::<usize>() == tokens)
        .map(<[usize]>::to_vec)
        .ok_or_else(|| {
            Error::file(
                path,
                format!(
                    "`{key}` has {tokens} tokens, this encoder needs {} ({target:?}), and the file records no grid (metadata `{POS_GRID_METADATA}`) to resample it from",
                    target.iter().product::<usize>()
                ),
            )
        })
}

/// The position embedding `[1, tokens, dim]` for this encoder's grid from the file (see the
/// module docs).
fn load_pos_embed(
    src: &mut Source,
    vit: &Vit,
    metadata: Option<&String>,
) -> Result<Tensor<3>, Error> {
    let d = vit.dim();
    let grid = &vit.pos_grid;
    let n: usize = grid.iter().product();
    let device = vit.pos_embed.device();
    let (bands_key, table_key) = ("pos_embed.frequency_bands", "pos_embed");
    let values = match (src.shape(bands_key), src.shape(table_key)) {
        (Some(_), Some(_)) => {
            return Err(Error::file(
                src.path,
                format!(
                    "both `{}` and `{}`: one position embedding expected",
                    src.full(bands_key),
                    src.full(table_key)
                ),
            ));
        }
        (None, None) => {
            return Err(Error::file(
                src.path,
                format!("missing tensor `{}`", src.full(bands_key)),
            ));
        }
        (Some(_), None) => {
            let axes = grid.len();
            let per_axis = d.div_ceil(2 * axes);
            let flat = src.get(bands_key, &[axes, per_axis])?;
            let bands: Vec<Vec<f64>> = flat
                .chunks_exact(per_axis)
                .map(|row| row.iter().map(|&w| w as f64).collect())
                .collect();
            sincos_from_bands(d, grid, &bands)
        }
        (None, Some(shape)) => {
            let tokens = match shape.as_slice() {
                [1, t, dd] if *dd == d => *t,
                _ => n,
            };
            let table = src.get(table_key, &[1, tokens, d])?;
            let full = src.full(table_key);
            let from = stored_grid(metadata, tokens, grid, src.path, &full)?;
            if from == *grid {
                table
            } else {
                let mode = match (from.len(), grid.len()) {
                    (2, 2) => Resample::Bicubic,
                    (3, 3) => Resample::Trilinear,
                    _ => {
                        return Err(Error::file(
                            src.path,
                            format!(
                                "`{full}` has grid {from:?}, this encoder {grid:?}: images and clips do not mix"
                            ),
                        ));
                    }
                };
                resample(&table, d, &from, grid, mode)
            }
        }
    };
    Ok(Tensor::from_data(
        TensorData::new(values, [1, n, d]),
        &device,
    ))
}

/// Loads encoder weights from a safetensors file with official key names (see the module docs).
/// `prefix` selects the sub-model (e.g. `"student_encoder.backbone."`); `None` finds it.
/// Memory is bounded by the file's size and the encoder's own tensors: a header whose shapes or
/// offsets do not fit the file is refused, and each tensor's shape is checked before its data is
/// read.
pub fn load_encoder(mut vit: Vit, path: &Path, prefix: Option<&str>) -> Result<Vit, Error> {
    let bytes = std::fs::read(path).map_err(|e| Error::file(path, e))?;
    let st = SafeTensors::deserialize(&bytes)
        .map_err(|e| Error::file(path, format!("not a complete safetensors file: {e}")))?;
    let metadata = SafeTensors::read_metadata(&bytes)
        .map_err(|e| Error::file(path, format!("not a complete safetensors file: {e}")))?
        .1
        .metadata()
        .clone()
        .unwrap_or_default();
    let mut names: Vec<String> = st.names().into_iter().map(|s| s.to_string()).collect();
    names.sort();
    let prefix = choose_prefix(&names, prefix, path)?;
    let mut src = Source {
        st,
        prefix: prefix.clone(),
        path,
        used: HashSet::new(),
    };
    let pshape = patch_weight_shape(&vit);
    let [pd, d] = vit.patch_embed.weight.dims();
    let w = src.get("patch_embed.proj.weight", &pshape)?;
    let mut t = vec![0.0; w.len()];
    for o in 0..d {
        for i in 0..pd {
            t[i * d + o] = w[o * pd + i];
        }
    }
    vit.patch_embed.weight = set(vit.patch_embed.weight, t, [pd, d]);
    if let Some(b) = vit.patch_embed.bias.take() {
        let v = src.get("patch_embed.proj.bias", &[d])?;
        vit.patch_embed.bias = Some(set(b, v, [d]));
    }
    vit.pos_embed = load_pos_embed(&mut src, &vit, metadata.get(POS_GRID_METADATA))?;
    let reg_key = src.full("register_tokens");
    match (
        vit.register_tokens.take(),
        src.shape("register_tokens").is_some(),
    ) {
        (Some(r), true) => {
            let shape = r.dims();
            let v = src.get("register_tokens", &shape)?;
            vit.register_tokens = Some(set(r, v, shape));
        }
        (None, false) => {}
        (Some(_), false) => {
            return Err(Error::file(path, format!("missing tensor `{reg_key}`")));
        }
        (None, true) => {
            return Err(Error::file(
                path,
                format!("`{reg_key}` present but this encoder has no register tokens"),
            ));
        }
    }
    let ls_in_file = names
        .iter()
        .filter_map(|n| n.strip_prefix(prefix.as_str()))
        .any(|rest| rest.starts_with("blocks.") && rest.ends_with(".gamma"));
    let device = vit.pos_embed.device();
    let blocks = std::mem::take(&mut vit.blocks);
    for (i, mut b) in blocks.into_iter().enumerate() {
        b.norm1 = load_norm(&mut src, &format!("blocks.{i}.norm1"), b.norm1)?;
        b.attn.qkv = load_linear(&mut src, &format!("blocks.{i}.attn.qkv"), b.attn.qkv)?;
        b.attn.proj = load_linear(&mut src, &format!("blocks.{i}.attn.proj"), b.attn.proj)?;
        b.ls1 = load_gamma(
            &mut src,
            &format!("blocks.{i}.ls1.gamma"),
            ls_in_file,
            b.ls1,
            d,
            &device,
        )?;
        b.norm2 = load_norm(&mut src, &format!("blocks.{i}.norm2"), b.norm2)?;
        b.mlp.fc1 = load_linear(&mut src, &format!("blocks.{i}.mlp.fc1"), b.mlp.fc1)?;
        b.mlp.fc2 = load_linear(&mut src, &format!("blocks.{i}.mlp.fc2"), b.mlp.fc2)?;
        b.ls2 = load_gamma(
            &mut src,
            &format!("blocks.{i}.ls2.gamma"),
            ls_in_file,
            b.ls2,
            d,
            &device,
        )?;
        vit.blocks.push(b);
    }
    vit.norm = load_norm(&mut src, "norm", vit.norm)?;
    // other encoders in the file (a bare encoder beside prefixed ones) are not ours
    let others: Vec<String> = names
        .iter()
        .filter_map(|n| n.strip_suffix("patch_embed.proj.weight"))
        .filter(|p| *p != prefix && p.starts_with(prefix.as_str()))
        .map(str::to_string)
        .collect();
    if let Some(extra) = names.iter().find(|n| {
        n.starts_with(prefix.as_str())
            && !src.used.contains(n.as_str())
            && !others.iter().any(|o| n.starts_with(o.as_str()))
    }) {
        return Err(Error::file(
            path,
            format!(
                "unexpected tensor `{extra}`: this encoder has no place for it (deeper model or unsupported layer)"
            ),
        ));
    }
    Ok(vit)
}

/// Writes `bytes` to `path` through a temporary file and a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), Error> {
    let tmp = path.with_extension("tmp-write");
    std::fs::write(&tmp, bytes).map_err(|e| Error::file(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| Error::file(path, e))
}
