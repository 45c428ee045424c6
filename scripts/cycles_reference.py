#!/usr/bin/env python3
"""Render a converged Blender Cycles reference of a Tyndall scene file.

    python scripts/cycles_reference.py SCENE.json --out REF.exr --samples N \
        [--seed S] [--time-log T.json] [--half]

Needs the `bpy` module (Blender 5.0.x from PyPI) plus numpy and OpenEXR.

The scene is rebuilt in bpy so that Cycles computes exactly what Tyndall
models: single scattering of point/spot lights (optionally with an IES
profile) in homogeneous world media, seen by a perspective camera, with
black surfaces that end view rays and cast shadows. See
docs/cycles-conventions.md for the conventions behind every mapping.

Anything that cannot be mapped exactly onto Cycles is rejected with a
clear error (exit code 2): sun/ambient/window lights (a sun in an infinite
world volume is fully extinguished in Cycles), height/fog-layer media,
boxed media, spectral coefficients, non-isotropic `distribution`s,
equirectangular cameras, Nishita phase functions, |g| > 0.999.

The EXR holds float32 channels R, G, B: the linear (scene-referred) radiance
in W·m⁻²·sr⁻¹ per Rec.709 channel, i.e. what Tyndall writes as
`inscatter.R/G/B`. Row 0 is the top row.

With --half the N samples are split into two renders of N/2 samples with
seeds S and S+1; the EXR holds their mean, and the time log records the
per-pixel noise estimate |A − B|/2 (the standard error of the mean), so the
reference carries its own Monte Carlo error.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time

import numpy as np


class Unsupported(Exception):
    """The scene uses something that has no exact Cycles equivalent."""


# --------------------------------------------------------------------------
# small maths helpers (no bpy needed)


def _normalize(v):
    v = np.asarray(v, dtype=float)
    n = np.linalg.norm(v)
    if n < 1e-300:
        raise Unsupported("zero-length vector")
    return v / n


def orientation_matrix(orientation, position):
    """3×3 rotation (columns = local X, Y, Z in world) of a Tyndall Orientation.

    Blender cameras and lights look/shine along local −Z with +Y up.
    """
    if orientation is None:
        return np.eye(3)
    if "look_at" in orientation:
        la = orientation["look_at"]
        f = _normalize(np.asarray(la["target"], float) - np.asarray(position, float))
        up = np.asarray(la.get("up", [0.0, 0.0, 1.0]), float)
        z = -f
        x = np.cross(up, z)
        if np.linalg.norm(x) < 1e-9 * np.linalg.norm(up):
            raise Unsupported("look_at.up is parallel to the view direction")
        x = x / np.linalg.norm(x)
        y = np.cross(z, x)
        return np.stack([x, y, z], axis=1)
    if "quaternion_wxyz" in orientation:
        w, x, y, z = _normalize(orientation["quaternion_wxyz"])
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
    raise Unsupported(f"orientation must have look_at or quaternion_wxyz, got {sorted(orientation)}")


def transform_matrix(t):
    """4×4 object → world matrix of a Tyndall Transform."""
    t = t or {}
    if "matrix" in t:
        m = np.asarray(t["matrix"], float)
        if m.shape != (4, 4):
            raise Unsupported("transform.matrix must be 4×4")
        return m
    m = np.eye(4)
    r = orientation_matrix({"quaternion_wxyz": t["rotation_wxyz"]}, None) if "rotation_wxyz" in t else np.eye(3)
    s = np.asarray(t.get("scale", [1.0, 1.0, 1.0]), float)
    m[:3, :3] = r @ np.diag(s)
    m[:3, 3] = np.asarray(t.get("translation", [0.0, 0.0, 0.0]), float)
    return m


def pose_matrix(rot3, position):
    m = np.eye(4)
    m[:3, :3] = rot3
    m[:3, 3] = position
    return m


def coefficient_rgb(c, field):
    """A Tyndall Coefficient as RGB m⁻¹ (only grey and RGB forms are exact)."""
    if isinstance(c, (int, float)):
        return np.array([float(c)] * 3)
    if isinstance(c, list) and len(c) == 3 and all(isinstance(v, (int, float)) for v in c):
        return np.array([float(v) for v in c])
    raise Unsupported(f"{field}: only grey and [r, g, b] coefficients map exactly to Cycles, got {json.dumps(c)[:80]}")


def density_and_colour(sigma):
    """Volume Scatter/Absorption (density D, colour C ≤ 1) for an RGB coefficient.

    Volume Scatter: σ_s = D·C. Keep D = 1 when every channel ≤ 1 (then C = σ
    exactly), otherwise D = max and C = σ/D.
    """
    sigma = np.asarray(sigma, float)
    m = float(sigma.max())
    if m <= 0.0:
        return 0.0, np.zeros(3)
    if m <= 1.0:
        return 1.0, sigma.copy()
    return m, sigma / m


# --------------------------------------------------------------------------
# scene validation / mapping (pure Python: usable without bpy)


HG_G_MAX = 1.0 - 1e-3  # volume_henyey_greenstein_setup() clamps |g| to this


def map_phase(phase, field):
    """Tyndall PhaseFunction → (Volume Scatter phase enum, anisotropy, alpha)."""
    phase = phase or {"type": "isotropic"}
    t = phase.get("type")
    if t == "isotropic":
        return ("HENYEY_GREENSTEIN", 0.0, None)
    if t == "henyey_greenstein":
        g = float(phase["g"])
        if abs(g) > HG_G_MAX:
            raise Unsupported(f"{field}.g: Cycles clamps |g| to {HG_G_MAX}, got {g}")
        return ("HENYEY_GREENSTEIN", g, None)
    if t == "rayleigh":
        return ("RAYLEIGH", 0.0, None)
    if t == "cornette_shanks":
        # Draine with alpha = 1 is exactly Cornette–Shanks (volume_util.h).
        g = float(phase["g"])
        return ("DRAINE", g, 1.0)
    raise Unsupported(f"{field}: phase type {t!r} has no exact Cycles equivalent")


def check_scene(scene):
    """Raise Unsupported for anything Cycles cannot reproduce exactly."""
    if scene.get("version") != 1:
        raise Unsupported(f"version: only version 1 is supported, got {scene.get('version')}")
    cam = scene["camera"]
    if cam.get("type") != "perspective":
        raise Unsupported(f"camera: only perspective cameras are supported, got {cam.get('type')!r}")
    for i, light in enumerate(scene.get("lights", [])):
        t = light.get("type")
        f = f"lights[{i}]"
        if t not in ("point", "spot"):
            raise Unsupported(
                f"{f}: light type {t!r} is not supported (a sun or ambient light behind an infinite "
                "world volume is extinguished completely in Cycles; window lights do not exist)"
            )
        dist = light.get("distribution", {"type": "isotropic"})
        if dist.get("type", "isotropic") != "isotropic":
            raise Unsupported(f"{f}.distribution: only isotropic (Blender has no {dist.get('type')!r})")
        if t == "spot" and light.get("spot_size_deg", 45.0) < 1.0:
            raise Unsupported(f"{f}.spot_size_deg: Blender's Spot Size is ≥ 1°, got {light['spot_size_deg']}")
        for k in light:
            if k not in (
                "type",
                "name",
                "position",
                "orientation",
                "color",
                "power_w",
                "radius_m",
                "spot_size_deg",
                "spot_blend",
                "ies",
                "distribution",
            ):
                raise Unsupported(f"{f}.{k}: unknown field")
    for i, m in enumerate(scene.get("media", [])):
        f = f"media[{i}]"
        if m.get("type") != "homogeneous":
            raise Unsupported(f"{f}: only homogeneous media are supported, got {m.get('type')!r}")
        if m.get("bounds", "world") != "world":
            raise Unsupported(f'{f}.bounds: only "world" is supported')
        coefficient_rgb(m["scattering"], f + ".scattering")
        coefficient_rgb(m.get("absorption", 0.0), f + ".absorption")
        map_phase(m.get("phase"), f + ".phase")
    out = scene.get("output", {})
    pf = out.get("pixel_filter", {"type": "blackman_harris", "width_px": 1.5})
    if pf.get("type") not in ("blackman_harris", "none"):
        raise Unsupported(f"output.pixel_filter: unknown type {pf.get('type')!r}")
    if out.get("spectral", "auto") == "always":
        raise Unsupported('output.spectral: "always" renders spectrally; Cycles renders RGB')


# --------------------------------------------------------------------------
# bpy scene construction


def _bpy():
    import bpy  # noqa: WPS433

    return bpy


def reset_blender():
    bpy = _bpy()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    return scene


def set_matrix(obj, m):
    import mathutils

    obj.matrix_world = mathutils.Matrix([list(map(float, row)) for row in m])


def black_material():
    """A surface that emits and reflects nothing but is opaque (ends rays, casts shadows)."""
    bpy = _bpy()
    mat = bpy.data.materials.get("tyndall_black")
    if mat is not None:
        return mat
    mat = bpy.data.materials.new("tyndall_black")
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    em = nt.nodes.new("ShaderNodeEmission")
    em.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    em.inputs["Strength"].default_value = 0.0
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(em.outputs["Emission"], out.inputs["Surface"])
    return mat


def diffuse_material(albedo):
    bpy = _bpy()
    mat = bpy.data.materials.new("diffuse")
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    d = nt.nodes.new("ShaderNodeBsdfDiffuse")
    d.inputs["Color"].default_value = (*albedo, 1.0)
    d.inputs["Roughness"].default_value = 0.0
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(d.outputs["BSDF"], out.inputs["Surface"])
    return mat


def add_mesh(name, positions, triangles, matrix, material):
    bpy = _bpy()
    me = bpy.data.meshes.new(name or "mesh")
    me.from_pydata([tuple(map(float, p)) for p in positions], [], [tuple(map(int, t)) for t in triangles])
    me.validate(clean_customdata=False)
    me.update()
    me.materials.append(material)
    ob = bpy.data.objects.new(name or "mesh", me)
    bpy.context.scene.collection.objects.link(ob)
    set_matrix(ob, matrix)
    return ob


def add_light(
    kind,
    name,
    matrix,
    color,
    power_w,
    radius_m=0.0,
    spot_size_deg=45.0,
    spot_blend=0.15,
    ies_path=None,
    ies_strength=1.0,
    soft_falloff=True,
):
    """A Blender Point/Spot light. Colour channels > 1 are folded into the power."""
    bpy = _bpy()
    color = np.asarray(color, float)
    cmax = float(color.max())
    if cmax > 1.0:
        color = color / cmax
        power_w = power_w * cmax
    ld = bpy.data.lights.new(name or kind, "SPOT" if kind == "spot" else "POINT")
    ld.color = tuple(color)
    ld.energy = float(power_w)
    ld.shadow_soft_size = float(radius_m)
    ld.use_soft_falloff = bool(soft_falloff)
    ld.exposure = 0.0
    ld.normalize = True
    ld.use_temperature = False
    ld.cycles.max_bounces = 1024
    ld.cycles.use_multiple_importance_sampling = True
    if kind == "spot":
        ld.spot_size = math.radians(float(spot_size_deg))
        ld.spot_blend = float(spot_blend)
    if ies_path is not None:
        ld.use_nodes = True
        nt = ld.node_tree
        nt.nodes.clear()
        ies = nt.nodes.new("ShaderNodeTexIES")
        ies.mode = "EXTERNAL"
        ies.filepath = os.path.abspath(ies_path)
        ies.inputs["Strength"].default_value = float(ies_strength)
        em = nt.nodes.new("ShaderNodeEmission")
        em.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        out = nt.nodes.new("ShaderNodeOutputLight")
        nt.links.new(ies.outputs["Fac"], em.inputs["Strength"])
        nt.links.new(em.outputs["Emission"], out.inputs["Surface"])
    ob = bpy.data.objects.new(name or kind, ld)
    bpy.context.scene.collection.objects.link(ob)
    set_matrix(ob, matrix)
    # Tyndall renders only what the medium adds: never show the light's sphere.
    ob.visible_camera = False
    return ob


def set_world_media(media):
    """World: black background, and the sum of homogeneous volumes.

    media: list of (sigma_s_rgb, sigma_a_rgb, phase_tuple).
    """
    bpy = _bpy()
    scene = bpy.context.scene
    world = scene.world or bpy.data.worlds.new("World")
    scene.world = world
    world.use_nodes = True
    nt = world.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputWorld")
    bg = nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    bg.inputs["Strength"].default_value = 0.0
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    shaders = []
    for sigma_s, sigma_a, (phase, g, alpha) in media:
        d, c = density_and_colour(sigma_s)
        if d > 0:
            vs = nt.nodes.new("ShaderNodeVolumeScatter")
            vs.phase = phase
            vs.inputs["Color"].default_value = (*c, 1.0)
            vs.inputs["Density"].default_value = d
            if phase in ("HENYEY_GREENSTEIN", "DRAINE"):
                vs.inputs["Anisotropy"].default_value = g
            if phase == "DRAINE":
                vs.inputs["Alpha"].default_value = alpha
            shaders.append(vs.outputs[0])
        da, ca = density_and_colour(sigma_a)
        if da > 0:
            va = nt.nodes.new("ShaderNodeVolumeAbsorption")
            # Volume Absorption: σ_a = D·(1 − C).
            va.inputs["Color"].default_value = (*(1.0 - ca), 1.0)
            va.inputs["Density"].default_value = da
            shaders.append(va.outputs[0])
    if shaders:
        acc = shaders[0]
        for s in shaders[1:]:
            add = nt.nodes.new("ShaderNodeAddShader")
            nt.links.new(acc, add.inputs[0])
            nt.links.new(s, add.inputs[1])
            acc = add.outputs[0]
        nt.links.new(acc, out.inputs["Volume"])
    return world


def add_camera(
    position,
    rot3,
    focal_mm=50.0,
    sensor_w=36.0,
    sensor_h=24.0,
    fit="auto",
    shift_x=0.0,
    shift_y=0.0,
    clip_start=0.0,
    clip_end=None,
):
    bpy = _bpy()
    cd = bpy.data.cameras.new("camera")
    cd.type = "PERSP"
    cd.lens_unit = "MILLIMETERS"
    cd.lens = float(focal_mm)
    cd.sensor_width = float(sensor_w)
    cd.sensor_height = float(sensor_h)
    cd.sensor_fit = {"auto": "AUTO", "horizontal": "HORIZONTAL", "vertical": "VERTICAL"}[fit]
    cd.shift_x = float(shift_x)
    cd.shift_y = float(shift_y)
    cd.clip_start = max(float(clip_start), 1e-6)
    cd.clip_end = float(clip_end) if clip_end is not None else 1e30
    cd.dof.use_dof = False
    ob = bpy.data.objects.new("camera", cd)
    bpy.context.scene.collection.objects.link(ob)
    set_matrix(ob, pose_matrix(rot3, position))
    bpy.context.scene.camera = ob
    return ob


def configure_render(
    resolution,
    samples,
    seed=0,
    filter_type="BLACKMAN_HARRIS",
    filter_width=1.5,
    threads=2,
    bounces_max=0,
    volume_bounces=0,
):
    """Cycles settings for an unbiased single-scattering render (see docs/cycles-conventions.md)."""
    bpy = _bpy()
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    r = scene.render
    r.resolution_x, r.resolution_y = int(resolution[0]), int(resolution[1])
    r.resolution_percentage = 100
    r.pixel_aspect_x = r.pixel_aspect_y = 1.0
    r.use_border = False
    r.film_transparent = False
    r.use_motion_blur = False
    r.use_persistent_data = False
    r.threads_mode = "FIXED"
    r.threads = int(threads)
    r.use_compositing = False
    r.use_sequencer = False
    c = scene.cycles
    c.device = "CPU"
    c.samples = int(samples)
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.time_limit = 0.0
    c.seed = int(seed)
    c.use_animated_seed = False
    c.max_bounces = int(bounces_max)
    c.diffuse_bounces = 0
    c.glossy_bounces = 0
    c.transmission_bounces = 0
    c.volume_bounces = int(volume_bounces)
    c.transparent_max_bounces = 0
    c.caustics_reflective = False
    c.caustics_refractive = False
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.light_sampling_threshold = 0.0
    c.use_light_tree = True
    c.use_guiding = False
    c.volume_biased = False
    c.pixel_filter_type = filter_type
    c.filter_width = float(filter_width)
    c.use_auto_tile = False
    c.film_exposure = 1.0
    vs = scene.view_settings
    vs.view_transform = "Standard"
    vs.look = "None"
    vs.exposure = 0.0
    vs.gamma = 1.0
    vs.use_curve_mapping = False
    scene.display_settings.display_device = "sRGB"
    im = r.image_settings
    im.file_format = "OPEN_EXR"
    im.color_mode = "RGB"
    im.color_depth = "32"
    im.exr_codec = "ZIP"
    return scene


def render_to_array(path=None):
    """Render the current scene; return (H×W×3 float32 array with row 0 at the top, seconds)."""
    bpy = _bpy()
    scene = bpy.context.scene
    tmpdir = tempfile.mkdtemp(prefix="cyref_")
    out = path or os.path.join(tmpdir, "render.exr")
    scene.render.filepath = out
    t0 = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    dt = time.perf_counter() - t0
    img = read_exr_rgb(out)
    if path is None:
        os.remove(out)
        os.rmdir(tmpdir)
    return img, dt


def read_exr_rgb(path, prefix=""):
    import OpenEXR

    with OpenEXR.File(path) as f:
        ch = f.channels()
        names = list(ch.keys())

        def get(c):
            if prefix + c in ch:
                return np.asarray(ch[prefix + c].pixels, dtype=np.float32)
            # multi-channel "RGB"/"RGBA" packing of the new OpenEXR API
            for n in ("RGB", "RGBA"):
                if n in ch:
                    return np.asarray(ch[n].pixels[..., "RGBA".index(c)], dtype=np.float32)
            raise KeyError(f"{path}: no channel {prefix + c} in {names}")

        return np.stack([get("R"), get("G"), get("B")], axis=-1)


def write_exr_rgb(path, img, half=False, extra_header=None):
    import OpenEXR

    img = np.ascontiguousarray(img, dtype=np.float16 if half else np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    if extra_header:
        header.update(extra_header)
    channels = {c: np.ascontiguousarray(img[..., i]) for i, c in enumerate("RGB")}
    tmp = path + ".tmp.exr"
    with OpenEXR.File(header, channels) as f:
        f.write(tmp)
    os.replace(tmp, path)


def build_scene(scene, base_dir, albedo=None):
    """Build the bpy scene for a (validated) Tyndall scene dict.

    ``albedo`` (grey, 0..1): give every mesh a diffuse surface of that albedo
    instead of the black one (the composite check: surfaces lit through the haze).
    """
    check_scene(scene)
    reset_blender()
    cam = scene["camera"]
    rot = orientation_matrix(cam["orientation"], cam["position"])
    add_camera(
        cam["position"],
        rot,
        focal_mm=cam.get("focal_length_mm", 50.0),
        sensor_w=cam.get("sensor_width_mm", 36.0),
        sensor_h=cam.get("sensor_height_mm", 24.0),
        fit=cam.get("sensor_fit", "auto"),
        shift_x=cam.get("shift_x", 0.0),
        shift_y=cam.get("shift_y", 0.0),
        clip_start=cam.get("clip_start_m", 0.0),
        clip_end=cam.get("clip_end_m"),
    )
    surface = black_material() if albedo is None else diffuse_material((float(albedo),) * 3)
    for i, m in enumerate(scene.get("meshes", [])):
        add_mesh(
            m.get("name") or f"mesh{i}", m["positions"], m["triangles"], transform_matrix(m.get("transform")), surface
        )
    for i, l in enumerate(scene.get("lights", [])):
        rotl = orientation_matrix(l.get("orientation", {"quaternion_wxyz": [1, 0, 0, 0]}), l["position"])
        ies = l.get("ies")
        ies_path = None
        if ies is not None:
            ies_path = ies["file"] if os.path.isabs(ies["file"]) else os.path.join(base_dir, ies["file"])
            if not os.path.isfile(ies_path):
                raise Unsupported(f"lights[{i}].ies.file: no such file {ies_path}")
        add_light(
            l["type"],
            l.get("name") or l["type"],
            pose_matrix(rotl, l["position"]),
            l.get("color", [1.0, 1.0, 1.0]),
            l.get("power_w", 1000.0),
            l.get("radius_m", 0.0),
            l.get("spot_size_deg", 45.0),
            l.get("spot_blend", 0.15),
            ies_path,
            (ies or {}).get("strength", 1.0),
        )
    media = []
    for i, m in enumerate(scene.get("media", [])):
        media.append(
            (
                coefficient_rgb(m["scattering"], f"media[{i}].scattering"),
                coefficient_rgb(m.get("absorption", 0.0), f"media[{i}].absorption"),
                map_phase(m.get("phase"), f"media[{i}].phase"),
            )
        )
    set_world_media(media)
    pf = scene.get("output", {}).get("pixel_filter", {"type": "blackman_harris", "width_px": 1.5})
    if pf["type"] == "blackman_harris":
        ftype, fw = "BLACKMAN_HARRIS", pf.get("width_px", 1.5)
    else:
        # Blender's narrowest box filter (width 0.01). Cycles renders it as a 1-px box,
        # not as point samples (measured: hi-res maps matched the 1-px box average to
        # 0.5 %, docs/cycles-conventions.md §2); the stored references all use Blackman–Harris.
        ftype, fw = "BOX", 0.01
    return cam["resolution"], ftype, fw


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--out", required=True)
    ap.add_argument("--samples", type=int, required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--time-log", default=None, help="write render wall time (and noise with --half) as JSON")
    ap.add_argument(
        "--half", action="store_true", help="render two seeds with N/2 samples each; write their mean and log the noise"
    )
    ap.add_argument("--float16", action="store_true", help="store the EXR as half floats")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument(
        "--albedo",
        type=float,
        default=None,
        help="diffuse grey surfaces of this albedo instead of black ones (full render: surfaces + haze)",
    )
    args = ap.parse_args(argv)

    with open(args.scene) as f:
        scene = json.load(f)
    base_dir = os.path.dirname(os.path.abspath(args.scene))
    try:
        res, ftype, fw = build_scene(scene, base_dir, albedo=args.albedo)
    except Unsupported as e:
        print(f"cycles_reference: error: {args.scene}: {e}", file=sys.stderr)
        return 2
    log = {
        "scene": os.path.basename(args.scene),
        "samples": args.samples,
        "seed": args.seed,
        "resolution": list(res),
        "albedo": args.albedo,
        "blender": _bpy().app.version_string,
        "settings": {
            "device": "CPU",
            "threads": args.threads,
            "max_bounces": 0,
            "volume_bounces": 0,
            "pixel_filter": ftype,
            "filter_width_px": fw,
            "adaptive_sampling": False,
            "denoising": False,
            "light_tree": True,
            "light_sampling_threshold": 0.0,
            "view_transform": "Standard",
        },
    }
    if args.half:
        n = max(1, args.samples // 2)
        configure_render(res, n, args.seed, ftype, fw, threads=args.threads)
        a, ta = render_to_array()
        configure_render(res, n, args.seed + 1, ftype, fw, threads=args.threads)
        b, tb = render_to_array()
        img = 0.5 * (a + b)
        se = 0.5 * np.abs(a.astype(np.float64) - b.astype(np.float64))
        rms_img = float(np.sqrt(np.mean(img.astype(np.float64) ** 2)))
        # E|A−B|² = 2σ²(N/2) = 4σ²(N): the standard error of the mean is rms(A−B)/2.
        rms_se = float(np.sqrt(np.mean(se**2)))
        log.update(
            {
                "render_seconds": ta + tb,
                "render_seconds_parts": [ta, tb],
                "samples_per_part": n,
                "seeds": [args.seed, args.seed + 1],
                "noise_rms_abs": rms_se,
                "image_rms": rms_img,
                "noise_rel_rms": rms_se / rms_img if rms_img > 0 else None,
                "noise_note": "noise_rms_abs = RMS over pixels and channels of |A-B|/2, the standard error "
                "of the stored mean of two half-sample renders A, B",
            }
        )
    else:
        configure_render(res, args.samples, args.seed, ftype, fw, threads=args.threads)
        img, t = render_to_array()
        log["render_seconds"] = t
    write_exr_rgb(args.out, img, half=args.float16)
    if args.time_log:
        with open(args.time_log, "w") as f:
            json.dump(log, f, indent=2)
    print(json.dumps({k: v for k, v in log.items() if k != "settings"}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
