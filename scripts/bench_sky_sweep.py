"""Error against run time for the sky texture: tolerance sweep of the layered
atmosphere, each result compared pixel by pixel with a reference rendered at
tolerance 1e-6 (same model, same size): largest luminance relative error and
largest chromaticity difference Δu′v′, next to the wall time.

    python scripts/bench_sky_sweep.py [--width 2048] [--elevations 2,20,60] [--json OUT]

With ``--json`` the rows are also written for ``scripts/plot_error_vs_time.py``
(one series per sun elevation, the largest luminance error as the error).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import tyndall


def luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb[..., 0] * 0.2126 + rgb[..., 1] * 0.7152 + rgb[..., 2] * 0.0722


def uv(rgb: np.ndarray) -> np.ndarray:
    m = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
    xyz = rgb @ m.T
    d = xyz[..., 0] + 15 * xyz[..., 1] + 3 * xyz[..., 2]
    d = np.where(d > 0, d, 1.0)
    return np.stack([4 * xyz[..., 0] / d, 9 * xyz[..., 1] / d], -1)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--width", type=int, default=2048)
    ap.add_argument("--elevations", default="2,20,60")
    ap.add_argument("--tolerances", default="1e-1,3e-2,1e-2,3e-3,1e-3,3e-4")
    ap.add_argument("--json", default="", help="also write the rows to this JSON file")
    args = ap.parse_args()
    rows: list[dict[str, object]] = []
    size = f"{args.width}×{args.width // 2}"
    print(f"Sky {size}, layered atmosphere, against tolerance 1e-6 (same model)\n")
    print("| sun elevation | tolerance | wall time, s | max luminance rel. error | max Δu′v′ |")
    print("|---|---|---|---|---|")
    for elev in [float(e) for e in args.elevations.split(",")]:
        ref, _ = tyndall.sky(elev, width=args.width, tolerance=1e-6, sun_disc=False)
        ref = ref.astype(np.float64)
        lum_ref = luminance(ref)
        floor = 1e-4 * lum_ref.max()
        mask = lum_ref > floor
        for tol in [float(t) for t in args.tolerances.split(",")]:
            best = float("inf")
            for _ in range(3):
                t0 = time.perf_counter()
                img, _ = tyndall.sky(elev, width=args.width, tolerance=tol, sun_disc=False)
                best = min(best, time.perf_counter() - t0)
            img = img.astype(np.float64)
            lum_err = np.max(np.abs(luminance(img) - lum_ref)[mask] / lum_ref[mask])
            duv = np.max(np.linalg.norm(uv(img) - uv(ref), axis=-1)[mask])
            print(f"| {elev:g}° | {tol:g} | {best:.3f} | {lum_err:.2e} | {duv:.2e} |")
            row = {"renderer": f"sun {elev:g}°", "setting": tol, "seconds": best, "rel_rmse": float(lum_err)}
            rows.append(dict(row, duv=float(duv)))
    if args.json:
        label = "largest luminance error vs tolerance 1e-6, %"
        Path(args.json).write_text(json.dumps({"scene": f"sky {size}", "error_label": label, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
