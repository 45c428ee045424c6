"""Inputs within the documented ranges that used to end badly (found by an
adversarial sweep of `tyndall.render`): no image may leave with a NaN or ∞,
a frame too large for the machine is an error, not an abort, and a light that
contributes nothing keeps its per-light layer."""

from __future__ import annotations

import copy
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

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


def _box_arrays() -> tuple[np.ndarray, np.ndarray]:
    """A 1 m cube on the floor (8 vertices, 12 triangles) as numpy arrays."""
    v = np.array([(x, y, z) for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (0.0, 1.0)], dtype=np.float32)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    t = np.array([tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))], dtype=np.int64)
    return v, t


def test_numpy_mesh_arrays_load_as_the_same_scene() -> None:
    """Meshes given as numpy arrays skip the JSON text (a million triangles took
    seconds to print and parse) and load to the same scene as lists; numpy scalars
    and arrays elsewhere stand for numbers and lists."""
    v, t = _box_arrays()
    as_lists = spot_stage(100.0)
    as_lists["meshes"].append({"name": "box", "positions": v.tolist(), "triangles": t.tolist()})
    as_arrays = spot_stage(np.float64(100.0))
    as_arrays["meshes"].append({"name": "box", "positions": v, "triangles": t.astype(np.uint32)})
    as_arrays["lights"][0]["position"] = np.array([0, 0, 4])
    as_arrays["output"]["tolerance"] = np.float64(1e-2)
    assert tyndall.as_scene(as_arrays).to_json() == tyndall.as_scene(as_lists).to_json()
    # Fortran order and a strided view are copied into place, not misread.
    as_arrays["meshes"][1]["positions"] = np.asfortranarray(v.astype(np.float64))
    as_arrays["meshes"][1]["triangles"] = np.concatenate([t, t], axis=1)[:, :3]
    assert tyndall.as_scene(as_arrays).to_json() == tyndall.as_scene(as_lists).to_json()
    a, _ = tyndall.render(as_arrays)
    b, _ = tyndall.render(as_lists)
    assert np.array_equal(a["inscatter"], b["inscatter"])


@pytest.mark.parametrize(
    ("change", "path", "message"),
    [
        (lambda v, t: (np.where(np.arange(24).reshape(8, 3) == 7, np.nan, v), t), "meshes[1].positions[2][1]",
         "must be a finite number, got nan"),
        (lambda v, t: (v[:, :2], t), "meshes[1].positions", r"shape \(n, 3\), got shape \(8, 2\)"),
        (lambda v, t: (v, t.astype(np.float64)), "meshes[1].triangles", "expected integers"),
        (lambda v, t: (v, np.where(t == 5, -1, t)), "meshes[1].triangles[3][2]", "must be in 0..2"),
        (lambda v, t: (v.astype(bool), t), "meshes[1].positions", "expected numbers"),
        (lambda v, t: (v, np.where(t == 5, 8, t)), "meshes[1].triangles[3][2]", "8"),
    ],
)
def test_bad_numpy_mesh_arrays_name_the_field(change: Any, path: str, message: str) -> None:
    """The array path checks what the JSON loader would and names the same field
    (an index past the vertices is the loader's own check, after the arrays are in)."""
    v, t = change(*_box_arrays())
    scene = spot_stage(100.0)
    scene["meshes"].append({"name": "box", "positions": v, "triangles": t})
    with pytest.raises(tyndall.SceneFormatError, match=message) as err:
        tyndall.as_scene(scene)
    assert err.value.path == path


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


def needle_lobe_sun_scene(medium: dict, diameter_deg: float) -> dict:
    """A 2000 mm lens (1.03° across) aimed at the sun's centre through haze;
    the odd resolution puts the centre pixel's ray exactly on the sun."""
    to_sun = [0.0, 0.8, 0.6]
    return {
        "version": 1,
        "camera": {"type": "perspective", "position": [0, 0, 0], "focal_length_mm": 2000.0,
                   "orientation": {"look_at": {"target": to_sun, "up": [0, 0, 1]}}, "resolution": [25, 15]},
        "lights": [{"type": "sun", "direction_to_sun": to_sun, "strength_w_m2": 3.0,
                    "angular_diameter_deg": diameter_deg}],
        "media": [medium],
        "output": {"layers": ["inscatter", "error"], "tolerance": 1e-3, "threads": 1, "pixel_filter": {"type": "none"}},
    }


NEEDLE_MEDIA = {
    "henyey-greenstein": {"type": "homogeneous", "scattering": 0.002,
                          "bounds": {"box": {"min": [-50, -50, -50], "max": [50, 50, 50]}},
                          "phase": {"type": "henyey_greenstein", "g": 0.9999}},
    "height-fog": {"type": "height_fog", "scale_height_m": 20.0,
                   "mie": {"scattering": 0.002, "phase": {"type": "henyey_greenstein", "g": 0.999999}}},
}


def _phase_of(medium: dict) -> dict:
    return medium["phase"] if "phase" in medium else medium["mie"]["phase"]


@pytest.mark.parametrize("medium", list(NEEDLE_MEDIA))
def test_a_sun_through_a_needle_phase_lobe_finishes_and_matches_the_closed_form(medium: str) -> None:
    """HG with g = 0.9999 (lobe 1e-4 rad wide) or 0.999999 under the default
    0.526° sun used to hang averaging the lobe over the disc. Along each view
    ray the sun's phase factor is a constant, so the render divided by the same
    render with an isotropic phase is 4π·p̄(θ). At the centre pixel (θ = 0) the
    cap average of HG has a closed form, 2π∫_{cos δ}^1 p dμ / (2π(1 − cos δ)),
    and is flat (a point sun would not be: at g = 0.999999 a ray 1e-8 rad off
    the peak already changes p by 1e-4). Run in a subprocess so a regression
    times out instead of stalling the suite."""
    code = (
        "import json, sys, numpy as np, tyndall\n"
        "out = []\n"
        "for scene in json.loads(sys.argv[1]):\n"
        "    layers, report = tyndall.render(scene)\n"
        "    out.append({'inscatter': layers['inscatter'][..., 1].astype(float).tolist(),\n"
        "                'finite': bool(np.isfinite(layers['inscatter']).all()\n"
        "                               and np.isfinite(layers['error']).all()),\n"
        "                'sun_disc_rel': report['error']['sun_disc_rel'],\n"
        "                'plan': report['plan']})\n"
        "print(json.dumps(out))\n"
    )
    needle = copy.deepcopy(NEEDLE_MEDIA[medium])
    isotropic = copy.deepcopy(needle)
    _phase_of(isotropic).clear()
    _phase_of(isotropic)["type"] = "isotropic"
    scenes = [needle_lobe_sun_scene(needle, 0.526), needle_lobe_sun_scene(isotropic, 0.526)]
    run = subprocess.run([sys.executable, "-c", code, json.dumps(scenes)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    disc, flat = json.loads(run.stdout)
    assert disc["finite"] and flat["finite"]
    plan = json.dumps(disc["plan"], ensure_ascii=False)
    assert "sun disc (0.526° wide)" in plan and "tabulated at" in plan
    assert disc["sun_disc_rel"] == pytest.approx(0.25e-3)
    g = _phase_of(needle)["g"]
    delta = math.radians(0.526) / 2
    cap = 4 * math.pi * math.sin(delta / 2) ** 2
    d0 = (1 - g) ** 2 + 4 * g * math.sin(delta / 2) ** 2
    averaged = (1 - g * g) / (2 * g) * (1 / (1 - g) - 1 / math.sqrt(d0)) / cap
    phase = np.array(disc["inscatter"]) / np.array(flat["inscatter"]) / (4 * math.pi)
    # The table is good to tolerance/4; f32 storage adds ≈ 1e-7.
    assert phase[7, 12] == pytest.approx(averaged, rel=0.25e-3 + 1e-6)
    assert np.all(np.isfinite(phase)) and np.all(phase > 0)
    # Far outside the disc the average is close to the lobe's own tail.
    assert phase[0, 0] < 1e-2 * averaged


def _with_ground(half_width_m: float) -> dict:
    """The spot stage with a triangle at z = 1 whose corners are ±half_width_m away."""
    s = spot_stage(1000.0)
    r = half_width_m
    s["meshes"].append({"name": "ground", "positions": [[-r, -r, 1], [r, -r, 1], [0, r, 1]], "triangles": [[0, 1, 2]]})
    s["output"]["layers"] = ["inscatter", "depth", "error"]
    return s


def test_a_ground_triangle_beyond_the_mesh_range_is_an_error() -> None:
    """A triangle 1e17 m across lost its hits' distances to rounding (depth 0 m in 136
    of 576 pixels, in-scatter off by half the image's maximum, with an estimate of
    2.2e-6; beyond ≈ 1e120 m it was ignored altogether): vertices farther than
    MAX_MESH_COORDINATE_M (1e7 m) are a SceneFormatError naming the vertex. Within
    it, a 1e7 m ground renders as a 1e3 m one does."""
    near, _ = tyndall.render(_with_ground(1e3))
    far, report = tyndall.render(_with_ground(1e7))
    # Depth is stored as f32: two of its steps (1.2e-7 each; the hit's own rounding is ≈ 1e-9 here).
    np.testing.assert_allclose(far["depth"], near["depth"], rtol=2.5e-7)
    scale = float(near["inscatter"].max())
    assert np.abs(far["inscatter"] - near["inscatter"]).max() <= 1e-6 * scale + far["error"].max()
    assert report["warnings"] == []
    for r in (1.01e7, 1e17, 1e150):
        beyond = r"meshes\[1\]\.positions\[0\]: in world space .*beyond ±1e7 m"
        with pytest.raises(tyndall.SceneFormatError, match=beyond):
            tyndall.render(_with_ground(r))
    # Through a transform as well: 1e4 m scaled by 1e4.
    s = _with_ground(1e4)
    s["meshes"][1]["transform"] = {"scale": [1e4, 1e4, 1.0]}
    with pytest.raises(tyndall.SceneFormatError, match=r"meshes\[1\]\.positions\[0\]"):
        tyndall.render(s)


def test_lights_beyond_the_layer_cap_are_named_dark_ones_too() -> None:
    """Per-light layers stop at 16. With 10 lit and 10 dark spots, the dark ones d6–d9 got
    no layer and no warning (the count looked at the lit lights only); the warning now
    names every light without a layer."""
    def spot(name: str, x: float, power: float) -> dict:
        return {"type": "spot", "name": name, "position": [x, 0, 4], "power_w": power, "spot_size_deg": 20,
                "orientation": {"look_at": {"target": [x, 0, 0], "up": [0, 1, 0]}}}

    s = spot_stage(1000.0)
    s["lights"] = [spot(f"s{i}", -4.5 + i, 500.0) for i in range(10)] + [spot(f"d{i}", 0.0, 0.0) for i in range(10)]
    s["output"]["layers"] = ["inscatter", "inscatter_per_light"]
    layers, report = tyndall.render(s)
    per_light = sorted(k for k in layers if k.startswith("inscatter."))
    assert per_light == sorted([f"inscatter.s{i}" for i in range(10)] + [f"inscatter.d{i}" for i in range(6)])
    warnings = report["warnings"]
    assert any("20 stage lights" in w and "none for d6, d7, d8, d9;" in w for w in warnings), warnings


def test_numpy_long_double_and_bad_layer_names() -> None:
    """np.longdouble stays a numpy scalar under .item(): the dict's encoding recursed
    (RecursionError). A layer name that is not a string raised a bare TypeError."""
    s = spot_stage(1000.0)
    s["lights"][0]["power_w"] = np.longdouble(1000.0)
    a, _ = tyndall.render(s)
    b, _ = tyndall.render(spot_stage(1000.0))
    np.testing.assert_array_equal(a["inscatter"], b["inscatter"])
    with pytest.raises(tyndall.SceneFormatError, match=r"output\.layers\[1\]: a layer name is a string, got int 5"):
        tyndall.render(spot_stage(1000.0), layers=["inscatter", 5])
    with pytest.raises(tyndall.SceneFormatError, match=r"output\.layers: .*not a mapping"):
        tyndall.render(spot_stage(1000.0), layers={"inscatter": 1})
    with pytest.raises(tyndall.SceneFormatError, match=r"5e-324 is outside the allowed range"):
        s = spot_stage(1000.0)
        s["output"]["tolerance"] = 5e-324
        tyndall.render(s)


def test_a_window_beyond_the_mesh_range_is_named() -> None:
    """A window 1e300 m across said its corners 'enclose no area' (Newell's normal overflowed)."""
    s = spot_stage(1000.0)
    big = 1e300
    s["lights"].append({"type": "window", "name": "w", "direction_to_light": [0, 0.3, 1], "irradiance_w_m2": 1.0,
                        "aperture": [[-big, -big, 3], [big, -big, 3], [big, big, 3], [-big, big, 3]]})
    with pytest.raises(tyndall.SceneFormatError, match=r"lights\[1\]\.aperture\[0\]: corner beyond ±1e7 m"):
        tyndall.render(s)


def test_render_overrides_are_checked_like_the_scene() -> None:
    """``tolerance``, ``threads`` and ``layers`` given to ``render`` raise SceneFormatError
    naming the field, as the scene's own ``output`` fields do (a bare ValueError before)."""
    scene = spot_stage(500.0)
    for kwargs, path in (({"tolerance": 2.0}, "output.tolerance"), ({"layers": ["bogus"]}, "layers")):
        with pytest.raises(tyndall.SceneFormatError) as info:
            tyndall.render(scene, **kwargs)
        assert info.value.path == path, kwargs


def test_a_scene_must_be_a_json_object(tmp_path: Path) -> None:
    """serde reads a struct from an array by field order: a whole scene written as
    ``[1, {camera}, …]`` rendered. The root must be an object."""
    scene = spot_stage(500.0)
    as_array = [scene["version"], scene["camera"], scene.get("meshes", []), scene["lights"], scene["media"], {}]
    path = tmp_path / "array.json"
    path.write_text(json.dumps(as_array))
    with pytest.raises(tyndall.SceneFormatError, match="a scene is a JSON object"):
        tyndall.render(path)


def test_a_colour_times_strength_that_overflows_names_the_light() -> None:
    """Each value valid on its own, their product past f64's range: the error names the
    light's field (it was reported as an internal bug with no field)."""
    scene = spot_stage(500.0)
    sun = {"type": "sun", "direction_to_sun": [0, 1, 1], "strength_w_m2": 1e300, "color": [1e10, 1, 1]}
    scene["lights"].append(sun)
    with pytest.raises(tyndall.SceneFormatError) as info:
        tyndall.render(scene)
    assert info.value.path == "lights[1].strength_w_m2"
