#!/usr/bin/env bash
# Tyndall developer entry point: sets everything up, then runs one job.
#   bash scripts/dev.sh demo   # venv + build + `tyndall demo` into ./tyndall-demo
#   bash scripts/dev.sh test   # venv + build + fmt, clippy, cargo tests, pytest
# Needs only a Rust toolchain, Python 3.11 and pip. Idempotent; safe to re-run.
set -euo pipefail
cd "$(dirname "$0")/.."
job="${1:-}"
case "$job" in demo|test) ;; *) echo "usage: bash scripts/dev.sh demo|test" >&2; exit 2;; esac

PY="${PYTHON:-python3.11}"
command -v "$PY" >/dev/null 2>&1 || PY=python3
if [ ! -x .venv/bin/python ]; then
  echo "== creating .venv with $PY"
  "$PY" -m venv .venv
fi
VPY=.venv/bin/python
"$VPY" -m pip install --quiet --upgrade pip
echo "== building and installing tyndall (Rust core + Python package)"
"$VPY" -m pip install --quiet ".[test]"
"$VPY" -m pip install --quiet ./usd

if [ "$job" = demo ]; then
  echo "== tyndall demo"
  .venv/bin/tyndall demo --out-dir tyndall-demo
  echo "== results in ./tyndall-demo (EXR layers, PNG previews, reports)"
  exit 0
fi

echo "== cargo fmt --check"
cargo fmt --all -- --check
echo "== cargo clippy -D warnings"
cargo clippy --workspace --all-targets --quiet -- -D warnings
echo "== cargo test"
cargo test --workspace --quiet
echo "== ruff"
.venv/bin/ruff check python tests usd blender_addon scripts
echo "== headless Blender: .venv-bpy with bpy 5.0.1 from PyPI (needs numpy<2), the tyndall wheel, the extension zip"
if [ ! -x .venv-bpy/bin/python ]; then
  "$PY" -m venv .venv-bpy
fi
BPY=.venv-bpy/bin/python
"$BPY" -m pip install --quiet --upgrade pip
"$BPY" -m pip install --quiet "bpy==5.0.1" "numpy<2" "pytest>=8" "OpenEXR>=3.3"
rm -rf dist/wheels
"$VPY" -m pip wheel --quiet --no-deps . -w dist/wheels
"$BPY" -m pip install --quiet --force-reinstall --no-deps dist/wheels/tyndall-*.whl
"$BPY" scripts/build_extension.py --wheel dist/wheels/tyndall-*.whl
export TYNDALL_BPY_PYTHON="$PWD/$BPY"
export TYNDALL_USD_PYTHON="$PWD/$VPY"  # usd-core for the add-on's USD round trip (bpy has its own USD)
echo "== pytest"
.venv/bin/python -m pytest -q ${PYTEST_ARGS:-}
echo "== pytest with bpy (Blender extension)"
"$BPY" -m pytest -q tests/test_blender_addon.py ${PYTEST_ARGS:-}
