"""PyTorch reference for the encoder forward benchmark (`cargo bench -p sparsh-ssl --bench embed`).

The same encoder as benches/embed.rs and sparsh_ssl::vit::Vit: a 6-channel input (I_t ⊕ I_{t−5})
cut into patches by a strided Conv2d, fixed position embeddings added, pre-norm blocks (LayerNorm
eps 1e-6, fused qkv Linear, scaled dot-product attention, GELU MLP of ratio 4), a final LayerNorm,
then the mean of the patch tokens. fp32, torch.inference_mode, on the CPU.
    pip install torch numpy && python3 benches/torch_embed.py SIZE HEIGHT WIDTH PATCH THREADS BATCH
SIZE: tiny (width 192, 12 blocks, 3 heads), small (384, 12, 6) or tiny6 (192, 6, 3, the CPU
recipes' encoder). Prints `frames/s F` (the median of the timed passes after a warm-up; at
least 3 passes and 1 s).
"""
import sys
import time

import torch
import torch.nn as nn
import torch.nn.functional as F

size, H, W, P, threads, B = sys.argv[1], *map(int, sys.argv[2:7])
torch.set_num_threads(threads)
torch.manual_seed(0)
D, DEPTH, HEADS = {"tiny": (192, 12, 3), "small": (384, 12, 6), "tiny6": (192, 6, 3)}[size]
C = 6
N = (H // P) * (W // P)


class Block(nn.Module):
    def __init__(self):
        super().__init__()
        self.norm1 = nn.LayerNorm(D, eps=1e-6)
        self.qkv = nn.Linear(D, 3 * D)
        self.proj = nn.Linear(D, D)
        self.norm2 = nn.LayerNorm(D, eps=1e-6)
        self.mlp = nn.Sequential(nn.Linear(D, 4 * D), nn.GELU(), nn.Linear(4 * D, D))

    def forward(self, x):
        b, n, _ = x.shape
        q, k, v = self.qkv(self.norm1(x)).reshape(b, n, 3, HEADS, D // HEADS).permute(2, 0, 3, 1, 4)
        a = F.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(b, n, D)
        x = x + self.proj(a)
        return x + self.mlp(self.norm2(x))


class Encoder(nn.Module):
    def __init__(self):
        super().__init__()
        self.patch = nn.Conv2d(C, D, P, P)
        self.pos = nn.Parameter(torch.zeros(1, N, D), requires_grad=False)
        self.blocks = nn.ModuleList([Block() for _ in range(DEPTH)])
        self.norm = nn.LayerNorm(D, eps=1e-6)

    def forward(self, x):
        t = self.patch(x).flatten(2).transpose(1, 2) + self.pos
        for b in self.blocks:
            t = b(t)
        return self.norm(t).mean(1)


model = Encoder().eval()
x = torch.rand(B, C, H, W)
times = []
with torch.inference_mode():
    model(x)
    start = time.perf_counter()
    while len(times) < 3 or (time.perf_counter() - start < 1.0 and len(times) < 50):
        t0 = time.perf_counter()
        model(x)
        times.append(time.perf_counter() - t0)
times.sort()
print(f"torch {torch.__version__} frames/s {B / times[len(times) // 2]:.2f}")
