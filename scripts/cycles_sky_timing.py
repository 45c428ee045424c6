"""Time Cycles rendering Blender's own Sky Texture (Single Scattering) to an
equirectangular EXR, for comparison with `tyndall sky` (docs/benchmarks.md).

Run with a Python 3.11 that has `bpy` 5.0.1 (PyPI), `numpy` and `OpenEXR`:

    python scripts/cycles_sky_timing.py [--width 2048] [--samples 1 4] [--repeat 2]

For each sample count it renders a panoramic (equirectangular) Cycles camera on
the CPU looking at a world whose only shader is the Sky Texture (Single
Scattering, sun elevation 60° and 2°, sun disc off), writes a 32-bit EXR and
reports the wall time of `bpy.ops.render.render` (best of `--repeat`; the first
render of a session also pays for kernel loading and the sky precomputation, so
it is reported separately). The sky is noise-free per sample (a deterministic
function of direction), so samples only anti-alias: the script reports the
relative RMS difference of each render to the highest sample count.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import bpy
import numpy as np
import OpenEXR


def setup(elevation_deg: float, width: int, samples: int, out: Path) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.render.resolution_x, scene.render.resolution_y = width, width // 2
    scene.render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    world = bpy.data.worlds.new("sky")
    scene.world = world
    world.use_nodes = True
    nodes = world.node_tree.nodes
    sky = nodes.new("ShaderNodeTexSky")
    sky.sky_type = "SINGLE_SCATTERING"
    sky.sun_elevation = math.radians(elevation_deg)
    sky.sun_rotation = 0.0
    sky.sun_disc = False
    background = nodes["Background"] if "Background" in nodes else nodes.new("ShaderNodeBackground")
    world.node_tree.links.new(sky.outputs["Color"], background.inputs["Color"])
    cam_data = bpy.data.cameras.new("pano")
    cam_data.type = "PANO"
    cam_data.panorama_type = "EQUIRECTANGULAR"
    cam = bpy.data.objects.new("pano", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    cam.rotation_euler = (math.pi / 2, 0.0, -math.pi / 2)
    scene.render.filepath = str(out)


def read(path: Path) -> np.ndarray:
    with OpenEXR.File(str(path)) as f:
        ch = f.channels()
        rgba = ch["RGBA"].pixels if "RGBA" in ch else ch["RGB"].pixels
    return np.asarray(rgba[..., :3], dtype=np.float64)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=2048)
    ap.add_argument("--samples", type=int, nargs="+", default=[1, 4, 16])
    ap.add_argument("--elevations", type=float, nargs="+", default=[60.0, 2.0])
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    tmp = Path(args.out or tempfile.mkdtemp())
    tmp.mkdir(parents=True, exist_ok=True)
    print(f"| sun | samples | first render (s) | best of {args.repeat} (s) | rel. RMS vs {max(args.samples)} spp |")
    print("|---|---|---|---|---|")
    for e in args.elevations:
        rows, images = [], {}
        for spp in args.samples:
            out = tmp / f"cycles_sky_{e:g}_{spp}.exr"
            times = []
            for _ in range(args.repeat + 1):
                setup(e, args.width, spp, out)
                t = time.perf_counter()
                bpy.ops.render.render(write_still=True)
                times.append(time.perf_counter() - t)
            images[spp] = read(out)
            rows.append((spp, times[0], min(times[1:])))
        ref = images[max(args.samples)]
        for spp, first, best in rows:
            d = images[spp] - ref
            rms = float(np.sqrt(np.mean(d**2)) / np.sqrt(np.mean(ref**2)))
            print(f"| {e:g}° | {spp} | {first:.2f} | {best:.2f} | {rms:.2e} |", flush=True)


if __name__ == "__main__":
    main()
