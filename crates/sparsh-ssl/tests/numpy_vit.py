"""Independent NumPy forward pass of the Sparsh ViT encoder, for the parity tests.

Reads a safetensors file holding the encoder under the official PyTorch key names (under
PREFIX, default none) and a safetensors file with one `input` tensor
[batch, frames, channels, height, width]; prints JSON with the normalized output tokens
(registers first) and, when the file stores a `pos_embed` table, its largest deviation from the
official sinusoidal formula (`numpy_pos_embed.sinusoidal`). A file with the official
`pos_embed.frequency_bands` instead gets its table from those bands. Blocks follow the official
`Block.forward` (tactile_ssl/model/layers/block.py), with layer scale `ls1`/`ls2` when present.

usage: python3 numpy_vit.py WEIGHTS INPUT NUM_HEADS [PREFIX]
"""
import json
import math
import struct
import sys

import numpy as np

from numpy_pos_embed import sinusoidal


def read_safetensors(path):
    with open(path, "rb") as f:
        data = f.read()
    n = struct.unpack("<Q", data[:8])[0]
    header = json.loads(data[8 : 8 + n])
    base = 8 + n
    out = {}
    for key, info in header.items():
        if key == "__metadata__":
            continue
        assert info["dtype"] == "F32", info["dtype"]
        start, end = info["data_offsets"]
        raw = np.frombuffer(data[base + start : base + end], dtype="<f4")
        out[key] = raw.reshape(info["shape"]).astype(np.float64)
    return out


def layer_norm(x, w, b, eps=1e-6):
    m = x.mean(-1, keepdims=True)
    v = ((x - m) ** 2).mean(-1, keepdims=True)
    return (x - m) / np.sqrt(v + eps) * w + b


_erf = np.vectorize(math.erf)


def gelu(x):
    return 0.5 * x * (1.0 + _erf(x / math.sqrt(2.0)))


def main():
    prefix = sys.argv[4] if len(sys.argv) > 4 else ""
    weights = {
        k[len(prefix) :]: v for k, v in read_safetensors(sys.argv[1]).items() if k.startswith(prefix)
    }
    x = read_safetensors(sys.argv[2])["input"]
    heads = int(sys.argv[3])
    pw = weights["patch_embed.proj.weight"]
    if pw.ndim == 4:
        pw = pw[:, :, None]
    dim, _, t, p, _ = pw.shape
    b, frames, _, height, width = x.shape
    gt, gh, gw = frames // t, height // p, width // p
    tokens = []
    for it in range(gt):
        for r in range(gh):
            for c in range(gw):
                patch = x[:, it * t : (it + 1) * t, :, r * p : (r + 1) * p, c * p : (c + 1) * p]
                patch = patch.transpose(0, 2, 1, 3, 4)  # conv3d: [B, C, t, p, p]
                tokens.append(np.einsum("bctyx,dctyx->bd", patch, pw))
    h = np.stack(tokens, 1) + weights["patch_embed.proj.bias"]
    grid = [gt, gh, gw] if frames > 1 else [gh, gw]
    formula = sinusoidal(dim, grid, weights.get("pos_embed.frequency_bands"))
    if "pos_embed" in weights:
        pos_dev = float(np.abs(weights["pos_embed"][0] - formula).max())
        h = h + weights["pos_embed"]
    else:
        pos_dev = None
        h = h + formula
    if "register_tokens" in weights:
        reg = weights["register_tokens"]
        h = np.concatenate([np.broadcast_to(reg, (b,) + reg.shape[1:]), h], 1)
    i = 0
    while f"blocks.{i}.norm1.weight" in weights:
        w = lambda k: weights[f"blocks.{i}.{k}"]
        y = layer_norm(h, w("norm1.weight"), w("norm1.bias"))
        qkv = y @ w("attn.qkv.weight").T + w("attn.qkv.bias")
        n, hd = h.shape[1], dim // heads
        qkv = qkv.reshape(b, n, 3, heads, hd).transpose(2, 0, 3, 1, 4)
        q, k, v = qkv[0], qkv[1], qkv[2]
        a = q @ k.transpose(0, 1, 3, 2) / math.sqrt(hd)
        a = np.exp(a - a.max(-1, keepdims=True))
        a = a / a.sum(-1, keepdims=True)
        o = (a @ v).transpose(0, 2, 1, 3).reshape(b, n, dim)
        ls1 = weights.get(f"blocks.{i}.ls1.gamma", 1.0)
        ls2 = weights.get(f"blocks.{i}.ls2.gamma", 1.0)
        h = h + ls1 * (o @ w("attn.proj.weight").T + w("attn.proj.bias"))
        y = layer_norm(h, w("norm2.weight"), w("norm2.bias"))
        y = gelu(y @ w("mlp.fc1.weight").T + w("mlp.fc1.bias"))
        h = h + ls2 * (y @ w("mlp.fc2.weight").T + w("mlp.fc2.bias"))
        i += 1
    h = layer_norm(h, weights["norm.weight"], weights["norm.bias"])
    json.dump({"shape": list(h.shape), "values": h.ravel().tolist(), "pos_dev": pos_dev}, sys.stdout)


if __name__ == "__main__":
    main()
