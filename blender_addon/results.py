"""Bring Tyndall results into Blender: world sky, sun lamp, light groups, compositor (main thread)."""

from __future__ import annotations

import hashlib
import math
import os
from typing import Any

import bpy
import mathutils

from . import gather
from .core.conversions import layer_safe_name, render_resolution

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
    scene: bpy.types.Scene,
    sky_exr: str,
    report: dict[str, Any],
    sun: bpy.types.Object | None,
    update_sun: bool,
    view_layer: bpy.types.ViewLayer | None = None,
) -> bpy.types.Object | None:
    """World: Environment Texture (equirectangular) → Background → World Output Surface; the Volume link is kept.
    The world is the one Cycles renders ``view_layer`` with (its World Override, else the scene's).

    With ``update_sun`` the sun lamp (created when there is none) gets the sky report's
    ``sun_lamp`` colour, strength (W·m⁻²), angle and rotation. Returns the sun lamp.
    """
    world = gather.world_of(scene, view_layer) if view_layer is not None else scene.world
    if world is None:
        world = bpy.data.worlds.new("World")
        scene.world = world
    if world.node_tree is None:
        world.use_nodes = True
    tree = world.node_tree
    # The output Cycles renders (an output for Cycles before an active one for All).
    out = gather._active_output(tree, "ShaderNodeOutputWorld")
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
    data = sun.data
    data.color = tuple(float(c) for c in lamp["color"])
    data.energy = float(lamp["strength_w_m2"])
    data.angle = math.radians(float(lamp.get("angle_deg", math.degrees(data.angle))))
    # What Cycles multiplies the Strength and Color by must not alter the report's values.
    data.exposure = 0.0
    data.normalize = True
    data.use_temperature = False
    # The report's rotation is the sun's direction in the world: a parent's turn must not add
    # to it (the lamp keeps its place and scale).
    rotation = mathutils.Euler(tuple(float(a) for a in lamp["rotation_euler_xyz_rad"]), "XYZ").to_matrix()
    (view_layer or bpy.context.view_layer).update()  # (a move made just before in a script)
    loc, _rot, scale = sun.matrix_world.decompose()
    sun.matrix_world = mathutils.Matrix.LocRotScale(loc, rotation, scale)
    return sun


#: Blender keeps names to 63 bytes: the pass ``Combined_<light group>`` must fit.
MAX_LIGHTGROUP_BYTES = 63 - len("Combined_")


def lightgroup_name(layer: str) -> str:
    """``tyndall_<layer name>`` (ASCII, see :func:`layer_safe_name`), shortened with a hash of
    the whole name where the pass ``Combined_<group>`` would pass Blender's 63 bytes: a
    truncated pass name matched no light group, and two long names shared one."""
    full = LIGHTGROUP_PREFIX + layer_safe_name(layer.removeprefix("inscatter."))
    if len(full) <= MAX_LIGHTGROUP_BYTES:
        return full
    digest = hashlib.sha1(full.encode()).hexdigest()[:8]
    return f"{full[: MAX_LIGHTGROUP_BYTES - 9]}_{digest}"


def setup_lightgroups(
    scene: bpy.types.Scene, light_layers: dict[str, str], kept: list[str] | None = None
) -> dict[str, str]:
    """One Cycles light group per light (``tyndall_<layer name>``); returns object name → light group.

    A light already in a light group of the user's keeps it (it is named in ``kept``) and
    gets no per-light composite: its surface light is dimmed by the view transmittance.
    Light groups of ours (``tyndall_…``) that no object or world of the scene uses any more,
    such as a renamed or deleted light's, are removed from every view layer.
    """
    out = {}
    for obj_name, layer in light_layers.items():
        obj = scene.objects.get(obj_name)
        if obj is None:
            continue
        if obj.lightgroup and not obj.lightgroup.startswith(LIGHTGROUP_PREFIX):
            if kept is not None:
                kept.append(f"{obj_name} keeps its light group '{obj.lightgroup}' (no per-light composite)")
            continue
        lg = lightgroup_name(layer)
        obj.lightgroup = lg
        for vl in scene.view_layers:
            if vl.lightgroups.get(lg) is None:
                vl.lightgroups.add(name=lg)
        out[obj_name] = lg
    used = {obj.lightgroup for obj in scene.objects if obj.lightgroup}
    if scene.world is not None and scene.world.lightgroup:
        used.add(scene.world.lightgroup)
    for vl in scene.view_layers:
        stale = [g for g in vl.lightgroups if g.name.startswith(LIGHTGROUP_PREFIX) and g.name not in used]
        for g in stale:
            vl.lightgroups.remove(g)
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


def mute_world_volume(scene: bpy.types.Scene) -> bool:
    """Mute the link into the World Output's Volume input (the surface render of the composite).

    The composite adds Tyndall's in-scatter and transmittance to a render *without*
    the haze; rendering with the world volume on would count the haze twice. The link
    is muted, not removed, and the world is marked so that ``gather`` still reads the
    haze from it and :func:`unmute_world_volume` restores it. Returns whether a link
    was muted (False: no world volume).
    """
    muted = False
    for world in gather.worlds_rendered(scene):  # the scene's and the view layers' World Overrides
        muted |= _mute_volume(world, "ShaderNodeOutputWorld")
    return muted


def _mute_volume(owner: bpy.types.World | bpy.types.Material, output: str) -> bool:
    """Mute the links into the Volume input of ``owner``'s ``output`` nodes and mark ``owner``
    (``gather`` still reads a marked volume). Returns whether there were any."""
    if owner.node_tree is None:
        return False
    links = [
        link
        for node in owner.node_tree.nodes
        if node.bl_idname == output
        for link in node.inputs["Volume"].links
    ]
    # Only links the user left live: a link the user muted is not haze Cycles renders, and
    # marking it would make the next export read it as haze.
    ours = [link for link in links if not link.is_muted]
    for link in ours:
        link.is_muted = True
    if ours:
        before = gather.muted_by_tyndall(owner)  # (True: an older marker that named no links)
        keys = (before if isinstance(before, set) else set()) | {gather.link_key(link) for link in ours}
        owner[gather.MUTED_VOLUME_PROP] = "\n".join(sorted(keys))
    return bool(ours)


def unmute_world_volume(scene: bpy.types.Scene) -> bool:
    """Undo :func:`mute_world_volume` (only links Tyndall muted). Returns whether it did."""
    done = False
    for world in gather.worlds_rendered(scene):
        ours = gather.muted_by_tyndall(world)
        if world.node_tree is None or ours is None:
            continue
        for node in world.node_tree.nodes:
            if node.bl_idname == "ShaderNodeOutputWorld":
                for link in node.inputs["Volume"].links:
                    if ours is True or gather.link_key(link) in ours:
                        link.is_muted = False
        del world[gather.MUTED_VOLUME_PROP]
        done = True
    return done


def mute_fog_volumes(names: list[str]) -> list[str]:
    """Mute the Volume link of the fog boxes' materials ``names`` (exported as media) for the
    composite's surface render, as :func:`mute_world_volume` does the world's; they are marked
    so that ``gather`` still reads them. Returns the materials muted."""
    muted = []
    for name in names:
        material = bpy.data.materials.get(name)
        if material is not None and _mute_volume(material, "ShaderNodeOutputMaterial"):
            muted.append(name)
    return muted


def setup_compositor(
    scene: bpy.types.Scene,
    exr: str,
    light_layers: dict[str, str],
    lightgroups: dict[str, str],
    notes: list[str] | None = None,
    exr_size: tuple[int, int] | None = None,
) -> bpy.types.NodeTree:
    """``scene.compositing_node_group``: the surface render seen through Tyndall's haze.

    Without light groups: ``Image = render × transmittance + inscatter``.

    With one Cycles light group per Tyndall light (``Combined_<group>``) and the
    ``surface_transmittance.<light>`` layers in the EXR, each light's surface
    contribution is dimmed by its own path through the haze (light → surface →
    camera), and what no Tyndall light group holds (other lights, emission, the
    world) by the view transmittance::

        Image = (render − Σ Combined_gᵢ) × transmittance
                + Σ Combined_gᵢ × surface_transmittance.ℓᵢ + inscatter

    plus one group output per light, ``Combined_gᵢ × surface_transmittance.ℓᵢ +
    inscatter.ℓᵢ``. A light whose pass or layer is missing stays in the
    render × transmittance part. What remains approximate: a pixel's
    product of filtered layers is not the filtered product (silhouettes; the
    surface transmittance is averaged over the pixel's surface samples), and
    the render must be made without the world volume (:func:`mute_world_volume`).

    Tyndall's layers are scaled to the render's size when they were computed at another
    (the panel's Resolution Scale) and multiplied by Cycles' Film Exposure, which scales
    every pass of the render (``exr_size``: the layers' size in pixels, from the report; a
    multilayer image's own size reads 0 until its pixels are loaded). What could not be
    wired is appended to ``notes``.
    """
    tree = bpy.data.node_groups.get(COMPOSITOR_GROUP)
    if tree is None or tree.bl_idname != "CompositorNodeTree":
        tree = bpy.data.node_groups.new(COMPOSITOR_GROUP, "CompositorNodeTree")
    tree.nodes.clear()
    tree.interface.clear()
    tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    img = _load_image(exr)
    links = tree.links

    def image_node(layer: str | None, label: str, y: float) -> bpy.types.Node | None:
        n = tree.nodes.new("CompositorNodeImage")
        n.image = img
        n.label = label
        n.location = (-900, y)
        if layer is not None:
            try:
                n.layer = layer
            except TypeError:
                tree.nodes.remove(n)
                return None
        return n

    def mix(blend: str, label: str, a: bpy.types.NodeSocket, b: bpy.types.NodeSocket, x: float, y: float) -> Any:
        m = _mix(tree, blend, label, (x, y))
        links.new(a, _sock(m.inputs, "A_Color"))
        links.new(b, _sock(m.inputs, "B_Color"))
        return _sock(m.outputs, "Result_Color")

    r = scene.render
    # (Blender's own rounding of resolution × percentage, as the export computes it.)
    render_size = render_resolution(r.resolution_x, r.resolution_y, r.resolution_percentage)
    rescale = exr_size is not None and tuple(exr_size) != render_size
    cycles = getattr(scene, "cycles", None)
    exposure = float(getattr(cycles, "film_exposure", 1.0)) if cycles is not None else 1.0

    def sized(sock: bpy.types.NodeSocket) -> bpy.types.NodeSocket:
        """``sock`` stretched to the render's size (the compositor does not scale images)."""
        if not rescale:
            return sock
        n = tree.nodes.new("CompositorNodeScale")
        n.label = f"{sock.name} to the render size"
        n.location = (sock.node.location.x + 180, sock.node.location.y)
        n.inputs["Type"].default_value = "Render Size"
        n.inputs["Frame Type"].default_value = "Stretch"
        n.inputs["Extension X"].default_value = "Extend"
        n.inputs["Extension Y"].default_value = "Extend"
        links.new(sock, n.inputs["Image"])
        return n.outputs["Image"]

    def exposed(sock: bpy.types.NodeSocket, x: float, y: float) -> bpy.types.NodeSocket:
        """In-scatter × Film Exposure, as Cycles scales the render's passes."""
        if exposure == 1.0:
            return sock
        m = _mix(tree, "MULTIPLY", f"× Film Exposure {exposure:g}", (x, y))
        links.new(sock, _sock(m.inputs, "A_Color"))
        _sock(m.inputs, "B_Color").default_value = (exposure, exposure, exposure, 1.0)
        return _sock(m.outputs, "Result_Color")

    rl = tree.nodes.new("CompositorNodeRLayers")
    rl.scene = scene
    rl.location = (-900, 400)
    vol = image_node(None, "Tyndall volumetrics", 0.0)
    assert vol is not None
    if rescale:
        (notes if notes is not None else []).append(
            f"volumetrics {exr_size[0]}×{exr_size[1]} px stretched to the render's {render_size[0]}×{render_size[1]} "
            "(Resolution Scale): a preview, softer than the render"
        )
    out = tree.nodes.new("NodeGroupOutput")
    out.location = (900, 150)

    per = image_node("inscatter", "Tyndall per-light inscatter", -400.0) if lightgroups else None
    surf = image_node("surface_transmittance", "Tyndall surface transmittance", -800.0) if lightgroups else None
    rest = rl.outputs["Image"]
    through_haze = None
    y = -300.0
    unwired: list[str] = []
    for obj_name, lg in lightgroups.items():
        pass_name = light_layers[obj_name].removeprefix("inscatter.")
        src = rl.outputs.get(f"Combined_{lg}")
        if src is None or surf is None or surf.outputs.get(pass_name) is None:
            unwired.append(obj_name)
            continue
        lit = mix("MULTIPLY", f"{obj_name} × its surface transmittance", src, sized(surf.outputs[pass_name]), -500, y)
        rest = mix("SUBTRACT", f"− {obj_name}", rest, src, -500, y + 120)
        through_haze = lit if through_haze is None else mix("ADD", f"+ {obj_name}", through_haze, lit, -200, y)
        if per is not None and per.outputs.get(pass_name) is not None:
            tree.interface.new_socket(obj_name, in_out="OUTPUT", socket_type="NodeSocketColor")
            own_light = exposed(sized(per.outputs[pass_name]), 150, y)
            own = mix("ADD", f"+ inscatter.{pass_name}", lit, own_light, 300, y)
            links.new(own, out.inputs[obj_name])
        y -= 300.0
    if unwired and notes is not None:
        why = (
            f"the render engine is {r.engine}, whose Render Layers have no light-group passes"
            if r.engine != "CYCLES"
            else "no light-group pass or surface-transmittance layer for them"
        )
        notes.append(f"no per-light composite for {', '.join(unwired)} ({why}): dimmed by the view transmittance")
    image = mix("MULTIPLY", "× transmittance", rest, sized(vol.outputs["transmittance"]), -200, 300)
    if through_haze is not None:
        image = mix("ADD", "+ lights through the haze", image, through_haze, 100, 300)
    image = mix("ADD", "+ inscatter", image, exposed(sized(vol.outputs["inscatter"]), 250, 450), 400, 300)
    links.new(image, out.inputs["Image"])
    scene.compositing_node_group = tree
    scene.render.use_compositing = True
    return tree
