"""Tyndall scene → USD stage, in Blender 5.0's USD conventions (the inverse of the reader).

``write_stage(scene, path)`` writes what :func:`tyndall_usd.convert_stage` reads back to
the same scene and what Blender's own USD importer reads back to the lights, camera and
meshes a Blender user had (the Blender → USD → Scene → USD → Blender round trip,
``tests/test_usd.py``):

* point / spot → ``SphereLight``: ``inputs:intensity = power_w / π``, ``inputs:radius``,
  ``inputs:normalize = 1``; a spot adds ``ShapingAPI`` with ``cone:angle = spot_size / 2``
  and ``cone:softness = spot_blend``; a ``usd_shaping`` distribution its cone angle,
  softness and focus; an IES profile ``inputs:shaping:ies:file`` (absolute path), the same
  path as ``tyndall:ies:file`` (Blender's importer keeps it as a custom property) and
  ``tyndall:ies:strength``; ``casts_shadows: false`` → ``ShadowAPI`` with ``shadow:enable = 0``.
* sun → ``DistantLight``: ``inputs:intensity = strength_w_m2 / 4``,
  ``inputs:angle = angular_diameter / 2``, local +Z towards the sun.
* ambient → untextured ``DomeLight``, ``inputs:intensity = radiance``.
* meshes → ``Mesh`` (triangles) with their transform as ``xformOp:transform``;
  ``visible_to_camera`` / ``casts_shadows`` false → ``tyndall:visibleToCamera`` /
  ``tyndall:castsShadows`` = 0 (no UsdGeom schema holds ray visibility).
* camera → ``Camera``: lengths in tenths of a stage unit (focal length, apertures, offsets);
  the aperture has the image's aspect on the fitted side; ``tyndall:output:resolution``.
* homogeneous and height-fog media → an ``Xform`` with the ``tyndall:medium:*`` attributes; a
  homogeneous medium with box bounds also gets ``tyndall:medium:bounds = "box"`` and a child
  ``Cube`` spanning the box (turned by an orient op when the box has ``rotation_wxyz``).

Stage: ``upAxis = Z``, ``metersPerUnit = 1``, default prim ``/root``. What UsdLux cannot
hold (window lights, Nishita and tabulated distributions, fog layers, ellipsoids,
spectral coefficients, equirectangular cameras) is not written; each is named in the
returned notes.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from typing import Any

from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdLux, Vt

ROOT = "/root"
#: Layers the reader accepts in ``tyndall:output:layers`` (per-light layers are Blender-side).
_BASIC_LAYERS = ("inscatter", "transmittance", "depth", "sun_transmittance", "error")


def _quat(q: Sequence[float]) -> Gf.Quatd:
    n = math.sqrt(sum(float(x) * float(x) for x in q))
    return Gf.Quatd(float(q[0]) / n, Gf.Vec3d(float(q[1]) / n, float(q[2]) / n, float(q[3]) / n))


def _look_at(position: Sequence[float], target: Sequence[float], up: Sequence[float]) -> Gf.Quatd:
    """The rotation whose local −Z points at ``target`` and whose +Y leans to ``up`` (scene format)."""
    f = (Gf.Vec3d(*map(float, target)) - Gf.Vec3d(*map(float, position))).GetNormalized()
    z = -f
    x = Gf.Cross(Gf.Vec3d(*map(float, up)), z).GetNormalized()
    y = Gf.Cross(z, x)
    r = Gf.Matrix3d(x[0], x[1], x[2], y[0], y[1], y[2], z[0], z[1], z[2])
    return r.ExtractRotation().GetQuat()


def _orientation(obj: Mapping[str, Any], field: str) -> Gf.Quatd:
    o = obj.get("orientation", {"quaternion_wxyz": [1.0, 0.0, 0.0, 0.0]})
    if "quaternion_wxyz" in o:
        return _quat(o["quaternion_wxyz"])
    if "look_at" in o:
        la = o["look_at"]
        return _look_at(obj["position"], la["target"], la.get("up", [0.0, 0.0, 1.0]))
    raise ValueError(f"{field}.orientation: expected look_at or quaternion_wxyz, got {sorted(o)}")


def _pose(prim: Usd.Prim, quat: Gf.Quatd, position: Sequence[float]) -> None:
    """``xformOp:transform`` = rotation, then translation (USD row vectors)."""
    m = Gf.Matrix4d().SetRotate(quat) * Gf.Matrix4d().SetTranslate(Gf.Vec3d(*map(float, position)))
    xf = UsdGeom.Xformable(prim)
    xf.ClearXformOpOrder()
    xf.AddTransformOp(UsdGeom.XformOp.PrecisionDouble).Set(m)


def _mesh_matrix(transform: Mapping[str, Any] | None) -> Gf.Matrix4d:
    """The scene's object → world transform (column vectors) as a USD row-vector matrix."""
    t = transform or {}
    if t.get("matrix") is not None:
        rows = t["matrix"]
        return Gf.Matrix4d(*[float(rows[c][r]) for r in range(4) for c in range(4)])
    s = t.get("scale") or [1.0, 1.0, 1.0]
    q = _quat(t.get("rotation_wxyz") or [1.0, 0.0, 0.0, 0.0])
    tr = t.get("translation") or [0.0, 0.0, 0.0]
    return (
        Gf.Matrix4d().SetScale(Gf.Vec3d(*map(float, s)))
        * Gf.Matrix4d().SetRotate(q)
        * Gf.Matrix4d().SetTranslate(Gf.Vec3d(*map(float, tr)))
    )


def _prim_name(name: str, fallback: str, used: set[str]) -> str:
    base = Tf.MakeValidIdentifier(name or fallback)
    out, k = base, 2
    while out in used:
        out, k = f"{base}_{k}", k + 1
    used.add(out)
    return out


def _coefficient(value: Any) -> float | Gf.Vec3d | None:
    """A grey or RGB coefficient for a ``tyndall:medium:*`` attribute; None for other forms."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, (list, tuple)) and len(value) == 3 and all(isinstance(x, (int, float)) for x in value):
        return Gf.Vec3d(*map(float, value))
    return None


def _set(prim: Usd.Prim, name: str, value: Any) -> None:
    if isinstance(value, float):
        prim.CreateAttribute(name, Sdf.ValueTypeNames.Double).Set(value)
    elif isinstance(value, Gf.Vec3d):
        prim.CreateAttribute(name, Sdf.ValueTypeNames.Double3).Set(value)
    elif isinstance(value, str):
        prim.CreateAttribute(name, Sdf.ValueTypeNames.String).Set(value)
    else:
        raise TypeError(name)


def write_stage(
    scene: Mapping[str, Any], path: str | os.PathLike[str], *, base_dir: str | os.PathLike[str] | None = None
) -> list[str]:
    """Write ``scene`` (a dict in the JSON scene format) as a USD stage at ``path``.

    ``base_dir``: where relative IES paths are resolved (default: the current directory;
    a scene file's own directory is what the core uses). Returns notes naming every part
    of the scene that has no USD form here and was not written.
    """
    path = os.fspath(path)
    base = os.fspath(base_dir) if base_dir is not None else os.getcwd()
    notes: list[str] = []
    stage = Usd.Stage.CreateNew(path)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, ROOT).GetPrim())
    stage.GetRootLayer().documentation = "Tyndall scene (tyndall_usd.write_stage)"
    used: set[str] = set()

    for i, light in enumerate(scene.get("lights", [])):
        field = f"lights[{i}]"
        kind = light.get("type")
        name = _prim_name(light.get("name", ""), kind or "light", used)
        color = Gf.Vec3f(*map(float, light.get("color", [1.0, 1.0, 1.0])))
        if kind in ("point", "spot"):
            dist = light.get("distribution", {"type": "isotropic"})
            if dist.get("type", "isotropic") not in ("isotropic", "usd_shaping"):
                notes.append(f"{field} ({name}): distribution {dist.get('type')!r} has no UsdLux form; not written")
                used.discard(name)
                continue
            sl = UsdLux.SphereLight.Define(stage, f"{ROOT}/{name}")
            prim = sl.GetPrim()
            _pose(prim, _orientation(light, field), light["position"])
            sl.CreateIntensityAttr(float(light.get("power_w", 1000.0)) / math.pi)
            sl.CreateColorAttr(color)
            sl.CreateRadiusAttr(float(light.get("radius_m", 0.0)))
            sl.CreateNormalizeAttr(True)
            if not light.get("casts_shadows", True):
                UsdLux.ShadowAPI.Apply(prim).CreateShadowEnableAttr(False)
            if kind == "spot":
                shaping = UsdLux.ShapingAPI.Apply(prim)
                shaping.CreateShapingConeAngleAttr(0.5 * float(light.get("spot_size_deg", 45.0)))
                shaping.CreateShapingConeSoftnessAttr(float(light.get("spot_blend", 0.15)))
            elif dist.get("type") == "usd_shaping":
                shaping = UsdLux.ShapingAPI.Apply(prim)
                shaping.CreateShapingConeAngleAttr(float(dist.get("cone_angle_deg", 90.0)))
                shaping.CreateShapingConeSoftnessAttr(float(dist.get("cone_softness", 0.0)))
                shaping.CreateShapingFocusAttr(float(dist.get("focus", 0.0)))
            ies = light.get("ies")
            if ies is not None:
                shaping = UsdLux.ShapingAPI.Apply(prim)
                file = ies["file"] if os.path.isabs(ies["file"]) else os.path.join(base, ies["file"])
                shaping.CreateShapingIesFileAttr(Sdf.AssetPath(os.path.abspath(file)))
                # Blender's importer ignores the shaping IES file; this comes back as a custom
                # property of the light data, which the add-on reads as the light's IES profile.
                prim.CreateAttribute("tyndall:ies:file", Sdf.ValueTypeNames.String).Set(os.path.abspath(file))
                prim.CreateAttribute("tyndall:ies:strength", Sdf.ValueTypeNames.Double).Set(
                    float(ies.get("strength", 1.0))
                )
        elif kind == "sun":
            dl = UsdLux.DistantLight.Define(stage, f"{ROOT}/{name}")
            to_sun = Gf.Vec3d(*map(float, light["direction_to_sun"])).GetNormalized()
            q = Gf.Rotation(Gf.Vec3d(0, 0, 1), to_sun).GetQuat()
            _pose(dl.GetPrim(), q, [0.0, 0.0, 0.0])
            dl.CreateIntensityAttr(float(light.get("strength_w_m2", 1.0)) / 4.0)
            dl.CreateAngleAttr(0.5 * float(light.get("angular_diameter_deg", 0.545)))
            dl.CreateNormalizeAttr(True)  # the strength is the irradiance, as Blender's Normalize on
            dl.CreateColorAttr(color)
        elif kind == "ambient":
            dome = UsdLux.DomeLight.Define(stage, f"{ROOT}/{name}")
            dome.CreateIntensityAttr(float(light.get("radiance", 1.0)))
            dome.CreateColorAttr(color)
        else:
            used.discard(name)
            notes.append(f"{field} ({name}): a {kind!r} light has no UsdLux form; not written")

    for i, m in enumerate(scene.get("meshes", [])):
        name = _prim_name(m.get("name", ""), f"mesh{i}", used)
        mesh = UsdGeom.Mesh.Define(stage, f"{ROOT}/{name}")
        mesh.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, p)) for p in m["positions"]]))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(m["triangles"])))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([int(v) for t in m["triangles"] for v in t]))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        xf = UsdGeom.Xformable(mesh.GetPrim())
        xf.AddTransformOp(UsdGeom.XformOp.PrecisionDouble).Set(_mesh_matrix(m.get("transform")))
        # Ray visibility has no UsdGeom schema: tyndall_usd's own attributes.
        for key, attr in (("visible_to_camera", "visibleToCamera"), ("casts_shadows", "castsShadows")):
            if not m.get(key, True):
                mesh.GetPrim().CreateAttribute(f"tyndall:{attr}", Sdf.ValueTypeNames.Bool).Set(False)

    cam = scene.get("camera")
    settings: Usd.Prim | None = None
    if cam is not None and cam.get("type") == "perspective":
        name = _prim_name("Camera", "Camera", used)
        c = UsdGeom.Camera.Define(stage, f"{ROOT}/{name}")
        settings = c.GetPrim()
        _pose(settings, _orientation(cam, "camera"), cam["position"])
        w, h = (int(x) for x in cam["resolution"])
        sw, sh = float(cam.get("sensor_width_mm", 36.0)), float(cam.get("sensor_height_mm", 24.0))
        fit = cam.get("sensor_fit", "auto")
        if fit == "auto":
            fit = "horizontal" if w >= h else "vertical"
            side = sw  # Blender's AUTO fit: the sensor width on the longer side
        else:
            side = sw if fit == "horizontal" else sh
        h_ap, v_ap = (side, side * h / w) if fit == "horizontal" else (side * w / h, side)
        k = 0.01  # millimetres → tenths of a metre
        c.CreateProjectionAttr(UsdGeom.Tokens.perspective)
        c.CreateFocalLengthAttr(float(cam.get("focal_length_mm", 50.0)) * k)
        c.CreateHorizontalApertureAttr(h_ap * k)
        c.CreateVerticalApertureAttr(v_ap * k)
        c.CreateHorizontalApertureOffsetAttr(float(cam.get("shift_x", 0.0)) * side * k)
        c.CreateVerticalApertureOffsetAttr(float(cam.get("shift_y", 0.0)) * side * k)
        far = cam.get("clip_end_m")
        c.CreateClippingRangeAttr(Gf.Vec2f(float(cam.get("clip_start_m", 0.0)), 1e30 if far is None else float(far)))
        settings.CreateAttribute("tyndall:output:resolution", Sdf.ValueTypeNames.Int2).Set(Gf.Vec2i(w, h))
    elif cam is not None:
        notes.append(f"camera: a {cam.get('type')!r} camera has no USD form here; not written")

    if settings is not None:
        out = scene.get("output", {})
        layers = [x for x in out.get("layers", []) if x in _BASIC_LAYERS]
        if layers:
            settings.CreateAttribute("tyndall:output:layers", Sdf.ValueTypeNames.String).Set(",".join(layers))
        if "tolerance" in out:
            settings.CreateAttribute("tyndall:output:tolerance", Sdf.ValueTypeNames.Double).Set(float(out["tolerance"]))
        if "spectral" in out:
            settings.CreateAttribute("tyndall:output:spectral", Sdf.ValueTypeNames.String).Set(str(out["spectral"]))

    for i, med in enumerate(scene.get("media", [])):
        field = f"media[{i}]"
        kind = med.get("type")
        name = _prim_name(med.get("name", ""), f"medium{i}", used)
        attrs: dict[str, Any] = {"tyndall:medium:type": kind, "tyndall:medium:name": med.get("name", name)}
        bounds = med.get("bounds", "world")
        box = bounds.get("box") if isinstance(bounds, dict) else None
        if kind == "homogeneous" and (bounds == "world" or box is not None):
            coeffs = {"scattering": med["scattering"], "absorption": med.get("absorption", 0.0)}
            if box is not None:
                attrs["tyndall:medium:bounds"] = "box"
            phase = med.get("phase", {"type": "isotropic"})
            attrs["tyndall:medium:phase"] = phase["type"]
            if "g" in phase:
                attrs["tyndall:medium:phaseG"] = float(phase["g"])
        elif kind == "height_fog":
            attrs["tyndall:medium:scaleHeightM"] = float(med["scale_height_m"])
            attrs["tyndall:medium:referenceHeightM"] = float(med.get("reference_height_m", 0.0))
            coeffs = {}
            for part in ("rayleigh", "mie"):
                if part in med:
                    coeffs[part + "Scattering"] = med[part]["scattering"]
                    coeffs[part + "Absorption"] = med[part].get("absorption", 0.0)
            if "mie" in med and "phase" in med["mie"]:
                attrs["tyndall:medium:miePhase"] = med["mie"]["phase"]["type"]
                if "g" in med["mie"]["phase"]:
                    attrs["tyndall:medium:miePhaseG"] = float(med["mie"]["phase"]["g"])
        else:
            used.discard(name)
            notes.append(f"{field} ({name}): a {kind!r} medium (or boxed bounds) has no USD form here; not written")
            continue
        bad = [k for k, v in coeffs.items() if _coefficient(v) is None]
        if bad:
            used.discard(name)
            notes.append(f"{field} ({name}): spectral coefficients ({', '.join(bad)}) have no USD form here")
            continue
        prim = UsdGeom.Xform.Define(stage, f"{ROOT}/{name}").GetPrim()
        for k, v in attrs.items():
            _set(prim, k, v)
        for k, v in coeffs.items():
            _set(prim, "tyndall:medium:" + k, _coefficient(v))
        if box is not None:
            # The box as a child Cube (size 2: −1..1, moved and scaled in double precision),
            # whose world bound the reader takes (geometry inside a medium prim is its box only).
            # Purpose guide: a helper, which USD importers (Blender's) do not render as a surface.
            lo, hi = (Gf.Vec3d(*(float(x) for x in box[k])) for k in ("min", "max"))
            cube = UsdGeom.Cube.Define(stage, f"{ROOT}/{name}/box")
            cube.CreatePurposeAttr(UsdGeom.Tokens.guide)
            cube.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set((lo + hi) * 0.5)
            turn = box.get("rotation_wxyz")
            if turn is not None:
                # Turned about the box's centre: translate · orient · scale.
                w, x, y, z = (float(v) for v in turn)
                cube.AddOrientOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Quatd(w, x, y, z).GetNormalized())
            cube.AddScaleOp(UsdGeom.XformOp.PrecisionDouble).Set((hi - lo) * 0.5)
    stage.GetRootLayer().Save()
    return notes
