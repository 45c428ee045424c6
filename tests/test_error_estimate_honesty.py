"""The error layer bounds the true error where the phase function varies along a long window.

Each case is one view ray (a 1×1 image looking along it) past a point light in homogeneous
haze, found by an independent sweep against a double-precision reference: with three
quadrature nodes per window first (the estimate |G3 − G1|), both rules agreed by accident
on windows up to π/2 wide, and the pixel was off by up to 472× its estimate (3e-5 relative
at tolerance 1e-6). The reference here is written from the physics, not from Tyndall's
code: single scattering of a Blender point lamp (P/(4π) W/sr) integrated in
u = atan((t − t_c)/h) (which removes the 1/r² peak) by composite Gauss–Legendre.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
import tyndall

PHASES: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    # docs/models.md: Nishita eq 4 normalised over the sphere, and Rayleigh.
    "nishita_hazy": lambda c: (1.0 + 9.0 * ((1.0 + c) / 2.0) ** 8) / (8.0 * math.pi),
    "nishita_murky": lambda c: (1.0 + 50.0 * ((1.0 + c) / 2.0) ** 32) * 33.0 / (332.0 * math.pi),
    "rayleigh": lambda c: 3.0 / (16.0 * math.pi) * (1.0 + c * c),
}

# (camera, view direction, light position, σ_s, σ_a, phase, tolerance) from the sweep.
CASES = {
    "hazy": ([-2.191, -4.563, 0.895], [0.005783471229965, 0.904088876442243, 0.427305341593029],
             [-3.123, 4.771, 4.297], 0.0035196835020510488, 0.0, "nishita_hazy", 1e-6),
    "rayleigh": ([1.103, -5.095, 0.643], [0.04000186300276, 0.90068620555193, 0.432624791343233],
                 [-1.853, -1.248, 1.081], 0.006684928692703195, 0.0013667653891159016, "rayleigh", 1e-4),
    "murky": ([0.0, -10.0, 2.0], [-0.433975929421697, 0.900098223985743, 0.038575638170818],
              [1.0, 0.0, 3.0], 0.05, 0.0, "nishita_murky", 1e-5),
}


def reference(cam: list[float], d: list[float], light: list[float], s: float, a: float, phase: str) -> float:
    """In-scatter along the ray (no surface: it rises into the sky) from a 1000 W point lamp."""
    o, v, lp = np.array(cam), np.array(d) / np.linalg.norm(d), np.array(light)
    tc = float((lp - o) @ v)
    h = float(np.linalg.norm(o + tc * v - lp))
    intensity = 1000.0 / (4.0 * math.pi)
    nodes, weights = np.polynomial.legendre.leggauss(24)
    edges = np.linspace(math.atan(-tc / h), math.pi / 2, 2001)
    total = 0.0
    for u0, u1 in zip(edges[:-1], edges[1:], strict=True):
        u = 0.5 * (u1 - u0) * nodes + 0.5 * (u0 + u1)
        t = tc + h * np.tan(u)
        r = h / np.cos(u)
        w = (o + t[:, None] * v - lp) / r[:, None]  # light → point
        cos_scatter = -(w @ v)  # between the light's travel and the way to the camera
        f = s * PHASES[phase](cos_scatter) * intensity * np.exp(-(s + a) * (t + r)) / h
        total += 0.5 * (u1 - u0) * float(weights @ f)
    return total


@pytest.mark.parametrize("case", sorted(CASES))
def test_error_layer_bounds_the_error_on_long_windows(case: str) -> None:
    cam, d, light, s, a, phase, tol = CASES[case]
    target = [c + 10.0 * x for c, x in zip(cam, d, strict=True)]
    scene = {
        "version": 1,
        "camera": {"type": "perspective", "position": cam, "resolution": [1, 1],
                   "orientation": {"look_at": {"target": target, "up": [0, 0, 1]}}},
        "lights": [{"type": "point", "position": light, "power_w": 1000}],
        "media": [{"type": "homogeneous", "scattering": s, "absorption": a, "phase": {"type": phase}}],
        "output": {"layers": ["inscatter", "error"], "tolerance": tol, "pixel_filter": {"type": "none"},
                   "spectral": "never"},
    }
    layers, _ = tyndall.render(scene)
    value, estimate = float(layers["inscatter"][0, 0, 0]), float(layers["error"][0, 0, 0])
    ref = reference(cam, d, light, s, a, phase)
    # float32 storage of the value and of the estimate
    assert abs(value - ref) <= estimate + 2.0**-23 * ref, (value, ref, estimate)
    assert abs(value - ref) <= tol * ref
