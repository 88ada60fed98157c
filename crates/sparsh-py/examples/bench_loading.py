"""Items per second reading a generated dataset: sparsh.GeneratedFrames (decoding and the official
preprocessing in Rust) against the same items made in Python as the official loaders make them
(Pillow decode, NumPy background subtraction, turn, crop, Pillow resize), in the same run, and the
frames sparsh.simulated_frames makes without touching the disk.

    python bench_loading.py DATASET SCENE [--items N]
"""
import argparse
import json
import os
import time

import numpy as np
from PIL import Image

import sparsh


def official_item(root, rows, frames_of, i, size=(320, 240)):
    """One I_t ⊕ I_{t−5} item the way the official Python code makes it."""
    row = rows[i]
    bg = np.asarray(Image.open(os.path.join(root, row["background"])).convert("RGB"))
    out = []
    for o in (0, 5):
        frame = frames_of[row["sequence"]][max(row["frame_in_sequence"] - o, 0)]
        img = np.asarray(Image.open(os.path.join(root, "frames", f"{frame:06}.png")).convert("RGB"))
        diff = np.uint8(np.clip((img.astype(np.int32) - bg.astype(np.int32)) / 255.0 + 0.5, 0, 1) * 255.0)
        if diff.shape[0] < diff.shape[1]:
            diff = np.rot90(diff, k=-1)
        h, w, _ = diff.shape
        if h / w != 4 / 3:
            h2 = int(h / (4 / 3))
            diff = diff[int((h - h2) / 2) : int((h + h2) / 2)]
        small = Image.fromarray(np.ascontiguousarray(diff)).resize((size[1], size[0]), Image.BILINEAR)
        out.append(np.asarray(small, dtype=np.float32).transpose(2, 0, 1) / 255.0)
    return np.concatenate(out)


def rate(make, n):
    start = time.perf_counter()
    for i in range(n):
        make(i)
    return n / (time.perf_counter() - start)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("dataset")
    parser.add_argument("scene")
    parser.add_argument("--items", type=int, default=200)
    args = parser.parse_args()
    ours = sparsh.GeneratedFrames(args.dataset)
    n = min(args.items, len(ours))
    rows = ours.labels
    frames_of = {}
    for r in rows:
        frames_of.setdefault(r["sequence"], []).append(r["frame"])
    ours[0], official_item(args.dataset, rows, frames_of, 0)  # warm the file cache
    python = rate(lambda i: official_item(args.dataset, rows, frames_of, i), n)
    rust = rate(lambda i: ours[i], n)
    sim = iter(sparsh.simulated_frames(args.scene, 0))
    simulated = rate(lambda i: next(sim), min(n, sparsh.Scene(args.scene).sequence(0)["frames"]))
    print(json.dumps({"items": n, "python_official_items_per_s": round(python, 1), "generated_frames_items_per_s": round(rust, 1),
                      "ratio": round(rust / python, 2), "simulated_frames_items_per_s": round(simulated, 1)}))


if __name__ == "__main__":
    main()
