"""Free-space evidence: points floating where other beams saw through.

The paper counts moving objects and airborne returns as outliers (exhaust condensation, spurious
returns over water, a passing car); a surface test cannot see them when they are smooth (a moving
barrier arm is a clean cylinder) or dense. Static surfaces are opaque: no beam ever passes through
them. So a point p is transient when at least ``min_rays`` beams of the survey passed within
``radius`` of p and ended more than ``margin`` metres beyond it (they saw through p's place).

This needs the scanner position of every beam. Mobile-mapping systems deliver it as a trajectory
(time, x, y, z of a reference point) plus each scanner's lever arm; :func:`scanner_origins`
turns those into one origin per point (heading from the trajectory's horizontal motion).

Beams are walked cell by cell (an exact 3D DDA) through a uniform grid in which every point is
registered in each cell its ``radius``-ball touches; only points in the cells a beam crosses are
tested against it, so the cost is the total beam length over the cell size plus the candidate
tests, and the result equals the brute-force test of every beam against every point. The walk
stops ``margin`` before the beam's own return: a beam grazing a road near its end is not
evidence against the road.

Defaults (measured on the simulated clouds A, B, C, see ``benchmarks/bench_mobile.py``):
``radius`` 6 mm (two range-noise sigmas: a 2 cm tube let beams skimming car edges "see through"
the edge points, 0.1-0.2 % false alarms), ``margin`` 8 cm (mist 3 cm above a puddle is still
seen through by beams ending beyond it; at 4 cm beams grazing the ground start to count), one
beam is enough. ``margin`` is the least: a beam that meets the surface at its end at a grazing
angle g runs within ``radius`` of that surface's own points over its last (radius + 8 x
roughness) / sin g metres, so its margin grows to that (:func:`grazing_margins`; range noise
over the sine of the incidence angle), whatever the range and the mounting.

A beam that passes a point on some pulses may return at it on others: the edge of a surface
that part of the footprint hits, or the same spot seen on every turn of a scanner that stands
still, whose beams a lever arm a few centimetres off moves past its own returns. A droplet is
almost never returned to. So with the points' times a point stays flagged only while the
returns of other pulses along its own beam (within ``radius`` across the line from its origin
through it, ``margin`` along it: :func:`beam_returns`) number at most ``hit_ratio`` times the
beams that saw through it (0.5: an edge is hit about half the time).
"""

from __future__ import annotations

import numpy as np

from algorithms.columns import column_max, column_min
from algorithms.errors import ParameterError
from algorithms.jit import njit, prange
from algorithms.result import DetectorResult
from algorithms.threads import worker_threads
from algorithms.transient import TransientParameters

#: Largest number of grid cells before the cell edge is doubled (memory of the cell index).
MAX_CELLS = 60_000_000
#: Metres of path over which the vehicle's heading is taken (:func:`_headings`).
HEADING_BASELINE = 1.0
#: Points (the return itself included) whose plane gives the surface at a beam's end.
SURFACE_NEIGHBOURS = 10
#: Points per batch of surface fits (bounds memory to ~100 MB).
NORMAL_BATCH = 200_000
#: How far apart two points of one surface may lie across it, in multiples of its roughness
#: (the difference of two offsets has sigma r sqrt 2: about 6 sigmas of it, for millions of
#: beam and point pairs, and a roughness estimated from few points).
ROUGHNESS_SPAN = 8.0
#: Beams flatter than this to the surface at their end are taken at this angle (sin 1 deg:
#: a beam's last (radius + 8 r) / 0.017 metres, about 0.35 m for r = 0, are no evidence).
MIN_GRAZING_DEGREES = 1.0


def scanner_origins(
    gps_time: np.ndarray,
    source_id: np.ndarray,
    trajectory: np.ndarray,
    lever_arms: dict[int, tuple[float, float, float]],
) -> np.ndarray:
    """Scanner position (n, 3) for each point from a trajectory and per-scanner lever arms.

    gps_time (n,) s; source_id (n,) scanner id; trajectory (m, 4) rows of time, x, y, z of the
    vehicle's reference point, sorted by time; lever_arms: scanner id -> (forward, left, up)
    metres in the vehicle frame. The heading is that of the horizontal motion over a metre of
    path (:func:`vehicle_pose`).
    """
    return posed_origins(*vehicle_pose(gps_time, trajectory), source_id, lever_arms)


def posed_origins(
    pos: np.ndarray, h: np.ndarray, source_id: np.ndarray,
    lever_arms: dict[int, tuple[float, float, float]],
) -> np.ndarray:
    """Scanner position (n, 3) for each point from the vehicle's reference point ``pos``
    (n, 3) and heading ``h`` (n,) at its time (:func:`vehicle_pose`) and the lever arms."""
    fwd = np.column_stack([np.cos(h), np.sin(h)])
    left = np.column_stack([-np.sin(h), np.cos(h)])
    arm = np.zeros((len(pos), 3))
    for sid, (f, lft, up) in lever_arms.items():
        m = source_id == sid
        arm[m, :2] = f * fwd[m] + lft * left[m]
        arm[m, 2] = up
    return pos + arm


def vehicle_pose(gps_time: np.ndarray, trajectory: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) reference point and (n,) heading (radians) of the vehicle at each time: positions
    interpolated, the heading of the nearest sample (:func:`_headings`)."""
    traj = np.asarray(trajectory, dtype=np.float64)
    if traj.ndim != 2 or traj.shape[1] != 4 or len(traj) < 2:
        raise ParameterError("trajectory must have rows of time x y z (at least two)")
    tt = traj[:, 0]
    if np.any(np.diff(tt) <= 0):
        raise ParameterError("trajectory times must increase strictly")
    heading = _headings(traj)
    pos = np.column_stack([np.interp(gps_time, tt, traj[:, c]) for c in (1, 2, 3)])
    # nearest sample's heading (interpolating angles across the wrap is not needed here)
    j = np.clip(np.searchsorted(tt, gps_time), 0, len(tt) - 1)
    return pos, heading[j]


def _headings(traj: np.ndarray) -> np.ndarray:
    """Heading (radians) at each trajectory sample from the horizontal motion, kept over stops.

    The direction from the path's point ``HEADING_BASELINE`` / 2 metres behind the sample to
    the one as far ahead (by distance travelled): trajectory positions are rounded and noisy at
    the millimetre level, so two samples a few centimetres apart (a creeping vehicle) would
    give a heading degrees off, turning far beams by as many decimetres. Over a stop the
    window spans the motion before and after it.
    """
    step = np.hypot(*np.diff(traj[:, 1:3], axis=0).T)
    if not np.any(step > 1e-6):
        return np.zeros(len(traj))
    travelled = np.concatenate([[0.0], np.cumsum(step)])
    half = min(HEADING_BASELINE, float(travelled[-1])) / 2
    back = np.searchsorted(travelled, travelled - half, side="right") - 1
    ahead = np.searchsorted(travelled, travelled + half, side="left")
    back = np.clip(back, 0, len(traj) - 1)
    ahead = np.clip(ahead, 0, len(traj) - 1)
    d = traj[ahead, 1:3] - traj[back, 1:3]
    return np.arctan2(d[:, 1], d[:, 0])


def _grid(xyz: np.ndarray, cell: float, radius: float) -> tuple[np.ndarray, float, np.ndarray]:
    """Origin (3,), cell edge and shape (3,) of a grid holding every point's radius-ball (the
    edge is doubled until the grid has at most MAX_CELLS cells)."""
    lo = column_min(xyz) - radius - 1e-6
    ext = column_max(xyz) + radius + 1e-6 - lo
    while True:
        shape = np.floor(ext / cell).astype(np.int64) + 1
        if int(np.prod(shape)) <= MAX_CELLS:
            return lo, cell, shape
        cell *= 2.0


@njit(cache=True)
def _ball_cells(x, radius, lo, cell, shape, c0, c1):
    """Grid cell ranges [c0, c1] (inclusive, clipped) overlapped by the ball around x."""
    for a in range(3):
        c0[a] = max(0, int(np.floor((x[a] - radius - lo[a]) / cell)))
        c1[a] = min(shape[a] - 1, int(np.floor((x[a] + radius - lo[a]) / cell)))


@njit(cache=True)
def _cell_index(xyz, lo, cell, shape, radius):
    """CSR index of points by grid cell, each point in every cell its radius-ball overlaps.

    Returns (start (cells + 1,), members) with members[start[c]:start[c + 1]] the points of
    cell c. With radius < cell / 2 a point sits in at most 8 cells.
    """
    n = xyz.shape[0]
    ncell = shape[0] * shape[1] * shape[2]
    start = np.zeros(ncell + 1, np.int64)
    c0 = np.empty(3, np.int64)
    c1 = np.empty(3, np.int64)
    for i in range(n):
        _ball_cells(xyz[i], radius, lo, cell, shape, c0, c1)
        for ax in range(c0[0], c1[0] + 1):
            for ay in range(c0[1], c1[1] + 1):
                for az in range(c0[2], c1[2] + 1):
                    start[(ax * shape[1] + ay) * shape[2] + az + 1] += 1
    for c in range(ncell):
        start[c + 1] += start[c]
    members = np.empty(start[ncell], np.int64)
    fill = start[:-1].copy()
    for i in range(n):
        _ball_cells(xyz[i], radius, lo, cell, shape, c0, c1)
        for ax in range(c0[0], c1[0] + 1):
            for ay in range(c0[1], c1[1] + 1):
                for az in range(c0[2], c1[2] + 1):
                    key = (ax * shape[1] + ay) * shape[2] + az
                    members[fill[key]] = i
                    fill[key] += 1
    return start, members


@njit(cache=True)
def ray_point_test(o, p, q, radius, margin):
    """Whether the beam o -> p passed within ``radius`` of q and ended > ``margin`` beyond it."""
    d0 = p[0] - o[0]
    d1 = p[1] - o[1]
    d2 = p[2] - o[2]
    length = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if length <= 0.0:
        return False
    d0 /= length
    d1 /= length
    d2 /= length
    w0 = q[0] - o[0]
    w1 = q[1] - o[1]
    w2 = q[2] - o[2]
    s = w0 * d0 + w1 * d1 + w2 * d2
    if s <= 0.0 or s >= length - margin:
        return False
    e0 = w0 - s * d0
    e1 = w1 - s * d1
    e2 = w2 - s * d2
    return e0 * e0 + e1 * e1 + e2 * e2 < radius * radius


@njit(cache=True)
def _clip(o, d, lo, hi, s_max):
    """Parameter range [s0, s1] of the ray o + s d (s in [0, s_max]) inside the box [lo, hi]."""
    s0 = 0.0
    s1 = s_max
    for a in range(3):
        if d[a] == 0.0:
            if o[a] < lo[a] or o[a] > hi[a]:
                return 1.0, 0.0
            continue
        t1 = (lo[a] - o[a]) / d[a]
        t2 = (hi[a] - o[a]) / d[a]
        if t1 > t2:
            t1, t2 = t2, t1
        s0 = max(s0, t1)
        s1 = min(s1, t2)
    return s0, s1


@njit(cache=True)
def _beam_hits(i, o, p, xyz, lo, cell, shape, start, members, radius, margin, seen, counts):
    """Walk the grid cells of beam i (exact 3D DDA) and count each point it saw through once
    (``margin``: this beam's own)."""
    d = p - o
    length = np.sqrt((d * d).sum())
    stop = length - margin
    if stop <= 0.0:
        return
    d = d / length
    hi = lo + shape * cell
    s0, s1 = _clip(o, d, lo, hi, stop)
    if s0 >= s1:
        return
    c = np.empty(3, np.int64)
    step = np.empty(3, np.int64)
    t_max = np.empty(3)
    t_delta = np.empty(3)
    for a in range(3):
        x = o[a] + s0 * d[a]
        c[a] = min(shape[a] - 1, max(0, int(np.floor((x - lo[a]) / cell))))
        if d[a] > 0.0:
            step[a] = 1
            t_max[a] = (lo[a] + (c[a] + 1) * cell - o[a]) / d[a]
            t_delta[a] = cell / d[a]
        elif d[a] < 0.0:
            step[a] = -1
            t_max[a] = (lo[a] + c[a] * cell - o[a]) / d[a]
            t_delta[a] = -cell / d[a]
        else:
            step[a] = 0
            t_max[a] = np.inf
            t_delta[a] = np.inf
    n_seen = 0
    while True:
        key = (c[0] * shape[1] + c[1]) * shape[2] + c[2]
        for m in range(start[key], start[key + 1]):
            j = members[m]
            if j == i or not ray_point_test(o, p, xyz[j], radius, margin):
                continue
            dup = False
            for q in range(n_seen):  # a point sits in up to 8 cells: count it once per beam
                if seen[q] == j:
                    dup = True
                    break
            if dup:
                continue
            if n_seen < seen.size:
                seen[n_seen] = j
                n_seen += 1
            counts[j] += 1
        a = 0
        if t_max[1] < t_max[a]:
            a = 1
        if t_max[2] < t_max[a]:
            a = 2
        if t_max[a] > s1:
            break
        c[a] += step[a]
        if c[a] < 0 or c[a] >= shape[a]:
            break
        t_max[a] += t_delta[a]


@njit(cache=True, parallel=True)
def _march(xyz, origin, lo, cell, shape, start, members, radius, margins, n_chunks):
    """(n_chunks, n) per-chunk counts of the beams that saw through each point (``margins``:
    (n,) each beam's)."""
    n = xyz.shape[0]
    counts = np.zeros((n_chunks, n), np.int32)
    size = (n + n_chunks - 1) // n_chunks
    for c in prange(n_chunks):
        seen = np.empty(4096, np.int64)
        for i in range(c * size, min(n, (c + 1) * size)):
            _beam_hits(i, origin[i], xyz[i], xyz, lo, cell, shape, start, members, radius,
                       margins[i], seen, counts[c])
    return counts


def see_through_counts(
    xyz: np.ndarray, origin: np.ndarray, *, radius: float = 0.006,
    margin: float | np.ndarray = 0.08, cell: float = 0.1,
) -> np.ndarray:
    """(n,) number of beams o_i -> p_i that passed within ``radius`` of each point and ended more
    than ``margin`` beyond it (each beam counts a point at most once). ``margin``: one for
    every beam, or (n,) each beam's own (:func:`grazing_margins`).
    """
    centre = xyz.mean(axis=0)
    local = xyz - centre
    o = origin - centre
    margins = np.broadcast_to(np.asarray(margin, dtype=np.float64), (len(xyz),))
    lo, cell, shape = _grid(local, cell, radius)
    start, members = _cell_index(local, lo, cell, shape, radius)
    n_chunks = 8
    counts = _march(local, o, lo, cell, shape, start, members, radius,
                    np.ascontiguousarray(margins), n_chunks)
    return counts.sum(axis=0)


#: Points whose beam returns are counted per batch (bounds the ball queries' memory).
RETURNS_BATCH = 20_000


def beam_returns(xyz: np.ndarray, origin: np.ndarray, gps_time: np.ndarray, points: np.ndarray,
                 *, radius: float, depth: float) -> np.ndarray:
    """(m,) for each of the points ``points`` (indices), how many returns of other pulses (a
    time of their own) lie on its beam at it: within ``radius`` of the line from its origin
    through it and within ``depth`` of it along that line."""
    from scipy.spatial import cKDTree

    from algorithms.neighbours import ball_candidates

    out = np.zeros(points.size, dtype=np.int64)
    if points.size == 0:
        return out
    centre = xyz[points].mean(axis=0)
    local = xyz - centre
    tree = cKDTree(local)
    reach = float(np.hypot(radius, depth))
    for s in range(0, points.size, RETURNS_BATCH):
        rows = points[s:s + RETURNS_BATCH]
        row, j = ball_candidates(tree, local, rows, reach)
        beam = local[rows] - (origin[rows] - centre)
        beam /= np.linalg.norm(beam, axis=1)[:, None]
        p = rows[row]
        d = local[j] - local[p]
        along = np.einsum("ij,ij->i", d, beam[row])
        across2 = np.einsum("ij,ij->i", d, d) - along * along
        on_beam = ((gps_time[j] != gps_time[p]) & (np.abs(along) <= depth)
                   & (across2 <= radius * radius))
        out[s:s + rows.size] = np.bincount(row[on_beam], minlength=rows.size)
    return out


def surface_at_points(xyz: np.ndarray, k: int = SURFACE_NEIGHBOURS
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) unit normal and (n,) roughness (metres) of the surface around each point.

    The plane of its k nearest points (itself included): the normal is the covariance's
    eigenvector of the smallest eigenvalue, the roughness that eigenvalue's square root (the
    scatter of the points across the plane: range noise, texture). Fewer than 3 points: no
    surface (NaN).
    """
    from scipy.spatial import cKDTree

    n = len(xyz)
    normal = np.full((n, 3), np.nan)
    rough = np.full(n, np.nan)
    kk = min(k, n)
    if kk < 3:
        return normal, rough
    local = xyz - xyz.mean(axis=0)
    tree = cKDTree(local)
    for s in range(0, n, NORMAL_BATCH):
        _, idx = tree.query(local[s:s + NORMAL_BATCH], k=kk, workers=worker_threads())
        nb = local[idx.reshape(-1, kk)]
        nb = nb - nb.mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", nb, nb) / kk
        value, vector = np.linalg.eigh(cov)
        normal[s:s + len(nb)] = vector[:, :, 0]
        rough[s:s + len(nb)] = np.sqrt(np.maximum(value[:, 0], 0.0))
    return normal, rough


def grazing_margins(xyz: np.ndarray, origin: np.ndarray, *, radius: float,
                    margin: float) -> np.ndarray:
    """(n,) how far before its return each beam stops counting as evidence.

    A beam meeting a surface at angle g (between the beam and the surface's plane) runs
    ``s sin g`` above that surface ``s`` metres before its end, so it passes within ``radius``
    of the surface's own points (each off the plane by its roughness r, so two of them differ
    by up to about 8 r) over the last (radius + 8 r) / sin g metres: no evidence against them.
    Each beam's margin is the larger of ``margin`` and that length, with g at least
    ``MIN_GRAZING_DEGREES`` (range noise divided by the sine of the incidence: at grazing
    incidence on a facade a fixed margin lets beams see through the facade's own points).
    Where the end has no surface (NaN normal) the beam keeps ``margin``.
    """
    normal, rough = surface_at_points(xyz)
    beam = xyz - origin
    length = np.linalg.norm(beam, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        sin_g = np.abs(np.einsum("ij,ij->i", beam, normal)) / length
    sin_g = np.maximum(sin_g, np.sin(np.radians(MIN_GRAZING_DEGREES)))
    along = (radius + ROUGHNESS_SPAN * rough) / sin_g
    return np.where(np.isfinite(along), np.maximum(along, margin), margin)


def detect_free_space(
    xyz: np.ndarray,
    origin: np.ndarray,
    *,
    radius: float = 0.006,
    margin: float = 0.08,
    min_rays: int = 1,
    seen_again: np.ndarray | None = None,
    beams: np.ndarray | None = None,
    gps_time: np.ndarray | None = None,
    hit_ratio: float = 0.5,
) -> DetectorResult:
    """Flag points that at least ``min_rays`` other beams saw through (module docstring).

    Each beam stops counting ``margin`` before its return, or longer where it meets the surface
    there at a grazing angle (:func:`grazing_margins`).

    ``seen_again`` (n,) bool: the points recorded again at another moment (persistent, as
    :func:`algorithms.transient.persistent_points` finds them). A beam and a point in conflict
    cannot both be right; the one seen again wins: such a point was there at two moments, so it
    is static and not flagged, and only beams whose own return was seen again count as evidence
    (a return seen once may be a multipath echo at a false range, whose beam "passes" through
    the real surface in front of it). None: every point may be flagged, every beam counts.
    ``beams`` (n,) bool: the points whose beam origin is known (others' beams never count).
    ``gps_time`` (n,) s: with it a flagged point stays flagged only while the returns of
    other pulses on its own beam (:func:`beam_returns`, ``radius`` across, ``margin`` along)
    are at most ``hit_ratio`` times its see-through count (module docstring).

    xyz (n, 3) and origin (n, 3) metres (the scanner position of each point's beam). Score (n,)
    = the see-through count; flagged = score >= min_rays; critical_value = min_rays.
    """
    arr = np.asarray(xyz, dtype=np.float64)
    org = np.asarray(origin, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3 or org.shape != arr.shape:
        raise ParameterError(f"xyz and origin must both have shape (n, 3), got {arr.shape} "
                             f"and {org.shape}")
    if not (np.all(np.isfinite(arr)) and np.all(np.isfinite(org))):
        raise ParameterError("xyz or origin holds NaN or infinite values")
    TransientParameters(free_space_radius=radius, free_space_margin=margin,
                        free_space_min_rays=min_rays, free_space_hit_ratio=hit_ratio)
    margins = grazing_margins(arr, org, radius=radius, margin=margin)
    if seen_again is not None:
        margins = np.where(seen_again, margins, np.inf)  # a beam with no evidence: never counts
    if beams is not None:
        margins = np.where(beams, margins, np.inf)
    score = see_through_counts(arr, org, radius=radius, margin=margins).astype(np.float64)
    flagged = score >= min_rays
    if seen_again is not None:
        flagged &= ~seen_again
    returned_to = 0
    if gps_time is not None:
        cand = np.flatnonzero(flagged)
        hits = beam_returns(arr, org, np.asarray(gps_time, dtype=np.float64), cand,
                            radius=radius, depth=margin)
        surface = hits > hit_ratio * score[cand]
        flagged[cand[surface]] = False
        returned_to = int(np.count_nonzero(surface))
    info = {"radius": radius, "margin": margin, "min_rays": int(min_rays), "points": len(arr),
            "hit_ratio": float(hit_ratio), "points_returned_to": returned_to,
            "points_tested": len(arr), "points_flagged": int(flagged.sum()),
            "beam_margin_median": (float(np.median(margins[np.isfinite(margins)]))
                                   if np.isfinite(margins).any() else margin),
            "beams_with_grazing_margin": int(np.count_nonzero(np.isfinite(margins)
                                                              & (margins > margin))),
            "beams_counted": int(np.count_nonzero(np.isfinite(margins)))}
    return DetectorResult(score=score, flagged=flagged, critical_value=float(min_rays), info=info)
