#!/usr/bin/env python3
"""Measure Blender Cycles' light and volume conventions against closed forms.

    python scripts/cycles_conventions_check.py [--samples N] [--only NAME ...] [--json OUT.json]

Each check builds a tiny bpy scene whose answer is computed independently
here in numpy (camera rays, the Blackman–Harris pixel filter, and the
single-scattering integral by Gauss–Legendre quadrature), renders it twice
with Cycles (two seeds, N samples each), and reports

    ratio = Σ Cycles / Σ prediction   over the lit pixels
    noise = |ratio_seed0 − ratio_seed1| / 2   (≈ standard error of the mean ratio)

plus per-pixel statistics. docs/cycles-conventions.md records the results.

Checks (the formula under test is in each docstring):
  point_plane      point light over a white Lambert plane: I = P·c/(4π)
  spot_plane       spot light over the plane, camera at the light: Cycles' smoothstep cone mask
  point_volume_hg  point light in a world Volume Scatter, HG g = +0.5: σ_s = D·C, HG sign
  spot_volume_rayleigh  spot in a Rayleigh world volume, side view
  ies_plane        point light + IES Texture (type C, asymmetric): 0.0706650768394·cd, orientation
  soft_falloff     point light with radius 0.3 m in a volume, soft falloff on and off
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cycles_reference as cr  # noqa: E402

FOUR_PI = 4.0 * math.pi
IES_CD_TO_W = 0.0706650768394  # util/ies.cpp: 4π / 177.83 (D65 luminous efficacy, lm/W)

# --------------------------------------------------------------------------
# independent numpy model of a Blender perspective camera + pixel filter


# Measured (check point_plane): Cycles' pixel (i, j), row j counted from the top of the
# written EXR, is centred on the image-plane point (i + 1, j + 1) px from the top-left
# corner, i.e. half a pixel right of and below the conventional centre (i + ½, j + ½).
PIXEL_SHIFT = (0.5, 0.5)


def camera_dirs(rot3, res, focal_mm, sensor_w, xs, ys, shift=None):
    """World ray directions through Cycles pixel positions (xs, ys), pixels from the top-left.

    The PIXEL_SHIFT measured for Blender 5.0.1 is added (xs = i + ½ is pixel i's nominal centre).
    """
    sx0, sy0 = PIXEL_SHIFT if shift is None else shift
    xs = xs + sx0
    ys = ys + sy0
    w, h = res
    # sensor_fit auto: sensor_w spans the larger side
    span = sensor_w / focal_mm
    if w >= h:
        sx, sy = span, span * h / w
    else:
        sx, sy = span * w / h, span
    u = (xs / w - 0.5) * sx
    v = (0.5 - ys / h) * sy
    d = np.stack([u, v, -np.ones_like(u)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return d @ rot3.T


def blackman_harris_image(radiance_fn, rot3, res, focal_mm, sensor_w=36.0, width=1.5, sub=4, shift=None):
    """Pixel values of Cycles' Blackman–Harris filter (support ±width px) over radiance_fn(dirs)."""
    w, h = res
    step = 1.0 / sub
    n_half = int(round(width * sub))  # samples each side of a pixel centre
    offs = (np.arange(-n_half, n_half) + 0.5) * step  # within (−width, width)
    t = offs / (2.0 * width) + 0.5
    a = 2 * math.pi * t
    wt = 0.35875 - 0.48829 * np.cos(a) + 0.14128 * np.cos(2 * a) - 0.01168 * np.cos(3 * a)
    wt /= wt.sum()
    # global fine grid: x = k·step + step/2 − width ..
    gx = (np.arange(w * sub + 2 * n_half) + 0.5) * step - width
    gy = (np.arange(h * sub + 2 * n_half) + 0.5) * step - width
    X, Y = np.meshgrid(gx, gy)
    L = radiance_fn(camera_dirs(rot3, res, focal_mm, sensor_w, X, Y, shift))  # (GY, GX, 3)
    # separable filter: pixel i centre at i + 0.5 = gx index i·sub + n_half (± offsets)
    out = np.zeros((h, w, L.shape[-1]))
    tmp = np.zeros((L.shape[0], w, L.shape[-1]))
    for i in range(w):
        tmp[:, i] = np.tensordot(wt, L[:, i * sub : i * sub + 2 * n_half], axes=(0, 1))
    for j in range(h):
        out[j] = np.tensordot(wt, tmp[j * sub : j * sub + 2 * n_half], axes=(0, 0))
    return out


# --------------------------------------------------------------------------
# phase functions and closed forms


def phase_hg(mu, g):
    if abs(g) < 1e-3:
        return np.full_like(mu, 1 / FOUR_PI)
    f = 1 + g * g - 2 * g * mu
    return (1 - g * g) / (FOUR_PI * f * np.sqrt(f))


def phase_rayleigh(mu):
    return 3.0 / (16 * math.pi) * (1 + mu * mu)


def smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def spot_mask(cos_t, size_rad, blend):
    """Cycles spot_light_attenuation(): smoothstep((cosθ − cos(s/2)) / ((1 − cos(s/2))·blend))."""
    c = math.cos(size_rad / 2)
    if blend <= 0:
        return (cos_t > c).astype(float)
    return smoothstep((cos_t - c) / ((1 - c) * blend))


def volume_point_radiance(o, dirs, light_pos, intensity_fn, sigma_s, sigma_t, phase_fn, t_max=np.inf, n=96):
    """Single scattering of a point light along rays o + t d, t ∈ [0, t_max] (no occluders).

    L = ∫ σ_s e^{−σ_t t} I(ω) e^{−σ_t r} / r² p(μ) dt, with t = t_c + b tan φ (dt/r² = dφ/b).
    intensity_fn(unit vectors from light to point) -> (..., 3) W/sr.
    """
    xg, wg = np.polynomial.legendre.leggauss(n)
    sigma_s = np.asarray(sigma_s, float)
    sigma_t = np.asarray(sigma_t, float)
    lp = np.asarray(light_pos, float) - o
    tc = dirs @ lp
    perp = lp - tc[..., None] * dirs
    b = np.maximum(np.linalg.norm(perp, axis=-1), 1e-9)
    phi0 = np.arctan2(0.0 - tc, b)
    phi1 = np.arctan2(t_max - tc, b) if np.isfinite(t_max) else np.full_like(b, math.pi / 2)
    # Split at φ = 0 to keep the quadrature accurate when the ray passes close to the light
    total = np.zeros(dirs.shape[:-1] + (3,))
    for lo, hi in ((phi0, np.minimum(phi1, np.maximum(phi0, 0.0))), (np.maximum(phi0, 0.0), phi1)):
        span = np.maximum(hi - lo, 0.0)
        for xk, wk in zip(xg, wg):
            phi = lo + (xk + 1) * 0.5 * span
            t = tc + b * np.tan(phi)
            r = b / np.cos(phi)
            x = dirs * t[..., None]
            to_light = (lp - x) / r[..., None]
            mu = np.sum(dirs * to_light, axis=-1)
            I = intensity_fn(-to_light)
            f = np.exp(-sigma_t * (t + r)[..., None]) * I * phase_fn(mu)[..., None]
            total += (wk * 0.5 * span / b)[..., None] * f
    return sigma_s * total


# --------------------------------------------------------------------------
# rendering helpers


def render_two_seeds(samples, seeds=(1, 2)):
    imgs, secs = [], []
    bpy = cr._bpy()
    for s in seeds:
        bpy.context.scene.cycles.seed = s
        img, dt = cr.render_to_array()
        imgs.append(img.astype(np.float64))
        secs.append(dt)
    return imgs, secs


def compare(imgs, pred, mask=None, name=""):
    a, b = imgs
    finite = np.all(np.isfinite(pred), axis=-1)
    ps = np.where(finite, pred.sum(-1), 0.0)
    m = (ps > 1e-3 * ps.max()) if mask is None else (mask & finite)
    mean = 0.5 * (a + b)
    ratios = [float(x[m].sum() / pred[m].sum()) for x in (a, b)]
    per_ch = [float(mean[m][:, c].sum() / pred[m][:, c].sum()) for c in range(3)]
    # per-pixel relative deviation of the 2-seed mean, and its noise level
    rel = (mean[m] - pred[m]) / pred[m]
    rel_noise = 0.5 * np.abs(a[m] - b[m]) / pred[m]
    return {
        "ratio": 0.5 * (ratios[0] + ratios[1]),
        "ratio_noise": 0.5 * abs(ratios[0] - ratios[1]),
        "ratio_seeds": ratios,
        "ratio_rgb": per_ch,
        "pixels": int(m.sum()),
        "pixel_rel_dev_rms": float(np.sqrt(np.mean(rel**2))),
        "pixel_rel_noise_rms": float(np.sqrt(np.mean(rel_noise**2))),
    }


def far_from_light_mask(cam, rot3, res, focal_mm, light, radius_px=3.0, sensor_w=36.0):
    """True for pixels whose centre ray passes more than radius_px pixels (in angle) from the light.

    The in-scatter of a point light grows like 1/b near it (b = ray–light distance); the
    4×4-per-pixel-sub-sampled prediction does not resolve that spike, so such pixels are
    compared separately.
    """
    w, h = res
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    d = camera_dirs(rot3, res, focal_mm, sensor_w, xs, ys)
    to_l = np.asarray(light, float) - np.asarray(cam, float)
    to_l /= np.linalg.norm(to_l)
    ang = np.arccos(np.clip(d @ to_l, -1, 1))
    px = (sensor_w / focal_mm) / max(w, h)  # radians per pixel near the centre
    return ang > radius_px * px


def setup(res, samples, cam_pos, cam_rot, focal=20.0, volume_bounces=0, max_bounces=0):
    cr.reset_blender()
    cr.add_camera(cam_pos, cam_rot, focal_mm=focal)
    cr.configure_render(
        res, samples, 1, "BLACKMAN_HARRIS", 1.5, threads=2, bounces_max=max_bounces, volume_bounces=volume_bounces
    )
    cr.set_world_media([])


def look_down():
    return np.eye(3)  # camera / light local −Z = world −Z, +Y up


def look_at(pos, target, up=(0, 0, 1)):
    return cr.orientation_matrix({"look_at": {"target": list(target), "up": list(up)}}, pos)


# --------------------------------------------------------------------------
# checks


RES = (64, 36)


def check_point_plane(samples):
    """White Lambert plane (albedo a) lit by a point light: L = a/π · I cosθ / r², I = P·c/(4π)."""
    h, P, col, alb = 2.0, 100.0, np.array([1.0, 0.5, 0.25]), 0.8
    light = np.array([0.3, 0.2, h])
    cam = np.array([0.0, 0.0, 3.0])
    setup(RES, samples, cam, look_down(), focal=30.0)
    cr.add_mesh(
        "plane",
        [(-50, -50, 0), (50, -50, 0), (50, 50, 0), (-50, 50, 0)],
        [(0, 1, 2), (0, 2, 3)],
        np.eye(4),
        cr.diffuse_material((alb, alb, alb)),
    )
    cr.add_light("point", "pt", cr.pose_matrix(np.eye(3), light), col, P)
    imgs, secs = render_two_seeds(samples)
    I0 = P * col / FOUR_PI

    def rad(d):
        t = cam[2] / -d[..., 2]
        x = cam + d * t[..., None]
        v = light - x
        r2 = np.sum(v * v, -1)
        cos_i = v[..., 2] / np.sqrt(r2)
        return (alb / math.pi) * I0 * (cos_i / r2)[..., None]

    pred = blackman_harris_image(rad, look_down(), RES, 30.0)
    out = compare(imgs, pred)
    out["formula"] = "I = P*c/(4*pi)"
    # pixel-centre convention: fit of the image-plane shift of Cycles' pixels
    mean = 0.5 * (imgs[0] + imgs[1])
    out["pixel_rel_dev_rms_by_shift_px"] = {}
    for sh in [(0.0, 0.0), (0.5, 0.0), (0.0, 0.5), (0.5, 0.5), (-0.5, -0.5), (0.4, 0.4), (0.6, 0.6)]:
        p = blackman_harris_image(rad, look_down(), RES, 30.0, shift=sh)
        out["pixel_rel_dev_rms_by_shift_px"][f"{sh[0]:+.1f},{sh[1]:+.1f}"] = float(
            np.sqrt(np.mean((mean / p - 1) ** 2))
        )
    out["seconds"] = secs
    return out


def check_spot_plane(samples):
    """Spot light shining down at a plane, camera at the light: L = a/π · I0 · mask(θ) cos³θ / h²."""
    h, P, alb = 2.0, 100.0, 0.8
    size, blend = math.radians(60.0), 0.4
    pos = np.array([0.0, 0.0, h])
    setup(RES, samples, pos, look_down(), focal=16.0)
    cr.add_mesh(
        "plane",
        [(-50, -50, 0), (50, -50, 0), (50, 50, 0), (-50, 50, 0)],
        [(0, 1, 2), (0, 2, 3)],
        np.eye(4),
        cr.diffuse_material((alb, alb, alb)),
    )
    cr.add_light("spot", "spot", cr.pose_matrix(np.eye(3), pos), (1, 1, 1), P, spot_size_deg=60.0, spot_blend=blend)
    imgs, secs = render_two_seeds(samples)
    I0 = P / FOUR_PI

    def rad_mask(mask_fn):
        def rad(d):
            cos_t = -d[..., 2]
            return ((alb / math.pi) * I0 * mask_fn(cos_t) * cos_t**3 / h**2)[..., None] * np.ones(3)

        return rad

    pred = blackman_harris_image(rad_mask(lambda c: spot_mask(c, size, blend)), look_down(), RES, 16.0)
    out = compare(imgs, pred)
    # Alternatives, to show the measurement discriminates: the older smoothstep in the
    # angle itself, and the mask without blend scaling by (1 − cos).
    alt = {
        "angle_linear_blend": lambda c: smoothstep((size / 2 - np.arccos(np.clip(c, -1, 1))) / (blend * size / 2)),
        "no_spot_mask": lambda c: np.ones_like(c),
    }
    mean = 0.5 * (imgs[0] + imgs[1])
    m = pred.sum(-1) > 1e-3 * pred.sum(-1).max()
    out["alternatives_pixel_rel_dev_rms"] = {}
    for k, f in alt.items():
        p2 = blackman_harris_image(rad_mask(f), look_down(), RES, 16.0)
        mm = m & (p2.sum(-1) > 1e-3 * p2.sum(-1).max())
        out["alternatives_pixel_rel_dev_rms"][k] = float(np.sqrt(np.mean(((mean[mm] - p2[mm]) / p2[mm]) ** 2)))
    # pixel filter: Blender's Filter Size 1.5 px, tabulated by Cycles at twice the width
    # (support ±1.5 px); compare with the support ±0.75 px (no doubling) and a point sample
    base = rad_mask(lambda c: spot_mask(c, size, blend))
    for label, wdt in (("filter_support_0.75px", 0.75), ("filter_support_3px", 3.0)):
        p2 = blackman_harris_image(base, look_down(), RES, 16.0, width=wdt)
        out["alternatives_pixel_rel_dev_rms"][label] = float(np.sqrt(np.mean(((mean[m] - p2[m]) / p2[m]) ** 2)))
    # centre pixels: on-axis intensity equals that of a point light of the same power
    cy, cx = RES[1] // 2, RES[0] // 2
    sl = (slice(cy - 2, cy + 2), slice(cx - 2, cx + 2))
    out["centre_ratio"] = float(mean[sl].sum() / pred[sl].sum())
    out["formula"] = "mask = smoothstep((cos t - cos(size/2)) / (blend (1 - cos(size/2)))), I_axis = P/(4 pi)"
    out["seconds"] = secs
    return out


def check_point_volume(samples, phase="HENYEY_GREENSTEIN", g=0.5, name="hg"):
    """Camera looking past a point light through a world Volume Scatter (D, C): σ_s = σ_t = D·C."""
    D, C = 2.0, np.array([0.06, 0.04, 0.02])  # σ_s = (0.12, 0.08, 0.04) m⁻¹
    sig = D * C
    P, col = 1000.0, np.array([1.0, 1.0, 1.0])
    light = np.array([0.0, 6.0, 1.0])
    cam = np.array([0.0, 0.0, 1.0])
    # look slightly to the side of the light: forward scattering (μ → 1) is on the image's left part
    rot = look_at(cam, (1.2, 6.0, 1.0))
    setup(RES, samples, cam, rot, focal=20.0)
    cr.add_light("point", "pt", cr.pose_matrix(np.eye(3), light), col, P)
    nt = None
    cr.set_world_media([(sig, np.zeros(3), (phase, g, None))])
    # Rebuild the scatter node with D and C as given (set_world_media normalises to D = 1)
    import bpy

    nt = bpy.context.scene.world.node_tree
    vs = [n for n in nt.nodes if n.bl_idname == "ShaderNodeVolumeScatter"][0]
    vs.inputs["Density"].default_value = D
    vs.inputs["Color"].default_value = (*C, 1.0)
    imgs, secs = render_two_seeds(samples)
    I = P * col / FOUR_PI
    pf = (lambda mu: phase_hg(mu, g)) if phase == "HENYEY_GREENSTEIN" else phase_rayleigh

    def rad(d):
        return volume_point_radiance(cam, d, light, lambda w: I * np.ones(w.shape[:-1] + (1,)), sig, sig, pf)

    pred = blackman_harris_image(rad, rot, RES, 20.0)
    far = far_from_light_mask(cam, rot, RES, 20.0, light)
    out = compare(imgs, pred, mask=far)
    out["all_pixels_incl_light_ratio"] = compare(imgs, pred)["ratio"]
    out["excluded_pixels_near_light"] = int((~far).sum())
    mean = 0.5 * (imgs[0] + imgs[1])
    if phase == "HENYEY_GREENSTEIN":
        # sign test: the same with g → −g
        pneg = blackman_harris_image(
            lambda d: volume_point_radiance(
                cam, d, light, lambda w: I * np.ones(w.shape[:-1] + (1,)), sig, sig, lambda mu: phase_hg(mu, -g)
            ),
            rot,
            RES,
            20.0,
        )
        out["ratio_if_g_negated"] = float(mean[far].sum() / pneg[far].sum())
    # without extinction (σ_t = 0), to show that extinction = D·C is measured
    p0 = blackman_harris_image(
        lambda d: volume_point_radiance(cam, d, light, lambda w: I * np.ones(w.shape[:-1] + (1,)), sig, 0 * sig, pf),
        rot,
        RES,
        20.0,
    )
    out["ratio_if_no_extinction"] = float(mean[far].sum() / p0[far].sum())
    out["formula"] = f"sigma_s = sigma_t = D*C, phase {phase} g={g}"
    out["seconds"] = secs
    return out


def check_spot_volume_rayleigh(samples):
    """Side view of a spot beam in a Rayleigh world volume (spot mask × Rayleigh × extinction)."""
    sig = np.array([0.05, 0.05, 0.05])
    P = 1000.0
    lpos = np.array([0.0, 0.0, 4.0])
    lrot = look_at(lpos, (1.0, 0.0, 0.0), up=(0, 1, 0))  # pointing down and along +x
    size, blend = math.radians(30.0), 0.25
    cam = np.array([1.0, -8.0, 2.0])
    crot = look_at(cam, (1.0, 0.0, 2.0))
    setup(RES, samples, cam, crot, focal=24.0)
    cr.add_light("spot", "spot", cr.pose_matrix(lrot, lpos), (1, 1, 1), P, spot_size_deg=30.0, spot_blend=blend)
    cr.set_world_media([(sig, np.zeros(3), ("RAYLEIGH", 0.0, None))])
    imgs, secs = render_two_seeds(samples)
    axis = -lrot[:, 2]

    def inten(w):
        return (P / FOUR_PI * spot_mask(w @ axis, size, blend))[..., None] * np.ones(3)

    pred = blackman_harris_image(
        lambda d: volume_point_radiance(cam, d, lpos, inten, sig, sig, phase_rayleigh, n=128), crot, RES, 24.0
    )
    far = far_from_light_mask(cam, crot, RES, 24.0, lpos)
    ps = pred.sum(-1)
    out = compare(imgs, pred, mask=far & (ps > 1e-3 * ps.max()))
    out["all_pixels_incl_light_ratio"] = compare(imgs, pred)["ratio"]
    out["excluded_pixels_near_light"] = int((~far).sum())
    mean = 0.5 * (imgs[0] + imgs[1])
    p_iso = blackman_harris_image(
        lambda d: volume_point_radiance(cam, d, lpos, inten, sig, sig, lambda mu: phase_hg(mu, 0.0), n=128),
        crot,
        RES,
        24.0,
    )
    m = far & (pred.sum(-1) > 1e-3 * pred.sum(-1).max())
    out["pixel_rel_dev_rms_if_isotropic"] = float(np.sqrt(np.mean(((mean[m] - p_iso[m]) / p_iso[m]) ** 2)))
    out["formula"] = "p = 3/(16 pi) (1 + mu^2); spot mask as spot_plane"
    out["seconds"] = secs
    return out


IES_V = np.arange(0.0, 181.0, 10.0)
IES_H = np.arange(0.0, 361.0, 15.0)


def ies_candela(v_deg, h_deg):
    """Smooth asymmetric test distribution, candela (before the multiplier)."""
    v = np.radians(v_deg)
    h = np.radians(h_deg)
    return 800.0 * (1.0 + 0.5 * np.cos(h) + 0.3 * np.sin(h)) * (0.4 + 0.6 * np.cos(v / 2) ** 2)


def write_test_ies(path, multiplier=1.5):
    vals = ies_candela(IES_V[None, :], IES_H[:, None])
    lines = [
        "IESNA:LM-63-2002",
        "[TEST] tyndall asymmetric test profile",
        "TILT=NONE",
        f"1 -1 {multiplier} {len(IES_V)} {len(IES_H)} 1 2 0 0 0",
        "1.0 1.0 100",
        " ".join(f"{x:g}" for x in IES_V),
        " ".join(f"{x:g}" for x in IES_H),
    ]
    for row in vals:
        lines.append(" ".join(f"{x:.4f}" for x in row))
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def check_ies_plane(samples):
    """Point light + IES Texture → Emission Strength; camera at the light looking along −Z.

    I(ω) = P·c/(4π) · strength · 0.0706650768394 · cd(v, h),
    v = acos(−z_local), h = atan2(x_local, y_local) + π  (h = 0 towards local −Y).
    """
    h, P, alb, strength, mult = 2.0, 100.0, 0.8, 2.0, 1.5
    pos = np.array([0.0, 0.0, h])
    tmp = tempfile.mkdtemp(prefix="ies_")
    path = os.path.join(tmp, "test.ies")
    write_test_ies(path, mult)
    setup(RES, samples, pos, look_down(), focal=16.0)
    cr.add_mesh(
        "plane",
        [(-50, -50, 0), (50, -50, 0), (50, 50, 0), (-50, 50, 0)],
        [(0, 1, 2), (0, 2, 3)],
        np.eye(4),
        cr.diffuse_material((alb, alb, alb)),
    )
    cr.add_light("point", "ies", cr.pose_matrix(np.eye(3), pos), (1, 1, 1), P, ies_path=path, ies_strength=strength)
    imgs, secs = render_two_seeds(samples)
    mean = 0.5 * (imgs[0] + imgs[1])

    def rad_h(hfun):
        def rad(d):
            cos_t = -d[..., 2]
            v = np.degrees(np.arccos(np.clip(-d[..., 2], -1, 1)))
            hh = np.degrees(hfun(d[..., 0], d[..., 1])) % 360.0
            I = P / FOUR_PI * strength * IES_CD_TO_W * mult * ies_candela(v, hh)
            return ((alb / math.pi) * I * cos_t**3 / h**2)[..., None] * np.ones(3)

        return rad

    cands = {
        "h=atan2(x,y)+pi (0 at -Y, 90 at -X)": lambda x, y: np.arctan2(x, y) + math.pi,
        "h=atan2(y,x) (0 at +X, 90 at +Y)": lambda x, y: np.arctan2(y, x),
        "h=atan2(x,y) (0 at +Y, 90 at +X)": lambda x, y: np.arctan2(x, y),
        "h=atan2(-y,x) (0 at +X, 90 at -Y)": lambda x, y: np.arctan2(-y, x),
        "h=atan2(-x,y)+pi (0 at -Y, 90 at +X)": lambda x, y: np.arctan2(-x, y) + math.pi,
        "h=atan2(-x,-y)+pi (0 at +Y, 90 at +X)": lambda x, y: np.arctan2(-x, -y) + math.pi,
    }
    res = {}
    best = None
    for k, f in cands.items():
        p = blackman_harris_image(rad_h(f), look_down(), RES, 16.0)
        c = compare(imgs, p)
        res[k] = {"ratio": c["ratio"], "pixel_rel_dev_rms": c["pixel_rel_dev_rms"]}
        if best is None or c["pixel_rel_dev_rms"] < best[1]["pixel_rel_dev_rms"]:
            best = (k, c)
    out = dict(best[1])
    out["orientation"] = best[0]
    out["candidates"] = res
    out["formula"] = "I = P c/(4 pi) * strength * 0.0706650768394 * cd * multiplier"
    out["seconds"] = secs
    return out


def check_soft_falloff(samples):
    """Point light of radius R in a thin isotropic volume, rays passing at ~R from the centre.

    soft falloff on  (default): an oriented disk of radius R facing the shading point:
        E-like factor (2/R²)(1 − d/√(d² + R²)) replaces 1/d²;
    soft falloff off (sphere):  L_sphere = P/(4π² R²) over the solid angle 2π(1 − √(1 − R²/d²)), d > R.
    """
    R = 0.3
    sig = np.array([0.02, 0.02, 0.02])
    P = 1000.0
    light = np.array([0.0, 4.0, 1.0])
    cam = np.array([0.0, 0.0, 1.0])
    rot = look_at(cam, (0.5, 4.0, 1.0))
    out = {}
    for soft in (True, False):
        setup(RES, samples, cam, rot, focal=30.0)
        cr.add_light("point", "pt", cr.pose_matrix(np.eye(3), light), (1, 1, 1), P, radius_m=R, soft_falloff=soft)
        cr.set_world_media([(sig, np.zeros(3), ("HENYEY_GREENSTEIN", 0.0, None))])
        imgs, secs = render_two_seeds(samples)

        def factor(d):  # replaces 1/d² in I/d²
            if soft:
                return (2.0 / R**2) * (1 - d / np.sqrt(d * d + R * R))
            inside = d <= R
            dd = np.maximum(d, R)
            return np.where(inside, np.nan, (2 * math.pi * (1 - np.sqrt(1 - (R / dd) ** 2))) / (math.pi * R * R))

        def rad_model(use_model):
            def rad(d):
                # brute-force quadrature along the ray (dense near the light)
                ts = np.linspace(0.0, 60.0, 6001)
                tm = 0.5 * (ts[1:] + ts[:-1])
                dt = np.diff(ts)
                acc = np.zeros(d.shape[:-1])
                for t, w in zip(tm, dt):
                    x = cam + d * t
                    r = np.linalg.norm(light - x, axis=-1)
                    f = factor(r) if use_model else 1 / r**2
                    acc += w * np.exp(-sig[0] * (t + r)) * f
                return (sig[0] * P / FOUR_PI / FOUR_PI * acc)[..., None] * np.ones(3)

            return rad

        pred = blackman_harris_image(rad_model(True), rot, RES, 30.0, sub=2)
        p_pt = blackman_harris_image(rad_model(False), rot, RES, 30.0, sub=2)
        c = compare(imgs, pred)
        mean = 0.5 * (imgs[0] + imgs[1])
        ok = np.all(np.isfinite(pred), axis=-1)
        c["ratio_vs_point_light"] = float(mean[ok].sum() / p_pt[ok].sum())
        c["seconds"] = secs
        out["soft_falloff" if soft else "sphere"] = c
    return out


CHECKS = {
    "point_plane": check_point_plane,
    "spot_plane": check_spot_plane,
    "point_volume_hg": lambda s: check_point_volume(s, "HENYEY_GREENSTEIN", 0.5),
    "spot_volume_rayleigh": check_spot_volume_rayleigh,
    "ies_plane": check_ies_plane,
    "soft_falloff": check_soft_falloff,
}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=1024)
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    results = {"blender": cr._bpy().app.version_string, "samples_per_seed": args.samples, "resolution": RES}
    for name, fn in CHECKS.items():
        if args.only and name not in args.only:
            continue
        t0 = time.perf_counter()
        r = fn(args.samples)
        r["wall_seconds"] = time.perf_counter() - t0
        results[name] = r
        print(name, json.dumps(r, indent=1), flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
