# Type stubs of the tactbench Python package (reference: docs/python.md).
import os
from typing import Any, Callable, Literal, Mapping, Optional, Sequence, Union

import numpy as np
import numpy.typing as npt

__version__: str

class Sensor:
    def __init__(self, path: Union[str, os.PathLike[str]]) -> None: ...
    @property
    def layers(self) -> list[str]: ...
    def markers(self, layer: str) -> npt.NDArray[np.float64]: ...
    @property
    def force_grid(self) -> npt.NDArray[np.float64]: ...
    @property
    def image_size(self) -> tuple[int, int]: ...
    @property
    def path(self) -> str: ...

class Tracker:
    def __init__(
        self,
        sensor: Sensor,
        reference: npt.NDArray[Union[np.uint8, np.uint16]],
        *,
        mode: Optional[Literal["frame-to-frame", "per-window"]] = None,
        channels: Optional[Literal["rgb", "bgr"]] = None,
    ) -> None: ...
    def track(
        self, frame: npt.NDArray[Union[np.uint8, np.uint16]]
    ) -> dict[str, npt.NDArray[Any]]: ...
    def reset(self) -> None: ...
    def __len__(self) -> int: ...

class Solver:
    def __init__(
        self,
        sensor: Sensor,
        method: Literal["pinv", "tikhonov", "tsvd", "fourier"] = "pinv",
        *,
        lam: Union[None, float, Literal["gcv", "lcurve", "auto"]] = None,
        precision: Literal["f64", "f32"] = "f64",
        uncertainty: bool = False,
        noise_px: Optional[float] = None,
        rank: Union[None, int, Literal["auto"]] = None,
        rcond: Optional[float] = None,
    ) -> None: ...
    def solve(
        self,
        tracks: Union[
            Mapping[str, Any],
            tuple[npt.ArrayLike, npt.ArrayLike],
            Sequence[npt.ArrayLike],
        ],
    ) -> dict[str, npt.NDArray[np.float64]]: ...
    @property
    def diagnostics(self) -> Optional[dict[str, Any]]: ...
    @property
    def method(self) -> str: ...

class Run(dict[str, Any]):
    manifest: dict[str, Any]
    journal: Any
    verdict: Optional[dict[str, Any]]
    path: str
    def displacements(self, setpoint: int) -> dict[str, npt.NDArray[Any]]: ...
    def forces(self, setpoint: int) -> dict[str, npt.NDArray[Any]]: ...

def read_run(path: Union[str, os.PathLike[str]]) -> Run: ...
