"""The long-running work of the operators: run in a :class:`~.jobs.Job`, never touching bpy.

Each function writes into a :class:`~.files.Staging` folder only; the operator commits the
staged files into the output folder on the main thread when the job is DONE.
"""

from __future__ import annotations

import json
import math
import os
import threading
from dataclasses import dataclass
from typing import Any

from .files import Staging, atomic_write_json, atomic_write_text
from .jobs import ProgressFn
from .scene_build import BuiltScene, resolve_ies_paths

VOLUMETRICS_EXR = "volumetrics.exr"
REPORT_JSON = "report.json"
SCENE_JSON = "scene.json"
SKY_EXR = "sky.exr"
SKY_REPORT_JSON = "sky.report.json"
STAGE_USDA = "stage.usda"


def stage_scene_files(built: BuiltScene, staging: Staging) -> list[str]:
    """Write ``scene.json`` and the internal IES texts into ``staging``; returns the staged names."""
    names = [SCENE_JSON]
    for rel, text in built.ies_texts.items():
        atomic_write_text(staging.file(rel), text)
        names.append(rel)
    atomic_write_json(staging.file(SCENE_JSON), built.scene)
    return names


def validate_scene(built: BuiltScene, folder: str) -> None:
    """Let Tyndall's loader check the scene (raises ``tyndall.SceneFormatError`` naming the field).

    IES files from internal texts are not written yet, so their lights are checked without ``ies``.
    A scene without IES files is the one the render needs: it is kept in ``built.parsed``.
    """
    import tyndall

    scene = resolve_ies_paths(built.scene, folder)
    uses_ies = any("ies" in lt for lt in scene["lights"])
    for lt in scene["lights"]:
        if "ies" in lt and not os.path.isfile(lt["ies"]["file"]):
            lt.pop("ies")
    parsed = tyndall.as_scene(scene)
    built.parsed = None if uses_ies else parsed


def volumetrics_work(
    built: BuiltScene, staging: Staging, progress: ProgressFn, stop: threading.Event | None = None
) -> dict[str, Any]:
    """Stage scene.json (+ IES files), render volumetrics.exr and report.json; returns the report.

    Once ``stop`` is set the render stops and ``tyndall.RenderCancelled`` is raised.
    """
    import tyndall

    progress(0.05, "writing scene")
    names = stage_scene_files(built, staging)
    scene = built.parsed if built.parsed is not None else resolve_ies_paths(built.scene, staging.path)
    progress(0.1, "rendering volumetrics")

    # Rows first (all the time without the pixel filter), then the filtered pixels (most
    # of the time where the filter runs): 10–40 % and 40–95 % of the bar. A stage not
    # listed keeps the bar where it is.
    bands = {"rendering rows": ("rows", 0.1, 0.3), "pixel filter": ("pixel filter", 0.4, 0.55)}
    at = 0.1

    def render_progress(stage: str, done: int, total: int) -> None:
        nonlocal at
        name, start, span = bands.get(stage, (stage, at, 0.0))
        at = start + span * (done / total if total else 1.0)
        progress(at, f"rendering volumetrics: {name} {done}/{total}")

    report = tyndall.render_to_files(
        scene,
        staging.file(VOLUMETRICS_EXR),
        report=staging.file(REPORT_JSON),
        cancel=stop,
        progress=render_progress,
    )
    report.setdefault("blender", {})["notes"] = list(built.notes)
    report["blender"]["light_layers"] = {k: f"inscatter.{v}" for k, v in built.light_names.items()}
    report["blender"]["fog_materials"] = list(built.fog_materials)
    atomic_write_json(staging.file(REPORT_JSON), report)
    progress(1.0, "done")
    return {"report": report, "files": [*names, VOLUMETRICS_EXR, REPORT_JSON]}


@dataclass
class SkyParams:
    """Arguments of ``tyndall.sky`` (Blender's Sky Texture parameters)."""

    sun_elevation_deg: float
    sun_rotation_deg: float = 0.0
    air: float = 1.0
    aerosol: float = 1.0
    ozone: float = 1.0
    altitude_m: float = 0.0
    sun_size_deg: float = 0.545
    width: int = 1024
    tolerance: float = 1e-3
    sun_disc: bool = True
    multiple_scattering: bool = False

    def check(self) -> None:
        """Finite numbers and the ranges the operator can state clearly (tyndall checks the rest)."""
        for k, v in self.__dict__.items():
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"sky {k} is not a finite number ({v})")
        if not -90.0 <= self.sun_elevation_deg <= 90.0:
            raise ValueError(f"sun elevation must be within −90..90°, got {self.sun_elevation_deg}")
        for k in ("air", "aerosol", "ozone", "altitude_m"):
            if getattr(self, k) < 0.0:
                raise ValueError(f"sky {k} must be ≥ 0, got {getattr(self, k)}")
        if self.width < 8:
            raise ValueError(f"sky width must be ≥ 8 px, got {self.width}")

    def kwargs(self) -> dict[str, Any]:
        """Keyword arguments after ``sun_elevation_deg`` for ``tyndall.sky``."""
        d = dict(self.__dict__)
        d.pop("sun_elevation_deg")
        return d


def sky_work(
    params: SkyParams, staging: Staging, progress: ProgressFn, stop: threading.Event | None = None
) -> dict[str, Any]:
    """Render sky.exr (+ sky.report.json) into ``staging``; returns the report.

    Once ``stop`` is set the sky stops and ``tyndall.RenderCancelled`` is raised.
    """
    import tyndall

    progress(0.05, "rendering sky")
    tmp = staging.file(SKY_EXR)
    _rgb, report = tyndall.sky(params.sun_elevation_deg, out=tmp, cancel=stop, **params.kwargs())
    side = os.path.splitext(tmp)[0] + ".report.json"  # written by tyndall.sky next to OUT
    if os.path.exists(side) and side != staging.file(SKY_REPORT_JSON):
        os.replace(side, staging.file(SKY_REPORT_JSON))
    report["blender"] = {"params": params.__dict__}
    atomic_write_json(staging.file(SKY_REPORT_JSON), report)
    progress(1.0, "done")
    return {"report": report, "files": [SKY_EXR, SKY_REPORT_JSON]}


def read_json(path: str) -> dict[str, Any]:
    """A JSON file as a dict."""
    with open(path, encoding="utf-8") as f:
        return json.load(f)
