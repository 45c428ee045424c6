"""The sky world texture from Python and the CLI: shape, orientation, sun lamp, EXR, errors."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import tyndall


def blender_sun_direction(elevation_deg: float, rotation_deg: float) -> np.ndarray:
    """Where Blender 5.0.1's Sky Texture puts the sun, as measured by rendering it and an
    Environment Texture with the same panoramic camera (scripts/compare_blender_sky.py):
    (cos e·sin ρ, cos e·cos ρ, sin e), restated independently of the core."""
    e, r = math.radians(elevation_deg), math.radians(rotation_deg)
    return np.array([math.cos(e) * math.sin(r), math.cos(e) * math.cos(r), math.sin(e)])


def test_sky_texture_shape_colour_and_sun_lamp() -> None:
    rgb, report = tyndall.sky(30.0, 40.0, width=128)
    assert rgb.shape == (64, 128, 3) and rgb.dtype == np.float32
    assert np.isfinite(rgb).all() and (rgb >= 0).all()
    # Row 0 is the zenith: blue sky (b > r) at noon-ish elevations.
    zenith = rgb[0].mean(axis=0)
    assert zenith[2] > zenith[0] > 0
    lamp = report["sun_lamp"]
    np.testing.assert_allclose(lamp["direction_to_sun"], blender_sun_direction(30.0, 40.0), atol=1e-12)
    assert lamp["elevation_deg"] == pytest.approx(30.0, abs=1e-9)
    assert lamp["blender_sun_rotation_deg"] == pytest.approx(40.0, abs=1e-9)
    assert max(lamp["color"]) == pytest.approx(1.0) and lamp["strength_w_m2"] > 0
    assert report["interpolation_error"] <= report["tolerance"]
    left_out = " ".join(item["what"] for item in report["plan"]["left_out"])
    assert "multiple scattering" in left_out and "per-pixel integrals" in left_out


def test_sky_orientation_matches_the_environment_mapping() -> None:
    # The brightest pixel (the sun disc) sits where Cycles' direction_to_equirectangular
    # puts the sun: u = 0.5 − atan2(y, x)/2π, v = 1 − acos(z)/π (v = 0 is the bottom row).
    rgb, _ = tyndall.sky(20.0, 120.0, width=512, tolerance=1e-2)
    h, w, _ = rgb.shape
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
    j, i = np.unravel_index(np.argmax(lum[: h // 2]), lum[: h // 2].shape)
    d = blender_sun_direction(20.0, 120.0)
    u = 0.5 - math.atan2(d[1], d[0]) / (2 * math.pi)
    v = 1.0 - math.acos(d[2]) / math.pi
    assert abs((i + 0.5) / w - u) < 2.0 / w
    assert abs((j + 0.5) / h - (1.0 - v)) < 2.0 / h


def test_sky_sun_below_horizon_has_no_sun_lamp_light() -> None:
    rgb, report = tyndall.sky(-4.0, 0.0, width=64)
    assert np.isfinite(rgb).all()
    assert report["sun_lamp"]["strength_w_m2"] == 0.0
    assert rgb[:16].max() > 0  # twilight sky still lit


def test_sky_exr_is_plain_rgb(tmp_path: Path) -> None:
    out = tmp_path / "sky.exr"
    rgb, _ = tyndall.sky(45.0, 10.0, width=64, out=out)
    assert (tmp_path / "sky.report.json").exists()
    with OpenEXR.File(str(out)) as f:
        assert len(f.parts) == 1
        assert sorted(c.name for c in f.header()["channels"]) == ["B", "G", "R"]
        # The OpenEXR package groups plain R, G, B into one H×W×3 array.
        np.testing.assert_array_equal(f.channels()["RGB"].pixels, rgb)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"sun_elevation_deg": 95.0}, "sun_elevation_deg"),
        ({"sun_elevation_deg": 10.0, "ozone": -1.0}, "ozone"),
        ({"sun_elevation_deg": 10.0, "sun_size_deg": 100.0}, "sun_size_deg"),
        ({"sun_elevation_deg": 10.0, "width": -5}, "width"),
        ({"sun_elevation_deg": 10.0, "tolerance": 2.0}, "tolerance"),
    ],
)
def test_sky_rejects_bad_parameters_naming_the_field(kwargs: dict[str, float], field: str) -> None:
    """Errors name the keyword the caller gave, in its units (the elevation's message once
    named ``sun_elevation_rad`` in radians; a negative width raised OverflowError)."""
    with pytest.raises(tyndall.SceneFormatError) as info:
        tyndall.sky(**kwargs)  # type: ignore[arg-type]
    assert info.value.path == field
    if field.endswith("_deg"):
        assert "degrees" in str(info.value)


def test_sky_output_path_is_checked_before_the_sky_is_computed(tmp_path: Path) -> None:
    """``out`` must end in .exr (EXR bytes were written into a .png), and a missing folder
    is created (it failed only after the whole sky was computed)."""
    with pytest.raises(tyndall.RenderFailed, match=r"\.exr"):
        tyndall.sky(10.0, width=16, out=tmp_path / "sky.png")
    assert not (tmp_path / "sky.png").exists()
    deep = tmp_path / "a" / "b" / "sky.exr"
    tyndall.sky(10.0, width=16, out=deep)
    assert deep.exists() and deep.with_suffix(".report.json").exists()


def test_a_sky_too_large_for_memory_is_a_parameter_error() -> None:
    """65536 px wide is within the width's range but needs 25.8 GB: a SceneFormatError
    naming ``width`` before any work, not an abort (in a subprocess with 4 GB of address
    space, so that the outcome does not depend on the machine, and a regression cannot take
    the test runner down)."""
    code = (
        "import resource, tyndall\n"
        "resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))\n"
        "try:\n"
        "    tyndall.sky(10.0, width=65536)\n"
        "except tyndall.SceneFormatError as e:\n"
        "    print('PATH', e.path)\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "PATH width" in run.stdout


def test_sky_cli(tmp_path: Path, tyndall_exe: Path) -> None:
    out = tmp_path / "sky.exr"
    r = subprocess.run(
        [str(tyndall_exe), "sky", "--sun-elevation", "-2", "--sun-azimuth", "30", "--width", "64", "--out", str(out)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert r.returncode == 0, r.stderr
    assert out.exists() and out.with_suffix(".report.json").exists()
    bad = subprocess.run(
        [str(tyndall_exe), "sky", "--sun-elevation", "100", "--out", str(tmp_path / "x.exr")],
        capture_output=True,
        text=True,
        check=False,
    )
    assert bad.returncode == 1 and "--sun-elevation: must be within -90..=90 degrees, got 100" in bad.stderr
    assert not (tmp_path / "x.exr").exists()
    klassen = tmp_path / "klassen.exr"
    r = subprocess.run(
        [
            str(tyndall_exe),
            "sky",
            "--model",
            "klassen",
            "--sun-elevation",
            "15",
            "--width",
            "64",
            "--out",
            str(klassen),
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert r.returncode == 0, r.stderr
    assert '"model": "klassen"' in klassen.with_suffix(".report.json").read_text()
    bad = subprocess.run(
        [
            str(tyndall_exe),
            "sky",
            "--model",
            "klassen",
            "--sun-elevation",
            "15",
            "--visibility=-5",
            "--out",
            str(klassen),
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert bad.returncode == 1 and "visibility_m" in bad.stderr


def test_sky_multiple_scattering_is_optional_and_adds_light() -> None:
    single, rep1 = tyndall.sky(10.0, 0.0, width=64, sun_disc=False)
    multi, rep2 = tyndall.sky(10.0, 0.0, width=64, sun_disc=False, multiple_scattering=True)
    assert rep1["multiple_scattering"] is False and rep2["multiple_scattering"] is True
    assert np.isfinite(multi).all()
    lum = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
    y1, y2 = single @ lum, multi @ lum
    assert (y2 >= y1 - 2e-3 * np.maximum(y1, 1e-4 * y1.max())).all()
    computed = " ".join(item["what"] for item in rep2["plan"]["computed"])
    assert "multiple scattering (approximation)" in computed


def _pixel_solid_angles(height: int, width: int) -> np.ndarray:
    """Exact solid angle of each row's pixels of an equirectangular texture, sr."""
    theta = np.pi * np.arange(height + 1) / height
    return (np.cos(theta[:-1]) - np.cos(theta[1:])) * 2 * np.pi / width


@pytest.mark.parametrize("width", [64, 256, 1024])
def test_the_sun_disc_carries_the_sun_lamps_irradiance(width: int) -> None:
    """The radiance the disc adds, integrated over the pixels' exact solid angles, equals the
    lamp's RGB irradiance: it was 6.3× too bright with the sun at the zenith at 256 px (the
    subsamples were weighted alike in pixel coordinates, not by solid angle), and absent at
    64 px (the disc fell between every subsample)."""
    for elevation in (90.0, 89.8, 45.0, 10.0):
        with_disc, report = tyndall.sky(elevation, 30.0, width=width)
        without, _ = tyndall.sky(elevation, 30.0, width=width, sun_disc=False)
        omega = _pixel_solid_angles(width // 2, width)[:, None]
        painted = [((with_disc[..., c].astype(np.float64) - without[..., c]) * omega).sum() for c in range(3)]
        lamp = report["sun_lamp"]["rgb_irradiance_w_m2"]
        np.testing.assert_allclose(painted, lamp, rtol=1e-5, err_msg=f"{width} px, {elevation}°")


def test_the_setting_sun_shines_above_the_horizon_only() -> None:
    """With the sun's centre on the horizon, half its disc is set: nothing is painted below
    the horizon (half the disc's light was drawn onto the ground), and the lamp carries what
    is painted above it. Just above, the whole disc shines again."""
    for width in (16, 64, 512):  # (at 16 and 64 px the disc falls between every subsample)
        omega = _pixel_solid_angles(width // 2, width)[:, None]
        irradiance = {}
        for elevation in (0.0, 0.3):
            with_disc, report = tyndall.sky(elevation, 0.0, width=width)
            without, _ = tyndall.sky(elevation, 0.0, width=width, sun_disc=False)
            disc = (with_disc[..., 0].astype(np.float64) - without[..., 0]) * omega
            lamp = report["sun_lamp"]["rgb_irradiance_w_m2"][0]
            assert disc[width // 4 :].sum() == 0.0, width  # rows below the horizon
            assert disc[: width // 4].sum() == pytest.approx(lamp, rel=1e-5), width
            irradiance[elevation] = lamp
        assert 0.0 < irradiance[0.0] < 0.6 * irradiance[0.3]


def test_a_low_suns_colours_are_brought_into_rec709() -> None:
    """A deep-red low sun lies outside Rec.709: its blue came out negative in the lamp
    (−1.9 W·m⁻²) and down to −5924 W·m⁻²·sr⁻¹ in the texture, which Cycles would emit as
    negative light. Every pixel and the lamp are now ≥ 0, at the same luminance."""
    for elevation in (0.0, 1.0, 3.0):
        rgb, report = tyndall.sky(elevation, 0.0, width=128)
        assert rgb.min() >= 0.0, elevation
        assert min(report["sun_lamp"]["rgb_irradiance_w_m2"]) >= 0.0, elevation
    rgb, report = tyndall.sky(1.0, 0.0, width=128)
    assert any(c["what"] == "colours outside Rec.709" for c in report["plan"]["computed"])
