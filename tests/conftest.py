"""Shared fixtures for the Python tests of Tyndall.

Tests marked ``slow`` are skipped unless a marker expression is given on the
command line (``pytest -m slow`` runs only them, ``pytest -m "slow or not slow"``
runs everything), so that the default run stays fast.
"""

from __future__ import annotations

import copy
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
EXAMPLES_DIR = REPO_ROOT / "examples"
EXAMPLE_FILES = sorted(EXAMPLES_DIR.glob("*.json"))

SceneDict = dict[str, Any]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Skip ``slow`` tests unless the user chose tests with ``-m``."""
    if config.getoption("markexpr", default=""):
        return
    skip = pytest.mark.skip(reason="slow: run with -m slow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The repository root (where README.md and examples/ are)."""
    return REPO_ROOT


@pytest.fixture(scope="session")
def tyndall_exe() -> Path:
    """The ``tyndall`` console script installed next to the interpreter running the tests."""
    exe = Path(sys.executable).parent / "tyndall"
    if not exe.exists():
        pytest.skip(f"no tyndall script next to {sys.executable}")
    return exe


def _wall_quad(y: float, half: float = 1000.0, name: str = "wall") -> dict[str, Any]:
    """A square mesh in the plane ``Y = y`` (facing the camera at the origin), ``2·half`` wide."""
    return {
        "name": name,
        "positions": [[-half, y, -half], [half, y, -half], [half, y, half], [-half, y, half]],
        "triangles": [[0, 1, 2], [0, 2, 3]],
    }


@pytest.fixture
def example_scene() -> Callable[[str], SceneDict]:
    """Loader of a shipped example scene as a dict (a fresh copy each call), by file stem."""

    def load(name: str) -> SceneDict:
        return json.loads((EXAMPLES_DIR / f"{name}.json").read_text())

    return load


@pytest.fixture
def small_scene() -> Callable[..., SceneDict]:
    """Factory of a small, fast scene: a camera looking along +Y at a wall 30 m away in world haze."""

    base: SceneDict = {
        "version": 1,
        "camera": {
            "type": "perspective",
            "position": [0.0, 0.0, 1.5],
            "orientation": {"look_at": {"target": [0.0, 10.0, 1.5]}},
            "resolution": [40, 30],
        },
        "meshes": [_wall_quad(30.0)],
        "lights": [
            {"type": "sun", "direction_to_sun": [0.3, 0.8, 0.5], "strength_w_m2": 3.0},
            {"type": "ambient", "radiance": 0.1},
        ],
        "media": [{"type": "homogeneous", "scattering": 0.02, "absorption": 0.005}],
    }

    def make(**overrides: Any) -> SceneDict:
        scene = copy.deepcopy(base)
        scene.update(copy.deepcopy(overrides))
        return scene

    return make


def light_image_pixel_mask(report: dict[str, Any], height: int, width: int) -> list[list[bool]]:
    """True at the pixels whose square [i, i+1] × [j, j+1] holds a point light's
    image (``stats.light_images`` of a Tyndall report). There Cycles 5.0.1 loses
    light (its float32 cone clip of view rays near a spot's apex,
    docs/cycles-conventions.md §2), so the Cycles comparisons leave them out."""
    mask = [[False] * width for _ in range(height)]
    for x, y in report["stats"].get("light_images", []):
        for j in (int(y // 1) - 1, int(y // 1)):
            for i in (int(x // 1) - 1, int(x // 1)):
                if 0 <= i < width and 0 <= j < height and i <= x <= i + 1 and j <= y <= j + 1:
                    mask[j][i] = True
    return mask


@pytest.fixture(scope="session")
def light_pixels() -> Callable[[dict[str, Any], int, int], list[list[bool]]]:
    """The mask of pixels holding a light's image (see :func:`light_image_pixel_mask`)."""
    return light_image_pixel_mask
