//! Encoder weights in safetensors under the official Sparsh (PyTorch) key names.
//!
//! | official key (PyTorch layout) | here |
//! |---|---|
//! | `patch_embed.proj.weight` `[D, C, p, p]` (`[D, C, t, p, p]` for tubelets) | `patch_embed.weight` `[C·t·p·p, D]` (reshaped, transposed) |
//! | `patch_embed.proj.bias` `[D]` | `patch_embed.bias` |
//! | `pos_embed` `[1, N, D]` (fixed) | `pos_embed` (loaded in place of the computed one) |
//! | `register_tokens` `[1, R, D]` | `register_tokens` |
//! | `blocks.i.norm1.{weight,bias}` | `blocks.i.norm1.{gamma,beta}` |
//! | `blocks.i.attn.qkv.{weight,bias}` `[3D, D]` | `blocks.i.attn.qkv` `[D, 3D]` (transposed) |
//! | `blocks.i.attn.proj.{weight,bias}` | `blocks.i.attn.proj` (transposed) |
//! | `blocks.i.norm2.{weight,bias}` | `blocks.i.norm2.{gamma,beta}` |
//! | `blocks.i.mlp.fc1/fc2.{weight,bias}` | `blocks.i.mlp.fc1/fc2` (transposed) |
//! | `norm.{weight,bias}` | `norm.{gamma,beta}` |
//!
//! Published checkpoints may nest the encoder under a prefix (`encoder.`, `student_encoder.`,
//! `model.encoder.`, ...): [`load_encoder`] finds it from the `patch_embed.proj.weight` key or
//! takes it from the caller. Encoder keys under the prefix that this encoder has no place for
//! (more blocks, layer scale `ls1.gamma`, ...) are an error, never silently dropped; other
//! sub-models (heads, decoders, predictors) are ignored.

use std::collections::HashSet;
use std::path::Path;

use burn::module::Param;
use burn::nn::{LayerNorm, Linear};
use burn::prelude::*;
use safetensors::{Dtype, SafeTensors, tensor::TensorView};

use crate::Error;
use crate::vit::Vit;

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
    }
    norm_out("norm", &vit.norm, &mut out);
    out
}

/// Writes the encoder to `path` in safetensors (f32, official key names), atomically.
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
    let data = safetensors::serialize(views, None).map_err(|e| Error::file(path, e))?;
    crate::train::write_atomic(path, &data)
}

/// Reads official-layout tensors under `prefix` and maps them onto the encoder.
struct Source<'a> {
    st: SafeTensors<'a>,
    prefix: String,
    path: &'a Path,
    used: Vec<String>,
}

impl Source<'_> {
    fn get(&mut self, key: &str, shape: &[usize]) -> Result<Vec<f32>, Error> {
        let full = format!("{}{key}", self.prefix);
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
        self.used.push(full);
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

/// Prefixes tried, in order, when the caller names none.
const PREFIXES: [&str; 6] = [
    "",
    "encoder.",
    "student_encoder.",
    "model.encoder.",
    "module.encoder.",
    "backbone.",
];

/// Loads encoder weights from a safetensors file with official key names (see the module docs).
/// `prefix` selects the sub-model (e.g. `"teacher_encoder."`); `None` finds it.
/// Memory is bounded by the file's size and the encoder's own tensors: a header whose shapes or
/// offsets do not fit the file is refused, and each tensor's shape is checked before its data is
/// read.
pub fn load_encoder(mut vit: Vit, path: &Path, prefix: Option<&str>) -> Result<Vit, Error> {
    let bytes = std::fs::read(path).map_err(|e| Error::file(path, e))?;
    let st = SafeTensors::deserialize(&bytes)
        .map_err(|e| Error::file(path, format!("not a complete safetensors file: {e}")))?;
    let names: Vec<String> = st.names().into_iter().map(|s| s.to_string()).collect();
    let key = "patch_embed.proj.weight";
    let prefix = match prefix {
        Some(p) => p.to_string(),
        None => {
            let found: Vec<&str> = names.iter().filter_map(|n| n.strip_suffix(key)).collect();
            PREFIXES
                .iter()
                .find(|p| found.contains(p))
                .map(|p| p.to_string())
                .or_else(|| found.iter().min_by_key(|p| p.len()).map(|p| p.to_string()))
                .ok_or_else(|| {
                    Error::file(path, format!("no `{key}`: not a ViT encoder checkpoint"))
                })?
        }
    };
    let mut src = Source {
        st,
        prefix: prefix.clone(),
        path,
        used: Vec::new(),
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
    let pos_key = format!("{prefix}pos_embed");
    if names.contains(&pos_key) {
        let shape = vit.pos_embed.dims();
        let v = src.get("pos_embed", &shape)?;
        vit.pos_embed = Tensor::from_data(TensorData::new(v, shape), &vit.pos_embed.device());
    }
    let reg_key = format!("{prefix}register_tokens");
    match (vit.register_tokens.take(), names.contains(&reg_key)) {
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
    let blocks = std::mem::take(&mut vit.blocks);
    for (i, mut b) in blocks.into_iter().enumerate() {
        b.norm1 = load_norm(&mut src, &format!("blocks.{i}.norm1"), b.norm1)?;
        b.attn.qkv = load_linear(&mut src, &format!("blocks.{i}.attn.qkv"), b.attn.qkv)?;
        b.attn.proj = load_linear(&mut src, &format!("blocks.{i}.attn.proj"), b.attn.proj)?;
        b.norm2 = load_norm(&mut src, &format!("blocks.{i}.norm2"), b.norm2)?;
        b.mlp.fc1 = load_linear(&mut src, &format!("blocks.{i}.mlp.fc1"), b.mlp.fc1)?;
        b.mlp.fc2 = load_linear(&mut src, &format!("blocks.{i}.mlp.fc2"), b.mlp.fc2)?;
        vit.blocks.push(b);
    }
    vit.norm = load_norm(&mut src, "norm", vit.norm)?;
    let used: HashSet<&str> = src.used.iter().map(String::as_str).collect();
    if let Some(extra) = names
        .iter()
        .filter(|n| !used.contains(n.as_str()))
        .filter(|n| {
            n.strip_prefix(prefix.as_str()).is_some_and(|rest| {
                ["blocks.", "patch_embed.", "norm."]
                    .iter()
                    .any(|k| rest.starts_with(k))
            })
        })
        .min()
    {
        return Err(Error::file(
            path,
            format!("`{extra}` has no place in this encoder (deeper model or unsupported layer)"),
        ));
    }
    Ok(vit)
}
