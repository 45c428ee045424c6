"""Read a Blender scene into the plain records of :mod:`.core.scene_build` (main thread only)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import bpy
import numpy as np

from .core import conversions as cv
from .core.scene_build import CameraData, IesData, LightData, MediumData, MeshData, SceneData, SceneInputError


def _rows(m: Any) -> list[list[float]]:
    return [[float(m[r][c]) for c in range(4)] for r in range(4)]


def _unlinked(node: bpy.types.Node, name: str, where: str) -> Any:
    sock = node.inputs.get(name)
    if sock is None:
        raise SceneInputError(f"{where}: node '{node.name}' has no input '{name}'")
    if sock.is_linked:
        raise SceneInputError(
            f"{where}: input '{name}' of node '{node.name}' is linked; Tyndall needs a constant value "
            "(textures and attributes are not supported)"
        )
    v = sock.default_value
    return tuple(v) if hasattr(v, "__len__") else float(v)


def _linked_from(
    sock: bpy.types.NodeSocket, include_muted_link: set[str] | bool | None = None
) -> bpy.types.Node | None:
    """The node feeding ``sock``, through reroutes and muted nodes: Cycles replaces a muted
    node by its internal link (a muted Add Shader passes its first shader on; a muted
    Volume Scatter or Emission, with no shader input, gives nothing). A muted link counts
    if ``include_muted_link`` is ``True`` or holds its :func:`link_key` (Tyndall muted it)."""
    for link in sock.links:
        if not link.is_valid:
            continue
        if link.is_muted and not (
            include_muted_link is True or (isinstance(include_muted_link, set) and link_key(link) in include_muted_link)
        ):
            continue
        node, out_sock = link.from_node, link.from_socket
        while node.type == "REROUTE" or node.mute:
            through = next((il for il in node.internal_links if il.to_socket == out_sock), None)
            if node.type == "REROUTE":
                through_in = node.inputs[0]
            elif through is not None:
                through_in = through.from_socket
            else:
                return None
            feeding = [lk for lk in through_in.links if lk.is_valid and not lk.is_muted]
            if not feeding:
                return None
            node, out_sock = feeding[0].from_node, feeding[0].from_socket
        return node
    return None


def _active_output(tree: bpy.types.NodeTree, idname: str) -> bpy.types.Node | None:
    """The output node Cycles renders (Blender's ``ntreeShaderOutputNode`` for the Cycles
    target): an output for Cycles before one for All, the active one among equals, else the
    first; never one for EEVEE only. ``None``: Cycles renders nothing from the tree."""
    chosen = None
    for n in tree.nodes:
        if n.bl_idname != idname:
            continue
        target = getattr(n, "target", "ALL")
        if target not in ("ALL", "CYCLES"):
            continue
        if chosen is None:
            chosen = n
            continue
        chosen_target = getattr(chosen, "target", "ALL")
        if target == "CYCLES" and chosen_target == "ALL":
            chosen = n
        elif target == chosen_target and n.is_active_output and not chosen.is_active_output:
            chosen = n
    return chosen


# -- world volume --------------------------------------------------------------

#: World (or fog material) custom property set while Tyndall has muted its Volume links:
#: the links' :func:`link_key` s, one per line (``True`` in files from before it named them).
MUTED_VOLUME_PROP = "tyndall_muted_volume"


def link_key(link: bpy.types.NodeLink) -> str:
    """A node link named by its ends (links have no names of their own)."""
    return f"{link.from_node.name}:{link.from_socket.identifier}>{link.to_node.name}:{link.to_socket.identifier}"


def muted_by_tyndall(owner: bpy.types.ID) -> set[str] | bool | None:
    """The keys of the Volume links Tyndall muted on ``owner`` (``True``: all of them, an
    older marker), or ``None``."""
    v = owner.get(MUTED_VOLUME_PROP)
    if v is None or v is False or v == "":
        return None
    if isinstance(v, str):
        return set(v.split("\n"))
    return True


def _volume_nodes(node: bpy.types.Node, where: str, out: list[bpy.types.Node]) -> None:
    if node.bl_idname == "ShaderNodeAddShader":
        for sock in node.inputs:
            child = _linked_from(sock)
            if child is not None:
                _volume_nodes(child, where, out)
        return
    if node.bl_idname in ("ShaderNodeVolumeScatter", "ShaderNodeVolumeAbsorption", "ShaderNodeVolumePrincipled"):
        out.append(node)
        return
    raise SceneInputError(
        f"{where}: node '{node.name}' ({node.bl_label}) is not supported; use Volume Scatter, Volume Absorption "
        "or Principled Volume (optionally combined with Add Shader)"
    )


def gather_world_medium(world: bpy.types.World | None) -> list[MediumData]:
    """The World Output's Volume input as one homogeneous medium (empty list when there is none)."""
    if world is None or world.node_tree is None:
        return []
    where = f"world '{world.name}'"
    out = _active_output(world.node_tree, "ShaderNodeOutputWorld")
    if out is None:
        return []
    # A volume link muted by Tyndall's import (surface render for the composite)
    # is still the scene's haze.
    root = _linked_from(out.inputs["Volume"], include_muted_link=muted_by_tyndall(world))
    if root is None:
        return []
    return [_medium_of(root, where, "")]


def _medium_of(root: bpy.types.Node, where: str, prefix: str) -> MediumData:
    """The volume shader tree at ``root`` (Volume Scatter, Volume Absorption, Principled
    Volume, Add Shader) as one homogeneous medium named ``prefix`` + its node names."""
    nodes: list[bpy.types.Node] = []
    _volume_nodes(root, where, nodes)
    sig_s = [0.0, 0.0, 0.0]
    sig_a = [0.0, 0.0, 0.0]
    phases: list[tuple[str, dict[str, Any]]] = []
    try:
        for n in nodes:
            w = f"{where}, node '{n.name}'"
            if n.bl_idname == "ShaderNodeVolumeScatter":
                s = cv.volume_scatter_sigma_s(_unlinked(n, "Density", w), _unlinked(n, "Color", w))
                # sockets of other phases are unavailable (Mie has no Anisotropy): read only what applies
                g = _unlinked(n, "Anisotropy", w) if n.phase in ("HENYEY_GREENSTEIN", "DRAINE") else 0.0
                alpha = _unlinked(n, "Alpha", w) if n.phase == "DRAINE" else 1.0
                phase = cv.phase_from_volume_scatter(n.phase, g, alpha)
                if max(s) > 0.0:
                    phases.append((n.name, phase))
                sig_s = [a + b for a, b in zip(sig_s, s, strict=True)]
            elif n.bl_idname == "ShaderNodeVolumeAbsorption":
                a = cv.volume_absorption_sigma_a(_unlinked(n, "Density", w), _unlinked(n, "Color", w))
                sig_a = [x + y for x, y in zip(sig_a, a, strict=True)]
            else:
                if (
                    float(_unlinked(n, "Emission Strength", w)) > 0.0
                    or float(_unlinked(n, "Blackbody Intensity", w)) > 0
                ):
                    raise SceneInputError(f"{w}: volume emission is not supported by Tyndall")
                s, a = cv.principled_volume_coefficients(
                    _unlinked(n, "Density", w), _unlinked(n, "Color", w), _unlinked(n, "Absorption Color", w)
                )
                if max(s) > 0.0:
                    phases.append((n.name, cv.phase_from_principled_volume(_unlinked(n, "Anisotropy", w))))
                sig_s = [x + y for x, y in zip(sig_s, s, strict=True)]
                sig_a = [x + y for x, y in zip(sig_a, a, strict=True)]
    except cv.ConversionError as e:
        raise SceneInputError(f"{where}: node '{n.name}': {e}") from e
    distinct = {repr(p) for _n, p in phases}
    if len(distinct) > 1:
        raise SceneInputError(f"{where}: scattering nodes with different phase functions are not supported ({phases})")
    phase = phases[0][1] if phases else {"type": "isotropic"}
    name = prefix + "+".join(n.name for n in nodes)
    return MediumData(node=name, scattering=tuple(sig_s), absorption=tuple(sig_a), phase=phase)


# -- what Cycles renders ------------------------------------------------------------


#: Object types whose evaluated geometry becomes a mesh (curves and text with faces: bevelled, filled).
GEOMETRY_TYPES = ("MESH", "CURVE", "SURFACE", "META", "FONT")

#: Geometry Cycles renders (and that casts shadows) but Tyndall does not read: hair curves
#: (ribbons or tubes) and point clouds (spheres), also where Geometry Nodes make them.
UNEXPORTED_GEOMETRY = {"CURVES": "hair curves", "POINTCLOUD": "point cloud"}


def world_of(scene: bpy.types.Scene, view_layer: bpy.types.ViewLayer) -> bpy.types.World | None:
    """The world Cycles renders ``view_layer`` with: its World Override, else the scene's."""
    return getattr(view_layer, "world_override", None) or scene.world


def worlds_rendered(scene: bpy.types.Scene) -> list[bpy.types.World]:
    """The scene's world and every view layer's World Override (each once)."""
    worlds = [scene.world, *(getattr(vl, "world_override", None) for vl in scene.view_layers)]
    return list({w.name: w for w in worlds if w is not None}.values())


@dataclass
class RenderedObject:
    """An object Cycles renders: ``name`` (``instancer/member`` for an instance), the original
    object (settings, node trees), its world matrix, and for geometry its evaluated triangles
    (``(n, 3)`` positions, ``(m, 3)`` indices; ``None`` without any)."""

    name: str
    original: bpy.types.Object
    matrix: Any
    geometry: tuple[np.ndarray, np.ndarray] | None = None
    instanced: bool = False
    kind: str = ""
    """The evaluated object's type: ``POINTCLOUD`` for a mesh that Geometry Nodes turned
    into points, where the original is a ``MESH``."""
    indirect_only: bool = False
    """In a collection set to Indirect Only for the view layer: camera rays pass through it."""


def _triangles(ev: bpy.types.Object) -> tuple[np.ndarray, np.ndarray] | None:
    """An evaluated object's triangles (modifiers applied), object space."""
    try:
        me = ev.to_mesh()
    except RuntimeError:  # "Object does not have geometry data" (an empty text, a bare curve)
        return None
    try:
        me.calc_loop_triangles()
        co = np.empty(len(me.vertices) * 3, dtype=np.float64)
        me.vertices.foreach_get("co", co)
        tri = np.empty(len(me.loop_triangles) * 3, dtype=np.int64)
        me.loop_triangles.foreach_get("vertices", tri)
        return co.reshape(-1, 3), tri.reshape(-1, 3)
    finally:
        ev.to_mesh_clear()


def _collect(depsgraph: bpy.types.Depsgraph) -> list[RenderedObject]:
    """The objects and instances of a render-mode depsgraph that Cycles draws (``show_self``)."""
    out: list[RenderedObject] = []
    view_layer = depsgraph.view_layer
    for inst in depsgraph.object_instances:
        if not inst.show_self:
            continue  # an emitter with Show Instancer for Render off, a hidden instancer
        # An instance's evaluated object lives only during this step of the iteration:
        # its matrix and triangles are copied now.
        ev = inst.object
        obj = ev.original
        if obj.type not in (*GEOMETRY_TYPES, *UNEXPORTED_GEOMETRY, "LIGHT", "VOLUME"):
            continue
        if inst.is_instance:
            if inst.parent is None:
                continue
            if inst.parent.original == obj and obj.type != "MESH":
                continue  # a curve's or text's own surface, listed again as a mesh instance of itself
            name = f"{inst.parent.original.name}/{obj.name}"
        else:
            name = obj.name
        geometry = _triangles(ev) if obj.type in GEOMETRY_TYPES and ev.type in GEOMETRY_TYPES else None
        # (An instance's own object may lie outside the view layer: its instancer decides.)
        holder = inst.parent.original if inst.is_instance and inst.parent is not None else obj
        try:
            indirect = bool(holder.indirect_only_get(view_layer=view_layer))
        except RuntimeError:  # (not in the view layer's collections: no such flag)
            indirect = False
        out.append(
            RenderedObject(name, obj, inst.matrix_world.copy(), geometry, inst.is_instance, ev.type, indirect)
        )
    return out


#: The Render Result slot the scene-reading render goes into (created once, then reused).
GATHER_SLOT = "Tyndall (reading the scene)"


def rendered_objects(
    scene: bpy.types.Scene, view_layer: bpy.types.ViewLayer, camera_matrix: list[Any] | None = None
) -> list[RenderedObject]:
    """The objects and instances (collection, particle, geometry-node, vertex instances) that
    Cycles renders in ``view_layer``, evaluated as for a render: render visibility of objects
    and collections, modifiers at their render settings.

    Blender evaluates a scene for rendering only inside a render, so a render engine that draws
    nothing is registered for the moment and run (without compositing or sequencer); the
    scene's settings are restored afterwards. An instance's name is
    ``<instancer>/<object>``, numbered from the second on (``Emitter/Lamp 2``). The scene
    camera's evaluated world matrix is appended to ``camera_matrix`` when one is given.
    """
    found: list[RenderedObject] = []

    class GatherEngine(bpy.types.RenderEngine):
        bl_idname = "TYNDALL_GATHER"
        bl_label = "Tyndall (reading the scene)"

        def render(self, depsgraph: bpy.types.Depsgraph) -> None:
            found.extend(_collect(depsgraph))
            if camera_matrix is not None and depsgraph.scene.camera is not None:
                # The camera as the render evaluates it (render-only modifiers of what it is
                # parented to, drivers, a move made just before in a script).
                camera_matrix.append(depsgraph.scene.camera.evaluated_get(depsgraph).matrix_world.copy())
            # An empty result in the engine's own slot (bpy 5.0's RenderEngine has no size_x:
            # reading it raised, and Blender printed a Python error at every export).
            rs = depsgraph.scene.render
            pct = rs.resolution_percentage / 100.0
            result = self.begin_result(0, 0, max(1, int(rs.resolution_x * pct)), max(1, int(rs.resolution_y * pct)))
            self.end_result(result)

    r = scene.render
    saved = (r.engine, r.use_compositing, r.use_sequencer)
    result = bpy.data.images.get("Render Result")
    slots = result.render_slots if result is not None and result.type == "RENDER_RESULT" else None
    active_slot = slots.active_index if slots is not None else 0
    stand_in = None
    bpy.utils.register_class(GatherEngine)
    try:
        # Blender renders only through a camera: a scene without one (a stage just imported)
        # gets one for the moment.
        if scene.camera is None:
            stand_in = bpy.data.objects.new("Tyndall stand-in camera", bpy.data.cameras.new("Tyndall stand-in camera"))
            scene.collection.objects.link(stand_in)
            scene.camera = stand_in
        # The user's last render stays in its Render Result slot: this one goes into its own.
        if slots is not None:
            own = next((i for i, slot in enumerate(slots) if slot.name == GATHER_SLOT), None)
            if own is None:
                slots.new(name=GATHER_SLOT)
                own = len(slots) - 1
            slots.active_index = own
        r.engine, r.use_compositing, r.use_sequencer = GatherEngine.bl_idname, False, False
        bpy.ops.render.render(scene=scene.name, layer=view_layer.name)
    finally:
        if slots is not None:
            slots.active_index = active_slot
        r.engine, r.use_compositing, r.use_sequencer = saved
        bpy.utils.unregister_class(GatherEngine)
        if stand_in is not None:
            cam_data = stand_in.data
            bpy.data.objects.remove(stand_in)
            bpy.data.cameras.remove(cam_data)
    seen: dict[str, int] = {}
    for ro in found:
        n = seen[ro.name] = seen.get(ro.name, 0) + 1
        if n > 1:
            ro.name = f"{ro.name} {n}"
    return found


# -- lights --------------------------------------------------------------------


def _light_nodes(obj: bpy.types.Object, light: bpy.types.Light) -> tuple[IesData | None, float, tuple[float, ...]]:
    """(IES, strength factor, colour factor) from a light's node tree (Emission [+ IES Texture])."""
    tree = light.node_tree
    if tree is None or not getattr(light, "use_nodes", True):
        return None, 1.0, (1.0, 1.0, 1.0)
    where = f"light '{obj.name}'"
    out = _active_output(tree, "ShaderNodeOutputLight")
    if out is None:
        return None, 0.0, (1.0, 1.0, 1.0)  # a node tree without a Light Output: Cycles' lamp is dark
    em = _linked_from(out.inputs["Surface"])
    if em is None:
        return None, 0.0, (1.0, 1.0, 1.0)
    if em.bl_idname != "ShaderNodeEmission":
        raise SceneInputError(f"{where}: light node '{em.name}' is not supported (use Emission, optionally with IES)")
    color = _unlinked(em, "Color", where)
    ies_node = _linked_from(em.inputs["Strength"])
    if ies_node is None:
        return None, float(_unlinked(em, "Strength", where)), color
    if ies_node.bl_idname != "ShaderNodeTexIES":
        raise SceneInputError(
            f"{where}: Emission Strength is driven by '{ies_node.name}'; only an IES Texture node is supported there"
        )
    strength = float(_unlinked(ies_node, "Strength", where))
    if ies_node.inputs["Vector"].is_linked:
        raise SceneInputError(f"{where}: IES node '{ies_node.name}' has a linked Vector input (not supported)")
    if ies_node.mode == "EXTERNAL":
        path = bpy.path.abspath(ies_node.filepath) if ies_node.filepath else ""
        ies = IesData(node=ies_node.name, mode="EXTERNAL", filepath=path, strength=strength)
    else:
        text = ies_node.ies
        ies = IesData(
            node=ies_node.name,
            mode="INTERNAL",
            text=text.as_string() if text is not None else None,
            text_name=text.name if text is not None else "",
            strength=strength,
        )
    return ies, 1.0, color


def _ies_property(obj: bpy.types.Object, light: bpy.types.Light) -> IesData | None:
    """``tyndall:ies:file`` / ``strength`` on the light data: the IES profile of a light that came
    from a USD stage (Blender's importer keeps the attribute as a custom property, not as a node)."""
    path = light.get("tyndall:ies:file")
    if not path:
        return None
    strength = light.get("tyndall:ies:strength", 1.0)
    return IesData(
        node=f"{obj.name} custom property tyndall:ies:file",
        mode="EXTERNAL",
        filepath=bpy.path.abspath(str(path)),
        strength=float(strength),
    )


def _links_include(collection: bpy.types.Collection | None) -> bool:
    """Whether a light-linking collection has an entry (object or child collection) set to Include."""
    if collection is None:
        return False
    entries = list(collection.collection_objects) + list(collection.collection_children)
    return any(e.light_linking.link_state == "INCLUDE" for e in entries)


def panel_light_count(scene: bpy.types.Scene, view_layer: bpy.types.ViewLayer, include_sun: bool) -> tuple[int, int]:
    """For the sidebar, without the render :func:`rendered_objects` needs: ``(exported,
    left_out)`` among the lamp objects a render of ``view_layer`` shows. A lamp is shown when
    it and every collection on some path to it from the scene's are enabled for renders
    (Disable in Renders off, the view layer's Exclude off) and its Ray Visibility > Volume
    Scatter is on; of those, area lamps are left out, and so are sun lamps that cast shadows
    unless ``include_sun`` (as :func:`~.core.scene_build.build_scene` does). Instanced lamps
    (particles, collection instances, geometry nodes) are not counted here."""
    shown: set[str] = set()

    def walk(layer: bpy.types.LayerCollection) -> None:
        if layer.exclude or layer.collection.hide_render:
            return
        shown.update(obj.name for obj in layer.collection.objects)
        for child in layer.children:
            walk(child)

    walk(view_layer.layer_collection)
    lights = [
        obj
        for obj in scene.objects
        if obj.type == "LIGHT" and obj.name in shown and not obj.hide_render and obj.visible_volume_scatter
    ]

    def exported(light: bpy.types.Light) -> bool:
        if light.type == "SUN":
            return include_sun or not light.use_shadow
        return light.type in ("POINT", "SPOT")

    n = sum(1 for obj in lights if exported(obj.data))
    return n, len(lights) - n


def gather_lights(objects: list[RenderedObject], notes: list[str]) -> list[LightData]:
    """The lights among the objects Cycles renders (:func:`rendered_objects`)."""
    out = []
    for ro in objects:
        obj = ro.original
        if obj.type != "LIGHT":
            continue
        if not obj.visible_volume_scatter:
            notes.append(f"{ro.name}: Ray Visibility > Volume Scatter is off, so it lights no haze in Cycles; left out")
            continue
        linking = getattr(obj, "light_linking", None)
        if linking is not None and _links_include(linking.receiver_collection):
            # Measured (Cycles 5.0.1): a receiver collection with an Include entry lights only
            # those; the world volume is not among them (an image of 0). Only Exclude entries:
            # the world is lit as without linking.
            notes.append(
                f"{ro.name}: Light Linking > Receiver Collection includes only some objects, so it lights no "
                "world haze in Cycles; left out"
            )
            continue
        if linking is not None and linking.blocker_collection is not None:
            notes.append(
                f"{ro.name}: Shadow Linking (Blocker Collection) is not reproduced: in Tyndall every mesh that "
                "casts shadows shadows it"
            )
        light = obj.data
        color = tuple(light.color)
        if getattr(light, "use_temperature", False):
            color = tuple(c * t for c, t in zip(color, light.temperature_color, strict=True))
        ies, k, node_color = (None, 1.0, (1.0, 1.0, 1.0))
        if light.type in ("POINT", "SPOT"):
            ies, k, node_color = _light_nodes(obj, light)
            if ies is None:
                ies = _ies_property(obj, light)
        color = tuple(c * n for c, n in zip(color, node_color[:3], strict=True))
        radius = float(getattr(light, "shadow_soft_size", 0.0))
        if light.type in ("POINT", "SPOT") and radius > 0.0:
            shape = "a disk facing each point it lights" if getattr(light, "use_soft_falloff", True) else "a sphere"
            notes.append(
                f"{ro.name}: Radius {radius:.4g} — Cycles renders {shape}, with soft shadow and beam edges; Tyndall "
                "treats it as a point (rays closer than the radius evaluated at it): the haze near the lamp and "
                "at shadow and beam edges differs (spot and box at 0.1 m: 3 % RMSE away from the lamp, 10 % with "
                "it); Radius 0 matches"
            )
        out.append(
            LightData(
                name=ro.name,
                kind=light.type,
                matrix=_rows(ro.matrix),
                color=(color[0], color[1], color[2]),
                energy=float(light.energy) * k,
                exposure=float(getattr(light, "exposure", 0.0)),
                radius=radius,
                spot_size=float(getattr(light, "spot_size", 0.785398)),
                spot_blend=float(getattr(light, "spot_blend", 0.15)),
                sun_angle=float(getattr(light, "angle", 0.00918)),
                normalize=bool(getattr(light, "normalize", True)),
                cast_shadow=bool(getattr(light, "use_shadow", True)),
                ies=ies,
                source=obj.name,
                instanced=ro.instanced,
            )
        )
    return out


# -- camera, meshes -------------------------------------------------------------


def gather_camera(scene: bpy.types.Scene, resolution_scale: float = 1.0) -> CameraData | None:
    """The active camera with the render resolution (× percentage × ``resolution_scale``) and pixel filter."""
    cam = scene.camera
    if cam is None:
        return None
    if cam.type != "CAMERA":
        raise SceneInputError(
            f"the scene camera '{cam.name}' is an object of type {cam.type}, not a camera: make a camera active"
        )
    r = scene.render
    w, h = cv.render_resolution(r.resolution_x, r.resolution_y, r.resolution_percentage, resolution_scale)
    cycles = getattr(scene, "cycles", None)
    data = cam.data
    filter_type = getattr(cycles, "pixel_filter_type", "BLACKMAN_HARRIS") if cycles else "BLACKMAN_HARRIS"
    # Cycles' own filter width (a Box filter is always 1 px wide); `render.filter_size` is EEVEE's.
    filter_width = float(getattr(cycles, "filter_width", 1.5)) if cycles else 1.5
    if filter_type == "BOX":
        filter_width = 1.0
    return CameraData(
        name=cam.name,
        matrix=_rows(cam.matrix_world),
        lens_mm=float(data.lens),
        sensor_width_mm=float(data.sensor_width),
        sensor_height_mm=float(data.sensor_height),
        sensor_fit=data.sensor_fit,
        shift_x=float(data.shift_x),
        shift_y=float(data.shift_y),
        clip_start=float(data.clip_start),
        clip_end=float(data.clip_end),
        resolution=(w, h),
        cam_type=data.type,
        filter_type=filter_type,
        filter_size_px=filter_width,
        pixel_aspect=(float(r.pixel_aspect_x), float(r.pixel_aspect_y)),
        render_region=("crop" if r.use_crop_to_border else "region") if r.use_border else "",
    )


def camera_dof(scene: bpy.types.Scene) -> bool:
    """Whether the scene camera renders with depth of field (Cycles: Depth of Field on, F-stop finite)."""
    cam = scene.camera
    dof = getattr(getattr(cam, "data", None), "dof", None)
    return bool(dof is not None and dof.use_dof)


def _volume_root(material: bpy.types.Material) -> bpy.types.Node | None:
    """The node feeding the Volume of ``material``'s Material Output; a link Tyndall muted
    for the composite's surface render still counts."""
    if not material.use_nodes or material.node_tree is None:
        return None
    out = _active_output(material.node_tree, "ShaderNodeOutputMaterial")
    if out is None:
        return None
    return _linked_from(out.inputs["Volume"], include_muted_link=muted_by_tyndall(material))


def _volume_only(material: bpy.types.Material | None) -> bool:
    """Whether ``material`` feeds only the Volume of its Material Output (a fog box: no surface)."""
    if material is None or not material.use_nodes or material.node_tree is None:
        return False
    out = _active_output(material.node_tree, "ShaderNodeOutputMaterial")
    return out is not None and _linked_from(out.inputs["Surface"]) is None and _volume_root(material) is not None


def _axis_aligned_box(world: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``(min, max)`` when the triangles (world vertices) close an axis-aligned box: every
    vertex at one of its 8 corners, all 8 used, and each of the 6 faces covered by the
    triangles lying in it (their areas sum to the face's); else ``None``."""
    if len(world) == 0 or not np.isfinite(world).all():
        return None
    lo, hi = world.min(axis=0), world.max(axis=0)
    size = hi - lo
    if not (size > 0.0).all():
        return None
    tol = 1e-6 * float(size.max())
    at_lo, at_hi = np.abs(world - lo) <= tol, np.abs(world - hi) <= tol
    if not (at_lo | at_hi).all():
        return None
    corners = {tuple(row) for row in at_hi.astype(int)}
    if len(corners) != 8:
        return None
    t = world[np.asarray(triangles, dtype=np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        face = float(size[u] * size[v])
        for side in (lo[axis], hi[axis]):
            on = (np.abs(t[:, :, axis] - side) <= tol).all(axis=1)
            if abs(float(area[on].sum()) - face) > 1e-6 * face:
                return None
    return lo, hi


def _turned_box(
    local: np.ndarray, triangles: np.ndarray, m: np.ndarray
) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float, float]] | None:
    """``(min, max, rotation_wxyz)`` of Tyndall's turned box when the mesh is an axis-aligned box
    in its own coordinates (``local``) and the object's matrix ``m`` turns and scales it without
    shear: the box about its world centre; else ``None``."""
    box = _axis_aligned_box(local, triangles)
    if box is None:
        return None
    try:
        frame = cv.frame_from_rows(m[:3, :3].tolist())
    except cv.ConversionError:
        return None
    # A parent's non-uniform scale shears a turned child: no box then. (float32 matrices are
    # perpendicular to ≈ 1e-5°.)
    if frame.shear_deg > 1e-3:
        return None
    lengths = np.asarray(frame.scale)
    axes = m[:3, :3] / lengths  # unit columns
    if frame.mirrored:
        axes[:, 0] = -axes[:, 0]  # a mirrored box is the same box
    lo, hi = box
    centre = m[:3, :3] @ (0.5 * (lo + hi)) + m[:3, 3]
    half = 0.5 * (hi - lo) * lengths
    return centre - half, centre + half, cv.quaternion_wxyz_from_rows(axes.tolist())


def _fog_materials(
    obj: bpy.types.Object, override: bpy.types.Material | None = None
) -> list[bpy.types.Material] | None:
    """The materials of a geometry object whose every material has only a Volume output
    (a fog volume, no surface); ``None`` for anything else. With the view layer's Material
    Override, Cycles renders every object with that material instead of its own."""
    if obj.type not in GEOMETRY_TYPES:
        return None
    if override is not None:
        return [override] if _volume_only(override) else None
    materials = [slot.material for slot in obj.material_slots]
    return materials if materials and all(_volume_only(m) for m in materials) else None


def gather_fog_boxes(
    objects: list[RenderedObject], notes: list[str], override: bpy.types.Material | None = None
) -> list[MediumData]:
    """Meshes whose material has only a Volume output (fog volumes) as homogeneous media
    bounded by their box, where the mesh is a box: axis-aligned in world space, or in its own
    coordinates and turned and scaled by its object (Tyndall's bounded media are boxes); others
    are left out with a note. Cycles fills a closed mesh's inside with its material's volume,
    over the world volume's (the coefficients add)."""
    out = []
    for ro in objects:
        materials = _fog_materials(ro.original, override)
        if materials is None:
            continue
        obj = ro.original
        if len({m.name for m in materials}) != 1:
            notes.append(f"{ro.name}: a fog volume with several materials is not exported; left out")
            continue
        if not obj.visible_camera:
            notes.append(f"{ro.name}: a fog volume with Ray Visibility > Camera off is not exported; left out")
            continue
        box, turn = None, None
        if ro.geometry is not None:
            positions, triangles = ro.geometry
            m = np.asarray(_rows(ro.matrix), dtype=np.float64)
            local = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
            tris = np.asarray(triangles).reshape(-1, 3)
            box = _axis_aligned_box(local @ m[:3, :3].T + m[:3, 3], tris)
            turned = _turned_box(local, tris, m) if box is None else None
            if turned is not None:
                box, turn = turned[:2], turned[2]
        if box is None:
            notes.append(
                f"{ro.name}: a fog volume that is not a box (Tyndall's bounded media are boxes: a box mesh, "
                "turned and scaled by its object, not sheared by a parent's scale); left out"
            )
            continue
        material = materials[0]
        root = _volume_root(material)
        if root is None:
            continue
        try:
            medium = _medium_of(root, f"fog volume '{ro.name}', material '{material.name}'", f"{ro.name}: ")
        except SceneInputError as e:
            # (A textured density, say: the fog mesh was left out before boxes were read, so
            # the export goes on without it rather than stopping.)
            notes.append(f"{ro.name}: {e}; left out")
            continue
        medium.material = material.name
        lo, hi = box
        medium.bounds = (
            (float(lo[0]), float(lo[1]), float(lo[2])),
            (float(hi[0]), float(hi[1]), float(hi[2])),
        )
        medium.rotation = turn
        medium.source = obj.name
        out.append(medium)
    return out


def gather_meshes(
    objects: list[RenderedObject], notes: list[str], override: bpy.types.Material | None = None
) -> list[MeshData]:
    """The surfaces among the objects Cycles renders (:func:`rendered_objects`), evaluated
    (modifiers applied, instances placed), as occluders. Fog volumes (a material with only a
    Volume output) are not surfaces: :func:`gather_fog_boxes` takes them."""
    out = []
    for ro in objects:
        obj = ro.original
        if obj.type not in GEOMETRY_TYPES or _fog_materials(obj, override) is not None:
            continue
        # An object in an Indirect Only collection is not seen by camera rays (Cycles).
        camera = bool(obj.visible_camera) and not ro.indirect_only
        if not camera and not obj.visible_shadow:
            why = (
                "in an Indirect Only collection and Ray Visibility > Shadow is off"
                if ro.indirect_only and obj.visible_camera
                else "Ray Visibility > Camera and Shadow are off"
            )
            notes.append(f"{ro.name}: {why}; left out")
            continue
        if ro.geometry is not None:
            positions, triangles = ro.geometry
            out.append(
                MeshData(
                    name=ro.name,
                    positions=positions,
                    triangles=triangles,
                    matrix=_rows(ro.matrix),
                    camera=camera,
                    shadow=bool(obj.visible_shadow),
                )
            )
    return out


def gather_scene(scene: bpy.types.Scene, view_layer: bpy.types.ViewLayer) -> SceneData:
    """Everything Tyndall needs from ``scene`` as rendered in ``view_layer`` (raises :class:`SceneInputError`)."""
    st = scene.tyndall
    camera = gather_camera(scene, st.resolution_scale)
    # Blender renders nothing without a camera: then the build reports the missing camera.
    evaluated_camera: list[Any] = []
    objects = rendered_objects(scene, view_layer, evaluated_camera) if camera is not None else []
    if camera is not None and evaluated_camera:
        camera.matrix = _rows(evaluated_camera[0])
    volumes = [ro.name for ro in objects if ro.original.type == "VOLUME"]
    notes = [
        f"{name}: volume objects (OpenVDB) are not exported (only the world volume and fog boxes)" for name in volumes
    ]
    for ro in objects:
        label = UNEXPORTED_GEOMETRY.get(ro.kind) or UNEXPORTED_GEOMETRY.get(ro.original.type)
        if label is not None:
            notes.append(
                f"{ro.name}: {label} geometry is not exported (Cycles renders it: it ends view rays and casts "
                "shadows into the haze); left out"
            )
    override = getattr(view_layer, "material_override", None)
    if override is not None:
        kind = "a fog volume on every object" if _volume_only(override) else "a surface on every object"
        notes.append(
            f"View layer '{view_layer.name}': Material Override '{override.name}' ({kind}, as Cycles renders it)"
        )
    world = world_of(scene, view_layer)
    if world is not None and world != scene.world:
        notes.append(f"View layer '{view_layer.name}': World Override '{world.name}' is the world exported")
    if camera is not None and camera_dof(scene):
        notes.append(
            f"{scene.camera.name}: Depth of Field is not reproduced (Tyndall renders a pinhole camera): the haze "
            "and its shadows are sharp at every distance"
        )
    lights = gather_lights(objects, notes)
    meshes = gather_meshes(objects, notes, override)
    fog = gather_fog_boxes(objects, notes, override)
    notes = list(dict.fromkeys(notes))  # once per instanced object, not once per instance
    return SceneData(
        camera=camera,
        lights=lights,
        media=gather_world_medium(world) + fog,
        meshes=meshes,
        unit_scale=float(scene.unit_settings.scale_length),
        skipped=notes,
        tolerance=float(st.tolerance),
        threads=int(st.threads),
        include_sun=bool(st.include_sun),
    )


def sun_lamp(scene: bpy.types.Scene) -> bpy.types.Object | None:
    """The Sky panel's chosen sun lamp, else the first render-visible Sun lamp."""
    chosen = scene.tyndall.sky_sun_object
    if chosen is not None and chosen.type == "LIGHT" and chosen.data.type == "SUN":
        return chosen
    for o in scene.objects:
        if o.type == "LIGHT" and o.data.type == "SUN" and not o.hide_render:
            return o
    return None
