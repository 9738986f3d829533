"""Bodies that move through the survey: cars, cyclists, pedestrians, birds, a barrier arm.

Each is cast at every pulse's own instant: a body moving at constant velocity is still in its
own frame, so the ray's origin is moved back by velocity x (t - t_ref) and the static
intersection applies; the barrier arm's axis turns with time.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lidar_outliers.tools.simulator import raycast as rc
from lidar_outliers.tools.simulator.family import ARM


@dataclass(frozen=True, eq=False)
class Mover:
    """A body in constant motion: boxes (k, 6), a vertical cylinder (cx, cy, r, z0, z1) or an
    ellipsoid (centre, semi-axes), as placed at ``t_ref``, moving at ``velocity`` (3,)."""

    kind: int
    label: str
    velocity: np.ndarray
    t_ref: float
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    cylinder: np.ndarray | None = None
    ellipsoid: np.ndarray | None = None

    def extent(self, t0: float, t1: float) -> tuple[float, float, float, float]:
        """x min, x max, y min, y max swept between t0 and t1."""
        parts = [self.boxes[:, [0, 3, 1, 4]]]
        if self.cylinder is not None:
            cx, cy, r = self.cylinder[:3]
            parts.append(np.array([[cx - r, cx + r, cy - r, cy + r]]))
        if self.ellipsoid is not None:
            c, s = self.ellipsoid[:3], self.ellipsoid[3:]
            parts.append(np.array([[c[0] - s[0], c[0] + s[0], c[1] - s[1], c[1] + s[1]]]))
        b = np.vstack(parts)
        lo = np.array([b[:, 0].min(), b[:, 2].min()])
        hi = np.array([b[:, 1].max(), b[:, 3].max()])
        shifts = np.array([self.velocity[:2] * (t - self.t_ref) for t in (t0, t1)])
        return (lo[0] + shifts[:, 0].min(), hi[0] + shifts[:, 0].max(),
                lo[1] + shifts[:, 1].min(), hi[1] + shifts[:, 1].max())

    def cast(self, o: np.ndarray, d: np.ndarray, t: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
        """First hit of rays fired at times t: the body is still in its own frame."""
        oo = o - np.outer(t - self.t_ref, self.velocity)
        best = np.full(len(o), np.inf)
        normal = np.zeros_like(o)
        for box in self.boxes:
            th, nrm = rc.hit_box(oo, d, box[:3], box[3:])
            closer = th < best
            best[closer], normal[closer] = th[closer], nrm[closer]
        if self.cylinder is not None:
            cx, cy, r, z0, z1 = self.cylinder
            th, nrm = rc.hit_vertical_cylinder(oo, d, cx, cy, r, z0, z1)
            closer = th < best
            best[closer], normal[closer] = th[closer], nrm[closer]
        if self.ellipsoid is not None:
            c, s = self.ellipsoid[:3], self.ellipsoid[3:]
            th, _ = rc.hit_ellipsoid(oo, d, c, s)
            th = np.where(th > rc.EPS, th, np.inf)
            p = oo + np.where(np.isfinite(th), th, 0.0)[:, None] * d
            closer = th < best
            best[closer], normal[closer] = th[closer], rc.ellipsoid_normal(p, c, s)[closer]
        return best, normal

    def contains(self, p: np.ndarray, t: np.ndarray, pad: float) -> np.ndarray:
        """Whether points p (n, 3) lie within ``pad`` of the body at times t."""
        q = p - np.outer(t - self.t_ref, self.velocity)
        inside = np.zeros(len(p), dtype=bool)
        for box in self.boxes:
            inside |= np.all((q >= box[:3] - pad) & (q <= box[3:] + pad), axis=1)
        if self.cylinder is not None:
            cx, cy, r, z0, z1 = self.cylinder
            inside |= ((np.hypot(q[:, 0] - cx, q[:, 1] - cy) <= r + pad)
                       & (q[:, 2] >= z0 - pad) & (q[:, 2] <= z1 + pad))
        if self.ellipsoid is not None:
            c, s = self.ellipsoid[:3], self.ellipsoid[3:]
            inside |= np.sum(((q - c) / (s + pad)) ** 2, axis=1) <= 1.0
        return inside


@dataclass(frozen=True, eq=False)
class Arm:
    """A barrier arm on a post at the road edge, turning about the street's x direction
    between horizontal (across the road) and vertical, one cycle per ``period`` seconds."""

    pivot: np.ndarray
    side: int  # the post stands at y = side x (half width + 0.3); down, the arm points inward
    length: float
    radius: float
    period: float
    phase: float

    def axis(self, t: np.ndarray) -> np.ndarray:
        theta = 0.25 * np.pi * (1 - np.cos(2 * np.pi * (t - self.phase) / self.period))
        return np.column_stack([np.zeros_like(t), -self.side * np.cos(theta), np.sin(theta)])

    def extent(self, t0: float, t1: float) -> tuple[float, float, float, float]:
        x, y = self.pivot[0], self.pivot[1]
        r = self.radius
        return (x - r, x + r, min(y, y - self.side * self.length) - r,
                max(y, y - self.side * self.length) + r)

    def cast(self, o: np.ndarray, d: np.ndarray, t: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
        return rc.hit_cylinder_axis(o, d, self.pivot, self.axis(t), self.radius, self.length)

    def contains(self, p: np.ndarray, t: np.ndarray, pad: float) -> np.ndarray:
        """Whether points p (n, 3) lie within ``pad`` of the arm at times t."""
        axis = self.axis(t)
        w = p - self.pivot
        s = np.clip(np.sum(w * axis, axis=1), 0.0, self.length)
        return np.linalg.norm(w - s[:, None] * axis, axis=1) <= self.radius + pad


def cast_dynamic(o: np.ndarray, d: np.ndarray, t: np.ndarray, bodies: list[Mover | Arm],
                 bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hit on any moving body: range (inf: none), body index (-1), |cos incidence|."""
    best = np.full(len(o), np.inf)
    which = np.full(len(o), -1, dtype=np.int16)
    cos = np.ones(len(o), dtype=np.float32)
    if not len(o):
        return best, which, cos
    t0, t1 = float(t.min()), float(t.max())
    reach = (bounds[:, 0].min(), bounds[:, 1].max(), bounds[:, 2].min(), bounds[:, 3].max())
    for j, body in enumerate(bodies):
        x0, x1, y0, y1 = body.extent(t0, t1)
        if reach[1] < x0 or reach[0] > x1 or reach[3] < y0 or reach[2] > y1:
            continue
        idx = np.flatnonzero((bounds[:, 1] >= x0) & (bounds[:, 0] <= x1)
                             & (bounds[:, 3] >= y0) & (bounds[:, 2] <= y1))
        if not len(idx):
            continue
        th, nrm = body.cast(o[idx], d[idx], t[idx])
        closer = th < best[idx]
        rows = idx[closer]
        best[rows], which[rows] = th[closer], j
        cos[rows] = np.abs(np.sum(nrm[closer] * d[idx][closer], axis=1))
    return best, which, cos




def body_kind(body: Mover | Arm) -> int:
    """The outlier kind of a body's returns."""
    return ARM if isinstance(body, Arm) else body.kind
