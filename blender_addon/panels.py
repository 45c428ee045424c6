"""Sidebar tab "Tyndall" in the 3D viewport."""

from __future__ import annotations

import bpy

from . import gather
from .core import conversions as cv
from .core.scene_build import SceneInputError
from .operators import RUNNING


class _TyndallPanel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Tyndall"


def _world_summary(scene: bpy.types.Scene, view_layer: bpy.types.ViewLayer) -> str:
    try:
        media = gather.gather_world_medium(gather.world_of(scene, view_layer))
    except SceneInputError as e:
        return f"Error: {e}"
    if not media:
        return "No world volume"
    m = media[0]
    s = ", ".join(f"{v:.3g}" for v in m.scattering)
    return f"σs ({s}) m⁻¹, {m.phase['type']}"


class VIEW3D_PT_tyndall_volumetrics(_TyndallPanel, bpy.types.Panel):
    bl_label = "Volumetrics"

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        scene = context.scene
        st = scene.tyndall
        layout.prop(st, "directory")
        col = layout.column(align=True)
        cam = scene.camera
        r = scene.render
        w, h = cv.render_resolution(r.resolution_x, r.resolution_y, r.resolution_percentage, st.resolution_scale)
        col.label(
            text=f"Camera: {cam.name if cam else 'none'}, {w}×{h} px",
            icon="CAMERA_DATA",
        )
        lights, left_out = gather.panel_light_count(scene, context.view_layer, st.include_sun)
        col.label(text=f"Lights: {lights}" + (f" ({left_out} left out)" if left_out else ""), icon="LIGHT")
        col.label(text=_world_summary(scene, context.view_layer), icon="WORLD")
        layout.prop(st, "resolution_scale")
        layout.prop(st, "tolerance")
        layout.prop(st, "threads")
        layout.prop(st, "include_sun")
        layout.prop(st, "use_lightgroups")
        layout.prop(st, "mute_world_volume")
        layout.prop(st, "apply_results")
        job = RUNNING.get("tyndall.compute_volumetrics")
        if job is not None and not job.poll().finished:
            layout.label(text=f"Computing… {job.elapsed:.0f} s (Esc cancels)", icon="TIME")
        layout.operator("tyndall.compute_volumetrics", icon="LIGHT_SPOT")
        row = layout.row(align=True)
        row.operator("tyndall.export_stage", icon="EXPORT")
        row.operator("tyndall.import_results", icon="IMPORT")


class VIEW3D_PT_tyndall_sky(_TyndallPanel, bpy.types.Panel):
    bl_label = "Sky"

    def draw(self, context: bpy.types.Context) -> None:
        layout = self.layout
        st = context.scene.tyndall
        layout.prop(st, "sky_use_sun_lamp")
        if st.sky_use_sun_lamp:
            layout.prop(st, "sky_sun_object")
            sun = gather.sun_lamp(context.scene)
            layout.label(text=f"Sun: {sun.name if sun else 'none found'}", icon="LIGHT_SUN")
        else:
            col = layout.column(align=True)
            col.prop(st, "sky_elevation")
            col.prop(st, "sky_rotation")
        col = layout.column(align=True)
        col.prop(st, "sky_air")
        col.prop(st, "sky_aerosol")
        col.prop(st, "sky_ozone")
        layout.prop(st, "sky_altitude")
        layout.prop(st, "sky_width")
        layout.prop(st, "sky_sun_disc")
        layout.prop(st, "sky_multiple_scattering")
        layout.prop(st, "sky_update_sun")
        job = RUNNING.get("tyndall.generate_sky")
        if job is not None and not job.poll().finished:
            layout.label(text=f"Rendering sky… {job.elapsed:.0f} s (Esc cancels)", icon="TIME")
        layout.operator("tyndall.generate_sky", icon="WORLD")


classes: tuple[type, ...] = (VIEW3D_PT_tyndall_volumetrics, VIEW3D_PT_tyndall_sky)
