"""Compare Tyndall's layered-atmosphere sky with Blender's own Sky Texture (Single Scattering).

Run with a Python 3.11 that has `bpy` 5.0.1 (PyPI), `tyndall` and `OpenEXR` installed:

    python scripts/compare_blender_sky.py [--width 256] [--out DIR]

For each sun elevation it renders Blender's Sky Texture (Single Scattering, sun disc
off) seen by an equirectangular Cycles camera, and Tyndall's sky with the same air,
aerosol and ozone densities, then compares the two over the upper hemisphere after
normalising each by its mean luminance: the luminance ratio and the chromaticity
difference Δu′v′. The camera orientation is the one that maps directions like
Blender's Environment Texture; it is checked with the sun disc before comparing.
Prints a Markdown table (docs/blender-sky-comparison.md records a run).
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import bpy
import numpy as np
import OpenEXR
import tyndall

M_XYZ = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])


def upv(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Luminance Y and CIE 1976 (u′, v′) of linear Rec.709 pixels."""
    xyz = rgb @ M_XYZ.T
    d = xyz[..., 0] + 15 * xyz[..., 1] + 3 * xyz[..., 2]
    d = np.where(d > 0, d, np.nan)
    return xyz[..., 1], np.stack([4 * xyz[..., 0] / d, 9 * xyz[..., 1] / d], axis=-1)


def blender_sky(
    elevation_deg: float, rotation_deg: float, width: int, sun_disc: bool, tmp: Path, environment: Path | None = None
) -> np.ndarray:
    """Blender's Sky Texture (or, with `environment`, that EXR as an Environment
    Texture) rendered by an equirectangular Cycles camera at the origin."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 4
    scene.cycles.use_denoising = False
    scene.cycles.filter_width = 0.01
    scene.render.resolution_x, scene.render.resolution_y = width, width // 2
    scene.render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    world = bpy.data.worlds.new("sky")
    scene.world = world
    world.use_nodes = True
    nodes = world.node_tree.nodes
    if environment is None:
        sky = nodes.new("ShaderNodeTexSky")
        sky.sky_type = "SINGLE_SCATTERING"
        sky.sun_elevation = math.radians(elevation_deg)
        sky.sun_rotation = math.radians(rotation_deg)
        sky.sun_disc = sun_disc
        sky.air_density, sky.aerosol_density, sky.ozone_density, sky.altitude = 1.0, 1.0, 1.0, 0.0
    else:
        sky = nodes.new("ShaderNodeTexEnvironment")
        sky.image = bpy.data.images.load(str(environment))
        sky.interpolation = "Closest"
    background = nodes["Background"] if "Background" in nodes else nodes.new("ShaderNodeBackground")
    world.node_tree.links.new(sky.outputs["Color"], background.inputs["Color"])
    cam_data = bpy.data.cameras.new("pano")
    cam_data.type = "PANO"
    cam_data.panorama_type = "EQUIRECTANGULAR"
    cam = bpy.data.objects.new("pano", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    # Looking along +X with +Z up. The camera's panorama is not the Environment
    # Texture's layout (it comes out mirrored in azimuth), so orientation is checked
    # by rendering Tyndall's EXR as an Environment Texture with this same camera.
    cam.rotation_euler = (math.pi / 2, 0.0, -math.pi / 2)
    out = tmp / f"blender_{elevation_deg}_{rotation_deg}_{'env' if environment else 'sky'}.exr"
    scene.render.filepath = str(out)
    bpy.ops.render.render(write_still=True)
    with OpenEXR.File(str(out)) as f:
        ch = f.channels()
        rgba = ch["RGBA"].pixels if "RGBA" in ch else ch["RGB"].pixels
    return np.asarray(rgba[..., :3], dtype=np.float64)


def brightest(rgb: np.ndarray) -> tuple[int, int]:
    y = rgb @ np.array([0.2126, 0.7152, 0.0722])
    j, i = np.unravel_index(int(np.argmax(y)), y.shape)
    return int(i), int(j)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    tmp = Path(args.out or tempfile.mkdtemp())
    tmp.mkdir(parents=True, exist_ok=True)
    w = args.width
    # Orientation: Tyndall's world texture used as Blender's Environment Texture must
    # put the sun where Blender's own Sky Texture puts it, seen by the same camera.
    for rot in (0.0, 60.0, 200.0):
        b = blender_sky(30.0, rot, w, True, tmp)
        env = tmp / f"tyndall_{rot}.exr"
        tyndall.sky(30.0, rot, width=w, sun_disc=True, tolerance=1e-2, out=env)
        e = blender_sky(30.0, rot, w, True, tmp, environment=env)
        print(
            f"orientation (sun 30°, rotation {rot:g}°): Blender's sky sun at {brightest(b)}, "
            f"Tyndall's texture sun at {brightest(e)}"
        )
    print()
    print("| sun elevation | median Y ratio | 5–95 % Y ratio | max \\|ln Y ratio\\| | median Δu′v′ | 95 % Δu′v′ |")
    print("|---|---|---|---|---|---|")
    for e in [2.0, 5.0, 10.0, 20.0, 40.0, 80.0]:
        b = blender_sky(e, 0.0, w, False, tmp)
        t, _ = tyndall.sky(e, 0.0, width=w, sun_disc=False, tolerance=1e-3)
        upper = slice(0, w // 4 - 1)  # rows above the horizon, away from it by a pixel
        yb, uvb = upv(b[upper])
        yt, uvt = upv(t[upper].astype(np.float64))
        yb, yt = yb / np.nanmean(yb), yt / np.nanmean(yt)
        ratio = yt / yb
        duv = np.linalg.norm(uvt - uvb, axis=-1)
        lo, hi = np.nanpercentile(ratio, [5, 95])
        print(
            f"| {e:g}° | {np.nanmedian(ratio):.3f} | {lo:.3f}–{hi:.3f} | {np.nanmax(np.abs(np.log(ratio))):.3f} "
            f"| {np.nanmedian(duv):.4f} | {np.nanpercentile(duv, 95):.4f} |"
        )


if __name__ == "__main__":
    main()
