"""Synthetic LAS/LAZ files for the tests: one writer, the named scenes, and real-file subsets.

Every test that needs an input file writes it here; tests read files with laspy directly.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import laspy
import numpy as np
from laspy.vlrs.known import WktCoordinateSystemVlr

WKT = 'PROJCS["ETRS89 / UTM zone 32N",GEOGCS["ETRS89",DATUM["European_Terrestrial_Reference_' \
      'System_1989",SPHEROID["GRS 1980",6378137,298.257222101]]],UNIT["metre",1]]'

VERSION_FOR_FORMAT = {0: "1.2", 1: "1.2", 2: "1.2", 3: "1.2", 4: "1.3", 5: "1.3",
                      6: "1.4", 7: "1.4", 8: "1.4", 9: "1.4", 10: "1.4"}


def tag_vlr() -> laspy.VLR:
    """A VLR of our own that a result file must carry over unchanged."""
    return laspy.VLR(user_id="lidar-outliers", record_id=7, description="test vlr",
                     record_data=b"keep me")


def write_las(
    path: Path,
    xyz: np.ndarray,
    *,
    gps_time: np.ndarray | None = None,
    point_format: int = 3,
    version: str | None = None,
    offsets: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0),
    scales: Sequence[float] | np.ndarray = (0.001, 0.001, 0.001),
    classification: np.ndarray | None = None,
    point_source_id: np.ndarray | None = None,
    intensity: np.ndarray | None = None,
    extra: dict[str, np.ndarray] | None = None,
    random_dims: bool = False,
    crs: bool = False,
    evlr: bool = False,
    vlrs: Sequence[laspy.VLR] | None = None,
    laz: bool | None = None,
    seed: int = 0,
    dims: dict[str, np.ndarray] | None = None,
) -> Path:
    """Write ``xyz`` and the given dimensions to a LAS file, or LAZ when ``laz`` (default: by
    suffix); returns ``path``.

    ``extra`` adds extra-bytes dimensions typed by their values; ``random_dims`` fills every other
    standard dimension with random values drawn from ``seed``; ``crs`` adds the WKT VLR, ``evlr``
    an EVLR; ``vlrs`` are written first (default: :func:`tag_vlr`, ``()`` for none); ``dims``
    sets further standard dimensions (``return_number``, ``scan_angle``, ...) by name.
    """
    header = laspy.LasHeader(version=version or VERSION_FOR_FORMAT[point_format],
                             point_format=point_format)
    header.offsets = np.asarray(offsets, dtype=float)
    header.scales = np.asarray(scales, dtype=float)
    if extra:
        header.add_extra_dims([laspy.ExtraBytesParams(name=k, type=v.dtype) for k, v in
                               extra.items()])
    header.vlrs.extend([tag_vlr()] if vlrs is None else vlrs)
    if crs:
        if header.version.minor >= 4:
            header.vlrs.append(WktCoordinateSystemVlr(WKT))
        else:
            header.vlrs.append(laspy.VLR(user_id="LASF_Projection", record_id=2112,
                                         record_data=WKT.encode() + b"\0"))
    if evlr:
        header.evlrs = laspy.vlrs.vlrlist.VLRList(
            [laspy.VLR(user_id="lidar-outliers", record_id=42, record_data=b"evlr payload")]
        )
    las = laspy.LasData(header)
    n = xyz.shape[0]
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if random_dims:
        fill_random(las, np.random.default_rng(seed))
    for name, values in (("gps_time", gps_time), ("classification", classification),
                         ("point_source_id", point_source_id), ("intensity", intensity),
                         *(dims or {}).items(), *(extra or {}).items()):
        if values is not None:
            las[name] = values
    path = Path(path)
    las.write(str(path), do_compress=path.suffix.lower() == ".laz" if laz is None else laz)
    assert laspy.read(str(path)).header.point_count == n
    return path


def fill_random(las: laspy.LasData, rng: np.random.Generator) -> None:
    """Random values in every standard dimension other than X, Y, Z (within their bit widths)."""
    n = len(las.points)
    for dim in las.point_format.dimensions:
        if dim.name in ("X", "Y", "Z") or not dim.is_standard:
            continue
        current = np.asarray(las[dim.name])
        if dim.name == "gps_time":
            las[dim.name] = rng.uniform(0, 1e6, n)
        elif current.dtype.kind == "f":
            las[dim.name] = rng.normal(size=current.shape).astype(current.dtype)
        else:
            bits = min(dim.num_bits // max(dim.num_elements, 1), 16)
            high = 2 ** bits
            if dim.name == "return_number" or dim.name == "number_of_returns":
                high = 8 if las.point_format.id < 6 else 16
            if dim.name == "classification" and las.point_format.id < 6:
                high = 32
            low = -(high // 2) if current.dtype.kind == "i" else 0
            hi = high // 2 if current.dtype.kind == "i" else high
            las[dim.name] = rng.integers(low, hi, size=current.shape).astype(current.dtype)


def subset_las(src: Path, dst: Path, n: int) -> np.ndarray:
    """Write n evenly strided points of src to dst (real points and header); returns the index."""
    las = laspy.read(str(src))
    index = np.linspace(0, len(las.points) - 1, min(n, len(las.points))).astype(int)
    out = laspy.LasData(las.header)
    out.points = las.points[index]
    out.write(str(dst))
    return index


# ------------------------------------------------------------------------------------ scenes


def scan_line_cloud(n: int, rng: np.random.Generator, *, spikes: int = 0,
                    spike_size: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A mobile-scanner-like cloud: smooth 3-D profiles along time, optional spikes.

    Returns xyz (n, 3) in metres near the origin, gps_time (n,) seconds from 0, and a bool mask of
    the spiked points.
    """
    t = np.arange(n) * 1e-4 + rng.uniform(0, 2e-5, n)
    phase = t * 50.0
    xyz = np.column_stack(
        [10 * np.cos(phase) + 2.0 * t, 10 * np.sin(phase), 0.5 * np.sin(3 * phase)]
    )
    xyz += rng.normal(0, 0.003, xyz.shape)
    spiked = np.zeros(n, dtype=bool)
    if spikes:
        idx = rng.choice(np.arange(20, n - 20), spikes, replace=False)
        xyz[idx, 2] += spike_size
        spiked[idx] = True
    return xyz, t, spiked


def write_cloud(
    path: Path, n: int = 4000, *, seed: int = 0, laz: bool | None = None, point_format: int = 1,
    spikes: int = 20,
) -> np.ndarray:
    """Write a scan of a gently curved road profile along a straight track, ordered by
    gps_time (near 500,000 s, coordinates near a projected easting/northing), with ``spikes``
    points lifted by 2 m. Returns the indices of the spikes."""
    rng = np.random.default_rng(seed)
    t = 500_000.0 + np.arange(n) * 1e-4
    phase = np.arange(n) * 0.05
    x = 500_000.0 + 10.0 * (t - t[0]) + 3.0 * np.cos(phase)
    y = 5_000_000.0 + 3.0 * np.sin(phase)
    z = 100.0 + 0.02 * np.sin(phase) + rng.normal(0.0, 0.003, n)
    idx = np.sort(rng.choice(np.arange(20, n - 20), size=spikes, replace=False))
    z[idx] += 2.0
    has_time = "gps_time" in laspy.PointFormat(point_format).dimension_names
    write_las(path, np.column_stack([x, y, z]), gps_time=t if has_time else None,
              point_format=point_format, version="1.2" if point_format < 6 else "1.4",
              offsets=(500_000.0, 5_000_000.0, 0.0),
              point_source_id=np.ones(n, dtype=np.uint16),
              classification=np.ones(n, dtype=np.uint8),
              intensity=rng.integers(0, 1000, n).astype(np.uint16), vlrs=(), laz=laz)
    return idx


def untimed_cloud(path: Path, n: int = 500) -> Path:
    """:func:`write_cloud`'s road with every gps_time NaN: the header and the request are
    fine, and the temporal detector fails in the worker (a job that fails)."""
    write_cloud(path, n=n, point_format=1)
    las = laspy.read(path)
    las.gps_time = np.full(n, np.nan)
    las.write(path)
    return path


def tile_scene(path: Path, n: int = 7000, seed: int = 3) -> Path:
    """A sloped, rolling 24 x 24 m ground with a 2 m box on it, 1 % of points 1.5 m off the
    surface, a few dark points (intensity 0), a drive's time stamps; near a UTM coordinate
    (600,000, 5,000,000). For runs tile by tile against the whole cloud."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 24, (n, 2))
    z = 0.05 * xy[:, 0] + 0.3 * np.sin(xy[:, 1] / 3) + rng.normal(0, 0.005, n)
    z[(np.abs(xy[:, 0] - 12) < 3) & (np.abs(xy[:, 1] - 10) < 2)] += 2.0
    off = rng.choice(n, n // 100, replace=False)
    z[off] += rng.choice([-1.5, 1.5], off.size)
    intensity = rng.integers(1, 50, n).astype(np.uint16)
    intensity[rng.choice(n, n // 25, replace=False)] = 0
    return write_las(path, np.column_stack([xy + [600_000, 5_000_000], z + 50]),
                     gps_time=np.sort(rng.uniform(1000, 1100, n)),
                     point_source_id=np.ones(n, np.uint16), intensity=intensity,
                     offsets=(600_000, 5_000_000, 0), vlrs=())


def scanned_tile_scene(path: Path, *, shuffled: bool = False, seed: int = 3) -> Path:
    """:func:`tile_scene`'s points with the time stamps of two scanners sweeping it line by
    line (lines 0.25 m apart in y, back and forth in x; scanner 1 the west half, 2 the east),
    so that ``temporal`` follows real scan lines; records in time order, or ``shuffled``."""
    las = laspy.read(tile_scene(path, seed=seed))
    x, y = np.asarray(las.x) - 600_000, np.asarray(las.y) - 5_000_000
    line = np.floor(y / 0.25)
    rng = np.random.default_rng(seed)
    along = (np.where(line % 2 == 0, x, 24.0 - x) + rng.normal(0, 0.005, x.size)) / 24.0
    t = 1000.0 + 0.1 * line + 0.09 * along  # a beam 5 mm off the line's pace
    order = rng.permutation(len(t)) if shuffled else np.argsort(t)
    las.gps_time = t
    las.point_source_id = np.where(x < 12.0, 1, 2).astype(np.uint16)
    las.points = las.points[order]
    las.write(str(path))
    return Path(path)


def _surface(rng: np.random.Generator, lo, hi, density: float) -> np.ndarray:
    """Points uniform in the box lo..hi (one side of zero size: a plane), ``density`` a m2."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    span = hi - lo
    area = np.prod(np.sort(span)[1:])
    return lo + rng.uniform(0, 1, (int(area * density), 3)) * span


def street_scene(path: Path, shuffled: bool = False) -> Path:
    """Two scanners driving along x at 5 m/s, the second seeing each place 2 s after the first:
    a road and a wall both saw (persistent); a 12 m stretch of road only the first saw (one
    pass, attached); a canopy 15 m long over the road only the second saw, between its road
    returns (floating and revisited, but wider than max_extent); a 4 m box floating over the
    road, seen by the first scanner while it swept the road 15 m behind (moving, flagged)."""
    rng = np.random.default_rng(8)
    parts, times, sources = [], [], []

    def add(xyz: np.ndarray, source: np.ndarray, t: np.ndarray) -> None:
        parts.append(xyz), sources.append(source), times.append(t)

    def seen(xyz: np.ndarray, source: np.ndarray) -> np.ndarray:
        return 10 + xyz[:, 0] / 5 + 2.0 * (source == 2) + rng.uniform(0, 0.01, len(xyz))

    for lo, hi in (((0, 0, 0), (30, 6, 0)), ((0, 7, 0), (30, 7, 3))):  # road and wall
        xyz = _surface(rng, lo, hi, 25)
        source = rng.integers(1, 3, len(xyz))
        add(xyz, source, seen(xyz, source))
    once = _surface(rng, (30, 0, 0), (42, 6, 0), 25)  # one pass
    add(once, np.ones(len(once), int), seen(once, np.ones(len(once))))
    canopy = _surface(rng, (5, 2, 4.5), (20, 3, 4.5), 40)
    add(canopy, np.full(len(canopy), 2), seen(canopy, np.full(len(canopy), 2)))
    box = np.vstack([_surface(rng, (20, 3.5, 2.5), (24, 5, 2.5), 40),
                     _surface(rng, (20, 3.5, 1.0), (24, 3.5, 2.5), 40)])
    add(box, np.ones(len(box), int), rng.uniform(11.0, 11.3, len(box)))
    xyz, t, source = np.vstack(parts), np.concatenate(times), np.concatenate(sources)
    xyz += rng.normal(0, 0.003, xyz.shape)  # surfaces a few mm rough, as scanned
    order = rng.permutation(len(t)) if shuffled else np.argsort(t)
    return write_las(path, xyz[order] + [600_000, 5_000_000, 50], gps_time=t[order] + 1000,
                     point_source_id=source[order].astype(np.uint16),
                     offsets=(600_000, 5_000_000, 0), vlrs=())


def corridor_survey(rng: np.random.Generator, stop: tuple[float, float] = (1.0, 2.0),
                    speed: float = 1.0, end: float = 3.0, plume: float = 0.0
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A profile scanner 1.5 m up turning at 50.37 Hz (20 kHz pulses, 0.9 degrees apart, the
    phase drifting from turn to turn) in the y-z plane inside a corridor (floor z = 0, walls
    y = +-5, ceiling z = 6), driving along x at ``speed`` except during ``stop``; while it
    stands, a share ``plume`` of the pulses that cross a ball of 0.4 m around (y 2, z 0.6)
    (exhaust beside the vehicle) return from a droplet somewhere inside it: (gps_time, xyz,
    droplet)."""
    t = np.arange(0.0, end, 1 / 20_000)
    moving = np.clip(t, None, stop[0]) + np.clip(t - stop[1], 0, None)
    x = speed * moving
    theta = 2 * np.pi * 50.37 * t
    dy, dz = np.cos(theta), np.sin(theta)
    with np.errstate(divide="ignore"):
        to_wall = np.where(dy != 0, 5.0 / np.abs(dy), np.inf)
        to_floor = np.where(dz < 0, 1.5 / -dz, np.inf)
        to_ceiling = np.where(dz > 0, 4.5 / dz, np.inf)
    r = np.minimum(to_wall, np.minimum(to_floor, to_ceiling))
    # the ball's chord along each beam (centre at range c along, b across it)
    along = 2.0 * dy + (0.6 - 1.5) * dz
    across = np.abs(2.0 * dz - (0.6 - 1.5) * dy)
    half = np.sqrt(np.clip(0.4**2 - across**2, 0, None))
    standing = (t >= stop[0]) & (t <= stop[1])
    droplet = standing & (half > 0) & (along > 0) & (rng.random(len(t)) < plume)
    r = np.where(droplet, along + rng.uniform(-1, 1, len(t)) * half, r)
    xyz = np.column_stack([x, r * dy, 1.5 + r * dz]) + rng.normal(0, 0.002, (len(t), 3))
    return t, xyz, droplet


def stop_scene(path: Path, shuffled: bool = False) -> Path:
    """:func:`corridor_survey` with exhaust at its stop of 1.8 s, which starts and ends inside
    seconds of GPS time (so it is cut into three pieces), as a LAS file near a UTM coordinate;
    the droplets' indices in the file in ``droplet`` of a ``.npy`` beside it."""
    t, xyz, droplet = corridor_survey(np.random.default_rng(11), stop=(0.75, 2.55), end=3.3,
                                      plume=0.3)
    order = np.random.default_rng(12).permutation(len(t)) if shuffled else np.arange(len(t))
    np.save(path.with_suffix(".npy"), np.flatnonzero(droplet[order]))
    return write_las(path, xyz[order] + [600_000, 5_000_000, 50], gps_time=t[order] + 1000.0,
                     point_source_id=np.ones(len(t), np.uint16), offsets=(600_000, 5_000_000, 0),
                     vlrs=())


#: transient's stage on :func:`street_scene`: radius for its density, max_extent below the
#: canopy's length and above the box's.
STREET_TRANSIENT = {"detector": "transient", "radius": 0.5, "max_extent": 6.0}


def airborne_scene(path: Path, seed: int = 4) -> Path:
    """A 32 x 32 m airborne-like cloud (4 returns a square metre): rolling, sloped ground, an
    8 x 6 m flat roof 4 m over it, a clump of 40 returns 4 m under the ground (low noise), a
    flock of 6 returns 30 m over it (birds) and one return 2.5 m under it (a pit); in scan
    order, near a UTM coordinate. For ``detached`` tile by tile against the whole cloud."""
    rng = np.random.default_rng(seed)

    def ground(xy: np.ndarray) -> np.ndarray:
        return 0.04 * xy[:, 0] + 0.4 * np.sin(xy[:, 1] / 4) + 0.2 * np.cos(xy[:, 0] / 5)

    xy = rng.uniform(0, 32, (4096, 2))
    z = ground(xy) + rng.normal(0, 0.03, len(xy))
    roof = (np.abs(xy[:, 0] - 20) < 4) & (np.abs(xy[:, 1] - 10) < 3)
    z[roof] = ground(np.array([[20.0, 10.0]]))[0] + 4.0 + rng.normal(0, 0.02, roof.sum())
    clump_xy = rng.normal([9.0, 22.0], 0.5, (40, 2))
    clump = np.c_[clump_xy, ground(clump_xy) - 4.0 + rng.normal(0, 0.3, 40)]
    birds_xy = rng.normal([24.0, 25.0], 0.8, (6, 2))
    birds = np.c_[birds_xy, ground(birds_xy) + 30.0 + rng.normal(0, 0.5, 6)]
    pit = np.array([[14.3, 5.7, ground(np.array([[14.3, 5.7]]))[0] - 2.5]])
    xyz = np.vstack([np.c_[xy, z], clump, birds, pit])
    xyz = xyz[np.argsort(xyz[:, 1] + 0.01 * xyz[:, 0], kind="stable")]  # scan lines along x
    return write_las(path, xyz + [600_000, 5_000_000, 300],
                     gps_time=np.linspace(2000, 2010, len(xyz)),
                     point_source_id=np.ones(len(xyz), np.uint16),
                     offsets=(600_000, 5_000_000, 0), vlrs=())
