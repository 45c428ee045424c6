"""Blender → Tyndall conversions (pure Python; see docs/cycles-conventions.md).

Every function here takes and returns plain numbers, so it is tested without Blender.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

FOUR_PI = 4.0 * math.pi

Rgb = tuple[float, float, float]


class ConversionError(ValueError):
    """A Blender setting that Tyndall cannot represent; the message says which and why."""


def finite(name: str, value: float) -> float:
    """``value`` as a float, or a :class:`ConversionError` naming ``name`` when it is NaN or infinite."""
    v = float(value)
    if not math.isfinite(v):
        raise ConversionError(f"{name} is not a finite number ({v})")
    return v


def rgb(name: str, values: Sequence[float]) -> Rgb:
    """The first three components of a Blender colour as finite floats ≥ 0."""
    if len(values) < 3:
        raise ConversionError(f"{name}: expected 3 colour components, got {len(values)}")
    out = tuple(finite(f"{name}[{i}]", values[i]) for i in range(3))
    if min(out) < 0.0:
        raise ConversionError(f"{name} has a negative component {out}")
    return (out[0], out[1], out[2])


def light_power_w(energy: float, exposure: float = 0.0) -> float:
    """Blender's Power (W) times the light's Exposure factor 2^exposure, as Cycles uses it."""
    p = finite("Power", energy) * 2.0 ** finite("Exposure", exposure)
    if p < 0.0:
        raise ConversionError(f"Power must be ≥ 0 W, got {p}")
    return p


def unnormalized_factor(kind: str, radius: float = 0.0, sun_angle: float = 0.0) -> float:
    """What Cycles multiplies a light's strength by when its *Normalize* is off.

    Cycles divides a normalised light's strength by the light's area: a point or spot lamp's
    sphere 4πr² (``Light::area`` takes 4 for r = 0), a sun's disc π·sin²(angle/2) (1 for
    angle 0); with Normalize off it does not. ``radius`` is the lamp's own Radius in Blender
    units: Cycles uses neither the object's scale nor the unit scale. Measured with Cycles
    5.0.1 (off/on ratios: 4.0 at r = 0, 0.12549 at r = 0.1 against 4π·0.01 = 0.12566, 0.19229
    for a 0.5 rad sun against π·sin²(0.25) = 0.19229; the object's scale changed nothing) and
    checked by ``test_unnormalized_lights_match_cycles``.
    """
    if kind in ("POINT", "SPOT"):
        r = finite("Radius", radius)
        return 4.0 * math.pi * r * r if r > 0.0 else 4.0
    if kind == "SUN":
        area = math.pi * math.sin(0.5 * finite("Angle", sun_angle)) ** 2
        return area if area > 0.0 else 1.0
    return 1.0


def radiant_intensity_w_sr(power_w: float) -> float:
    """On-axis radiant intensity of a Cycles point/spot light of radius 0: I = P/(4π) W·sr⁻¹ per colour unit."""
    return power_w / FOUR_PI


def render_resolution(res_x: int, res_y: int, percentage: int, scale: float = 1.0) -> tuple[int, int]:
    """Blender's output size, resolution × percentage / 100 truncated as Blender does (63 × 35 px
    at 50 % renders 31 × 17), then Tyndall's preview ``scale`` (rounded; at least 1 px)."""
    w, h = res_x * percentage // 100, res_y * percentage // 100
    if scale != 1.0:
        w, h = round(w * scale), round(h * scale)
    return max(1, w), max(1, h)


def spot_size_deg(spot_size_rad: float) -> float:
    """Blender's Spot Size (full cone angle, radians in the RNA) in degrees, the Tyndall field ``spot_size_deg``."""
    deg = math.degrees(finite("Spot Size", spot_size_rad))
    # The RNA stores radians in 32 bits: its maximum, π, reads as 180.000005°.
    if not 0.1 <= deg <= 180.0 * (1.0 + 2.0**-23):
        raise ConversionError(f"Spot Size must be within 0.1..180°, got {deg}°")
    return min(deg, 180.0)


def spot_blend(blend: float) -> float:
    """Blender's Spot Blend (0..1) unchanged: Cycles' mask is smoothstep((cos θ − cos(s/2)) / (b·(1 − cos(s/2))))."""
    b = finite("Spot Blend", blend)
    if not 0.0 <= b <= 1.0:
        raise ConversionError(f"Spot Blend must be within 0..1, got {b}")
    return b


def spot_mask(cos_theta: float, size_deg: float, blend: float) -> float:
    """Cycles' spot attenuation (``spot_light_attenuation``) for reference and tests."""
    cos_half = math.cos(math.radians(size_deg) / 2.0)
    if blend <= 0.0:
        return 1.0 if cos_theta > cos_half else 0.0
    x = (cos_theta - cos_half) / (blend * (1.0 - cos_half))
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


def volume_scatter_sigma_s(density: float, color: Sequence[float]) -> Rgb:
    """Cycles' Volume Scatter: σ_s = max(Density, 0)·Color per channel (m⁻¹); the extinction is the same σ_s."""
    d = max(finite("Density", density), 0.0)
    c = rgb("Color", color)
    return (d * c[0], d * c[1], d * c[2])


def volume_absorption_sigma_a(density: float, color: Sequence[float]) -> Rgb:
    """Cycles' Volume Absorption: σ_a = max(Density, 0)·(1 − Color) per channel (m⁻¹).

    Cycles does not clamp 1 − Color: a component above 1 gives a negative absorption that
    brightens what lies behind (measured: G = 1.5 rendered 3.8× brighter than the same haze
    with G = 1). Tyndall's media cannot amplify, so that is an error, not a silent clamp."""
    d = max(finite("Density", density), 0.0)
    c = rgb("Color", color)
    if d > 0.0 and max(c) > 1.0:
        raise ConversionError(
            f"Volume Absorption Color {tuple(round(x, 6) for x in c)} has a component above 1: Cycles then "
            "amplifies light (negative absorption), which Tyndall does not model; use components ≤ 1"
        )
    return (d * (1.0 - c[0]), d * (1.0 - c[1]), d * (1.0 - c[2]))


def principled_volume_coefficients(
    density: float, color: Sequence[float], absorption_color: Sequence[float]
) -> tuple[Rgb, Rgb]:
    """(σ_s, σ_a) of Cycles' Principled Volume (``svm_node_principled_volume``), m⁻¹.

    σ_s = D·C; σ_a = D·max(1 − C, 0)·max(1 − √A, 0) with A the Absorption Color
    (black by default, so σ_a = D·(1 − C)). Read from the Cycles source, not measured.
    """
    d = max(finite("Density", density), 0.0)
    c = rgb("Color", color)
    a = rgb("Absorption Color", absorption_color)
    s = (d * c[0], d * c[1], d * c[2])
    ab = tuple(d * max(1.0 - c[i], 0.0) * max(1.0 - math.sqrt(a[i]), 0.0) for i in range(3))
    return s, (ab[0], ab[1], ab[2])


def anisotropy_g(g: float) -> float:
    """Anisotropy g clamped as Cycles does (|g| ≤ 0.999; Tyndall needs −1 < g < 1)."""
    v = finite("Anisotropy", g)
    return max(-0.999, min(0.999, v))


def phase_from_volume_scatter(phase: str, anisotropy: float = 0.0, alpha: float = 1.0) -> dict[str, object]:
    """Tyndall phase function of a Blender 5 Volume Scatter ``phase`` enum.

    HENYEY_GREENSTEIN → ``henyey_greenstein`` (|g| < 1e-3 → ``isotropic``, as Cycles);
    RAYLEIGH → ``rayleigh``; DRAINE with Alpha = 1 → ``cornette_shanks`` (exactly equal);
    DRAINE with Alpha = 1 and g ≈ 0 is Rayleigh. Other phases raise :class:`ConversionError`.
    """
    if phase == "HENYEY_GREENSTEIN":
        g = anisotropy_g(anisotropy)
        if abs(g) < 1e-3:
            return {"type": "isotropic"}
        return {"type": "henyey_greenstein", "g": g}
    if phase == "RAYLEIGH":
        return {"type": "rayleigh"}
    if phase == "DRAINE":
        a = finite("Alpha", alpha)
        if abs(a - 1.0) > 1e-6:
            raise ConversionError(
                f"Draine phase with Alpha = {a:g} is not supported: "
                "Tyndall has Draine only for Alpha = 1 (Cornette–Shanks)"
            )
        g = anisotropy_g(anisotropy)
        if abs(g) < 1e-3:
            return {"type": "rayleigh"}
        return {"type": "cornette_shanks", "g": g}
    names = {"FOURNIER_FORAND": "Fournier–Forand", "MIE": "Mie"}
    raise ConversionError(
        f"the {names.get(phase, phase)} phase function is not supported by Tyndall "
        "(use Henyey-Greenstein, Rayleigh or Draine with Alpha 1)"
    )


def phase_from_principled_volume(anisotropy: float) -> dict[str, object]:
    """Principled Volume scatters with Henyey–Greenstein of its Anisotropy."""
    return phase_from_volume_scatter("HENYEY_GREENSTEIN", anisotropy)


_LAYER_NAME = re.compile(r"[^A-Za-z0-9_]")


def layer_safe_name(name: str) -> str:
    """A light name usable in an EXR layer (``inscatter.<name>``) and as a Cycles light group.

    Blender names like ``Spot.001`` contain dots, which EXR readers take as layer separators.
    """
    s = _LAYER_NAME.sub("_", name.strip()) or "light"
    return s


def unique_names(names: Sequence[str]) -> list[str]:
    """:func:`layer_safe_name` of each name, made unique by ``_2``, ``_3``, … suffixes."""
    seen: set[str] = set()
    out: list[str] = []
    for n in names:
        base = layer_safe_name(n)
        cand, k = base, 2
        while cand in seen:
            cand = f"{base}_{k}"
            k += 1
        seen.add(cand)
        out.append(cand)
    return out


def quaternion_wxyz_from_rows(m: Sequence[Sequence[float]]) -> tuple[float, float, float, float]:
    """Rotation quaternion [w, x, y, z] of the rotation part of a 3×3 (or 4×4) matrix given by rows.

    Axis scale is removed first (columns normalised); a reflection is not a rotation and raises.
    """
    cols = [[float(m[r][c]) for r in range(3)] for c in range(3)]
    for i, col in enumerate(cols):
        n = math.sqrt(sum(x * x for x in col))
        if not math.isfinite(n) or n < 1e-300:
            raise ConversionError(f"degenerate transform: axis {i} has length {n}")
        cols[i] = [x / n for x in col]
    r = [[cols[c][row] for c in range(3)] for row in range(3)]
    det = (
        r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
        - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
        + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0])
    )
    if det <= 0.0:
        raise ConversionError("the transform mirrors (negative scale): not a rotation")
    tr = r[0][0] + r[1][1] + r[2][2]
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        w, x, y, z = 0.25 * s, (r[2][1] - r[1][2]) / s, (r[0][2] - r[2][0]) / s, (r[1][0] - r[0][1]) / s
    elif r[0][0] > r[1][1] and r[0][0] > r[2][2]:
        s = math.sqrt(1.0 + r[0][0] - r[1][1] - r[2][2]) * 2.0
        w, x, y, z = (r[2][1] - r[1][2]) / s, 0.25 * s, (r[0][1] + r[1][0]) / s, (r[0][2] + r[2][0]) / s
    elif r[1][1] > r[2][2]:
        s = math.sqrt(1.0 + r[1][1] - r[0][0] - r[2][2]) * 2.0
        w, x, y, z = (r[0][2] - r[2][0]) / s, (r[0][1] + r[1][0]) / s, 0.25 * s, (r[1][2] + r[2][1]) / s
    else:
        s = math.sqrt(1.0 + r[2][2] - r[0][0] - r[1][1]) * 2.0
        w, x, y, z = (r[1][0] - r[0][1]) / s, (r[0][2] + r[2][0]) / s, (r[1][2] + r[2][1]) / s, 0.25 * s
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return (w / n, x / n, y / n, z / n)


def _dot(a: Sequence[float], b: Sequence[float]) -> float:
    return sum(p * q for p, q in zip(a, b, strict=True))


def _cross(a: Sequence[float], b: Sequence[float]) -> list[float]:
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


@dataclass
class Frame:
    """What an object's world matrix says about its orientation (see :func:`frame_from_rows`)."""

    quaternion_wxyz: tuple[float, float, float, float]
    #: Largest departure of two axes from perpendicular, degrees (a shear of a parent's non-uniform scale).
    shear_deg: float
    #: The matrix mirrors (negative determinant).
    mirrored: bool
    #: Lengths of the local X, Y and Z axes (object and parents' scale).
    scale: tuple[float, float, float]


def frame_from_rows(m: Sequence[Sequence[float]]) -> Frame:
    """The rotation that keeps an object's local −Z axis (a camera's view, a lamp's beam) exactly
    and its local Y as nearly as a rotation can, from a 3×3 or 4×4 matrix given by rows.

    A parent's non-uniform scale can shear a child's axes, and a negative scale mirrors them;
    neither is a rotation. The quaternion is that of Z = the normalised third column, Y = the
    second column made perpendicular to it, X = Y × Z; what it leaves out is returned beside it.
    """
    cols = [[float(m[r][c]) for r in range(3)] for c in range(3)]
    lengths = []
    for i, col in enumerate(cols):
        n = math.sqrt(sum(x * x for x in col))
        if not math.isfinite(n) or n < 1e-300:
            raise ConversionError(f"degenerate transform: axis {i} has length {n}")
        lengths.append(n)
        cols[i] = [x / n for x in col]
    x, y, z = cols
    angles = (math.degrees(math.acos(max(-1.0, min(1.0, _dot(a, b))))) for a, b in ((x, y), (y, z), (z, x)))
    shear = max(abs(90.0 - a) for a in angles)
    mirrored = _dot(_cross(x, y), z) < 0.0
    y_perp = [b - _dot(y, z) * a for a, b in zip(z, y, strict=True)]
    n = math.sqrt(_dot(y_perp, y_perp))
    if n < 1e-12:
        raise ConversionError("degenerate transform: the local Y and Z axes are parallel")
    y_perp = [v / n for v in y_perp]
    x_new = _cross(y_perp, z)
    rows = [[x_new[r], y_perp[r], z[r]] for r in range(3)]
    return Frame(quaternion_wxyz_from_rows(rows), shear, mirrored, (lengths[0], lengths[1], lengths[2]))


def sun_angles_from_direction(direction_to_sun: Sequence[float]) -> tuple[float, float]:
    """(elevation, Blender Sun Rotation) in degrees of a vector towards the sun.

    A Sun lamp shines along its local −Z, so its local +Z (the third column of its
    world matrix) points at the sun. Elevation = asin(ẑ); Sun Rotation = atan2(x, y),
    the convention of ``tyndall.sky`` and Blender's Sky Texture.
    """
    x, y, z = (finite("sun direction", v) for v in direction_to_sun[:3])
    n = math.sqrt(x * x + y * y + z * z)
    if n < 1e-12:
        raise ConversionError("zero-length sun direction")
    x, y, z = x / n, y / n, z / n
    elev = math.degrees(math.asin(max(-1.0, min(1.0, z))))
    rot = math.degrees(math.atan2(x, y)) if abs(x) + abs(y) > 1e-15 else 0.0
    return elev, rot
