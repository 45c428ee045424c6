"""Build a small scene in Blender (bpy), export it with Blender's own USD exporter, and write
the bpy values the converter must reproduce.

Run with a Python that has bpy (5.0.1):
    python blender_export.py OUT.usda OUT.json
tests/data/usd/blender_scene.usda and blender_scene.json were made with it (bpy 5.0.1).
"""

from __future__ import annotations

import json
import math
import sys
from typing import Any

import bpy  # only ever imported by this script, in Blender's Python


def _light(name: str, kind: str, loc: tuple[float, ...], rot: tuple[float, ...], **kw: Any) -> bpy.types.Object:
    data = bpy.data.lights.new(name, kind)
    for k, v in kw.items():
        setattr(data, k, v)
    obj = bpy.data.objects.new(name, data)
    obj.location = loc
    obj.rotation_euler = rot
    bpy.context.scene.collection.objects.link(obj)
    return obj


def build() -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    _light("Point", "POINT", (1, 2, 3), (0.1, 0.2, 0.3), energy=250.0, color=(1, 0.5, 0.25), shadow_soft_size=0.2)
    _light(
        "Spot",
        "SPOT",
        (-1, 2, 5),
        (0.5, 0, 0.7),
        energy=1000.0,
        color=(0.2, 0.4, 1.0),
        shadow_soft_size=0.05,
        spot_size=math.radians(40),
        spot_blend=0.3,
    )
    # A wide spot under a rotated, translated parent (nested transforms).
    rig = bpy.data.objects.new("Rig", None)
    rig.location = (4, -3, 6)
    rig.rotation_euler = (0, math.radians(30), math.radians(-20))
    scene.collection.objects.link(rig)
    wide = _light("WideSpot", "SPOT", (0, 1, 0), (0.2, 0, 0), energy=40.0, spot_size=math.radians(150), spot_blend=0.85)
    wide.parent = rig
    _light("Sun", "SUN", (0, 0, 10), (0.6, 0.1, 0.2), energy=3.5, color=(1, 0.9, 0.8), angle=math.radians(1.5))
    _light("Area", "AREA", (0, 0, 3), (0, 0, 0), energy=50.0)

    cam = bpy.data.cameras.new("Cam")
    cam.lens = 35
    cam.sensor_width = 36
    cam.sensor_height = 24
    cam.shift_x = 0.1
    cam.shift_y = -0.05
    cam.clip_start = 0.2
    cam.clip_end = 500
    cam_obj = bpy.data.objects.new("Cam", cam)
    cam_obj.location = (0, -20, 2)
    cam_obj.rotation_euler = (math.radians(85), 0, 0.1)
    cam_obj["tyndall:output:resolution"] = [640, 360]
    cam_obj["tyndall:output:layers"] = "inscatter, transmittance, depth"
    scene.collection.objects.link(cam_obj)
    scene.camera = cam_obj
    scene.render.resolution_x = 640
    scene.render.resolution_y = 360
    scene.render.resolution_percentage = 100

    haze = bpy.data.objects.new("Haze", None)
    haze["tyndall:medium:type"] = "homogeneous"
    haze["tyndall:medium:scattering"] = 0.02
    haze["tyndall:medium:absorption"] = [0.001, 0.002, 0.003]
    haze["tyndall:medium:phase"] = "henyey_greenstein"
    haze["tyndall:medium:phaseG"] = 0.6
    scene.collection.objects.link(haze)

    bpy.ops.mesh.primitive_cube_add(size=2, location=(0, 0, 1))
    bpy.context.object.name = "Box"
    bpy.context.object.scale = (1, 2, 0.5)
    bpy.context.object.rotation_euler = (0, 0, 0.4)
    bpy.ops.mesh.primitive_plane_add(size=10, location=(0, 0, 0))
    bpy.context.object.name = "Ground"
    bpy.ops.mesh.primitive_circle_add(vertices=7, radius=1.5, fill_type="NGON", location=(3, 3, 0.5))
    bpy.context.object.name = "Disc"


def values() -> dict[str, Any]:
    scene = bpy.context.scene
    deps = bpy.context.evaluated_depsgraph_get()
    out: dict[str, Any] = {"blender": bpy.app.version_string, "lights": {}, "meshes": {}}
    for obj in scene.objects:
        mw = [list(r) for r in obj.matrix_world]
        if obj.type == "LIGHT":
            d = obj.data
            v: dict[str, Any] = {"type": d.type, "energy": d.energy, "color": list(d.color), "matrix_world": mw}
            if d.type in ("POINT", "SPOT"):
                v["radius"] = d.shadow_soft_size
            if d.type == "SPOT":
                v["spot_size_deg"] = math.degrees(d.spot_size)
                v["spot_blend"] = d.spot_blend
            if d.type == "SUN":
                v["angle_deg"] = math.degrees(d.angle)
            out["lights"][obj.name] = v
        elif obj.type == "CAMERA":
            c = obj.data
            out["camera"] = {
                "lens": c.lens,
                "sensor_width": c.sensor_width,
                "sensor_height": c.sensor_height,
                "sensor_fit": c.sensor_fit,
                "shift_x": c.shift_x,
                "shift_y": c.shift_y,
                "clip_start": c.clip_start,
                "clip_end": c.clip_end,
                "resolution": [scene.render.resolution_x, scene.render.resolution_y],
                "matrix_world": mw,
            }
        elif obj.type == "MESH":
            me = obj.evaluated_get(deps).to_mesh()
            me.calc_loop_triangles()
            out["meshes"][obj.name] = {
                "world_vertices": [list(obj.matrix_world @ vert.co) for vert in me.vertices],
                "triangles": len(me.loop_triangles),
                "area": sum(t.area for t in me.loop_triangles),
                "matrix_world": mw,
            }
    return out


def main() -> None:
    usda, js = sys.argv[-2], sys.argv[-1]
    build()
    bpy.ops.wm.usd_export(
        filepath=usda, export_lights=True, export_cameras=True, export_materials=False, export_custom_properties=True
    )
    with open(js, "w") as f:
        json.dump(values(), f, indent=1)


if __name__ == "__main__":
    main()
