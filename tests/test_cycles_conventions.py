"""Re-measure Cycles' light and volume conventions (docs/cycles-conventions.md).

These tests render tiny scenes with Blender Cycles (bpy 5.0.x) at low sample
counts and compare them with closed forms, through
``scripts/cycles_conventions_check.py``. They are marked ``slow`` and are
skipped unless bpy is available: either importable by the interpreter running
pytest, or through the interpreter named by the environment variable
``TYNDALL_BPY_PYTHON`` (for example ``/tmp/bpyvenv/bin/python``).

Tolerances: at 256 samples per seed the measured Monte Carlo noise of the
ratios is ≤ 0.003 (point_volume_hg, the noisiest); the tolerances are about
3–5 × the noise measured at that sample count, and far below the deviation of
the alternative conventions that each check rules out (≥ 10 %).
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
SCRIPT = REPO_ROOT / "scripts" / "cycles_conventions_check.py"
SAMPLES = 256


def _bpy_python() -> str | None:
    env = os.environ.get("TYNDALL_BPY_PYTHON")
    if env:
        return env
    if importlib.util.find_spec("bpy") is not None:
        return sys.executable
    return None


@pytest.fixture(scope="module")
def measured(tmp_path_factory: pytest.TempPathFactory) -> dict:
    py = _bpy_python()
    if py is None:
        pytest.skip("bpy is not importable (set TYNDALL_BPY_PYTHON to a Python with bpy 5.0)")
    out = tmp_path_factory.mktemp("cycles") / "conventions.json"
    subprocess.run(
        [
            py,
            str(SCRIPT),
            "--samples",
            str(SAMPLES),
            "--json",
            str(out),
            "--only",
            "point_plane",
            "spot_plane",
            "point_volume_hg",
            "spot_volume_rayleigh",
            "ies_plane",
        ],
        check=True,
        capture_output=True,
        timeout=1800,
    )
    return json.loads(out.read_text())


@pytest.mark.slow
def test_point_light_intensity_is_power_over_4pi(measured: dict) -> None:
    r = measured["point_plane"]
    assert abs(r["ratio"] - 1.0) < 1e-3
    assert all(abs(c - 1.0) < 1e-3 for c in r["ratio_rgb"])


@pytest.mark.slow
def test_pixel_centres_are_shifted_half_a_pixel(measured: dict) -> None:
    by_shift = measured["point_plane"]["pixel_rel_dev_rms_by_shift_px"]
    assert by_shift["+0.5,+0.5"] < 1e-3
    assert by_shift["+0.0,+0.0"] > 10 * by_shift["+0.5,+0.5"]


@pytest.mark.slow
def test_spot_mask_is_smoothstep_in_cosine(measured: dict) -> None:
    r = measured["spot_plane"]
    assert abs(r["ratio"] - 1.0) < 2e-3
    assert abs(r["centre_ratio"] - 1.0) < 2e-3
    assert r["pixel_rel_dev_rms"] < 0.03
    assert r["alternatives_pixel_rel_dev_rms"]["angle_linear_blend"] > 0.2


@pytest.mark.slow
def test_volume_scatter_density_colour_and_hg_sign(measured: dict) -> None:
    r = measured["point_volume_hg"]
    assert abs(r["ratio"] - 1.0) < 0.01
    assert all(abs(c - 1.0) < 0.01 for c in r["ratio_rgb"])
    assert abs(r["ratio_if_g_negated"] - 1.0) > 0.05
    assert abs(r["ratio_if_no_extinction"] - 1.0) > 0.2


@pytest.mark.slow
def test_rayleigh_spot_in_volume(measured: dict) -> None:
    r = measured["spot_volume_rayleigh"]
    assert abs(r["ratio"] - 1.0) < 0.01


@pytest.mark.slow
def test_ies_constant_and_orientation(measured: dict) -> None:
    r = measured["ies_plane"]
    assert abs(r["ratio"] - 1.0) < 1e-3
    assert r["orientation"].startswith("h=atan2(x,y)+pi") or r["orientation"].startswith("h=atan2(-x,-y)")
    assert r["pixel_rel_dev_rms"] < 5e-3
