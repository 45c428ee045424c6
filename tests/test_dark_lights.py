"""A light that contributes nothing (zero power or irradiance, black colour,
zero IES strength) is left out of the computation, and the report says so,
but its per-light in-scatter layer is still there, exactly 0: a pipeline that
exported the light finds `inscatter.<light>`. (Both per-light layers used to
vanish, and with every stage light dark the report claimed the scene had none.)
"""

from __future__ import annotations

import numpy as np
import pytest
import tyndall


def stage(dark: dict) -> dict:
    spot = {"type": "spot", "name": "key", "position": [0, 0, 4], "power_w": 500, "spot_size_deg": 40,
            "orientation": {"look_at": {"target": [0, 0, 0], "up": [0, 1, 0]}}}
    return {
        "version": 1,
        "camera": {"type": "perspective", "position": [0, -8, 2],
                   "orientation": {"look_at": {"target": [0, 0, 1.5], "up": [0, 0, 1]}}, "resolution": [24, 16]},
        "meshes": [{"name": "floor", "positions": [[-9, -9, 0], [9, -9, 0], [9, 9, 0], [-9, 9, 0]],
                    "triangles": [[0, 1, 2], [0, 2, 3]]}],
        "lights": [spot, dark],
        "media": [{"type": "homogeneous", "name": "haze", "scattering": 0.05}],
        "output": {"layers": ["inscatter", "inscatter_per_light", "surface_transmittance_per_light"],
                   "tolerance": 1e-3, "threads": 1},
    }


DARK = [
    {"type": "spot", "name": "off", "position": [1, 0, 4], "power_w": 0.0, "spot_size_deg": 30},
    {"type": "point", "name": "off", "position": [1, 0, 4], "power_w": 100.0, "color": [0, 0, 0]},
    {"type": "window", "name": "off", "direction_to_light": [0, 0.3, 1], "irradiance_w_m2": 0.0,
     "aperture": [[-1, -1, 3], [1, -1, 3], [1, 1, 3], [-1, 1, 3]]},
]


@pytest.mark.parametrize("dark", DARK, ids=["zero power", "black", "zero irradiance"])
def test_a_dark_light_keeps_its_inscatter_layer_at_zero(dark: dict) -> None:
    layers, report = tyndall.render(stage(dark))
    assert "inscatter.off" in layers
    assert np.all(layers["inscatter.off"] == 0.0)
    # The lit light is unaffected and alone in the total.
    np.testing.assert_array_equal(layers["inscatter.key"], layers["inscatter"])
    assert layers["inscatter"].max() > 0.0
    assert "surface_transmittance.key" in layers
    left_out = {entry["what"]: entry["why"] for entry in report["plan"]["left_out"]}
    assert any("off" in what and "no contribution" in why for what, why in left_out.items())
    assert any(what.startswith("surface_transmittance") and "off" in what for what in left_out)


def test_every_stage_light_dark_is_not_reported_as_no_lights() -> None:
    scene = stage(DARK[0])
    scene["lights"] = [DARK[0]]
    layers, report = tyndall.render(scene)
    assert np.all(layers["inscatter.off"] == 0.0) and np.all(layers["inscatter"] == 0.0)
    whys = [entry["why"] for entry in report["plan"]["left_out"]]
    assert not any("no point, spot or window lights" in why for why in whys)
