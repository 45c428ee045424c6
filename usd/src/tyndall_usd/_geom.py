"""Frames, transforms and polygon triangulation (pure Python + numpy + pxr.Gf; no bpy)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from pxr import Gf, UsdGeom

#: Rotation of a Y-up stage into Tyndall's Z-up world (+90° about X: +Y → +Z, +Z → −Y),
#: the rotation Blender's USD importer applies to Y-up stages.
Y_UP_TO_Z_UP = Gf.Matrix4d().SetRotate(Gf.Rotation(Gf.Vec3d(1.0, 0.0, 0.0), 90.0))


def stage_to_world(up_axis: str, meters_per_unit: float) -> Gf.Matrix4d:
    """The matrix (USD's row-vector convention) from stage world space to Tyndall's world (m, Z up)."""
    m = Gf.Matrix4d().SetScale(Gf.Vec3d(meters_per_unit, meters_per_unit, meters_per_unit))
    if up_axis == UsdGeom.Tokens.y:
        m = m * Y_UP_TO_Z_UP
    return m


def det3(m: Gf.Matrix4d) -> float:
    """Determinant of the upper-left 3×3 block."""
    return float(Gf.Matrix3d(*[m[i][j] for i in range(3) for j in range(3)]).GetDeterminant())


def is_finite_matrix(m: Gf.Matrix4d) -> bool:
    return all(math.isfinite(m[i][j]) for i in range(4) for j in range(4))


def to_row_major(m: Gf.Matrix4d) -> list[list[float]]:
    """Tyndall's row-major 4×4 (column vectors, translation in the last column) of a USD matrix."""
    rows = [[float(m[j][i]) for j in range(4)] for i in range(3)]
    return [*rows, [0.0, 0.0, 0.0, 1.0]]


def axis(m: Gf.Matrix4d, i: int) -> Gf.Vec3d:
    """Image of local axis ``i`` under the linear part of ``m`` (row ``i`` in USD's convention)."""
    return Gf.Vec3d(m[i][0], m[i][1], m[i][2])


def frame_quaternion(m: Gf.Matrix4d) -> list[float]:
    """``[w, x, y, z]`` of the rotation whose local −Z and +Y follow ``m``'s (scale and shear removed).

    The local Z axis is kept exactly; X is made orthogonal to it; Y = Z × X.
    """
    z = axis(m, 2).GetNormalized()
    x = axis(m, 0)
    x = (x - z * Gf.Dot(x, z)).GetNormalized()
    y = Gf.Cross(z, x)
    r = Gf.Matrix3d(x[0], x[1], x[2], y[0], y[1], y[2], z[0], z[1], z[2])
    q = r.ExtractRotation().GetQuat()
    im = q.GetImaginary()
    return [float(q.GetReal()), float(im[0]), float(im[1]), float(im[2])]


def turned_box(m: Gf.Matrix4d, lo: Gf.Vec3d, hi: Gf.Vec3d) -> tuple[dict[str, list[float]] | None, str]:
    """Tyndall's ``bounds.box`` of the local box ``[lo, hi]`` placed by ``m`` (local → world).

    When ``m`` turns the box (its axes are orthogonal but not along the world's), the box with
    ``rotation_wxyz`` about its centre and ``""``. Otherwise ``None`` and why: ``"aligned"``
    (the world-space axis-aligned bound is then exact) or ``"sheared"`` (no box matches). The
    axes must be orthogonal to 1e-6 relative: float32 matrices (Blender's export) are.
    """
    axes = [axis(m, i) for i in range(3)]
    lens = [a.GetLength() for a in axes]
    if not all(math.isfinite(n) and n > 0.0 for n in lens):
        return None, "sheared"
    for i, j in ((0, 1), (0, 2), (1, 2)):
        if abs(Gf.Dot(axes[i], axes[j])) > 1e-6 * lens[i] * lens[j]:
            return None, "sheared"
    u = [axes[i] / lens[i] for i in range(3)]
    if all(sum(abs(c) > 1e-12 for c in ui) == 1 for ui in u):
        return None, "aligned"
    if Gf.Dot(Gf.Cross(u[0], u[1]), u[2]) < 0.0:
        u[0] = -u[0]  # a mirrored box is the same box: keep a proper rotation
    r = Gf.Matrix3d(*u[0], *u[1], *u[2])
    q = r.ExtractRotation().GetQuat()
    im = q.GetImaginary()
    centre = m.Transform((lo + hi) * 0.5)
    half = [(hi[i] - lo[i]) * 0.5 * lens[i] for i in range(3)]
    box = {
        "min": [float(centre[i] - half[i]) for i in range(3)],
        "max": [float(centre[i] + half[i]) for i in range(3)],
        "rotation_wxyz": [float(q.GetReal()), float(im[0]), float(im[1]), float(im[2])],
    }
    return box, ""


def mean_axis_scale(m: Gf.Matrix4d) -> float:
    """Mean length of the images of the three local axes (the light-radius scale)."""
    return sum(axis(m, i).GetLength() for i in range(3)) / 3.0


def rotate_wxyz(q: Sequence[float], v: Sequence[float]) -> list[float]:
    """Rotate vector ``v`` by the quaternion ``[w, x, y, z]``."""
    rot = Gf.Rotation(Gf.Quatd(q[0], Gf.Vec3d(q[1], q[2], q[3])))
    out = rot.TransformDir(Gf.Vec3d(*v))
    return [float(out[0]), float(out[1]), float(out[2])]


def quaternion_from_to(a: Sequence[float], b: Sequence[float]) -> Gf.Quatd:
    """The shortest rotation taking direction ``a`` to direction ``b``."""
    return Gf.Rotation(Gf.Vec3d(*a), Gf.Vec3d(*b)).GetQuat()


# ---------------------------------------------------------------- triangulation


def _ear_clip(pts2: np.ndarray) -> list[tuple[int, int, int]] | None:
    """Ear clipping of a counter-clockwise simple polygon; ``None`` if no ear is found."""
    idx = list(range(len(pts2)))
    tris: list[tuple[int, int, int]] = []

    def cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    guard = 0
    while len(idx) > 3:
        guard += 1
        if guard > 4 * len(pts2) * len(pts2):
            return None
        found = False
        n = len(idx)
        for k in range(n):
            i0, i1, i2 = idx[(k - 1) % n], idx[k], idx[(k + 1) % n]
            a, b, c = pts2[i0], pts2[i1], pts2[i2]
            if cross(a, b, c) <= 0.0:
                continue  # reflex or degenerate corner
            inside = False
            for j in idx:
                if j in (i0, i1, i2):
                    continue
                p = pts2[j]
                if cross(a, b, p) >= 0.0 and cross(b, c, p) >= 0.0 and cross(c, a, p) >= 0.0:
                    inside = True
                    break
            if not inside:
                tris.append((i0, i1, i2))
                del idx[k]
                found = True
                break
        if not found:
            return None
    tris.append((idx[0], idx[1], idx[2]))
    return tris


def triangulate_polygon(points: np.ndarray, face: Sequence[int]) -> list[tuple[int, int, int]]:
    """Triangles (vertex indices, the polygon's winding kept) of one planar polygon.

    Concave polygons are ear-clipped in the plane of their Newell normal; a polygon
    that cannot be ear-clipped (self-intersecting, degenerate) falls back to a fan.
    """
    n = len(face)
    if n == 3:
        return [(face[0], face[1], face[2])]
    p = points[list(face)]
    normal = np.zeros(3)
    for i in range(n):
        a, b = p[i], p[(i + 1) % n]
        normal += np.array(
            [(a[1] - b[1]) * (a[2] + b[2]), (a[2] - b[2]) * (a[0] + b[0]), (a[0] - b[0]) * (a[1] + b[1])]
        )
    k = int(np.argmax(np.abs(normal)))
    fan = [(face[0], face[i], face[i + 1]) for i in range(1, n - 1)]
    if normal[k] == 0.0:
        return fan
    u, v = [(1, 2), (2, 0), (0, 1)][k]
    pts2 = p[:, [u, v]].astype(float)
    if normal[k] < 0.0:
        pts2[:, 1] = -pts2[:, 1]  # make the projected polygon counter-clockwise
    tris = _ear_clip(pts2)
    if tris is None:
        return fan
    return [(face[a], face[b], face[c]) for a, b, c in tris]


def triangulate(points: np.ndarray, counts: np.ndarray, indices: np.ndarray, skip: set[int]) -> list[list[int]]:
    """Triangulate a USD polygon mesh (faces in ``skip`` left out); keeps each face's winding."""
    out: list[list[int]] = []
    start = 0
    for f, c in enumerate(counts.tolist()):
        face = indices[start : start + c].tolist()
        start += c
        if f in skip or c < 3:
            continue
        out.extend([list(t) for t in triangulate_polygon(points, face)])
    return out
