"""USD interchange (usd/, package tyndall_usd): stage → scene, results layer, Blender's exporter.

The bpy tests run Blender's Python in a subprocess (bpy bundles its own USD libraries):
set TYNDALL_BPY_PYTHON to a Python with bpy 5.0.x; by default the test Python itself is
used if it can import bpy, otherwise those tests are skipped. The Blender fixture
(tests/data/usd/blender_scene.usda + .json) is read without bpy.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("pxr")
tyndall_usd = pytest.importorskip("tyndall_usd")

import tyndall  # noqa: E402
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender  # noqa: E402
from tyndall_usd import (  # noqa: E402
    UsdSceneError,
    convert_stage,
    read_results_layer,
    write_results_layer,
    write_stage,
)
from tyndall_usd._geom import rotate_wxyz  # noqa: E402

DATA = Path(__file__).parent / "data" / "usd"
TOL = 1e-5


def _close(a: Any, b: Any, tol: float = TOL) -> bool:
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_close(x, y, tol) for x, y in zip(a, b, strict=True))
    return math.isclose(float(a), float(b), rel_tol=tol, abs_tol=tol)


def _same_tree(a: Any, b: Any, tol: float, where: str = "") -> None:
    """Dicts, lists and strings equal, numbers within ``tol`` (relative and absolute)."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and sorted(a) == sorted(b), f"{where}: keys {sorted(a)} vs {sorted(b)}"
        for k in a:
            _same_tree(a[k], b[k], tol, f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b), f"{where}: {a} vs {b}"
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _same_tree(x, y, tol, f"{where}[{i}]")
    elif isinstance(a, (str, bool)) or a is None:
        assert a == b, f"{where}: {a!r} vs {b!r}"
    else:
        assert math.isclose(float(a), float(b), rel_tol=tol, abs_tol=tol), f"{where}: {a} vs {b}"


def _stage(tmp_path: Path, up: str = "Z", mpu: float = 1.0, name: str = "s.usda") -> Usd.Stage:
    stage = Usd.Stage.CreateNew(str(tmp_path / name))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if up == "Z" else UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/World").GetPrim())
    cam = UsdGeom.Camera.Define(stage, "/World/Cam")
    cam.CreateFocalLengthAttr(0.5)
    cam.CreateHorizontalApertureAttr(0.36)
    cam.CreateVerticalApertureAttr(0.2025)
    UsdGeom.XformCommonAPI(cam).SetTranslate(Gf.Vec3d(0, -10, 2))
    return stage


def _xform(prim: Usd.Prim, translate: tuple[float, ...], rotate: tuple[float, ...], scale: float = 1.0) -> None:
    api = UsdGeom.XformCommonAPI(prim)
    api.SetTranslate(Gf.Vec3d(*translate))
    api.SetRotate(Gf.Vec3f(*rotate), UsdGeom.XformCommonAPI.RotationOrderXYZ)
    api.SetScale(Gf.Vec3f(scale, scale, scale))


def _world_dir(stage: Usd.Stage, path: str, local: tuple[float, float, float]) -> list[float]:
    m = UsdGeom.Xformable(stage.GetPrimAtPath(path)).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    d = m.TransformDir(Gf.Vec3d(*local)).GetNormalized()
    return [d[0], d[1], d[2]]


def _validate(scene: dict[str, Any]) -> None:
    """The scene loads in Tyndall (SceneFormatError names the field otherwise)."""
    tyndall.as_scene(scene)


# ------------------------------------------------------------------ per light type


def test_point_light(tmp_path: Path) -> None:
    stage = _stage(tmp_path)
    rig = UsdGeom.Xform.Define(stage, "/World/Rig")
    _xform(rig.GetPrim(), (1, 2, 3), (10, 20, 30), scale=2.0)
    light = UsdLux.SphereLight.Define(stage, "/World/Rig/Lamp")
    _xform(light.GetPrim(), (0.5, 0, 0), (0, 15, 0))
    light.CreateIntensityAttr(100.0)
    light.CreateExposureAttr(1.0)
    light.CreateColorAttr(Gf.Vec3f(1.0, 0.5, 0.25))
    light.CreateRadiusAttr(0.1)
    light.CreateNormalizeAttr(True)
    conv = convert_stage(stage)
    (pt,) = conv.scene["lights"]
    assert pt["type"] == "point" and pt["name"] == "Lamp"
    assert _close(pt["power_w"], 100.0 * math.pi * 2.0)
    assert _close(pt["color"], [1.0, 0.5, 0.25])
    assert _close(pt["radius_m"], 0.2)  # scaled by the parent's scale 2
    m = UsdGeom.Xformable(light).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    assert _close(pt["position"], list(m.ExtractTranslation()))
    q = pt["orientation"]["quaternion_wxyz"]
    assert _close(rotate_wxyz(q, (0, 0, -1)), _world_dir(stage, "/World/Rig/Lamp", (0, 0, -1)))
    assert _close(rotate_wxyz(q, (1, 0, 0)), _world_dir(stage, "/World/Rig/Lamp", (1, 0, 0)))
    assert conv.light_prims == ["/World/Rig/Lamp"] and conv.skipped == []
    _validate(conv.scene)


def test_spot_light_with_ies(tmp_path: Path) -> None:
    stage = _stage(tmp_path)
    (tmp_path / "ies").mkdir()
    (tmp_path / "ies" / "beam.ies").write_text("IESNA:LM-63-2002\nTILT=NONE\n")
    light = UsdLux.SphereLight.Define(stage, "/World/Spot")
    _xform(light.GetPrim(), (0, 0, 5), (30, 0, 45))
    light.CreateIntensityAttr(1000.0 / math.pi)
    light.CreateColorAttr(Gf.Vec3f(0.2, 0.4, 1.0))
    light.CreateRadiusAttr(0.0)
    light.CreateTreatAsPointAttr(True)
    light.CreateNormalizeAttr(True)
    shaping = UsdLux.ShapingAPI.Apply(light.GetPrim())
    shaping.CreateShapingConeAngleAttr(25.0)
    shaping.CreateShapingConeSoftnessAttr(0.4)
    shaping.CreateShapingIesFileAttr(Sdf.AssetPath("./ies/beam.ies"))
    light.GetPrim().CreateAttribute("tyndall:ies:strength", Sdf.ValueTypeNames.Double).Set(0.5)
    stage.Save()
    conv = convert_stage(str(tmp_path / "s.usda"))
    (spot,) = conv.scene["lights"]
    assert spot["type"] == "spot"
    assert _close(spot["power_w"], 1000.0)
    assert _close(spot["spot_size_deg"], 50.0) and _close(spot["spot_blend"], 0.4)
    assert spot["radius_m"] == 0.0
    assert spot["ies"] == {"file": str((tmp_path / "ies" / "beam.ies").resolve()), "strength": 0.5}
    q = spot["orientation"]["quaternion_wxyz"]
    assert _close(rotate_wxyz(q, (0, 0, -1)), _world_dir(stage, "/World/Spot", (0, 0, -1)))
    _validate(conv.scene)


def test_shaping_beyond_a_blender_spot_is_a_point_with_usd_shaping(tmp_path: Path) -> None:
    stage = _stage(tmp_path)
    light = UsdLux.SphereLight.Define(stage, "/World/Wide")
    shaping = UsdLux.ShapingAPI.Apply(light.GetPrim())
    shaping.CreateShapingConeAngleAttr(120.0)
    shaping.CreateShapingConeSoftnessAttr(0.2)
    shaping.CreateShapingFocusAttr(2.0)
    (pt,) = convert_stage(stage).scene["lights"]
    assert pt["type"] == "point"
    dist = pt["distribution"]
    assert dist["type"] == "usd_shaping" and dist["cone_angle_deg"] == 120.0 and dist["focus"] == 2.0
    assert _close(dist["cone_softness"], 0.2)
    _validate(convert_stage(stage).scene)


def test_sun_light(tmp_path: Path) -> None:
    stage = _stage(tmp_path)
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    _xform(sun.GetPrim(), (0, 0, 10), (40, 0, 120))
    sun.CreateIntensityAttr(2.5)
    sun.CreateAngleAttr(0.3)
    sun.CreateColorAttr(Gf.Vec3f(1.0, 0.9, 0.8))
    sun.CreateNormalizeAttr(True)
    (s,) = convert_stage(stage).scene["lights"]
    assert s["type"] == "sun"
    assert _close(s["strength_w_m2"], 10.0)  # Blender: intensity = Strength / 4
    assert _close(s["angular_diameter_deg"], 0.6)  # Blender: angle = Angle / 2
    assert _close(s["direction_to_sun"], _world_dir(stage, "/World/Sun", (0, 0, 1)))
    assert _close(s["color"], [1.0, 0.9, 0.8])
    _validate(convert_stage(stage).scene)


def test_unnormalized_lights_as_blender_imports_and_cycles_renders(tmp_path: Path) -> None:
    """``inputs:normalize`` off (the UsdLux default, and how Blender 5.0 exports a lamp with
    Normalize off): Blender's importer keeps the flag, and Cycles then does not divide the
    strength by the light's area: 4πr² with r the light's own radius (the transform and
    metersPerUnit do not enter), 4 for r = 0, π·sin²(angle) for a sun (the add-on's
    ``test_unnormalized_lights_match_cycles`` measures these in Cycles). A radius-0 lamp was
    read 4× too dark, a scaled one by the square of its scale, a sun by up to 1/π·sin²(angle)."""
    stage = _stage(tmp_path, mpu=0.01)
    rig = UsdGeom.Xform.Define(stage, "/World/Rig")
    _xform(rig.GetPrim(), (0, 0, 0), (0, 0, 0), scale=3.0)
    lamp = UsdLux.SphereLight.Define(stage, "/World/Rig/Lamp")
    lamp.CreateIntensityAttr(10.0)
    lamp.CreateRadiusAttr(20.0)  # cm, scaled 3× by the rig: Cycles still takes 20
    tiny = UsdLux.SphereLight.Define(stage, "/World/Tiny")
    tiny.CreateIntensityAttr(10.0)
    tiny.CreateRadiusAttr(0.0)
    point = UsdLux.SphereLight.Define(stage, "/World/Point")
    point.CreateIntensityAttr(10.0)
    point.CreateRadiusAttr(0.5)
    point.CreateTreatAsPointAttr(True)  # Blender imports it with radius 0
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.CreateIntensityAttr(1000.0)
    sun.CreateAngleAttr(0.3)
    conv = convert_stage(stage)
    got = {x["name"]: x for x in conv.scene["lights"]}
    assert _close(got["Lamp"]["power_w"], 10.0 * math.pi * 4.0 * math.pi * 20.0**2)
    assert _close(got["Lamp"]["radius_m"], 0.6)  # the geometry is still in metres
    assert _close(got["Tiny"]["power_w"], 10.0 * math.pi * 4.0)
    assert _close(got["Point"]["power_w"], 10.0 * math.pi * 4.0)
    assert _close(got["Sun"]["strength_w_m2"], 4000.0 * math.pi * math.sin(math.radians(0.3)) ** 2)
    assert sum("inputs:normalize is off" in n for n in conv.notes) == 4
    # The sun's factor, 8.6e-5 at 0.3°, leaves it nearly dark: the note says how to get the strength.
    (sun_note,) = [n for n in conv.notes if n.startswith("/World/Sun:")]
    assert "nearly dark" in sun_note and "author inputs:normalize = 1" in sun_note, sun_note
    assert not any("nearly dark" in n for n in conv.notes if not n.startswith("/World/Sun:"))
    _validate(conv.scene)


def test_shadow_and_ray_visibility_flags(tmp_path: Path) -> None:
    """A light's UsdLux ``inputs:shadow:enable`` (or ``tyndall:castsShadows``) and a mesh's
    ``tyndall:visibleToCamera``/``castsShadows`` (on the prim or its parent Xform, where an
    object's custom property lands in Blender's export) become the scene's flags, and the
    writer writes them back."""
    stage = _stage(tmp_path)
    lamp = UsdLux.SphereLight.Define(stage, "/World/Lamp")
    UsdLux.ShadowAPI.Apply(lamp.GetPrim()).CreateShadowEnableAttr(False)
    keep = UsdLux.SphereLight.Define(stage, "/World/Keep")
    UsdLux.ShadowAPI.Apply(keep.GetPrim()).CreateShadowEnableAttr(True)
    rig = UsdGeom.Xform.Define(stage, "/World/Box")
    rig.GetPrim().CreateAttribute("tyndall:visibleToCamera", Sdf.ValueTypeNames.Int).Set(0)
    box = UsdGeom.Mesh.Define(stage, "/World/Box/Box")
    box.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (0, 1, 0)])
    box.CreateFaceVertexCountsAttr([3])
    box.CreateFaceVertexIndicesAttr([0, 1, 2])
    box.GetPrim().CreateAttribute("tyndall:castsShadows", Sdf.ValueTypeNames.Bool).Set(False)
    scene = convert_stage(stage).scene
    lights = {x["name"]: x for x in scene["lights"]}
    assert lights["Lamp"]["casts_shadows"] is False and "casts_shadows" not in lights["Keep"]
    (m,) = scene["meshes"]
    assert m["visible_to_camera"] is False and m["casts_shadows"] is False
    _validate(scene)
    write_stage(scene, str(tmp_path / "back.usda"))
    again = convert_stage(str(tmp_path / "back.usda")).scene
    assert {x["name"]: x.get("casts_shadows", True) for x in again["lights"]} == {"Lamp": False, "Keep": True}
    assert again["meshes"][0]["visible_to_camera"] is False and again["meshes"][0]["casts_shadows"] is False


def test_a_boxed_medium_round_trips_through_write_stage(tmp_path: Path) -> None:
    """A homogeneous medium bounded by a box (the add-on's fog boxes) is written as a medium prim
    with ``tyndall:medium:bounds = "box"`` and a child Cube spanning it, and read back as the same
    box and coefficients; before, it was left out with a note."""
    scene = json.loads((DATA.parent.parent.parent / "examples" / "stage_four_spots.json").read_text())
    scene["media"].append(
        {
            "type": "homogeneous",
            "name": "Fog: Volume Scatter",
            "scattering": [0.24, 0.2, 0.16],
            "absorption": 0.01,
            "phase": {"type": "henyey_greenstein", "g": 0.4},
            "bounds": {"box": {"min": [-0.8, -0.75, 0.5], "max": [1.2, 0.8, 1.9]}},
        }
    )
    _validate(scene)
    assert write_stage(scene, str(tmp_path / "fog.usda")) == []
    again = convert_stage(str(tmp_path / "fog.usda")).scene
    (fog,) = [m for m in again["media"] if m["name"] == "Fog: Volume Scatter"]
    assert _close(fog["bounds"]["box"]["min"], [-0.8, -0.75, 0.5], 1e-9)
    assert _close(fog["bounds"]["box"]["max"], [1.2, 0.8, 1.9], 1e-9)
    assert _close(fog["scattering"], [0.24, 0.2, 0.16], 1e-6) and _close(fog["absorption"], 0.01, 1e-6)
    assert fog["phase"]["type"] == "henyey_greenstein" and _close(fog["phase"]["g"], 0.4, 1e-6)
    assert not any(m["name"] == "box" for m in again["meshes"])  # the Cube is the box, not an occluder
    written = Usd.Stage.Open(str(tmp_path / "fog.usda"))  # (kept: its prims die with it)
    cube = written.GetPrimAtPath("/root/Fog__Volume_Scatter/box")
    assert UsdGeom.Imageable(cube).GetPurposeAttr().Get() == UsdGeom.Tokens.guide  # no surface in Blender
    _validate(again)


def _turn(q: list[float], v: list[float]) -> np.ndarray:
    """``v`` turned by the quaternion ``[w, x, y, z]``, by the rotation-matrix formula."""
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    return r @ np.asarray(v, dtype=float)


def _medium_box(tmp_path: Path, ops: Any) -> tuple[dict[str, Any], list[str]]:
    """A haze Cube placed by ``ops(xformable)``, read back: its ``bounds.box`` and the notes."""
    stage = _stage(tmp_path)
    cube = UsdGeom.Cube.Define(stage, "/World/Haze")
    ops(UsdGeom.Xformable(cube.GetPrim()))
    p = cube.GetPrim()
    p.CreateAttribute("tyndall:medium:type", Sdf.ValueTypeNames.Token).Set("homogeneous")
    p.CreateAttribute("tyndall:medium:scattering", Sdf.ValueTypeNames.Double).Set(0.1)
    p.CreateAttribute("tyndall:medium:bounds", Sdf.ValueTypeNames.Token).Set("box")
    conv = convert_stage(stage)
    (med,) = conv.scene["media"]
    _validate(conv.scene)
    return med["bounds"]["box"], conv.notes


def test_a_turned_box_medium_is_read_as_the_turned_box(tmp_path: Path) -> None:
    """A Cube turned 30° about Z (and scaled 2 × 1 × 0.5) bounds the medium by that turned box,
    not by its larger axis-aligned bound (as before)."""

    def place(xf: UsdGeom.Xformable) -> None:
        xf.AddTranslateOp().Set(Gf.Vec3d(1.0, 2.0, 3.0))
        xf.AddRotateXYZOp().Set(Gf.Vec3f(0.0, 0.0, 30.0))
        xf.AddScaleOp().Set(Gf.Vec3f(2.0, 1.0, 0.5))

    box, _ = _medium_box(tmp_path, place)
    assert _close(box["min"], [-1.0, 1.0, 2.5], 1e-6) and _close(box["max"], [3.0, 3.0, 3.5], 1e-6)
    c30, s30 = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
    assert np.allclose(_turn(box["rotation_wxyz"], [1, 0, 0]), [c30, s30, 0.0], atol=1e-6)
    assert np.allclose(_turn(box["rotation_wxyz"], [0, 0, 1]), [0.0, 0.0, 1.0], atol=1e-6)


def test_an_unturned_or_sheared_box_medium_keeps_its_aligned_bound(tmp_path: Path) -> None:
    """A box turned by a multiple of 90° is an axis-aligned box (no rotation written); a sheared
    one has no box form, so its world-space axis-aligned bound is used, with a note naming it."""

    def quarter(xf: UsdGeom.Xformable) -> None:
        xf.AddRotateZOp().Set(90.0)
        xf.AddScaleOp().Set(Gf.Vec3f(2.0, 1.0, 0.5))

    box, _ = _medium_box(tmp_path, quarter)
    assert "rotation_wxyz" not in box
    assert _close(box["min"], [-1.0, -2.0, -0.5], 1e-6) and _close(box["max"], [1.0, 2.0, 0.5], 1e-6)

    def sheared(xf: UsdGeom.Xformable) -> None:
        xf.AddTransformOp().Set(Gf.Matrix4d(1, 0, 0, 0, 0.5, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1))

    box, notes = _medium_box(tmp_path / "s", sheared)
    assert "rotation_wxyz" not in box
    assert _close(box["min"], [-1.5, -1.0, -1.0], 1e-9) and _close(box["max"], [1.5, 1.0, 1.0], 1e-9)
    assert any("/World/Haze" in n and "sheared" in n for n in notes), notes


def test_a_turned_boxed_medium_round_trips_through_write_stage(tmp_path: Path) -> None:
    """``write_stage`` turns the box's Cube with an orient op; the reader gives the same box back."""
    scene = json.loads((DATA.parent.parent.parent / "examples" / "stage_four_spots.json").read_text())
    q = [math.cos(0.35), 0.6 * math.sin(0.35), 0.0, 0.8 * math.sin(0.35)]
    box = {"min": [-0.8, -0.75, 0.5], "max": [1.2, 0.8, 1.9], "rotation_wxyz": q}
    scene["media"].append({"type": "homogeneous", "name": "Turned", "scattering": 0.2, "bounds": {"box": box}})
    _validate(scene)
    assert write_stage(scene, str(tmp_path / "turned.usda")) == []
    (fog,) = [m for m in convert_stage(str(tmp_path / "turned.usda")).scene["media"] if m["name"] == "Turned"]
    back = fog["bounds"]["box"]
    assert _close(back["min"], box["min"], 1e-9) and _close(back["max"], box["max"], 1e-9)
    for v in ([1, 0, 0], [0, 1, 0], [0, 0, 1]):
        assert np.allclose(_turn(back["rotation_wxyz"], v), _turn(q, v), atol=1e-9)


def test_color_temperature_outside_blender_exports(tmp_path: Path) -> None:
    stage = _stage(tmp_path)
    light = UsdLux.SphereLight.Define(stage, "/World/Warm")
    light.CreateEnableColorTemperatureAttr(True)
    light.CreateColorTemperatureAttr(3000.0)
    (pt,) = convert_stage(stage).scene["lights"]
    assert _close(pt["color"], list(UsdLux.BlackbodyTemperatureAsRgb(3000.0)))


def test_untextured_dome_is_ambient(tmp_path: Path) -> None:
    stage = _stage(tmp_path)
    dome = UsdLux.DomeLight.Define(stage, "/World/Env")
    dome.CreateIntensityAttr(0.25)
    dome.CreateColorAttr(Gf.Vec3f(0.5, 0.6, 1.0))
    (amb,) = convert_stage(stage).scene["lights"]
    assert amb == {"type": "ambient", "name": "Env", "color": [0.5, 0.6000000238418579, 1.0], "radiance": 0.25}


def test_y_up_and_meters_per_unit(tmp_path: Path) -> None:
    stage = _stage(tmp_path, up="Y", mpu=0.01)
    light = UsdLux.SphereLight.Define(stage, "/World/Lamp")
    _xform(light.GetPrim(), (0, 100, 0), (0, 0, 0))  # 1 m up in a Y-up centimetre stage
    light.CreateRadiusAttr(5.0)
    cam = UsdGeom.Camera(stage.GetPrimAtPath("/World/Cam"))
    cam.GetFocalLengthAttr().Set(50.0)  # tenths of a cm = mm
    cam.GetHorizontalApertureAttr().Set(36.0)
    cam.GetVerticalApertureAttr().Set(24.0)
    cam.CreateClippingRangeAttr(Gf.Vec2f(10.0, 10000.0))
    UsdGeom.XformCommonAPI(cam).SetTranslate(Gf.Vec3d(0, 0, 1000))  # 10 m towards the viewer (−Y in Z-up)
    scene = convert_stage(stage).scene
    (pt,) = scene["lights"]
    assert _close(pt["position"], [0, 0, 1]) and _close(pt["radius_m"], 0.05)
    # The light's −Z (towards −Z_usd = +Y in Tyndall) follows the up-axis rotation.
    assert _close(rotate_wxyz(pt["orientation"]["quaternion_wxyz"], (0, 0, -1)), [0, 1, 0])
    c = scene["camera"]
    assert _close(c["position"], [0, -10, 0])
    assert _close(c["focal_length_mm"], 50.0) and _close(c["sensor_width_mm"], 36.0)
    assert _close(c["clip_start_m"], 0.1) and _close(c["clip_end_m"], 100.0)
    assert _close(rotate_wxyz(c["orientation"]["quaternion_wxyz"], (0, 0, -1)), [0, 1, 0])
    assert _close(rotate_wxyz(c["orientation"]["quaternion_wxyz"], (0, 1, 0)), [0, 0, 1])
    assert c["resolution"] == [1920, 1280]
    _validate(scene)


def test_camera_shift_resolution_and_render_settings(tmp_path: Path) -> None:
    stage = _stage(tmp_path)
    cam = UsdGeom.Camera(stage.GetPrimAtPath("/World/Cam"))
    cam.CreateHorizontalApertureOffsetAttr(0.036)
    cam.CreateVerticalApertureOffsetAttr(-0.018)
    rs = UsdRender.Settings.Define(stage, "/Render/Settings")
    rs.CreateResolutionAttr(Gf.Vec2i(640, 360))
    rs.CreateCameraRel().SetTargets([cam.GetPath()])
    UsdGeom.Camera.Define(stage, "/World/Other")
    conv = convert_stage(stage)
    c = conv.scene["camera"]
    assert c["resolution"] == [640, 360] and c["sensor_fit"] == "horizontal"
    assert _close(c["focal_length_mm"], 50.0) and _close(c["sensor_width_mm"], 36.0)
    assert _close(c["shift_x"], 0.1) and _close(c["shift_y"], -0.05)
    assert {"prim": "/World/Other", "reason": "camera not chosen by /Render/Settings.camera"} in conv.skipped
    _validate(conv.scene)


def test_mesh_triangulation(tmp_path: Path) -> None:
    stage = _stage(tmp_path)
    mesh = UsdGeom.Mesh.Define(stage, "/World/L")
    # An L-shaped (concave) hexagon of area 3, a triangle, and a quad that is a hole.
    pts = [(0, 0, 0), (2, 0, 0), (2, 1, 0), (1, 1, 0), (1, 2, 0), (0, 2, 0), (5, 5, 0), (6, 5, 0), (5, 6, 0)]
    mesh.CreatePointsAttr([Gf.Vec3f(*p) for p in pts])
    mesh.CreateFaceVertexCountsAttr([6, 3, 4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 4, 5, 6, 7, 8, 0, 1, 2, 3])
    mesh.CreateHoleIndicesAttr([2])
    mesh.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    _xform(mesh.GetPrim(), (1, 2, 3), (0, 0, 90), scale=2.0)
    UsdGeom.Mesh.Define(stage, "/World/Empty")
    conv = convert_stage(stage)
    (m,) = conv.scene["meshes"]
    assert len(m["triangles"]) == 5
    p = m["positions"]
    area = 0.0
    for a, b, c in m["triangles"]:
        ab = [p[b][i] - p[a][i] for i in range(3)]
        ac = [p[c][i] - p[a][i] for i in range(3)]
        nz = ab[0] * ac[1] - ab[1] * ac[0]
        assert nz < 0.0  # left-handed faces flipped: clockwise seen from +Z
        area += -nz / 2.0
    assert _close(area, 3.5)
    mat = m["transform"]["matrix"]
    assert _close(mat[0], [0, -2, 0, 1]) and _close(mat[1], [2, 0, 0, 2]) and _close(mat[2], [0, 0, 2, 3])
    assert {"prim": "/World/Empty", "reason": "mesh with no faces"} in conv.skipped
    _validate(conv.scene)


def test_unusable_prims_are_listed(tmp_path: Path) -> None:
    stage = _stage(tmp_path)
    UsdLux.RectLight.Define(stage, "/World/Rect")
    UsdLux.DiskLight.Define(stage, "/World/Disk")
    UsdLux.CylinderLight.Define(stage, "/World/Cyl")
    stage.DefinePrim("/World/Smoke", "Volume")
    UsdGeom.Sphere.Define(stage, "/World/Ball")
    hidden = UsdLux.SphereLight.Define(stage, "/World/Hidden")
    hidden.CreateVisibilityAttr(UsdGeom.Tokens.invisible)
    odd = UsdLux.SphereLight.Define(stage, "/World/OddIes")
    UsdLux.ShapingAPI.Apply(odd.GetPrim()).CreateShapingIesFileAttr(Sdf.AssetPath(str(tmp_path / "x.ies")))
    odd.GetPrim().GetAttribute("inputs:shaping:ies:angleScale").Set(0.5)
    conv = convert_stage(stage)
    listed = {s["prim"]: s["reason"] for s in conv.skipped}
    assert set(listed) == {
        "/World/Rect",
        "/World/Disk",
        "/World/Cyl",
        "/World/Smoke",
        "/World/Ball",
        "/World/Hidden",
        "/World/OddIes",
    }
    assert "RectLight" in listed["/World/Rect"] and "Volume" in listed["/World/Smoke"]
    assert "angleScale" in listed["/World/OddIes"]
    assert conv.scene["lights"] == []


def _bad(tmp_path: Path, case: str) -> Usd.Stage:
    stage = _stage(tmp_path)
    light = UsdLux.SphereLight.Define(stage, "/World/Lamp")
    if case == "nan":
        light.CreateIntensityAttr(float("nan"))
    elif case == "radius":
        light.CreateRadiusAttr(-1.0)
    elif case == "cone":
        UsdLux.ShapingAPI.Apply(light.GetPrim()).CreateShapingConeAngleAttr(0.01)
    elif case == "softness":
        UsdLux.ShapingAPI.Apply(light.GetPrim()).CreateShapingConeSoftnessAttr(1.5)
        light.GetPrim().GetAttribute("inputs:shaping:cone:angle").Set(30.0)
    elif case == "scale":
        UsdGeom.XformCommonAPI(light).SetScale(Gf.Vec3f(1, 0, 1))
    elif case == "ies":
        UsdLux.ShapingAPI.Apply(light.GetPrim()).CreateShapingIesFileAttr(Sdf.AssetPath("./missing.ies"))
    elif case == "color":
        light.CreateColorAttr(Gf.Vec3f(1, -0.5, 1))
    elif case == "exposure":  # 2^2000 overflowed in Python: a bare OverflowError
        light.CreateExposureAttr(2000.0)
    elif case == "medium":
        stage.DefinePrim("/World/Haze").CreateAttribute("tyndall:medium:type", Sdf.ValueTypeNames.String).Set("fog")
    return stage


@pytest.mark.parametrize(
    ("case", "attribute"),
    [
        ("nan", "inputs:intensity"),
        ("radius", "inputs:radius"),
        ("cone", "inputs:shaping:cone:angle"),
        ("softness", "inputs:shaping:cone:softness"),
        ("scale", "xformOpOrder"),
        ("ies", "inputs:shaping:ies:file"),
        ("color", "inputs:color"),
        ("exposure", "inputs:exposure"),
        ("medium", "tyndall:medium:type"),
    ],
)
def test_malformed_stage_names_prim_and_attribute(tmp_path: Path, case: str, attribute: str) -> None:
    stage = _bad(tmp_path, case)
    with pytest.raises(UsdSceneError) as err:
        convert_stage(stage)
    prim = "/World/Haze" if case == "medium" else "/World/Lamp"
    assert err.value.prim == prim and err.value.attribute == attribute
    assert str(err.value).startswith(f"{prim}.{attribute}: ")


def test_no_camera_and_two_cameras(tmp_path: Path) -> None:
    stage = _stage(tmp_path)
    UsdGeom.Camera.Define(stage, "/World/Cam2")
    with pytest.raises(UsdSceneError, match="several cameras"):
        convert_stage(stage)
    settings = stage.DefinePrim("/World/TyndallSettings")
    settings.CreateRelationship("tyndall:output:camera").SetTargets([Sdf.Path("/World/Cam2")])
    assert convert_stage(stage).skipped == [
        {"prim": "/World/Cam", "reason": "camera not chosen by /World/TyndallSettings.tyndall:output:camera"}
    ]
    for path in ("/World/Cam", "/World/Cam2", "/World/TyndallSettings"):
        stage.RemovePrim(path)
    with pytest.raises(UsdSceneError, match="no Camera"):
        convert_stage(stage)


def test_tyndall_attributes_medium_output_sky(tmp_path: Path) -> None:
    stage = _stage(tmp_path)
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    _xform(sun.GetPrim(), (0, 0, 0), (60, 0, 45))
    box = UsdGeom.Cube.Define(stage, "/World/HazeBox")
    _xform(box.GetPrim(), (0, 0, 2), (0, 0, 0), scale=3.0)
    p = box.GetPrim()
    tok, dbl, d3 = Sdf.ValueTypeNames.Token, Sdf.ValueTypeNames.Double, Sdf.ValueTypeNames.Double3
    p.CreateAttribute("tyndall:medium:type", tok).Set("homogeneous")
    p.CreateAttribute("tyndall:medium:scattering", d3).Set(Gf.Vec3d(0.01, 0.02, 0.03))
    p.CreateAttribute("tyndall:medium:phase", tok).Set("cornette_shanks")
    p.CreateAttribute("tyndall:medium:phaseG", dbl).Set(0.8)
    p.CreateAttribute("tyndall:medium:bounds", tok).Set("box")
    fog = stage.DefinePrim("/World/Fog")
    fog.CreateAttribute("tyndall:medium:type", tok).Set("height_fog")
    fog.CreateAttribute("tyndall:medium:scaleHeightM", dbl).Set(20.0)
    fog.CreateAttribute("tyndall:medium:mieScattering", dbl).Set(0.02)
    s = stage.DefinePrim("/World/TyndallSettings")
    s.CreateAttribute("tyndall:output:resolution", Sdf.ValueTypeNames.Int2).Set(Gf.Vec2i(64, 36))
    s.CreateAttribute("tyndall:output:layers", Sdf.ValueTypeNames.TokenArray).Set(["inscatter", "depth"])
    s.CreateAttribute("tyndall:output:tolerance", dbl).Set(1e-3)
    s.CreateAttribute("tyndall:sky:enabled", Sdf.ValueTypeNames.Bool).Set(True)
    s.CreateAttribute("tyndall:sky:aerosol", dbl).Set(2.0)
    conv = convert_stage(stage)
    box_m, fog_m = conv.scene["media"]
    assert box_m["bounds"] == {"box": {"min": [-3.0, -3.0, -1.0], "max": [3.0, 3.0, 5.0]}}
    assert box_m["phase"] == {"type": "cornette_shanks", "g": 0.8} and box_m["scattering"] == [0.01, 0.02, 0.03]
    assert fog_m == {
        "type": "height_fog",
        "name": "Fog",
        "scale_height_m": 20.0,
        "reference_height_m": 0.0,
        "mie": {"scattering": 0.02, "absorption": 0.0, "phase": {"type": "cornette_shanks", "g": 0.76}},
    }
    assert conv.scene["meshes"] == []  # the haze box is a medium, not an occluder
    assert conv.scene["output"] == {"layers": ["inscatter", "depth"], "tolerance": 1e-3}
    assert conv.scene["camera"]["resolution"] == [64, 36]
    d = conv.scene["lights"][0]["direction_to_sun"]
    assert conv.sky is not None and conv.sky.aerosol == 2.0
    assert _close(conv.sky.sun_elevation_deg, math.degrees(math.asin(d[2])))
    assert _close(conv.sky.sun_rotation_deg, math.degrees(math.atan2(d[0], d[1])) % 360.0)
    _validate(conv.scene)


# ------------------------------------------------------------------ results layer


def test_results_layer_round_trip(tmp_path: Path) -> None:
    (tmp_path / "volumetrics.exr").write_bytes(b"")
    (tmp_path / "sky.exr").write_bytes(b"")
    sun = {
        "type": "sun",
        "direction_to_sun": [0.3, -0.5, 0.8],
        "color": [1.0, 0.9, 0.7],
        "strength_w_m2": 6.0,
        "angular_diameter_deg": 0.545,
    }
    skipped = [{"prim": "/root/Area/Area", "reason": "RectLight is not supported"}]
    write_results_layer(
        tmp_path / "results.usda",
        sun=sun,
        sky_texture=tmp_path / "sky.exr",
        assets={"volumetrics": tmp_path / "volumetrics.exr", "sky": tmp_path / "sky.exr"},
        layers=["inscatter", "transmittance", "depth"],
        skipped=skipped,
    )
    text = (tmp_path / "results.usda").read_text()
    assert "@./volumetrics.exr@" in text and 'inputs:texture:format = "latlong"' in text
    back = read_results_layer(tmp_path / "results.usda")
    assert back["assets"]["volumetrics"] == str(tmp_path / "volumetrics.exr")
    assert back["sky"] == {"texture": str(tmp_path / "sky.exr"), "format": "latlong", "strength": 1.0}
    assert back["layers"] == ["inscatter", "transmittance", "depth"]
    assert back["skipped"] == ["/root/Area/Area: RectLight is not supported"]
    s = back["sun"]
    n = math.sqrt(0.3**2 + 0.5**2 + 0.8**2)
    assert _close(s["direction_to_sun"], [0.3 / n, -0.5 / n, 0.8 / n])
    assert _close(s["strength_w_m2"], 6.0) and _close(s["angular_diameter_deg"], 0.545)
    assert _close(s["color"], [1.0, 0.9, 0.7])
    # The results layer is itself a USD stage the reader understands (sun back as a sun).
    stage = Usd.Stage.Open(str(tmp_path / "results.usda"))
    UsdGeom.Camera.Define(stage, "/Cam")
    conv = convert_stage(stage)
    assert _close(conv.scene["lights"][0]["strength_w_m2"], 6.0)
    assert conv.skipped[0]["prim"] == "/Tyndall/Sky"  # a textured dome is not a uniform ambient light


# ------------------------------------------------------------------ Blender's exporter


def _check_against_blender(conv: Any, bl: dict[str, Any]) -> None:
    """Compare the converted scene with the values bpy reported for the same scene."""
    lights = {x["name"]: x for x in conv.scene["lights"]}
    assert set(lights) == {"Point", "Spot", "WideSpot", "Sun"}
    for name, v in bl["lights"].items():
        if v["type"] == "AREA":
            assert any(s["prim"].endswith("/" + name) and "RectLight" in s["reason"] for s in conv.skipped)
            continue
        lt = lights[name]
        mw = v["matrix_world"]
        down = [-mw[i][2] for i in range(3)]
        n = math.sqrt(sum(x * x for x in down))
        down = [x / n for x in down]
        assert _close(lt["color"], v["color"], 1e-6)
        if v["type"] == "SUN":
            assert _close(lt["strength_w_m2"], v["energy"], 1e-6)
            assert _close(lt["angular_diameter_deg"], v["angle_deg"], 1e-5)
            assert _close(lt["direction_to_sun"], [-x for x in down], 1e-6)
            continue
        assert lt["type"] == v["type"].lower()
        assert _close(lt["power_w"], v["energy"], 1e-6)
        assert _close(lt["radius_m"], v["radius"], 1e-6)
        assert _close(lt["position"], [mw[i][3] for i in range(3)], 1e-6)
        assert _close(rotate_wxyz(lt["orientation"]["quaternion_wxyz"], (0, 0, -1)), down, 1e-6)
        if v["type"] == "SPOT":
            assert _close(lt["spot_size_deg"], v["spot_size_deg"], 1e-5)
            assert _close(lt["spot_blend"], v["spot_blend"], 1e-6)
    c, bc = conv.scene["camera"], bl["camera"]
    assert c["resolution"] == bc["resolution"]  # from the tyndall:output:resolution custom property
    assert _close(c["focal_length_mm"], bc["lens"], 1e-6)
    assert _close(c["sensor_width_mm"], bc["sensor_width"], 1e-6)  # AUTO fit, landscape: width
    assert c["sensor_fit"] == "horizontal"
    assert _close(c["shift_x"], bc["shift_x"], 1e-6) and _close(c["shift_y"], bc["shift_y"], 1e-6)
    assert _close(c["clip_start_m"], bc["clip_start"], 1e-6) and _close(c["clip_end_m"], bc["clip_end"], 1e-6)
    mw = bc["matrix_world"]
    assert _close(c["position"], [mw[i][3] for i in range(3)], 1e-6)
    q = c["orientation"]["quaternion_wxyz"]
    for axis in range(3):
        local = [1.0 if i == axis else 0.0 for i in range(3)]
        assert _close(rotate_wxyz(q, local), [mw[i][axis] for i in range(3)], 1e-6)
    meshes = {m["name"]: m for m in conv.scene["meshes"]}
    by_blender = {"Box": "Cube", "Ground": "Plane", "Disc": "Circle"}
    for obj, v in bl["meshes"].items():
        m = meshes[by_blender[obj]]
        mat = m["transform"]["matrix"]
        world = [[sum(mat[r][k] * p[k] for k in range(3)) + mat[r][3] for r in range(3)] for p in m["positions"]]
        assert _close(sorted(world), sorted(v["world_vertices"]), 1e-5)
        assert len(m["triangles"]) == v["triangles"]
        area = 0.0  # bpy's loop-triangle areas are in object space
        loc = m["positions"]
        for a, b, cc in m["triangles"]:
            ab = [loc[b][i] - loc[a][i] for i in range(3)]
            ac = [loc[cc][i] - loc[a][i] for i in range(3)]
            cr = [ab[1] * ac[2] - ab[2] * ac[1], ab[2] * ac[0] - ab[0] * ac[2], ab[0] * ac[1] - ab[1] * ac[0]]
            area += math.sqrt(sum(x * x for x in cr)) / 2.0
        assert _close(area, v["area"], 1e-5)
    (haze,) = conv.scene["media"]
    assert haze == {
        "type": "homogeneous",
        "name": "Haze",
        "scattering": 0.02,
        "absorption": [0.001, 0.002, 0.003],
        "phase": {"type": "henyey_greenstein", "g": 0.6},
    }
    assert conv.scene["output"] == {"layers": ["inscatter", "transmittance", "depth"]}
    _validate(conv.scene)


def test_blender_fixture() -> None:
    """The .usda Blender 5.0.1 exported (committed) reads back to the bpy values."""
    conv = convert_stage(DATA / "blender_scene.usda")
    _check_against_blender(conv, json.loads((DATA / "blender_scene.json").read_text()))


def _bpy_python() -> str:
    exe = os.environ.get("TYNDALL_BPY_PYTHON") or sys.executable
    try:
        ok = subprocess.run([exe, "-c", "import bpy"], capture_output=True, timeout=120).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        ok = False
    if not ok:
        pytest.skip(f"no bpy in {exe} (set TYNDALL_BPY_PYTHON to a Python with bpy 5.0)")
    return exe


def test_blender_export_live(tmp_path: Path) -> None:
    """Export with bpy now (subprocess: bpy bundles its own USD) and compare with bpy's values."""
    exe = _bpy_python()
    usda, js = tmp_path / "b.usda", tmp_path / "b.json"
    subprocess.run([exe, str(DATA / "blender_export.py"), str(usda), str(js)], check=True, capture_output=True)
    bl = json.loads(js.read_text())
    assert bl["blender"].startswith("5.")
    _check_against_blender(convert_stage(usda), bl)


_IMPORT = """
import json, math, sys, bpy
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.context.scene.world = bpy.data.worlds.new("W")
bpy.ops.wm.usd_import(filepath=sys.argv[1])
sun = [o for o in bpy.data.objects if o.type == "LIGHT"][0]
mapping = [n for n in bpy.context.scene.world.node_tree.nodes if n.bl_idname == "ShaderNodeMapping"][0]
rot = list(mapping.inputs["Rotation"].default_value)
json.dump({"energy": sun.data.energy, "angle_deg": math.degrees(sun.data.angle), "color": list(sun.data.color),
           "to_sun": list(sun.matrix_world.col[2][:3]), "mapping_rotation": rot}, open(sys.argv[2], "w"))
"""


def test_results_layer_imports_into_blender(tmp_path: Path) -> None:
    """Blender's USD importer reads our sun and sky back (Blender's own conventions)."""
    exe = _bpy_python()
    (tmp_path / "sky.exr").write_bytes(b"")
    sun = {"direction_to_sun": [0.3, -0.5, 0.8], "color": [1.0, 0.9, 0.7], "strength_w_m2": 6.0}
    write_results_layer(
        tmp_path / "r.usda", sun={**sun, "angular_diameter_deg": 0.545}, sky_texture=tmp_path / "sky.exr"
    )
    (tmp_path / "imp.py").write_text(_IMPORT)
    out = tmp_path / "imp.json"
    subprocess.run([exe, str(tmp_path / "imp.py"), str(tmp_path / "r.usda"), str(out)], check=True, capture_output=True)
    got = json.loads(out.read_text())
    n = math.sqrt(0.3**2 + 0.5**2 + 0.8**2)
    assert _close(got["energy"], 6.0, 1e-5) and _close(got["angle_deg"], 0.545, 1e-4)
    assert _close(got["color"], [1.0, 0.9, 0.7], 1e-6)
    assert _close(got["to_sun"], [0.3 / n, -0.5 / n, 0.8 / n], 1e-5)
    assert _close(got["mapping_rotation"], [0.0, 0.0, 0.0], 1e-5)  # an unrotated Environment Texture


_IMPORT_INSTANCES = """
import json, sys, bpy
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.wm.usd_import(filepath=sys.argv[1])
out = {"lights": [], "meshes": []}
for inst in bpy.context.evaluated_depsgraph_get().object_instances:
    ob, m = inst.object, inst.matrix_world
    if ob.type == "LIGHT":
        out["lights"].append(list(m.translation))
    elif ob.type == "MESH":
        out["meshes"].append(sorted(list(m @ v.co) for v in ob.data.vertices))
json.dump(out, open(sys.argv[2], "w"))
"""


def test_blender_places_a_point_instancers_instances_where_we_do(tmp_path: Path) -> None:
    """Blender 5.0's own USD importer, the authority on what a stage means in Blender,
    puts the instancer's lamps and meshes where the reader does (the rig of
    test_a_point_instancers_lamps_and_meshes_stand_where_it_places_them: a turned instancer
    under a turned Xform, one instance turned and doubled, one hidden)."""
    exe = _bpy_python()
    stage = _stage(tmp_path, name="rig.usda")
    _instancer_rig(stage, explicit=False)
    stage.Save()
    conv = convert_stage(stage)
    (tmp_path / "imp.py").write_text(_IMPORT_INSTANCES)
    out = tmp_path / "imp.json"
    cmd = [exe, str(tmp_path / "imp.py"), str(tmp_path / "rig.usda"), str(out)]
    subprocess.run(cmd, check=True, capture_output=True)
    got = json.loads(out.read_text())
    ours_lights = sorted(light["position"] for light in conv.scene["lights"])
    ours_meshes = []
    for m in conv.scene["meshes"]:
        matrix = np.array(m["transform"]["matrix"])
        points = np.c_[np.array(m["positions"]), np.ones(len(m["positions"]))]
        ours_meshes.append(sorted((matrix @ points.T).T[:, :3].tolist()))
    assert len(got["lights"]) == len(ours_lights) == 2 and len(got["meshes"]) == len(ours_meshes) == 2, got
    assert _close(sorted(got["lights"]), ours_lights, 1e-5), (got["lights"], ours_lights)
    assert _close(sorted(got["meshes"]), sorted(ours_meshes), 1e-5), (got["meshes"], ours_meshes)


# ------------------------------------------------------------------ CLI


def test_cli_renders_a_usd_stage(tmp_path: Path) -> None:
    cli = pytest.importorskip("tyndall.cli")
    if not hasattr(cli, "render_usd"):
        pytest.skip("installed tyndall predates the USD hook (reinstall: pip install .)")
    stage = _stage(tmp_path, name="shot.usda")
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    _xform(sun.GetPrim(), (0, 0, 0), (50, 0, 30))
    sun.CreateIntensityAttr(1.0)  # UsdLux's fallback for a DistantLight is 50000
    sun.CreateNormalizeAttr(True)
    UsdLux.RectLight.Define(stage, "/World/Rect")
    s = stage.DefinePrim("/World/TyndallSettings")
    s.CreateAttribute("tyndall:output:resolution", Sdf.ValueTypeNames.Int2).Set(Gf.Vec2i(32, 18))
    s.CreateAttribute("tyndall:medium:type", Sdf.ValueTypeNames.Token).Set("homogeneous")
    s.CreateAttribute("tyndall:medium:scattering", Sdf.ValueTypeNames.Double).Set(0.01)
    stage.Save()
    out = tmp_path / "out"
    rc = cli.render_usd([str(tmp_path / "shot.usda"), "--out", str(out), "--quiet"])
    assert rc == 0
    assert (out / "volumetrics.exr").is_file() and (out / "scene.json").is_file()
    report = json.loads((out / "volumetrics.report.json").read_text())
    assert report["usd"]["skipped"] == [{"prim": "/World/Rect", "reason": report["usd"]["skipped"][0]["reason"]}]
    back = read_results_layer(out / "tyndall_results.usda")
    assert back["assets"]["volumetrics"] == str(out / "volumetrics.exr")
    assert back["skipped"][0].startswith("/World/Rect: ")
    assert _close(back["sun"]["strength_w_m2"], 4.0)  # DistantLight intensity 1 = Blender Strength 4


def test_cli_reports_a_malformed_stage(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cli = pytest.importorskip("tyndall.cli")
    if not hasattr(cli, "render_usd"):
        pytest.skip("installed tyndall predates the USD hook (reinstall: pip install .)")
    stage = _bad(tmp_path, "radius")
    stage.Save()
    rc = cli.render_usd([str(tmp_path / "s.usda"), "--out", str(tmp_path / "o")])
    assert rc == 1
    assert "/World/Lamp.inputs:radius: must be ≥ 0" in capsys.readouterr().err


# ------------------------------------------------------------------ Scene → USD → Blender

_IMPORT_VALUES = """
import json, sys, bpy
sys.path.insert(0, sys.argv[3])
import blender_export
bpy.ops.wm.read_factory_settings(use_empty=True)
bpy.ops.wm.usd_import(filepath=sys.argv[1], property_import_mode="ALL")
vals = blender_export.values()
cam = bpy.context.scene.camera or next(o for o in bpy.data.objects if o.type == "CAMERA")
def props(idb):
    return {k: (list(v) if hasattr(v, "__len__") and not isinstance(v, str) else v)
            for k, v in idb.items() if k.startswith("tyndall")}
vals["camera_properties"] = {**props(cam), **props(cam.data)}
vals["medium_properties"] = {o.name: props(o) for o in bpy.data.objects if o.type == "EMPTY" and props(o)}
json.dump(vals, open(sys.argv[2], "w"))
"""


def test_scene_to_usd_to_scene_is_identity(tmp_path: Path) -> None:
    """write_stage is the inverse of convert_stage: the scene converted from Blender's export,
    written back as USD and read again, is the same scene (float tolerance)."""
    conv = convert_stage(DATA / "blender_scene.usda")
    assert write_stage(conv.scene, tmp_path / "rt.usda") == []
    again = convert_stage(tmp_path / "rt.usda")
    assert again.skipped == []
    # float32 in USD's schema attributes (radius, colour, camera apertures): 1e-6 relative
    _same_tree(again.scene, conv.scene, 1e-6)
    _validate(again.scene)


def test_blender_usd_scene_usd_blender_round_trip(tmp_path: Path) -> None:
    """Issue 5: Blender → USD (Blender's exporter) → Scene → USD (write_stage) → Blender (Blender's
    importer) keeps each light type (point, spot, spot under a rotated parent, sun), their colours,
    powers, radii, cones, blends and transforms, the camera and the meshes."""
    exe = _bpy_python()
    usda, js = tmp_path / "b.usda", tmp_path / "b.json"
    subprocess.run([exe, str(DATA / "blender_export.py"), str(usda), str(js)], check=True, capture_output=True)
    bl = json.loads(js.read_text())
    conv = convert_stage(usda)
    assert write_stage(conv.scene, tmp_path / "rt.usda") == []
    (tmp_path / "imp.py").write_text(_IMPORT_VALUES)
    out = tmp_path / "back.json"
    r = subprocess.run(
        [exe, str(tmp_path / "imp.py"), str(tmp_path / "rt.usda"), str(out), str(DATA)], capture_output=True, text=True
    )
    assert r.returncode == 0, r.stderr[-3000:]
    back = json.loads(out.read_text())
    kinds = {}
    for name, v in bl["lights"].items():
        if v["type"] == "AREA":
            assert name not in back["lights"]  # not convertible: listed as skipped, never written
            continue
        w = back["lights"][name]
        kinds[v["type"]] = kinds.get(v["type"], 0) + 1
        assert w["type"] == v["type"], name
        assert _close(w["energy"], v["energy"], 1e-5), name
        assert _close(w["color"], v["color"], 1e-6), name
        if v["type"] == "SUN":
            # A sun is a direction: its local +Z (position and roll carry nothing).
            z = [[r[2] for r in m[:3]] for m in (w["matrix_world"], v["matrix_world"])]
            assert _close(z[0], z[1], 1e-6), name
        else:
            assert _close(w["matrix_world"], v["matrix_world"], 1e-5), name
        for k in ("radius", "spot_size_deg", "spot_blend", "angle_deg"):
            if k in v:
                assert _close(w[k], v[k], 1e-5), (name, k)
    assert kinds == {"POINT": 1, "SPOT": 2, "SUN": 1}
    c, bc = back["camera"], bl["camera"]
    for k in ("lens", "shift_x", "shift_y", "clip_start", "clip_end"):
        assert _close(c[k], bc[k], 1e-5), k
    assert _close(c["matrix_world"], bc["matrix_world"], 1e-5)
    assert back["camera_properties"].get("tyndall:output:resolution") == bc["resolution"]
    # The haze comes back as an Empty carrying the tyndall:medium attributes Blender exported.
    haze = back["medium_properties"]["Haze"]
    assert haze["tyndall:medium:type"] == "homogeneous" and haze["tyndall:medium:phase"] == "henyey_greenstein"
    assert _close(haze["tyndall:medium:scattering"], 0.02, 1e-9)
    assert _close(haze["tyndall:medium:absorption"], [0.001, 0.002, 0.003], 1e-9)
    assert _close(haze["tyndall:medium:phaseG"], 0.6, 1e-9)
    by_blender = {"Box": "Cube", "Ground": "Plane", "Disc": "Circle"}
    for obj, v in bl["meshes"].items():
        m = back["meshes"][by_blender[obj]]
        assert _close(sorted(m["world_vertices"]), sorted(v["world_vertices"]), 1e-5), obj
        assert m["triangles"] == v["triangles"]


def _instancer_rig(stage: Usd.Stage, explicit: bool) -> None:
    """Three fixtures (a spot lamp on a yoke, and a box) under a turned Xform, placed by a
    PointInstancer (the middle one hidden by invisibleIds), or, with ``explicit``, as
    ordinary prims at the instances' places (positions, orientations, scales, composed as
    UsdGeom.PointInstancer documents: scale, then orientation, then translation)."""
    rig = UsdGeom.Xform.Define(stage, "/World/Rig")
    _xform(rig.GetPrim(), (0.5, 1.0, 0.25), (0, 0, 30))
    positions = [Gf.Vec3f(-2, 0, 4), Gf.Vec3f(0, 0, 4), Gf.Vec3f(2, 0.5, 4.5)]
    orientations = [Gf.Quath(1, 0, 0, 0), Gf.Quath(1, 0, 0, 0), Gf.Quath(0, 1, 0, 0)]
    scales = [Gf.Vec3f(1, 1, 1), Gf.Vec3f(1, 1, 1), Gf.Vec3f(2, 2, 2)]

    if not explicit:
        inst = UsdGeom.PointInstancer.Define(stage, "/World/Rig/Truss")
        _xform(inst.GetPrim(), (1, 0, 0), (10, 20, 30))
        _fixture(stage, "/World/Rig/Truss/Protos/Fixture")
        inst.CreatePrototypesRel().SetTargets([Sdf.Path("/World/Rig/Truss/Protos/Fixture")])
        inst.CreateProtoIndicesAttr([0, 0, 0])
        inst.CreatePositionsAttr(positions)
        inst.CreateOrientationsAttr(orientations)
        inst.CreateScalesAttr(scales)
        inst.CreateInvisibleIdsAttr([1])
        return
    truss = UsdGeom.Xform.Define(stage, "/World/Rig/Truss")
    _xform(truss.GetPrim(), (1, 0, 0), (10, 20, 30))
    for i in (0, 2):
        place = UsdGeom.Xform.Define(stage, f"/World/Rig/Truss/Place{i}")
        place.AddTransformOp().Set(_instance_matrix(positions[i], orientations[i], scales[i]))
        _fixture(stage, f"/World/Rig/Truss/Place{i}/Fixture")


def _fixture(stage: Usd.Stage, root: str) -> None:
    """A spot lamp on a yoke (two levels of transforms below ``root``) and a flag mesh."""
    yoke = UsdGeom.Xform.Define(stage, root)
    _xform(yoke.GetPrim(), (0, 0, 0.5), (0, 0, 0))
    head = UsdGeom.Xform.Define(stage, root + "/Head")
    _xform(head.GetPrim(), (0, 0.2, 0), (-20, 0, 0))
    lamp = UsdLux.SphereLight.Define(stage, root + "/Head/Lamp")
    lamp.CreateIntensityAttr(200.0)
    lamp.CreateRadiusAttr(0.05)
    shaping = UsdLux.ShapingAPI.Apply(lamp.GetPrim())
    shaping.CreateShapingConeAngleAttr(15.0)
    shaping.CreateShapingConeSoftnessAttr(0.2)
    box = UsdGeom.Mesh.Define(stage, root + "/Flag")
    box.CreatePointsAttr([(-0.2, -0.2, -0.6), (0.2, -0.2, -0.6), (0.2, 0.2, -0.6), (-0.2, 0.2, -0.6)])
    box.CreateFaceVertexCountsAttr([4])
    box.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    _xform(box.GetPrim(), (0.1, 0, 0), (0, 0, 0), 1.5)


def _instance_matrix(position: Gf.Vec3f, orientation: Gf.Quath, scale: Gf.Vec3f) -> Gf.Matrix4d:
    """An instance's transform as UsdGeom.PointInstancer documents it: scale, then
    orientation, then translation (row vectors)."""
    rot = Gf.Rotation(Gf.Quatd(orientation.GetReal(), Gf.Vec3d(orientation.GetImaginary())))
    m = Gf.Matrix4d().SetScale(Gf.Vec3d(scale)) * Gf.Matrix4d().SetRotate(rot)
    return m * Gf.Matrix4d().SetTranslate(Gf.Vec3d(position))


def _nested_rig(stage: Usd.Stage, explicit: bool) -> None:
    """Two trusses placed by an outer PointInstancer (the second turned and scaled), each
    a prototype with its own transform holding, below a turned bar, an inner PointInstancer
    that places three fixtures (the middle one hidden); or, with ``explicit``, the same
    lamps and flags as ordinary prims at the composed transforms."""
    kind = UsdGeom.Xform if explicit else UsdGeom.PointInstancer
    outer = kind.Define(stage, "/World/Rigs")
    _xform(outer.GetPrim(), (0.5, 1.0, 0.25), (0, 0, 30))
    outer_places = [
        (Gf.Vec3f(-1, 0, 3), Gf.Quath(1, 0, 0, 0), Gf.Vec3f(1, 1, 1)),
        (Gf.Vec3f(1.5, 0.5, 3.5), Gf.Quath(0.5, 0.5, 0.5, 0.5), Gf.Vec3f(1.5, 1.5, 1.5)),
    ]
    inner_places = [
        (Gf.Vec3f(-1, 0, 0), Gf.Quath(1, 0, 0, 0), Gf.Vec3f(1, 1, 1)),
        (Gf.Vec3f(0, 0, 0), Gf.Quath(1, 0, 0, 0), Gf.Vec3f(1, 1, 1)),
        (Gf.Vec3f(1, 0.2, 0), Gf.Quath(0, 1, 0, 0), Gf.Vec3f(0.5, 0.5, 0.5)),
    ]

    def truss(root: str) -> None:
        t = UsdGeom.Xform.Define(stage, root)
        _xform(t.GetPrim(), (0, 0, 0.3), (0, 0, 10))
        bar = UsdGeom.Xform.Define(stage, root + "/Bar")
        _xform(bar.GetPrim(), (0.2, 0, 0), (5, 0, 0))
        if explicit:
            lamps = UsdGeom.Xform.Define(stage, root + "/Bar/Lamps")
            _xform(lamps.GetPrim(), (0, 0.1, 0), (0, 0, -15))
            for j in (0, 2):
                place = UsdGeom.Xform.Define(stage, f"{root}/Bar/Lamps/Place{j}")
                place.AddTransformOp().Set(_instance_matrix(*inner_places[j]))
                _fixture(stage, f"{root}/Bar/Lamps/Place{j}/Fixture")
            return
        inner = UsdGeom.PointInstancer.Define(stage, root + "/Bar/Lamps")
        _xform(inner.GetPrim(), (0, 0.1, 0), (0, 0, -15))
        _fixture(stage, root + "/Bar/Lamps/Protos/Fixture")
        inner.CreatePrototypesRel().SetTargets([Sdf.Path(root + "/Bar/Lamps/Protos/Fixture")])
        inner.CreateProtoIndicesAttr([0, 0, 0])
        inner.CreatePositionsAttr([p for p, _, _ in inner_places])
        inner.CreateOrientationsAttr([q for _, q, _ in inner_places])
        inner.CreateScalesAttr([s_ for _, _, s_ in inner_places])
        inner.CreateInvisibleIdsAttr([1])

    if explicit:
        for i, place_i in enumerate(outer_places):
            place = UsdGeom.Xform.Define(stage, f"/World/Rigs/Place{i}")
            place.AddTransformOp().Set(_instance_matrix(*place_i))
            truss(f"/World/Rigs/Place{i}/Truss")
        return
    truss("/World/Rigs/Protos/Truss")
    inst = UsdGeom.PointInstancer(outer)
    inst.CreatePrototypesRel().SetTargets([Sdf.Path("/World/Rigs/Protos/Truss")])
    inst.CreateProtoIndicesAttr([0, 0])
    inst.CreatePositionsAttr([p for p, _, _ in outer_places])
    inst.CreateOrientationsAttr([q for _, q, _ in outer_places])
    inst.CreateScalesAttr([s_ for _, _, s_ in outer_places])


def test_a_point_instancers_lamps_and_meshes_stand_where_it_places_them(tmp_path: Path) -> None:
    """Each drawn instance of a PointInstancer gives its prototype's lamps and meshes, at the
    same places as ordinary prims at the instances' transforms would (the instancer turned
    and under a turned Xform, the prototype with its own transform, the lamp two levels
    below it, one instance turned and scaled, one hidden). (A turned instancer was once
    refused: the inverse of the prototype's transform left 1 − 2⁻⁵² in its corner.)"""
    haze = '{"type": "homogeneous", "scattering": 0.03}'
    convs = []
    for explicit in (False, True):
        stage = _stage(tmp_path, name=f"rig_{explicit}.usda")
        h = stage.DefinePrim("/World/Haze")
        h.CreateAttribute("tyndall:medium:type", Sdf.ValueTypeNames.String).Set("homogeneous")
        h.CreateAttribute("tyndall:medium:scattering", Sdf.ValueTypeNames.Double).Set(0.03)
        _instancer_rig(stage, explicit)
        convs.append(convert_stage(stage))
    inst, ref = convs
    assert inst.skipped == [] and ref.skipped == [], (inst.skipped, ref.skipped)
    assert [light["name"] for light in inst.scene["lights"]] == ["Lamp_0", "Lamp_2"]
    assert [m["name"] for m in inst.scene["meshes"]] == ["Flag_0", "Flag_2"]
    assert inst.light_prims == ["/World/Rig/Truss/Protos/Fixture/Head/Lamp"] * 2
    assert any("2 of 3 instances drawn: 2 lights and 2 meshes placed" in n for n in inst.notes), inst.notes
    for a, b in zip(inst.scene["lights"], ref.scene["lights"], strict=True):
        assert a["type"] == b["type"] == "spot"
        _same_tree({**a, "name": ""}, {**b, "name": ""}, 1e-6, a["name"])
    for a, b in zip(inst.scene["meshes"], ref.scene["meshes"], strict=True):
        _same_tree({**a, "name": ""}, {**b, "name": ""}, 1e-6, a["name"])
    # The lamp's radius follows the instance's scale, as a prim's scale.
    assert math.isclose(inst.scene["lights"][1]["radius_m"], 0.1, rel_tol=1e-6)
    # Both render the same image.
    scenes = []
    for conv in convs:
        scene = dict(conv.scene)
        scene["camera"] = {
            "type": "perspective",
            "position": [0, -12, 3],
            "orientation": {"look_at": {"target": [0.5, 1, 3]}},
            "resolution": [32, 18],
        }
        scene["media"] = [json.loads(haze)]
        scene["output"] = {"layers": ["inscatter"], "pixel_filter": {"type": "none"}, "tolerance": 1e-4}
        scenes.append(scene)
    a, b = (tyndall.render(s_)[0]["inscatter"] for s_ in scenes)
    assert np.max(a) > 0.0
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7 * float(np.max(a)))


def test_a_point_instancers_prototypes_drawn_as_usd_imaging_draws_them(tmp_path: Path) -> None:
    """Prototypes under an ``over`` (the layout UsdGeomPointInstancer's docs recommend) or
    under a hidden container are still drawn at every instance; an animated instancer with
    velocities is read at its positions' first sample (the default, earliest time code is
    no time to move points by their velocities)."""
    for layout in ("over", "hidden"):
        stage = _stage(tmp_path, name=f"{layout}.usda")
        inst = UsdGeom.PointInstancer.Define(stage, "/World/PI")
        UsdLux.SphereLight.Define(stage, "/World/Protos/P/Lamp")
        if layout == "over":
            stage.GetPrimAtPath("/World/Protos").SetSpecifier(Sdf.SpecifierOver)
        else:
            UsdGeom.Scope.Define(stage, "/World/Protos").MakeInvisible()
        inst.CreatePrototypesRel().SetTargets([Sdf.Path("/World/Protos/P")])
        inst.CreateProtoIndicesAttr([0, 0])
        inst.CreatePositionsAttr([Gf.Vec3f(-1, 0, 4), Gf.Vec3f(1, 0, 4)])
        conv = convert_stage(stage)
        assert [light["position"] for light in conv.scene["lights"]] == [[-1.0, 0.0, 4.0], [1.0, 0.0, 4.0]], layout
        # Drawn by its instances, so not listed as an invisible prim left out.
        assert all(d["prim"] != "/World/Protos/P/Lamp" for d in conv.skipped), (layout, conv.skipped)
    # A hidden prototype no drawn instance places is listed as left out.
    stage = _stage(tmp_path, name="unplaced.usda")
    inst = UsdGeom.PointInstancer.Define(stage, "/World/PI")
    UsdGeom.Scope.Define(stage, "/World/Protos").MakeInvisible()
    UsdLux.SphereLight.Define(stage, "/World/Protos/P/Lamp")
    UsdLux.SphereLight.Define(stage, "/World/Protos/Q/Lamp")
    inst.CreatePrototypesRel().SetTargets([Sdf.Path("/World/Protos/P"), Sdf.Path("/World/Protos/Q")])
    inst.CreateProtoIndicesAttr([0, 1])
    inst.CreatePositionsAttr([Gf.Vec3f(-1, 0, 4), Gf.Vec3f(1, 0, 4)])
    inst.CreateInvisibleIdsAttr([1])
    conv = convert_stage(stage)
    assert [light["position"] for light in conv.scene["lights"]] == [[-1.0, 0.0, 4.0]]
    assert {"prim": "/World/Protos/Q/Lamp", "reason": "invisible SphereLight"} in conv.skipped
    assert all(d["prim"] != "/World/Protos/P/Lamp" for d in conv.skipped), conv.skipped
    stage = _stage(tmp_path, name="moving.usda")
    inst = UsdGeom.PointInstancer.Define(stage, "/World/PI")
    UsdLux.SphereLight.Define(stage, "/World/PI/Protos/Lamp")
    inst.CreatePrototypesRel().SetTargets([Sdf.Path("/World/PI/Protos/Lamp")])
    inst.CreateProtoIndicesAttr([0])
    for t, z in ((1.0, 4.0), (10.0, 5.0)):
        inst.CreatePositionsAttr().Set([Gf.Vec3f(0, 0, z)], t)
        inst.CreateVelocitiesAttr().Set([Gf.Vec3f(0, 0, 24)], t)
    assert [light["position"] for light in convert_stage(stage).scene["lights"]] == [[0.0, 0.0, 4.0]]


def test_a_point_instancer_with_bad_indices_or_sizes_is_named(tmp_path: Path) -> None:
    for attribute in ("protoIndices", "positions", "orientations"):
        stage = _stage(tmp_path, name=f"bad_{attribute}.usda")
        inst = UsdGeom.PointInstancer.Define(stage, "/World/PI")
        lamp = UsdLux.SphereLight.Define(stage, "/World/PI/Protos/Lamp")
        inst.CreatePrototypesRel().SetTargets([lamp.GetPath()])
        if attribute == "protoIndices":
            inst.CreatePositionsAttr([Gf.Vec3f(0, 0, 4), Gf.Vec3f(1, 0, 4)])
            inst.CreateProtoIndicesAttr([0, 1])
            want = "index 1 is out of range for 1 prototypes"
        elif attribute == "positions":
            inst.CreatePositionsAttr([Gf.Vec3f(0, 0, 4)])
            inst.CreateProtoIndicesAttr([0, 0])
            want = "1 values for 2 instances"
        else:
            # (USD itself only warns, and then turns none of the instances.)
            inst.CreatePositionsAttr([Gf.Vec3f(0, 0, 4), Gf.Vec3f(1, 0, 4)])
            inst.CreateOrientationsAttr([Gf.Quath(0, 1, 0, 0)])
            inst.CreateProtoIndicesAttr([0, 0])
            want = "1 values for 2 instances"
        with pytest.raises(UsdSceneError) as e:
            convert_stage(stage)
        assert e.value.prim == "/World/PI" and e.value.attribute == attribute, str(e.value)
        assert want in str(e.value)


def test_what_a_point_instancers_prototype_cannot_hold_is_listed(tmp_path: Path) -> None:
    """A camera (with what it holds) or a dome light inside a prototype is listed once, not
    once per instance, and the prototype's lamp is still placed at every instance."""
    stage = _stage(tmp_path)
    inst = UsdGeom.PointInstancer.Define(stage, "/World/PI")
    UsdLux.SphereLight.Define(stage, "/World/PI/Protos/P/Lamp")
    UsdLux.DomeLight.Define(stage, "/World/PI/Protos/P/Dome")
    UsdGeom.Camera.Define(stage, "/World/PI/Protos/P/Cam")
    UsdLux.SphereLight.Define(stage, "/World/PI/Protos/P/Cam/Deep")
    inst.CreatePrototypesRel().SetTargets([Sdf.Path("/World/PI/Protos/P")])
    inst.CreatePositionsAttr([Gf.Vec3f(-1, 0, 4), Gf.Vec3f(1, 0, 4)])
    inst.CreateProtoIndicesAttr([0, 0])
    conv = convert_stage(stage)
    assert [light["name"] for light in conv.scene["lights"]] == ["Lamp_0", "Lamp_1"]
    assert [light["position"] for light in conv.scene["lights"]] == [[-1.0, 0.0, 4.0], [1.0, 0.0, 4.0]]
    assert [d["prim"] for d in conv.skipped] == ["/World/PI/Protos/P/Dome", "/World/PI/Protos/P/Cam"]
    assert "a Camera inside the prototype of the PointInstancer /World/PI" in conv.skipped[1]["reason"]


def test_nested_point_instancers_place_their_lamps_in_every_outer_instance(tmp_path: Path) -> None:
    """A PointInstancer inside another's prototype places its fixtures in every drawn outer
    instance, where ordinary prims at the composed transforms stand (outer instancer turned,
    one outer instance turned and scaled, the prototype and the bar below it with their own
    transforms, the inner instancer turned, one inner instance hidden, one turned and halved);
    copies are named ``<name>_<outer>_<inner>``."""
    convs = []
    for explicit in (False, True):
        stage = _stage(tmp_path, name=f"nested_{explicit}.usda")
        _nested_rig(stage, explicit)
        convs.append(convert_stage(stage))
    inst, ref = convs
    assert inst.skipped == [] and ref.skipped == [], (inst.skipped, ref.skipped)
    assert [light["name"] for light in inst.scene["lights"]] == ["Lamp_0_0", "Lamp_0_2", "Lamp_1_0", "Lamp_1_2"]
    assert [m["name"] for m in inst.scene["meshes"]] == ["Flag_0_0", "Flag_0_2", "Flag_1_0", "Flag_1_2"]
    assert inst.light_prims == ["/World/Rigs/Protos/Truss/Bar/Lamps/Protos/Fixture/Head/Lamp"] * 4
    notes = " | ".join(inst.notes)
    placed = "/World/Rigs: PointInstancer with 2 of 2 instances drawn: 4 lights and 4 meshes placed (8 of them by"
    assert placed in notes, notes
    assert "2 of 3 instances drawn in each of its instances" in notes, notes
    assert len(ref.scene["lights"]) == len(ref.scene["meshes"]) == 4
    for a, b in zip(inst.scene["lights"], ref.scene["lights"], strict=True):
        _same_tree({**a, "name": ""}, {**b, "name": ""}, 1e-6, a["name"])
    for a, b in zip(inst.scene["meshes"], ref.scene["meshes"], strict=True):
        _same_tree({**a, "name": ""}, {**b, "name": ""}, 1e-6, a["name"])
    # The outer instance's scale 1.5 and the inner one's 0.5 both reach the lamp's radius.
    assert [round(light["radius_m"], 6) for light in inst.scene["lights"]] == [0.05, 0.025, 0.075, 0.0375]


def test_an_instancer_among_its_own_prototypes_is_named(tmp_path: Path) -> None:
    """A PointInstancer whose prototype holds the instancer itself would place itself
    forever: an error naming it and its prototypes, not a hang."""
    stage = _stage(tmp_path)
    inst = UsdGeom.PointInstancer.Define(stage, "/World/Loop/PI")
    UsdLux.SphereLight.Define(stage, "/World/Loop/Lamp")
    inst.CreatePrototypesRel().SetTargets([Sdf.Path("/World/Loop")])
    inst.CreatePositionsAttr([Gf.Vec3f(0, 0, 4)])
    inst.CreateProtoIndicesAttr([0])
    with pytest.raises(UsdSceneError) as e:
        convert_stage(stage)
    assert e.value.prim == "/World/Loop/PI" and e.value.attribute == "prototypes", str(e.value)
    assert "among its own prototypes" in str(e.value)


def test_a_singular_nested_instancer_is_named(tmp_path: Path) -> None:
    """A third-level instancer whose own transform is singular (a scale of 0) is named with
    ``xformOpOrder``, also when a lamp placed before it in the outer prototype left its
    instance's matrix behind (the error once named the lamp of the innermost prototype)."""
    for lamp_first in (False, True):
        stage = _stage(tmp_path, name=f"singular_{lamp_first}.usda")
        UsdGeom.Xform.Define(stage, "/World/A/Protos/T")
        if lamp_first:
            UsdLux.SphereLight.Define(stage, "/World/A/Protos/T/AFirst")
        UsdLux.SphereLight.Define(stage, "/World/Lamps/Fixture/Lamp")
        levels = {
            "/World/A": "/World/A/Protos/T",
            "/World/A/Protos/T/B": "/World/A/Protos/T/B/Protos/U",
            "/World/A/Protos/T/B/Protos/U/C": "/World/Lamps/Fixture",
        }
        for path, proto in levels.items():
            inst = UsdGeom.PointInstancer.Define(stage, path)
            inst.CreatePrototypesRel().SetTargets([Sdf.Path(proto)])
            inst.CreateProtoIndicesAttr([0])
            inst.CreatePositionsAttr([Gf.Vec3f(0, 0, 1)])
        UsdGeom.XformCommonAPI(stage.GetPrimAtPath("/World/A/Protos/T/B/Protos/U/C")).SetScale(Gf.Vec3f(0, 1, 1))
        with pytest.raises(UsdSceneError) as e:
            convert_stage(stage)
        where = (e.value.prim, e.value.attribute)
        assert where == ("/World/A/Protos/T/B/Protos/U/C", "xformOpOrder"), (lamp_first, str(e.value))


@pytest.mark.parametrize("mpu", [1e-300, 1e-10, 2e9, 1e300])
def test_meters_per_unit_out_of_range_is_named(tmp_path: Path, mpu: float) -> None:
    """1e-300 was blamed on a prim's xformOpOrder, 1e300 on camera.clip_start_m (a field
    the stage never wrote): metersPerUnit itself is named now."""
    stage = _stage(tmp_path, mpu=mpu)
    with pytest.raises(UsdSceneError, match=r"^/\.metersPerUnit: must be within 1e-9\.\.=1e9"):
        convert_stage(stage)


def test_non_uniform_scale_of_a_shaped_light_is_noted(tmp_path: Path) -> None:
    """Only a spot's orientation is read: a stretched cone is read round, and said so."""
    stage = _stage(tmp_path)
    haze = stage.DefinePrim("/World/Haze")
    haze.CreateAttribute("tyndall:medium:type", Sdf.ValueTypeNames.String).Set("homogeneous")
    haze.CreateAttribute("tyndall:medium:scattering", Sdf.ValueTypeNames.Double).Set(0.03)
    spot = UsdLux.SphereLight.Define(stage, "/World/Spot")
    UsdLux.ShapingAPI.Apply(spot.GetPrim()).CreateShapingConeAngleAttr(20.0)
    UsdGeom.XformCommonAPI(spot).SetScale(Gf.Vec3f(2, 1, 1))
    conv = convert_stage(stage)
    assert conv.scene["lights"][0]["type"] == "spot"
    assert any(n.startswith("/World/Spot: non-uniform scale (2, 1, 1)") for n in conv.notes), conv.notes


def test_a_mesh_light_is_listed_and_kept_as_an_occluder(tmp_path: Path) -> None:
    """A mesh with MeshLightAPI emits in Hydra: Tyndall cannot, so it says so, and keeps the
    mesh as the occluder it also is. An authored subdivision scheme is noted (the cage is
    used); the catmullClark fallback on an ordinary mesh is not."""
    stage = _stage(tmp_path)
    quad = ([(-1, -1, 3), (1, -1, 3), (1, 1, 3), (-1, 1, 3)], [4], [0, 1, 2, 3])
    for path in ("/World/Panel", "/World/Plain", "/World/Smooth"):
        mesh = UsdGeom.Mesh.Define(stage, path)
        mesh.CreatePointsAttr(quad[0])
        mesh.CreateFaceVertexCountsAttr(quad[1])
        mesh.CreateFaceVertexIndicesAttr(quad[2])
    UsdLux.MeshLightAPI.Apply(stage.GetPrimAtPath("/World/Panel"))
    UsdGeom.Mesh(stage.GetPrimAtPath("/World/Smooth")).CreateSubdivisionSchemeAttr(UsdGeom.Tokens.catmullClark)
    conv = convert_stage(stage)
    assert sorted(m["name"] for m in conv.scene["meshes"]) == ["Panel", "Plain", "Smooth"]
    assert conv.scene["lights"] == []
    assert [d["prim"] for d in conv.skipped] == ["/World/Panel"]
    assert "emission is not supported" in conv.skipped[0]["reason"]
    subdivided = [n for n in conv.notes if "subdivisionScheme" in n]
    assert len(subdivided) == 1 and subdivided[0].startswith("/World/Smooth: ")


def test_light_and_shadow_linking_are_noted_not_dropped(tmp_path: Path) -> None:
    """A light-linking or shadow-linking collection that leaves something out cannot be
    applied (every medium is lit, every mesh shadows): the light is kept and the report says
    so. Collections left at their fallback (everything) give no note."""
    stage = _stage(tmp_path)
    wall = UsdGeom.Mesh.Define(stage, "/World/Wall")
    wall.CreatePointsAttr([(-1, 1, 0), (1, 1, 0), (1, 1, 3)])
    wall.CreateFaceVertexCountsAttr([3])
    wall.CreateFaceVertexIndicesAttr([0, 1, 2])
    linked = UsdLux.SphereLight.Define(stage, "/World/Linked")
    lux = UsdLux.LightAPI(linked.GetPrim())
    lux.GetShadowLinkCollectionAPI().CreateIncludeRootAttr(False)
    lux.GetLightLinkCollectionAPI().CreateExcludesRel().AddTarget("/World/Wall")
    UsdLux.SphereLight.Define(stage, "/World/Plain")
    # Includes that name every mesh and medium leave nothing out: no note.
    listed = UsdLux.SphereLight.Define(stage, "/World/Listed")
    listed_link = UsdLux.LightAPI(listed.GetPrim()).GetLightLinkCollectionAPI()
    listed_link.CreateIncludeRootAttr(False)
    listed_link.CreateIncludesRel().AddTarget("/World")
    conv = convert_stage(stage)
    assert [light["name"] for light in conv.scene["lights"]] == ["Linked", "Plain", "Listed"]
    linking = sorted(n for n in conv.notes if "linking" in n)
    assert len(linking) == 2 and all(n.startswith("/World/Linked: ") for n in linking), linking
    assert "light linking collection (lightLink)" in linking[0]
    assert "shadow linking collection (shadowLink)" in linking[1]


def test_a_relative_ies_property_resolves_against_the_layer_that_wrote_it(tmp_path: Path) -> None:
    """``tyndall:ies:file`` authored in a referenced asset names a file beside that asset,
    not beside the shot that references it (a stray profile of the same name beside the
    shot must not be picked up)."""
    (tmp_path / "assets").mkdir()
    (tmp_path / "shot").mkdir()
    (tmp_path / "assets" / "beam.ies").write_text("IESNA:LM-63-2002\nTILT=NONE\n")
    (tmp_path / "shot" / "beam.ies").write_text("IESNA:LM-63-2002\nTILT=NONE\n")
    asset = Usd.Stage.CreateNew(str(tmp_path / "assets" / "lamp.usda"))
    lamp = UsdLux.SphereLight.Define(asset, "/Lamp")
    lamp.GetPrim().CreateAttribute("tyndall:ies:file", Sdf.ValueTypeNames.String).Set("beam.ies")
    asset.SetDefaultPrim(lamp.GetPrim())
    asset.Save()
    shot = _stage(tmp_path / "shot")
    shot.DefinePrim("/World/Lamp").GetReferences().AddReference("../assets/lamp.usda")
    shot.Save()
    conv = convert_stage(str(tmp_path / "shot" / "s.usda"))
    assert conv.scene["lights"][0]["ies"]["file"] == str((tmp_path / "assets" / "beam.ies").resolve())


def _fov_deg(camera: dict[str, Any]) -> tuple[float, float]:
    """Horizontal and vertical field of view of a converted camera, in degrees."""
    w, h = camera["resolution"]
    fit = camera["sensor_fit"]
    side = camera["sensor_width_mm"] if fit == "horizontal" else camera["sensor_height_mm"]
    half = side / 2 / camera["focal_length_mm"]
    hx, hy = (half, half * h / w) if fit == "horizontal" else (half * w / h, half)
    return 2 * math.degrees(math.atan(hx)), 2 * math.degrees(math.atan(hy))


def test_render_settings_conform_policy_and_products_are_honoured(tmp_path: Path) -> None:
    """UsdRender's aspectRatioConformPolicy decides which side of the aperture is kept
    (the camera's aperture is 0.36 × 0.2025 units, the image 400 × 100 px); a RenderProduct's
    own camera and resolution override the settings'; non-square pixels are an error naming
    the attribute."""
    h_deg = 2 * math.degrees(math.atan(0.36 / 2 / 0.5))
    v_deg = 2 * math.degrees(math.atan(0.2025 / 2 / 0.5))
    expected = {
        "expandAperture": (2 * math.degrees(math.atan(0.2025 * 2 / 0.5)), v_deg),
        "cropAperture": (h_deg, 2 * math.degrees(math.atan(0.36 / 8 / 0.5))),
        "adjustApertureHeight": (h_deg, 2 * math.degrees(math.atan(0.36 / 8 / 0.5))),
        "adjustApertureWidth": (2 * math.degrees(math.atan(0.2025 * 2 / 0.5)), v_deg),
    }
    for policy, (hx, vy) in expected.items():
        stage = _stage(tmp_path, name=f"{policy}.usda")
        rs = UsdRender.Settings.Define(stage, "/Render/Settings")
        rs.CreateResolutionAttr(Gf.Vec2i(400, 100))
        rs.CreateAspectRatioConformPolicyAttr(policy)
        conv = convert_stage(stage)
        got = _fov_deg(conv.scene["camera"])
        assert got == pytest.approx((hx, vy), rel=1e-6), policy
        assert any(policy in n for n in conv.notes), policy
    # A product overrides the camera and the resolution of the settings.
    stage = _stage(tmp_path, name="product.usda")
    tele = UsdGeom.Camera.Define(stage, "/World/Tele")
    tele.CreateFocalLengthAttr(2.0)
    rs = UsdRender.Settings.Define(stage, "/Render/Settings")
    rs.CreateResolutionAttr(Gf.Vec2i(320, 240))
    rs.CreateCameraRel().SetTargets([Sdf.Path("/World/Cam")])
    product = UsdRender.Product.Define(stage, "/Render/Beauty")
    product.CreateCameraRel().SetTargets([Sdf.Path("/World/Tele")])
    product.CreateResolutionAttr(Gf.Vec2i(64, 32))
    rs.CreateProductsRel().SetTargets([product.GetPath()])
    conv = convert_stage(stage)
    assert conv.scene["camera"]["resolution"] == [64, 32]
    assert conv.scene["camera"]["focal_length_mm"] == pytest.approx(200.0)  # 2 tenths of a unit
    stage = _stage(tmp_path, name="pixels.usda")
    UsdRender.Settings.Define(stage, "/Render/Settings").CreatePixelAspectRatioAttr(2.0)
    with pytest.raises(UsdSceneError) as err:
        convert_stage(stage)
    assert (err.value.prim, err.value.attribute) == ("/Render/Settings", "pixelAspectRatio")


def test_a_hidden_camera_can_still_be_rendered_through(tmp_path: Path) -> None:
    """Visibility hides a camera's gizmo, not its view: the only camera, under a hidden
    group, is used; a chosen hidden camera is not listed as skipped; without a choice, a
    visible camera wins over a hidden one."""
    stage = _stage(tmp_path)
    UsdGeom.Imageable(stage.GetPrimAtPath("/World/Cam")).MakeInvisible()
    conv = convert_stage(stage)
    assert conv.scene["camera"]["position"] == [0.0, -10.0, 2.0] and conv.skipped == []
    rig = UsdGeom.Xform.Define(stage, "/World/Rig")
    rig.MakeInvisible()
    other = UsdGeom.Camera.Define(stage, "/World/Rig/Other")
    UsdGeom.XformCommonAPI(other).SetTranslate(Gf.Vec3d(5, -10, 2))
    UsdGeom.Imageable(stage.GetPrimAtPath("/World/Cam")).MakeVisible()
    conv = convert_stage(stage)
    assert conv.scene["camera"]["position"] == [0.0, -10.0, 2.0]
    assert [d["prim"] for d in conv.skipped] == ["/World/Rig/Other"]
    UsdRender.Settings.Define(stage, "/Render/Settings").CreateCameraRel().SetTargets([other.GetPath()])
    conv = convert_stage(stage)
    assert conv.scene["camera"]["position"] == [5.0, -10.0, 2.0]
    assert [d["prim"] for d in conv.skipped] == ["/World/Cam"]


def test_values_of_the_wrong_type_are_named(tmp_path: Path) -> None:
    """A string where numbers belong (each character was once read as a number, or a bare
    ValueError escaped) or a number where names belong is an error naming the attribute."""
    cases = [
        ("/World/Haze", "tyndall:medium:scattering", Sdf.ValueTypeNames.String, "0.05"),
        ("/World/Haze", "tyndall:medium:scattering", Sdf.ValueTypeNames.String, "5"),
        ("/World/Lamp", "inputs:color", Sdf.ValueTypeNames.String, "1 0 0"),
        ("/World/Settings", "tyndall:output:layers", Sdf.ValueTypeNames.Int, 1),
    ]
    for k, (prim, attribute, type_name, value) in enumerate(cases):
        stage = _stage(tmp_path, name=f"types{k}.usda")
        haze = stage.DefinePrim("/World/Haze")
        haze.CreateAttribute("tyndall:medium:type", Sdf.ValueTypeNames.String).Set("homogeneous")
        haze.CreateAttribute("tyndall:medium:scattering", Sdf.ValueTypeNames.Double).Set(0.05)
        UsdLux.SphereLight.Define(stage, "/World/Lamp")
        stage.GetPrimAtPath(prim) or stage.DefinePrim(prim)
        # (Through Sdf: a schema's attribute keeps its declared type in Usd's API, but a
        # layer may hold any, as a hand-written .usda does.)
        spec = stage.GetRootLayer().GetPrimAtPath(prim)
        if attribute in spec.attributes:
            spec.RemoveProperty(spec.attributes[attribute])
        Sdf.AttributeSpec(spec, attribute, type_name).default = value
        with pytest.raises(UsdSceneError) as err:
            convert_stage(stage)
        assert (err.value.prim, err.value.attribute) == (prim, attribute), (value, str(err.value))


def test_light_inputs_connected_to_a_node_graph_take_its_values(tmp_path: Path) -> None:
    """A light's ``inputs:intensity`` and ``inputs:color`` connected to a NodeGraph's
    interface take its values (UsdShade's value-producing attributes, as UsdImaging reads
    them); a connection to a shader's output, which only a renderer can evaluate, is an
    error naming the input."""
    from pxr import UsdShade

    stage = _stage(tmp_path)
    rig = UsdShade.NodeGraph.Define(stage, "/World/Rig")
    level = rig.CreateInput("level", Sdf.ValueTypeNames.Float)
    level.Set(50.0)
    tint = rig.CreateInput("tint", Sdf.ValueTypeNames.Color3f)
    tint.Set(Gf.Vec3f(1.0, 0.25, 0.125))
    lamp = UsdLux.SphereLight.Define(stage, "/World/Lamp")
    UsdShade.Input(lamp.CreateIntensityAttr()).ConnectToSource(level)
    UsdShade.Input(lamp.CreateColorAttr()).ConnectToSource(tint)
    cone = rig.CreateInput("cone", Sdf.ValueTypeNames.Float)
    cone.Set(20.0)
    shaping = UsdLux.ShapingAPI.Apply(lamp.GetPrim())
    UsdShade.Input(shaping.CreateShapingConeAngleAttr()).ConnectToSource(cone)
    light = convert_stage(stage).scene["lights"][0]
    assert light["power_w"] == pytest.approx(50.0 * math.pi * 4.0 * math.pi * 0.25)  # normalize off, r = 0.5
    assert light["color"] == [1.0, 0.25, 0.125]
    assert (light["type"], light["spot_size_deg"]) == ("spot", 40.0)  # a connected cone counts as authored
    shader = UsdShade.Shader.Define(stage, "/World/Rig/Noise")
    UsdShade.Input(lamp.GetIntensityAttr()).ConnectToSource(shader.CreateOutput("out", Sdf.ValueTypeNames.Float))
    with pytest.raises(UsdSceneError) as err:
        convert_stage(stage)
    assert (err.value.prim, err.value.attribute) == ("/World/Lamp", "inputs:intensity")


def test_shaping_inputs_at_the_edges_of_usdlux(tmp_path: Path) -> None:
    """Shaping authored without the ShapingAPI schema is read (with a note), a negative
    focus is ignored as UsdLux says, and a cone over 180° excludes nothing."""
    stage = _stage(tmp_path)
    bare = UsdLux.SphereLight.Define(stage, "/World/Bare")
    bare.GetPrim().CreateAttribute("inputs:shaping:cone:angle", Sdf.ValueTypeNames.Float).Set(20.0)
    unfocused = UsdLux.SphereLight.Define(stage, "/World/Unfocused")
    api = UsdLux.ShapingAPI.Apply(unfocused.GetPrim())
    api.CreateShapingConeAngleAttr(40.0)
    api.CreateShapingFocusAttr(-1.0)
    wide = UsdLux.SphereLight.Define(stage, "/World/Wide")
    UsdLux.ShapingAPI.Apply(wide.GetPrim()).CreateShapingConeAngleAttr(200.0)
    conv = convert_stage(stage)
    by_name = {light["name"]: light for light in conv.scene["lights"]}
    assert (by_name["Bare"]["type"], by_name["Bare"]["spot_size_deg"]) == ("spot", 40.0)
    assert (by_name["Unfocused"]["type"], by_name["Unfocused"]["spot_size_deg"]) == ("spot", 80.0)
    assert by_name["Wide"]["distribution"]["cone_angle_deg"] == 180.0
    assert any(n.startswith("/World/Bare: inputs:shaping:cone:angle read although") for n in conv.notes)
    assert any(n.startswith("/World/Unfocused: inputs:shaping:focus = -1") for n in conv.notes)


def test_an_invisible_medium_is_left_out(tmp_path: Path) -> None:
    """A medium prim under a hidden group is listed as skipped, not rendered."""
    stage = _stage(tmp_path)
    UsdGeom.Scope.Define(stage, "/World/FX").MakeInvisible()
    fog = stage.DefinePrim("/World/FX/Fog")
    fog.CreateAttribute("tyndall:medium:type", Sdf.ValueTypeNames.String).Set("homogeneous")
    fog.CreateAttribute("tyndall:medium:scattering", Sdf.ValueTypeNames.Double).Set(0.05)
    conv = convert_stage(stage)
    assert conv.scene["media"] == []
    assert conv.skipped == [{"prim": "/World/FX/Fog", "reason": "invisible medium"}]
