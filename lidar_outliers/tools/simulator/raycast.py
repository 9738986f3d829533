"""Analytic ray casting: where a laser beam first meets each kind of surface.

Every function takes ray origins ``o`` (n, 3) and unit directions ``d`` (n, 3) and returns the
ray parameter ``t`` (n,) of the first intersection in front of the origin (``inf`` where the ray
misses), most also the unit surface normal (n, 3) there. Beams are straight lines; every surface
is solved in closed form (a quadric or a plane), so a simulated return lies on its surface to
rounding, with no tessellation error for a detector to learn.
"""

from __future__ import annotations

import numpy as np

#: Smallest accepted ray parameter: a ray starting on a surface does not hit it again.
EPS = 1e-6


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of two (n, 3) arrays."""
    return np.einsum("ij,ij->i", a, b)


def nearest_positive_root(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Smaller positive root of a t^2 + b t + c = 0 elementwise (inf if none)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = b * b - 4 * a * c
        sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
        linear = np.abs(a) < 1e-12
        r1 = np.where(linear, -c / b, (-b - sq) / (2 * a))
        r2 = np.where(linear, np.inf, (-b + sq) / (2 * a))
    lo, hi = np.minimum(r1, r2), np.maximum(r1, r2)
    t = np.where(lo > EPS, lo, np.where(hi > EPS, hi, np.inf))
    return np.where(np.isnan(t), np.inf, t)


def hit_road(o: np.ndarray, d: np.ndarray, half_width: float, crown: float, grade: float,
             lift: float | np.ndarray = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Ray vs the crowned road z = g x - a y^2 + lift for |y| <= half_width (a = crown / hw^2).

    The surface is a parabolic cylinder, so t solves a quadratic. ``lift`` raises the surface
    (per ray, or one value): the same call gives the level ``lift`` metres above the asphalt.
    """
    a_ = crown / half_width**2
    oz = o[:, 2] - lift
    qa = a_ * d[:, 1] ** 2
    qb = 2 * a_ * o[:, 1] * d[:, 1] + d[:, 2] - grade * d[:, 0]
    qc = a_ * o[:, 1] ** 2 + oz - grade * o[:, 0]
    t = nearest_positive_root(qa, qb, qc)
    y = o[:, 1] + np.where(np.isfinite(t), t, 0.0) * d[:, 1]
    t = np.where(np.abs(y) <= half_width, t, np.inf)
    n = np.stack([np.full_like(y, -grade), 2 * a_ * y, np.ones_like(y)], axis=1)
    return t, n / np.linalg.norm(n, axis=1, keepdims=True)


def plane_t(o: np.ndarray, d: np.ndarray, axis: int, value: float) -> np.ndarray:
    """Ray vs the axis-aligned plane ``coordinate[axis] = value``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (value - o[:, axis]) / d[:, axis]
    return np.where(t > EPS, t, np.inf)


def slab(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Entry t, exit t and entry axis of rays through the axis-aligned box [lo, hi].

    Kay & Kajiya's slab method; entry is -inf for a ray starting inside, and entry > exit for a
    ray that misses.
    """
    n = len(o)
    t_in = np.full(n, -np.inf)
    t_out = np.full(n, np.inf)
    face = np.zeros(n, dtype=np.int8)
    with np.errstate(divide="ignore", invalid="ignore"):
        for ax in range(3):
            inv = 1.0 / d[:, ax]
            t1 = (lo[..., ax] - o[:, ax]) * inv
            t2 = (hi[..., ax] - o[:, ax]) * inv
            near = np.fmin(t1, t2)
            near = np.where(np.isnan(near), -np.inf, near)
            far = np.fmax(t1, t2)
            far = np.where(np.isnan(far), np.inf, far)
            # a ray parallel to the slab and outside it never enters
            outside = (d[:, ax] == 0) & ((o[:, ax] < lo[..., ax]) | (o[:, ax] > hi[..., ax]))
            far = np.where(outside, -np.inf, far)
            later = near > t_in
            face[later] = ax
            t_in = np.where(later, near, t_in)
            t_out = np.minimum(t_out, far)
    return t_in, t_out, face


def hit_box(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Ray vs the outside of an axis-aligned box; entry t and the entry face's normal."""
    t_in, t_out, face = slab(o, d, lo, hi)
    t = np.where((t_in <= t_out) & (t_in > EPS), t_in, np.inf)
    nrm = np.zeros_like(o)
    rows = np.arange(len(o))
    nrm[rows, face] = -np.sign(d[rows, face])
    return t, nrm


def box_exit(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Ray from inside a box to its wall (a room seen through a window): exit t and the inward
    normal of the wall it meets. ``lo``, ``hi``: (3,) or one box per ray (n, 3)."""
    n = len(o)
    t_out = np.full(n, np.inf)
    face = np.zeros(n, dtype=np.int8)
    with np.errstate(divide="ignore", invalid="ignore"):
        for ax in range(3):
            far = np.fmax((lo[..., ax] - o[:, ax]) / d[:, ax], (hi[..., ax] - o[:, ax]) / d[:, ax])
            far = np.where(np.isnan(far), np.inf, far)
            sooner = far < t_out
            face[sooner] = ax
            t_out = np.where(sooner, far, t_out)
    nrm = np.zeros_like(o)
    rows = np.arange(n)
    nrm[rows, face] = -np.sign(d[rows, face])
    return np.where(t_out > EPS, t_out, np.inf), nrm


def hit_vertical_cylinder(o: np.ndarray, d: np.ndarray, cx: float, cy: float, radius: float,
                          z0: float, z1: float, cap: bool = True
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Ray vs the side (and top cap) of the cylinder (x-cx)^2+(y-cy)^2 <= r^2, z0 <= z <= z1."""
    wx, wy = o[:, 0] - cx, o[:, 1] - cy
    qa = d[:, 0] ** 2 + d[:, 1] ** 2
    qb = 2 * (wx * d[:, 0] + wy * d[:, 1])
    qc = wx**2 + wy**2 - radius**2
    t_side = nearest_positive_root(qa, qb, qc)
    z = o[:, 2] + t_side * d[:, 2]
    t_side = np.where((z >= z0) & (z <= z1), t_side, np.inf)
    n = np.zeros_like(o)
    ts = np.where(np.isfinite(t_side), t_side, 0.0)
    n[:, 0] = wx + ts * d[:, 0]
    n[:, 1] = wy + ts * d[:, 1]
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    if cap:
        t_top = plane_t(o, d, 2, z1)
        r2 = (wx + t_top * d[:, 0]) ** 2 + (wy + t_top * d[:, 1]) ** 2
        t_top = np.where(r2 <= radius**2, t_top, np.inf)
        top = t_top < t_side
        n[top] = [0.0, 0.0, 1.0]
        t_side = np.where(top, t_top, t_side)
    return t_side, n


def hit_cylinder_axis(o: np.ndarray, d: np.ndarray, p0: np.ndarray, axis: np.ndarray,
                      radius: float, length: float) -> tuple[np.ndarray, np.ndarray]:
    """Ray vs the side of a finite cylinder from p0 along unit axis (per ray, (n, 3))."""
    w = o - p0
    dd = d - np.sum(d * axis, axis=1, keepdims=True) * axis
    ww = w - np.sum(w * axis, axis=1, keepdims=True) * axis
    qa = dot(dd, dd)
    qb = 2 * dot(dd, ww)
    qc = dot(ww, ww) - radius**2
    t = nearest_positive_root(qa, qb, qc)
    tt = np.where(np.isfinite(t), t, 0.0)[:, None]
    s = dot((w + tt * d), axis)
    t = np.where((s >= 0) & (s <= length), t, np.inf)
    n = ww + tt * dd
    with np.errstate(invalid="ignore"):
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return t, n


def hit_ellipsoid(o: np.ndarray, d: np.ndarray, centre: np.ndarray, semi: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit t of rays through an axis-aligned ellipsoid (inf, inf when they miss).

    ``centre`` is (3,) or per ray (n, 3) (a drifting cloud); a ray starting inside enters at 0.
    """
    oo = (o - centre) / semi
    dd = d / semi
    qa = dot(dd, dd)
    qb = 2 * dot(oo, dd)
    qc = dot(oo, oo) - 1.0
    disc = qb * qb - 4 * qa * qc
    with np.errstate(invalid="ignore"):
        sq = np.sqrt(np.where(disc > 0, disc, np.nan))
    t_in = (-qb - sq) / (2 * qa)
    t_out = (-qb + sq) / (2 * qa)
    ok = np.isfinite(t_in) & (t_out > EPS)
    return np.where(ok, np.maximum(t_in, 0.0), np.inf), np.where(ok, t_out, np.inf)


def ellipsoid_normal(p: np.ndarray, centre: np.ndarray, semi: np.ndarray) -> np.ndarray:
    """Outward unit normal of an axis-aligned ellipsoid at points p (n, 3) on or near it."""
    n = (p - centre) / semi**2
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def reflect(d: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Specular reflection of directions d (n, 3) about unit normals (n, 3) or (3,)."""
    nrm = np.broadcast_to(normal, d.shape)
    return d - 2.0 * dot(d, nrm)[:, None] * nrm
