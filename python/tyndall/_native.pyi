from collections.abc import Callable
from os import PathLike
from typing import Protocol

import numpy as np

class _CancelEvent(Protocol):
    def is_set(self) -> bool: ...

__version__: str

class SceneFormatError(ValueError):
    path: str
    source_name: str
    detail: str

class RenderFailed(RuntimeError): ...
class RenderCancelled(RenderFailed): ...

class Scene:
    @property
    def resolution(self) -> tuple[int, int]: ...
    def to_json(self) -> str: ...

def load_scene(path: str | PathLike[str]) -> Scene: ...
def scene_from_json(
    text: str,
    source_name: str = "<string>",
    mesh_arrays: list[tuple[int, np.ndarray, np.ndarray]] | None = None,
) -> Scene: ...
def render(
    scene: Scene,
    tolerance: float | None = None,
    threads: int | None = None,
    layers: list[str] | None = None,
    cancel: _CancelEvent | None = None,
    progress: Callable[[str, int, int], object] | None = None,
) -> tuple[dict[str, np.ndarray], str]: ...
def render_to_files(
    scene: Scene,
    out: str,
    report: str | None = None,
    preview: str | None = None,
    tolerance: float | None = None,
    threads: int | None = None,
    cancel: _CancelEvent | None = None,
    progress: Callable[[str, int, int], object] | None = None,
) -> str: ...
def scene_schema() -> str: ...
def cli_main(argv: list[str]) -> int: ...
def sky(
    sun_elevation_deg: float,
    sun_rotation_deg: float = 0.0,
    *,
    air: float = 1.0,
    aerosol: float = 1.0,
    ozone: float = 1.0,
    altitude_m: float = 0.0,
    sun_size_deg: float = 0.545,
    width: int = 1024,
    tolerance: float = 1e-3,
    sun_disc: bool = True,
    multiple_scattering: bool = False,
    out: str | None = None,
    cancel: _CancelEvent | None = None,
) -> tuple[np.ndarray, str]: ...
