"""Nishita's daisy and polka-dot distributions (eqs 8–10) against an
independent brute force along one view ray.

With a negative minimum ratio p the pattern is 0 over most of each period
(eq 8's triangle wave clamped at 0) and lit only on slivers. A quadrature
whose nodes all fall where the pattern is 0 returns 0 with an estimate of 0:
at p ≤ −6 a daisy rendered exactly 0 against 4.0e-4 by brute force (found by
an adversarial sweep). The renderer now cuts rays at the pattern's kinks
(period boundaries, troughs, and where the clamp starts and ends), so every
quadrature window is smooth.

The brute force is a midpoint sum of the documented D(θ, φ) (docs/scene-format.md)
over the ray in the light's frame, at N and 2N points: its own error is
bounded by their difference (the sum converges as O(h) at the pattern's jumps
and kinks).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import tyndall

SIGMA = 0.03
POWER = 1000.0
LIGHT = np.array([0.0, 0.0, 5.5])
CAMERA = np.array([0.1, -10.0, 2.5])
GAMMA, Q = 30.0, 0.2


def scene(distribution: dict) -> dict:
    return {
        "version": 1,
        "camera": {
            "type": "perspective",
            "position": CAMERA.tolist(),
            "orientation": {"look_at": {"target": [0.1, 0.0, 2.5], "up": [0, 0, 1]}},
            "resolution": [1, 1],
        },
        # Default orientation: the light shines along world −Z, local +X = world +X.
        "lights": [{"type": "point", "name": "pattern", "position": LIGHT.tolist(), "power_w": POWER,
                    "distribution": distribution}],
        "media": [{"type": "homogeneous", "name": "haze", "scattering": SIGMA}],
        "output": {"layers": ["inscatter", "error"], "tolerance": 1e-6, "threads": 1, "spectral": "never",
                   "pixel_filter": {"type": "none"}},
    }


def k(x: np.ndarray, period: float, p: float) -> np.ndarray:
    """Eq 8: max(p + (1 − p)·|2 mod(x, Δ) − Δ|/Δ, 0), angles in degrees."""
    return np.maximum(p + (1 - p) * np.abs(2 * np.mod(x, period) - period) / period, 0.0)


def pattern(theta_deg: np.ndarray, phi_deg: np.ndarray, d: dict) -> np.ndarray:
    cos_g = math.cos(math.radians(GAMMA))
    eq7 = np.where(theta_deg <= GAMMA, (1 - Q) * (np.cos(np.radians(theta_deg)) - cos_g) / (1 - cos_g) + Q, 0.0)
    phi = np.mod(phi_deg, 360.0)
    value = eq7 * k(phi, d["period_phi_deg"], d["min_ratio"])
    if d["type"] == "polka_dot":
        dth = d["period_theta_deg"]
        parity = np.mod(np.floor(phi / d["period_phi_deg"]) + np.floor(theta_deg / dth), 2)
        value = value * k(theta_deg, dth, d["min_ratio"]) * parity
    return value


def brute_force(d: dict, n: int) -> float:
    """Midpoint sum over the part of the ray y ∈ [−3, 3] that can be in the 30° cone
    (isotropic phase, homogeneous extinction σ on the view and light paths)."""
    y0, y1 = -3.0, 3.0
    h = (y1 - y0) / n
    y = y0 + (np.arange(n) + 0.5) * h
    x = np.stack([np.full(n, CAMERA[0]), y, np.full(n, CAMERA[2])], 1)
    v = x - LIGHT
    r = np.linalg.norm(v, axis=1)
    theta = np.degrees(np.arccos(-v[:, 2] / r))
    phi = np.degrees(np.arctan2(v[:, 1], v[:, 0]))
    intensity = POWER / (4 * math.pi) * pattern(theta, phi, d)
    t = y - CAMERA[1]
    integrand = SIGMA / (4 * math.pi) * intensity / r**2 * np.exp(-SIGMA * (t + r))
    return float(integrand.sum() * h)


CASES = [
    {"type": "daisy", "beam_spread_deg": GAMMA, "sharpness": Q, "period_phi_deg": 45.0, "min_ratio": p}
    for p in (0.3, 0.0, -1.0, -6.0, -10.0)
] + [
    {"type": "polka_dot", "beam_spread_deg": GAMMA, "sharpness": Q, "period_phi_deg": 20.0,
     "period_theta_deg": dth, "min_ratio": p}
    for dth, p in ((10.0, 0.0), (10.0, -10.0), (30.0, -1.0))
]


@pytest.mark.parametrize("distribution", CASES, ids=lambda d: f"{d['type']}-p{d['min_ratio']}")
def test_pattern_inscatter_matches_brute_force(distribution: dict) -> None:
    layers, report = tyndall.render(scene(distribution))
    got = float(layers["inscatter"][0, 0, 0])
    estimate = float(layers["error"][0, 0, 0])
    fine, coarse = brute_force(distribution, 4_000_000), brute_force(distribution, 2_000_000)
    brute_error = abs(fine - coarse)
    print(f"{distribution['type']} p={distribution['min_ratio']}: Tyndall {got:.6e} ± {estimate:.1e}, "
          f"brute force {fine:.6e} ± {brute_error:.1e}")
    assert fine > 1e-5  # the ray crosses lit slivers
    assert np.isfinite(got) and estimate >= 0.0
    # Both errors, plus the f32 rounding of the stored result (half an ulp).
    assert abs(got - fine) <= estimate + 2.0 * brute_error + 2.0**-24 * abs(got)
    assert not any("pattern" in entry["what"] for entry in report["plan"]["left_out"])
