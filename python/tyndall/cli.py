"""The ``tyndall`` command: runs the Rust command line (same code as the cargo binary).

``tyndall render STAGE.usda --out DIR`` (also .usd, .usdc, .usdz) is handled here first:
the stage is converted with the ``tyndall_usd`` package (``pip install ./usd``; it needs
``usd-core``) into ``DIR/scene.json``, which the Rust command line renders to
``DIR/volumetrics.exr``; then ``DIR/tyndall_results.usda`` is written (sun, sky
DomeLight when the stage asks for a sky, image assets). Prims the converter cannot use
are printed and added to the report under ``usd``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
from pathlib import Path
from typing import Any

from ._native import cli_main

USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
DEFAULT_LAYERS = ["inscatter", "transmittance", "depth"]


def _is_usd_render(argv: list[str]) -> bool:
    return (
        len(argv) >= 2
        and argv[0] == "render"
        and not any(a in ("-h", "--help") for a in argv)
        and any(a.lower().endswith(USD_SUFFIXES) and not a.startswith("-") for a in argv[1:])
    )


def _usd_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tyndall render",
        description="Render a USD stage: convert it to a Tyndall scene, render it, write a USD results layer.",
    )
    p.add_argument("stage", help="USD stage (.usda, .usdc, .usd, .usdz)")
    p.add_argument("--out", required=True, help="output folder, or an .exr file (its folder gets the rest)")
    p.add_argument("--report", help="report file (JSON); default: the EXR with extension .report.json")
    p.add_argument("--preview", help="tone-mapped PNG preview")
    p.add_argument("--tolerance", help="relative tolerance (overrides tyndall:output:tolerance)")
    p.add_argument("--threads", help="worker threads, 0 = all cores")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--no-sky", action="store_true", help="do not render the sky even if the stage asks for one")
    return p


def _error(msg: str, code: int) -> int:
    print(f"tyndall: error: {msg}", file=sys.stderr)
    return code


def render_usd(argv: list[str]) -> int:
    """``tyndall render STAGE --out DIR [...]`` for a USD stage; returns the exit code."""
    args = _usd_parser().parse_args(argv)
    try:
        import tyndall_usd  # noqa: PLC0415 (optional dependency, imported only for USD stages)
    except ImportError as e:
        return _error(f"rendering a USD stage needs the tyndall-usd package and usd-core (pip install ./usd): {e}", 2)
    out = Path(args.out)
    if out.suffix.lower() == ".exr":
        out_dir, exr = out.parent, out
    else:
        out_dir, exr = out, out / "volumetrics.exr"
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        conv = tyndall_usd.convert_stage(args.stage)
    except (tyndall_usd.UsdSceneError, FileNotFoundError) as e:
        msg = str(e)
        return _error(msg if msg.startswith(args.stage) else f"{args.stage}: {msg}", 1)
    for s in conv.skipped:
        print(f"tyndall: skipped {s['prim']}: {s['reason']}", file=sys.stderr)
    for n in conv.notes:
        print(f"tyndall: note: {n}", file=sys.stderr)

    scene_path = out_dir / "scene.json"
    scene_path.write_text(json.dumps(conv.scene, indent=1) + "\n")
    cmd = ["tyndall", "render", str(scene_path), "--out", str(exr)]
    for flag in ("report", "preview", "tolerance", "threads"):
        if getattr(args, flag) is not None:
            cmd += [f"--{flag}", str(getattr(args, flag))]
    if args.quiet:
        cmd.append("--quiet")
    rc = cli_main(cmd)
    if rc != 0:
        return rc

    report = Path(args.report) if args.report else exr.with_suffix(".report.json")
    usd_info: dict[str, Any] = {"stage": os.path.abspath(args.stage), "skipped": conv.skipped, "notes": conv.notes}
    sun: dict[str, Any] | None = next((x for x in conv.scene["lights"] if x["type"] == "sun"), None)
    sky_exr: Path | None = None
    if conv.sky is not None and not args.no_sky:
        import tyndall  # noqa: PLC0415

        sky_exr = out_dir / "sky.exr"
        _, sky_report = tyndall.sky(**conv.sky.kwargs(), out=sky_exr)
        sun = sky_report["sun_lamp"]
        usd_info["sky"] = {"texture": str(sky_exr), "sun_lamp": sun}
    if report.is_file():
        data = json.loads(report.read_text())
        data["usd"] = usd_info
        report.write_text(json.dumps(data, indent=1) + "\n")

    assets: dict[str, Path | str] = {"volumetrics": exr, "scene": scene_path, "source": os.path.abspath(args.stage)}
    if report.is_file():
        assets["report"] = report
    if args.preview:
        assets["preview"] = args.preview
    if sky_exr is not None:
        assets["sky"] = sky_exr
    results = out_dir / "tyndall_results.usda"
    tyndall_usd.write_results_layer(
        results,
        sun=sun,
        sky_texture=sky_exr,
        assets=assets,
        layers=conv.scene.get("output", {}).get("layers", DEFAULT_LAYERS),
        skipped=conv.skipped,
        notes=conv.notes,
    )
    print(f"tyndall: results layer {results}", file=sys.stderr)
    return 0


def main() -> None:
    """Entry point of the ``tyndall`` console script."""
    argv = sys.argv[1:]
    if _is_usd_render(argv):
        sys.exit(render_usd(argv[1:]))
    # The Rust command line runs with the interpreter released, so Python's
    # own Ctrl-C handler (a flag checked between bytecodes) would never run:
    # Ctrl-C would leave the render going to its end. The default action
    # ends the process at once, as for any command-line program; outputs are
    # written through temporary files and renames, so none is left half
    # written.
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    sys.exit(cli_main(["tyndall", *argv]))


if __name__ == "__main__":
    main()
