"""Type stubs of the compiled module (src/lib.rs)."""

import os
from typing import Any, Dict, Iterator, List, Optional, Tuple, TypedDict, Union

import numpy as np
import numpy.typing as npt

_Path = Union[str, "os.PathLike[str]"]

__version__: str

class SparshError(Exception):
    """A scene, dataset or solver problem; the message names the file and what is wrong."""

class SequenceInfo(TypedDict):
    sequence: int
    family: str
    split: str
    frames: int
    width_px: int
    height_px: int
    mm_per_px: float
    solver: str

class Frame(TypedDict):
    image: npt.NDArray[np.uint8]
    """(height, width, 3) sensor image."""
    fields: Dict[str, np.ndarray]
    """p qx qy (kPa), ux uy uz (mm) float64 and contact slip bool, each (ny, nx)."""
    cell_mm: float
    """Edge of a field cell (mm)."""
    label: Dict[str, Any]
    """The row labels.jsonl holds for the frame."""

class Scene:
    """A scene or dataset file: one scene, or [[family]] tables drawing many sequences."""

    def __init__(self, path: _Path) -> None: ...
    @property
    def path(self) -> str: ...
    @property
    def seed(self) -> int: ...
    @property
    def sequences(self) -> int: ...
    @property
    def frames(self) -> int: ...
    def sequence(self, index: int) -> SequenceInfo: ...
    def simulate(self, sequence: int = 0, *, threads: Optional[int] = None) -> Simulator: ...

class Simulator:
    """One sequence's frames in order; the same bits whatever the thread count."""

    @property
    def background(self) -> npt.NDArray[np.uint8]: ...
    def __len__(self) -> int: ...
    def __iter__(self) -> Iterator[Frame]: ...
    def __next__(self) -> Frame: ...

class GenerateReport(TypedDict):
    frames: int
    wall_s: float
    complete: bool
    outside_validity: int
    notes: List[str]

def generate(
    scene: _Path,
    out: _Path,
    *,
    force: bool = False,
    resume: bool = False,
    shard: Optional[str] = None,
    threads: Optional[int] = None,
) -> GenerateReport: ...
def verify(dir: _Path, *, shard: Optional[str] = None, complete: bool = False) -> List[str]: ...
def validate(cases: _Path, *, threads: Optional[int] = None) -> Dict[str, Any]: ...
def read_image(path: _Path) -> npt.NDArray[np.uint8]: ...
def read_fields(path: _Path) -> Dict[str, npt.NDArray[np.float32]]: ...
def preprocess(
    image: npt.NDArray[np.uint8],
    background: Optional[npt.NDArray[np.uint8]] = None,
    size: Tuple[int, int] = (320, 240),
) -> npt.NDArray[np.float32]: ...
