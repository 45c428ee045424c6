"""Error against run time, log-log: one panel per benchmark JSON written by
``scripts/bench_stage_vs_cycles.py --json`` (Tyndall's tolerance sweep next to
Cycles' sample sweep, relative RMSE against the converged reference) or by
``scripts/bench_sky_sweep.py --json`` (the sky's tolerance sweep). A JSON of
``scripts/bench_stage_resolution.py`` gives one panel per scene, with a pair of
curves (Tyndall solid, Cycles dashed) per resolution.

    python scripts/plot_error_vs_time.py docs/data/narrow_beam_5deg.json ... --out docs/img/error_vs_time.png

Needs matplotlib (``pip install matplotlib``; not needed by the tests).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def plot_by_resolution(ax: plt.Axes, scene: str, rows: list[dict]) -> None:
    """Error against time at each resolution: Tyndall solid, Cycles dashed, one colour per resolution."""
    resolutions = list(dict.fromkeys(tuple(r["resolution"]) for r in rows))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, res in enumerate(resolutions):
        for renderer, style in (("Tyndall", "o-"), ("Cycles CPU", "s--")):
            pts = sorted(
                (r["seconds"], 100.0 * r["rel_rmse"])
                for r in rows
                if tuple(r["resolution"]) == res and r["renderer"] == renderer
            )
            if pts:
                label = f"{renderer.split()[0]} {res[0]}×{res[1]}"
                ax.loglog(*zip(*pts, strict=True), style, color=colours[k % len(colours)], label=label, ms=3)
    ax.axhline(1.0, color="grey", lw=0.8, ls="--")
    ax.set_title(f"{scene}: by resolution", fontsize=10)
    ax.set_xlabel("run time, s")
    ax.set_ylabel("relative RMSE vs Cycles reference, %")
    ax.grid(True, which="both", lw=0.3)
    ax.legend(fontsize=6, ncol=2)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("inputs", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--error-key", default="rel_rmse_without_light", help="which error of the rows to plot")
    args = ap.parse_args()
    data: list[dict] = []
    for p in args.inputs:
        d = json.loads(p.read_text())
        if "summary" in d:
            for scene in dict.fromkeys(str(r["scene"]) for r in d["rows"]):
                data.append({"scene": scene, "by_resolution": [r for r in d["rows"] if r["scene"] == scene]})
        else:
            data.append(d)
    fig, axes = plt.subplots(1, len(data), figsize=(4.6 * len(data), 4.0), squeeze=False)
    for ax, d in zip(axes[0], data, strict=True):
        if "by_resolution" in d:
            plot_by_resolution(ax, d["scene"], d["by_resolution"])
            continue
        renderers: dict[str, list[dict[str, float]]] = {}
        for row in d["rows"]:
            renderers.setdefault(str(row["renderer"]), []).append(row)
        for name, rows in renderers.items():
            rows = sorted(rows, key=lambda r: r["seconds"])
            key = args.error_key if args.error_key in rows[0] else "rel_rmse"
            xs = [r["seconds"] for r in rows]
            ys = [100.0 * r[key] for r in rows]
            ax.loglog(xs, ys, "o-", label=name)
            for r, x, y in zip(rows, xs, ys, strict=True):
                ax.annotate(f"{r['setting']:g}", (x, y), textcoords="offset points", xytext=(4, 3), fontsize=7)
        ax.axhline(1.0, color="grey", lw=0.8, ls="--")
        ax.set_title(str(d.get("scene", "")), fontsize=10)
        ax.set_xlabel("run time, s")
        ax.set_ylabel(str(d.get("error_label", "relative RMSE vs converged reference, %")))
        ax.grid(True, which="both", lw=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(args.out)


if __name__ == "__main__":
    main()
