"""Independent NumPy references of the pretraining objectives and schedules, for the parity test
`numpy_losses.rs`. Every formula is written from the papers and the official PyTorch code named
next to it (float64 throughout).

Reads one JSON object on stdin: `case` names the reference, the other fields are its inputs
(arrays as {"shape": [...], "data": [...]}, row-major). Prints a JSON object of results.

usage: python3 numpy_losses.py < case.json
"""
import json
import math
import sys

import numpy as np


def array(v):
    return np.asarray(v["data"], dtype=np.float64).reshape(v["shape"])


def log_softmax(x):
    m = x.max(axis=-1, keepdims=True)
    return x - m - np.log(np.exp(x - m).sum(axis=-1, keepdims=True))


def softmax(x):
    return np.exp(log_softmax(x))


# --- MAE: He et al. 2022, official `MAEModule.compute_loss` (tactile_ssl/algorithm/mae.py) ---
def mae_loss(pred, target, mask, norm_pix_loss):
    if norm_pix_loss:
        mean = target.mean(axis=-1, keepdims=True)
        var = target.var(axis=-1, ddof=1, keepdims=True)  # torch.var: unbiased
        target = (target - mean) / (var + 1.0e-6) ** 0.5
    loss = ((pred - target) ** 2).mean(axis=-1)  # [N, L], mean loss per patch
    return (loss * mask).sum() / mask.sum()  # mean loss on removed patches


# --- DINO: Caron et al. 2021, Algorithm 1 and `DINOLoss` of facebookresearch/dino ---
def dino(case):
    b = case["batch"]
    t = array(case["teacher"])  # [n_global * b, K] teacher head outputs, view by view
    s = array(case["student"])  # [n_views * b, K] student head outputs, global views first
    c = array(case["center"])  # [1, K]
    tt, ts, m = case["teacher_temp"], case["student_temp"], case["center_momentum"]
    teacher_out = softmax((t - c) / tt)
    student_out = s / ts
    n_global, n_views = t.shape[0] // b, s.shape[0] // b
    total, n_loss_terms = 0.0, 0
    for iq in range(n_global):
        q = teacher_out[iq * b : (iq + 1) * b]
        for v in range(n_views):
            if v == iq:
                continue  # the same view for student and teacher is skipped
            loss = np.sum(-q * log_softmax(student_out[v * b : (v + 1) * b]), axis=-1)
            total += loss.mean()
            n_loss_terms += 1
    total /= n_loss_terms
    # update_center: batch_center = sum(teacher_output) / len(teacher_output)
    batch_center = t.sum(axis=0, keepdims=True) / len(t)
    center = c * m + batch_center * (1 - m)
    # the project's batch-standardized teacher targets: each prototype's score standardized
    # over the rows, (t - mean) / sqrt(var + 1e-8), variance biased
    std_t = (t - t.mean(axis=0)) / np.sqrt(t.var(axis=0) + 1e-8)
    return {
        "loss": total,
        "center": center.ravel().tolist(),
        "teacher_batch": softmax(std_t / tt).ravel().tolist(),
    }


# --- iBOT masked-patch term: Zhou et al. 2022 eq. 2, DINOv2 `iBOTPatchLoss.forward_masked` ---
def ibot(case):
    t = array(case["teacher"])  # teacher patch scores [masked tokens of all images, K]
    s = array(case["student"])  # the student's patch scores at the same tokens
    masks = np.asarray(case["masks"], dtype=bool)  # [images, tokens of a view]
    # the project's teacher targets for iBOT: scores standardized over the masked tokens
    t = softmax((t - t.mean(axis=0)) / np.sqrt(t.var(axis=0) + 1e-8) / case["teacher_temp"])
    loss = np.sum(t * log_softmax(s / case["student_temp"]), axis=-1)
    masks_weight = (1 / np.clip(masks.sum(-1), 1.0, None))[:, None].repeat(masks.shape[1], 1)[masks]
    return {"loss": -(loss * masks_weight).sum() / masks.shape[0]}


# --- KoLeo: Sablayrolles et al. 2019, DINOv2 `KoLeoLoss` ---
def koleo(case):
    x = array(case["x"])
    eps = 1e-8
    x = x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), eps)  # F.normalize
    dots = x @ x.T
    np.fill_diagonal(dots, -1)
    nearest = dots.argmax(axis=1)
    distances = np.linalg.norm(x - x[nearest] + eps, axis=-1)  # nn.PairwiseDistance(2, eps)
    return {"loss": -np.log(distances + eps).mean()}


# --- I-JEPA (Assran et al. 2023) / V-JEPA (Bardes et al. 2024), official forward / loss_fn ---
def layer_norm(h):
    mean = h.mean(axis=-1, keepdims=True)
    var = h.var(axis=-1, keepdims=True)  # F.layer_norm: biased, eps 1e-5
    return (h - mean) / np.sqrt(var + 1e-5)


def smooth_l1(pred, target, beta=1.0):
    d = np.abs(pred - target)
    return np.where(d < beta, 0.5 * d**2 / beta, d - 0.5 * beta).mean()


def jepa(case):
    preds = [array(p) for p in case["preds"]]
    targets = [layer_norm(array(h)) for h in case["features"]]
    if case["loss"] == "smooth_l1":
        # I-JEPA: F.smooth_l1_loss over all predictions, one set
        loss = sum(smooth_l1(z, h) for z, h in zip(preds, targets)) / len(preds)
    else:
        # V-JEPA loss_fn: sum over mask sets of mean(|z - h| ** p) / p, over the number of sets
        p = 1.0
        loss = sum(np.mean(np.abs(z - h) ** p) / p for z, h in zip(preds, targets)) / len(preds)
    return {"loss": loss, "targets": [t.ravel().tolist() for t in targets]}


# --- EMA teacher: official `update_moving_average` (tactile_ssl/utils/ema.py) ---
def ema(case):
    beta = case["momentum"]
    out = []
    for old, new in zip(case["target"], case["source"]):
        old, new = np.asarray(old, dtype=np.float64), np.asarray(new, dtype=np.float64)
        out.append((old * beta + (1.0 - beta) * new).tolist())
    return {"params": out}


# --- schedules ---
def schedules(case):
    steps = case["steps"]
    total = case["total"]
    # momentum: the official generator start + i (end - start) / total, one value per step
    m0, m1 = case["ema"]
    momentum = [m0 + i * (m1 - m0) / total for i in steps]
    # teacher temperature: the official teacher_temp_schedule, i > warm-up → final value
    t0, t1 = case["teacher_temp"]
    w = case["teacher_temp_warmup"]
    temp = [t1 if i > w else t0 + i * (t1 - t0) / w for i in steps]
    # learning rate: the official WarmupCosineScheduler (start_lr 0); torch's LRScheduler
    # counts one step at construction, so the optimizer step i runs at _step_count = i + 1
    base, final, warm = case["lr"], case["min_lr"], case["warmup"]
    t_max = total - warm
    lr = []
    for i in steps:
        count = i + 1
        if count < warm:
            lr.append(0.0 + float(count) / float(max(1, warm)) * (base - 0.0))
        else:
            progress = float(count - warm) / float(max(1, t_max))
            lr.append(
                max(final, final + (base - final) * 0.5 * (1.0 + math.cos(math.pi * progress)))
            )
    return {"momentum": momentum, "teacher_temp": temp, "lr": lr}


def main():
    case = json.load(sys.stdin)
    name = case["case"]
    if name == "mae":
        pred, target = array(case["pred"]), array(case["target"])
        mask = np.asarray(case["mask"], dtype=np.float64)
        out = {
            "plain": mae_loss(pred, target, mask, False),
            "norm_pix": mae_loss(pred, target, mask, True),
        }
    else:
        out = {"dino": dino, "ibot": ibot, "koleo": koleo, "jepa": jepa, "ema": ema,
               "schedules": schedules}[name](case)
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
