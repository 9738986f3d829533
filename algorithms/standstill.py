"""Where a scanner stood still, from its own points and times.

A profile scanner fires the same beams on every turn of its mirror. While the vehicle stands
still, those beams meet the same spots again and again: a window of a tenth of a second holds
5-25 turns whose returns, with the mirror's phase drifting from turn to turn, lie millimetres
apart on every surface, and the returns of a window a few tenths of a second later lie on top
of them. Moving at v, that later window's profile lies v x the lag away (1 cm at 5 cm/s over
0.2 s). So the time series of one scanner is cut into windows of ``window`` seconds, a spread
sample of each window's points is compared with all points of the window ``lag`` windows later,
and where the median distance to the later profile (the line through the two nearest of its
returns: pulses a degree apart leave centimetres between them along the scan line, none across
it) is at most ``tolerance`` the scanner stood still from the start of the first window to the
end of the second. Airborne returns and moving objects in a window do not move the median.

Free space at a stop (:func:`stop_flags`, :func:`stream_stop_flags`): the still windows are cut
into pieces of whole seconds of GPS time; in each piece the scanner's position is fitted from
the piece's own returns (:func:`stop_origin`: every beam leaves it) and a return that the
piece's beams passed at least ``STOP_MIN_PASSES`` times and that its own beam returned to at
most ``STOP_RETURN_RATIO`` times as often is flagged: a surface is hit on every turn, a droplet
of exhaust once. A piece is decided from its returns and the ``lag`` windows on either side, so
a pass over a file in chunks gives the result of a run over the whole file.
numpy in, numpy out (scipy's k-d tree).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from algorithms.checks import check_xyz
from algorithms.errors import ParameterError

#: Seconds of one window.
WINDOW = 0.1
#: Windows between the two compared (0.3 s at WINDOW: a vehicle creeping at 2 cm/s has moved
#: more than the tolerance).
LAG = 3
#: Metres: the median distance of a still scanner's returns to the later window's profile (range
#: noise of a few millimetres).
TOLERANCE = 0.005
#: Points of a window compared (a spread sample in time order).
SAMPLE = 256
#: Later points of the first, coarse comparison (a spread sample in time order).
SCREEN_POINTS = 2048
#: Metres: a median distance to the coarse later profile over this is not still (20 times
#: the tolerance; a scanner moving at walking pace has moved 0.4 m between the windows).
SCREEN_DISTANCE = 0.1
#: Fewer points than this in either window: nothing is decided there.
MIN_WINDOW_POINTS = 20


def profile_distances(points: np.ndarray, later: np.ndarray) -> np.ndarray:
    """(n,) distance from each of ``points`` (n, 3) to the line through its two nearest
    returns among ``later`` (m >= 2, 3): on a still scanner's profile those bracket it along
    the scan line, however far apart the pulses are, and the line passes within the range noise;
    where they coincide, the distance to the nearest."""
    from scipy.spatial import cKDTree

    _, j = cKDTree(later).query(points, k=2)
    q1, q2 = later[j[:, 0]], later[j[:, 1]]
    along = q2 - q1
    length = np.linalg.norm(along, axis=1)
    to_p = points - q1
    across = np.linalg.norm(np.cross(to_p, along), axis=1) / np.where(length > 0, length, 1.0)
    return np.where(length > 0, across, np.linalg.norm(to_p, axis=1))


def window_still(earlier: np.ndarray, later: np.ndarray, tolerance: float, sample: int) -> bool:
    """Whether the median :func:`profile_distances` of a spread sample of the points
    ``earlier`` (n, 3), in time order, to ``later`` (m, 3) is at most ``tolerance`` metres.

    A moving scanner's later profile lies metres away: a spread sample of ``SCREEN_POINTS`` of
    the later points, whose lines between neighbours stray from the surface by millimetres,
    tells it first when the median is over ``SCREEN_DISTANCE``, without the whole window's
    k-d tree."""
    pick = np.linspace(0, len(earlier) - 1, min(sample, len(earlier))).astype(np.int64)
    if len(later) > SCREEN_POINTS:
        screen = later[np.linspace(0, len(later) - 1, SCREEN_POINTS).astype(np.int64)]
        if np.median(profile_distances(earlier[pick], screen)) > SCREEN_DISTANCE:
            return False
    return bool(np.median(profile_distances(earlier[pick], later)) <= tolerance)


def window_ids(gps_time: np.ndarray, window: float = WINDOW) -> np.ndarray:
    """(n,) int64 window of each time on the absolute grid of ``window`` seconds (the same
    windows in any part of the file)."""
    return np.floor(np.asarray(gps_time, dtype=np.float64) / window).astype(np.int64)


def still_windows(which: np.ndarray, xyz: np.ndarray, *, lag: int = LAG,
                  tolerance: float = TOLERANCE, sample: int = SAMPLE,
                  first: int | None = None, last: int | None = None) -> np.ndarray:
    """Sorted window ids i (``first`` <= i <= ``last``, default every one) whose points lie on
    the profile of window i + ``lag`` (:func:`window_still`); ``which`` (n,) the window id of
    each of one scanner's points, in time order, ``xyz`` (n, 3)."""
    if len(which) == 0:
        return np.zeros(0, dtype=np.int64)
    lo = int(which[0]) if first is None else first
    hi = int(which[-1]) if last is None else last
    ids = np.arange(lo, hi + lag + 2)
    starts = np.searchsorted(which, ids)
    out = []
    for i in range(hi - lo + 1):
        a = slice(starts[i], starts[i + 1])
        b = slice(starts[i + lag], starts[i + lag + 1])
        if min(a.stop - a.start, b.stop - b.start) < MIN_WINDOW_POINTS:
            continue
        if window_still(xyz[a], xyz[b], tolerance, sample):
            out.append(lo + i)
    return np.array(out, dtype=np.int64)


def still_spans(gps_time: np.ndarray, xyz: np.ndarray, *, window: float = WINDOW,
                lag: int = LAG, tolerance: float = TOLERANCE, sample: int = SAMPLE
                ) -> np.ndarray:
    """(m, 2) start and end times of the spans over which one scanner stood still (module
    docstring), in time order, overlapping spans merged; windows on the absolute grid of
    ``window`` seconds.

    gps_time (n,) seconds of one scanner's returns (NaN: left out); xyz (n, 3) metres.
    """
    arr = check_xyz(xyz)
    t = np.asarray(gps_time, dtype=np.float64)
    if t.shape != (len(arr),):
        raise ParameterError(f"gps_time must have shape ({len(arr)},), got {t.shape}")
    if not (window > 0 and lag >= 1 and tolerance > 0 and sample >= 1):
        raise ParameterError("window and tolerance must be > 0, lag and sample >= 1")
    timed = np.flatnonzero(np.isfinite(t))
    if timed.size == 0:
        return np.zeros((0, 2))
    order = timed[np.argsort(t[timed], kind="stable")]
    still = still_windows(window_ids(t[order], window), arr[order], lag=lag,
                          tolerance=tolerance, sample=sample)
    spans = np.column_stack([still * window, (still + lag + 1) * window])
    return merged_spans(spans.reshape(-1, 2))


def merged_spans(spans: np.ndarray) -> np.ndarray:
    """(m, 2) spans sorted by start with those that overlap or touch joined."""
    if len(spans) == 0:
        return spans
    spans = spans[np.argsort(spans[:, 0], kind="stable")]
    out = [spans[0].copy()]
    for start, end in spans[1:]:
        if start <= out[-1][1]:
            out[-1][1] = max(out[-1][1], end)
        else:
            out.append(np.array([start, end]))
    return np.array(out)


# --- free space at a stop -------------------------------------------------------------------

#: Windows per piece a stop is cut into: each piece's scanner position is fitted from the
#: piece's own points, so a stop of any length costs a piece's memory, and a pass over the file
#: in chunks cuts it exactly as a run over the whole file does.
PIECE_WINDOWS = 10
#: Fewer points than this in a piece's still windows: no position is fitted, nothing flagged.
MIN_PIECE_POINTS = 200
#: Metres: a beam passes a point within this (free space's radius: two range-noise sigmas).
STOP_RADIUS = 0.006
#: Metres: the least a beam must end beyond a point to see through it (free space's margin).
STOP_MARGIN = 0.08
#: Metres along a point's own beam within which other pulses' returns count as returns to it.
STOP_DEPTH = 0.03
#: Beams of the piece that passed a point, at least, to flag it.
STOP_MIN_PASSES = 5
#: A point is flagged while its own beam's other pulses returned to it at most this many times
#: the beams that passed it: a still scanner hits a surface on every turn, a droplet once.
STOP_RETURN_RATIO = 0.1


def still_members(which: np.ndarray, still: np.ndarray, lag: int = LAG) -> np.ndarray:
    """(n,) bool: the point's window j lies in a still span, j - lag <= i <= j for a still
    window i (window i and the one ``lag`` later were compared and found on one profile)."""
    covered = (still[:, None] + np.arange(lag + 1)[None, :]).ravel()
    return np.isin(which, covered)


def stop_origin(xyz: np.ndarray, gps_time: np.ndarray) -> tuple[np.ndarray | None, dict]:
    """(3,) where a still profile scanner stands, from its own points: every beam leaves it
    (:func:`algorithms.lever_arms.fit_lever_arm` at a zero pose, started from the points'
    centroid and, when that fit is refused, from the guesses of :func:`profile_starts`); None
    when the points do not lie in one plane or no start gives an accepted fit."""
    from algorithms.lever_arms import fit_lever_arm

    n = len(xyz)
    centre = xyz.mean(axis=0)
    local = xyz - centre
    if not in_one_plane(local):  # a spinning head's azimuth turns at one rate too
        return None, {"points": n, "reason": "the points do not lie in one plane (not a "
                      "profile scanner)"}
    fit = fit_lever_arm(local, gps_time, np.zeros((n, 3)), np.zeros(n), STOP_FIT_POINTS)
    if still_fit(fit.arm, fit.info):
        return np.asarray(fit.arm) + centre, fit.info
    for start in profile_starts(local, gps_time):
        fit = fit_lever_arm(local, gps_time, np.tile(start, (n, 1)), np.zeros(n),
                            STOP_FIT_POINTS)
        if still_fit(fit.arm, fit.info):  # fitted relative to the start
            return np.asarray(fit.arm) + start + centre, fit.info
    return None, {**fit.info, "reason": fit.info.get("reason", (
        f"the beams miss their returns by more than {STOP_MAX_RESIDUAL} rad (median) from "
        "every start"))}


def still_fit(arm: tuple | None, info: dict) -> bool:
    """Whether a lever-arm fit places a standing scanner: accepted, and its beams' median
    angle to their returns at most ``STOP_MAX_RESIDUAL``."""
    return arm is not None and info["median_angle_residual_rad"] <= STOP_MAX_RESIDUAL


#: Metres from the plane of a still profile scanner's points within which ``PLANE_SHARE`` of
#: them lie (range noise and a vehicle rocking on its springs: centimetres); the points of a
#: multi-beam spinning head standing still do not.
PLANE_BAND = 0.1
PLANE_SHARE = 0.9


def in_one_plane(xyz: np.ndarray) -> bool:
    """Whether ``PLANE_SHARE`` of the points lie within ``PLANE_BAND`` of their plane."""
    from algorithms.lever_arms import scan_plane

    pick = np.linspace(0, len(xyz) - 1, min(len(xyz), START_POINTS)).astype(np.int64)
    normal, centre, _ = scan_plane(xyz[pick])
    return bool(np.mean(np.abs((xyz[pick] - centre) @ normal) <= PLANE_BAND) >= PLANE_SHARE)


#: Radians: the median angle between a standing scanner's beams and its returns, at most. No
#: vehicle motion, roll or trajectory error enters at a stop, only the returns' few millimetres
#: of noise across the beam (1 mrad at 5 m); the fit's 10 mrad for a moving vehicle let a wrong
#: position through (metres off, 9.99 mrad) where the right one gave 0.7 mrad.
STOP_MAX_RESIDUAL = 0.002
#: Points of a piece (a spread sample in time order) its scanner's position is fitted to: a
#: second of a still scanner turns its mirror 50-250 times.
STOP_FIT_POINTS = 5000
#: Starts tried when the centroid's fit is rejected, at most.
MAX_STARTS = 4
#: Points (a spread sample in time order) the starts are scored on.
START_POINTS = 1000


def profile_starts(xyz: np.ndarray, gps_time: np.ndarray) -> list[np.ndarray]:
    """Up to ``MAX_STARTS`` guesses (3,) of a still scanner's position, best first.

    At a stop the in-plane position z(t) = c + r(t) exp(i theta(t)) of a profile scanner's
    returns turns with its mirror, so the periodogram of z peaks at the mirror's rate (and its
    harmonics) whatever c is; for each such rate omega and a grid of phases phi, the beams
    theta = omega t + phi give c by least squares ((z - c) x u(theta) = 0), and the guesses are
    the c whose beams leave their points with the smallest median angle."""
    from algorithms.lever_arms import MAX_RATE_HZ, MIN_RATE_HZ, scan_plane

    n = len(xyz)
    pick = np.linspace(0, n - 1, min(n, START_POINTS)).astype(np.int64)
    order = np.argsort(gps_time, kind="stable")[pick]
    q, t = xyz[order], gps_time[order] - gps_time[order][0]
    _, centre, basis = scan_plane(q)
    w = (q - centre) @ basis.T
    z = (w[:, 0] - w[:, 0].mean()) + 1j * (w[:, 1] - w[:, 1].mean())
    span = max(min(0.25, float(t[-1])), 1e-3)
    step = np.pi / (4 * span)
    grid = np.arange(2 * np.pi * MIN_RATE_HZ, 2 * np.pi * MAX_RATE_HZ, step)
    omegas = np.concatenate([-grid[::-1], grid])
    use = t <= span
    power = np.abs(np.exp(-1j * np.outer(omegas, t[use])) @ z[use])
    rates: list[float] = []
    for i in np.argsort(power)[::-1]:
        if all(abs(omegas[i] - r) > 4 * step for r in rates):
            rates.append(float(omegas[i]))
        if len(rates) == 2:
            break
    candidates = {sign * r / k for r in rates for k in range(1, 7) for sign in (1, -1)
                  if abs(r / k) >= 2 * np.pi * MIN_RATE_HZ}
    phis = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    scored = []
    for omega in sorted(candidates):
        theta = (omega * t)[:, None] + phis[None, :]  # (n, phases)
        sin, cos = np.sin(theta), np.cos(theta)
        # least squares c of (w - c) x u = 0 for every phase at once: 2 x 2 normal equations
        b = w[:, :1] * sin - w[:, 1:] * cos
        m00, m01, m11 = (sin * sin).sum(0), -(sin * cos).sum(0), (cos * cos).sum(0)
        r0, r1 = (sin * b).sum(0), -(cos * b).sum(0)
        det = m00 * m11 - m01 * m01
        ok = np.abs(det) > 1e-12 * np.maximum(m00 * m11, 1e-300)
        det = np.where(ok, det, 1.0)
        cx, cy = (m11 * r0 - m01 * r1) / det, (m00 * r1 - m01 * r0) / det
        dx, dy = w[:, :1] - cx[None, :], w[:, 1:] - cy[None, :]
        ahead = (dx * cos + dy * sin).mean(0) > 0  # the points lie ahead of their beams
        miss = np.median(np.abs(np.angle(np.exp(1j * (np.arctan2(dy, dx) - theta)))), axis=0)
        for j in np.flatnonzero(ok & ahead):
            scored.append((float(miss[j]), centre + np.array([cx[j], cy[j]]) @ basis))
    scored.sort(key=lambda s: s[0])
    return [c for _, c in scored[:MAX_STARTS]]


def flags_at_stop(xyz: np.ndarray, gps_time: np.ndarray) -> tuple[np.ndarray, dict]:
    """(n,) bool: the points of one still piece of one scanner that at least
    ``STOP_MIN_PASSES`` of the piece's beams passed and whose own beam returned to them at most
    ``STOP_RETURN_RATIO`` times as often (:func:`algorithms.free_space.see_through_counts`,
    :func:`algorithms.free_space.beam_returns`), from the position :func:`stop_origin` fits;
    and how."""
    from algorithms.free_space import beam_returns, grazing_margins, see_through_counts

    n = len(xyz)
    origin, info = stop_origin(xyz, gps_time)
    if origin is None:
        return np.zeros(n, dtype=bool), {"placed": False, **info}
    origins = np.tile(origin, (n, 1))
    margins = grazing_margins(xyz, origins, radius=STOP_RADIUS, margin=STOP_MARGIN)
    passes = see_through_counts(xyz, origins, radius=STOP_RADIUS, margin=margins)
    seen = np.flatnonzero(passes >= STOP_MIN_PASSES)
    returns = beam_returns(xyz, origins, gps_time, seen, radius=STOP_RADIUS, depth=STOP_DEPTH)
    flagged = np.zeros(n, dtype=bool)
    flagged[seen] = returns <= STOP_RETURN_RATIO * passes[seen]
    return flagged, {"placed": True}


def piece_flags(which: np.ndarray, xyz: np.ndarray, gps_time: np.ndarray, piece: int,
                lag: int = LAG) -> tuple[np.ndarray, dict]:
    """(n,) bool flags of the points of piece ``piece`` (windows ``piece * PIECE_WINDOWS`` up
    to the next piece's first) among one scanner's points in time order, ``which`` their
    window ids; the points given must hold every window from ``lag`` before the piece to
    ``lag`` after it (what its still windows are decided on)."""
    first, last = piece * PIECE_WINDOWS, (piece + 1) * PIECE_WINDOWS - 1
    still = still_windows(which, xyz, lag=lag, first=first - lag, last=last)
    mine = (which >= first) & (which <= last) & still_members(which, still, lag)
    flags = np.zeros(len(which), dtype=bool)
    rows = np.flatnonzero(mine)
    info = {"still_points": int(rows.size), "placed": False}
    if rows.size >= MIN_PIECE_POINTS:
        got, how = flags_at_stop(xyz[rows], gps_time[rows])
        flags[rows] = got
        info.update(how)
    return flags, info


def stream_stop_flags(gps_time: np.ndarray, source: np.ndarray, use: np.ndarray,
                      xyz_columns: tuple[np.ndarray, np.ndarray, np.ndarray],
                      mark: Callable[[np.ndarray], None], chunk: int = 4_000_000,
                      chunk_done: Callable[[], None] | None = None) -> dict | None:
    """Free space at every stop of every scanner (:func:`piece_flags`) of the points ``use``
    (n,) bool, each piece's flagged points (indices) given to ``mark``, in one pass of
    ``chunk`` points at a time over a file whose returns come in time order per scanner. The
    arrays may be memory maps: memory is a chunk's and each scanner's current piece's. Returns
    None at the first return earlier than its scanner's previous one (the pieces given to
    ``mark`` so far are then not the file's: sort, :func:`stop_flags`); else the counts for
    the statistics."""
    buffers: dict[int, list[np.ndarray]] = {}
    done: dict[int, int] = {}  # each scanner's next piece to decide
    last_time: dict[int, float] = {}
    info = {"stop_pieces": 0, "stop_pieces_placed": 0, "stop_points": 0, "points_flagged": 0}
    n = len(gps_time)

    def decide(sid: int, upto: int | None) -> None:
        """Decide the scanner's pieces whose windows up to ``lag`` after them are all read
        (``upto``: the latest window read, None: the file ended)."""
        rows = np.concatenate(buffers[sid]) if buffers[sid] else np.zeros(0, np.int64)
        if rows.size == 0:
            return
        t = np.asarray(gps_time[rows], dtype=np.float64)
        which = window_ids(t)
        piece = done.get(sid, int(which[0]) // PIECE_WINDOWS)
        while True:
            at = np.searchsorted(which, piece * PIECE_WINDOWS)
            if at == which.size:
                break
            piece = max(piece, int(which[at]) // PIECE_WINDOWS)  # over a gap in one step
            if upto is not None and (piece + 1) * PIECE_WINDOWS - 1 + LAG >= upto:
                break
            lo = np.searchsorted(which, piece * PIECE_WINDOWS - LAG)
            hi = np.searchsorted(which, (piece + 1) * PIECE_WINDOWS + LAG)
            if np.any((which[lo:hi] >= piece * PIECE_WINDOWS)
                      & (which[lo:hi] < (piece + 1) * PIECE_WINDOWS)):
                ctx = rows[lo:hi]
                xyz = np.column_stack([np.asarray(c[ctx], dtype=np.float64)
                                       for c in xyz_columns])
                got, how = piece_flags(which[lo:hi], xyz, t[lo:hi], piece)
                if got.any():
                    mark(ctx[got])
                info["stop_pieces"] += int(how["still_points"] > 0)
                info["stop_pieces_placed"] += int(how["placed"])
                info["stop_points"] += how["still_points"]
                info["points_flagged"] += int(got.sum())
            piece += 1
        done[sid] = piece
        keep = which >= piece * PIECE_WINDOWS - LAG
        buffers[sid] = [rows[keep]]

    for s in range(0, n, chunk):
        rows = s + np.flatnonzero(np.asarray(use[s:s + chunk]))
        src = np.asarray(source[rows], dtype=np.int64)
        order = np.argsort(src, kind="stable")  # each scanner's returns, in file order
        rows, src = rows[order], src[order]
        t = np.asarray(gps_time[rows], dtype=np.float64)
        cuts = np.flatnonzero(np.r_[True, src[1:] != src[:-1], True])
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            sid = int(src[a])
            if np.any(t[a + 1:b] < t[a:b - 1]) or t[a] < last_time.get(sid, -np.inf):
                return None
            last_time[sid] = float(t[b - 1])
            buffers.setdefault(sid, []).append(rows[a:b])
            decide(sid, int(window_ids(t[b - 1:b])[0]))
        if chunk_done is not None:
            chunk_done()
    for sid in buffers:
        decide(sid, None)
    return info


def stop_flags(gps_time: np.ndarray, source: np.ndarray, xyz: np.ndarray,
               use: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """(n,) bool free space at every stop (:func:`stream_stop_flags`) of the points in
    memory, in any order: each scanner's points are taken in time order (ties in their order
    here), as a pass over a file recorded in that order takes them."""
    t = np.asarray(gps_time, dtype=np.float64)
    n = len(t)
    use = np.isfinite(t) if use is None else np.asarray(use, dtype=bool) & np.isfinite(t)
    order = np.lexsort((t, np.asarray(source, dtype=np.int64)))
    flags = np.zeros(n, dtype=bool)
    sorted_flags = np.zeros(n, dtype=bool)
    def mark(rows: np.ndarray) -> None:
        sorted_flags[rows] = True

    info = stream_stop_flags(t[order], np.asarray(source)[order], use[order],
                             tuple(np.asarray(xyz)[order, j] for j in range(3)),
                             mark, chunk=max(n, 1))
    assert info is not None  # sorted by scanner and time
    flags[order] = sorted_flags
    return flags, info
