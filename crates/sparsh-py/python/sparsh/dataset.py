"""Frames with their labels, as the official Sparsh loaders give them: read from a dataset that
``sparsh generate`` wrote (:class:`GeneratedFrames`) or straight from the simulator
(:func:`simulated_frames`). Both give the same items, as NumPy arrays:

``image``
    float32 ``(3·len(offsets), height, width)``: the frames ``t − o`` for each ``o`` in
    ``offsets`` (default ``(0, 5)``: I_t ⊕ I_{t−5}), each preprocessed as the official code
    does (:func:`sparsh.preprocess`: minus the sequence's no-contact image, turned clockwise,
    the official 4:3 crop, resized to ``size``), concatenated on channels. An offset reaching
    before the sequence's first frame reads the first frame, as the official loaders clip it.
``force_n``, ``delta_force_n``
    float32 ``(3,)``: the total force [Fx, Fy, Fz] in N (Fz > 0 presses) and its change since
    frame t − 5 (clipped to the first frame, as the force/slip loader does).
``slip_cone``
    bool: the official slip label, ‖(Fx, Fy)‖ > ratio · Fz.
``contact_area_mm2``, ``sequence``, ``frame``
    float, int, int.
``fields`` (when ``fields`` names channels)
    ``{channel: float32 (ny, nx)}`` of ``p qx qy`` (kPa), ``ux uy uz`` (mm), ``contact slip``
    (0/1), on the scene's mechanics grid.

The full label row of ``labels.jsonl`` (pose, slip state, validity, markers...) is
``GeneratedFrames.labels[i]``, or the ``label`` of a simulator frame.
"""

from __future__ import annotations

import json
import os
from collections import deque
from typing import Any, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np

from ._native import Scene, SparshError, preprocess, read_fields, read_image

#: The ground-truth field channels, as named in ``fields/*.exr``.
FIELD_CHANNELS = ("p", "qx", "qy", "ux", "uy", "uz", "contact", "slip")


def _check_options(offsets: Sequence[int], size: Tuple[int, int], fields: Sequence[str]) -> None:
    if len(offsets) == 0 or any(int(o) != o or o < 0 for o in offsets):
        raise ValueError(f"offsets: {tuple(offsets)} must be one or more whole numbers ≥ 0")
    if len(size) != 2 or any(int(s) != s or s <= 0 for s in size):
        raise ValueError(f"size: {tuple(size)} must be (height, width) in pixels, both > 0")
    unknown = [f for f in fields if f not in FIELD_CHANNELS]
    if unknown:
        raise ValueError(f"fields: unknown channel {unknown[0]!r}; known: {' '.join(FIELD_CHANNELS)}")


def _item(
    images: List[np.ndarray],
    background: Optional[np.ndarray],
    size: Tuple[int, int],
    label: Dict[str, Any],
    fields: Optional[Dict[str, np.ndarray]],
) -> Dict[str, Any]:
    stacked = np.concatenate([preprocess(i, background, size) for i in images], axis=0)
    item: Dict[str, Any] = {
        "image": stacked,
        "force_n": np.asarray(label["force_n"], dtype=np.float32),
        "delta_force_n": np.asarray(label["delta_force_n"], dtype=np.float32),
        "slip_cone": bool(label["slip_cone"]),
        "contact_area_mm2": float(label["contact_area_mm2"]),
        "sequence": int(label["sequence"]),
        "frame": int(label["frame"]),
    }
    if fields is not None:
        item["fields"] = fields
    return item


class GeneratedFrames:
    """The frames of a dataset written by ``sparsh generate`` (or :func:`sparsh.generate`), one
    item per labelled frame (see the module docs for the items).

    ``root`` is the dataset directory; ``offsets`` the frames stacked on channels (``(0, 5)``:
    the official I_t ⊕ I_{t−5}); ``background=False`` skips the background subtraction;
    ``size`` is ``(height, width)`` after preprocessing (the official 320×240); ``fields`` the
    ground-truth channels to read with each frame; ``split`` keeps ``"train"`` or ``"test"``
    sequences only. Images are decoded in Rust; the object holds paths and label rows only, so it
    pickles into DataLoader workers.
    """

    def __init__(
        self,
        root: "os.PathLike[str] | str",
        *,
        offsets: Sequence[int] = (0, 5),
        background: bool = True,
        size: Tuple[int, int] = (320, 240),
        fields: Sequence[str] = (),
        split: Optional[str] = None,
    ) -> None:
        _check_options(offsets, size, fields)
        if split not in (None, "train", "test"):
            raise ValueError(f"split: {split!r} must be 'train', 'test' or None")
        self.root = os.fspath(root)
        labels_path = os.path.join(self.root, "labels.jsonl")
        if not os.path.isfile(labels_path):
            raise FileNotFoundError(
                f"{labels_path}: not found (is {self.root} a dataset written by `sparsh generate`, "
                "and is it complete?)"
            )
        rows = []
        with open(labels_path, encoding="utf-8") as f:
            for number, line in enumerate(f, start=1):
                try:
                    rows.append(json.loads(line))
                except json.JSONDecodeError as e:
                    raise SparshError(f"{labels_path}: line {number}: {e.msg}") from None
        # frame ids of every sequence in time order, for the offsets
        self._frames_of: Dict[int, List[int]] = {}
        for row in rows:
            self._frames_of.setdefault(row["sequence"], []).append(row["frame"])
        self.labels: List[Dict[str, Any]] = [r for r in rows if split is None or r["split"] == split]
        self.offsets = tuple(int(o) for o in offsets)
        self.background = background
        self.size = (int(size[0]), int(size[1]))
        self.fields = tuple(fields)

    def __len__(self) -> int:
        return len(self.labels)

    def __getitem__(self, index: int) -> Dict[str, Any]:
        if index < 0:
            index += len(self.labels)
        if not 0 <= index < len(self.labels):
            raise IndexError(f"frame {index} of a dataset of {len(self.labels)}")
        row = self.labels[index]
        frames = self._frames_of[row["sequence"]]
        k = row["frame_in_sequence"]
        images = [
            read_image(os.path.join(self.root, "frames", f"{frames[max(k - o, 0)]:06}.png"))
            for o in self.offsets
        ]
        bg = read_image(os.path.join(self.root, row["background"])) if self.background else None
        fields = None
        if self.fields:
            path = os.path.join(self.root, "fields", f"{row['frame']:06}.exr")
            stored = read_fields(path)
            missing = [f for f in self.fields if f not in stored]
            if missing:
                raise SparshError(f"{path}: no channel {missing[0]!r} (the scene's [output] fields)")
            fields = {f: stored[f] for f in self.fields}
        return _item(images, bg, self.size, row, fields)


def simulated_frames(
    scene: "Scene | os.PathLike[str] | str",
    sequence: int = 0,
    *,
    offsets: Sequence[int] = (0, 5),
    background: bool = True,
    size: Tuple[int, int] = (320, 240),
    fields: Sequence[str] = (),
    threads: Optional[int] = None,
) -> Iterator[Dict[str, Any]]:
    """The items of one sequence, simulated as they are asked for (no files written): the same
    items :class:`GeneratedFrames` reads from the dataset ``sparsh generate`` writes of
    ``scene``, the ``fields`` as float32 as the EXR files store them."""
    _check_options(offsets, size, fields)
    if not isinstance(scene, Scene):
        scene = Scene(scene)
    sim = scene.simulate(sequence, threads=threads)
    bg = sim.background if background else None
    first: Optional[np.ndarray] = None
    recent: deque = deque(maxlen=max(offsets) + 1)
    for frame in sim:
        image = frame["image"]
        if first is None:
            first = image
        recent.append(image)
        images = [recent[-1 - o] if o < len(recent) else first for o in offsets]
        chosen = None
        if fields:
            chosen = {f: frame["fields"][f].astype(np.float32) for f in fields}
        yield _item(images, bg, size, frame["label"], chosen)
