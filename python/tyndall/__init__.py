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
import math
import os
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol, Union

import numpy as np

from ._native import (
    RenderCancelled,
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


class CancelEvent(Protocol):
    """What ``cancel=`` takes: anything with ``is_set()``, e.g. a :class:`threading.Event`."""

    def is_set(self) -> bool: ...


ProgressCallback = Callable[[str, int, int], object]
"""What ``progress=`` takes: called as ``progress(stage, done, total)`` on the calling
thread with the latest state when it changed, at most every 50 ms, and once more when the
render has finished (then ``done == total`` of the last stage). ``stage`` is
``"rendering rows"`` (``done``/``total`` count image rows) and then, where pixels need
Blender's pixel filter integral, ``"pixel filter"`` (they count those pixels; where it
runs, this stage is most of the time). An exception it raises while the render runs stops
the render and comes out of the call; one raised by the last call comes out too, though
the render had finished (and ``render_to_files`` had written its files)."""

__all__ = [
    "CancelEvent",
    "ProgressCallback",
    "RenderCancelled",
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


def _scene_error(path: str, detail: str, source: str = "<dict>") -> SceneFormatError:
    """A :class:`SceneFormatError` as the loader raises it (``source: path: detail``)."""
    err = SceneFormatError(f"{source}: {path}: {detail}")
    err.path, err.source_name, err.detail = path, source, detail
    return err


def _non_finite(value: Any, path: str) -> tuple[str, float] | None:
    """The path and value of the first NaN or ±∞ in a scene dict (JSON cannot hold
    them, and the loader would point into text the caller never wrote)."""
    if isinstance(value, (float, np.floating)):
        return None if math.isfinite(value) else (path, float(value))
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "fc":
            return None
        bad = np.argwhere(~np.isfinite(value))
        if len(bad) == 0:
            return None
        at = tuple(int(k) for k in bad[0])
        return path + "".join(f"[{k}]" for k in at), float(value[at])
    if isinstance(value, Mapping):
        for key, item in value.items():
            found = _non_finite(item, f"{path}.{key}" if path else str(key))
            if found:
                return found
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            found = _non_finite(item, f"{path}[{i}]")
            if found:
                return found
    return None


def _json_default(value: Any) -> Any:
    """numpy scalars and arrays inside a scene dict, as JSON numbers and lists."""
    if isinstance(value, np.generic):
        item = value.item()
        if isinstance(item, np.generic):
            # np.longdouble (and clongdouble) stay numpy scalars under .item(): JSON gets
            # the nearest double, or a TypeError that names the field (not a recursion).
            if isinstance(item, np.floating):
                return float(item)
            raise TypeError(f"a scene holds numbers, strings, lists and dicts, not {type(value).__name__}")
        return item
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"a scene holds numbers, strings, lists and dicts, not {type(value).__name__}")


def _mesh_arrays(mesh: Mapping[str, Any], path: str) -> tuple[np.ndarray, np.ndarray] | None:
    """A mesh's ``positions`` and ``triangles`` as the arrays the loader takes apart from
    the JSON text, when the caller gave numpy arrays; ``None`` for lists (they go into the
    text, and the loader names anything wrong in them)."""
    p, t = mesh.get("positions"), mesh.get("triangles")
    if not (isinstance(p, np.ndarray) and isinstance(t, np.ndarray)):
        return None
    for name, a, kinds, what in (("positions", p, "fiu", "numbers"), ("triangles", t, "iu", "integers")):
        if a.ndim != 2 or a.shape[1] != 3:
            raise _scene_error(f"{path}.{name}", f"expected an array of shape (n, 3), got shape {a.shape}")
        if a.dtype.kind not in kinds:
            raise _scene_error(f"{path}.{name}", f"expected {what}, got an array of {a.dtype}")
    found = _non_finite(p, f"{path}.positions")
    if found:
        raise _scene_error(found[0], f"must be a finite number, got {found[1]}")
    if t.size and (t.min() < 0 or t.max() > np.iinfo(np.uint32).max):
        at = tuple(int(k) for k in np.argwhere((t < 0) | (t > np.iinfo(np.uint32).max))[0])
        raise _scene_error(
            f"{path}.triangles[{at[0]}][{at[1]}]", f"a vertex index must be in 0..2^32, got {int(t[at])}"
        )
    return np.ascontiguousarray(p, dtype=np.float64), np.ascontiguousarray(t, dtype=np.uint32)


def as_scene(scene: SceneLike) -> Scene:
    """A :class:`Scene` from a Scene, a path to a JSON file, or a dict in the scene format.

    In a dict, numpy scalars and arrays stand for numbers and lists. A mesh whose
    ``positions`` and ``triangles`` are numpy arrays (``(n, 3)`` numbers and ``(m, 3)``
    integers) reaches the loader as arrays, not as JSON text: for a million triangles
    that is a fraction of a second instead of several."""
    if isinstance(scene, Scene):
        return scene
    if isinstance(scene, Mapping):
        arrays = []
        meshes = scene.get("meshes")
        if isinstance(meshes, list) and any(isinstance(m, Mapping) for m in meshes):
            text_meshes = []
            for i, mesh in enumerate(meshes):
                found = _mesh_arrays(mesh, f"meshes[{i}]") if isinstance(mesh, Mapping) else None
                if found is None:
                    text_meshes.append(mesh)
                else:
                    arrays.append((i, *found))
                    text_meshes.append({**mesh, "positions": [], "triangles": []})
            scene = {**scene, "meshes": text_meshes}
        try:
            # The C encoder refuses NaN and ±∞ itself; only then is the dict
            # walked for the field to name (a walk of a million-triangle mesh
            # in Python took seconds).
            text = json.dumps(scene, allow_nan=False, default=_json_default)
        except (ValueError, TypeError) as e:
            found = _non_finite(scene, "")
            if found:
                raise _scene_error(found[0], f"must be a finite number, got {found[1]}") from None
            raise _scene_error(".", f"not a scene in JSON terms: {e}") from None
        return scene_from_json(text, "<dict>", arrays or None)
    return load_scene(os.fspath(scene))


def _checked_overrides(
    tolerance: float | None, threads: int | None, layers: Sequence[str] | None
) -> tuple[float | None, int | None, list[str] | None]:
    """The keyword overrides of ``output``, checked here so that an error names the argument."""
    if tolerance is not None:
        if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float, np.integer, np.floating)):
            raise _scene_error(
                "output.tolerance", f"tolerance must be a number, got {type(tolerance).__name__}", "<render>"
            )
        tolerance = float(tolerance)
    if threads is not None:
        if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or not 0 <= threads < 2**32:
            raise _scene_error(
                "output.threads", f"threads must be an integer in 0..2^32 (0 = all cores), got {threads!r}", "<render>"
            )
        threads = int(threads)
    if layers is not None:
        if isinstance(layers, str):
            raise _scene_error(
                "output.layers", f"layers must be a list of layer names, not the string {layers!r}", "<render>"
            )
        if isinstance(layers, Mapping):
            raise _scene_error("output.layers", "layers must be a list of layer names, not a mapping", "<render>")
        try:
            layers = list(layers)
        except TypeError:
            raise _scene_error(
                "output.layers", f"layers must be a list of layer names, got {type(layers).__name__}", "<render>"
            ) from None
        for i, name in enumerate(layers):
            if not isinstance(name, str):
                raise _scene_error(
                    f"output.layers[{i}]", f"a layer name is a string, got {type(name).__name__} {name!r}", "<render>"
                )
    return tolerance, threads, layers


def render(
    scene: SceneLike,
    *,
    tolerance: float | None = None,
    threads: int | None = None,
    layers: Sequence[str] | None = None,
    cancel: CancelEvent | None = None,
    progress: ProgressCallback | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Render ``scene``; return ``(layers, report)``.

    ``layers`` maps ``inscatter``, ``transmittance``, ``sun_transmittance``, ``error``
    (float32 arrays of shape H×W×3, W·m⁻²·sr⁻¹ or unitless) and ``depth`` (H×W, metres,
    1e10 where no surface) to numpy arrays, row 0 at the top. ``report`` holds the
    timings, the error estimate and the plan (what was computed and what was left out).

    ``tolerance`` (relative, 1e-12..0.5), ``threads`` (0 = all cores) and ``layers``
    override the scene's ``output`` settings. Invalid scenes raise
    :class:`SceneFormatError` whose ``path`` names the field.

    The render can be interrupted: Ctrl-C raises ``KeyboardInterrupt``, and an
    exception raised by any signal handler (e.g. a ``signal.setitimer`` time
    limit) comes out of ``render``, within about one view ray's time (0.1–0.2 s
    measured for a 1080p stage), also while a large scene is prepared (a million
    triangles: 0.03 s after the request, where the preparation takes 1.3 s; the
    scene's parse from a dict, before, is not interrupted); no partial image is
    returned. Signals reach only
    the main thread: from any thread, pass ``cancel`` (a :class:`threading.Event`);
    once it is set the render stops the same way and raises :class:`RenderCancelled`.
    ``progress`` (see :data:`ProgressCallback`) is told how far the render is.
    """
    tolerance, threads, layers = _checked_overrides(tolerance, threads, layers)
    images, report_json = _render(as_scene(scene), tolerance, threads, layers, cancel, progress)
    return dict(images), json.loads(report_json)


def render_to_files(
    scene: SceneLike,
    out: str | os.PathLike[str],
    *,
    report: str | os.PathLike[str] | None = None,
    preview: str | os.PathLike[str] | None = None,
    tolerance: float | None = None,
    threads: int | None = None,
    cancel: CancelEvent | None = None,
    progress: ProgressCallback | None = None,
) -> dict[str, Any]:
    """Render and write a multi-layer EXR to ``out`` (atomically), the report JSON and a PNG preview if asked.

    Interruptible as :func:`render`: interrupted before its images are complete it writes
    no file; while writing, only the files already complete remain (each is written atomically).
    ``progress`` as in :func:`render`. The paths are checked before the render: ``out`` must
    end in ``.exr`` and ``preview`` in ``.png``, none may be a folder (:class:`RenderFailed`
    naming the path), and missing folders are made.
    """
    tolerance, threads, _ = _checked_overrides(tolerance, threads, None)
    report_json = _render_to_files(
        as_scene(scene),
        os.fspath(out),
        os.fspath(report) if report is not None else None,
        os.fspath(preview) if preview is not None else None,
        tolerance,
        threads,
        cancel,
        progress,
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
    cancel: CancelEvent | None = None,
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

    Like :func:`render` it can be interrupted: Ctrl-C (or any signal handler's
    exception) comes out of ``sky``, and once ``cancel`` (a :class:`threading.Event`)
    is set it raises :class:`RenderCancelled`; nothing is returned or written then.
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
        cancel=cancel,
    )
    return rgb, json.loads(report_json)
