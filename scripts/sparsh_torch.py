"""An encoder trained by sparsh, in PyTorch, in the official Sparsh model layout.

`sparsh pretrain` writes `encoder.safetensors` under the official key names
(`tactile_ssl/model/vision_transformer.py`, `VisionTransformer.state_dict()`: `patch_embed.proj`,
`pos_embed`, `register_tokens`, `blocks.i.{norm1, attn.qkv, attn.proj, ls1.gamma, norm2, mlp.fc1,
mlp.fc2, ls2.gamma}`, `norm`). `load_encoder` builds a `torch.nn.Module` with exactly that
layout from the file's shapes and loads it with `strict=True`, so the weights drop into PyTorch
code (a probe, a fine-tune, the official downstream heads) unchanged. Its forward pass is the
official `Block.forward` (pre-norm attention and MLP, exact GELU, layer norm ε = 1e-6, layer
scale where the file has it): tokens `[batch, registers + patches, width]`, registers first,
after the final norm — what `sparsh embed --pool none` computes.

    pip install torch numpy
    python3 scripts/sparsh_torch.py run/encoder.safetensors INPUT.safetensors --out tokens.npy

`INPUT` holds one f32 tensor `input` `[batch, frames, channels, height, width]` (safetensors or
.npy), already preprocessed as the recipe feeds the encoder. In Python:

    from sparsh_torch import load_encoder        # with scripts/ on sys.path
    encoder = load_encoder("run/encoder.safetensors")
    tokens = encoder(x)                            # x: [B, F, C, H, W]
"""
import argparse
import json
import math
import os
import struct
import sys

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn


def read_safetensors(path):
    """Every tensor of a safetensors file as float32 torch tensors, and its metadata."""
    with open(path, "rb") as f:
        data = f.read()
    n = struct.unpack("<Q", data[:8])[0]
    header = json.loads(data[8 : 8 + n])
    metadata = header.pop("__metadata__", {}) or {}
    out = {}
    for key, info in header.items():
        if info["dtype"] != "F32":
            sys.exit(f"{path}: {key}: dtype {info['dtype']}, expected F32")
        start, end = info["data_offsets"]
        raw = np.frombuffer(data[8 + n + start : 8 + n + end], dtype="<f4")
        out[key] = torch.from_numpy(raw.reshape(info["shape"]).copy())
    return out, metadata


class PatchEmbed(nn.Module):
    """Non-overlapping patches (a tubelet of `t` frames for clips) projected to the width."""

    def __init__(self, channels, width, patch, tubelet):
        super().__init__()
        self.tubelet = tubelet
        if tubelet == 1:
            self.proj = nn.Conv2d(channels, width, patch, patch)
        else:
            kernel = (tubelet, patch, patch)
            self.proj = nn.Conv3d(channels, width, kernel, kernel)

    def forward(self, x):
        b, frames = x.shape[:2]
        if self.tubelet == 1:
            # each frame's patches in turn (frames > 1 without tubelets: frame-major order)
            t = self.proj(x.flatten(0, 1)).flatten(2).transpose(1, 2)
            return t.reshape(b, frames * t.shape[1], t.shape[2])
        return self.proj(x.transpose(1, 2)).flatten(2).transpose(1, 2)


class LayerScale(nn.Module):
    def __init__(self, width):
        super().__init__()
        self.gamma = nn.Parameter(torch.ones(width))

    def forward(self, x):
        return x * self.gamma


class Attention(nn.Module):
    def __init__(self, width, heads):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(width, 3 * width)
        self.proj = nn.Linear(width, width)

    def forward(self, x):
        b, n, d = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        o = F.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2])
        return self.proj(o.transpose(1, 2).reshape(b, n, d))


class Mlp(nn.Module):
    def __init__(self, width, hidden):
        super().__init__()
        self.fc1 = nn.Linear(width, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, width)

    def forward(self, x):
        return self.fc2(self.act(self.fc1(x)))


class Block(nn.Module):
    def __init__(self, width, heads, hidden, layer_scale):
        super().__init__()
        self.norm1 = nn.LayerNorm(width, eps=1e-6)
        self.attn = Attention(width, heads)
        self.ls1 = LayerScale(width) if layer_scale else nn.Identity()
        self.norm2 = nn.LayerNorm(width, eps=1e-6)
        self.mlp = Mlp(width, hidden)
        self.ls2 = LayerScale(width) if layer_scale else nn.Identity()

    def forward(self, x):
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


class VisionTransformer(nn.Module):
    """The encoder: patch embedding + the stored position table, registers, blocks, final norm."""

    def __init__(self, channels, width, patch, tubelet, tokens, depth, heads, hidden,
                 registers, layer_scale):
        super().__init__()
        self.patch_embed = PatchEmbed(channels, width, patch, tubelet)
        self.pos_embed = nn.Parameter(torch.zeros(1, tokens, width), requires_grad=False)
        if registers:
            self.register_tokens = nn.Parameter(torch.zeros(1, registers, width))
        else:
            self.register_tokens = None
        self.blocks = nn.ModuleList(
            [Block(width, heads, hidden, layer_scale) for _ in range(depth)]
        )
        self.norm = nn.LayerNorm(width, eps=1e-6)

    def forward(self, x):
        h = self.patch_embed(x)
        if h.shape[1] != self.pos_embed.shape[1]:
            raise ValueError(
                f"input gives {h.shape[1]} tokens; the stored position table has "
                f"{self.pos_embed.shape[1]} (the encoder's input size and frames)"
            )
        h = h + self.pos_embed
        if self.register_tokens is not None:
            h = torch.cat([self.register_tokens.expand(h.shape[0], -1, -1), h], 1)
        for block in self.blocks:
            h = block(h)
        return self.norm(h)


def load_encoder(path, heads=None, prefix=""):
    """The encoder of `path` (keys under `prefix`), built from its shapes and loaded strictly.
    `heads` defaults to width / 64 (ViT-tiny 3, small 6, base 12, as the official sizes)."""
    tensors, _ = read_safetensors(path)
    state = {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}
    if "patch_embed.proj.weight" not in state:
        sys.exit(f"{path}: no `{prefix}patch_embed.proj.weight`: not an encoder under that prefix")
    if "pos_embed" not in state:
        sys.exit(
            f"{path}: no `{prefix}pos_embed` table (an official checkpoint with "
            "`pos_embed.frequency_bands`: load it with the official code)"
        )
    w = state["patch_embed.proj.weight"]
    width, channels, patch = w.shape[0], w.shape[1], w.shape[-1]
    tubelet = w.shape[2] if w.ndim == 5 else 1
    depth = 0
    while f"blocks.{depth}.norm1.weight" in state:
        depth += 1
    heads = heads or width // 64
    if width % heads:
        sys.exit(f"{path}: width {width} does not split into {heads} heads (give --heads)")
    model = VisionTransformer(
        channels=channels,
        width=width,
        patch=patch,
        tubelet=tubelet,
        tokens=state["pos_embed"].shape[1],
        depth=depth,
        heads=heads,
        hidden=state["blocks.0.mlp.fc1.weight"].shape[0],
        registers=state["register_tokens"].shape[1] if "register_tokens" in state else 0,
        layer_scale="blocks.0.ls1.gamma" in state,
    )
    model.load_state_dict(state, strict=True)
    return model.eval()


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("weights", help="encoder.safetensors written by sparsh")
    parser.add_argument("input", help="`input` [B, F, C, H, W] as safetensors, or a .npy")
    parser.add_argument("--heads", type=int, help="attention heads (default: width / 64)")
    parser.add_argument("--prefix", default="", help="key prefix of the encoder in the file")
    parser.add_argument("--out", help="write the tokens here (.npy); else JSON on stdout")
    args = parser.parse_args()
    torch.backends.cuda.matmul.allow_tf32 = False
    model = load_encoder(args.weights, args.heads, args.prefix)
    if args.input.endswith(".npy"):
        x = torch.from_numpy(np.load(args.input).astype(np.float32))
    else:
        x = read_safetensors(args.input)[0]["input"]
    with torch.no_grad():
        tokens = model(x)
    if args.out:
        tmp = args.out + ".tmp.npy"
        np.save(tmp, tokens.numpy())
        os.replace(tmp, args.out)
    else:
        json.dump({"shape": list(tokens.shape), "values": tokens.ravel().tolist()}, sys.stdout)


if __name__ == "__main__":
    main()
