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


def _inscatter_and_error(name: str, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    scene = json.loads((DATA / f"{name}.json").read_text())
    scene["output"] = dict(scene.get("output", {}), layers=["inscatter", "error"], tolerance=tolerance)
    layers, _ = tyndall.render(scene)
    return layers["inscatter"].astype(np.float64), layers["error"].astype(np.float64)


@pytest.mark.parametrize("tolerance", [0.1, 0.3])
@pytest.mark.parametrize("name", ["narrow_beam_5deg", "spot_box_occluder", "two_coloured_spots"])
def test_loose_tolerance_error_layer_bounds_a_tight_render(name: str, tolerance: float) -> None:
    """At tolerances 0.1 and 0.3 the error layer bounds the distance to a render at 1e-3
    (plus that render's own estimate) in ≥ 99 % of pixels (issue 3's criterion,
    with Tyndall itself as the independent reference, free of Monte Carlo noise).
    Pixels next to a beam's edge, where the centre sample stands, used to be
    charged their own Laplacian term only. Pixels outside their estimate, of
    5184: narrow beam 39 (24 of them claiming an error of 0 although their
    filter window reaches the beam), box occluder 48, two coloured spots 53
    (98.98 %, below the criterion).
    The term is now the largest of the 3×3 neighbourhood's, whose stencils cover
    the window; a step beside the centre (both third differences across it)
    is charged its worst case (box occluder 48 → 4); and every pixel whose
    window holds a point light's image gets the filter integral (the last 4:
    a sliver of the cone at its apex that no centre sample within reach saw,
    errors of 5.2e-4 and 4e-8 against estimates of 0).
    At 0.3 the box's shadow edge, slanted further down, crossed one pixel's
    centre part-way: one third difference was small, and the pixel was wrong
    by 3.3e-3 against an estimate of 2.3e-3; the step term now also charges
    each side's rise (render::step_beside_centre)."""
    loose, loose_err = _inscatter_and_error(name, tolerance)
    tight, tight_err = _inscatter_and_error(name, 1e-3)
    deviation = np.abs(loose - tight).max(-1)
    bound = (loose_err + tight_err).max(-1) * (1.0 + 1e-6) + 2.0**-23 * tight.max(-1)
    outside = deviation > bound
    claims_exact = outside & (loose_err.max(-1) == 0.0)
    print(f"{name}: {outside.sum()} of {outside.size} pixels outside their estimate, {claims_exact.sum()} estimated 0")
    assert outside.mean() <= 0.01
    assert outside.sum() == 0


def _render_layers(scene: dict, **output: object) -> tuple[dict, dict]:
    scene = dict(scene, output=dict(scene.get("output", {}), **output))
    return tyndall.render(scene)


@pytest.mark.parametrize(
    "name", ["narrow_beam_5deg", "spot_box_occluder", "two_coloured_spots", "composite_stage", "camera_in_dense_beam"]
)
def test_unlit_tiles_are_left_out_without_changing_a_pixel(name: str) -> None:
    """With only in-scatter layers requested, the rays of tiles whose view
    rays (padded by every pixel their results read) miss every spot's cone are
    not traced. Tracing every pixel instead (skip_unlit_tiles false) gives the
    same in-scatter, per-light and error layers bit for bit, so every left-out
    pixel is exactly 0 and none of its neighbours' filtering changed. A camera
    inside a beam has no unlit tile. With point samples the same holds for
    the layers that need the rays (transmittance, depth, surface
    transmittance): unlit tiles give them from the surface hit alone. (The
    interpolation of smooth pixels
    needs unlit tiles on when no layer needs every ray: it is off on both
    sides here, and tested below.)"""
    scene = json.loads((DATA / f"{name}.json").read_text())
    layers = ["inscatter", "inscatter_per_light", "error"]
    plain = {"tolerance": 0.05, "interpolate_smooth_pixels": False}
    skipped, report = _render_layers(scene, layers=layers, **plain)
    traced, full_report = _render_layers(scene, layers=layers, skip_unlit_tiles=False, **plain)
    assert report["stats"]["pixels_interpolated"] == 0
    assert sorted(skipped) == sorted(traced)
    for k in skipped:
        assert np.array_equal(skipped[k], traced[k]), k
    unlit = report["stats"]["pixels_unlit"]
    assert full_report["stats"]["pixels_unlit"] == 0
    left_out = [e for e in report["plan"]["left_out"] if "unlit" in e["why"]]
    if name == "camera_in_dense_beam":
        assert unlit == 0 and not left_out
    else:
        assert unlit > 0.2 * skipped["inscatter"].shape[0] * skipped["inscatter"].shape[1]
        assert left_out and str(unlit) in left_out[0]["what"]
    # Asking for a layer that needs every ray (depth) traces every pixel
    # under the pixel filter (its passes read unlit pixels as defaults) ...
    _, with_depth = _render_layers(scene, layers=["inscatter", "depth"], **plain)
    assert with_depth["stats"]["pixels_unlit"] == 0
    # ... and with point samples follows every ray only to its surface in
    # unlit tiles: transmittance, depth and each light's surface
    # transmittance are the same bits as with every ray traced in full.
    ray_layers = layers + ["transmittance", "depth", "surface_transmittance_per_light"]
    none = {"type": "none"}
    skipped, report = _render_layers(scene, layers=ray_layers, pixel_filter=none, **plain)
    traced, _ = _render_layers(scene, layers=ray_layers, pixel_filter=none, skip_unlit_tiles=False, **plain)
    assert sorted(skipped) == sorted(traced) and len(skipped) == 4 + 2 * len(scene["lights"])
    for k in skipped:
        assert np.array_equal(skipped[k], traced[k]), k
    assert (report["stats"]["pixels_unlit"] > 0) == (name != "camera_in_dense_beam")


# Sunlight through a 2 m skylight beside the narrow beam's spot.
SKYLIGHT = {
    "type": "window",
    "name": "skylight",
    "direction_to_light": [0.3, 0.2, 1.0],
    "irradiance_w_m2": 50,
    "aperture": [[-1, -1, 6], [1, -1, 6], [1, 1, 6], [-1, 1, 6]],
}


def _extreme_beam(scene: dict, case: str) -> dict:
    """The narrow beam's scene changed for one extreme case of the tests below
    (other cases leave it as it is)."""
    spot = scene["lights"][0]
    if case == "half_degree_beam":
        spot["spot_size_deg"] = 0.5
    elif case == "beam_away_from_camera":
        scene["camera"]["position"] = [-9.0, -4.0, 6.5]
        scene["camera"]["orientation"]["look_at"]["target"] = [-9.0, 4.0, 6.0]
        spot["orientation"]["look_at"]["target"] = [-9.0, 30.0, 5.0]
    elif case == "camera_beside_the_apex":
        scene["camera"]["position"] = [-9.0, 1.999, 6.0]
        scene["camera"]["orientation"]["look_at"]["target"] = [-9.0, 12.0, 6.0]
    elif case == "wide_spot_179deg":
        spot["spot_size_deg"] = 179.0
    elif case == "window_shaft":
        scene["lights"].append(dict(SKYLIGHT))
    return scene


@pytest.mark.parametrize(
    "case",
    ["half_degree_beam", "beam_away_from_camera", "camera_beside_the_apex", "wide_spot_179deg", "window_shaft"],
)
def test_unlit_tiles_on_extreme_beams(case: str) -> None:
    """The unlit-tile test on purpose at its edges: a 0.5° beam (a sliver of
    lit tiles), a beam pointing away from a camera behind the light (its cone
    still in view), the eye 1 mm beside the apex (the cone fills half the
    view), a 179° spot (wider than a hemisphere: no tile can be unlit), and a
    window light's shaft beside the beam (its prism separated like a cone).
    Every case gives the same layers bit for bit with every pixel traced."""
    scene = _extreme_beam(json.loads((DATA / "narrow_beam_5deg.json").read_text()), case)
    layers = ["inscatter", "error"]
    plain = {"tolerance": 0.05, "interpolate_smooth_pixels": False}
    skipped, report = _render_layers(scene, layers=layers, **plain)
    traced, _ = _render_layers(scene, layers=layers, skip_unlit_tiles=False, **plain)
    for k in skipped:
        assert np.isfinite(skipped[k]).all(), k
        assert np.array_equal(skipped[k], traced[k]), k
    unlit = report["stats"]["pixels_unlit"]
    lit = int((skipped["inscatter"].max(-1) > 0).sum())
    height, width = skipped["inscatter"].shape[:2]
    print(f"{case}: {unlit} unlit pixels, {lit} with in-scatter, of {height * width}")
    if case == "wide_spot_179deg":
        assert unlit == 0
    else:
        assert unlit > 0 and lit > 0


@pytest.mark.parametrize("width_px", [0.8, 1.5, 2.5])
def test_requesting_transmittance_does_not_change_the_inscatter(width_px: float) -> None:
    """Without surfaces, and with the view transmittance smooth, the in-scatter
    layer must not depend on whether the transmittance layer is requested:
    in-scatter-only renders hold T at 1, skip unlit tiles and take the
    classification's shortcut for all-zero windows, the others do none of
    that. (At width 0.8 px that shortcut once left 189 instead of 722 pixels
    filtered: its neighbours' terms read ±2 px, outside a 1 px window.)"""
    scene = json.loads((DATA / "narrow_beam_5deg.json").read_text())
    scene["meshes"] = []
    scene["camera"]["clip_end_m"] = 40.0
    pixel_filter = {"type": "blackman_harris", "width_px": width_px}
    only, only_report = _render_layers(
        scene, layers=["inscatter"], tolerance=0.1, pixel_filter=pixel_filter, interpolate_smooth_pixels=False
    )
    both, both_report = _render_layers(
        scene,
        layers=["inscatter", "transmittance"],
        tolerance=0.1,
        pixel_filter=pixel_filter,
        interpolate_smooth_pixels=False,
    )
    assert only_report["stats"]["pixels_unlit"] > 0 and both_report["stats"]["pixels_unlit"] == 0
    assert only_report["error"]["edge_pixels"] == both_report["error"]["edge_pixels"]
    assert np.array_equal(only["inscatter"], both["inscatter"])


def _scaled(name: str, scale: int) -> dict:
    scene = json.loads((DATA / f"{name}.json").read_text())
    w, h = scene["camera"]["resolution"]
    scene["camera"]["resolution"] = [w * scale, h * scale]
    return scene


@pytest.mark.parametrize(
    ("name", "scale"),
    [("narrow_beam_5deg", 4), ("two_coloured_spots", 2), ("camera_in_dense_beam", 2), ("spot_box_occluder", 2)],
)
def test_interpolated_pixels_are_within_their_estimate(name: str, scale: int) -> None:
    """Pixels interpolated where the in-scatter is smooth (render::smooth)
    against the same scene traced at every pixel to 1e-7 (no pixel filter, so
    each pixel is its centre sample): at tolerances 0.3, 0.01 and 1e-3 every
    interpolated pixel is within its error estimate (plus f32 rounding) and
    within the tolerance, and the report counts them. A box occluder shadows
    the beam: nothing is interpolated across its shadow (a ray that enters
    one of its faces' shadow pyramids is traced), but the rest of the beam is."""
    scene = _scaled(name, scale)
    exact, _ = _render_layers(
        scene, layers=["inscatter"], tolerance=1e-7, pixel_filter={"type": "none"}, interpolate_smooth_pixels=False
    )
    ref = exact["inscatter"].astype(np.float64)
    for tol in (0.3, 0.01, 1e-3):
        on, report = _render_layers(scene, layers=["inscatter", "error"], tolerance=tol, pixel_filter={"type": "none"})
        off, _ = _render_layers(
            scene, layers=["inscatter"], tolerance=tol, pixel_filter={"type": "none"}, interpolate_smooth_pixels=False
        )
        got, est = on["inscatter"].astype(np.float64), on["error"].astype(np.float64)
        changed = (on["inscatter"] != off["inscatter"]).any(-1)
        err = np.abs(got - ref)
        outside = (err > est + 2e-7 * np.abs(ref)).any(-1) & changed
        beyond_tol = (err > tol * np.abs(ref) + 2e-7 * np.abs(ref)).any(-1) & changed
        interpolated = report["stats"]["pixels_interpolated"]
        print(
            f"{name} ×{scale}, tolerance {tol}: {interpolated} interpolated, {changed.sum()} changed, "
            f"{outside.sum()} outside the estimate, {beyond_tol.sum()} beyond the tolerance"
        )
        assert outside.sum() == 0 and beyond_tol.sum() == 0
        assert np.isfinite(got).all() and np.isfinite(est).all()
        assert interpolated > 0 and changed.sum() > 0
        assert any("interpolated" in e["why"] for e in report["plan"]["left_out"])


def _faceted_sphere(centre: tuple[float, float, float], radius: float, rings: int, segments: int) -> dict:
    """A UV sphere mesh: a plane per facet, so its shadow is bounded by a
    ball, not by per-plane pyramids (render::smooth::ShadowBall)."""
    positions = [[centre[0], centre[1], centre[2] + radius], [centre[0], centre[1], centre[2] - radius]]
    for i in range(1, rings):
        theta = np.pi * i / rings
        for j in range(segments):
            phi = 2 * np.pi * j / segments
            positions.append(
                [
                    centre[0] + radius * np.sin(theta) * np.cos(phi),
                    centre[1] + radius * np.sin(theta) * np.sin(phi),
                    centre[2] + radius * np.cos(theta),
                ]
            )
    ring = lambda i, j: 2 + (i - 1) * segments + j % segments  # noqa: E731
    triangles = []
    for j in range(segments):
        triangles.append([0, ring(1, j), ring(1, j + 1)])
        triangles.append([1, ring(rings - 1, j + 1), ring(rings - 1, j)])
        for i in range(1, rings - 1):
            triangles.append([ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)])
            triangles.append([ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)])
    return {"name": "ball", "positions": positions, "triangles": triangles}


@pytest.mark.parametrize(
    ("name", "scale", "sphere", "pure"),
    [
        ("two_coloured_spots", 2, False, False),
        ("two_coloured_spots", 2, True, False),
        ("two_coloured_spots", 2, False, True),
        ("spot_box_occluder", 2, False, False),
    ],
)
def test_interpolation_with_transmittance_depth_and_per_light_layers(
    name: str, scale: int, sphere: bool, pure: bool
) -> None:
    """With layers that need every ray (transmittance, depth, each light's
    surface transmittance: the add-on's default set) and per-light
    in-scatter, smooth pixels are still interpolated: their transmittance,
    depth and surface transmittances come from their own ray (the same bits
    as with every pixel traced), the in-scatter as before, and each light's layer from its own
    samples, interpolated only where every light meets the tolerance too.
    Against every pixel traced to 1e-7: every changed pixel is within its
    estimate and the tolerance, every light's layer within the tolerance of
    that light's value, and the lights sum to the in-scatter. With a faceted
    sphere (288 planes) in both beams, its shadow is bounded by a ball: rays
    that pass clear of it are still interpolated. With pure colours (a red
    and a blue gel: channels exactly 0 on every ray of a light, whose own
    errors are 0 too) pixels are interpolated as well; before, a zero
    channel failed `error ≤ tolerance · 0` and none was."""
    scene = _scaled(name, scale)
    if pure:
        for light, colour in zip(scene["lights"], ([1.0, 0.0, 0.0], [0.0, 0.0, 1.0]), strict=True):
            light["color"] = colour
    if sphere:
        scene["meshes"].append(_faceted_sphere((0.0, 0.0, 2.5), 0.8, 12, 12))
    layers = ["inscatter", "transmittance", "depth", "error", "inscatter_per_light", "surface_transmittance_per_light"]
    none = {"type": "none"}
    exact, _ = _render_layers(
        scene, layers=layers, tolerance=1e-7, pixel_filter=none, interpolate_smooth_pixels=False
    )
    per_light = sorted(k for k in exact if k.startswith("inscatter."))
    assert len(per_light) == len(scene["lights"])
    for tol in (0.01, 1e-3):
        on, report = _render_layers(scene, layers=layers, tolerance=tol, pixel_filter=none)
        off, _ = _render_layers(scene, layers=layers, tolerance=tol, pixel_filter=none, interpolate_smooth_pixels=False)
        exact_layers = [k for k in on if not k.startswith("inscatter") and k != "error"]
        assert {"transmittance", "depth"} < set(exact_layers) and len(exact_layers) == 2 + len(scene["lights"])
        for k in exact_layers:
            assert np.array_equal(on[k], off[k]), k
        interpolated = report["stats"]["pixels_interpolated"]
        changed = (on["inscatter"] != off["inscatter"]).any(-1)
        ref = exact["inscatter"].astype(np.float64)
        got, est = on["inscatter"].astype(np.float64), on["error"].astype(np.float64)
        err = np.abs(got - ref)
        outside = (err > est + 2e-7 * np.abs(ref)).any(-1) & changed
        beyond = (err > (tol + 2e-7) * np.abs(ref)).any(-1) & changed
        light_beyond = 0
        total = np.zeros_like(got)
        for k in per_light:
            ref_k = exact[k].astype(np.float64)
            got_k = on[k].astype(np.float64)
            total += got_k
            light_changed = (on[k] != off[k]).any(-1)
            light_beyond += int(((np.abs(got_k - ref_k) > (tol + 2e-7) * np.abs(ref_k)).any(-1) & light_changed).sum())
        summed = np.abs(total - got) <= 1e-6 * np.abs(got) + 1e-30
        print(
            f"{name} ×{scale}{' + sphere' if sphere else ''}{' pure' if pure else ''}, tolerance {tol}: "
            f"{interpolated} interpolated, "
            f"{changed.sum()} changed, {outside.sum()} outside the estimate, {beyond.sum()} beyond the tolerance, "
            f"{light_beyond} per-light pixels beyond it"
        )
        assert interpolated > 0 and changed.sum() > 0
        assert outside.sum() == 0 and beyond.sum() == 0 and light_beyond == 0
        assert summed.all()
        assert np.isfinite(got).all() and np.isfinite(est).all()


@pytest.mark.parametrize("case", ["half_degree_beam", "camera_beside_the_apex", "window_shaft", "height_fog"])
def test_interpolation_on_extreme_beams(case: str) -> None:
    """Interpolation at its edges: a 0.5° beam (a sliver a few pixels wide,
    whose samples may miss it while the pixel between hits it: the pixel's own
    cone test sees it), the eye 1 mm beside the apex (the light's image in
    view: its neighbourhood is traced), a window light's shaft beside the
    beam (rays crossing its prism are traced: its edges are kinks the codes
    do not record), and the beam in height fog instead of haze. Against every
    pixel traced to 1e-7: every pixel is within its estimate."""
    scene = _extreme_beam(_scaled("narrow_beam_5deg", 2), case)
    if case == "height_fog":
        scene["media"] = [
            {
                "type": "height_fog",
                "name": "fog",
                "scale_height_m": 3.0,
                "mie": {"scattering": 0.05, "phase": {"type": "henyey_greenstein", "g": 0.5}},
            }
        ]
    exact, _ = _render_layers(
        scene, layers=["inscatter"], tolerance=1e-7, pixel_filter={"type": "none"}, interpolate_smooth_pixels=False
    )
    ref = exact["inscatter"].astype(np.float64)
    on, report = _render_layers(scene, layers=["inscatter", "error"], tolerance=0.01, pixel_filter={"type": "none"})
    got, est = on["inscatter"].astype(np.float64), on["error"].astype(np.float64)
    assert np.isfinite(got).all() and np.isfinite(est).all()
    outside = (np.abs(got - ref) > est + 2e-7 * np.abs(ref)).any(-1)
    print(f"{case}: {report['stats']['pixels_interpolated']} interpolated, {outside.sum()} outside the estimate")
    assert outside.sum() == 0
