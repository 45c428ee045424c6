"""Study (not a benchmark, not a test): how well can a narrow beam's *filtered* pixels be
computed from the pixel-centre samples alone, with the beam's cross profile in closed form?

Issue 3's unmet target is ≥ 300× Cycles' speed at 1 % relative RMSE below 384×216. There the
pixel filter dominates: a 2–4 px wide beam flags every pixel near it, and the adaptive lattice
traces ≈ 14 rays per flagged pixel, across the beam's square-root silhouettes
(docs/benchmarks.md, eighteenth and twentieth sessions). This script measures the accuracy of
the alternative the issue note names, before anyone builds it in Rust:

For a thin cone, a view ray at angular impact parameter β from the axis (seen from the light)
crosses the cone's cross-section along a chord, so its in-scatter is

    L(x, y) ≈ G(x, y) · A(β(x, y)),   A(β) = ∫ I(√(β² + s²)) ds   (the Abel transform of
                                                                  the spot's angular profile)

with G smooth (phase function, 1/r², transmittance, obliquity vary slowly along the beam) and
β an analytic function of the pixel position. The pixel-centre samples give G = L/A(β) where
A > 0 (elsewhere G is filled from its neighbours); the filtered pixel is the window integral of
G_interp · A(β), evaluated here on a 16 × 16-per-pixel grid (no view rays: β is geometry).

Reported against the exact filtered image (Tyndall point samples on the same 16× grid, filtered)
and against the converged Cycles reference, over the interior (3 px from the frame, where this
script's filter pads the fine grid at the edge). The floor's intersection with the beam, where
view rays end inside the cone, is not modelled (a real implementation would fall back to the
lattice there).

With ``--lattices`` it first prints, for comparison, uniform lattices of view rays (1, ½, ⅓, ¼
and ⅛ px) integrated against the window with bilinear and with Catmull–Rom interpolation: what
interpolation order alone gives without the profile.

    .venv/bin/python scripts/study_beam_profile_model.py [--scale 1|2|4] [--lattices]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import tyndall  # noqa: E402
from bench_stage_vs_cycles import DATA, ROOT, read_rgb, rel_rmse  # noqa: E402

FINE = 16


def bh(x: np.ndarray, width: float = 1.5) -> np.ndarray:
    """Cycles' Blackman–Harris window (doubled width), unnormalised."""
    a = 2 * np.pi * (x / (2 * width) + 0.5)
    w = 0.35875 - 0.48829 * np.cos(a) + 0.14128 * np.cos(2 * a) - 0.01168 * np.cos(3 * a)
    return np.where(np.abs(x) <= width, w, 0.0)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scale", type=int, default=1)
    ap.add_argument("--lattices", action="store_true", help="also uniform lattices without the profile")
    args = ap.parse_args()
    sc = json.loads((DATA / "narrow_beam_5deg.json").read_text())
    w0, h0 = sc["camera"]["resolution"]
    W, H = w0 * args.scale, h0 * args.scale
    sc["camera"]["resolution"] = [W, H]
    ref_path = (
        DATA / "narrow_beam_5deg.exr"
        if args.scale == 1
        else ROOT / ".cache" / "cycles_refs" / f"narrow_beam_5deg_x{args.scale}.exr"
    )
    ref = read_rgb(ref_path)[..., 0].astype(float)

    def point_samples(scale: int) -> np.ndarray:
        s = json.loads(json.dumps(sc))
        s["camera"]["resolution"] = [W * scale, H * scale]
        s["output"] = {
            "layers": ["inscatter"],
            "tolerance": 1e-4,
            "threads": 2,
            "pixel_filter": {"type": "none"},
            "spectral": "never",
        }
        return np.asarray(tyndall.render(s)[0]["inscatter"])[..., 0].astype(float)

    fine, centre = point_samples(FINE), point_samples(1)

    # Blender's camera: horizontal fit (W > H), sensor 36 mm.
    C = np.array(sc["camera"]["position"], float)
    T = np.array(sc["camera"]["orientation"]["look_at"]["target"], float)
    fwd = (T - C) / np.linalg.norm(T - C)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    f, sw = sc["camera"]["focal_length_mm"], sc["camera"]["sensor_width_mm"]
    sh = sw * H / W

    def dirs(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        cx, cy = (x / W - 0.5) * sw, (0.5 - y / H) * sh
        d = right * cx[..., None] + up * cy[..., None] + fwd * f
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    light = sc["lights"][0]
    Lp = np.array(light["position"], float)
    Lt = np.array(light["orientation"]["look_at"]["target"], float)
    ax = (Lt - Lp) / np.linalg.norm(Lt - Lp)
    alpha, blend = np.radians(light["spot_size_deg"] / 2), light["spot_blend"]

    def profile(theta: np.ndarray) -> np.ndarray:
        ca = np.cos(alpha)
        x = np.clip((np.cos(theta) - ca) / (blend * (1 - ca)), 0, 1)
        return x * x * (3 - 2 * x)

    betas = np.linspace(0, alpha * 1.0001, 4001)
    s = np.linspace(-alpha, alpha, 8001)
    a_tab = np.array([np.trapezoid(profile(np.sqrt(b * b + s * s)), s) for b in betas])

    def abel(beta: np.ndarray) -> np.ndarray:
        return np.interp(beta, betas, a_tab, right=0.0)

    def beta_of(d: np.ndarray) -> np.ndarray:
        """Angle from the light between the cone's axis and the view ray's closest approach to it."""
        w = C - Lp
        b, dd, e = (d * ax).sum(-1), (d * w).sum(-1), (w * ax).sum()
        den = 1.0 - b * b
        t, u = (b * e - dd) / den, (e - b * dd) / den
        dist = np.linalg.norm(C + d * t[..., None] - (Lp + ax * u[..., None]), axis=-1)
        return np.arctan2(dist, u)

    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    a_c = abel(beta_of(dirs(xx, yy)))
    known = a_c > 1e-3 * a_tab[0]
    g = np.where(known, centre / np.maximum(a_c, 1e-300), np.nan)
    for _ in range(10 * max(W, H)):  # fill G outside the cone from its neighbours
        m = np.isnan(g)
        if not m.any():
            break
        pad = np.pad(g, 1, constant_values=np.nan)
        nb = np.stack([pad[1:-1, :-2], pad[1:-1, 2:], pad[:-2, 1:-1], pad[2:, 1:-1]])
        cnt = (~np.isnan(nb)).sum(0)
        fill = m & (cnt > 0)
        g[fill] = np.nansum(nb, 0)[fill] / cnt[fill]

    fy, fx = np.mgrid[0 : H * FINE, 0 : W * FINE]
    fx, fy = (fx + 0.5) / FINE, (fy + 0.5) / FINE
    a_f = abel(beta_of(dirs(fx, fy)))

    def interp(x: np.ndarray, y: np.ndarray, cubic: bool) -> np.ndarray:
        gx, gy = x - 0.5, y - 0.5
        ix, iy = np.floor(gx).astype(int), np.floor(gy).astype(int)
        tx, ty = gx - ix, gy - iy

        def at(j: np.ndarray, i: np.ndarray) -> np.ndarray:
            return g[np.clip(j, 0, H - 1), np.clip(i, 0, W - 1)]

        if not cubic:
            return (
                at(iy, ix) * (1 - tx) * (1 - ty)
                + at(iy, ix + 1) * tx * (1 - ty)
                + at(iy + 1, ix) * (1 - tx) * ty
                + at(iy + 1, ix + 1) * tx * ty
            )

        def cr(t: np.ndarray) -> list[np.ndarray]:  # Catmull–Rom weights
            return [
                -0.5 * t**3 + t**2 - 0.5 * t,
                1.5 * t**3 - 2.5 * t**2 + 1,
                -1.5 * t**3 + 2 * t**2 + 0.5 * t,
                0.5 * t**3 - 0.5 * t**2,
            ]

        wx, wy = cr(tx), cr(ty)
        return sum(wy[a] * wx[b] * at(iy - 1 + a, ix - 1 + b) for a in range(4) for b in range(4))

    def filtered(grid: np.ndarray) -> np.ndarray:
        ks = np.arange(-2 * FINE, 3 * FINE)
        wv = bh((ks + 0.5) / FINE - 0.5)
        P = 3 * FINE + 4
        pad = np.pad(grid, ((P, P), (P, P)), mode="edge")
        tmp = sum(
            wv[j] * pad[P : P + H * FINE, P + k : P + k + FINE * W : FINE][:, :W] for j, k in enumerate(ks) if wv[j]
        )
        padr = np.pad(tmp, ((P, P), (0, 0)), mode="edge")
        out = sum(wv[j] * padr[P + k : P + k + FINE * H : FINE][:H] for j, k in enumerate(ks) if wv[j])
        return out / wv.sum() ** 2

    exact = filtered(fine)
    keep = np.zeros((H, W), bool)
    keep[3:-3, 3:-3] = True
    print(f"narrow beam at {W}×{H}, interior (3 px from the frame)")
    if args.lattices:
        # Point samples at (m + ½)/k px, interpolated (hat or Catmull–Rom cardinal functions)
        # and integrated against the window: weights by quadrature of w × cardinal function.
        xs = np.linspace(-1.5, 1.5, 30001)
        dx = xs[1] - xs[0]
        wx = bh(xs)

        def hat(t: np.ndarray) -> np.ndarray:
            return np.maximum(0.0, 1.0 - np.abs(t))

        def keys(t: np.ndarray) -> np.ndarray:
            t = np.abs(t)
            near = 1.5 * t**3 - 2.5 * t**2 + 1
            far = -0.5 * t**3 + 2.5 * t**2 - 4 * t + 2
            return np.where(t < 1, near, np.where(t < 2, far, 0.0))

        for k in (1, 2, 3, 4, 8):
            grid = point_samples(k)
            ks = np.arange(-2 * k - 2, 3 * k + 2)
            P = 3 * k + 4
            for name, card in (("bilinear", hat), ("Catmull–Rom", keys)):
                wv = np.array([np.sum(wx * card((xs - ((j + 0.5) / k - 0.5)) * k)) * dx for j in ks])
                pad = np.pad(grid, ((P, P), (P, P)), mode="edge")
                tmp = sum(wv[i] * pad[P : P + H * k, P + j : P + j + k * W : k][:, :W] for i, j in enumerate(ks))
                padr = np.pad(tmp, ((P, P), (0, 0)), mode="edge")
                out = sum(wv[i] * padr[P + j : P + j + k * H : k][:H] for i, j in enumerate(ks)) / wv.sum() ** 2
                rays = W * H * k * k
                print(f"  uniform lattice 1/{k} px ({rays} rays), {name}: vs exact {rel_rmse(out, exact, keep):.3%}")
    print(
        f"  exact filtered vs Cycles: {rel_rmse(exact, ref, keep):.3%} (the reference's noise and Tyndall's own error)"
    )
    print(f"  centre samples, no filter, vs exact: {rel_rmse(centre, exact, keep):.2%}")
    for cubic in (False, True):
        model = interp(fx, fy, cubic) * a_f
        fm = filtered(model)
        name = "Catmull–Rom" if cubic else "bilinear"
        vs_exact, vs_cycles = rel_rmse(fm, exact, keep), rel_rmse(fm, ref, keep)
        points = np.sqrt(np.mean((model - fine) ** 2)) / np.sqrt(np.mean(fine**2))
        print(f"  profile model, G {name}: vs exact {vs_exact:.3%}, vs Cycles {vs_cycles:.3%}")
        print(f"    (its point values against the fine samples: {points:.2%})")
        # Where the error sits: the largest pixels' share of the squared error.
        err2 = ((fm - exact) * keep) ** 2
        top = np.sort(err2.ravel())[::-1]
        print(f"    the worst 5 pixels hold {top[:5].sum() / top.sum():.0%} of the squared error")


if __name__ == "__main__":
    main()
