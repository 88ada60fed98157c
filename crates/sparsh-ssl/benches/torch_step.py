"""PyTorch reference for the training-step benchmarks: `cargo bench -p sparsh-ssl --bench
train_step` runs it right after burn's step of the same size, and `scripts/gpu-check.sh` beside
`sparsh bench-train --reference` on the same GPU.

The same step as `sparsh_ssl::bench::ReferenceStep`: a 6-channel input, a ViT of MLP ratio 4
(tiny: width 192, 6 blocks, 3 heads; small: 384, 12, 6; base: 768, 12, 12), a linear pixel head,
MSE against the patchified input, Adam at lr 1e-4. Defaults: 96×96, patch 8 (144 tokens),
batch 32, fp32 on the CPU.

    pip install torch && python3 benches/torch_step.py [threads] [tiny|small|base] [warmup timed]
    python3 benches/torch_step.py --device cuda --precision bf16 --input 320x240 --patch 16 \
        --batch 64 0 base 3 10

Prints seconds per step (median of `timed` steps, default 10, after `warmup`, default 3), images/s
and the mean CPU time per step (steadier than wall time on a shared machine); `--json FILE` also
writes them. Precisions: fp32 (full fp32 matrix products), tf32 (fp32 tensors, TensorFloat-32
matrix products on CUDA), bf16 (autocast to bfloat16, fp32 master weights). On CUDA each step
ends with a synchronisation, as burn's ends with a read-back.
"""
import argparse
import json
import os
import time

import torch
import torch.nn as nn

SIZES = {"tiny": (192, 6, 3), "small": (384, 12, 6), "base": (768, 12, 12)}

parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
parser.add_argument("threads", nargs="?", type=int, default=2, help="CPU threads (0: torch's default)")
parser.add_argument("size", nargs="?", default="tiny", choices=SIZES)
parser.add_argument("warmup", nargs="?", type=int, default=3)
parser.add_argument("timed", nargs="?", type=int, default=10)
parser.add_argument("--device", default="cpu", help="cpu or cuda")
parser.add_argument("--precision", default="fp32", choices=["fp32", "tf32", "bf16"])
parser.add_argument("--input", default="96x96", help="HEIGHTxWIDTH in pixels")
parser.add_argument("--patch", type=int, default=8)
parser.add_argument("--batch", type=int, default=32)
parser.add_argument("--json", help="also write the result here")
args = parser.parse_args()

if args.threads > 0:
    torch.set_num_threads(args.threads)
torch.manual_seed(0)
device = torch.device(args.device)
cuda = device.type == "cuda"
if cuda:
    tf32 = args.precision == "tf32"
    torch.backends.cuda.matmul.allow_tf32 = tf32
    torch.backends.cudnn.allow_tf32 = tf32

D, DEPTH, HEADS = SIZES[args.size]
C, P, B = 6, args.patch, args.batch
H, W = (int(v) for v in args.input.lower().split("x"))
assert H % P == 0 and W % P == 0, f"--input {args.input}: not a multiple of the patch {P}"
N = (H // P) * (W // P)


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
    gh, gw = H // P, W // P
    return x.reshape(b, C, gh, P, gw, P).permute(0, 2, 4, 1, 3, 5).reshape(b, gh * gw, C * P * P)


model = Model().to(device)
opt = torch.optim.Adam(model.parameters(), lr=1e-4)
x = torch.rand(B, C, H, W, device=device)
target = patchify(x)
autocast = torch.autocast(device.type, dtype=torch.bfloat16, enabled=args.precision == "bf16")
times = []
cpu = 0.0
for i in range(args.warmup + args.timed):
    t0 = time.perf_counter()
    c0 = time.process_time()
    with autocast:
        loss = ((model(x).float() - target) ** 2).mean()
    opt.zero_grad()
    loss.backward()
    opt.step()
    if cuda:
        torch.cuda.synchronize()
    if i >= args.warmup:
        times.append(time.perf_counter() - t0)
        cpu += time.process_time() - c0
times.sort()
step = times[len(times) // 2]
where = f"{args.device} {args.precision}" if cuda else f"threads {args.threads}"
print(
    f"torch {torch.__version__} {args.size} {where}: {step:.3f} s/step, {B / step:.1f} images/s, "
    f"{cpu / args.timed:.3f} CPU s/step"
)
if args.json:
    result = {
        "torch": torch.__version__,
        "size": args.size,
        "device": torch.cuda.get_device_name(device) if cuda else "cpu",
        "precision": args.precision,
        "input": f"{H}x{W}",
        "patch": P,
        "batch": B,
        "seconds_per_step": step,
        "images_per_second": B / step,
        "cpu_seconds_per_step": cpu / args.timed,
    }
    with open(args.json + ".tmp", "w") as f:
        json.dump(result, f, indent=1)
    os.replace(args.json + ".tmp", args.json)
