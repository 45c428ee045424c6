"""USD stage → Tyndall scene (a dict in the JSON scene format, docs/scene-format.md).

Light units follow Blender 5.0's USD exporter exactly (verified by exporting from
bpy 5.0.1, see usd/README.md), so that Blender → USD → Tyndall gives the values
Blender had:

* SphereLight (point, spot): ``power_w = inputs:intensity · π · 2^inputs:exposure``
  (× 4π·inputs:radius², or × 4 at radius 0, when ``inputs:normalize`` is off: see usd/README.md)
* DistantLight (sun): ``strength_w_m2 = inputs:intensity · 4 · 2^inputs:exposure``
  (× π·sin²(inputs:angle) when ``inputs:normalize`` is off), ``angular_diameter_deg = 2 · inputs:angle``
* ShapingAPI: ``spot_size_deg = 2 · inputs:shaping:cone:angle``,
  ``spot_blend = inputs:shaping:cone:softness``
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender, UsdShade

from . import _geom

NS = "tyndall:"

#: Prim types that only structure or shade a stage; they are passed over without a note.
_STRUCTURAL = {
    "",
    "Xform",
    "Scope",
    "Material",
    "Shader",
    "NodeGraph",
    "GeomSubset",
    "RenderSettings",
    "RenderProduct",
    "RenderVar",
    "RenderPass",
    "SkelRoot",
    "Skeleton",
    "SkelAnimation",
    "BlendShape",
}
_UNSUPPORTED_LIGHTS = {"RectLight", "DiskLight", "CylinderLight", "GeometryLight", "PortalLight", "PluginLight"}
_PHASES = {"isotropic", "rayleigh", "henyey_greenstein", "cornette_shanks", "nishita_hazy", "nishita_murky"}
_LAYERS = {"inscatter", "transmittance", "depth", "sun_transmittance", "error"}
#: Blender's default render width, used when the stage gives no resolution.
DEFAULT_WIDTH = 1920


class UsdSceneError(ValueError):
    """A stage that cannot be converted; the message names the prim path and the attribute."""

    def __init__(self, prim: str, attribute: str | None, message: str) -> None:
        self.prim = prim
        self.attribute = attribute
        where = f"{prim}.{attribute}" if attribute else prim
        super().__init__(f"{where}: {message}")


@dataclass
class SkySettings:
    """A sky world texture to render with ``tyndall.sky`` (from ``tyndall:sky:*``)."""

    sun_elevation_deg: float
    sun_rotation_deg: float
    sun_size_deg: float
    air: float = 1.0
    aerosol: float = 1.0
    ozone: float = 1.0
    altitude_m: float = 0.0
    width: int = 1024
    tolerance: float = 1e-3
    sun_disc: bool = True

    def kwargs(self) -> dict[str, Any]:
        """Keyword arguments of ``tyndall.sky``."""
        return {
            "sun_elevation_deg": self.sun_elevation_deg,
            "sun_rotation_deg": self.sun_rotation_deg,
            "air": self.air,
            "aerosol": self.aerosol,
            "ozone": self.ozone,
            "altitude_m": self.altitude_m,
            "sun_size_deg": self.sun_size_deg,
            "width": self.width,
            "tolerance": self.tolerance,
            "sun_disc": self.sun_disc,
        }


@dataclass
class Conversion:
    """Result of :func:`convert_stage`."""

    #: The Tyndall scene (JSON-ready dict, format version 1).
    scene: dict[str, Any]
    #: Prims the converter could not use: ``{"prim": path, "reason": text}``.
    skipped: list[dict[str, str]] = field(default_factory=list)
    #: Conventions applied and defaults assumed, for the report.
    notes: list[str] = field(default_factory=list)
    #: Sky to render, when the stage asks for one (``tyndall:sky:enabled``).
    sky: SkySettings | None = None
    #: Prim path of each converted light, in ``scene["lights"]`` order (for a PointInstancer's
    #: instances, the prototype's lamp, once per instance).
    light_prims: list[str] = field(default_factory=list)


# ------------------------------------------------------------------ attribute access


def _value(prim: Usd.Prim, name: str, time: Usd.TimeCode) -> Any:
    """The attribute's value (authored or schema fallback), or ``None``. An ``inputs:``
    attribute connected to another input (a NodeGraph's interface, say) takes the value
    at the end of the connections, as UsdImaging reads a light's inputs."""
    attr = prim.GetAttribute(name)
    if not attr or not attr.IsValid():
        return None
    if name.startswith("inputs:") and attr.HasAuthoredConnections():
        sources = UsdShade.Input(attr).GetValueProducingAttributes()
        if sources:
            source = sources[0]
            if UsdShade.Utils.GetType(source.GetName()) == UsdShade.AttributeType.Output:
                raise UsdSceneError(
                    str(prim.GetPath()),
                    name,
                    f"is connected to the shader output {source.GetPath()}: only values (or inputs holding "
                    "them) can be read",
                )
            return source.Get(time)
    return attr.Get(time)


def _authored(prim: Usd.Prim, name: str) -> bool:
    """A value authored on the attribute, or (for ``inputs:``) a connection that gives one."""
    attr = prim.GetAttribute(name)
    return bool(attr) and (
        attr.HasAuthoredValue() or (name.startswith("inputs:") and attr.HasAuthoredConnections())
    )


def _float(prim: Usd.Prim, name: str, time: Usd.TimeCode, default: float | None = None) -> float:
    v = _value(prim, name, time)
    if v is None:
        if default is None:
            raise UsdSceneError(str(prim.GetPath()), name, "is required")
        return default
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise UsdSceneError(str(prim.GetPath()), name, f"must be a number, got {v!r}")
    x = float(v)
    if not math.isfinite(x):
        raise UsdSceneError(str(prim.GetPath()), name, f"must be finite, got {x}")
    return x


def _vec(prim: Usd.Prim, name: str, time: Usd.TimeCode, n: int, default: Sequence[float]) -> list[float]:
    v = _value(prim, name, time)
    if v is None:
        return [float(x) for x in default]
    try:
        if isinstance(v, (str, bytes)):
            raise TypeError  # (a string's characters are no vector)
        out = [float(x) for x in v]
    except (TypeError, ValueError):
        raise UsdSceneError(str(prim.GetPath()), name, f"must be {n} numbers, got {v!r}") from None
    if len(out) != n or not all(math.isfinite(x) for x in out):
        raise UsdSceneError(str(prim.GetPath()), name, f"must be {n} finite numbers, got {out}")
    return out


def _text(prim: Usd.Prim, name: str, time: Usd.TimeCode, default: str | None = None) -> str:
    v = _value(prim, name, time)
    if v is None:
        if default is None:
            raise UsdSceneError(str(prim.GetPath()), name, "is required")
        return default
    return str(v)


def _bool(prim: Usd.Prim, name: str, time: Usd.TimeCode, default: bool) -> bool:
    v = _value(prim, name, time)
    if v is None:
        return default
    if isinstance(v, (bool, int)):
        return bool(v)
    if isinstance(v, str) and v.lower() in {"true", "false", "1", "0"}:
        return v.lower() in {"true", "1"}
    raise UsdSceneError(str(prim.GetPath()), name, f"must be a bool, got {v!r}")


def _coefficient(prim: Usd.Prim, name: str, time: Usd.TimeCode, default: float | None) -> float | list[float]:
    """A coefficient in m⁻¹: a number (grey) or three numbers (linear Rec.709 RGB), each ≥ 0."""
    v = _value(prim, name, time)
    if v is None:
        if default is None:
            raise UsdSceneError(str(prim.GetPath()), name, "is required")
        return default
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        vals = [float(v)]
    else:
        try:
            if isinstance(v, (str, bytes)):
                raise TypeError  # (a string's characters are no coefficients)
            vals = [float(x) for x in v]
        except (TypeError, ValueError):
            raise UsdSceneError(str(prim.GetPath()), name, f"must be a number or 3 numbers, got {v!r}") from None
        if len(vals) != 3:
            raise UsdSceneError(str(prim.GetPath()), name, f"must be a number or 3 numbers, got {vals}")
    for x in vals:
        if not math.isfinite(x) or x < 0.0:
            raise UsdSceneError(str(prim.GetPath()), name, f"must be finite and ≥ 0 m⁻¹, got {x}")
    return vals[0] if len(vals) == 1 else vals


def _names(prim: Usd.Prim, name: str, time: Usd.TimeCode) -> list[str] | None:
    """A token[]/string[] or a comma/space-separated string (Blender custom properties)."""
    v = _value(prim, name, time)
    if v is None:
        return None
    if isinstance(v, str):
        return [s for s in v.replace(",", " ").split() if s]
    if not isinstance(v, Sequence) and not hasattr(v, "__len__"):
        raise UsdSceneError(str(prim.GetPath()), name, f"must be a list of names (token[] or string), got {v!r}")
    return [str(s) for s in v]


# ------------------------------------------------------------------ the converter


#: A PointInstancer's prototype indices, drawn mask and instance transforms (in its own
#: space), and, by prototype index, what the prototype holds: (prim, type name, transform
#: below the prototype's root).
_InstancerPlan = tuple[list[int], list[bool], list[Gf.Matrix4d], dict[int, list[tuple[Usd.Prim, str, Gf.Matrix4d]]]]


class _Converter:
    def __init__(self, stage: Usd.Stage, time: Usd.TimeCode) -> None:
        self.stage = stage
        self.time = time
        self.skipped: list[dict[str, str]] = []
        self.notes: list[str] = []
        self.untinted: list[str] = []
        up = UsdGeom.GetStageUpAxis(stage)
        if up not in (UsdGeom.Tokens.y, UsdGeom.Tokens.z):
            raise UsdSceneError("/", "upAxis", f"must be Y or Z, got {up!r}")
        mpu = float(UsdGeom.GetStageMetersPerUnit(stage))
        if not math.isfinite(mpu) or not 1e-9 <= mpu <= 1e9:
            # (Beyond that every length overflows or vanishes on the way to metres, and the
            # error would surface later at a field the stage never wrote.)
            raise UsdSceneError("/", "metersPerUnit", f"must be within 1e-9..=1e9 (m per stage unit), got {mpu:g}")
        self.mpu = mpu
        self.up = str(up)
        self.to_world = _geom.stage_to_world(up, mpu)
        self.xf_cache = UsdGeom.XformCache(time)
        self.bbox_cache = UsdGeom.BBoxCache(time, [UsdGeom.Tokens.default_, UsdGeom.Tokens.render])
        self.from_blender = "Blender" in (stage.GetRootLayer().documentation or "")
        #: Stage-space local → world matrix of the PointInstancer instance being converted
        #: (``None`` outside :meth:`point_instancer`): it replaces the prim's own.
        self.instance_matrix: Gf.Matrix4d | None = None
        #: Each PointInstancer's instances and prototypes' contents (:meth:`instancer_plan`),
        #: and each prototype mesh converted once, by path.
        self.instancer_plans: dict[str, _InstancerPlan] = {}
        self.prototype_meshes: dict[Sdf.Path, dict[str, Any] | None] = {}
        #: Prims a PointInstancer drew at one of its instances at least once: a hidden
        #: container of prototypes does not make them prims left out.
        self.placed: set[str] = set()
        #: The entries of ``skipped`` for prims invisible at their own place on the stage.
        self.invisible_in_place: list[dict[str, str]] = []
        #: The meshes and media a linking collection could leave out (read at the first light).
        self.linkable: list[Sdf.Path] | None = None
        if up == UsdGeom.Tokens.y:
            self.notes.append("Y-up stage: rotated +90° about X into Tyndall's Z-up world (as Blender imports it)")
        if mpu != 1.0:
            self.notes.append(f"metersPerUnit = {mpu}: lengths scaled to metres")

    def skip(self, prim: Usd.Prim, reason: str) -> None:
        self.skipped.append({"prim": str(prim.GetPath()), "reason": reason})

    # -- transforms

    def world_matrix(self, prim: Usd.Prim) -> Gf.Matrix4d:
        """Local → Tyndall world (row-vector convention), checked to be finite and invertible."""
        instance = self.instance_matrix
        m = (instance if instance is not None else self.xf_cache.GetLocalToWorldTransform(prim)) * self.to_world
        if instance is not None and _geom.is_finite_matrix(m) and abs(_geom.det3(m)) > 1e-300:
            return m
        if _geom.is_finite_matrix(m) and abs(_geom.det3(m)) > 1e-300 and m.GetColumn(3) == Gf.Vec4d(0, 0, 0, 1):
            return m
        # Name the prim whose own xform ops are at fault.
        p = prim
        while p and not p.IsPseudoRoot():
            xf = UsdGeom.Xformable(p)
            if xf:
                local = xf.GetLocalTransformation(self.time)
                if not _geom.is_finite_matrix(local) or abs(_geom.det3(local)) <= 1e-300:
                    order = [str(op.GetOpName()) for op in xf.GetOrderedXformOps()]
                    raise UsdSceneError(
                        str(p.GetPath()),
                        "xformOpOrder",
                        f"non-invertible or non-finite transform (ops {order}, determinant {_geom.det3(local):.3g})",
                    )
            p = p.GetParent()
        raise UsdSceneError(str(prim.GetPath()), "xformOpOrder", "non-invertible, non-finite or projective transform")

    # -- lights

    def object_name(self, prim: Usd.Prim) -> str:
        """The Blender object's name for a light Blender exported as an object Xform holding
        the light data prim (named after the data); the prim's own name otherwise."""
        parent = prim.GetParent()
        if (
            _authored(prim, "userProperties:blender:data_name")
            and parent
            and _authored(parent, "userProperties:blender:object_name")
            and len(parent.GetChildren()) == 1
        ):
            return parent.GetName()
        return prim.GetName()

    def light_color(self, prim: Usd.Prim) -> list[float]:
        path = str(prim.GetPath())
        color = _vec(prim, "inputs:color", self.time, 3, (1.0, 1.0, 1.0))
        for c in color:
            if c < 0.0:
                raise UsdSceneError(path, "inputs:color", f"components must be ≥ 0, got {color}")
        if _bool(prim, "inputs:enableColorTemperature", self.time, False):
            authored = _authored(prim, "inputs:colorTemperature")
            if self.from_blender and not authored:
                # Blender 5.0 writes enableColorTemperature = 1 for every light, whether or not
                # Use Temperature is on, and writes colorTemperature only when it is not 6500 K.
                self.untinted.append(path)
            else:
                t = _float(prim, "inputs:colorTemperature", self.time, 6500.0)
                if t <= 0.0:
                    raise UsdSceneError(path, "inputs:colorTemperature", f"must be > 0 K, got {t}")
                tint = UsdLux.BlackbodyTemperatureAsRgb(t)
                color = [c * float(k) for c, k in zip(color, tint, strict=True)]
                self.notes.append(f"{path}: colour multiplied by the {t:g} K blackbody colour {tuple(tint)}")
        return color

    def intensity_and_exposure(self, prim: Usd.Prim) -> float:
        path = str(prim.GetPath())
        intensity = _float(prim, "inputs:intensity", self.time, 1.0)
        if intensity < 0.0:
            raise UsdSceneError(path, "inputs:intensity", f"must be ≥ 0, got {intensity}")
        exposure = _float(prim, "inputs:exposure", self.time, 0.0)
        try:
            scaled = intensity * 2.0**exposure
        except OverflowError:
            scaled = math.inf
        if not math.isfinite(scaled):
            raise UsdSceneError(
                path, "inputs:exposure", f"intensity {intensity:g} × 2^{exposure:g} overflows: give a smaller exposure"
            )
        return scaled

    def sphere_light(self, prim: Usd.Prim) -> dict[str, Any] | None:
        path = str(prim.GetPath())
        m = self.world_matrix(prim)
        radius = _float(prim, "inputs:radius", self.time, 0.5)
        if radius < 0.0:
            raise UsdSceneError(path, "inputs:radius", f"must be ≥ 0, got {radius}")
        if _bool(prim, "treatAsPoint", self.time, False):
            radius = 0.0
        radius_m = radius * _geom.mean_axis_scale(m)
        power = self.intensity_and_exposure(prim) * math.pi
        if not _bool(prim, "inputs:normalize", self.time, False):
            # Not normalised (the UsdLux default; Blender's exporter writes `normalize = 1` only for
            # lights with Normalize on): Blender's importer keeps the flag, and Cycles then does not
            # divide the power by the light's area 4πr², r the light's own radius (neither the
            # transform nor metersPerUnit enter), or 4 for r = 0 (Cycles' `Light::area`).
            factor = 4.0 * math.pi * radius * radius if radius > 0.0 else 4.0
            power *= factor
            self.notes.append(
                f"{path}: inputs:normalize is off: power × {factor:.6g} (the area Cycles does not divide by)"
            )
        pos = m.ExtractTranslation()
        light: dict[str, Any] = {
            "name": self.object_name(prim),
            "position": [float(pos[0]), float(pos[1]), float(pos[2])],
            "orientation": {"quaternion_wxyz": _geom.frame_quaternion(m)},
            "color": self.light_color(prim),
            "power_w": power,
            "radius_m": radius_m,
        }
        ies = self.ies(prim)
        if ies is False:
            return None
        if ies:
            light["ies"] = ies
        scales = [_geom.axis(m, i).GetLength() for i in range(3)]
        shaped = bool(ies) or prim.HasAPI(UsdLux.ShapingAPI)
        if shaped and max(scales) > min(scales) * (1.0 + 1e-6):
            self.notes.append(
                f"{path}: non-uniform scale ({', '.join(f'{k:.4g}' for k in scales)}): its cone or profile is read "
                "unstretched (only the orientation is kept; Blender would stretch a spot's cone into an ellipse)"
            )
        if not self.casts_shadows(prim):
            light["casts_shadows"] = False
        self.note_linking(prim)

        # Shaping inputs count where authored, with or without the ShapingAPI schema applied
        # (UsdImaging reads a light's inputs by name; `ies` above does the same).
        shaping_inputs = [
            n
            for n in ("inputs:shaping:focus", "inputs:shaping:cone:angle", "inputs:shaping:cone:softness")
            if _authored(prim, n)
        ]
        has_shaping = prim.HasAPI(UsdLux.ShapingAPI) or bool(shaping_inputs)
        if shaping_inputs and not prim.HasAPI(UsdLux.ShapingAPI):
            self.notes.append(f"{path}: {', '.join(shaping_inputs)} read although ShapingAPI is not applied")
        focus = _float(prim, "inputs:shaping:focus", self.time, 0.0) if has_shaping else 0.0
        if focus < 0.0:
            self.notes.append(f"{path}: inputs:shaping:focus = {focus:g} < 0 is ignored (UsdLux), read as 0")
            focus = 0.0
        if has_shaping and _authored(prim, "inputs:shaping:focusTint"):
            tint = _vec(prim, "inputs:shaping:focusTint", self.time, 3, (0.0, 0.0, 0.0))
            if any(t != 0.0 for t in tint) and focus > 0.0:
                self.skip(prim, "unsupported shaping: inputs:shaping:focusTint (off-axis tint)")
                return None
        cone_authored = has_shaping and _authored(prim, "inputs:shaping:cone:angle")
        if not cone_authored and focus == 0.0:
            return {"type": "point", **light}
        angle = _float(prim, "inputs:shaping:cone:angle", self.time, 90.0)
        if angle > 180.0:
            # (UsdLux sets no upper limit: a cone past 180° from the axis excludes nothing.)
            self.notes.append(f"{path}: inputs:shaping:cone:angle = {angle:g}° read as 180° (it excludes nothing)")
            angle = 180.0
        if not 0.05 <= angle <= 180.0:
            raise UsdSceneError(path, "inputs:shaping:cone:angle", f"must be ≥ 0.05 degrees, got {angle}")
        softness = _float(prim, "inputs:shaping:cone:softness", self.time, 0.0)
        if not 0.0 <= softness <= 1.0:
            raise UsdSceneError(path, "inputs:shaping:cone:softness", f"must be in 0..=1, got {softness}")
        if focus == 0.0 and angle <= 90.0:
            # Blender's spot: cone angle = Spot Size / 2, softness = Blend — as Blender's importer
            # reads it, and as Cycles' own Hydra delegate does (spot_angle = 2·angle,
            # spot_smooth = softness): the blend ramps in cos θ, not UsdLux's smoothstep in θ.
            if softness > 0.0 and not self.from_blender:
                self.notes.append(
                    f"{path}: cone softness {softness:g} read as Cycles reads it (Blender's spot blend, a ramp in "
                    "cos θ), not as UsdLux's smoothstep in θ"
                )
            return {"type": "spot", **light, "spot_size_deg": 2.0 * angle, "spot_blend": softness}
        self.notes.append(
            f"{path}: shaping (cone {angle:g}°, softness {softness:g}, focus {focus:g}) is not a Blender spot: "
            "read as a point light with the UsdLux shaping distribution"
        )
        light["distribution"] = {
            "type": "usd_shaping",
            "cone_angle_deg": min(angle, 180.0),
            "cone_softness": softness,
            "focus": focus,
        }
        return {"type": "point", **light}

    def ies(self, prim: Usd.Prim) -> dict[str, Any] | None | bool:
        """The ``ies`` object, ``None`` without a profile, ``False`` if the light must be skipped."""
        path = str(prim.GetPath())
        attr = prim.GetAttribute("inputs:shaping:ies:file")
        if not attr or not attr.HasAuthoredValue():
            return self.ies_from_custom_property(prim)
        asset = attr.Get(self.time)
        if asset is None or not asset.path:
            return self.ies_from_custom_property(prim)
        scale = _float(prim, "inputs:shaping:ies:angleScale", self.time, 0.0)
        if scale != 0.0:
            self.skip(prim, f"unsupported shaping: inputs:shaping:ies:angleScale = {scale:g} (only 0 is supported)")
            return False
        resolved = asset.resolvedPath
        if not resolved or not os.path.isfile(resolved):
            raise UsdSceneError(path, "inputs:shaping:ies:file", f"IES file {asset.path!r} not found")
        if _bool(prim, "inputs:shaping:ies:normalize", self.time, False):
            self.notes.append(f"{path}: inputs:shaping:ies:normalize is ignored (the profile is used as written)")
        strength = _float(prim, NS + "ies:strength", self.time, 1.0)
        if strength < 0.0:
            raise UsdSceneError(path, NS + "ies:strength", f"must be ≥ 0, got {strength}")
        return {"file": os.path.abspath(resolved), "strength": strength}

    def ies_from_custom_property(self, prim: Usd.Prim) -> dict[str, Any] | None:
        """``tyndall:ies:file`` (string; relative to the layer): Blender's exporter writes no IES
        shaping, so the add-on sets this custom property on the light data, which Blender
        exports on the SphereLight prim (and its importer brings back)."""
        path = str(prim.GetPath())
        name = _text(prim, NS + "ies:file", self.time, "")
        if not name:
            return None
        # Relative to the layer that authored the value (a referenced asset's own folder),
        # as an asset path would be resolved.
        stack = prim.GetAttribute(NS + "ies:file").GetPropertyStack(self.time)
        layer = stack[0].layer if stack else prim.GetStage().GetRootLayer()
        if os.path.isabs(name):
            file = name
        elif layer.realPath:
            file = layer.ComputeAbsolutePath(name)
        else:
            file = os.path.join(os.getcwd(), name)
        if not os.path.isfile(file):
            raise UsdSceneError(path, NS + "ies:file", f"IES file {name!r} not found (resolved to {file})")
        strength = _float(prim, NS + "ies:strength", self.time, 1.0)
        if strength < 0.0:
            raise UsdSceneError(path, NS + "ies:strength", f"must be ≥ 0, got {strength}")
        return {"file": os.path.abspath(file), "strength": strength}

    def note_linking(self, prim: Usd.Prim) -> None:
        """A note for a light whose light-linking or shadow-linking collection leaves
        anything out: Tyndall lights every medium and lets every mesh shadow every light."""
        lux = UsdLux.LightAPI(prim)
        if self.linkable is None:
            # What a collection could leave out that Tyndall draws: meshes and media.
            self.linkable = [
                p.GetPath()
                for p in self.stage.Traverse(Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate))
                if p.IsA(UsdGeom.Mesh) or _authored(p, NS + "medium:type")
            ]
        for what, coll in (
            ("light linking", lux.GetLightLinkCollectionAPI()),
            ("shadow linking", lux.GetShadowLinkCollectionAPI()),
        ):
            include_root = coll.GetIncludeRootAttr().Get(self.time)
            if (include_root is None or include_root) and not coll.GetExcludesRel().GetTargets():
                continue  # the fallback: everything is in the collection
            query = coll.ComputeMembershipQuery()
            if all(query.IsPathIncluded(p) for p in self.linkable):
                continue  # (includes that name every mesh and medium leave nothing out)
            self.notes.append(
                f"{prim.GetPath()}: its {what} collection ({coll.GetName()}) is not applied: "
                + ("it lights every medium" if what == "light linking" else "every mesh shadows it")
            )

    def casts_shadows(self, prim: Usd.Prim) -> bool:
        """``tyndall:castsShadows`` (which the add-on writes, as Blender's exporter writes no
        shadow switch), else UsdLux ShadowAPI ``inputs:shadow:enable``."""
        own = self.tyndall_flag(prim, "castsShadows")
        return own if own is not None else _bool(prim, "inputs:shadow:enable", self.time, True)

    def tyndall_flag(self, prim: Usd.Prim, name: str) -> bool | None:
        """``tyndall:<name>`` on the prim or, if not there, its parent (an object's custom
        property lands on the Xform Blender writes for it); ``None`` where neither has it."""
        for p in (prim, prim.GetParent()):
            if _authored(p, NS + name):
                return _bool(p, NS + name, self.time, True)
        return None

    def distant_light(self, prim: Usd.Prim) -> dict[str, Any]:
        path = str(prim.GetPath())
        m = self.world_matrix(prim)
        to_sun = _geom.axis(m, 2).GetNormalized()  # the light travels along its local −Z
        angle = _float(prim, "inputs:angle", self.time, 0.53)
        if not 0.0 <= angle <= 90.0:
            raise UsdSceneError(path, "inputs:angle", f"must be in 0..=90 degrees, got {angle}")
        strength = self.intensity_and_exposure(prim) * 4.0
        if not _bool(prim, "inputs:normalize", self.time, False):
            # As for sphere lights: Cycles does not divide by the sun's disc π·sin²(angle) (1 for 0).
            area = math.pi * math.sin(math.radians(angle)) ** 2
            factor = area if area > 0.0 else 1.0
            strength *= factor
            if factor != 1.0:
                dim = (
                    f": the sun gives {strength:.4g} W/m², nearly dark as UsdLux defines it and as Blender + "
                    "Cycles render it; if the stage's tool meant inputs:intensity as the sun's strength, "
                    "author inputs:normalize = 1"
                    if factor < 0.01
                    else ""
                )
                self.notes.append(
                    f"{path}: inputs:normalize is off: strength × {factor:.6g} "
                    f"(the disc Cycles does not divide by){dim}"
                )
        return {
            "type": "sun",
            "name": self.object_name(prim),
            "direction_to_sun": [float(to_sun[0]), float(to_sun[1]), float(to_sun[2])],
            "color": self.light_color(prim),
            "strength_w_m2": strength,
            "angular_diameter_deg": 2.0 * angle,
        }

    def dome_light(self, prim: Usd.Prim) -> dict[str, Any] | None:
        tex = _value(prim, "inputs:texture:file", self.time)
        if tex is not None and tex.path:
            self.skip(
                prim,
                f"textured DomeLight ({tex.path}): Tyndall's ambient light is uniform (an untextured DomeLight "
                "is read as an ambient light)",
            )
            return None
        return {
            "type": "ambient",
            "name": self.object_name(prim),
            "color": self.light_color(prim),
            "radiance": self.intensity_and_exposure(prim),
        }

    # -- meshes

    def mesh(self, prim: Usd.Prim) -> dict[str, Any] | None:
        path = str(prim.GetPath())
        mesh = UsdGeom.Mesh(prim)
        pts = mesh.GetPointsAttr().Get(self.time)
        counts = mesh.GetFaceVertexCountsAttr().Get(self.time)
        indices = mesh.GetFaceVertexIndicesAttr().Get(self.time)
        if not pts or not counts or not indices:
            self.skip(prim, "mesh with no faces")
            return None
        points = np.asarray(pts, dtype=float).reshape(-1, 3)
        counts_a = np.asarray(counts, dtype=np.int64)
        idx = np.asarray(indices, dtype=np.int64)
        if not np.all(np.isfinite(points)):
            raise UsdSceneError(path, "points", "contains NaN or infinite coordinates")
        if int(counts_a.sum()) != len(idx) or np.any(counts_a < 0):
            raise UsdSceneError(path, "faceVertexCounts", f"sum {int(counts_a.sum())} ≠ {len(idx)} face-vertex indices")
        if len(idx) and (idx.min() < 0 or idx.max() >= len(points)):
            raise UsdSceneError(path, "faceVertexIndices", f"index out of range for {len(points)} points")
        holes = set(int(h) for h in (mesh.GetHoleIndicesAttr().Get(self.time) or []))
        small = int(np.count_nonzero(counts_a < 3))
        if small:
            self.notes.append(f"{path}: {small} faces with fewer than 3 vertices left out")
        tris = _geom.triangulate(points, counts_a, idx, holes)
        if not tris:
            self.skip(prim, "mesh with no faces")
            return None
        if mesh.GetOrientationAttr().Get(self.time) == UsdGeom.Tokens.leftHanded:
            tris = [[a, c, b] for a, b, c in tris]
        m = self.world_matrix(prim)
        if prim.HasAPI(UsdLux.LightAPI):
            # (A mesh light emits from its surface: Tyndall's lights are points, spots, suns
            # and windows. The mesh itself still blocks light, as it does in Cycles.)
            self.skip(prim, "mesh light (UsdLux MeshLightAPI): its emission is not supported; kept as an occluder")
        scheme_attr = mesh.GetSubdivisionSchemeAttr()
        scheme = scheme_attr.Get(self.time)
        if scheme_attr.HasAuthoredValue() and scheme != UsdGeom.Tokens.none:
            # (Only where authored: the fallback, catmullClark, is on most polygon meshes, and
            # Blender 5.0.1's importer, like Hydra at refine level 0, draws their cage too.)
            self.notes.append(
                f"{path}: subdivisionScheme {scheme}: its control cage is used as it stands (Tyndall does not "
                "subdivide; nor does Blender's importer unless Import Subdivision is on)"
            )
        out: dict[str, Any] = {
            "name": prim.GetName(),
            "positions": points.tolist(),
            "triangles": tris,
            "transform": {"matrix": _geom.to_row_major(m)},
        }
        # Ray visibility: no UsdGeom schema holds it; the add-on writes these.
        for attr, key in (("visibleToCamera", "visible_to_camera"), ("castsShadows", "casts_shadows")):
            if self.tyndall_flag(prim, attr) is False:
                out[key] = False
        return out

    # -- camera

    def camera(self, prim: Usd.Prim, resolution: list[int] | None, render: list[Usd.Prim]) -> dict[str, Any]:
        path = str(prim.GetPath())
        cam = UsdGeom.Camera(prim)
        proj = cam.GetProjectionAttr().Get(self.time)
        if proj != UsdGeom.Tokens.perspective:
            raise UsdSceneError(path, "projection", f"only perspective cameras are supported, got {proj!r}")
        k = 100.0 * self.mpu  # USD camera lengths are in tenths of a scene unit
        focal = _float(prim, "focalLength", self.time, 50.0) * k
        h_ap = _float(prim, "horizontalAperture", self.time, 20.955) * k
        v_ap = _float(prim, "verticalAperture", self.time, 15.2908) * k
        h_off = _float(prim, "horizontalApertureOffset", self.time, 0.0) * k
        v_off = _float(prim, "verticalApertureOffset", self.time, 0.0) * k
        for name, v in (("focalLength", focal), ("horizontalAperture", h_ap), ("verticalAperture", v_ap)):
            if v <= 0.0:
                raise UsdSceneError(path, name, f"must be > 0, got {v / k}")
        if resolution is None:
            w = DEFAULT_WIDTH
            resolution = [w, max(1, round(w * v_ap / h_ap))]
            self.notes.append(
                f"no resolution on the stage (Blender does not export it): {resolution[0]}×{resolution[1]} "
                "from the aperture aspect; set tyndall:output:resolution"
            )
        for r in render:
            attr = r.GetAttribute("pixelAspectRatio")
            if attr and attr.HasAuthoredValue():
                par = _float(r, "pixelAspectRatio", self.time)
                if abs(par - 1.0) > 1e-6:
                    raise UsdSceneError(
                        str(r.GetPath()), "pixelAspectRatio", f"only square pixels (1) are supported, got {par:g}"
                    )
                break
        policy = "expandAperture"  # UsdRender's fallback
        where = ""
        for r in render:
            if _authored(r, "aspectRatioConformPolicy"):
                policy, where = _text(r, "aspectRatioConformPolicy", self.time), f"{r.GetPath()}."
                break
        img_aspect = resolution[0] / resolution[1]
        ap_aspect = h_ap / v_ap
        if abs(img_aspect - ap_aspect) <= 1e-4 * img_aspect:
            fit = "horizontal" if resolution[0] >= resolution[1] else "vertical"
        else:
            # UsdRender's aspectRatioConformPolicy: which side of the aperture is kept (the
            # other follows the image's aspect).
            wider = img_aspect > ap_aspect
            fits = {
                "expandAperture": ("vertical" if wider else "horizontal", "the aperture expanded"),
                "cropAperture": ("horizontal" if wider else "vertical", "the aperture cropped"),
                "adjustApertureWidth": ("vertical", "its width adjusted"),
                "adjustApertureHeight": ("horizontal", "its height adjusted"),
            }
            if policy not in fits:
                raise UsdSceneError(
                    where.rstrip(".") or path,
                    "aspectRatioConformPolicy",
                    f"{policy!r} is not supported (expandAperture, cropAperture, adjustApertureWidth, "
                    "adjustApertureHeight; square pixels only)",
                )
            fit, how = fits[policy]
            self.notes.append(
                f"{path}: aperture aspect {ap_aspect:.4g} ≠ image aspect {img_aspect:.4g}: {how} "
                f"({where}aspectRatioConformPolicy = {policy})"
            )
        side = h_ap if fit == "horizontal" else v_ap
        near, far = _vec(prim, "clippingRange", self.time, 2, (1.0, 1e6))
        if near < 0.0 or far <= near:
            raise UsdSceneError(path, "clippingRange", f"needs 0 ≤ near < far, got ({near}, {far})")
        m = self.world_matrix(prim)
        scale = _geom.mean_axis_scale(m)
        pos = m.ExtractTranslation()
        return {
            "type": "perspective",
            "position": [float(pos[0]), float(pos[1]), float(pos[2])],
            "orientation": {"quaternion_wxyz": _geom.frame_quaternion(m)},
            "focal_length_mm": focal,
            "sensor_width_mm": h_ap,
            "sensor_height_mm": v_ap,
            "sensor_fit": fit,
            "shift_x": h_off / side,
            "shift_y": v_off / side,
            "resolution": list(resolution),
            "clip_start_m": near * scale,
            "clip_end_m": far * scale if math.isfinite(far) else None,
        }

    # -- media

    def medium(self, prim: Usd.Prim) -> dict[str, Any]:
        path = str(prim.GetPath())
        t = self.time
        kind = _text(prim, NS + "medium:type", t)
        name = _text(prim, NS + "medium:name", t, prim.GetName())
        if kind == "homogeneous":
            med: dict[str, Any] = {
                "type": "homogeneous",
                "name": name,
                "scattering": _coefficient(prim, NS + "medium:scattering", t, None),
                "absorption": _coefficient(prim, NS + "medium:absorption", t, 0.0),
                "phase": self.phase(prim, NS + "medium:phase", "isotropic", None),
            }
            bounds = _text(prim, NS + "medium:bounds", t, "world")
            if bounds == "box":
                med["bounds"] = {"box": self.box(prim)}
            elif bounds != "world":
                raise UsdSceneError(path, NS + "medium:bounds", f"must be 'world' or 'box', got {bounds!r}")
            return med
        if kind == "height_fog":
            med = {
                "type": "height_fog",
                "name": name,
                "scale_height_m": _float(prim, NS + "medium:scaleHeightM", t),
                "reference_height_m": _float(prim, NS + "medium:referenceHeightM", t, 0.0),
            }
            if _value(prim, NS + "medium:rayleighScattering", t) is not None:
                med["rayleigh"] = {
                    "scattering": _coefficient(prim, NS + "medium:rayleighScattering", t, None),
                    "absorption": _coefficient(prim, NS + "medium:rayleighAbsorption", t, 0.0),
                }
            if _value(prim, NS + "medium:mieScattering", t) is not None:
                med["mie"] = {
                    "scattering": _coefficient(prim, NS + "medium:mieScattering", t, None),
                    "absorption": _coefficient(prim, NS + "medium:mieAbsorption", t, 0.0),
                    "phase": self.phase(prim, NS + "medium:miePhase", "cornette_shanks", 0.76),
                }
            return med
        raise UsdSceneError(path, NS + "medium:type", f"must be 'homogeneous' or 'height_fog', got {kind!r}")

    def phase(self, prim: Usd.Prim, name: str, default: str, default_g: float | None) -> dict[str, Any]:
        kind = _text(prim, name, self.time, default)
        if kind not in _PHASES:
            raise UsdSceneError(str(prim.GetPath()), name, f"must be one of {sorted(_PHASES)}, got {kind!r}")
        if kind in ("henyey_greenstein", "cornette_shanks"):
            g = _float(prim, name + "G", self.time, default_g if kind == default else None)
            if not -1.0 < g < 1.0:
                raise UsdSceneError(str(prim.GetPath()), name + "G", f"must be in (-1, 1), got {g}")
            return {"type": kind, "g": g}
        return {"type": kind}

    def box(self, prim: Usd.Prim) -> dict[str, list[float]]:
        # Every purpose: the box's geometry is a helper, and may be a guide (write_stage's is).
        every = [UsdGeom.Tokens.default_, UsdGeom.Tokens.render, UsdGeom.Tokens.proxy, UsdGeom.Tokens.guide]
        cache = UsdGeom.BBoxCache(self.time, every)
        # One geometry prim, turned with its transform: the box turned with it.
        geometry = [p for p in Usd.PrimRange(prim) if p.IsA(UsdGeom.Gprim)]
        if len(geometry) == 1:
            bound = cache.ComputeWorldBound(geometry[0])
            local = bound.GetRange()
            if not local.IsEmpty():
                turned, why = _geom.turned_box(bound.GetMatrix() * self.to_world, local.GetMin(), local.GetMax())
                if turned is not None:
                    return turned
                if why == "sheared":
                    self.notes.append(
                        f"{prim.GetPath()}: the medium's box is sheared by its transform; "
                        "its world-space axis-aligned bounding box is used"
                    )
        elif len(geometry) > 1:
            self.notes.append(
                f"{prim.GetPath()}: the medium has {len(geometry)} geometry prims; "
                "their common world-space axis-aligned bounding box is its box"
            )
        rng = cache.ComputeWorldBound(prim).ComputeAlignedRange()
        if rng.IsEmpty():
            raise UsdSceneError(str(prim.GetPath()), NS + "medium:bounds", "'box' needs a prim with geometry (extent)")
        corners = [self.to_world.Transform(rng.GetCorner(i)) for i in range(8)]
        lo = [min(float(c[i]) for c in corners) for i in range(3)]
        hi = [max(float(c[i]) for c in corners) for i in range(3)]
        return {"min": lo, "max": hi}

    # -- settings

    def settings_prim(self, prims: list[Usd.Prim]) -> Usd.Prim | None:
        carriers = [
            p
            for p in prims
            if any(a.GetName().startswith((NS + "output:", NS + "sky:")) for a in p.GetAuthoredAttributes())
            or any(r.GetName().startswith(NS + "output:") for r in p.GetAuthoredRelationships())
        ]
        if len(carriers) > 1:
            paths = ", ".join(str(p.GetPath()) for p in carriers)
            raise UsdSceneError(
                str(carriers[1].GetPath()), None, f"tyndall:output/sky settings on several prims: {paths}"
            )
        return carriers[0] if carriers else None

    def output(self, prim: Usd.Prim | None) -> dict[str, Any]:
        if prim is None:
            return {}
        path = str(prim.GetPath())
        t = self.time
        out: dict[str, Any] = {}
        layers = _names(prim, NS + "output:layers", t)
        if layers is not None:
            bad = [x for x in layers if x not in _LAYERS]
            if bad or not layers:
                raise UsdSceneError(
                    path, NS + "output:layers", f"must be non-empty, from {sorted(_LAYERS)}, got {layers}"
                )
            out["layers"] = layers
        if _value(prim, NS + "output:tolerance", t) is not None:
            out["tolerance"] = _float(prim, NS + "output:tolerance", t)
        if _value(prim, NS + "output:threads", t) is not None:
            out["threads"] = int(_float(prim, NS + "output:threads", t))
        if _value(prim, NS + "output:spectral", t) is not None:
            out["spectral"] = _text(prim, NS + "output:spectral", t)
        return out

    def resolution(self, prim: Usd.Prim | None, render: list[Usd.Prim]) -> list[int] | None:
        for p, name in ((prim, NS + "output:resolution"), *((r, "resolution") for r in render)):
            if p is None:
                continue
            v = _value(p, name, self.time)
            if v is None or (name == "resolution" and not _authored(p, name)):
                continue
            try:
                res = [int(x) for x in v]
                ok = len(res) == 2 and all(1 <= x <= 65536 and x == float(y) for x, y in zip(res, v, strict=True))
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise UsdSceneError(str(p.GetPath()), name, f"must be two integers in 1..=65536, got {v!r}")
            return res
        return None

    def sky(self, prim: Usd.Prim | None, lights: list[dict[str, Any]]) -> SkySettings | None:
        if prim is None or not _bool(prim, NS + "sky:enabled", self.time, False):
            return None
        path = str(prim.GetPath())
        suns = [x for x in lights if x["type"] == "sun"]
        if not suns:
            raise UsdSceneError(path, NS + "sky:enabled", "the sky needs a DistantLight (the sun) on the stage")
        d = suns[0]["direction_to_sun"]
        t = self.time
        s = SkySettings(
            sun_elevation_deg=math.degrees(math.asin(max(-1.0, min(1.0, d[2])))),
            sun_rotation_deg=math.degrees(math.atan2(d[0], d[1])) % 360.0,
            sun_size_deg=suns[0]["angular_diameter_deg"],
            air=_float(prim, NS + "sky:air", t, 1.0),
            aerosol=_float(prim, NS + "sky:aerosol", t, 1.0),
            ozone=_float(prim, NS + "sky:ozone", t, 1.0),
            altitude_m=_float(prim, NS + "sky:altitudeM", t, 0.0),
            width=int(_float(prim, NS + "sky:widthPx", t, 1024.0)),
            tolerance=_float(prim, NS + "sky:tolerance", t, 1e-3),
            sun_disc=_bool(prim, NS + "sky:sunDisc", t, True),
        )
        return s

    # -- the whole stage

    def drawn(self, prim: Usd.Prim, type_name: str) -> bool:
        """False, and the prim listed as skipped, for an invisible prim or a guide or proxy."""
        img = UsdGeom.Imageable(prim)
        if img and img.ComputeVisibility(self.time) == UsdGeom.Tokens.invisible:
            self.skip(prim, f"invisible {type_name}")
            self.invisible_in_place.append(self.skipped[-1])
            return False
        if img and img.ComputePurpose() in (UsdGeom.Tokens.guide, UsdGeom.Tokens.proxy):
            self.skip(prim, f"{type_name} with purpose {img.ComputePurpose()}")
            return False
        return True

    def light_or_mesh(self, prim: Usd.Prim, type_name: str) -> tuple[str, dict[str, Any] | None]:
        """``("light", …)``, ``("mesh", …)`` (``None`` where the prim turned out unusable and
        is listed as skipped), or ``("", None)`` for a prim that is neither (listed too, unless
        it only structures the stage)."""
        if type_name == "SphereLight":
            return "light", self.sphere_light(prim)
        if type_name == "DistantLight":
            return "light", self.distant_light(prim)
        if type_name in ("DomeLight", "DomeLight_1"):
            return "light", self.dome_light(prim)
        if type_name == "Mesh":
            return "mesh", self.mesh(prim)
        if type_name in _UNSUPPORTED_LIGHTS:
            self.skip(prim, f"{type_name} is not supported (Tyndall has point, spot and sun lights)")
        elif type_name == "Volume":
            self.skip(prim, "Volume without tyndall:medium attributes (OpenVDB grids are not read)")
        elif type_name not in _STRUCTURAL and (UsdGeom.Imageable(prim) or prim.HasAPI(UsdLux.LightAPI)):
            self.skip(prim, f"{type_name} prims are not supported")
        return "", None

    def point_instancer(
        self,
        prim: Usd.Prim,
        base: Gf.Matrix4d | None = None,
        suffix: str = "",
        outer: tuple[str, ...] = (),
    ) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[str]]:
        """The lights and meshes a PointInstancer places: every lamp and mesh under each
        prototype, once per instance that ``invisibleIds`` and ``inactiveIds`` leave drawn,
        at ``(its transform below the prototype) · (the instance's transform, which holds the
        prototype's own) · (the instancer's local → world)`` — UsdGeom.PointInstancer's
        ``ComputeInstanceTransformsAtTime``. A prototype is traversed as UsdImaging does:
        defined prims under it (also below an ``over``), its visibility and purpose from its
        root down. Instance ``i``'s copies are named ``<name>_<i>``; the light prims listed
        are the prototypes' (once per instance).

        A PointInstancer inside a prototype (nested instancing) places its own prototypes
        in every drawn instance of the outer one: it is called again with ``base`` its local
        → world matrix in that instance (``None``: its place on the stage), ``suffix`` the
        outer instances' numbers (copies of nested instances are named
        ``<name>_<outer>_<inner>``) and ``outer`` the instancers it is nested in (an
        instancer among its own prototypes is an error, not an endless loop)."""
        path = str(prim.GetPath())
        if path in outer:
            chain = " → ".join((*outer, path))
            raise UsdSceneError(path, "prototypes", f"the instancer is among its own prototypes ({chain})")
        plan = self.instancer_plans.get(path)
        if plan is None:
            plan = self.instancer_plan(prim)
            self.instancer_plans[path] = plan
        indices, mask, xforms, contents = plan
        lights: list[dict[str, Any]] = []
        meshes: list[dict[str, Any]] = []
        light_prims: list[str] = []
        if not indices:
            return lights, meshes, light_prims  # listed as skipped by instancer_plan
        if base is None:
            base = self.xf_cache.GetLocalToWorldTransform(prim)
            if not _geom.is_finite_matrix(base) or abs(_geom.det3(base)) <= 1e-300:
                self.world_matrix(prim)  # names the prim whose own xform ops are singular
        nested = 0
        try:
            for i, (k, drawn) in enumerate(zip(indices, mask, strict=True)):
                if not drawn:
                    continue
                x = xforms[i]
                if not _geom.is_finite_matrix(x) or abs(_geom.det3(x)) <= 1e-300:
                    raise UsdSceneError(
                        path, "scales", f"instance {i}'s transform is singular or not finite (a scale of 0?)"
                    )
                for q, type_name, rel in contents[k]:
                    m = rel * x * base
                    if type_name == "PointInstancer":
                        # (Its plan's checks name prims from the stage, not from this instance.)
                        self.instance_matrix = None
                        got = self.point_instancer(q, m, f"{suffix}_{i}", (*outer, path))
                        nested += len(got[0]) + len(got[1])
                        lights += got[0]
                        meshes += got[1]
                        light_prims += got[2]
                        continue
                    self.instance_matrix = m
                    self.placed.add(str(q.GetPath()))
                    name = f"{q.GetName()}{suffix}_{i}"
                    if type_name == "Mesh" and q.GetPath() in self.prototype_meshes:
                        # The same points and triangles: only the transform differs.
                        first = self.prototype_meshes[q.GetPath()]
                        if first is not None:
                            matrix = _geom.to_row_major(self.world_matrix(q))
                            meshes.append({**first, "name": name, "transform": {"matrix": matrix}})
                        continue
                    kind, obj = self.light_or_mesh(q, type_name)
                    if kind == "mesh":
                        self.prototype_meshes[q.GetPath()] = obj
                    if obj is None:
                        continue
                    obj["name"] = f"{obj['name']}{suffix}_{i}"
                    if kind == "mesh":
                        meshes.append(obj)
                    else:
                        lights.append(obj)
                        light_prims.append(str(q.GetPath()))
        finally:
            self.instance_matrix = None
        n_drawn = sum(mask)
        if outer:
            self.notes.append(
                f"{path}: PointInstancer nested in the prototypes of {outer[-1]}, "
                f"with {n_drawn} of {len(indices)} instances drawn in each of its instances"
            )
        else:
            through = f" ({nested} of them by nested PointInstancers)" if nested else ""
            self.notes.append(
                f"{path}: PointInstancer with {n_drawn} of {len(indices)} instances drawn: "
                f"{len(lights)} lights and {len(meshes)} meshes placed{through}"
            )
        return lights, meshes, light_prims

    def instancer_plan(self, prim: Usd.Prim) -> _InstancerPlan:
        """A PointInstancer's instances (prototype indices, drawn mask, transforms in its own
        space) and what each prototype it uses holds, with its transform below the
        prototype's root: the lamps, meshes and nested PointInstancers (read once, however
        many outer instances place it)."""
        path = str(prim.GetPath())
        inst = UsdGeom.PointInstancer(prim)
        protos = inst.GetPrototypesRel().GetTargets()
        indices = [int(k) for k in (inst.GetProtoIndicesAttr().Get(self.time) or [])]
        if not indices:
            self.skip(prim, "PointInstancer with no instances (protoIndices is empty)")
            return [], [], [], {}
        bad = next((k for k in indices if not 0 <= k < len(protos)), None)
        if bad is not None:
            raise UsdSceneError(path, "protoIndices", f"index {bad} is out of range for {len(protos)} prototypes")
        # USD only warns about (and then ignores) arrays of the wrong length but positions.
        for name in ("positions", "orientations", "orientationsf", "scales"):
            attr = prim.GetAttribute(name)
            n = len(attr.Get(self.time) or []) if attr and attr.HasAuthoredValue() else None
            if (n is not None or name == "positions") and n != len(indices):
                raise UsdSceneError(path, name, f"{n or 0} values for {len(indices)} instances (protoIndices)")
        # The earliest time code (the default) is no time to move points by their velocities:
        # the earliest sample of the positions is.
        at = self.time
        if at.IsEarliestTime():
            samples = inst.GetPositionsAttr().GetTimeSamples()
            at = Usd.TimeCode(samples[0]) if samples else Usd.TimeCode.Default()
        xforms = list(
            inst.ComputeInstanceTransformsAtTime(
                at, at, UsdGeom.PointInstancer.IncludeProtoXform, UsdGeom.PointInstancer.IgnoreMask
            )
        )
        if len(xforms) != len(indices):
            raise UsdSceneError(path, "positions", f"no instance transforms for {len(indices)} instances")
        mask = [bool(d) for d in inst.ComputeMaskAtTime(self.time)] or [True] * len(indices)
        proto_pred = Usd.TraverseInstanceProxies(Usd.PrimIsActive & Usd.PrimHasDefiningSpecifier)
        # What each prototype holds, with its transform below the prototype's root: the
        # product of the local transforms from the prim up to the root's child (exact, no
        # inverse; the root's own is in the instance's transform).
        contents: dict[int, list[tuple[Usd.Prim, str, Gf.Matrix4d]]] = {}
        for k in sorted(set(indices)):
            root = self.stage.GetPrimAtPath(protos[k])
            if not root:
                raise UsdSceneError(path, "prototypes", f"target {protos[k]} is not a prim on the stage")
            if not root.IsActive() or not root.HasDefiningSpecifier():
                what = "inactive" if not root.IsActive() else "not defined (an over)"
                self.skip(root, f"prototype {k} of the PointInstancer {path} is {what}: its instances are left out")
                contents[k] = []
                continue
            held: list[tuple[Usd.Prim, str, Gf.Matrix4d]] = []
            # Subtrees a prototype's walk does not enter: what it cannot hold, and nested
            # instancers (which place their own prototypes).
            closed: list[Sdf.Path] = []
            for q in Usd.PrimRange(root, proto_pred):
                type_name = str(q.GetTypeName())
                if any(q.GetPath().HasPrefix(n) for n in closed):
                    continue
                if _authored(q, NS + "medium:type") or type_name == "Camera":
                    closed.append(q.GetPath())
                    what = "a medium" if _authored(q, NS + "medium:type") else f"a {type_name}"
                    self.skip(q, f"{what} inside the prototype of the PointInstancer {path} is not supported")
                    continue
                if type_name in ("DomeLight", "DomeLight_1"):
                    self.skip(q, f"a DomeLight inside the prototype of the PointInstancer {path} is not supported")
                    continue
                if type_name == "PointInstancer":
                    closed.append(q.GetPath())
                if type_name in _STRUCTURAL or not self.drawn_in_prototype(q, root, type_name):
                    continue
                rel = Gf.Matrix4d(1.0)
                p = q
                while p != root:
                    xf = UsdGeom.Xformable(p)
                    if xf:
                        local, resets = self.xf_cache.GetLocalTransformation(p)
                        if resets:
                            self.skip(q, f"resetXformStack inside the prototype of the PointInstancer {path}")
                            break
                        rel = rel * local
                    p = p.GetParent()
                else:
                    if not _geom.is_finite_matrix(rel) or abs(_geom.det3(rel)) <= 1e-300:
                        self.world_matrix(q)  # names the prim whose own xform ops are singular
                    held.append((q, type_name, rel))
            contents[k] = held
        return indices, mask, xforms, contents

    def drawn_in_prototype(self, q: Usd.Prim, root: Usd.Prim, type_name: str) -> bool:
        """:meth:`drawn` for a prim of a PointInstancer's prototype, whose visibility and
        purpose come from the prototype's root down (as UsdImaging draws instances), not from
        the prims above it (a hidden container of prototypes hides no instance)."""
        purpose = None
        p = q
        while True:
            img = UsdGeom.Imageable(p)
            if img:
                if img.GetVisibilityAttr().Get(self.time) == UsdGeom.Tokens.invisible:
                    self.skip(q, f"invisible {type_name} (in a PointInstancer's prototype)")
                    return False
                attr = img.GetPurposeAttr()
                if purpose is None and attr.HasAuthoredValue():
                    purpose = attr.Get()
            if p == root:
                break
            p = p.GetParent()
        if purpose in (UsdGeom.Tokens.guide, UsdGeom.Tokens.proxy):
            self.skip(q, f"{type_name} with purpose {purpose} (in a PointInstancer's prototype)")
            return False
        return True

    def run(self) -> Conversion:
        pred = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
        prims = list(Usd.PrimRange(self.stage.GetPseudoRoot(), pred))[1:]
        lights: list[dict[str, Any]] = []
        light_prims: list[str] = []
        meshes: list[dict[str, Any]] = []
        media: list[dict[str, Any]] = []
        cameras: list[Usd.Prim] = []
        render_settings: list[Usd.Prim] = []
        medium_paths: list[Sdf.Path] = []
        instancers: list[Sdf.Path] = []
        for prim in prims:
            type_name = str(prim.GetTypeName())
            if any(prim.GetPath().HasPrefix(p) for p in instancers):
                continue  # under a PointInstancer: its prototypes are drawn only where it places them
            if _authored(prim, NS + "medium:type"):
                medium_paths.append(prim.GetPath())
                # (A medium prim is often typeless: its nearest imageable ancestor decides.)
                img_prim = prim
                while img_prim and not UsdGeom.Imageable(img_prim):
                    img_prim = img_prim.GetParent()
                img = UsdGeom.Imageable(img_prim) if img_prim else None
                if img and img.ComputeVisibility(self.time) == UsdGeom.Tokens.invisible:
                    self.skip(prim, "invisible medium")
                else:
                    media.append(self.medium(prim))
                continue
            owner = next((m for m in medium_paths if prim.GetPath().HasPrefix(m)), None)
            if owner is not None:
                if type_name not in _STRUCTURAL:
                    self.skip(prim, f"{type_name} inside the medium prim {owner}: it gives the medium's box only")
                continue
            if type_name == "PointInstancer":
                instancers.append(prim.GetPath())
                if self.drawn(prim, type_name):
                    got_lights, got_meshes, got_prims = self.point_instancer(prim)
                    lights += got_lights
                    meshes += got_meshes
                    light_prims += got_prims
                continue
            if type_name == "RenderSettings":
                render_settings.append(prim)
                continue
            if type_name in _STRUCTURAL:
                continue
            if type_name == "Camera":
                # (Visibility and purpose hide a camera's gizmo, not the view through it.)
                cameras.append(prim)
                continue
            if not self.drawn(prim, type_name):
                continue
            kind, obj = self.light_or_mesh(prim, type_name)
            if kind == "mesh" and obj is not None:
                meshes.append(obj)
            elif kind == "light" and obj is not None:
                lights.append(obj)
                light_prims.append(str(prim.GetPath()))

        settings = self.settings_prim(prims)
        render = self.render_sources(self.render_settings(render_settings))
        cam_prim = self.pick_camera(cameras, settings, render)
        res = self.resolution(settings, render)
        scene: dict[str, Any] = {
            "version": 1,
            "camera": self.camera(cam_prim, res, render),
            "meshes": meshes,
            "lights": lights,
            "media": media,
        }
        out = self.output(settings)
        if out:
            scene["output"] = out
        sky = self.sky(settings, lights)
        if self.untinted:
            self.notes.append(
                "Blender export: enableColorTemperature is written for every light, so it is ignored where "
                f"colorTemperature is not authored (no tint): {', '.join(dict.fromkeys(self.untinted))}"
            )
        # (A PointInstancer's instances repeat their prototype's notes and skips.) A prototype
        # under a hidden container is drawn where its instancer places it: it was left out
        # only at its own place, so it is not listed as an invisible prim.
        drawn_elsewhere = {id(d) for d in self.invisible_in_place if d["prim"] in self.placed}
        unique = dict.fromkeys(tuple(d.items()) for d in self.skipped if id(d) not in drawn_elsewhere)
        skipped = [dict(t) for t in unique]
        return Conversion(scene, skipped, list(dict.fromkeys(self.notes)), sky, light_prims)

    def render_settings(self, prims: list[Usd.Prim]) -> Usd.Prim | None:
        path = self.stage.GetMetadata("renderSettingsPrimPath")
        if path:
            p = self.stage.GetPrimAtPath(path)
            if p:
                return p
        return prims[0] if len(prims) == 1 else None

    def render_sources(self, rs: Usd.Prim | None) -> list[Usd.Prim]:
        """Where UsdRender settings are read: the first RenderProduct of the RenderSettings
        prim (its own values override the settings', as UsdRender specifies), then the
        settings. Tyndall renders one image: further products are noted, not rendered."""
        if rs is None:
            return []
        products = [self.stage.GetPrimAtPath(t) for t in UsdRender.Settings(rs).GetProductsRel().GetForwardedTargets()]
        products = [p for p in products if p and p.IsA(UsdRender.Product)]
        if len(products) > 1:
            self.notes.append(
                f"{rs.GetPath()}: {len(products)} render products: only the first, {products[0].GetPath()}, is rendered"
            )
        return [*products[:1], rs]

    def pick_camera(self, cameras: list[Usd.Prim], settings: Usd.Prim | None, render: list[Usd.Prim]) -> Usd.Prim:
        for p, rel_name in ((settings, NS + "output:camera"), *((r, "camera") for r in render)):
            if p is None:
                continue
            rel = p.GetRelationship(rel_name)
            targets = rel.GetForwardedTargets() if rel else []
            if targets:
                cam = self.stage.GetPrimAtPath(targets[0])
                if not cam or cam.GetTypeName() != "Camera":
                    raise UsdSceneError(str(p.GetPath()), rel_name, f"target {targets[0]} is not a Camera")
                for other in cameras:
                    if other.GetPath() != cam.GetPath():
                        self.skip(other, f"camera not chosen by {p.GetPath()}.{rel_name}")
                return cam
        if not cameras:
            raise UsdSceneError("/", None, "the stage has no Camera (Tyndall renders for one camera)")
        # Without a choice, a visible camera before a hidden one (a hidden rig's camera or a
        # guide is most likely not the shot's).
        shown = [c for c in cameras if self.shown(c)] or cameras
        if len(shown) > 1:
            paths = ", ".join(str(c.GetPath()) for c in shown)
            raise UsdSceneError(
                "/", None, f"several cameras ({paths}): choose one with the relationship tyndall:output:camera"
            )
        for other in cameras:
            if other.GetPath() != shown[0].GetPath():
                self.skip(other, "hidden camera not chosen (a visible one is)")
        return shown[0]

    def shown(self, prim: Usd.Prim) -> bool:
        """Visible, and not a guide or a proxy (without listing the prim as skipped)."""
        img = UsdGeom.Imageable(prim)
        return not img or (
            img.ComputeVisibility(self.time) != UsdGeom.Tokens.invisible
            and img.ComputePurpose() not in (UsdGeom.Tokens.guide, UsdGeom.Tokens.proxy)
        )


def open_stage(source: Usd.Stage | str | os.PathLike[str]) -> Usd.Stage:
    """A stage from a ``Usd.Stage`` or a .usda/.usdc/.usd/.usdz path."""
    if isinstance(source, Usd.Stage):
        return source
    path = os.fspath(source)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"USD stage not found: {path}")
    try:
        stage = Usd.Stage.Open(path)
    except Exception as e:  # pxr raises Tf.ErrorException
        raise UsdSceneError(path, None, f"cannot open the stage: {e}") from e
    if stage is None:
        raise UsdSceneError(path, None, "cannot open the stage")
    return stage


def convert_stage(source: Usd.Stage | str | os.PathLike[str], *, time: float | None = None) -> Conversion:
    """Convert a USD stage into a Tyndall scene.

    ``time`` is the time code to read; default: the earliest time sample (or the
    default value where an attribute has no samples). Raises :class:`UsdSceneError`
    (naming the prim and the attribute) for a malformed stage; prims that cannot be
    used are listed in :attr:`Conversion.skipped`.
    """
    stage = open_stage(source)
    tc = Usd.TimeCode.EarliestTime() if time is None else Usd.TimeCode(time)
    return _Converter(stage, tc).run()


__all__ = ["Conversion", "SkySettings", "UsdSceneError", "convert_stage", "open_stage"]
