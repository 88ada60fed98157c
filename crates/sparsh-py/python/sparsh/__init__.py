"""sparsh: a physics-based simulator of vision-based tactile sensors (DIGIT, GelSight) with
ground truth, and the datasets it writes, for Python and PyTorch.

- :class:`Scene` reads a scene or dataset file; :meth:`Scene.simulate` steps one sequence and
  gives each frame's image, every ground-truth field and its label row as NumPy arrays.
- :func:`generate`, :func:`verify`, :func:`validate`: the CLI's commands of the same names.
- :class:`GeneratedFrames` reads a generated dataset frame by frame (NumPy);
  :func:`simulated_frames` yields the same items straight from the simulator.
- ``sparsh.torch`` (needs PyTorch): the two as ``torch.utils.data.Dataset`` and
  ``IterableDataset``, safe in DataLoader workers.
"""

from ._native import (
    Scene,
    Simulator,
    SparshError,
    __version__,
    generate,
    preprocess,
    read_fields,
    read_image,
    validate,
    verify,
)
from .dataset import GeneratedFrames, simulated_frames

__all__ = [
    "GeneratedFrames",
    "Scene",
    "Simulator",
    "SparshError",
    "__version__",
    "generate",
    "preprocess",
    "read_fields",
    "read_image",
    "simulated_frames",
    "validate",
    "verify",
]
