"""EXR files written by ``tyndall.render_to_files``, read back with the independent ``OpenEXR`` package.

The composite test computes the radiance reaching the eye through a homogeneous
medium in front of a wall independently: Blender's pinhole ray per pixel (from
Cycles' view plane: focal length, sensor size and fit, shift), the distance to
the wall, and the volume rendering equation by quadrature in double precision,

    L_total = S·e^{−σ_t ℓ} + ∫ σ_s (p(μ) E T_sun(s) + L_amb) e^{−σ_t s} ds,

then checks ``S·transmittance + inscatter`` from the file against it: per centre
ray with ``pixel_filter: none``, and averaged over Cycles' Blackman–Harris pixel
filter (Blender's default) otherwise.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR
import pytest
import tyndall

SceneDict = dict[str, Any]
ALL_LAYERS = ["inscatter", "transmittance", "depth", "sun_transmittance", "error"]
RGB = ("R", "G", "B")


def _channel_names(layers: list[str]) -> set[str]:
    names: set[str] = set()
    for layer in layers:
        names |= {"depth.Z"} if layer == "depth" else {f"{layer}.{c}" for c in RGB}
    return names


def _read_exr(path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """(header, {channel name: OpenEXR.Channel}) of a single-part file."""
    exr = OpenEXR.File(str(path), separate_channels=True)
    assert len(exr.parts) == 1
    part = exr.parts[0]
    return part.header, dict(part.channels)


def _exr_layer(channels: dict[str, Any], layer: str) -> np.ndarray:
    """A layer as the API returns it: H×W×3 for RGB layers, H×W for depth."""
    if layer == "depth":
        return channels["depth.Z"].pixels
    return np.stack([channels[f"{layer}.{c}"].pixels for c in RGB], axis=-1)


# ---------------------------------------------------------------- file layout and bit-exact values


@pytest.fixture(scope="module")
def valley_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict[str, Any], SceneDict]:
    """The valley example (it requests all five layers) rendered to files once."""
    root = Path(__file__).resolve().parent.parent
    raw: SceneDict = json.loads((root / "examples" / "valley_height_fog.json").read_text())
    assert sorted(raw["output"]["layers"]) == sorted(ALL_LAYERS)
    out = tmp_path_factory.mktemp("exr") / "valley.exr"
    report_path = out.with_suffix(".report.json")
    report = tyndall.render_to_files(raw, out, report=report_path)
    return out, report_path, report, raw


def test_channel_names_types_compression_and_windows(
    valley_files: tuple[Path, Path, dict[str, Any], SceneDict],
) -> None:
    out, _, _, raw = valley_files
    width, height = raw["camera"]["resolution"]
    header, channels = _read_exr(out)
    assert set(channels) == _channel_names(ALL_LAYERS)
    assert len(channels) == 13
    for name, ch in channels.items():
        assert ch.type() == OpenEXR.FLOAT, name
        assert ch.xSampling == 1 and ch.ySampling == 1, name
        assert ch.pixels.dtype == np.float32, name
        assert ch.pixels.shape == (height, width), name
    assert header["compression"] == OpenEXR.ZIP_COMPRESSION
    assert header["lineOrder"] == OpenEXR.INCREASING_Y
    assert header["type"] == OpenEXR.scanlineimage
    for window in ("dataWindow", "displayWindow"):
        lo, hi = header[window]
        assert list(lo) == [0, 0], window
        assert list(hi) == [width - 1, height - 1], window
    assert header["pixelAspectRatio"] == 1.0


def test_exr_values_equal_render_arrays_bit_exactly(
    valley_files: tuple[Path, Path, dict[str, Any], SceneDict],
) -> None:
    out, _, _, raw = valley_files
    _, channels = _read_exr(out)
    layers, _ = tyndall.render(raw)
    assert set(layers) == set(ALL_LAYERS)
    for name, arr in layers.items():
        from_file = _exr_layer(channels, name)
        assert from_file.shape == arr.shape, name
        # Compare bit patterns: equal floats, no rounding anywhere on the way.
        np.testing.assert_array_equal(from_file.view(np.uint32), arr.view(np.uint32), err_msg=name)


def test_report_file_equals_returned_report(valley_files: tuple[Path, Path, dict[str, Any], SceneDict]) -> None:
    _, report_path, report, raw = valley_files
    assert json.loads(report_path.read_text()) == report
    assert report["resolution"] == raw["camera"]["resolution"]
    stages = [t["stage"] for t in report["timings"]]
    assert "write_exr" in stages


def test_default_layers_give_seven_channels(small_scene: Callable[..., SceneDict], tmp_path: Path) -> None:
    out = tmp_path / "nested" / "dir" / "small.exr"  # parent directories are created
    tyndall.render_to_files(small_scene(), out)
    header, channels = _read_exr(out)
    assert set(channels) == _channel_names(["inscatter", "transmittance", "depth"])
    assert header["compression"] == OpenEXR.ZIP_COMPRESSION
    # Written atomically: nothing but the file itself is left in the directory.
    assert sorted(p.name for p in out.parent.iterdir()) == ["small.exr"]


# ---------------------------------------------------------------- composite identity, independently computed

SIGMA_S = np.array([0.02, 0.03, 0.05])  # m⁻¹
SIGMA_A = np.array([0.004, 0.002, 0.01])  # m⁻¹
SIGMA_T = SIGMA_S + SIGMA_A
HG_G = 0.6
SUN_DIR = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])  # towards the sun
SUN_COLOR, SUN_STRENGTH = np.array([1.0, 0.9, 0.7]), 3.0
AMB_COLOR, AMB_RADIANCE = np.array([0.5, 0.7, 1.0]), 0.2
SURFACE = np.array([0.3, 0.5, 0.2])  # W·m⁻²·sr⁻¹ leaving the wall towards the eye
WALL_Y = 30.0
BOX_MIN, BOX_MAX = np.array([-8.0, -5.0, -2.0]), np.array([8.0, 40.0, 6.0])
FILTER_WIDTH_PX = 1.5  # Blender's default "Filter Size" (Cycles film.filter_width)

CAMERAS: dict[str, dict[str, Any]] = {
    # landscape, auto fit (sensor width spans the width), turned and tilted
    "landscape-auto": {
        "position": [0.3, 0.0, 1.5],
        "orientation": {"look_at": {"target": [2.0, 30.0, 3.0]}},
        "focal_length_mm": 35.0,
        "resolution": [24, 16],
    },
    # portrait, auto fit (sensor width spans the height), lens shift
    "portrait-auto-shift": {
        "position": [0.0, 0.0, 1.0],
        "orientation": {"look_at": {"target": [-1.0, 30.0, 1.5]}},
        "resolution": [14, 22],
        "shift_x": 0.1,
        "shift_y": -0.05,
    },
    # vertical fit with a custom sensor height
    "vertical-fit": {
        "position": [1.0, 2.0, 2.0],
        "orientation": {"look_at": {"target": [0.0, 30.0, 1.0]}},
        "focal_length_mm": 40.0,
        "sensor_height_mm": 20.0,
        "sensor_fit": "vertical",
        "resolution": [20, 15],
    },
}


def pixel_centres(cam: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Image-plane coordinates (x, y) in px from the top-left corner of the pixel centres, each H×W."""
    width, height = cam["resolution"]
    return np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)


def blender_rays(cam: dict[str, Any], x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eye (3,) and unit view directions (x.shape + (3,)) through image points (x, y), px from the top left.

    Cycles' ``blender_camera_viewplane``: the shorter side of the view plane spans
    [−1, 1] and the fitted side [−a, a] (a = the aspect ratio), shift moves it by
    2·a·shift; ``fov = 2·atan(sensor/2 / focal / a)`` maps view-plane units to the
    camera's unit-distance plane. The camera looks along its local −Z, +Y up,
    turned by a Track-To (−Z, up Y) towards the target.
    """
    width, height = cam["resolution"]
    focal = cam.get("focal_length_mm", 50.0)
    fit = cam.get("sensor_fit", "auto")
    if fit == "auto":
        horizontal, sensor = width > height, cam.get("sensor_width_mm", 36.0)
    elif fit == "horizontal":
        horizontal, sensor = True, cam.get("sensor_width_mm", 36.0)
    else:
        horizontal, sensor = False, cam.get("sensor_height_mm", 24.0)
    if horizontal:
        aspect = width / height
        xaspect, yaspect = aspect, 1.0
    else:
        aspect = height / width
        xaspect, yaspect = 1.0, aspect
    dx = 2.0 * aspect * cam.get("shift_x", 0.0)
    dy = 2.0 * aspect * cam.get("shift_y", 0.0)
    left, right, bottom, top = -xaspect + dx, xaspect + dx, -yaspect + dy, yaspect + dy
    tan_half_fov = 0.5 * sensor / focal / aspect
    sx = left + x / width * (right - left)
    sy = top - y / height * (top - bottom)  # y = 0 at the top
    local = np.stack([sx * tan_half_fov, sy * tan_half_fov, -np.ones_like(sx)], axis=-1)
    eye = np.array(cam["position"], dtype=float)
    forward = np.array(cam["orientation"]["look_at"]["target"], dtype=float) - eye
    forward /= np.linalg.norm(forward)
    cam_right = np.cross(forward, [0.0, 0.0, 1.0])
    cam_right /= np.linalg.norm(cam_right)
    cam_up = np.cross(cam_right, forward)
    world = local[..., :1] * cam_right + local[..., 1:2] * cam_up - local[..., 2:3] * forward
    return eye, world / np.linalg.norm(world, axis=-1, keepdims=True)


def henyey_greenstein(mu: np.ndarray, g: float) -> np.ndarray:
    """HG phase function, sr⁻¹, μ = cos(angle between view direction and direction to the light)."""
    return (1.0 - g * g) / (4.0 * math.pi * (1.0 + g * g - 2.0 * g * mu) ** 1.5)


def box_path_length(points: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Length of the half-lines ``points + t·direction`` (t ≥ 0) inside the box (slab method)."""
    t_near = np.zeros(points.shape[:-1])
    t_far = np.full(points.shape[:-1], np.inf)
    for i in range(3):
        if direction[i] == 0.0:
            outside = (points[..., i] < BOX_MIN[i]) | (points[..., i] > BOX_MAX[i])
            t_far = np.where(outside, -np.inf, t_far)
            continue
        a = (BOX_MIN[i] - points[..., i]) / direction[i]
        b = (BOX_MAX[i] - points[..., i]) / direction[i]
        t_near = np.maximum(t_near, np.minimum(a, b))
        t_far = np.minimum(t_far, np.maximum(a, b))
    return np.maximum(t_far - t_near, 0.0)


def reference_radiance(eye: np.ndarray, dirs: np.ndarray, box: bool) -> dict[str, np.ndarray]:
    """Per view ray (``dirs`` of shape (..., 3)): distance ℓ to the wall, T, L, sun transmittance at the wall.

    L by Gauss–Legendre quadrature (16 nodes per piece) over the part of [0, ℓ]
    inside the medium. In the box the sun's path from x(s) is the distance to the
    nearest exit plane, min_i of lines in s: the pieces end where two lines cross,
    so each piece's integrand is a smooth exponential.
    """
    ell = (WALL_Y - eye[1]) / dirs[..., 1]
    entry, leave = np.zeros_like(ell), ell.copy()
    breaks = [entry, leave]
    if box:
        for i in range(3):
            a = (BOX_MIN[i] - eye[i]) / dirs[..., i]
            b = (BOX_MAX[i] - eye[i]) / dirs[..., i]
            entry = np.maximum(entry, np.minimum(a, b))
            leave = np.minimum(leave, np.maximum(a, b))
        leave = np.maximum(leave, entry)
        # Exit distance towards the sun through plane i: (B_i − eye_i − s·dir_i)/sun_i = p_i + q_i·s.
        exit_plane = np.where(SUN_DIR > 0.0, BOX_MAX, BOX_MIN)
        p = (exit_plane - eye) / SUN_DIR
        q = -dirs / SUN_DIR
        breaks = [entry, leave]
        for i, j in ((0, 1), (0, 2), (1, 2)):
            with np.errstate(divide="ignore", invalid="ignore"):
                cross = (p[j] - p[i]) / (q[..., i] - q[..., j])
            breaks.append(np.clip(np.nan_to_num(cross, nan=0.0, posinf=0.0, neginf=0.0), entry, leave))
    cuts = np.sort(np.stack(breaks, axis=-1), axis=-1)
    nodes, weights = np.polynomial.legendre.leggauss(16)
    lo, hi = cuts[..., :-1, None], cuts[..., 1:, None]  # (..., pieces, 1)
    s = ((lo + hi) / 2 + (hi - lo) / 2 * nodes).reshape(*ell.shape, -1)
    w = ((hi - lo) / 2 * weights).reshape(*ell.shape, -1)
    points = eye + s[..., None] * dirs[..., None, :]
    sun_t = np.exp(-SIGMA_T * box_path_length(points, SUN_DIR)[..., None]) if box else 1.0
    phase = henyey_greenstein(dirs @ SUN_DIR, HG_G)[..., None, None]
    source = SIGMA_S * (phase * SUN_COLOR * SUN_STRENGTH * sun_t + AMB_COLOR * AMB_RADIANCE)
    # Attenuation from the eye: only the length inside the medium counts.
    integrand = source * np.exp(-SIGMA_T * (s - entry[..., None])[..., None])
    inscatter = np.einsum("...nc,...n->...c", integrand, w)
    transmittance = np.exp(-SIGMA_T * (leave - entry)[..., None])
    wall = eye + ell[..., None] * dirs
    sun_at_wall = np.exp(-SIGMA_T * box_path_length(wall, SUN_DIR)[..., None]) if box else np.ones_like(inscatter)
    return {"depth": ell, "transmittance": transmittance, "inscatter": inscatter, "sun_transmittance": sun_at_wall}


def blackman_harris_nodes(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (px) and normalised weights of Cycles' Blackman–Harris pixel filter along one axis.

    Cycles (``scene/film.cpp``): ``filter_table`` doubles the width for this filter,
    ``width' = 2·filter_width``, and tabulates ``filter_func_blackman_harris(x, width')``,
    w(v) = 0.35875 − 0.48829 cos v + 0.14128 cos 2v − 0.01168 cos 3v with
    v = 2π(x/width' + 1/2), for x in [0, width'/2], mirrored (``util_cdf_inverted``
    with ``make_symmetric``): the window covers |x| ≤ filter_width from the pixel
    centre, ±1.5 px for Blender's default "Filter Size" 1.50 px. Each of x and y is
    drawn from it independently, so the 2-D filter is separable. Integrated here
    with Gauss–Legendre (the window is a trigonometric polynomial: exponential
    convergence).
    """
    support = FILTER_WIDTH_PX
    t, w = np.polynomial.legendre.leggauss(n)
    x = support * t
    v = 2.0 * math.pi * (x / (2.0 * FILTER_WIDTH_PX) + 0.5)
    window = 0.35875 - 0.48829 * np.cos(v) + 0.14128 * np.cos(2 * v) - 0.01168 * np.cos(3 * v)
    weights = w * window
    return x, weights / weights.sum()


def filtered_reference(cam: dict[str, Any], box: bool, n: int = 10) -> dict[str, np.ndarray]:
    """The pixel values Blender renders: the reference radiance averaged over the separable window."""
    xc, yc = pixel_centres(cam)
    offsets, weights = blackman_harris_nodes(n)
    total: dict[str, np.ndarray] = {}
    for oy, wy in zip(offsets, weights, strict=True):
        for ox, wx in zip(offsets, weights, strict=True):
            eye, dirs = blender_rays(cam, xc + ox, yc + oy)
            for name, value in reference_radiance(eye, dirs, box).items():
                total[name] = total.get(name, 0.0) + wx * wy * value
    return total


def composite_scene(
    camera: dict[str, Any], box: bool, pixel_filter: dict[str, Any] | None, tolerance: float = 1e-6
) -> SceneDict:
    medium: dict[str, Any] = {
        "type": "homogeneous",
        "scattering": SIGMA_S.tolist(),
        "absorption": SIGMA_A.tolist(),
        "phase": {"type": "henyey_greenstein", "g": HG_G},
    }
    if box:
        medium["bounds"] = {"box": {"min": BOX_MIN.tolist(), "max": BOX_MAX.tolist()}}
    half = 1000.0
    output: dict[str, Any] = {
        "layers": ["inscatter", "transmittance", "depth", "sun_transmittance", "error"],
        "tolerance": tolerance,
    }
    if pixel_filter is not None:
        output["pixel_filter"] = pixel_filter
    return {
        "version": 1,
        "camera": {"type": "perspective", **camera},
        "meshes": [
            {
                "name": "wall",
                "positions": [
                    [-half, WALL_Y, -half],
                    [half, WALL_Y, -half],
                    [half, WALL_Y, half],
                    [-half, WALL_Y, half],
                ],
                "triangles": [[0, 1, 2], [0, 2, 3]],
            }
        ],
        "lights": [
            {
                "type": "sun",
                "direction_to_sun": SUN_DIR.tolist(),
                "color": SUN_COLOR.tolist(),
                "strength_w_m2": SUN_STRENGTH,
                # A point sun: the numpy reference evaluates the phase function in one
                # direction (a finite disc is averaged over when it matters, see core).
                "angular_diameter_deg": 0.0,
            },
            {"type": "ambient", "color": AMB_COLOR.tolist(), "radiance": AMB_RADIANCE},
        ],
        "media": [medium],
        "output": output,
    }


def _max_rel(got: np.ndarray, want: np.ndarray) -> float:
    return float(np.max(np.abs(got.astype(np.float64) - want) / np.abs(want)))


def _render_and_read(scene: SceneDict, out: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    report = tyndall.render_to_files(scene, out)
    _, channels = _read_exr(out)
    layers = {name: _exr_layer(channels, name) for name in scene["output"]["layers"]}
    return layers, report


def test_reference_quadrature_is_converged() -> None:
    """The independent reference itself: kink-aware pieces vs a dense composite rule, filter n=10 vs n=20."""
    cam = CAMERAS["landscape-auto"]
    eye, dirs = blender_rays(cam, *pixel_centres(cam))
    ref = reference_radiance(eye, dirs, box=True)
    # Dense midpoint rule over the part of the ray inside the box, ignoring the kinks,
    # for a ray that leaves the box through its top and one that reaches the wall inside it.
    for pixel, leaves_early in (((3, 5), True), ((8, 8), False)):
        one, ell = dirs[pixel], ref["depth"][pixel]
        enter = max(0.0, *np.minimum((BOX_MIN - eye) / one, (BOX_MAX - eye) / one))
        leave = min(ell, *np.maximum((BOX_MIN - eye) / one, (BOX_MAX - eye) / one))
        assert enter == 0.0 and (leave < ell) == leaves_early  # the eye is inside the box
        panels = 200_000
        s = enter + (np.arange(panels) + 0.5) / panels * (leave - enter)
        pts = eye + s[:, None] * one
        sun = np.exp(-SIGMA_T * box_path_length(pts, SUN_DIR)[:, None])
        phase = henyey_greenstein(one @ SUN_DIR, HG_G)
        source = SIGMA_S * (phase * SUN_COLOR * SUN_STRENGTH * sun + AMB_COLOR * AMB_RADIANCE)
        dense = np.sum(source * np.exp(-SIGMA_T * (s - enter)[:, None]), axis=0) * (leave - enter) / panels
        np.testing.assert_allclose(ref["inscatter"][pixel], dense, rtol=1e-8)
    # The filter integral of the smooth (world-medium) image converges exponentially.
    coarse, fine = filtered_reference(cam, box=False, n=10), filtered_reference(cam, box=False, n=20)
    for name in ("inscatter", "transmittance"):
        assert _max_rel(coarse[name], fine[name]) < 1e-7, name


@pytest.mark.parametrize("box", [False, True], ids=["world", "box"])
@pytest.mark.parametrize("camera_name", list(CAMERAS))
def test_composite_identity_point_samples(camera_name: str, box: bool, tmp_path: Path) -> None:
    """``pixel_filter: none``: each pixel is its centre ray; S·T + L equals the quadrature."""
    camera = CAMERAS[camera_name]
    layers, report = _render_and_read(composite_scene(camera, box, {"type": "none"}), tmp_path / "c.exr")
    assert report["plan"]["colour_path"] == "rgb"
    eye, dirs = blender_rays(camera, *pixel_centres(camera))
    ref = reference_radiance(eye, dirs, box)
    if box:
        # The scene exercises rays that leave the box through its sides before the wall.
        assert np.any(ref["transmittance"][..., 0] > np.exp(-SIGMA_T[0] * ref["depth"]) * 1.01)
        assert np.any(ref["sun_transmittance"][..., 0] < 1.0)

    # The depth layer is the distance along each view ray to the wall, as documented
    # (LayerKind::Depth). Note: Cycles' Depth pass is the camera-space axial depth
    # (`camera_z_depth`), which differs from this off the image centre.
    assert _max_rel(layers["depth"], ref["depth"]) < 1e-6
    # Tolerances: f32 storage rounds by ≤ 6e-8 relative; the quadrature is good to ~1e-12.
    for name in ("transmittance", "inscatter", "sun_transmittance"):
        assert _max_rel(layers[name], ref[name]) < 1e-6, name
    total = SURFACE * layers["transmittance"].astype(np.float64) + layers["inscatter"]
    total_ref = SURFACE * ref["transmittance"] + ref["inscatter"]
    assert _max_rel(total, total_ref) < 1e-6, f"max relative error {_max_rel(total, total_ref):.3e}"


@pytest.mark.parametrize("camera_name", list(CAMERAS))
def test_composite_identity_blender_pixel_filter(camera_name: str, tmp_path: Path) -> None:
    """Default (Blender) pixel filter: S·T + L equals the window-averaged quadrature, within the error layer.

    World medium only: the image is smooth, so the reference filter integral converges
    exponentially. (In the box scenes T and L have kinks along the projected box
    edges, where an independent filter integral would need the kink lines.)
    """
    camera, box = CAMERAS[camera_name], False
    layers, report = _render_and_read(composite_scene(camera, box, None), tmp_path / "c.exr")
    ref = filtered_reference(camera, box)
    total = SURFACE * layers["transmittance"].astype(np.float64) + layers["inscatter"]
    total_ref = SURFACE * ref["transmittance"] + ref["inscatter"]
    assert _max_rel(total, total_ref) < 1e-5, f"max relative error {_max_rel(total, total_ref):.3e}"
    assert _max_rel(layers["transmittance"], ref["transmittance"]) < 1e-5
    # The error layer bounds the in-scatter's deviation from the filtered value (plus f32 rounding).
    deviation = np.abs(layers["inscatter"].astype(np.float64) - ref["inscatter"])
    bound = layers["error"].astype(np.float64) * (1.0 + 1e-6) + 2.0**-23 * ref["inscatter"]
    worst = np.unravel_index(np.argmax(deviation - bound), deviation.shape)
    assert np.all(deviation <= bound), (
        f"pixel {worst}: |L − L_filtered| = {deviation[worst]:.3e} > error layer {layers['error'][worst]:.3e}"
    )
    summary = max(report["error"]["max_abs"], report["error"].get("edge_max_abs", 0.0))
    assert summary >= float(layers["error"].max()) * (1.0 - 1e-6)
