"""Plain-data records of a Blender scene and the Tyndall scene dict built from them (no bpy).

The bpy side (``..gather``) fills these records on the main thread; :func:`build_scene`
checks them and returns a dict in the format of docs/scene-format.md. Every problem
raises :class:`SceneInputError` with a message meant for the operator report.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import conversions as cv

DEFAULT_LAYERS: tuple[str, ...] = (
    "inscatter",
    "transmittance",
    "depth",
    "error",
    "inscatter_per_light",
    "surface_transmittance_per_light",
)
#: Layers written once per light.
PER_LIGHT_LAYERS: tuple[str, ...] = ("inscatter_per_light", "surface_transmittance_per_light")
MAX_PER_LIGHT_LAYERS = 16  # core/src/render/stage.rs MAX_LIGHT_LAYERS


class SceneInputError(ValueError):
    """The Blender scene cannot be computed; the message names the object and the setting."""


@dataclass
class IesData:
    """An IES Texture node in a light's node tree."""

    node: str
    mode: str  # "EXTERNAL" (filepath) or "INTERNAL" (text datablock)
    filepath: str = ""  # absolute path (EXTERNAL)
    text: str | None = None  # file contents (INTERNAL)
    text_name: str = ""
    strength: float = 1.0


@dataclass
class LightData:
    """A Blender light object."""

    name: str
    kind: str  # Blender Light.type: POINT, SPOT, SUN, AREA
    matrix: list[list[float]]  # 4×4 rows of matrix_world
    color: tuple[float, float, float]
    energy: float
    exposure: float = 0.0
    radius: float = 0.0
    spot_size: float = math.radians(45.0)  # radians, as the RNA
    spot_blend: float = 0.15
    sun_angle: float = math.radians(0.526)  # radians
    #: Blender's Normalize (on by default); off, Cycles does not divide the strength by the area.
    normalize: bool = True
    #: Blender's Cast Shadow (``use_shadow``); off, meshes shadow none of its light.
    cast_shadow: bool = True
    ies: IesData | None = None
    colour_note: str = ""  # e.g. "× Emission Color (0.5, …)"
    #: The light object's own name; for an instance (``name`` = ``instancer/object``) the object's.
    source: str = ""
    instanced: bool = False


@dataclass
class MediumData:
    """The world volume, or a fog box's, reduced to homogeneous coefficients."""

    node: str  # node names for messages
    scattering: tuple[float, float, float]
    absorption: tuple[float, float, float] = (0.0, 0.0, 0.0)
    phase: dict[str, Any] = field(default_factory=lambda: {"type": "isotropic"})
    # A volume object's box in world space (min, max corners before `rotation`, Blender units);
    # None: the world volume, everywhere.
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    # The box's rotation about its centre, quaternion [w, x, y, z]; None: axis-aligned.
    rotation: tuple[float, float, float, float] | None = None
    material: str = ""  # a fog box's material (muted with the world volume for the surface render)
    source: str = ""  # a fog box's object (Export Stage marks it as the medium's box)


@dataclass
class CameraData:
    """The active camera and the render settings."""

    name: str
    matrix: list[list[float]]
    lens_mm: float
    sensor_width_mm: float
    sensor_height_mm: float
    sensor_fit: str  # AUTO, HORIZONTAL, VERTICAL
    shift_x: float
    shift_y: float
    clip_start: float
    clip_end: float
    resolution: tuple[int, int]
    cam_type: str = "PERSP"
    filter_type: str = "BLACKMAN_HARRIS"
    filter_size_px: float = 1.5
    pixel_aspect: tuple[float, float] = (1.0, 1.0)  # Render > Format > Aspect X, Y
    render_region: str = ""  # "" (whole frame), "region" (Render Region) or "crop" (… and Crop to Render Region)


@dataclass
class MeshData:
    """An evaluated mesh (occluder) in object space with its world matrix."""

    name: str
    #: ``(n, 3)`` vertex positions; a numpy array from Blender (it reaches Tyndall as one).
    positions: np.ndarray | Sequence[Sequence[float]]
    #: ``(m, 3)`` vertex indices.
    triangles: np.ndarray | Sequence[Sequence[int]]
    matrix: list[list[float]]
    #: Ray Visibility > Camera and > Shadow (``visible_to_camera``, ``casts_shadows``).
    camera: bool = True
    shadow: bool = True


@dataclass
class SceneData:
    """Everything gathered from one Blender scene."""

    camera: CameraData | None
    lights: list[LightData]
    media: list[MediumData]
    meshes: list[MeshData]
    unit_scale: float = 1.0  # metres per Blender unit (Scene.unit_settings.scale_length)
    skipped: list[str] = field(default_factory=list)  # "<object>: <reason>" gathered but left out
    tolerance: float = 1e-3  # as the panel's default (props.py)
    threads: int = 0
    layers: tuple[str, ...] = DEFAULT_LAYERS
    include_sun: bool = False  # sun lamps light the medium (Cycles extinguishes them in a world volume)


@dataclass
class BuiltScene:
    """The Tyndall scene dict, the IES files it needs written next to it, and notes for the user."""

    scene: dict[str, Any]
    ies_texts: dict[str, str]  # file name (relative to the scene folder) → contents of internal IES texts
    light_names: dict[str, str]  # Blender object name → Tyndall light name (= EXR layer inscatter.<name>)
    notes: list[str]
    # Materials of the fog boxes exported as media: the surface render of the composite mutes
    # their Volume as it does the world's (else the haze in them would count twice).
    fog_materials: list[str] = field(default_factory=list)
    # Fog box media: their index in scene["media"] → the Blender object that is their box.
    fog_objects: dict[int, str] = field(default_factory=dict)
    # The tyndall.Scene the validation parsed, where it is the one the render needs (no IES
    # file, whose path depends on the folder): the render reuses it instead of parsing again
    # (0.19 s per million triangles).
    parsed: Any = None


def _scaled_rows(m: list[list[float]], s: float) -> list[list[float]]:
    """Rows of diag(s, s, s, 1) · m, checked finite."""
    out = []
    for r in range(4):
        row = []
        for c in range(4):
            v = float(m[r][c]) * (s if r < 3 else 1.0)
            if not math.isfinite(v):
                raise SceneInputError(f"non-finite transform entry [{r}][{c}] = {v}")
            row.append(v)
        out.append(row)
    return out


def _position(m: list[list[float]], s: float) -> list[float]:
    return [float(m[r][3]) * s for r in range(3)]


def _camera(c: CameraData, s: float, notes: list[str]) -> dict[str, Any]:
    where = f"camera '{c.name}'"
    if c.cam_type != "PERSP":
        raise SceneInputError(f"{where}: only perspective cameras are supported (got {c.cam_type})")
    w, h = c.resolution
    if w < 1 or h < 1:
        raise SceneInputError(f"render resolution {w}×{h} is empty")
    if c.pixel_aspect[0] != c.pixel_aspect[1]:
        raise SceneInputError(
            f"pixel aspect {c.pixel_aspect[0]:g}:{c.pixel_aspect[1]:g} (Render > Format > Aspect X/Y): Tyndall "
            "renders square pixels; set both to the same value"
        )
    if c.render_region == "crop":
        raise SceneInputError(
            "Crop to Render Region is on: Cycles' image is the region's size, Tyndall renders the whole frame; "
            "turn off Crop to Render Region (or Render Region)"
        )
    if c.render_region == "region":
        notes.append("Render Region is ignored: Tyndall renders the whole frame")
    try:
        frame = cv.frame_from_rows(c.matrix)
    except cv.ConversionError as e:
        raise SceneInputError(f"{where}: {e}") from e
    if frame.mirrored:
        raise SceneInputError(f"{where}: the transform mirrors (negative scale), which Tyndall's camera cannot")
    if frame.shear_deg > 0.01:
        notes.append(
            f"{where}: its transform shears its axes by {frame.shear_deg:.2f}° (a parent's non-uniform scale); "
            "Blender's view is sheared, Tyndall's keeps the view axis and an upright image"
        )
    fit = {"AUTO": "auto", "HORIZONTAL": "horizontal", "VERTICAL": "vertical"}[c.sensor_fit]
    return {
        "type": "perspective",
        "position": _position(c.matrix, s),
        "orientation": {"quaternion_wxyz": list(frame.quaternion_wxyz)},
        "focal_length_mm": c.lens_mm,
        "sensor_width_mm": c.sensor_width_mm,
        "sensor_height_mm": c.sensor_height_mm,
        "sensor_fit": fit,
        "shift_x": c.shift_x,
        "shift_y": c.shift_y,
        "resolution": [int(w), int(h)],
        "clip_start_m": max(c.clip_start * s, 0.0),
        # Cycles ends surfaces at Clip End but the world volume goes on to infinity (a
        # render with Clip End 10 m matched one with 1000 m to 0.1 %): no far clip here.
        "clip_end_m": None,
    }


def _pixel_filter(c: CameraData, notes: list[str]) -> dict[str, Any]:
    width = min(max(float(c.filter_size_px), 0.01), 10.0)
    if c.filter_type != "BLACKMAN_HARRIS":
        notes.append(
            f"pixel filter {c.filter_type.replace('_', ' ').title()} is not modelled: Blackman-Harris "
            f"{width:g} px used instead"
        )
    if width <= 0.01:
        return {"type": "none"}
    return {"type": "blackman_harris", "width_px": width}


def _light(
    light: LightData, name: str, s: float, ies_texts: dict[str, str], notes: list[str], include_sun: bool
) -> dict[str, Any] | None:
    where = f"light '{light.name}'"
    try:
        color = cv.rgb("Color", light.color)
        matrix = light.matrix
        if light.kind == "SUN":
            if not include_sun and light.cast_shadow:
                notes.append(
                    f"{light.name}: sun lamp left out of the volumetrics (Cycles extinguishes a sun behind an "
                    "infinite world volume; enable 'Sun lamps' to light the medium with it)"
                )
                return None
            if not light.cast_shadow:
                # Cycles traces no shadow ray for it, so the world volume does not extinguish it:
                # it lights the haze undimmed, as Tyndall's sun in a homogeneous medium does.
                notes.append(f"{light.name}: Cast Shadow is off, so the sun lights the haze undimmed (as in Cycles)")
            z = [float(matrix[r][2]) for r in range(3)]
            return {
                "type": "sun",
                "name": name,
                "direction_to_sun": z,
                "color": list(color),
                "strength_w_m2": cv.light_power_w(light.energy, light.exposure) * _normalize(light, notes),
                "angular_diameter_deg": min(max(math.degrees(cv.finite("Angle", light.sun_angle)), 0.0), 180.0),
            }
        if light.kind not in ("POINT", "SPOT"):
            notes.append(f"{light.name}: {light.kind.lower()} lights are not supported by Tyndall, left out")
            return None
        frame = cv.frame_from_rows(matrix)
        if frame.mirrored and light.ies is not None:
            raise cv.ConversionError(
                "the transform mirrors (negative scale), which would mirror its IES profile; Tyndall cannot"
            )
        sx, sy, sz = frame.scale
        stretched = max(sx, sy, sz) > min(sx, sy, sz) * (1.0 + 1e-6) or frame.shear_deg > 0.01
        if light.kind == "SPOT" and stretched:
            raise cv.ConversionError(
                f"non-uniform scale ({sx:.4g}, {sy:.4g}, {sz:.4g}) or shear ({frame.shear_deg:.2g}°): Cycles "
                "stretches the spot's cone into an ellipse, Tyndall's spot is round; apply or equalise the scale"
            )
        if light.ies is not None and stretched:
            # Cycles looks the profile up in the direction turned into object space as a normal
            # (normalize(Mᵀ·ω)): a scaled lamp stretches its IES distribution (measured: a narrow
            # profile 2.04× brighter in the haze at scale (2, 1, 1)).
            raise cv.ConversionError(
                f"non-uniform scale ({sx:.4g}, {sy:.4g}, {sz:.4g}) or shear ({frame.shear_deg:.2g}°): Cycles "
                "stretches the lamp's IES profile with it, Tyndall reads the profile unstretched; apply or "
                "equalise the scale"
            )
        # Cycles ignores the unit scale: a lamp's light falls off over Blender units. The scene
        # is in metres (lengths × s, densities ÷ s), so the intensity is × s² for the same image.
        power = cv.light_power_w(light.energy, light.exposure) * _normalize(light, notes) * s * s
        radius = cv.finite("Radius", light.radius) * s
        if radius < 0.0:
            raise cv.ConversionError(f"Radius must be ≥ 0, got {radius}")
        d: dict[str, Any] = {
            "type": light.kind.lower(),
            "name": name,
            "position": _position(matrix, s),
            "orientation": {"quaternion_wxyz": list(frame.quaternion_wxyz)},
            "color": list(color),
            "power_w": power,
            "radius_m": radius,
        }
        if light.kind == "SPOT":
            d["spot_size_deg"] = cv.spot_size_deg(light.spot_size)
            d["spot_blend"] = cv.spot_blend(light.spot_blend)
        if light.ies is not None:
            d["ies"] = _ies(light, name, ies_texts)
        if not light.cast_shadow:
            d["casts_shadows"] = False
        return d
    except cv.ConversionError as e:
        raise SceneInputError(f"{where}: {e}") from e


def _normalize(light: LightData, notes: list[str]) -> float:
    """1 for a normalised light; with Normalize off, Cycles' factor (the light's area), noted."""
    if light.normalize:
        return 1.0
    factor = cv.unnormalized_factor(light.kind, light.radius, light.sun_angle)
    notes.append(f"{light.name}: Normalize is off, so Cycles does not divide its power by its area: × {factor:.6g}")
    return factor


def _ies(light: LightData, name: str, ies_texts: dict[str, str]) -> dict[str, Any]:
    ies = light.ies
    assert ies is not None
    strength = cv.finite(f"IES node '{ies.node}' Strength", ies.strength)
    if strength < 0.0:
        raise cv.ConversionError(f"IES node '{ies.node}' Strength must be ≥ 0, got {strength}")
    if ies.mode == "EXTERNAL":
        if not ies.filepath:
            raise cv.ConversionError(f"IES node '{ies.node}' has no file path")
        if not os.path.isfile(ies.filepath):
            raise cv.ConversionError(f"IES node '{ies.node}': file not found: {ies.filepath}")
        return {"file": os.path.abspath(ies.filepath), "strength": strength}
    if not ies.text:
        raise cv.ConversionError(f"IES node '{ies.node}' uses an internal text, but none is set or it is empty")
    fname = f"ies/{name}.ies"
    ies_texts[fname] = ies.text
    return {"file": fname, "strength": strength}


def _left_out(notes: list[str]) -> str:
    """What was left out, for an error that may be its consequence (a lamp in an excluded collection)."""
    return f" (left out: {'; '.join(notes)})" if notes else ""


def _farthest_depth(mesh: MeshData, camera: CameraData) -> float:
    """How far ``mesh`` reaches along the view axis of the perspective ``camera`` (its −Z
    column), Blender units: Cycles ends a perspective camera's rays at the depth Clip End,
    not the distance (``camera_sample_perspective`` scales each ray's length by 1/cos of its
    angle to the axis). The largest over the vertices in world space (a triangle's deepest
    point is a vertex)."""
    p = np.asarray(mesh.positions, dtype=np.float64).reshape(-1, 3)
    m = np.asarray(mesh.matrix, dtype=np.float64)
    if len(p) == 0:
        return 0.0
    world = p @ m[:3, :3].T + m[:3, 3]
    c = np.asarray(camera.matrix, dtype=np.float64)
    axis = -c[:3, 2]
    return float(((world - c[:3, 3]) @ (axis / np.linalg.norm(axis))).max())


def build_scene(data: SceneData) -> BuiltScene:
    """Check ``data`` and build the Tyndall scene dict.

    IES profiles kept in Blender text datablocks are returned in ``ies_texts`` with paths
    relative to the scene file; the caller writes them next to ``scene.json`` (relative
    ``ies.file`` paths are resolved against the scene's folder, or the working directory
    for scenes given as dicts: :func:`resolve_ies_paths` makes them absolute).
    """
    notes: list[str] = list(data.skipped)
    s = cv.finite("unit scale", data.unit_scale)
    if s <= 0.0:
        raise SceneInputError(f"unit scale must be > 0, got {s}")
    if data.camera is None:
        raise SceneInputError("the scene has no active camera: add a camera and make it active")
    camera = _camera(data.camera, s, notes)
    if not data.lights:
        raise SceneInputError("the scene has no lights: add a point, spot or sun light" + _left_out(notes))
    if not data.media:
        raise SceneInputError(
            "the scene has no participating medium: connect a Volume Scatter or Principled Volume "
            "to the World Output's Volume input, or to a box mesh's material (Volume output only)"
        )

    names = cv.unique_names([lt.name for lt in data.lights])
    ies_texts: dict[str, str] = {}
    lights: list[dict[str, Any]] = []
    light_names: dict[str, str] = {}
    # A Cycles light group belongs to the light object and so to all its instances: only a
    # light object that is not instanced gets one (light_names feeds the light groups).
    instanced = {lt.source for lt in data.lights if lt.instanced}
    for light, name in zip(data.lights, names, strict=True):
        d = _light(light, name, s, ies_texts, notes, data.include_sun)
        if d is not None:
            lights.append(d)
            if not light.instanced and (light.source or light.name) not in instanced:
                light_names[light.name] = name
            elif not light.instanced:
                notes.append(f"{light.name}: also instanced, so no light group of its own (instances share it)")
    if not lights:
        raise SceneInputError("the scene has no light Tyndall supports (point, spot, sun)" + _left_out(notes))

    media: list[dict[str, Any]] = []
    for m in data.media:
        sig_s = [float(v) / s for v in m.scattering]
        sig_a = [float(v) / s for v in m.absorption]
        if not all(math.isfinite(v) and v >= 0.0 for v in sig_s + sig_a):
            raise SceneInputError(f"medium '{m.node}': coefficients must be finite and ≥ 0, got {sig_s}, {sig_a}")
        entry = {"type": "homogeneous", "name": m.node, "scattering": sig_s, "absorption": sig_a, "phase": m.phase}
        if m.bounds is not None:
            lo, hi = ([cv.finite(f"medium '{m.node}' bounds", float(v)) * s for v in c] for c in m.bounds)
            if not all(a < b for a, b in zip(lo, hi, strict=True)):
                raise SceneInputError(f"medium '{m.node}': its box is empty ({lo} .. {hi})")
            entry["bounds"] = {"box": {"min": lo, "max": hi}}
            if m.rotation is not None:
                entry["bounds"]["box"]["rotation_wxyz"] = [
                    cv.finite(f"medium '{m.node}' rotation", float(v)) for v in m.rotation
                ]
        media.append(entry)
    if all(max(m["scattering"]) + max(m["absorption"]) <= 0.0 for m in media):
        raise SceneInputError("the world volume has zero density: nothing to compute")

    meshes = []
    for mesh in data.meshes:
        if len(mesh.triangles) == 0:
            continue
        far = _farthest_depth(mesh, data.camera)
        if far > data.camera.clip_end and mesh.camera:
            notes.append(
                f"{mesh.name}: reaches {far:.4g} from the camera (depth along its view axis), past its Clip End "
                f"({data.camera.clip_end:.4g}): Cycles does not show surfaces there, Tyndall does "
                "(in both the haze goes on past it)"
            )
        entry: dict[str, Any] = {
            "name": mesh.name,
            "positions": mesh.positions,
            "triangles": mesh.triangles,
            "transform": {"matrix": _scaled_rows(mesh.matrix, s)},
        }
        if not mesh.camera:
            entry["visible_to_camera"] = False
        if not mesh.shadow:
            entry["casts_shadows"] = False
        meshes.append(entry)

    layers = list(data.layers)
    n_stage = sum(1 for lt in lights if lt["type"] in ("point", "spot"))
    if any(x in layers for x in PER_LIGHT_LAYERS) and n_stage > MAX_PER_LIGHT_LAYERS:
        layers = [x for x in layers if x not in PER_LIGHT_LAYERS]
        notes.append(f"{n_stage} lights: more than {MAX_PER_LIGHT_LAYERS}, no per-light layers")
    output: dict[str, Any] = {
        "layers": layers,
        "tolerance": data.tolerance,
        "threads": data.threads,
        "pixel_filter": _pixel_filter(data.camera, notes),
    }
    scene = {"version": 1, "camera": camera, "meshes": meshes, "lights": lights, "media": media, "output": output}
    fog_materials = sorted({m.material for m in data.media if m.material})
    fog_objects = {i: m.source for i, m in enumerate(data.media) if m.source}
    return BuiltScene(
        scene=scene,
        ies_texts=ies_texts,
        light_names=light_names,
        notes=notes,
        fog_materials=fog_materials,
        fog_objects=fog_objects,
    )


def fog_box_media_by_object(built: BuiltScene) -> dict[str, tuple[int, str]]:
    """Per Blender object that is a fog box: the index of one of its media in
    ``built.scene["media"]`` and the medium name its exported prim should carry.

    An object instanced several times (a collection instance, say) is the box of one medium per
    instance, named ``<instancer>/<object>: <node>``; Blender's USD exporter writes the object's
    custom properties onto every instance's prim, so they can carry one name only: the one the
    instances share, ``<object>: <node>`` (they share coefficients and phase, being one material).
    """
    by_object: dict[str, list[int]] = {}
    for i, obj in built.fog_objects.items():
        by_object.setdefault(obj, []).append(i)
    out: dict[str, tuple[int, str]] = {}
    for obj, indices in by_object.items():
        names = [str(built.scene["media"][i]["name"]) for i in indices]
        if len(indices) == 1:
            out[obj] = (indices[0], names[0])
            continue
        marker = f"{obj}: "
        tails = set()
        for n in names:
            at = n.find("/" + marker)
            tails.add(n[at + 1 + len(marker) :] if at >= 0 else n[len(marker) :] if n.startswith(marker) else n)
        shared = f"{marker}{tails.pop()}" if len(tails) == 1 else f"{obj} ({len(indices)} instances)"
        out[obj] = (indices[0], shared)
    return out


def resolve_ies_paths(scene: dict[str, Any], folder: str) -> dict[str, Any]:
    """A copy of ``scene`` whose relative ``ies.file`` paths are made absolute against ``folder``."""
    out = dict(scene)
    out["lights"] = []
    for lt in scene.get("lights", []):
        lt = dict(lt)
        ies = lt.get("ies")
        if ies is not None and not os.path.isabs(ies["file"]):
            lt["ies"] = {**ies, "file": os.path.join(folder, ies["file"])}
        out["lights"].append(lt)
    return out
