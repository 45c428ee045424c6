"""Tyndall's stage-light in-scatter against converged Cycles renders.

The references in ``tests/data/cycles`` were rendered by ``scripts/cycles_reference.py``
(bpy 5.0.1, CPU, 2 × 16384 samples, single scattering, black surfaces); their own
Monte Carlo noise is in ``manifest.json``. The requirement (issue 3) is a relative
RMSE ≤ 1 % over the image.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import tyndall

OpenEXR = pytest.importorskip("OpenEXR")

DATA = Path(__file__).parent / "data" / "cycles"
MANIFEST = json.loads((DATA / "manifest.json").read_text())


def read_rgb(path: Path) -> np.ndarray:
    with OpenEXR.File(str(path)) as f:
        ch = f.channels()
        if "RGB" in ch:
            return np.asarray(ch["RGB"].pixels, dtype=np.float64)
        return np.stack([np.asarray(ch[k].pixels, dtype=np.float64) for k in ("R", "G", "B")], -1)


def relative_rmse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b**2)))


def render_inscatter(name: str) -> tuple[np.ndarray, dict]:
    scene = json.loads((DATA / f"{name}.json").read_text())
    scene["output"] = dict(scene.get("output", {}), layers=["inscatter"], tolerance=1e-3)
    layers, report = tyndall.render(scene)
    return layers["inscatter"].astype(np.float64), report


@pytest.mark.parametrize(
    "name", ["spot_box_occluder", "narrow_beam_5deg", "camera_in_dense_beam", "two_coloured_spots"]
)
def test_inscatter_matches_converged_cycles(name: str, light_pixels: Callable[..., list[list[bool]]]) -> None:
    """Relative RMSE over the image, leaving out the pixels that hold a spot's
    image: there Cycles 5.0.1 loses light (its cone clip of a view ray passing
    within ~2 cm of the apex runs in 32-bit floats and comes out empty; the loss
    grows with the camera–light distance and is gone with the ray origin 0.24 m
    from the light: docs/cycles-conventions.md §2). At most two pixels per light
    are left out; both figures are printed."""
    ref = read_rgb(DATA / f"{name}.exr")
    got, report = render_inscatter(name)
    at_light = np.array(light_pixels(report, *ref.shape[:2]), dtype=bool)
    assert at_light.sum() <= 2 * max(1, len(report["stats"].get("light_images", [])))
    rmse_all = relative_rmse(got, ref)
    rmse = relative_rmse(got[~at_light], ref[~at_light])
    noise = MANIFEST["references"][name].get("noise_rel_rms", 0.0)
    print(
        f"{name}: relative RMSE {rmse:.4%} without the {at_light.sum()} light pixels, "
        f"{rmse_all:.4%} over all (reference noise {noise:.4%})"
    )
    assert rmse <= 0.01


def test_spot_with_occluder_shadow_shaft_matches_cycles() -> None:
    """Away from the light's own image (where the pixel filter integrates a 1/r
    singularity and Cycles' noise is largest) the shadow shaft of the box matches
    to well under the whole-image figure."""
    name = "spot_box_occluder"
    ref = read_rgb(DATA / f"{name}.exr")
    got, _ = render_inscatter(name)
    mask = np.ones(ref.shape[:2], dtype=bool)
    mask[3:9, 45:51] = False
    away = relative_rmse(got[mask], ref[mask])
    print(f"{name}: relative RMSE {away:.4%} outside the light's 6x6 px")
    assert away <= 0.006
