"""Writes the shipped example scenes (examples/*.json). Run from the repo root.

The scenes are plain JSON in the documented format; this script only saves
typing the box meshes. Re-running it reproduces the committed files.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

Vec3 = tuple[float, float, float]


def box(name: str, lo: Vec3, hi: Vec3) -> dict:
    """An axis-aligned box as 12 triangles."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    p = [[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)]
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [t for a, b, c, d in quads for t in ([a, b, c], [a, c, d])]
    return {"name": name, "positions": p, "triangles": tris}


def ground(size: float) -> dict:
    h = size / 2
    return {
        "name": "ground",
        "positions": [[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]],
        "triangles": [[0, 1, 2], [0, 2, 3]],
    }


def sun_dir(elevation_deg: float, azimuth_deg: float) -> list[float]:
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return [round(math.cos(e) * math.sin(a), 6), round(math.cos(e) * math.cos(a), 6), round(math.sin(e), 6)]


def valley() -> dict:
    pillars = [
        box(f"pillar{i}", (x - 1.5, y - 1.5, 0), (x + 1.5, y + 1.5, h))
        for i, (x, y, h) in enumerate(
            [(-12, 20, 14), (10, 35, 18), (-6, 60, 22), (16, 80, 26), (-20, 110, 30), (4, 150, 34)]
        )
    ]
    return {
        "version": 1,
        "camera": {
            "type": "perspective",
            "position": [0, -20, 3],
            "orientation": {"look_at": {"target": [0, 40, 8]}},
            "focal_length_mm": 35,
            "resolution": [960, 540],
        },
        "meshes": [ground(2000)] + pillars,
        "lights": [
            {
                "type": "sun",
                "name": "low sun",
                "direction_to_sun": sun_dir(12, 15),
                "color": [1.0, 0.85, 0.65],
                "strength_w_m2": 4.0,
            },
            {"type": "ambient", "name": "sky", "color": [0.55, 0.7, 1.0], "radiance": 0.08},
        ],
        "media": [
            {
                "type": "height_fog",
                "name": "valley fog",
                "scale_height_m": 12,
                "reference_height_m": 0,
                "rayleigh": {"scattering": [0.00058, 0.00135, 0.00331]},
                "mie": {"scattering": 0.012, "absorption": 0.0012, "phase": {"type": "cornette_shanks", "g": 0.76}},
            }
        ],
        "output": {"layers": ["inscatter", "transmittance", "depth", "sun_transmittance", "error"]},
    }


def fog_layer() -> dict:
    pillars = [
        box(f"tower{i}", (x - 4, y - 4, 0), (x + 4, y + 4, h))
        for i, (x, y, h) in enumerate([(-60, 150, 45), (40, 260, 80), (-20, 420, 60), (120, 600, 110)])
    ]
    return {
        "version": 1,
        "camera": {
            "type": "perspective",
            "position": [0, -30, 45],
            "orientation": {"look_at": {"target": [0, 400, 25]}},
            "focal_length_mm": 30,
            "resolution": [960, 540],
        },
        "meshes": [ground(6000)] + pillars,
        "lights": [
            {
                "type": "sun",
                "name": "morning sun",
                "direction_to_sun": sun_dir(25, 10),
                "spectrum": "solar",
                "strength_w_m2": 5.0,
            },
            {"type": "ambient", "name": "sky", "color": [0.5, 0.65, 1.0], "radiance": 0.1},
        ],
        "media": [
            {
                "type": "fog_layer",
                "name": "morning fog",
                "ground_height_m": 0,
                "top_height_m": 30,
                "extinction": 0.008,
                "phase": {"type": "nishita_hazy"},
            }
        ],
        "output": {"layers": ["inscatter", "transmittance", "depth", "sun_transmittance"]},
    }


if __name__ == "__main__":
    out = Path("examples")
    out.mkdir(exist_ok=True)
    for name, scene in [("valley_height_fog", valley()), ("fog_layer_sunrise", fog_layer())]:
        (out / f"{name}.json").write_text(json.dumps(scene, indent=1) + "\n")
        print(f"wrote examples/{name}.json")
