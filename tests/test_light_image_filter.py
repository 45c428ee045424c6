"""The pixel filter at a spot lamp's own image, against an independent polar sum.

Where a lamp is in view, the in-scatter has a 1/ρ peak at its image inside
the beam's wedge, which near the apex can be far narrower than a pixel. The
squares of the windows that hold the image, and those near it that a beam
narrower than the lattice's cells crosses, are integrated with a polar rule
about it (``render::filter::PolarSquare``). The reference here is independent of
that rule: Tyndall's point samples (pixel filter off, each ray to 1e-7)
along straight lines through the image, one render of a 1 × N strip per
angle (a camera rolled by the angle, its lens shift putting the image at the
strip's centre), weighted by |t| · Blender's window and summed over the
angles (the Jacobian |t| cancels the peak). Its own error is taken as its
difference from the same sum at half the angles and half the samples.

Before the polar rule (the lattice's graded mesh alone), three of the nine
pixels were outside their estimates at every tolerance: 5° beam, 3.5e-6 ±
4.2e-6 against 1.98e-5; 0.5° beam, 0 ± 0 against 2.5e-7 (a pixel whose
centre samples all miss the wedge).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import tyndall

DATA = Path(__file__).parent / "data" / "cycles"
BLACKMAN_HARRIS = (0.35875, 0.48829, 0.14128, 0.01168)
# Centre samples only, each ray's integral to 1e-7.
POINT_SAMPLES = {"layers": ["inscatter"], "tolerance": 1e-7, "pixel_filter": {"type": "none"}, "spectral": "never"}


def _lamp_in_view(spot_size_deg: float) -> dict:
    """The narrow-beam scene with the camera drawn back, so that the lamp is in view."""
    scene = json.loads((DATA / "narrow_beam_5deg.json").read_text())
    scene["camera"]["position"] = [0.0, -14.0, 2.5]
    scene["lights"][0]["spot_size_deg"] = spot_size_deg
    return scene


def _window(x: np.ndarray) -> np.ndarray:
    """Blender's Blackman–Harris window, 1.5 px (unnormalised, 0 beyond its reach)."""
    t = x / 3.0 + 0.5
    a0, a1, a2, a3 = BLACKMAN_HARRIS
    w = a0 - a1 * np.cos(2 * np.pi * t) + a2 * np.cos(4 * np.pi * t) - a3 * np.cos(6 * np.pi * t)
    return np.where(np.abs(x) <= 1.5, w, 0.0)


def _polar_reference(
    scene: dict, image: tuple[float, float], pixels: list[tuple[int, int]], angles: int, samples: int
) -> dict:
    """Each pixel's filtered in-scatter from point samples on lines through `image`."""
    cam = scene["camera"]
    width, height = cam["resolution"]
    focal, sensor = cam["focal_length_mm"], cam["sensor_width_mm"]
    pixel_mm = sensor / width
    position = np.array(cam["position"], float)
    forward = np.array(cam["orientation"]["look_at"]["target"], float) - position
    forward /= np.linalg.norm(forward)
    back = -forward
    right = np.cross(np.array(cam["orientation"]["look_at"]["up"], float), back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    # The image on the view plane at unit distance (x right, y up).
    a_c = (image[0] / width - 0.5) * sensor / focal
    b_c = (0.5 - image[1] / height) * sensor * height / width / focal
    reach = 5.0  # px: the window of every pixel within 3.5 px of the image lies within it
    strip_mm = 2 * reach * pixel_mm
    t = (np.arange(samples) + 0.5 - samples / 2) * (2 * reach / samples)
    strip = json.loads(json.dumps(scene))
    strip["output"] = POINT_SAMPLES
    # The window is separable: per angle, its x factor for each column and
    # its y factor for each row of the pixels, combined in one product.
    columns = sorted({px for px, _ in pixels})
    rows = sorted({py for _, py in pixels})
    sums = np.zeros((len(rows), len(columns), 3))
    for j in range(angles):
        phi = (j + 0.5) * np.pi / angles
        # Rolled by φ, the strip's row runs along (cos φ, sin φ) in pixel coordinates (y down).
        rolled_up = np.cos(phi) * up + np.sin(phi) * right
        a = a_c * np.cos(phi) - b_c * np.sin(phi)
        b = a_c * np.sin(phi) + b_c * np.cos(phi)
        strip["camera"].update(
            sensor_width_mm=strip_mm,
            sensor_height_mm=strip_mm / samples,
            sensor_fit="horizontal",
            shift_x=a * focal / strip_mm,
            shift_y=b * focal / strip_mm,
            resolution=[samples, 1],
            orientation={"look_at": {"target": list(position + forward), "up": list(rolled_up)}},
        )
        values = tyndall.render(strip)[0]["inscatter"][0].astype(np.float64)
        x, y = image[0] + t * np.cos(phi), image[1] + t * np.sin(phi)
        wx = _window(x[None, :] - (np.array(columns)[:, None] + 0.5))
        wy = _window(y[None, :] - (np.array(rows)[:, None] + 0.5))
        weighted = wy[:, :, None] * (np.abs(t)[:, None] * values)[None, :, :]
        sums += np.einsum("ck,rkz->rcz", wx, weighted) * (2 * reach / samples) * (np.pi / angles)
    norm = (BLACKMAN_HARRIS[0] * 3.0) ** 2
    return {(px, py): sums[rows.index(py), columns.index(px)] / norm for px, py in pixels}


@pytest.mark.parametrize(("spot_size_deg", "angles"), [(0.5, 2048), (5.0, 512), (20.0, 512)])
def test_windows_near_a_lamps_image_are_within_their_estimate(spot_size_deg: float, angles: int) -> None:
    """At tolerances 0.3, 0.1 and 0.01, every channel of the 7 × 7 pixels
    around the lamp's image (the nine whose windows hold it, and those the
    beam leaves within 3.5 px of it, where the profile filter leaves them
    to the lattice) is within its error estimate of the polar sum (plus that
    sum's own error), and within the tolerance of its window.

    Before the squares a thin beam crosses near the image were polar too
    (``PolarPlan::add_thin_squares``), the 0.5° beam left pixel (14, 11),
    2.9 px from the image, at 2.27e-5 ± 2.5e-5 against 1.095e-4 (tolerance
    0.01), and pixel (13, 13) at 0 ± 0 against 8e-10 at every tolerance."""
    scene = _lamp_in_view(spot_size_deg)
    _, report = tyndall.render(dict(scene, output={"layers": ["inscatter"], "tolerance": 0.3}))
    image = tuple(report["stats"]["light_images"][0])
    x0, y0 = int(np.floor(image[0])) - 3, int(np.floor(image[1])) - 3
    pixels = [(x, y) for y in range(y0, y0 + 7) for x in range(x0, x0 + 7)]
    holding = [(x, y) for x, y in pixels if abs(image[0] - (x + 0.5)) <= 1.5 and abs(image[1] - (y + 0.5)) <= 1.5]
    assert len(holding) >= 4
    # The tolerance's scale: the brightest centre sample within ±2 px (or the pixel's own value).
    centres = tyndall.render(dict(scene, output=POINT_SAMPLES))[0]["inscatter"].astype(np.float64)
    # The 0.5° beam's wedge is ~0.01 rad wide at the image: 512 angles were
    # 25 % off the sum at 4096 there, 2048 within 0.1 %.
    fine = _polar_reference(scene, image, pixels, angles, 4000)
    coarse = _polar_reference(scene, image, pixels, angles // 2, 2000)
    for tolerance in (0.3, 0.1, 0.01):
        layers, _ = tyndall.render(
            dict(scene, output={"layers": ["inscatter", "error"], "tolerance": tolerance, "spectral": "never"})
        )
        got, estimate = layers["inscatter"].astype(np.float64), layers["error"].astype(np.float64)
        worst = 0.0
        for x, y in pixels:
            own = np.abs(fine[(x, y)] - coarse[(x, y)]) + 1e-6 * fine[(x, y)]
            error = np.abs(got[y, x] - fine[(x, y)])
            worst = max(worst, float(np.max(error / np.maximum(estimate[y, x] + own, 1e-300))))
            assert np.all(error <= estimate[y, x] + own), (
                f"{spot_size_deg}° beam, tolerance {tolerance}, pixel ({x}, {y}): "
                f"{got[y, x]} ± {estimate[y, x]} against {fine[(x, y)]}"
            )
            scale = max(float(centres[y - 2 : y + 3, x - 2 : x + 3].max()), float(fine[(x, y)].max()))
            assert np.all(error <= tolerance * scale + own)
        print(f"{spot_size_deg}° beam, tolerance {tolerance}: worst error / estimate {worst:.2f}")


def _supersampled_window(scene: dict, pixel: tuple[int, int], n: int) -> tuple[np.ndarray, np.ndarray]:
    """The pixel's window integral from an n × n midpoint grid of point samples
    (a crop camera over its 3 × 3 px window), and the same from every other
    sample (for the reference's own error)."""
    cam = scene["camera"]
    width, height = cam["resolution"]
    sensor = cam["sensor_width_mm"]
    crop_mm = 3.0 * sensor / width
    cx, cy = pixel[0] + 0.5, pixel[1] + 0.5
    crop = json.loads(json.dumps(scene))
    crop["output"] = POINT_SAMPLES
    crop["camera"].update(
        sensor_width_mm=crop_mm,
        sensor_fit="horizontal",
        resolution=[n, n],
        shift_x=(cx / width - 0.5) * sensor / crop_mm,
        shift_y=(0.5 - cy / height) * (sensor * height / width) / crop_mm,
    )
    values = tyndall.render(crop)[0]["inscatter"].astype(np.float64)
    u = -1.5 + (np.arange(n) + 0.5) * 3.0 / n
    w = np.outer(_window(u), _window(u))
    fine = (w[:, :, None] * values).sum((0, 1)) / w.sum()
    half = w[::2, ::2]
    coarse = (half[:, :, None] * values[::2, ::2]).sum((0, 1)) / half.sum()
    return fine, coarse


def test_thin_beam_beyond_the_lamps_image_within_the_estimate() -> None:
    """The 0.5° beam 6–16 px from its lamp's image, 0.1–0.2 px wide: every
    pixel of a 11 × 10 block along it within its estimate of a 384² point-
    sampled window (plus that sum's own error, and 1e-9 of the brightest
    filtered pixel within ±2 px: pixel (26, 20)'s window holds 4.6e-17 of
    it, beside pixels of 3e-5), at tolerance 0.01.

    Pixels whose windows the beam only clips at a corner have all their
    centre samples at 0, so their tolerance is relative to their own tiny
    value. The profile filter's thin-beam rule used to hand them to the
    lattice when it missed that (or when its segment held fewer than four
    nodes), and the lattice, whose corners the beam passes between, gave
    0 ± 0: pixel (25, 19) against 8.05e-9, (17, 15) against 1.83e-9."""
    scene = _lamp_in_view(0.5)
    layers, _ = tyndall.render(
        dict(scene, output={"layers": ["inscatter", "error"], "tolerance": 0.01, "spectral": "never"})
    )
    got, estimate = layers["inscatter"].astype(np.float64), layers["error"].astype(np.float64)
    outside = []
    for y in range(12, 22):
        for x in range(17, 28):
            fine, coarse = _supersampled_window(scene, (x, y), 384)
            floor = 1e-9 * float(got[y - 2 : y + 3, x - 2 : x + 3].max())
            error = np.abs(got[y, x] - fine)
            if np.any(error > estimate[y, x] + np.abs(fine - coarse) + floor):
                outside.append(((x, y), got[y, x, 0], estimate[y, x, 0], fine[0]))
    assert not outside, outside
