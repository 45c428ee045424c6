from os import PathLike

import numpy as np

__version__: str

class SceneFormatError(ValueError):
    path: str
    source_name: str
    detail: str

class RenderFailed(RuntimeError): ...

class Scene:
    @property
    def resolution(self) -> tuple[int, int]: ...
    def to_json(self) -> str: ...

def load_scene(path: str | PathLike[str]) -> Scene: ...
def scene_from_json(text: str, source_name: str = "<string>") -> Scene: ...
def render(
    scene: Scene, tolerance: float | None = None, threads: int | None = None, layers: list[str] | None = None
) -> tuple[dict[str, np.ndarray], str]: ...
def render_to_files(
    scene: Scene,
    out: str,
    report: str | None = None,
    preview: str | None = None,
    tolerance: float | None = None,
    threads: int | None = None,
) -> str: ...
def scene_schema() -> str: ...
def cli_main(argv: list[str]) -> int: ...
