"""Tyndall results → a USD layer: the sky as a DomeLight, the sun as a DistantLight, and the
rendered images as asset attributes on ``/Tyndall/Results``.

The lights are written with Blender 5.0's USD conventions (the inverse of the reader), so
Blender's USD importer brings back the sun lamp and the World texture Tyndall computed.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from typing import Any

from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, Vt

from . import _geom

ROOT = "/Tyndall"
RESULTS = ROOT + "/Results"
SKY = ROOT + "/Sky"
SUN = ROOT + "/Sun"

#: Orientation of the sky DomeLight: the rotation Blender's exporter gives an unrotated
#: Environment Texture (+90° about X after +90° about Z, USD row-vector order), which
#: Blender 5.0's importer turns back into an unrotated Environment Texture.
DOME_ROTATION = Gf.Matrix4d().SetRotate(Gf.Rotation(Gf.Vec3d(1, 0, 0), 90.0)) * Gf.Matrix4d().SetRotate(
    Gf.Rotation(Gf.Vec3d(0, 0, 1), 90.0)
)

#: ``tyndall:results:*`` asset attributes and what they hold.
RESULT_ASSETS = {
    "volumetrics": "multi-layer EXR rendered by Tyndall (channels <layer>.R/G/B, depth.Z)",
    "report": "render report (JSON)",
    "preview": "tone-mapped PNG preview",
    "sky": "equirectangular sky EXR (the DomeLight's texture)",
    "scene": "the Tyndall scene JSON the stage was converted to",
    "source": "the USD stage that was rendered",
}


def _asset_path(path: str | os.PathLike[str], layer_dir: str) -> Sdf.AssetPath:
    p = os.path.abspath(os.fspath(path))
    rel = os.path.relpath(p, layer_dir)
    return Sdf.AssetPath(p if rel.startswith("..") else "./" + rel.replace(os.sep, "/"))


def _orient(prim: Usd.Prim, quat: Gf.Quatd) -> None:
    xf = UsdGeom.Xformable(prim)
    xf.ClearXformOpOrder()
    xf.AddOrientOp(UsdGeom.XformOp.PrecisionDouble).Set(quat)


def write_results_layer(
    path: str | os.PathLike[str],
    *,
    sun: Mapping[str, Any] | None = None,
    sky_texture: str | os.PathLike[str] | None = None,
    sky_strength: float = 1.0,
    assets: Mapping[str, str | os.PathLike[str]] | None = None,
    layers: Sequence[str] = (),
    skipped: Sequence[Mapping[str, str]] = (),
    notes: Sequence[str] = (),
) -> Usd.Stage:
    """Write the results layer at ``path`` (.usda/.usdc/.usd) and return the stage.

    ``sun`` is a light in Tyndall's scene format (``type`` "sun": ``direction_to_sun``,
    ``color``, ``strength_w_m2``, ``angular_diameter_deg``) or the ``sun_lamp`` of a
    ``tyndall.sky`` report. ``assets`` maps keys of :data:`RESULT_ASSETS` to files;
    paths inside the layer's folder are written relative to it.
    """
    path = os.fspath(path)
    layer_dir = os.path.dirname(os.path.abspath(path))
    for key in assets or {}:
        if key not in RESULT_ASSETS:
            raise ValueError(f"unknown result asset {key!r}, expected one of {sorted(RESULT_ASSETS)}")
    if os.path.exists(path):
        os.remove(path)
    stage = Usd.Stage.CreateNew(path)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, ROOT).GetPrim()
    stage.SetDefaultPrim(root)
    stage.GetRootLayer().documentation = "Tyndall results"

    if sky_texture is not None:
        dome = UsdLux.DomeLight.Define(stage, SKY)
        dome.CreateTextureFileAttr().Set(_asset_path(sky_texture, layer_dir))
        dome.CreateTextureFormatAttr().Set(UsdLux.Tokens.latlong)
        dome.CreateIntensityAttr().Set(float(sky_strength))
        dome.CreateColorAttr().Set(Gf.Vec3f(1.0, 1.0, 1.0))
        _orient(dome.GetPrim(), DOME_ROTATION.ExtractRotationQuat())

    if sun is not None:
        d = [float(x) for x in sun["direction_to_sun"]]
        n = math.sqrt(sum(x * x for x in d))
        if not n > 0.0:
            raise ValueError(f"sun direction_to_sun must be non-zero, got {d}")
        d = [x / n for x in d]
        strength = float(sun["strength_w_m2"])
        diameter = float(sun.get("angular_diameter_deg", sun.get("angle_deg", 0.526)))
        color = [float(x) for x in sun.get("color", (1.0, 1.0, 1.0))]
        light = UsdLux.DistantLight.Define(stage, SUN)
        # Blender 5.0's conventions: intensity = Strength / 4, angle = Angle / 2.
        light.CreateIntensityAttr().Set(strength / 4.0)
        light.CreateAngleAttr().Set(diameter / 2.0)
        light.CreateColorAttr().Set(Gf.Vec3f(*color))
        light.CreateNormalizeAttr().Set(True)
        # The light travels along its local −Z, so its +Z points at the sun.
        _orient(light.GetPrim(), _geom.quaternion_from_to((0.0, 0.0, 1.0), d))
        prim = light.GetPrim()
        prim.CreateAttribute("tyndall:sun:strengthWm2", Sdf.ValueTypeNames.Double).Set(strength)
        prim.CreateAttribute("tyndall:sun:angularDiameterDeg", Sdf.ValueTypeNames.Double).Set(diameter)

    res = stage.DefinePrim(RESULTS, "Scope")
    for key, file in (assets or {}).items():
        res.CreateAttribute(f"tyndall:results:{key}", Sdf.ValueTypeNames.Asset).Set(_asset_path(file, layer_dir))
    if layers:
        res.CreateAttribute("tyndall:results:layers", Sdf.ValueTypeNames.TokenArray).Set(Vt.TokenArray(list(layers)))
    if skipped:
        res.CreateAttribute("tyndall:results:skippedPrims", Sdf.ValueTypeNames.StringArray).Set(
            Vt.StringArray([f"{s['prim']}: {s['reason']}" for s in skipped])
        )
    if notes:
        res.CreateAttribute("tyndall:results:notes", Sdf.ValueTypeNames.StringArray).Set(Vt.StringArray(list(notes)))
    stage.GetRootLayer().Save()
    return stage


def read_results_layer(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a layer written by :func:`write_results_layer` back: resolved asset paths, the sun
    (in Tyndall's scene format), the sky texture, layers, skipped prims and notes."""
    stage = Usd.Stage.Open(os.fspath(path))
    out: dict[str, Any] = {"assets": {}, "layers": [], "skipped": [], "notes": [], "sun": None, "sky": None}
    res = stage.GetPrimAtPath(RESULTS)
    if res:
        for key in RESULT_ASSETS:
            attr = res.GetAttribute(f"tyndall:results:{key}")
            if attr and attr.HasAuthoredValue():
                a = attr.Get()
                out["assets"][key] = a.resolvedPath or a.path
        for key, attr_name in (
            ("layers", "tyndall:results:layers"),
            ("skipped", "tyndall:results:skippedPrims"),
            ("notes", "tyndall:results:notes"),
        ):
            attr = res.GetAttribute(attr_name)
            if attr and attr.HasAuthoredValue():
                out[key] = [str(x) for x in attr.Get()]
    sky = stage.GetPrimAtPath(SKY)
    if sky:
        dome = UsdLux.DomeLight(sky)
        tex = dome.GetTextureFileAttr().Get()
        out["sky"] = {
            "texture": tex.resolvedPath or tex.path,
            "format": str(dome.GetTextureFormatAttr().Get()),
            "strength": float(dome.GetIntensityAttr().Get()),
        }
    sun = stage.GetPrimAtPath(SUN)
    if sun:
        m = UsdGeom.Xformable(sun).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
        z = _geom.axis(m, 2).GetNormalized()
        light = UsdLux.DistantLight(sun)
        out["sun"] = {
            "type": "sun",
            "name": sun.GetName(),
            "direction_to_sun": [float(z[0]), float(z[1]), float(z[2])],
            "color": [float(c) for c in light.GetColorAttr().Get()],
            "strength_w_m2": 4.0 * float(light.GetIntensityAttr().Get()),
            "angular_diameter_deg": 2.0 * float(light.GetAngleAttr().Get()),
        }
    return out
