"""Tyndall: noise-free light in haze and fog, computed by a Rust core.

>>> import tyndall
>>> scene = tyndall.load_scene("examples/valley_height_fog.json")
>>> layers, report = tyndall.render(scene)
>>> layers["inscatter"].shape        # (height, width, 3), float32, row 0 at the top
(540, 960, 3)
>>> report["error"]["max_rel"] <= report["error"]["tolerance"]
True

Composite a surface render through the medium with ``final = surface * T + L``
(``layers["transmittance"]`` and ``layers["inscatter"]``).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from typing import Any, Union

import numpy as np

from ._native import (
    RenderFailed,
    Scene,
    SceneFormatError,
    __version__,
    load_scene,
    scene_from_json,
    scene_schema,
)
from ._native import render as _render
from ._native import render_to_files as _render_to_files
from ._native import sky as _sky

SceneLike = Union[Scene, str, "os.PathLike[str]", Mapping[str, Any]]

__all__ = [
    "RenderFailed",
    "Scene",
    "SceneFormatError",
    "__version__",
    "as_scene",
    "load_scene",
    "render",
    "render_to_files",
    "scene_from_json",
    "scene_schema",
    "sky",
]


def as_scene(scene: SceneLike) -> Scene:
    """A :class:`Scene` from a Scene, a path to a JSON file, or a dict in the scene format."""
    if isinstance(scene, Scene):
        return scene
    if isinstance(scene, Mapping):
        return scene_from_json(json.dumps(scene, allow_nan=True), "<dict>")
    return load_scene(os.fspath(scene))


def render(
    scene: SceneLike,
    *,
    tolerance: float | None = None,
    threads: int | None = None,
    layers: Sequence[str] | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Render ``scene``; return ``(layers, report)``.

    ``layers`` maps ``inscatter``, ``transmittance``, ``sun_transmittance``, ``error``
    (float32 arrays of shape H×W×3, W·m⁻²·sr⁻¹ or unitless) and ``depth`` (H×W, metres,
    1e10 where no surface) to numpy arrays, row 0 at the top. ``report`` holds the
    timings, the error estimate and the plan (what was computed and what was left out).

    ``tolerance`` (relative, 1e-12..0.5), ``threads`` (0 = all cores) and ``layers``
    override the scene's ``output`` settings. Invalid scenes raise
    :class:`SceneFormatError` whose ``path`` names the field.
    """
    images, report_json = _render(as_scene(scene), tolerance, threads, list(layers) if layers is not None else None)
    return dict(images), json.loads(report_json)


def render_to_files(
    scene: SceneLike,
    out: str | os.PathLike[str],
    *,
    report: str | os.PathLike[str] | None = None,
    preview: str | os.PathLike[str] | None = None,
    tolerance: float | None = None,
    threads: int | None = None,
) -> dict[str, Any]:
    """Render and write a multi-layer EXR to ``out`` (atomically), the report JSON and a PNG preview if asked."""
    report_json = _render_to_files(
        as_scene(scene),
        os.fspath(out),
        os.fspath(report) if report is not None else None,
        os.fspath(preview) if preview is not None else None,
        tolerance,
        threads,
    )
    return json.loads(report_json)


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
    out: str | os.PathLike[str] | None = None,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Render a sky world texture with the layered atmosphere (Blender's Sky Texture parameters).

    Returns ``(rgb, report)``: an H×W×3 float32 array in linear Rec.709, W·m⁻²·sr⁻¹
    (row 0 the zenith, centre column towards +X, as Blender's Environment Texture maps
    it), and the report with ``sun_lamp`` (direction, Blender rotation, colour, strength),
    timings, the error estimate and the plan. ``sun_rotation_deg`` is Blender's Sun
    Rotation. With ``out``, the EXR (plain R, G, B) and ``OUT.report.json`` are written.
    ``multiple_scattering=True`` adds an optional, approximate multiple-scattering term
    (isotropic second order, off by default; ``report["multiple_scattering"]`` says so).
    Invalid parameters raise :class:`SceneFormatError` naming the field.
    """
    rgb, report_json = _sky(
        sun_elevation_deg,
        sun_rotation_deg,
        air=air,
        aerosol=aerosol,
        ozone=ozone,
        altitude_m=altitude_m,
        sun_size_deg=sun_size_deg,
        width=width,
        tolerance=tolerance,
        sun_disc=sun_disc,
        multiple_scattering=multiple_scattering,
        out=os.fspath(out) if out is not None else None,
    )
    return rgb, json.loads(report_json)
