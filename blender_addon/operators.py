"""Operators of the Tyndall tab.

``tyndall.compute_volumetrics`` and ``tyndall.generate_sky`` run their long work in a
:class:`~.core.jobs.Job`: with INVOKE_DEFAULT (the UI) in a background thread polled by a
modal timer (progress in the status bar, Esc cancels), with EXEC_DEFAULT to completion
before returning. Only the main thread touches bpy: gathering happens before the job
starts, committing files and applying results after it is done. Esc stops waiting and
sets the job's stop event: the volumetrics render stops within about a view ray's time,
the sky within one round of its grid or one row, and the staged files are deleted.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from typing import Any

import bpy
from bpy.props import StringProperty

from . import gather, results
from .core import conversions as cv
from .core import tasks
from .core.files import Staging
from .core.jobs import Job, JobState
from .core.scene_build import PER_LIGHT_LAYERS, BuiltScene, SceneInputError, build_scene, fog_box_media_by_object

# Jobs running from the UI, by operator id (one at a time each); read by the panels.
RUNNING: dict[str, Job] = {}

Finish = Callable[[bpy.types.Context, Any], str]


class UserError(Exception):
    """Bad input: reported with self.report({'ERROR'}) and nothing is written."""


def output_directory(context: bpy.types.Context, override: str) -> str:
    """The operator's ``directory`` or the scene setting, made absolute (``//`` needs a saved .blend)."""
    raw = override or context.scene.tyndall.directory
    if not raw:
        raise UserError("no output folder: set the Tyndall output folder")
    path = bpy.path.abspath(raw)
    if path.startswith("//"):
        raise UserError(f"output folder '{raw}' is relative to the .blend file: save the file or choose a folder")
    return os.path.abspath(path)


def build_from_context(context: bpy.types.Context, folder: str) -> BuiltScene:
    """Gather, build and validate the Tyndall scene (raises :class:`UserError`)."""
    try:
        data = gather.gather_scene(context.scene, context.view_layer)
        built = build_scene(data)
    except (SceneInputError, cv.ConversionError) as e:
        raise UserError(str(e)) from e
    try:
        tasks.validate_scene(built, folder)
    except ValueError as e:  # tyndall.SceneFormatError names the field
        raise UserError(f"invalid Tyndall scene: {e}") from e
    return built


class _JobOperator:
    """Shared invoke/modal/execute of the job operators; subclasses implement :meth:`prepare`."""

    bl_options = {"REGISTER"}
    job_label = "Tyndall"
    _job: Job | None = None
    _finish: Finish | None = None
    _timer: Any = None

    def prepare(self, context: bpy.types.Context) -> tuple[Job, Finish]:
        raise NotImplementedError

    def _start(self, context: bpy.types.Context) -> bool:
        try:
            self._job, self._finish = self.prepare(context)
        except UserError as e:
            self.report({"ERROR"}, str(e))
            return False
        return True

    def _complete(self, context: bpy.types.Context) -> set[str]:
        job = self._job
        assert job is not None and self._finish is not None
        state = job.poll()
        if state is JobState.FAILED:
            self.report({"ERROR"}, f"{self.job_label} failed: {job.error}")
            return {"CANCELLED"}
        if state is JobState.CANCELLED:
            self.report({"WARNING"}, f"{self.job_label} cancelled; its result is discarded")
            return {"CANCELLED"}
        try:
            msg = self._finish(context, job.result())
        except Exception as e:  # noqa: BLE001 - any failure while committing reaches the user
            self.report({"ERROR"}, f"{self.job_label}: could not apply the result: {e}")
            return {"CANCELLED"}
        self.report({"INFO"}, msg)
        return {"FINISHED"}

    def execute(self, context: bpy.types.Context) -> set[str]:
        if not self._start(context):
            return {"CANCELLED"}
        assert self._job is not None
        self._job.run()
        return self._complete(context)

    def invoke(self, context: bpy.types.Context, _event: bpy.types.Event) -> set[str]:
        key = type(self).bl_idname
        if key in RUNNING and not RUNNING[key].poll().finished:
            self.report({"WARNING"}, f"{self.job_label} is already running")
            return {"CANCELLED"}
        if not self._start(context):
            return {"CANCELLED"}
        assert self._job is not None
        RUNNING[key] = self._job
        self._job.start()
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.2, window=context.window)
        wm.modal_handler_add(self)
        wm.progress_begin(0, 100)
        return {"RUNNING_MODAL"}

    def _end_modal(self, context: bpy.types.Context) -> None:
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        if context.workspace is not None:
            context.workspace.status_text_set(None)
        RUNNING.pop(type(self).bl_idname, None)
        for area in context.screen.areas if context.screen else ():
            area.tag_redraw()

    def modal(self, context: bpy.types.Context, event: bpy.types.Event) -> set[str]:
        job = self._job
        assert job is not None
        if event.type == "ESC" and event.value == "PRESS":
            job.cancel()
            self._end_modal(context)
            self.report({"WARNING"}, f"{self.job_label} cancelled (stopped; nothing is written)")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        state = job.poll()
        context.window_manager.progress_update(int(100 * job.progress))
        if context.workspace is not None:
            context.workspace.status_text_set(
                f"{self.job_label}: {job.message or state.value} {job.elapsed:.1f} s — Esc to cancel"
            )
        if not state.finished:
            return {"PASS_THROUGH"}
        self._end_modal(context)
        return self._complete(context)


class TYNDALL_OT_compute_volumetrics(_JobOperator, bpy.types.Operator):
    """Compute the volumetric light (in-scatter, transmittance, depth, error, per light) of the scene"""

    bl_idname = "tyndall.compute_volumetrics"
    bl_label = "Compute Volumetrics"
    job_label = "Tyndall volumetrics"

    directory: StringProperty(name="Directory", subtype="DIR_PATH", default="")  # type: ignore[valid-type]

    def prepare(self, context: bpy.types.Context) -> tuple[Job, Finish]:
        folder = output_directory(context, self.directory)
        built = build_from_context(context, folder)
        staging = Staging(folder)
        apply_results = context.scene.tyndall.apply_results

        def work(progress: Any) -> dict[str, Any]:
            # `job` is bound below, before the work can run: Esc stops the render itself.
            return tasks.volumetrics_work(built, staging, progress, stop=job.stop_requested)

        def finish(ctx: bpy.types.Context, res: dict[str, Any]) -> str:
            staging.commit(res["files"])
            if apply_results:
                import_results(ctx, folder, sky=False)
            rep = res["report"]
            notes = "; ".join(built.notes)
            for n in built.notes:
                self.report({"WARNING"}, n)
            return f"Tyndall: volumetrics.exr written to {folder} (max rel. error {rep['error']['max_rel']:.2g})" + (
                f"; notes: {notes}" if notes else ""
            )

        job = Job(work, "volumetrics", on_discard=lambda _r: staging.discard())
        return job, finish


def sky_params(scene: bpy.types.Scene) -> tuple[tasks.SkyParams, bpy.types.Object | None]:
    """Sky parameters from the panel settings (sun direction from a sun lamp when asked)."""
    st = scene.tyndall
    sun = gather.sun_lamp(scene)
    elev, rot = st.sky_elevation, st.sky_rotation
    size = 0.545
    if st.sky_use_sun_lamp:
        if sun is None:
            raise UserError("Sky 'From Sun Lamp' is on but the scene has no sun lamp")
        z = [sun.matrix_world[r][2] for r in range(3)]
        try:
            elev, rot = cv.sun_angles_from_direction(z)
        except cv.ConversionError as e:
            raise UserError(f"sun lamp '{sun.name}': {e}") from e
        import math

        size = max(math.degrees(sun.data.angle), 0.0)
    p = tasks.SkyParams(
        sun_elevation_deg=float(elev),
        sun_rotation_deg=float(rot),
        air=float(st.sky_air),
        aerosol=float(st.sky_aerosol),
        ozone=float(st.sky_ozone),
        altitude_m=float(st.sky_altitude) * float(scene.unit_settings.scale_length),
        sun_size_deg=float(size),
        width=int(st.sky_width),
        sun_disc=bool(st.sky_sun_disc),
        multiple_scattering=bool(st.sky_multiple_scattering),
    )
    try:
        p.check()
    except ValueError as e:
        raise UserError(str(e)) from e
    return p, sun


class TYNDALL_OT_generate_sky(_JobOperator, bpy.types.Operator):
    """Render a sky texture with the layered atmosphere and use it as the World; match the sun lamp"""

    bl_idname = "tyndall.generate_sky"
    bl_label = "Generate Sky"
    job_label = "Tyndall sky"

    directory: StringProperty(name="Directory", subtype="DIR_PATH", default="")  # type: ignore[valid-type]

    def prepare(self, context: bpy.types.Context) -> tuple[Job, Finish]:
        params, sun = sky_params(context.scene)
        folder = output_directory(context, self.directory)
        staging = Staging(folder)
        st = context.scene.tyndall
        sun_name = sun.name if sun is not None else None
        apply_results, update_sun = st.apply_results, st.sky_update_sun

        def work(progress: Any) -> dict[str, Any]:
            # `job` is bound below, before the work can run: Esc stops the sky itself.
            return tasks.sky_work(params, staging, progress, stop=job.stop_requested)

        def finish(ctx: bpy.types.Context, res: dict[str, Any]) -> str:
            staging.commit(res["files"])
            if apply_results:
                lamp = ctx.scene.objects.get(sun_name) if sun_name else None
                sky_exr = os.path.join(folder, tasks.SKY_EXR)
                results.apply_sky(ctx.scene, sky_exr, res["report"], lamp, update_sun, ctx.view_layer)
            lamp_rep = res["report"].get("sun_lamp", {})
            return (
                f"Tyndall: sky.exr written to {folder} (sun {params.sun_elevation_deg:.1f}° elevation, "
                f"strength {lamp_rep.get('strength_w_m2', float('nan')):.4g} W/m²)"
            )

        job = Job(work, "sky", on_discard=lambda _r: staging.discard())
        return job, finish


def _export_usd(context: bpy.types.Context, path: str, built: BuiltScene) -> str:
    """Blender's own USD exporter, with the medium and output as ``tyndall:`` custom properties.

    A temporary Empty carries ``tyndall:medium:*`` (tyndall_usd reads it as the medium), each
    fog box's object its own with ``tyndall:medium:bounds = "box"``, the
    camera ``tyndall:output:*``, each IES light's data ``tyndall:ies:file``/``strength``, a lamp
    without Cast Shadow ``tyndall:castsShadows`` and a mesh object without Ray Visibility Camera
    or Shadow ``tyndall:visibleToCamera``/``castsShadows``; all are removed again. Returns "" or
    the reason it failed.
    """
    if not hasattr(bpy.ops.wm, "usd_export"):
        return "this Blender has no USD exporter"
    scene = context.scene
    med = built.scene["media"][0]
    empty = bpy.data.objects.new("TyndallMedium", None)
    scene.collection.objects.link(empty)
    cam = scene.camera
    added: list[tuple[Any, str]] = []

    def setp(idb: Any, key: str, value: Any) -> None:
        idb[key] = value
        added.append((idb, key))

    # Blender's exporter writes Blender units with metersPerUnit = 1 (so lamps fall off over
    # Blender units, as Cycles has them); scene.json's coefficients are per metre, ÷ the unit
    # scale: per Blender unit again here (at unit scale 0.01 the stage had 100× the density).
    per_unit = float(scene.unit_settings.scale_length)
    try:
        def medium_props(idb: Any, m: dict[str, Any]) -> None:
            setp(idb, "tyndall:medium:type", "homogeneous")
            setp(idb, "tyndall:medium:name", m["name"])
            setp(idb, "tyndall:medium:scattering", [v * per_unit for v in m["scattering"]])
            setp(idb, "tyndall:medium:absorption", [v * per_unit for v in m["absorption"]])
            setp(idb, "tyndall:medium:phase", m["phase"]["type"])
            if "g" in m["phase"]:
                setp(idb, "tyndall:medium:phaseG", float(m["phase"]["g"]))

        medium_props(empty, med)
        # A fog box's object carries its medium too, with bounds = "box": tyndall_usd then reads
        # its mesh as the medium's (turned) box, not as an occluder.
        # (An instanced object's properties go onto every instance's prim: one name for all.)
        for name, (i, medium_name) in fog_box_media_by_object(built).items():
            fobj = scene.objects.get(name)
            if fobj is not None:
                medium_props(fobj, {**built.scene["media"][i], "name": medium_name})
                setp(fobj, "tyndall:medium:bounds", "box")
        # Blender's exporter writes no IES shaping: the profile goes on the light data (exported
        # onto the SphereLight prim), where tyndall_usd reads it.
        by_scene_name = {v: k for k, v in built.light_names.items()}
        for lt in built.scene["lights"]:
            obj = scene.objects.get(by_scene_name.get(lt.get("name", ""), ""))
            if "ies" in lt and obj is not None and obj.type == "LIGHT":
                setp(obj.data, "tyndall:ies:file", lt["ies"]["file"])
                setp(obj.data, "tyndall:ies:strength", float(lt["ies"]["strength"]))
            if not lt.get("casts_shadows", True) and obj is not None and obj.type == "LIGHT":
                setp(obj.data, "tyndall:castsShadows", 0)
        # Nor does it write ray visibility: an object's flags go on its Xform prim.
        for m in built.scene["meshes"]:
            mobj = scene.objects.get(m.get("name", ""))
            flags = (("visible_to_camera", "tyndall:visibleToCamera"), ("casts_shadows", "tyndall:castsShadows"))
            for key, prop in flags:
                if not m.get(key, True) and mobj is not None:
                    setp(mobj, prop, 0)
        if cam is not None:
            setp(cam, "tyndall:output:resolution", list(built.scene["camera"]["resolution"]))
            # tyndall_usd 0.1 reads the five basic layers only (not the per-light ones)
            basic = [x for x in built.scene["output"]["layers"] if x not in PER_LIGHT_LAYERS]
            setp(cam, "tyndall:output:layers", ",".join(basic))
            setp(cam, "tyndall:output:tolerance", float(built.scene["output"]["tolerance"]))
        res = bpy.ops.wm.usd_export(
            filepath=path,
            selected_objects_only=False,
            export_custom_properties=True,
            export_materials=False,
            export_animation=False,
        )
        if "FINISHED" not in res or not os.path.isfile(path):
            return "Blender's USD export did not finish"
        return ""
    except Exception as e:  # noqa: BLE001 - the stage is optional; scene.json is the primary export
        return f"USD export failed: {e}"
    finally:
        for idb, key in added:
            if idb is not empty and key in idb:
                del idb[key]
        bpy.data.objects.remove(empty, do_unlink=True)


class TYNDALL_OT_export_stage(bpy.types.Operator):
    """Export the scene for Tyndall: scene.json (the Tyndall scene) and stage.usda (Blender's USD export)"""

    bl_idname = "tyndall.export_stage"
    bl_label = "Export Stage"
    bl_options = {"REGISTER"}

    directory: StringProperty(name="Directory", subtype="DIR_PATH", default="")  # type: ignore[valid-type]

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            folder = output_directory(context, self.directory)
            built = build_from_context(context, folder)
        except UserError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        staging = Staging(folder)
        try:
            names = tasks.stage_scene_files(built, staging)
            why = _export_usd(context, staging.file(tasks.STAGE_USDA), built)
            if not why:
                names.append(tasks.STAGE_USDA)
            staging.commit(names)
        except Exception as e:  # noqa: BLE001
            staging.discard()
            self.report({"ERROR"}, f"Tyndall export failed: {e}")
            return {"CANCELLED"}
        if why:
            self.report({"WARNING"}, f"stage.usda not written ({why}); scene.json written")
        for n in built.notes:
            self.report({"WARNING"}, n)
        self.report({"INFO"}, f"Tyndall: {', '.join(names)} written to {folder}")
        return {"FINISHED"}


def import_results(context: bpy.types.Context, folder: str, sky: bool = True, volumetrics: bool = True) -> list[str]:
    """Apply what ``folder`` holds: volumetrics.exr → light groups + compositor; sky.exr → world + sun."""
    scene = context.scene
    st = scene.tyndall
    done = []
    exr = os.path.join(folder, tasks.VOLUMETRICS_EXR)
    if volumetrics and os.path.isfile(exr):
        rep_path = os.path.join(folder, tasks.REPORT_JSON)
        rep = tasks.read_json(rep_path) if os.path.isfile(rep_path) else {}
        light_layers = rep.get("blender", {}).get("light_layers", {})
        kept: list[str] = []
        lgs = results.setup_lightgroups(scene, light_layers, kept) if st.use_lightgroups else {}
        wiring: list[str] = []
        size = rep.get("resolution")
        exr_size = (int(size[0]), int(size[1])) if isinstance(size, list) and len(size) == 2 else None
        results.setup_compositor(scene, exr, light_layers, lgs, wiring, exr_size)
        done.append("compositor")
        done.extend(wiring)
        done.extend(kept)
        if st.mute_world_volume and results.mute_world_volume(scene):
            done.append("world volume muted for the surface render")
        if st.mute_world_volume:
            fog = results.mute_fog_volumes(rep.get("blender", {}).get("fog_materials", []))
            if fog:
                done.append(f"fog boxes' volume muted for the surface render ({', '.join(fog)})")
        if lgs:
            done.append(f"{len(lgs)} light groups")
    sky_exr = os.path.join(folder, tasks.SKY_EXR)
    if sky and os.path.isfile(sky_exr):
        rep_path = os.path.join(folder, tasks.SKY_REPORT_JSON)
        rep = tasks.read_json(rep_path) if os.path.isfile(rep_path) else {}
        results.apply_sky(scene, sky_exr, rep, gather.sun_lamp(scene), st.sky_update_sun, context.view_layer)
        done.append("world sky" + (" + sun lamp" if rep.get("sun_lamp") and st.sky_update_sun else ""))
    return done


class TYNDALL_OT_import_results(bpy.types.Operator):
    """Load Tyndall results from the folder: compositor (render × T + L), light groups, world sky and sun"""

    bl_idname = "tyndall.import_results"
    bl_label = "Import Results"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(name="Directory", subtype="DIR_PATH", default="")  # type: ignore[valid-type]

    def execute(self, context: bpy.types.Context) -> set[str]:
        try:
            folder = output_directory(context, self.directory)
            if not os.path.isdir(folder):
                raise UserError(f"folder not found: {folder}")
            done = import_results(context, folder)
        except (UserError, OSError, json.JSONDecodeError, KeyError) as e:
            self.report({"ERROR"}, f"Tyndall import: {e}")
            return {"CANCELLED"}
        if not done:
            self.report({"ERROR"}, f"Tyndall import: no volumetrics.exr or sky.exr in {folder}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"Tyndall: imported {', '.join(done)}")
        return {"FINISHED"}


classes: tuple[type, ...] = (
    TYNDALL_OT_compute_volumetrics,
    TYNDALL_OT_generate_sky,
    TYNDALL_OT_export_stage,
    TYNDALL_OT_import_results,
)
