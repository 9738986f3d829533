"""What a cloud's points say about the platform that recorded them: pure functions of arrays.

The sensor profile (airborne, mobile, spinning, terrestrial) is chosen from physics that holds
for every survey, not from a file's density alone (today's airborne surveys reach 50-100 points
per m2 and more, as dense as mobile data seen over a large bounding box). Each function here
measures one piece of evidence from a bounded sample of points; the decision is made elsewhere
(:mod:`lidar_outliers.profiles`).

* :func:`platform_speed`: how fast the platform moved. The points of one scanner (point source)
  within one second of GPS time are regressed on time; the slope is the velocity of the scan
  pattern's centre, which moves with the platform (the cross-track sweep averages out over the
  tens to hundreds of scan lines of a second). Survey aircraft fly 50-80 m/s, helicopters
  20-40 m/s, cars 0-30 m/s; a tripod stands still.
* :func:`pulse_directions`: where the laser looked. The returns of one pulse (same GPS time and
  point source, distinct return numbers) lie on its beam, first return nearest the sensor; the
  vector from the first to the last return is the beam's direction. An airborne sensor looks
  down, within its scan half-angle (15-40 degrees) of nadir; a mobile or terrestrial scanner
  looks sideways and up as much as down.
* :func:`occupied_density`: points per square metre of the cells that hold points. A sensor
  hundreds of metres up spreads its pulses evenly (0.1-100 points per m2 for crewed aircraft);
  a sensor 2-4 m over the road puts thousands per m2 on the surfaces next to it.
* :func:`scan_angle_extent`: the largest scan angle off nadir the file records.

numpy only (this module is imported when the command line starts).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from algorithms.columns import column_min

#: Beams within this angle of nadir count as looking down (scan half-angles of airborne
#: scanners are 15-40 degrees, plus attitude).
NADIR_CONE_DEG = 45.0


@dataclass(frozen=True)
class SpeedEstimate:
    """Platform speed from :func:`platform_speed`: the median over windows (m/s, None without
    a usable window), its lower and upper quartiles, the number of windows, and whether they
    were short ones (``short``: the sample spans less than a window; the cross-track sweep
    then inflates the speed, so a short-window speed bounds the platform's from above)."""

    speed: float | None
    low: float | None
    high: float | None
    windows: int
    short: bool = False


@dataclass(frozen=True)
class PulseDirections:
    """Beam directions from :func:`pulse_directions`: pulses with returns far enough apart, the
    share of them whose beam lies within ``NADIR_CONE_DEG`` of nadir, pointing down (None
    without pulses) and the median angle of the beams from nadir in degrees."""

    pulses: int
    down_share: float | None
    median_nadir_angle: float | None


def usable_time(gps_time: np.ndarray | None) -> bool:
    """True when ``gps_time`` is present, finite somewhere and not one value everywhere."""
    if gps_time is None or gps_time.size < 2:
        return False
    finite = gps_time[np.isfinite(gps_time)]
    return finite.size >= 2 and bool(finite.min() < finite.max())


def platform_speed(
    gps_time: np.ndarray,
    xy: np.ndarray,
    source: np.ndarray | None = None,
    *,
    window: float = 1.0,
    min_span: float = 0.5,
    short_span: float = 0.2,
    min_points: int = 20,
) -> SpeedEstimate:
    """Speed of the platform: the median over time windows of the least-squares velocity of the
    points recorded in the window.

    gps_time : (n,) seconds; xy : (n, 2) metres; source : (n,) integer scanner or flight-line id
    (point source id, channel), or None for one source. Each source's points are cut where the
    time jumps by more than ``window`` seconds, and each piece into ``window``-second bins; a
    bin with at least ``min_points`` points spanning at least ``min_span`` x ``window`` seconds
    gives one velocity: the slopes of x and y regressed on t. Over a second the sweep across
    track averages out over tens to hundreds of scan lines. Without such a bin, pieces shorter
    than a window but spanning ``short_span`` seconds give short windows (``short``).
    Returns a :class:`SpeedEstimate`.

    >>> t = np.linspace(0, 10, 5000)
    >>> sweep = 300 * np.sin(2 * np.pi * 100 * t)  # 100 scan lines a second, 600 m swath
    >>> xy = np.c_[60 * t, sweep]  # flying along x at 60 m/s
    >>> round(platform_speed(t, xy).speed)
    60
    """
    t = np.asarray(gps_time, dtype=np.float64)
    xy = np.asarray(xy, dtype=np.float64)
    ok = np.isfinite(t) & np.all(np.isfinite(xy), axis=1)
    src = np.zeros(t.size, dtype=np.int64) if source is None else np.asarray(source, np.int64)
    t, xy, src = t[ok], xy[ok], src[ok]
    if t.size < min_points:
        return SpeedEstimate(None, None, None, 0)
    order = np.lexsort((t, src))
    t, xy, src = t[order], xy[order], src[order]
    cut = np.r_[True, (src[1:] != src[:-1]) | (np.diff(t) > window)]
    piece = np.cumsum(cut) - 1
    piece_start = t[cut][piece]
    bins = np.floor((t - piece_start) / window).astype(np.int64)
    full = _window_speeds(t, xy, piece, bins, piece_start, window, min_span * window,
                          min_points)
    if full.size:
        return _summary(full, short=False)
    single = np.zeros_like(bins)
    short = _window_speeds(t, xy, piece, single, piece_start, window, short_span, min_points)
    return _summary(short, short=True) if short.size else SpeedEstimate(None, None, None, 0)


def _window_speeds(
    t: np.ndarray, xy: np.ndarray, piece: np.ndarray, bins: np.ndarray, piece_start: np.ndarray,
    window: float, min_span: float, min_points: int,
) -> np.ndarray:
    """Speeds of the (piece, bin) groups (consecutive in the arrays) with enough points and
    span: |slope of x and y on t|."""
    first = np.flatnonzero(np.r_[True, (piece[1:] != piece[:-1]) | (bins[1:] != bins[:-1])])
    count = np.diff(np.r_[first, t.size])
    # Times relative to each bin's start and positions to the sample's mean: the sums stay exact.
    tt = t - (piece_start + bins * window)
    pp = xy - xy.mean(axis=0)
    span = np.maximum.reduceat(tt, first) - np.minimum.reduceat(tt, first)
    good = (count >= min_points) & (span >= min_span)
    if not good.any():
        return np.zeros(0)
    sums = [np.add.reduceat(v, first)[good] for v in (
        tt, tt * tt, pp[:, 0], pp[:, 1], tt * pp[:, 0], tt * pp[:, 1])]
    st, stt, sx, sy, stx, sty = sums
    n = count[good].astype(np.float64)
    var_t = stt - st * st / n
    vx = (stx - st * sx / n) / var_t
    vy = (sty - st * sy / n) / var_t
    return np.hypot(vx, vy)


def _summary(speed: np.ndarray, short: bool) -> SpeedEstimate:
    low, mid, high = np.percentile(speed, [25, 50, 75])
    return SpeedEstimate(float(mid), float(low), float(high), int(speed.size), short)


def pulse_directions(
    gps_time: np.ndarray,
    xyz: np.ndarray,
    return_number: np.ndarray,
    source: np.ndarray | None = None,
    *,
    min_separation: float = 1.0,
    max_returns: int = 15,
) -> PulseDirections:
    """Directions of the beams of pulses that gave several returns.

    gps_time : (n,) seconds; xyz : (n, 3) metres; return_number : (n,) integers; source : (n,)
    scanner or flight-line id (None: one source). The records of one (source, time) with
    distinct return numbers, at most ``max_returns`` of them, are one pulse (a time shared by
    more records, or with repeated return numbers, is a coarse time stamp, not a pulse); its
    beam points from its first to its last return, taken when they are at least
    ``min_separation`` metres apart (centimetre noise then bends it by under 2 degrees).
    Returns a :class:`PulseDirections`.

    >>> xyz = np.array([[0, 0, 20.0], [1, 0, 0], [5, 5, 3], [9, 5, 3.5]])  # down, then sideways
    >>> pulse_directions(np.array([1.0, 1, 2, 2]), xyz, np.array([1, 2, 1, 2])).down_share
    0.5
    """
    t = np.asarray(gps_time, dtype=np.float64)
    xyz = np.asarray(xyz, dtype=np.float64)
    rn = np.asarray(return_number, dtype=np.int64)
    src = np.zeros(t.size, dtype=np.int64) if source is None else np.asarray(source, np.int64)
    if t.size < 2:
        return PulseDirections(0, None, None)
    order = np.lexsort((rn, t, src))
    t, xyz, rn, src = t[order], xyz[order], rn[order], src[order]
    first = np.flatnonzero(np.r_[True, (src[1:] != src[:-1]) | (t[1:] != t[:-1])])
    last = np.r_[first[1:], t.size] - 1
    size = last - first + 1
    distinct = np.ones(t.size, dtype=bool)
    distinct[1:] = rn[1:] != rn[:-1]
    repeats = np.add.reduceat((~distinct).astype(np.int64), first) - (~distinct[first])
    pulse = (size >= 2) & (size <= max_returns) & (repeats == 0)
    beam = xyz[last[pulse]] - xyz[first[pulse]]
    length = np.linalg.norm(beam, axis=1)
    keep = length >= min_separation
    if not keep.any():
        return PulseDirections(0, None, None)
    cos_nadir = -beam[keep, 2] / length[keep]
    angle = np.degrees(np.arccos(np.clip(cos_nadir, -1.0, 1.0)))
    return PulseDirections(int(keep.sum()), float(np.mean(angle <= NADIR_CONE_DEG)),
                           float(np.median(angle)))


def occupied_density(xy: np.ndarray, cell: float = 1.0) -> float | None:
    """Points per square metre where the points are: the median, over points, of the count of
    the ``cell``-metre XY cell each lies in, divided by the cell's area. None without points."""
    xy = np.asarray(xy, dtype=np.float64)
    if xy.shape[0] == 0:
        return None
    ij = np.floor((xy - column_min(xy)) / cell).astype(np.int64)
    key = ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1]
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    return float(np.median(counts[inverse.ravel()]) / (cell * cell))


def scan_angle_extent(scan_angle: np.ndarray | None) -> float | None:
    """Largest absolute scan angle in degrees, or None when the file records none (all the
    same value, as files that do not fill the field)."""
    if scan_angle is None or scan_angle.size == 0:
        return None
    angle = np.asarray(scan_angle, dtype=np.float64)
    if angle.min() == angle.max():
        return None
    return float(np.abs(angle).max())
