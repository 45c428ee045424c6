"""Error against run time for a stage scene: Tyndall's tolerance sweep next to
Cycles' sample sweep, both measured against the converged Cycles reference in
tests/data/cycles (relative RMSE over the image).

    python scripts/bench_stage_vs_cycles.py SCENE_NAME --bpy-python /path/to/python-with-bpy
    python scripts/bench_stage_vs_cycles.py NAME --scene S.json --reference S.exr ...

Writes a markdown table to stdout, and with ``--json OUT`` the same rows as JSON
for ``scripts/plot_error_vs_time.py``. Tyndall's timings are wall times of
``tyndall.render`` (best of 3); Cycles' are the render time from its own log.

A second error column leaves out the pixels holding a point light's image
(from Tyndall's report, ``stats.light_images``). There Cycles 5.0.1 loses light:
it clips each view ray to the spot's cone in 32-bit floats, and for rays within
~1–2 cm of the apex the chord comes out empty or wrong (``spot_light_valid_ray_segment``
→ ``ray_cone_intersect``; the loss grows with the camera–light distance and vanishes
when the light's radius is ≥ 1 cm). See docs/cycles-conventions.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import tempfile
import time
from pathlib import Path

# numpy's BLAS threads would wait (spinning) beside the renderer's threads on
# a 2-core machine; nothing here uses BLAS (small renders were ~30 % slower).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import OpenEXR  # noqa: E402
import tyndall  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT / "tests" / "data" / "cycles"


def read_rgb(path: Path) -> np.ndarray:
    with OpenEXR.File(str(path)) as f:
        ch = f.channels()
        if "RGB" in ch:
            return np.asarray(ch["RGB"].pixels, dtype=np.float64)
        return np.stack([np.asarray(ch[k].pixels, dtype=np.float64) for k in ("R", "G", "B")], -1)


def rel_rmse(a: np.ndarray, b: np.ndarray, keep: np.ndarray | None = None) -> float:
    """Relative RMSE of `a` against `b` over the pixels where `keep` is true (all by default)."""
    if keep is None:
        keep = np.ones(b.shape[:2], dtype=bool)
    return float(np.sqrt(np.mean((a[keep] - b[keep]) ** 2)) / np.sqrt(np.mean(b[keep] ** 2)))


def light_pixel_mask(light_images: list[list[float]], height: int, width: int) -> np.ndarray:
    """True except at pixels whose square [i, i+1] × [j, j+1] holds a light's image."""
    keep = np.ones((height, width), dtype=bool)
    for x, y in light_images:
        for j in range(int(np.floor(y)) - 1, int(np.floor(y)) + 1):
            for i in range(int(np.floor(x)) - 1, int(np.floor(x)) + 1):
                if 0 <= i < width and 0 <= j < height and i <= x <= i + 1 and j <= y <= j + 1:
                    keep[j, i] = False
    return keep


def render_tyndall(scene: dict, tolerance: float, runs: int = 3) -> tuple[float, dict, dict]:
    """Best wall time of `runs` ``tyndall.render`` calls (in-scatter only, 2 threads), layers, report."""
    s = json.loads(json.dumps(scene))
    s["output"] = dict(s.get("output", {}), layers=["inscatter"], tolerance=tolerance, threads=2)
    best = float("inf")
    for _ in range(runs):
        t0 = time.perf_counter()
        layers, report = tyndall.render(s)
        best = min(best, time.perf_counter() - t0)
    return best, layers, report


def render_cycles(bpy_python: str, scene_path: Path, samples: int) -> tuple[float, np.ndarray]:
    """Cycles' render time (from its own log) and image, `samples` per pixel, seed 7, 2 threads."""
    with tempfile.TemporaryDirectory() as tmp:
        out, log = Path(tmp) / "c.exr", Path(tmp) / "t.json"
        cmd = [bpy_python, str(ROOT / "scripts" / "cycles_reference.py"), str(scene_path)]
        cmd += ["--out", str(out), "--samples", str(samples), "--seed", "7", "--time-log", str(log), "--threads", "2"]
        subprocess.run(cmd, check=True, capture_output=True)
        return float(json.loads(log.read_text()).get("render_seconds", float("nan"))), read_rgb(out)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("name")
    ap.add_argument("--bpy-python", default="")
    ap.add_argument("--samples", default="4,16,64,256,1024")
    ap.add_argument("--tolerances", default="1e-1,1e-2,1e-3,1e-4,1e-6")
    ap.add_argument("--scene", default="", help="scene JSON (default: tests/data/cycles/NAME.json)")
    ap.add_argument("--reference", default="", help="converged Cycles EXR (default: tests/data/cycles/NAME.exr)")
    ap.add_argument("--json", default="", help="also write the rows to this JSON file")
    args = ap.parse_args()
    rows: list[dict[str, object]] = []
    scene_path = Path(args.scene) if args.scene else DATA / f"{args.name}.json"
    ref = read_rgb(Path(args.reference) if args.reference else DATA / f"{args.name}.exr")
    scene = json.loads(scene_path.read_text())
    print(f"## {args.name}: relative RMSE against the converged Cycles reference\n")
    print("| renderer | setting | wall time, s | relative RMSE | without light pixels |")
    print("|---|---|---|---|---|")
    keep = None
    for tol in [float(t) for t in args.tolerances.split(",")]:
        best, layers, report = render_tyndall(scene, tol)
        if keep is None:
            keep = light_pixel_mask(report["stats"].get("light_images", []), *ref.shape[:2])
        img = layers["inscatter"].astype(np.float64)
        err, err_keep = rel_rmse(img, ref), rel_rmse(img, ref, keep)
        row = {"renderer": "Tyndall", "setting": tol, "seconds": best, "rel_rmse": err}
        rows.append(dict(row, rel_rmse_without_light=err_keep))
        print(f"| Tyndall | tolerance {tol:g} | {best:.3f} | {err:.3%} | {err_keep:.3%} |")
    if args.bpy_python:
        for n in [int(x) for x in args.samples.split(",")]:
            render_s, img = render_cycles(args.bpy_python, scene_path, n)
            err, err_keep = rel_rmse(img, ref), rel_rmse(img, ref, keep)
            rows.append(
                {
                    "renderer": "Cycles CPU",
                    "setting": n,
                    "seconds": render_s,
                    "rel_rmse": err,
                    "rel_rmse_without_light": err_keep,
                }
            )
            print(f"| Cycles CPU | {n} samples | {render_s:.3f} | {err:.3%} | {err_keep:.3%} |")
    if args.json:
        Path(args.json).write_text(json.dumps({"scene": args.name, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
