"""Error against run time for stage scenes at several resolutions: where does
Tyndall reach 1 % relative RMSE, where does Cycles, and what is the ratio?

    python scripts/bench_stage_resolution.py narrow_beam_5deg spot_box_occluder \
        --bpy-python .venv-bpy/bin/python --scales 1,2,4,8 --json docs/data/stage_resolution.json

Each scene of tests/data/cycles is rendered with its resolution multiplied by
the scale (same camera, same field of view). Scale 1 uses the stored converged
reference; larger scales render their own with scripts/cycles_reference.py
(--half: the mean of two seeds, whose difference gives the reference's own
noise, logged) into --ref-dir, which is reused on the next run. Their sample
counts are lower than the stored ones (the render time grows with the pixel
count); the reference noise is printed beside the results and enters both
renderers' errors alike.

For every scale: Tyndall's tolerance sweep (best of ``--runs``, default 3, wall times of
``tyndall.render``) and Cycles' sample sweep (render time from its own log,
CPU, 2 threads), errors against the reference over all pixels and without
the pixels whose filter window (±1.5 px) holds a point light's image: there
the 1/r peak of the in-scatter is filtered, Cycles 5.0.1 loses light within
~1–2 cm of a spot's apex (see bench_stage_vs_cycles.py and
docs/cycles-conventions.md), and its references are noisiest. The pixels
holding the image, which bench_stage_vs_cycles.py leaves out, are too few at
the larger scales: the peak spreads over the whole window. The time each needs for
1 % is interpolated log-log between the two settings that bracket 1 %; the
ratio of the two is the speed-up at equal error. A renderer whose sweep does
not bracket 1 % gets no interpolated time (reported as such).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from pathlib import Path

# numpy's BLAS threads would wait (spinning) beside the renderer's threads on
# a 2-core machine; nothing here uses BLAS.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_stage_vs_cycles import DATA, ROOT, read_rgb, rel_rmse, render_cycles, render_tyndall  # noqa: E402

TARGET = 0.01


def scaled_scene(name: str, scale: int) -> dict:
    scene = json.loads((DATA / f"{name}.json").read_text())
    w, h = scene["camera"]["resolution"]
    scene["camera"]["resolution"] = [w * scale, h * scale]
    return scene


def reference(
    name: str, scale: int, scene_path: Path, ref_dir: Path, samples: int, bpy_python: str
) -> tuple[Path, float]:
    """The reference EXR and its relative noise (RMS |A − B|/2 over the image RMS)."""
    if scale == 1:
        manifest = json.loads((DATA / "manifest.json").read_text())
        return DATA / f"{name}.exr", float(manifest["references"][name]["noise_rel_rms"])
    out = ref_dir / f"{name}_x{scale}.exr"
    log = ref_dir / f"{name}_x{scale}.ref.json"
    if not (out.exists() and log.exists()):
        if not bpy_python:
            raise SystemExit(f"{out} is missing: pass --bpy-python to render it")
        cmd = [bpy_python, str(ROOT / "scripts" / "cycles_reference.py"), str(scene_path), "--out", str(out)]
        cmd += ["--samples", str(samples), "--seed", "0", "--half", "--time-log", str(log), "--threads", "2"]
        print(f"rendering the reference {out.name} ({samples} samples) ...", flush=True)
        subprocess.run(cmd, check=True, capture_output=True)
    return out, float(json.loads(log.read_text())["noise_rel_rms"])


def light_window_mask(light_images: list[list[float]], height: int, width: int, radius: float) -> np.ndarray:
    """True except at pixels whose filter window (centre ± radius px) holds a light's image."""
    keep = np.ones((height, width), dtype=bool)
    cx = np.arange(width) + 0.5
    cy = np.arange(height) + 0.5
    for x, y in light_images:
        near = (np.abs(cy - y)[:, None] <= radius) & (np.abs(cx - x)[None, :] <= radius)
        keep &= ~near
    return keep


def time_at_target(points: list[tuple[float, float]]) -> float | None:
    """Log-log interpolation of (error, seconds) pairs at the target error."""
    pts = sorted(points, key=lambda p: -p[0])
    for (e0, t0), (e1, t1) in zip(pts, pts[1:], strict=False):
        if e0 >= TARGET >= e1 and e0 > 0 and e1 > 0 and e0 != e1:
            f = math.log(TARGET / e0) / math.log(e1 / e0)
            return math.exp(math.log(t0) + f * math.log(t1 / t0))
    return None


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("names", nargs="+")
    ap.add_argument("--bpy-python", default="")
    ap.add_argument("--scales", default="1,2,4,8")
    ap.add_argument("--tolerances", default="0.1,0.05,0.03,0.01")
    ap.add_argument("--samples", default="16,64,256,1024", help="Cycles sample counts of the sweep")
    ap.add_argument(
        "--ref-samples", default="2:16384,4:8192,8:2048", help="reference samples per scale (total of both seeds)"
    )
    ap.add_argument("--ref-dir", default=str(ROOT / ".cache" / "cycles_refs"))
    ap.add_argument("--json", default="")
    ap.add_argument("--runs", type=int, default=3, help="Tyndall: best wall time of this many renders per point")
    args = ap.parse_args()
    ref_dir = Path(args.ref_dir)
    ref_dir.mkdir(parents=True, exist_ok=True)
    ref_samples = {int(k): int(v) for k, v in (p.split(":") for p in args.ref_samples.split(","))}
    rows: list[dict[str, object]] = []
    summary: list[dict[str, object]] = []
    for name in args.names:
        for scale in [int(s) for s in args.scales.split(",")]:
            scene = scaled_scene(name, scale)
            res = scene["camera"]["resolution"]
            scene_path = ref_dir / f"{name}_x{scale}.json"
            scene_path.write_text(json.dumps(scene, indent=1))
            ref_path, ref_noise = reference(
                name, scale, scene_path, ref_dir, ref_samples.get(scale, 2048), args.bpy_python
            )
            ref = read_rgb(ref_path)
            keep = None
            tyndall_pts, cycles_pts = [], []
            for tol in [float(t) for t in args.tolerances.split(",")]:
                best, layers, report = render_tyndall(scene, tol, args.runs)
                if keep is None:
                    radius = scene.get("output", {}).get("pixel_filter", {}).get("width_px", 1.5)
                    keep = light_window_mask(report["stats"].get("light_images", []), *ref.shape[:2], radius)
                img = layers["inscatter"].astype(np.float64)
                err, err_all = rel_rmse(img, ref, keep), rel_rmse(img, ref)
                timings = {t["stage"]: t["seconds"] for t in report["timings"]}
                rows.append(
                    {"scene": name, "resolution": res, "renderer": "Tyndall", "setting": tol, "seconds": best}
                    | {"rel_rmse": err, "rel_rmse_all_pixels": err_all}
                    | {"stages": timings, "edge_pixels": report["error"]["edge_pixels"]}
                )
                tyndall_pts.append((err, best))
                print(
                    f"{name} {res[0]}x{res[1]} Tyndall tol {tol:g}: {best * 1e3:.1f} ms, {err:.3%}"
                    f" ({err_all:.3%} all pixels)",
                    flush=True,
                )
            if args.bpy_python:
                for n in [int(x) for x in args.samples.split(",")]:
                    secs, img = render_cycles(args.bpy_python, scene_path, n)
                    err, err_all = rel_rmse(img, ref, keep), rel_rmse(img, ref)
                    rows.append(
                        {"scene": name, "resolution": res, "renderer": "Cycles CPU", "setting": n, "seconds": secs}
                        | {"rel_rmse": err, "rel_rmse_all_pixels": err_all}
                    )
                    cycles_pts.append((err, secs))
                    print(
                        f"{name} {res[0]}x{res[1]} Cycles {n} samples: {secs:.2f} s, {err:.3%}"
                        f" ({err_all:.3%} all pixels)",
                        flush=True,
                    )
            t_ty, t_cy = time_at_target(tyndall_pts), time_at_target(cycles_pts)
            summary.append(
                {
                    "scene": name,
                    "resolution": res,
                    "reference_noise_rel": ref_noise,
                    "pixels_left_out": int((~keep).sum()) if keep is not None else 0,
                    "tyndall_seconds_at_1pc": t_ty,
                    "cycles_seconds_at_1pc": t_cy,
                    "ratio": t_cy / t_ty if t_ty and t_cy else None,
                }
            )
    print("\n| scene | resolution | reference noise | Tyndall at 1 % | Cycles at 1 % | ratio |")
    print("|---|---|---|---|---|---|")
    for s in summary:
        ty, cy, r = s["tyndall_seconds_at_1pc"], s["cycles_seconds_at_1pc"], s["ratio"]
        print(
            f"| {s['scene']} | {s['resolution'][0]}×{s['resolution'][1]} | {s['reference_noise_rel']:.2%} | "
            + (f"{ty * 1e3:.1f} ms" if ty else "not bracketed")
            + " | "
            + (f"{cy:.2f} s" if cy else "not bracketed")
            + " | "
            + (f"{r:.0f}×" if r else "–")
            + " |"
        )
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "summary": summary}, indent=1))


if __name__ == "__main__":
    main()
