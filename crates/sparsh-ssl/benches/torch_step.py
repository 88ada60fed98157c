"""PyTorch reference for the training-step benchmark (`cargo bench -p sparsh-ssl`), which runs it
right after burn's step of the same size.

The same step as benches/train_step.rs: 6×96×96 input, patch 8 (144 tokens), a ViT of MLP ratio 4
(tiny: width 192, 6 blocks, 3 heads; small: 384, 12, 6; base: 768, 12, 12), a linear pixel head,
MSE, Adam, batch 32, fp32 on the CPU.
    pip install torch numpy && python3 benches/torch_step.py [threads] [tiny|small|base] [warmup timed]
Prints seconds per step (median of `timed` steps, default 10, after `warmup`, default 3), images/s
and the mean CPU time per step (steadier than wall time on a shared machine).
"""
import sys
import time

import torch
import torch.nn as nn

threads = int(sys.argv[1]) if len(sys.argv) > 1 else 2
torch.set_num_threads(threads)
torch.manual_seed(0)

size = sys.argv[2] if len(sys.argv) > 2 else "tiny"
D, DEPTH, HEADS = {"tiny": (192, 6, 3), "small": (384, 12, 6), "base": (768, 12, 12)}[size]
WARMUP, TIMED = (int(sys.argv[3]), int(sys.argv[4])) if len(sys.argv) > 4 else (3, 10)
C, H, P, B = 6, 96, 8, 32
N = (H // P) ** 2


class Block(nn.Module):
    def __init__(self):
        super().__init__()
        self.norm1 = nn.LayerNorm(D, eps=1e-6)
        self.attn = nn.MultiheadAttention(D, HEADS, batch_first=True)
        self.norm2 = nn.LayerNorm(D, eps=1e-6)
        self.mlp = nn.Sequential(nn.Linear(D, 4 * D), nn.GELU(), nn.Linear(4 * D, D))

    def forward(self, x):
        y = self.norm1(x)
        x = x + self.attn(y, y, y, need_weights=False)[0]
        return x + self.mlp(self.norm2(x))


class Model(nn.Module):
    def __init__(self):
        super().__init__()
        self.patch = nn.Conv2d(C, D, P, P)
        self.pos = nn.Parameter(torch.zeros(1, N, D), requires_grad=False)
        self.blocks = nn.ModuleList([Block() for _ in range(DEPTH)])
        self.norm = nn.LayerNorm(D, eps=1e-6)
        self.head = nn.Linear(D, C * P * P)

    def forward(self, x):
        t = self.patch(x).flatten(2).transpose(1, 2) + self.pos
        for b in self.blocks:
            t = b(t)
        return self.head(self.norm(t))


def patchify(x):
    b = x.shape[0]
    g = H // P
    return x.reshape(b, C, g, P, g, P).permute(0, 2, 4, 1, 3, 5).reshape(b, g * g, C * P * P)


model = Model()
opt = torch.optim.Adam(model.parameters(), lr=1e-4)
x = torch.rand(B, C, H, H)
target = patchify(x)
times = []
cpu = 0.0
for i in range(WARMUP + TIMED):
    t0 = time.perf_counter()
    c0 = time.process_time()
    loss = ((model(x) - target) ** 2).mean()
    opt.zero_grad()
    loss.backward()
    opt.step()
    if i >= WARMUP:
        times.append(time.perf_counter() - t0)
        cpu += time.process_time() - c0
times.sort()
step = times[len(times) // 2]
print(
    f"torch {torch.__version__} {size} threads {threads}: {step:.3f} s/step, {B / step:.1f} images/s, "
    f"{cpu / TIMED:.3f} CPU s/step"
)
