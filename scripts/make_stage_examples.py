"""Writes examples/bench/stage_four_spots.json: 4 spot lights in haze over a 10k-triangle
set piece (a UV sphere and a floor), 1920×1080 — the stage benchmark of issue 3 — and
examples/stage_four_spots.json, the same rig at 640×360 for `tyndall demo`."""

from __future__ import annotations

import json
import math
from pathlib import Path


def uv_sphere(cx: float, cy: float, cz: float, r: float, rings: int, segments: int) -> dict:
    pos = [[cx, cy, cz + r], [cx, cy, cz - r]]
    for i in range(1, rings):
        th = math.pi * i / rings
        for j in range(segments):
            ph = 2 * math.pi * j / segments
            pos.append(
                [cx + r * math.sin(th) * math.cos(ph), cy + r * math.sin(th) * math.sin(ph), cz + r * math.cos(th)]
            )
    tris = []

    def v(i: int, j: int) -> int:
        return 2 + (i - 1) * segments + (j % segments)

    for j in range(segments):
        tris.append([0, v(1, j), v(1, j + 1)])
        tris.append([1, v(rings - 1, j + 1), v(rings - 1, j)])
    for i in range(1, rings - 1):
        for j in range(segments):
            a, b, c, d = v(i, j), v(i, j + 1), v(i + 1, j), v(i + 1, j + 1)
            tris.append([a, c, b])
            tris.append([b, c, d])
    return {"name": "sphere", "positions": pos, "triangles": tris}


def main() -> None:
    sphere = uv_sphere(0.0, 0.0, 1.5, 1.0, 71, 71)  # 2·71 + 2·70·71 = 10,082 triangles
    floor = {
        "name": "floor",
        "positions": [[-30, -30, 0], [30, -30, 0], [30, 30, 0], [-30, 30, 0]],
        "triangles": [[0, 1, 2], [0, 2, 3]],
    }
    spots = []
    for k, (x, y, col) in enumerate(
        [(-3, 1, [1, 0.8, 0.6]), (3, 1, [0.6, 0.7, 1]), (-1.5, 3, [1, 0.4, 0.4]), (1.5, 3, [0.5, 1, 0.6])]
    ):
        spots.append(
            {
                "type": "spot",
                "name": f"spot{k + 1}",
                "position": [x, y, 6.0],
                "orientation": {"look_at": {"target": [0, 0, 0.5], "up": [0, 1, 0]}},
                "color": col,
                "power_w": 2000,
                "spot_size_deg": 30,
                "spot_blend": 0.2,
            }
        )
    scene = {
        "version": 1,
        "camera": {
            "type": "perspective",
            "position": [0, -12, 2.5],
            "orientation": {"look_at": {"target": [0, 0, 2.5]}},
            "focal_length_mm": 30,
            "resolution": [1920, 1080],
        },
        "meshes": [sphere, floor],
        "lights": spots,
        "media": [
            {
                "type": "homogeneous",
                "name": "haze",
                "scattering": 0.04,
                "phase": {"type": "henyey_greenstein", "g": 0.3},
                "bounds": "world",
            }
        ],
        "output": {
            "layers": ["inscatter", "transmittance", "depth", "error", "inscatter_per_light"],
            "tolerance": 1e-3,
            # The benchmark times the point-sampled render (docs/benchmarks.md).
            "pixel_filter": {"type": "none"},
        },
    }
    root = Path(__file__).resolve().parent.parent / "examples"
    out = root / "bench" / "stage_four_spots.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(scene))
    print(f"{out}: {sum(len(m['triangles']) for m in scene['meshes'])} triangles")
    # The demo's stage: the same rig with a coarser sphere, 640×360, Blender's pixel filter.
    demo = json.loads(json.dumps(scene))
    demo["meshes"][0] = uv_sphere(0.0, 0.0, 1.5, 1.0, 24, 32)
    demo["camera"]["resolution"] = [640, 360]
    demo["output"]["tolerance"] = 1e-3
    del demo["output"]["pixel_filter"]  # the demo keeps Blender's pixel filter
    (root / "stage_four_spots.json").write_text(json.dumps(demo, indent=1))
    print(f"{root / 'stage_four_spots.json'}: demo stage")


if __name__ == "__main__":
    main()
