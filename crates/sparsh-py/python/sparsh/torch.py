"""The datasets of :mod:`sparsh.dataset` for PyTorch: :class:`GeneratedDataset` (map-style, over
a dataset on disk) and :class:`SimulatedDataset` (iterable, simulating as it goes, its sequences
split among DataLoader workers). Items are those of :mod:`sparsh.dataset` with the arrays as
tensors, so the default ``collate_fn`` batches them.

Both are safe in DataLoader workers, forked or spawned: they hold paths and options only, and
each worker decodes and simulates on threads it starts itself (the compiled module starts no
global thread pool). Give a :class:`SimulatedDataset` ``threads=1`` when many workers share the
cores.
"""

from __future__ import annotations

import os
from typing import Any, Dict, Iterator, Optional, Sequence, Tuple

import numpy as np
import torch
from torch.utils.data import Dataset, IterableDataset, get_worker_info

from ._native import Scene
from .dataset import GeneratedFrames, _check_options, simulated_frames


def _tensors(item: Dict[str, Any]) -> Dict[str, Any]:
    out: Dict[str, Any] = {}
    for key, value in item.items():
        if isinstance(value, np.ndarray):
            out[key] = torch.from_numpy(value)
        elif isinstance(value, dict):
            out[key] = _tensors(value)
        else:
            out[key] = value
    return out


class GeneratedDataset(Dataset):
    """A dataset written by ``sparsh generate`` as a ``torch.utils.data.Dataset``; the options
    are :class:`sparsh.GeneratedFrames`'."""

    def __init__(self, root: "os.PathLike[str] | str", **options: Any) -> None:
        self.frames = GeneratedFrames(root, **options)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> Dict[str, Any]:
        return _tensors(self.frames[index])


class SimulatedDataset(IterableDataset):
    """The sequences of a scene or dataset file, simulated on the fly, as a
    ``torch.utils.data.IterableDataset``: the i-th chosen sequence goes to worker
    ``i mod num_workers``, so each is simulated once per epoch, its frames in order. ``sequences`` picks some
    (default: all); the other options are :func:`sparsh.simulated_frames`'."""

    def __init__(
        self,
        scene: "os.PathLike[str] | str",
        *,
        sequences: Optional[Sequence[int]] = None,
        offsets: Sequence[int] = (0, 5),
        background: bool = True,
        size: Tuple[int, int] = (320, 240),
        fields: Sequence[str] = (),
        threads: Optional[int] = None,
    ) -> None:
        _check_options(offsets, size, fields)
        count = Scene(scene).sequences
        chosen = list(range(count)) if sequences is None else [int(s) for s in sequences]
        bad = [s for s in chosen if not 0 <= s < count]
        if bad:
            raise ValueError(f"sequences: {bad[0]} is not one of the file's {count} sequences")
        self.scene = os.fspath(scene)
        self.sequences = chosen
        self.options = dict(
            offsets=tuple(offsets), background=background, size=tuple(size), fields=tuple(fields), threads=threads
        )

    def __iter__(self) -> Iterator[Dict[str, Any]]:
        info = get_worker_info()
        mine = self.sequences if info is None else self.sequences[info.id :: info.num_workers]
        scene = Scene(self.scene)
        for s in mine:
            for item in simulated_frames(scene, s, **self.options):
                yield _tensors(item)
