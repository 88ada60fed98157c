"""Independent NumPy transcriptions of the official Sparsh position embeddings, for the tests.

- `sinusoidal`: `SinusoidalEmbed` of facebookresearch/sparsh
  (tactile_ssl/model/layers/patch_embed.py, `logspace=False`) with `create_ndgrid`
  (tactile_ssl/utils/__init__.py, `normalized_coords=False`, "ij" indexing, first axis slowest).
- `bicubic` / `trilinear`: PyTorch's `F.interpolate(..., align_corners=False, antialias=False)`
  as used by `VisionTransformer.interpolate_pos_encoding` (tactile_ssl/model/vision_transformer.py),
  written point by point after aten/src/ATen/native/UpSample.h.

usage: python3 numpy_pos_embed.py < request.json
  {"op": "sinusoidal", "dim": D, "grid": [..], "bands": [[..], ..] or null}
  {"op": "bicubic" | "trilinear", "dim": D, "src": [..], "dst": [..], "table": [..]}
prints {"values": [...]} (row-major tokens × dim).
"""
import json
import math
import sys

import numpy as np


def default_bands(dim, axes):
    num_bands = math.ceil(dim / (2 * axes))
    bands = np.stack([np.linspace(0, 1.0, num_bands + 1)[:-1] for _ in range(axes)], 0)
    return 10000.0 ** -bands


def sinusoidal(dim, grid, bands=None):
    """[prod(grid), dim] table; `bands` [axes, B] (the checkpoint buffer) or the default."""
    bands = default_bands(dim, len(grid)) if bands is None else np.asarray(bands, np.float64)
    axes = [np.arange(0, r, dtype=np.float64) for r in grid]
    coords = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(grid))
    features = coords[..., None] * bands  # [N, axes, B]
    encoded = np.concatenate([np.sin(features), np.cos(features)], -1)  # [N, axes, 2B]
    return encoded.reshape(coords.shape[0], -1)[:, :dim]


def _cubic_weights(t, a=-0.75):
    def near(x):
        return ((a + 2) * x - (a + 3)) * x * x + 1

    def far(x):
        return ((a * x - 5 * a) * x + 8 * a) * x - 4 * a

    return [far(t + 1), near(t), near(1 - t), far(2 - t)]


def bicubic(table, src, dst):
    """upsample_bicubic2d: table [H, W, D] → [h, w, D]."""
    (hi, wi), (ho, wo) = src, dst
    out = np.zeros((ho, wo, table.shape[-1]))
    for y in range(ho):
        ry = hi / ho * (y + 0.5) - 0.5
        y0 = math.floor(ry)
        wy = _cubic_weights(ry - y0)
        for x in range(wo):
            rx = wi / wo * (x + 0.5) - 0.5
            x0 = math.floor(rx)
            wx = _cubic_weights(rx - x0)
            acc = 0.0
            for j in range(4):
                yy = min(max(y0 - 1 + j, 0), hi - 1)
                for k in range(4):
                    xx = min(max(x0 - 1 + k, 0), wi - 1)
                    acc = acc + wy[j] * wx[k] * table[yy, xx]
            out[y, x] = acc
    return out


def _linear_taps(size_in, size_out, i):
    if size_in == size_out:
        return [(i, 1.0)]
    real = max(size_in / size_out * (i + 0.5) - 0.5, 0.0)
    i0 = min(int(real), size_in - 1)
    i1 = i0 + (1 if i0 < size_in - 1 else 0)
    l1 = min(max(real - i0, 0.0), 1.0)
    return [(i0, 1.0 - l1), (i1, l1)]


def trilinear(table, src, dst):
    """upsample_trilinear3d: table [T, H, W, D] → [t, h, w, D]."""
    out = np.zeros(tuple(dst) + (table.shape[-1],))
    for t in range(dst[0]):
        for y in range(dst[1]):
            for x in range(dst[2]):
                acc = 0.0
                for it, wt in _linear_taps(src[0], dst[0], t):
                    for iy, wy in _linear_taps(src[1], dst[1], y):
                        for ix, wx in _linear_taps(src[2], dst[2], x):
                            acc = acc + wt * wy * wx * table[it, iy, ix]
                out[t, y, x] = acc
    return out


def main():
    req = json.load(sys.stdin)
    dim = req["dim"]
    if req["op"] == "sinusoidal":
        values = sinusoidal(dim, req["grid"], req.get("bands"))
    else:
        src, dst = req["src"], req["dst"]
        table = np.asarray(req["table"], np.float64).reshape(tuple(src) + (dim,))
        values = (bicubic if req["op"] == "bicubic" else trilinear)(table, src, dst)
    json.dump({"values": np.asarray(values).ravel().tolist()}, sys.stdout)


if __name__ == "__main__":
    main()
