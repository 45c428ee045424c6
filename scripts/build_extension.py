#!/usr/bin/env python3
"""Build the Tyndall Blender extension: dist/tyndall-<version>.zip.

    python scripts/build_extension.py [--wheel PATH] [--out dist] [--python PY]

1. Builds the abi3 wheel of the ``tyndall`` package (``pip wheel . --no-deps``; maturin, a
   few minutes of Rust compile) unless ``--wheel`` gives one.
2. Copies it into ``blender_addon/wheels/`` and rewrites the manifest's ``wheels = [...]``.
3. Runs Blender's own extension build tool, ``blender_ext.py build`` (what
   ``blender --command extension build`` runs), found in the ``bpy`` wheel under
   ``bpy/<ver>/scripts/addons_core/bl_pkg/cli/``. It only needs the standard library. Without
   bpy (or with ``--zip-only``) the archive is zipped here following the manifest rules
   (manifest at the archive root, ``paths_exclude_pattern`` honoured for the common cases).

``tyndall_usd`` is not bundled: it needs ``usd-core``, whose ``pxr`` clashes with the USD
libraries Blender links in; the add-on writes ``scene.json`` and uses Blender's own USD exporter.
"""

from __future__ import annotations

import argparse
import glob
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
import zipfile

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ADDON = os.path.join(REPO, "blender_addon")
MANIFEST = os.path.join(ADDON, "blender_manifest.toml")


def build_wheel(python: str) -> str:
    """``pip wheel`` the repository (abi3) into a temporary folder; returns the wheel path."""
    out = tempfile.mkdtemp(prefix="tyndall-wheel-")
    subprocess.run([python, "-m", "pip", "wheel", REPO, "--no-deps", "-w", out], check=True)
    wheels = glob.glob(os.path.join(out, "tyndall-*.whl"))
    if len(wheels) != 1:
        raise SystemExit(f"expected one tyndall wheel in {out}, found {wheels}")
    return wheels[0]


def place_wheel(wheel: str) -> str:
    """Copy ``wheel`` into blender_addon/wheels/ (replacing older ones) and list it in the manifest."""
    wdir = os.path.join(ADDON, "wheels")
    os.makedirs(wdir, exist_ok=True)
    for old in glob.glob(os.path.join(wdir, "tyndall-*.whl")):
        os.unlink(old)
    name = os.path.basename(wheel)
    if "abi3" not in name:
        print(f"warning: {name} is not an abi3 wheel", file=sys.stderr)
    shutil.copy2(wheel, os.path.join(wdir, name))
    text = open(MANIFEST, encoding="utf-8").read()
    new = re.sub(r"wheels = \[[^\]]*\]", f'wheels = [\n  "./wheels/{name}",\n]', text, count=1)
    if new != text:
        with open(MANIFEST, "w", encoding="utf-8") as f:
            f.write(new)
    return name


def find_blender_ext() -> str | None:
    """Path of Blender's ``blender_ext.py`` inside the installed ``bpy`` module, if any."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        return None
    for base in spec.submodule_search_locations:
        hits = glob.glob(os.path.join(base, "*", "scripts", "addons_core", "bl_pkg", "cli", "blender_ext.py"))
        if hits:
            return sorted(hits)[-1]
    return None


def zip_by_hand(out_zip: str, excludes: list[str]) -> None:
    """Fallback archive: every file of blender_addon/ except caches and excluded patterns."""
    skip_dirs = {"__pycache__", ".git", ".ruff_cache", ".pytest_cache"}
    with zipfile.ZipFile(out_zip, "w", zipfile.ZIP_DEFLATED) as z:
        for root, dirs, files in os.walk(ADDON):
            dirs[:] = [d for d in dirs if d not in skip_dirs and not d.startswith(".")]
            for f in files:
                rel = os.path.relpath(os.path.join(root, f), ADDON)
                if f.endswith((".zip", ".pyc")) or any(p.strip("/") in rel.split(os.sep) for p in excludes):
                    continue
                z.write(os.path.join(root, f), rel)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--wheel", help="use this tyndall wheel instead of building one")
    ap.add_argument("--out", default=os.path.join(REPO, "dist"), help="output folder (default dist/)")
    ap.add_argument("--python", default=sys.executable, help="Python used for pip wheel")
    ap.add_argument("--zip-only", action="store_true", help="do not use Blender's build tool")
    args = ap.parse_args(argv)

    wheel = args.wheel or build_wheel(args.python)
    name = place_wheel(wheel)
    print(f"bundled {name}")
    with open(MANIFEST, "rb") as f:
        manifest = tomllib.load(f)
    os.makedirs(args.out, exist_ok=True)
    out_zip = os.path.join(os.path.abspath(args.out), f"{manifest['id']}-{manifest['version']}.zip")
    if os.path.exists(out_zip):
        os.unlink(out_zip)
    tool = None if args.zip_only else find_blender_ext()
    if tool is not None:
        cmd = [sys.executable, tool, "build", "--source-dir", ADDON, "--output-filepath", out_zip]
        print("running", " ".join(cmd))
        subprocess.run(cmd, check=True)
        subprocess.run([sys.executable, tool, "validate", out_zip], check=True)
    else:
        print("Blender's extension build tool not found (no bpy): zipping by hand", file=sys.stderr)
        zip_by_hand(out_zip, manifest.get("build", {}).get("paths_exclude_pattern", []))
    print(out_zip)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
