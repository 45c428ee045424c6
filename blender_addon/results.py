"""Bring Tyndall results into Blender: world sky, sun lamp, light groups, compositor (main thread)."""

from __future__ import annotations

import math
import os
from typing import Any

import bpy

from .core.conversions import layer_safe_name

COMPOSITOR_GROUP = "Tyndall Composite"
LIGHTGROUP_PREFIX = "tyndall_"


def _load_image(path: str, colorspace: str | None = None) -> bpy.types.Image:
    path = os.path.abspath(path)
    for img in bpy.data.images:
        if img.filepath and os.path.abspath(bpy.path.abspath(img.filepath)) == path:
            img.reload()
            return img
    img = bpy.data.images.load(path, check_existing=False)
    if colorspace:
        try:
            img.colorspace_settings.name = colorspace
        except TypeError:
            pass
    return img


def apply_sky(
    scene: bpy.types.Scene, sky_exr: str, report: dict[str, Any], sun: bpy.types.Object | None, update_sun: bool
) -> bpy.types.Object | None:
    """World: Environment Texture (equirectangular) → Background → World Output Surface; the Volume link is kept.

    With ``update_sun`` the sun lamp (created when there is none) gets the sky report's
    ``sun_lamp`` colour, strength (W·m⁻²), angle and rotation. Returns the sun lamp.
    """
    world = scene.world
    if world is None:
        world = bpy.data.worlds.new("World")
        scene.world = world
    if world.node_tree is None:
        world.use_nodes = True
    tree = world.node_tree
    out = next((n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputWorld" and n.is_active_output), None)
    if out is None:
        out = tree.nodes.new("ShaderNodeOutputWorld")
    env = tree.nodes.get("Tyndall Sky") or tree.nodes.new("ShaderNodeTexEnvironment")
    env.name = env.label = "Tyndall Sky"
    env.projection = "EQUIRECTANGULAR"
    env.image = _load_image(sky_exr, "Linear Rec.709")
    env.location = (out.location.x - 500, out.location.y + 200)
    bg = tree.nodes.get("Tyndall Background") or tree.nodes.new("ShaderNodeBackground")
    bg.name = bg.label = "Tyndall Background"
    bg.inputs["Strength"].default_value = 1.0
    bg.location = (out.location.x - 220, out.location.y + 200)
    tree.links.new(env.outputs["Color"], bg.inputs["Color"])
    tree.links.new(bg.outputs["Background"], out.inputs["Surface"])

    lamp = report.get("sun_lamp")
    if not update_sun or not lamp:
        return sun
    if sun is None:
        data = bpy.data.lights.new("Tyndall Sun", "SUN")
        sun = bpy.data.objects.new("Tyndall Sun", data)
        scene.collection.objects.link(sun)
    sun.data.color = tuple(float(c) for c in lamp["color"])
    sun.data.energy = float(lamp["strength_w_m2"])
    sun.data.angle = math.radians(float(lamp.get("angle_deg", math.degrees(sun.data.angle))))
    sun.rotation_mode = "XYZ"
    sun.rotation_euler = tuple(float(a) for a in lamp["rotation_euler_xyz_rad"])
    return sun


def setup_lightgroups(scene: bpy.types.Scene, light_layers: dict[str, str]) -> dict[str, str]:
    """One Cycles light group per light (``tyndall_<layer name>``); returns object name → light group."""
    view_layer = scene.view_layers[0] if scene.view_layers else None
    out = {}
    for obj_name, layer in light_layers.items():
        obj = scene.objects.get(obj_name)
        if obj is None:
            continue
        lg = LIGHTGROUP_PREFIX + layer_safe_name(layer.removeprefix("inscatter."))
        obj.lightgroup = lg
        for vl in scene.view_layers:
            if vl.lightgroups.get(lg) is None:
                vl.lightgroups.add(name=lg)
        out[obj_name] = lg
    del view_layer
    return out


def _sock(sockets: Any, identifier: str) -> bpy.types.NodeSocket:
    """A socket by identifier (``A_Color``…): ``inputs[...]`` looks sockets up by name."""
    for sck in sockets:
        if sck.identifier == identifier:
            return sck
    raise KeyError(identifier)


def _mix(tree: bpy.types.NodeTree, blend: str, label: str, loc: tuple[float, float]) -> bpy.types.Node:
    n = tree.nodes.new("ShaderNodeMix")
    n.data_type = "RGBA"
    n.blend_type = blend
    n.clamp_result = False
    n.clamp_factor = True
    _sock(n.inputs, "Factor_Float").default_value = 1.0
    n.label = label
    n.location = loc
    return n


def setup_compositor(
    scene: bpy.types.Scene, exr: str, light_layers: dict[str, str], lightgroups: dict[str, str]
) -> bpy.types.NodeTree:
    """``scene.compositing_node_group`` = render × transmittance + inscatter (from the multilayer EXR).

    Per light with a light group (Cycles), an extra group output ``<light>`` =
    ``Combined_<light group> × transmittance + inscatter.<light>``: the view transmittance
    stands in for each light's own path transmittance to the surface (an approximation:
    Tyndall does not output per-light surface transmittance layers yet).
    """
    tree = bpy.data.node_groups.get(COMPOSITOR_GROUP)
    if tree is None or tree.bl_idname != "CompositorNodeTree":
        tree = bpy.data.node_groups.new(COMPOSITOR_GROUP, "CompositorNodeTree")
    tree.nodes.clear()
    tree.interface.clear()
    tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    img = _load_image(exr)

    rl = tree.nodes.new("CompositorNodeRLayers")
    rl.scene = scene
    rl.location = (-600, 200)
    vol = tree.nodes.new("CompositorNodeImage")
    vol.image = img
    vol.label = "Tyndall volumetrics"
    vol.location = (-600, -200)
    mul = _mix(tree, "MULTIPLY", "× transmittance", (-250, 150))
    add = _mix(tree, "ADD", "+ inscatter", (0, 150))
    out = tree.nodes.new("NodeGroupOutput")
    out.location = (300, 150)
    links = tree.links
    links.new(rl.outputs["Image"], _sock(mul.inputs, "A_Color"))
    links.new(vol.outputs["transmittance"], _sock(mul.inputs, "B_Color"))
    links.new(_sock(mul.outputs, "Result_Color"), _sock(add.inputs, "A_Color"))
    links.new(vol.outputs["inscatter"], _sock(add.inputs, "B_Color"))
    links.new(_sock(add.outputs, "Result_Color"), out.inputs["Image"])

    if lightgroups:
        per = tree.nodes.new("CompositorNodeImage")
        per.image = img
        per.label = "Tyndall per-light inscatter"
        per.location = (-600, -600)
        try:
            per.layer = "inscatter"
        except TypeError:
            per = None
        y = -350.0
        for obj_name, lg in lightgroups.items():
            pass_name = light_layers[obj_name].removeprefix("inscatter.")
            src = rl.outputs.get(f"Combined_{lg}")
            if src is None or per is None or per.outputs.get(pass_name) is None:
                continue
            m = _mix(tree, "MULTIPLY", f"{obj_name} × T (approx.)", (-250, y))
            a = _mix(tree, "ADD", f"+ inscatter.{pass_name}", (0, y))
            tree.interface.new_socket(obj_name, in_out="OUTPUT", socket_type="NodeSocketColor")
            links.new(src, _sock(m.inputs, "A_Color"))
            links.new(vol.outputs["transmittance"], _sock(m.inputs, "B_Color"))
            links.new(_sock(m.outputs, "Result_Color"), _sock(a.inputs, "A_Color"))
            links.new(per.outputs[pass_name], _sock(a.inputs, "B_Color"))
            links.new(_sock(a.outputs, "Result_Color"), out.inputs[obj_name])
            y -= 250.0
    scene.compositing_node_group = tree
    scene.render.use_compositing = True
    return tree
