"""Inputs within the documented ranges that used to end badly (found by an
adversarial sweep of `tyndall.render`): no image may leave with a NaN or ∞,
a frame too large for the machine is an error, not an abort, and a light that
contributes nothing keeps its per-light layer."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tyndall


def spot_stage(power_w: float, *others: dict) -> dict:
    """A 40° spot over a floor in haze, plus the lights `others`."""
    return {
        "version": 1,
        "camera": {"type": "perspective", "position": [0, -8, 2],
                   "orientation": {"look_at": {"target": [0, 0, 1.5], "up": [0, 0, 1]}}, "resolution": [32, 18]},
        "meshes": [{"name": "floor", "positions": [[-9, -9, 0], [9, -9, 0], [9, 9, 0], [-9, 9, 0]],
                    "triangles": [[0, 1, 2], [0, 2, 3]]}],
        "lights": [{"type": "spot", "name": "key", "position": [0, 0, 4], "power_w": power_w, "spot_size_deg": 40,
                    "orientation": {"look_at": {"target": [0, 0, 0], "up": [0, 1, 0]}}}, *others],
        "media": [{"type": "homogeneous", "name": "haze", "scattering": 0.03}],
        "output": {"layers": ["inscatter", "error", "inscatter_per_light", "surface_transmittance_per_light"],
                   "tolerance": 1e-2, "threads": 1},
    }


def test_strengths_beyond_f32_are_an_error_naming_the_layer() -> None:
    """A 1e45 W spot overflows f32 storage (3.4e38): the render fails with a
    message naming the layer and the cause, instead of returning ∞ and NaN
    pixels with a report that counted none."""
    with pytest.raises(tyndall.RenderFailed, match=r"inscatter layer has \d+ pixels that are not finite.*f32"):
        tyndall.render(spot_stage(1e45))


def test_large_but_representable_strengths_render_finite() -> None:
    """1e30 W is absurd but fits: finite, and linear in the power."""
    big, _ = tyndall.render(spot_stage(1e30))
    unit, _ = tyndall.render(spot_stage(1.0))
    assert np.all(np.isfinite(big["inscatter"])) and np.all(np.isfinite(big["error"]))
    lit = unit["inscatter"] > 1e-6 * unit["inscatter"].max()
    ratio = big["inscatter"][lit].astype(np.float64) / unit["inscatter"][lit]
    np.testing.assert_allclose(ratio, 1e30, rtol=1e-5)


def test_a_frame_too_large_for_memory_is_a_scene_error() -> None:
    """65536 × 65536 px is within the resolution's range but needs hundreds of
    GB: a SceneFormatError naming camera.resolution, not SIGABRT (run in a
    subprocess so that a regression cannot take the test runner down)."""
    code = (
        "import tyndall\n"
        "scene = {'version': 1, 'camera': {'type': 'equirectangular', 'position': [0, 0, 0],"
        " 'resolution': [65536, 65536]}, 'output': {'layers': ['depth'], 'threads': 1}}\n"
        "try:\n"
        "    tyndall.render(scene)\n"
        "except tyndall.SceneFormatError as e:\n"
        "    print('PATH', e.path)\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "PATH camera.resolution" in run.stdout


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf"), np.float32("nan")])
def test_non_finite_numbers_in_a_dict_name_the_field(bad: float) -> None:
    """JSON cannot hold NaN or ∞; the loader used to point at a column of the
    JSON text the dict was turned into, which the caller never wrote."""
    scene = spot_stage(100.0)
    scene["lights"][0]["position"][1] = bad
    with pytest.raises(tyndall.SceneFormatError, match="must be a finite number") as err:
        tyndall.render(scene)
    assert err.value.path == "lights[0].position[1]"


@pytest.mark.parametrize(
    ("override", "path"),
    [({"threads": -1}, "output.threads"), ({"threads": 10**20}, "output.threads"),
     ({"tolerance": "0.1"}, "output.tolerance"), ({"layers": "inscatter"}, "output.layers")],
)
def test_bad_keyword_overrides_name_the_argument(override: dict, path: str) -> None:
    """Used to raise OverflowError/TypeError without a name, or split a string of
    layers into characters (`unknown layer "i"`)."""
    with pytest.raises(tyndall.SceneFormatError) as err:
        tyndall.render(spot_stage(100.0), **override)
    assert err.value.path == path


def test_spectra_outside_rec709_are_kept_and_counted() -> None:
    """Scattering ∝ λ^20 puts the light at the red end: the spectral path's
    Rec.709 values have negative channels. They are kept (not clamped) and the
    report counts them instead of saying nothing."""
    scene = spot_stage(500.0)
    scene["media"][0]["scattering"] = {"power_law": {"at_550nm": 0.1, "exponent": 20}}
    scene["output"]["spectral"] = "auto"
    layers, report = tyndall.render(scene)
    negative = int((layers["inscatter"] < 0).any(axis=-1).sum())
    assert negative > 0
    assert any(w.startswith(f"{negative} pixels have a negative in-scatter channel") and "gamut" in w
               for w in report["warnings"])
    grey, grey_report = tyndall.render(spot_stage(500.0))
    assert not any("negative" in w for w in grey_report["warnings"])


DARK = [
    {"type": "spot", "name": "off", "position": [1, 0, 4], "power_w": 0.0, "spot_size_deg": 30},
    {"type": "point", "name": "off", "position": [1, 0, 4], "power_w": 100.0, "color": [0, 0, 0]},
    {"type": "window", "name": "off", "direction_to_light": [0, 0.3, 1], "irradiance_w_m2": 0.0,
     "aperture": [[-1, -1, 3], [1, -1, 3], [1, 1, 3], [-1, 1, 3]]},
]


@pytest.mark.parametrize("dark", DARK, ids=["zero power", "black", "zero irradiance"])
def test_a_dark_light_keeps_its_inscatter_layer_at_zero(dark: dict) -> None:
    """A light that contributes nothing (zero power or irradiance, black colour,
    zero IES strength) is left out of the computation, and the report says so,
    but `inscatter.<light>` is still there, exactly 0, for a pipeline that
    exported the light. (Both per-light layers used to vanish.)"""
    layers, report = tyndall.render(spot_stage(500.0, dark))
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
    """With every stage light dark the report used to say the scene had none."""
    scene = spot_stage(500.0)
    scene["lights"] = [DARK[0]]
    layers, report = tyndall.render(scene)
    assert np.all(layers["inscatter.off"] == 0.0) and np.all(layers["inscatter"] == 0.0)
    whys = [entry["why"] for entry in report["plan"]["left_out"]]
    assert not any("no point, spot or window lights" in why for why in whys)


UPLIGHT = str(Path(__file__).resolve().parents[1] / "core" / "tests" / "data" / "ies" / "typec_uplight_90_180.ies")


def test_an_ies_profile_dark_inside_the_cone_is_left_out_with_its_reason() -> None:
    """An uplight's file (0 below 90°) on a 40° spot pointing down emits
    nothing: the light is left out, named with the angles, and its layer is 0
    (it used to be listed as computed). The same file on a point light, which
    reaches every direction, is computed."""
    dark = {"type": "spot", "name": "off", "position": [1, 0, 4], "power_w": 800.0, "spot_size_deg": 40,
            "orientation": {"look_at": {"target": [1, 0, 0], "up": [0, 1, 0]}}, "ies": {"file": UPLIGHT}}
    layers, report = tyndall.render(spot_stage(500.0, dark))
    assert np.all(layers["inscatter.off"] == 0.0)
    whys = [e["why"] for e in report["plan"]["left_out"] if "off" in e["what"]]
    assert any("IES profile is 0 below 90.0°" in why and "20.0°" in why for why in whys), whys
    assert not any("off" in e["what"] for e in report["plan"]["computed"])
    lit = dict(dark, type="point")
    del lit["spot_size_deg"]
    layers, report = tyndall.render(spot_stage(500.0, lit))
    assert layers["inscatter.off"].max() > 0.0
