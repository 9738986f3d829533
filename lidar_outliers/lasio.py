"""LAS/LAZ in and out: header validation, reading into plain arrays, writing flagged results.

Three jobs, kept apart from the detectors (which only ever see numpy arrays):

* :func:`inspect_las` checks the public header, the VLR chain, the LASzip VLR and the EVLRs with
  ``struct`` before laspy opens the file, because some malformed files make laspy hang (a VLR
  count of ~1e9) or make lazrs panic (no chunk table). Every refusal is a one-line
  :class:`~lidar_outliers.errors.LasFormatError`.
* :func:`read_cloud` reads the points in chunks into a :class:`Cloud`: coordinates as float64
  relative to a local origin (so that polynomial arithmetic on coordinates near 5,000,000 m keeps
  its precision), GPS time as float64 and the few other dimensions the detectors need.
* :func:`read_profile_sample` reads a bounded sample of short runs of consecutive points spread
  over the file (a :class:`ProfileSample`), with the dimensions that tell the platform apart
  (return numbers, scan angle, scanner channel), for the choice of the sensor profile.
* :func:`write_result` rewrites the input chunk by chunk with every original dimension, VLR, EVLR
  and CRS, plus the extra-bytes dimensions ``outlier_flags`` and ``<detector>_score``. Output goes
  to a temporary name in the target folder and is renamed when complete, so a failed or repeated
  run never leaves a partial file. :func:`write_filtered` does the same for ``?keep=`` downloads.
"""

from __future__ import annotations

import contextlib
import copy
import os
import struct
import sys
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import laspy
import numpy as np
from laspy.vlrs.vlrlist import VLRList

from lidar_outliers.atomic import atomic_path
from lidar_outliers.cloud import Cloud
from lidar_outliers.errors import LasFormatError
from lidar_outliers.output import FLAGS_DIMENSION, result_dimensions, score_dimension
from lidar_outliers.pages import release

Progress = Callable[[float, str], None]

#: Minimum point record length (bytes) per point data record format (LAS 1.4 R15, table 8 ff.).
MIN_RECORD_LENGTH: dict[int, int] = {
    0: 20, 1: 28, 2: 26, 3: 34, 4: 57, 5: 63, 6: 30, 7: 36, 8: 38, 9: 59, 10: 67,
}
#: Smallest public header per minor version.
MIN_HEADER_SIZE: dict[int, int] = {0: 227, 1: 227, 2: 227, 3: 235, 4: 375}
FORMATS_WITH_GPS_TIME = frozenset({1, 3, 4, 5, 6, 7, 8, 9, 10})
#: VLR user ids laspy writes itself (LASzip) or that describe a layout we do not keep (COPC).
_DROPPED_VLR_USERS = frozenset({"laszip encoded", "copc"})
_VLR_HEADER = 54
_EVLR_HEADER = 60
_LASZIP_USER, _LASZIP_RECORD = b"laszip encoded", 22204
#: Points read or written at a time. A chunk's arrays (about 9 MB of records for 250 k points)
#: stay below glibc's largest mmap threshold (32 MB), so freed chunks are reused from the heap
#: instead of being mapped and zero-filled again; 1 M point chunks made a command 4 % slower.
DEFAULT_CHUNK_POINTS = 250_000


@dataclass
class LasFacts:
    """What the header says about a LAS/LAZ file (all JSON-serialisable via :meth:`to_dict`)."""

    name: str
    bytes: int
    points: int
    las_version: str
    point_format: int
    compressed: bool
    has_gps_time: bool
    record_length: int
    scales: list[float]
    offsets: list[float]
    bounds: dict[str, list[float]]
    extra_dimensions: list[str]
    crs: str | None
    geotiff_crs: bool = False
    vlrs: list[str] = field(default_factory=list)
    evlrs: list[str] = field(default_factory=list)
    system_identifier: str = ""
    generating_software: str = ""
    geographic: bool = False

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


# --------------------------------------------------------------------------- header validation


def inspect_las(path: str | os.PathLike[str]) -> LasFacts:
    """Validate a LAS/LAZ header with ``struct`` and return its facts.

    Raises
    ------
    LasFormatError
        With a one-line message for anything that is not a readable LAS 1.0-1.4 file with point
        format 0-10 (bad signature or version, truncated header, VLR chain inconsistent with the
        offset to the point data, too few bytes for the points, unsupported LAZ compressor...).
    """
    path = Path(path)
    name = path.name
    try:
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(375)
    except OSError as exc:
        raise LasFormatError(f"cannot read {name}: {exc.strerror or exc}") from None
    if len(head) < 4 or head[:4] != b"LASF":
        raise LasFormatError(
            f"{name} is not a LAS/LAZ file (signature {head[:4]!r}, expected b'LASF')"
        )
    if len(head) < 227:
        raise LasFormatError(f"{name} is truncated: {size} bytes, a LAS header needs 227")
    major, minor = head[24], head[25]
    if major != 1 or minor not in MIN_HEADER_SIZE:
        raise LasFormatError(f"{name}: LAS version {major}.{minor} is not supported (1.0-1.4)")
    header_size, offset, n_vlrs, pf_byte, record_length, legacy_count = struct.unpack_from(
        "<HIIBHI", head, 94
    )
    if header_size < MIN_HEADER_SIZE[minor]:
        raise LasFormatError(
            f"{name}: header size {header_size} is smaller than the {MIN_HEADER_SIZE[minor]} "
            f"bytes of a LAS 1.{minor} header"
        )
    if len(head) < MIN_HEADER_SIZE[minor]:
        raise LasFormatError(f"{name} is truncated inside the LAS 1.{minor} header")
    if offset < header_size or offset > size:
        raise LasFormatError(
            f"{name}: offset to point data {offset} lies outside the file "
            f"(header {header_size} bytes, file {size} bytes)"
        )
    compressed = bool(pf_byte & 0xC0)
    point_format = pf_byte & 0x3F
    if point_format not in MIN_RECORD_LENGTH:
        raise LasFormatError(f"{name}: point format {point_format} is not supported (0-10)")
    if record_length < MIN_RECORD_LENGTH[point_format]:
        raise LasFormatError(
            f"{name}: point record length {record_length} is below the "
            f"{MIN_RECORD_LENGTH[point_format]} bytes of point format {point_format}"
        )
    scales = struct.unpack_from("<3d", head, 131)
    offsets = struct.unpack_from("<3d", head, 155)
    mx, nx, my, ny, mz, nz = struct.unpack_from("<6d", head, 179)
    if not all(np.isfinite(s) and s != 0 for s in scales) or not np.all(np.isfinite(offsets)):
        raise LasFormatError(f"{name}: scale factors {scales} / offsets {offsets} are not usable")
    count = legacy_count
    n_evlrs, evlr_start = 0, 0
    if minor >= 4:
        evlr_start, n_evlrs, count64 = struct.unpack_from("<QIQ", head, 235)
        count = count64 or legacy_count

    with open(path, "rb") as fh:
        fh.seek(header_size)
        vlr_bytes = fh.read(offset - header_size)
        vlrs = _walk_vlrs(name, vlr_bytes, n_vlrs, header_size, offset)
        evlrs = _walk_evlrs(name, fh, size, evlr_start, n_evlrs) if n_evlrs else []

    point_end = offset + count * record_length
    if compressed:
        _check_laszip(name, vlrs, path, offset, size, count)
    elif point_end > size:
        have = (size - offset) // record_length
        raise LasFormatError(
            f"{name} is truncated: header says {count} points of {record_length} bytes, "
            f"the file holds {have}"
        )
    if n_evlrs and not compressed and evlr_start < point_end:
        raise LasFormatError(f"{name}: EVLRs start at byte {evlr_start}, inside the point data")

    all_records = vlrs + evlrs
    wkt = _wkt(all_records)
    facts = LasFacts(
        name=name,
        bytes=size,
        points=int(count),
        las_version=f"{major}.{minor}",
        point_format=point_format,
        compressed=compressed,
        has_gps_time=point_format in FORMATS_WITH_GPS_TIME,
        record_length=record_length,
        scales=list(scales),
        offsets=list(offsets),
        bounds={"min": [nx, ny, nz], "max": [mx, my, mz]},
        extra_dimensions=[],
        crs=wkt,
        geotiff_crs=any(u == "LASF_Projection" and r == 34735 for u, r, _ in all_records),
        vlrs=[f"{u}/{r}" for u, r, _ in vlrs],
        evlrs=[f"{u}/{r}" for u, r, _ in evlrs],
        system_identifier=_header_text(head[26:58]),
        generating_software=_header_text(head[58:90]),
        geographic=_geographic(wkt, all_records),
    )
    # The header is sound: laspy may now parse it (extra-bytes descriptors, LAZ chunk table).
    with _laspy_errors(name):
        with laspy.open(path) as reader:
            facts.extra_dimensions = list(reader.header.point_format.extra_dimension_names)
    return facts


def _geographic(wkt: str | None, records: list[tuple[str, int, bytes]]) -> bool:
    """True when the CRS is geographic (coordinates in degrees): a WKT that starts with a
    geographic CRS, or GeoTIFF's GTModelTypeGeoKey (1024) = 2."""
    if wkt is not None:
        return wkt.lstrip().upper().startswith(("GEOGCS", "GEOGCRS", "GEODCRS"))
    for user, record_id, payload in records:
        if user == "LASF_Projection" and record_id == 34735 and len(payload) >= 8:
            keys = struct.unpack_from("<H", payload, 6)[0]
            for i in range(min(keys, (len(payload) - 8) // 8)):
                key, location, _, value = struct.unpack_from("<4H", payload, 8 + 8 * i)
                if key == 1024 and location == 0:
                    return value == 2
    return False


def _header_text(raw: bytes) -> str:
    """A fixed-width header string: up to its first NUL, printable ASCII, stripped."""
    text = raw.split(b"\0", 1)[0].decode("ascii", errors="replace")
    return "".join(c for c in text if c.isprintable()).strip()


def _walk_vlrs(
    name: str, data: bytes, n_vlrs: int, header_size: int, offset: int
) -> list[tuple[str, int, bytes]]:
    """(user_id, record_id, payload) of every VLR; the chain must end before the points."""
    room = len(data)
    if n_vlrs * _VLR_HEADER > room:
        raise LasFormatError(
            f"{name}: header claims {n_vlrs} VLRs but only {room} bytes lie between the header "
            f"and the point data at byte {offset}"
        )
    out, pos = [], 0
    for i in range(n_vlrs):
        if pos + _VLR_HEADER > room:
            raise LasFormatError(
                f"{name}: header claims {n_vlrs} VLRs but only {i} fit before the point data "
                f"at byte {offset}"
            )
        user = data[pos + 2 : pos + 18].split(b"\0", 1)[0]
        record_id, length = struct.unpack_from("<HH", data, pos + 18)
        end = pos + _VLR_HEADER + length
        if end > room:
            raise LasFormatError(
                f"{name}: VLR {i + 1} of {n_vlrs} ({length} bytes) runs past the start of the "
                f"point data at byte {offset}"
            )
        user_id = user.decode("ascii", errors="replace")
        out.append((user_id, record_id, data[pos + _VLR_HEADER : end]))
        pos = end
    return out


def _walk_evlrs(name: str, fh: Any, size: int, start: int, n: int) -> list[tuple[str, int, bytes]]:
    out, pos = [], start
    for i in range(n):
        if pos + _EVLR_HEADER > size:
            raise LasFormatError(f"{name}: EVLR {i + 1} of {n} starts past the end of the file")
        fh.seek(pos)
        head = fh.read(_EVLR_HEADER)
        user = head[2:18].split(b"\0", 1)[0].decode("ascii", errors="replace")
        record_id, length = struct.unpack_from("<HQ", head, 18)
        if pos + _EVLR_HEADER + length > size:
            raise LasFormatError(f"{name}: EVLR {i + 1} of {n} runs past the end of the file")
        # Only the CRS payload is needed; do not read large EVLRs (e.g. waveforms) into memory.
        wanted = user == "LASF_Projection" and record_id == 2112 and length < 1 << 20
        payload = fh.read(length) if wanted else b""
        out.append((user, record_id, payload))
        pos += _EVLR_HEADER + length
    return out


def _check_laszip(
    name: str, vlrs: list[tuple[str, int, bytes]], path: Path, offset: int, size: int, count: int
) -> None:
    """A compressed file needs a LASzip VLR describing a chunked compressor lazrs can read."""
    laszip = [p for u, r, p in vlrs if u.encode() == _LASZIP_USER and r == _LASZIP_RECORD]
    if not laszip:
        raise LasFormatError(f"{name}: the point format says compressed but there is no LASzip VLR")
    payload = laszip[0]
    if len(payload) < 34:
        raise LasFormatError(f"{name}: the LASzip VLR is truncated ({len(payload)} bytes)")
    compressor, _, vmaj, vmin, vrev, _, chunk_size = struct.unpack_from("<HHBBHII", payload)
    if compressor not in (2, 3):
        raise LasFormatError(
            f"{name}: LAZ compressor {compressor} (LASzip {vmaj}.{vmin}r{vrev}, not chunked) is "
            f"not supported; re-compress it with a current laszip"
        )
    if count == 0:
        return
    if size < offset + 8:
        raise LasFormatError(f"{name} is truncated: no compressed point data after byte {offset}")
    with open(path, "rb") as fh:
        fh.seek(offset)
        (table_offset,) = struct.unpack("<q", fh.read(8))
    if chunk_size == 0xFFFFFFFF and not (offset + 8 <= table_offset <= size - 8):
        raise LasFormatError(
            f"{name}: LAZ file with variable-size chunks has no valid chunk table "
            f"(offset {table_offset}, file {size} bytes)"
        )
    if table_offset > size - 8:  # -1: a writer that kept no table; nothing to check
        raise LasFormatError(
            f"{name} is truncated: its compressed points end at byte {table_offset} (where "
            f"their chunk table starts) but the file has {size} bytes; send the whole file"
        )


def _wkt(records: list[tuple[str, int, bytes]]) -> str | None:
    for user, record_id, payload in records:
        if user == "LASF_Projection" and record_id == 2112 and payload:
            text = payload.split(b"\0", 1)[0].decode("utf-8", errors="replace").strip()
            return text or None
    return None


@contextlib.contextmanager
def _laspy_errors(name: str) -> Iterator[None]:
    """Turn anything laspy or lazrs raises (lazrs panics are BaseExceptions) into one line."""
    try:
        yield
    except LasFormatError:
        raise
    except (KeyboardInterrupt, SystemExit, GeneratorExit):
        raise
    except BaseException as exc:  # noqa: B036 - pyo3 PanicException derives from BaseException
        text = " ".join(str(exc).split()) or type(exc).__name__
        raise LasFormatError(f"{name}: cannot read the points ({text})") from None


# --------------------------------------------------------------------------- reading


def iter_chunks(
    path: str | os.PathLike[str], chunk_points: int = DEFAULT_CHUNK_POINTS
) -> Iterator[laspy.ScaleAwarePointRecord]:
    """Point records of a validated file, ``chunk_points`` at a time, laspy errors as one line.

    Raises LasFormatError when the file ends before the header's point count.
    """
    name = Path(path).name
    with _laspy_errors(name):
        reader = laspy.open(path)
    with reader:
        expected = reader.header.point_count
        seen = 0
        iterator = reader.chunk_iterator(chunk_points)
        while True:
            with _laspy_errors(name):
                chunk = next(iterator, None)
            if chunk is None or len(chunk) == 0:
                break
            seen += len(chunk)
            yield chunk
        if seen != expected:
            raise LasFormatError(f"{name} is truncated: header says {expected} points, read {seen}")


def local_origin(header: laspy.LasHeader) -> np.ndarray:
    """A point of the file's integer grid near the centre of the header bounds.

    Centring on a grid point makes ``(X - X0) * scale`` exact up to one rounding, so that local
    coordinates keep full precision whatever the magnitude of the world coordinates.
    """
    scales, offsets = np.asarray(header.scales), np.asarray(header.offsets)
    centre = (np.asarray(header.mins) + np.asarray(header.maxs)) / 2.0
    centre = np.where(np.isfinite(centre), centre, offsets)
    grid = np.round((centre - offsets) / scales)
    grid = np.clip(grid, -(2.0**31), 2.0**31 - 1)
    return offsets + grid * scales


def grid_origin(header: laspy.LasHeader) -> tuple[np.ndarray, np.ndarray]:
    """The integer grid index and world position of the local origin."""
    scales, offsets = np.asarray(header.scales), np.asarray(header.offsets)
    origin = local_origin(header)
    grid = np.round((origin - offsets) / scales).astype(np.int64)
    return grid, origin


def local_anchor(header: laspy.LasHeader, grid: np.ndarray) -> np.ndarray:
    """(2,) the header's lower-left XY corner in the local frame, computed as :func:`local_xyz`
    computes a point's coordinates (so the lowest point lies exactly on it, far from 0 too)."""
    scales, offsets = np.asarray(header.scales), np.asarray(header.offsets)
    low = np.round((np.asarray(header.mins, dtype=np.float64) - offsets) / scales)
    low = np.where(np.isfinite(low), low, grid)
    return ((low - grid) * scales)[:2]


def local_xyz(
    chunk: laspy.ScaleAwarePointRecord, grid: np.ndarray, scales: np.ndarray,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """(c, 3) float64 coordinates of a chunk relative to the grid point ``grid`` (integers)."""
    if out is None:
        out = np.empty((len(chunk), 3), dtype=np.float64)
    for axis, dim in enumerate("XYZ"):
        # X - grid is exact in float64 (|X - grid| < 2^33), so this is (X - grid) * scale with
        # one rounding, as with integer arithmetic, and without temporaries.
        column = out[:, axis]
        np.subtract(chunk.array[dim], float(grid[axis]), out=column)
        column *= scales[axis]
    return out


def read_cloud(
    path: str | os.PathLike[str],
    *,
    chunk_points: int = DEFAULT_CHUNK_POINTS,
    progress: Progress | None = None,
    progress_span: tuple[float, float] = (0.0, 1.0),
    records: list[laspy.ScaleAwarePointRecord] | None = None,
) -> Cloud:
    """Read a validated LAS/LAZ file into a :class:`Cloud` (chunk by chunk, in file order).

    ``progress(fraction, message)`` is called after each chunk, with fractions inside
    ``progress_span``; an exception it raises propagates unchanged. ``records``, when given,
    receives the raw point records too, so that ``write_result`` need not read the file again
    (they hold the file's point bytes in memory).
    """
    name = Path(path).name
    with _laspy_errors(name), laspy.open(path) as reader:
        header = reader.header
    n = int(header.point_count)
    dims = set(header.point_format.dimension_names)
    grid, origin = grid_origin(header)
    scales = np.asarray(header.scales)
    xyz = np.empty((n, 3), dtype=np.float64)
    gps = np.empty(n, dtype=np.float64) if "gps_time" in dims else None
    psid = np.empty(n, dtype=np.uint16)
    cls = np.empty(n, dtype=np.uint8)
    intensity = np.empty(n, dtype=np.uint16)
    start = 0
    lo, hi = progress_span
    for chunk in iter_chunks(path, chunk_points):
        stop = start + len(chunk)
        local_xyz(chunk, grid, scales, out=xyz[start:stop])
        if gps is not None:
            gps[start:stop] = chunk.array["gps_time"]
        psid[start:stop] = chunk.array["point_source_id"]
        cls[start:stop] = np.asarray(chunk.classification)
        intensity[start:stop] = chunk.array["intensity"]
        if records is not None:
            records.append(chunk)
        start = stop
        if progress is not None:
            progress(lo + (hi - lo) * stop / max(n, 1), f"reading {stop:,} of {n:,} points")
    return Cloud(xyz, origin, gps, psid, cls, intensity, anchor=local_anchor(header, grid),
                 scales=np.asarray(header.scales, dtype=np.float64))


#: Points read for the profile choice (:func:`read_profile_sample`), whatever the file's size.
PROFILE_SAMPLE_POINTS = 250_000
#: Consecutive points per run of the sample: whole pulses and scan lines, a millisecond or more
#: of acquisition.
PROFILE_RUN_POINTS = 2_500


@dataclass
class ProfileSample:
    """A bounded sample of a file's points, for the choice of the sensor profile.

    Runs of consecutive points (in file order) spread evenly over the file; every array has one
    entry per sampled point. ``xyz`` is relative to ``origin`` (world = xyz + origin);
    ``source`` is point_source_id x 16 + scanner channel (one id per scanner and flight line);
    ``scan_angle`` in degrees. Dimensions the point format lacks are None.
    """

    xyz: np.ndarray
    origin: np.ndarray
    gps_time: np.ndarray | None
    return_number: np.ndarray | None
    number_of_returns: np.ndarray | None
    source: np.ndarray
    scan_angle: np.ndarray | None
    points_in_file: int
    runs: int

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


def read_profile_sample(
    path: str | os.PathLike[str],
    max_points: int = PROFILE_SAMPLE_POINTS,
    run_points: int = PROFILE_RUN_POINTS,
) -> ProfileSample:
    """At most ``max_points`` points of a validated file: all of a small file, else runs of
    consecutive points at even steps through the file (so the sample spans the whole
    acquisition, and each run holds whole pulses and scan lines).

    Files of up to 4 x ``max_points`` points (or LAZ files of under ten chunks) are read through
    once; larger ones run by run after a seek, in a LAZ file with fixed-size chunks from chunk
    boundaries (a run then costs its own points only), so the cost is bounded whatever the
    file's size.
    """
    name = Path(path).name
    with _laspy_errors(name), laspy.open(path) as reader:
        header = reader.header
    n = int(header.point_count)
    count = max(1, max_points // run_points)
    chunk = _laz_chunk_points(header)
    # One pass costs little below 4 x max_points, or when a LAZ file has too few chunks to
    # start ten runs on their boundaries (under ten chunks, 500 k points at the usual 50 k).
    sequential = n <= 4 * max_points or bool(chunk and n // chunk < 10)
    runs: list[tuple[int, int]]  # (first point, points)
    if n <= max_points:
        runs = [(0, n)] if n else []
    elif sequential or not chunk:
        runs = [(i * (n // count), run_points) for i in range(count)]
    else:  # whole chunks are decompressed: start runs on their boundaries
        count = min(count, n // chunk)
        step = (n // chunk) // count * chunk
        length = min(chunk, max(run_points, max_points // count))
        runs = [(i * step, length) for i in range(count)]
    records = _read_runs(path, runs, sequential=sequential)
    grid, origin = grid_origin(header)
    scales = np.asarray(header.scales)
    dims = set(header.point_format.dimension_names)

    def column(dim: str, dtype: type) -> np.ndarray:
        if not records:
            return np.zeros(0, dtype=dtype)
        return np.concatenate([np.asarray(r[dim], dtype=dtype) for r in records])

    xyz = (np.concatenate([local_xyz(r, grid, scales) for r in records]) if records
           else np.zeros((0, 3)))
    channel = column("scanner_channel", np.int64) if "scanner_channel" in dims else 0
    if "scan_angle" in dims:  # point formats 6-10: 0.006 degree steps
        scan_angle = column("scan_angle", np.float64) * 0.006
    elif "scan_angle_rank" in dims:
        scan_angle = column("scan_angle_rank", np.float64)
    else:
        scan_angle = None
    return ProfileSample(
        xyz=xyz,
        origin=origin,
        gps_time=column("gps_time", np.float64) if "gps_time" in dims else None,
        return_number=column("return_number", np.int64),
        number_of_returns=column("number_of_returns", np.int64),
        source=column("point_source_id", np.int64) * 16 + channel,
        scan_angle=scan_angle,
        points_in_file=n,
        runs=len(runs),
    )


def _read_runs(
    path: str | os.PathLike[str], runs: list[tuple[int, int]], sequential: bool
) -> list[laspy.ScaleAwarePointRecord]:
    """The point records of each (first point, points) run, in file order."""
    name = Path(path).name
    if sequential:
        wanted = np.zeros(0, dtype=np.int64)
        if runs:
            wanted = np.concatenate([np.arange(a, a + k) for a, k in runs])
        out, start = [], 0
        for chunk in iter_chunks(path):
            stop = start + len(chunk)
            lo, hi = np.searchsorted(wanted, [start, stop])
            if hi > lo:
                out.append(chunk[wanted[lo:hi] - start])
            start = stop
        return out
    out = []
    # The single-threaded LAZ decoder seeks in milliseconds; the parallel one re-reads chunks.
    backend = laspy.LazBackend.Lazrs if laspy.LazBackend.Lazrs.is_available() else None
    with _laspy_errors(name), laspy.open(path, laz_backend=backend) as reader:
        for first, count in runs:
            reader.seek(first)
            out.append(reader.read_points(count))
    return out


def _laz_chunk_points(header: laspy.LasHeader) -> int | None:
    """Points per LAZ chunk from the LASzip VLR (None: not LAZ, or variable-size chunks)."""
    for vlr in header.vlrs:
        if isinstance(vlr, laspy.vlrs.known.LasZipVlr):
            raw = bytes(vlr.record_data_bytes())
            if len(raw) >= 16:
                (chunk,) = struct.unpack_from("<I", raw, 12)
                return chunk if 0 < chunk < 0xFFFFFFFF else None
    return None


# --------------------------------------------------------------------------- writing


def _output_header(
    in_header: laspy.LasHeader, new_dims: list[tuple[str, type, str]]
) -> laspy.LasHeader:
    """Copy of the input header with our extra dimensions appended (replaced if already there).

    LASzip and COPC VLRs are dropped: laspy writes its own LASzip VLR, and the COPC hierarchy
    does not describe the rewritten file. LAS 1.0 is written as 1.2 (laspy cannot write 1.0).
    """
    header = copy.deepcopy(in_header)
    if header.version.minor == 0:
        # laspy cannot write LAS 1.0; 1.2 has the same point formats 0 and 1 and header layout.
        header.version = laspy.header.Version(1, 2)
    header.vlrs = VLRList(
        v for v in header.vlrs if v.user_id.strip("\0").strip() not in _DROPPED_VLR_USERS
    )
    if header.evlrs is not None:
        header.evlrs = VLRList(
            v for v in header.evlrs if v.user_id.strip("\0").strip() not in _DROPPED_VLR_USERS
        )
    _register_unregistered_bytes(header)
    _rename_clashing_dimensions(header, new_dims)
    existing = set(header.point_format.extra_dimension_names)
    params = [
        laspy.ExtraBytesParams(name=n, type=t, description=d)
        for n, t, d in new_dims
        if n not in existing
    ]
    if params:
        header.add_extra_dims(params)
    return header


#: Appended to the name of an input dimension that a result dimension of another type needs.
CLASHING_SUFFIX = "_input"


def _rename_clashing_dimensions(header: laspy.LasHeader,
                                new_dims: list[tuple[str, type, str]]) -> None:
    """Rename the input's extra dimensions that carry a result dimension's name but not its type
    (a ``detached_score`` of uint8 would cut scores to integers and NaN to 0): their bytes stay,
    under ``<name>_input``; a dimension of the same type (an earlier result) is overwritten in
    place."""
    wanted = {name: np.dtype(kind) for name, kind, _ in new_dims}
    dimensions = header.point_format.dimensions
    taken = {d.name for d in dimensions}
    for i, dim in enumerate(dimensions):
        if dim.is_standard or dim.name not in wanted or (
                dim.num_elements == 1 and dim.scales is None and dim.offsets is None
                and dim.dtype == wanted[dim.name]):
            continue
        new = f"{dim.name}{CLASHING_SUFFIX}"
        while new in taken:
            new += "_"
        dimensions[i] = dim._replace(name=new)
        taken.add(new)


def _register_unregistered_bytes(header: laspy.LasHeader) -> None:
    """Describe extra bytes that have no ExtraBytes descriptor as single uint8 dimensions.

    laspy calls such a block ``ExtraBytes`` and, when it rewrites the ExtraBytes VLR, describes it
    as "undocumented" (data type 0) with the byte count in the options field, which readers then
    misparse as scale/offset bits. One uint8 per byte (``ExtraBytes_0``, ...) keeps every byte and
    is valid LAS 1.4.
    """
    dimensions = header.point_format.dimensions
    for i, dim in enumerate(dimensions):
        if dim.is_standard or dim.description != "Un-registered ExtraBytes":
            continue
        single = [
            laspy.point.dims.DimensionInfo(
                name=f"{dim.name}_{j}",
                kind=laspy.point.dims.DimensionKind.UnsignedInteger,
                num_bits=8,
                num_elements=1,
                is_standard=False,
                description="unregistered byte",
            )
            for j in range(dim.num_elements)
        ]
        dimensions[i : i + 1] = single
        return


Fill = Callable[[int, laspy.ScaleAwarePointRecord, laspy.ScaleAwarePointRecord], None]


class ResultWriter:
    """Write a result file from the input's chunks: original bytes plus ``new_dims``.

    Use as a context manager; the file appears under ``out_path`` only if the block completes
    (temporary name in the same folder, renamed at the end), EVLRs are written after the points.
    Each record is written (and compressed, for LAZ) on a thread of its own while the caller
    prepares the next one; at most one write is in flight, and ``write`` must not be given a
    record that the caller changes afterwards.

    >>> with ResultWriter(src, dst, result_dimensions(["temporal"])) as w:  # doctest: +SKIP
    ...     for chunk in iter_chunks(src):
    ...         out = w.record(chunk)
    ...         out["outlier_flags"] = 0
    ...         w.write(out)
    """

    def __init__(
        self,
        in_path: str | os.PathLike[str],
        out_path: str | os.PathLike[str],
        new_dims: list[tuple[str, type, str]],
        *,
        laz: bool | None = None,
    ) -> None:
        self.in_path, self.out_path = Path(in_path), Path(out_path)
        name = self.in_path.name
        with _laspy_errors(name), laspy.open(self.in_path) as reader:
            in_header = reader.header
        self.points = int(in_header.point_count)
        self.compress = _is_compressed(in_header) if laz is None else laz
        self.header = _output_header(in_header, new_dims)
        check_laz_output(name, self.header.point_format.id, self.compress)
        self._atomic: contextlib.AbstractContextManager[Path] | None = None
        self._writer: laspy.LasWriter | None = None
        self._thread = ThreadPoolExecutor(1, thread_name_prefix="las-writer")
        self._in_flight: Future[None] | None = None

    def __enter__(self) -> ResultWriter:
        self._atomic = atomic_path(self.out_path)
        tmp = self._atomic.__enter__()
        try:
            self._writer = laspy.open(tmp, mode="w", header=self.header,
                                      do_compress=self.compress)
        except BaseException:
            self._atomic.__exit__(*sys.exc_info())
            raise
        return self

    def record(self, chunk: laspy.ScaleAwarePointRecord) -> laspy.ScaleAwarePointRecord:
        """An output record for ``chunk``: every original byte copied, new dimensions zero."""
        out = laspy.ScaleAwarePointRecord.zeros(len(chunk), header=self.header)
        _copy_record_bytes(chunk.array, out.array)
        return out

    def write(self, record: laspy.ScaleAwarePointRecord) -> None:
        """Queue ``record`` after the previous one (waiting for that one: its errors raise here)."""
        assert self._writer is not None, "use ResultWriter as a context manager"
        self._wait()
        self._in_flight = self._thread.submit(self._writer.write_points, record)

    def _wait(self) -> None:
        in_flight, self._in_flight = self._in_flight, None
        if in_flight is not None:
            in_flight.result()

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        assert self._writer is not None and self._atomic is not None
        try:
            self._finish(complete=exc_type is None)
        except BaseException:
            self._atomic.__exit__(*sys.exc_info())
            raise
        self._atomic.__exit__(exc_type, exc, tb)

    def _finish(self, complete: bool) -> None:
        """Wait for the last write, add the EVLRs if the block completed, and close the file in
        every case: a removed file that stays open keeps its space on the disk. A write error
        raises only if the block completed; otherwise the block's own error is the one to
        report."""
        assert self._writer is not None
        try:
            self._wait()
            if complete:
                _write_evlrs(self._writer, self.header)
        except Exception:
            if complete:
                raise
        finally:
            self._thread.shutdown()
            self._writer.close()


def rewrite(
    in_path: str | os.PathLike[str],
    out_path: str | os.PathLike[str],
    new_dims: list[tuple[str, type, str]],
    fill: Fill,
    *,
    laz: bool | None = None,
    chunk_points: int = DEFAULT_CHUNK_POINTS,
    progress: Progress | None = None,
    progress_span: tuple[float, float] = (0.0, 1.0),
    records: list[laspy.ScaleAwarePointRecord] | None = None,
) -> None:
    """Copy ``in_path`` to ``out_path`` chunk by chunk, adding ``new_dims`` filled by ``fill``.

    ``fill(start, chunk_in, chunk_out)`` receives the index of the chunk's first point in the file,
    the input record and the output record (original dimensions already copied) and sets the new
    dimensions (and, if it wants, the classification). ``laz=None`` keeps the input's compression.
    ``records``: the file's point records as ``read_cloud`` kept them (else it is read again).
    """
    lo, hi = progress_span
    with ResultWriter(in_path, out_path, new_dims, laz=laz) as writer:
        n = writer.points
        start = 0
        chunks = iter_chunks(in_path, chunk_points) if records is None else records
        for chunk in chunks:
            out = writer.record(chunk)
            fill(start, chunk, out)
            writer.write(out)
            start += len(chunk)
            if progress is not None:
                message = f"writing {start:,} of {n:,} points"
                progress(lo + (hi - lo) * start / max(n, 1), message)


#: Point formats whose waveform fields lazrs does not round-trip (checked with laspy 2.7/lazrs).
LAZ_LOSSY_FORMATS = frozenset({9, 10})


def check_laz_output(name: str, point_format: int, compress: bool) -> None:
    """Refuse LAZ output where the LAZ backend would silently change the data."""
    if compress and point_format in LAZ_LOSSY_FORMATS:
        raise LasFormatError(
            f"{name}: LAZ output of point format {point_format} is refused because lazrs does not "
            f"keep its waveform fields intact; write LAS instead"
        )


def _write_evlrs(writer: laspy.LasWriter, header: laspy.LasHeader) -> None:
    """laspy reads EVLRs into the header but writes them only when asked (after the points)."""
    if header.evlrs:
        writer.write_evlrs(header.evlrs)


def _copy_record_bytes(src: np.ndarray, dst: np.ndarray) -> None:
    """Copy every original byte of each record; the new dimensions are appended after them."""
    width = src.dtype.itemsize
    # One opaque field over the first ``width`` bytes: numpy copies it record by record with
    # memcpy, about 4x faster than a (n, width) uint8 copy.
    head = np.dtype({"names": ["head"], "formats": [f"V{width}"],
                     "itemsize": dst.dtype.itemsize})
    dst.view(head)["head"] = np.ascontiguousarray(src).view(f"V{width}")


def _is_compressed(header: laspy.LasHeader) -> bool:
    return any(isinstance(v, laspy.vlrs.known.LasZipVlr) for v in header.vlrs) or bool(
        getattr(header, "are_points_compressed", False)
    )


def write_result(
    in_path: str | os.PathLike[str],
    out_path: str | os.PathLike[str],
    *,
    flags: np.ndarray,
    scores: dict[str, np.ndarray],
    classification: np.ndarray | None = None,
    laz: bool | None = None,
    chunk_points: int = DEFAULT_CHUNK_POINTS,
    progress: Progress | None = None,
    progress_span: tuple[float, float] = (0.0, 1.0),
    records: list[laspy.ScaleAwarePointRecord] | None = None,
) -> None:
    """Write the input's points with ``outlier_flags`` (n,) and ``<name>_score`` (n,) float32.

    ``classification`` (n,) replaces the class of every point when given (``classify`` on);
    None leaves the classes untouched. ``records``: as ``rewrite``.
    """
    def fill(start: int, _chunk: Any, out: laspy.ScaleAwarePointRecord) -> None:
        stop = start + len(out)
        out[FLAGS_DIMENSION] = flags[start:stop]
        for det, values in scores.items():
            out[score_dimension(det)] = values[start:stop].astype(np.float32)
        if classification is not None:
            out.classification = classification[start:stop]
        release(flags, *scores.values(), classification)  # maps of a tiled run: a chunk's pages

    rewrite(
        in_path, out_path, result_dimensions(list(scores)), fill, laz=laz,
        chunk_points=chunk_points, progress=progress, progress_span=progress_span, records=records,
    )


def write_filtered(
    result_path: str | os.PathLike[str],
    out_path: str | os.PathLike[str],
    keep: Literal["inliers", "outliers"],
    laz: bool,
    *,
    chunk_points: int = DEFAULT_CHUNK_POINTS,
) -> int:
    """Write the points of a result file whose ``outlier_flags`` are zero (inliers) or not.

    Returns the number of points written. Raises LasFormatError if the file has no
    ``outlier_flags`` dimension.
    """
    if keep not in ("inliers", "outliers"):
        raise ValueError(f"keep must be 'inliers' or 'outliers', got {keep!r}")
    result_path, out_path = Path(result_path), Path(out_path)
    with _laspy_errors(result_path.name), laspy.open(result_path) as reader:
        header = _output_header(reader.header, [])
    if FLAGS_DIMENSION not in header.point_format.extra_dimension_names:
        raise LasFormatError(f"{result_path.name} has no {FLAGS_DIMENSION} dimension")
    written = 0
    check_laz_output(result_path.name, header.point_format.id, laz)
    with atomic_path(out_path) as tmp:
        with laspy.open(tmp, mode="w", header=header, do_compress=laz) as writer:
            for chunk in iter_chunks(result_path, chunk_points):
                flagged = np.asarray(chunk[FLAGS_DIMENSION]) != 0
                mask = flagged if keep == "outliers" else ~flagged
                if mask.any():
                    writer.write_points(chunk[mask])
                    written += int(mask.sum())
            _write_evlrs(writer, header)
    return written


def convert(
    source: str | os.PathLike[str],
    target: str | os.PathLike[str],
    laz: bool,
    *,
    chunk_points: int = DEFAULT_CHUNK_POINTS,
) -> None:
    """Rewrite a LAS file as LAZ or back, every point, VLR, EVLR and extra byte kept.

    Refuses LAZ output of point formats whose waveform fields the LAZ backend would change.
    """
    rewrite(source, target, [], lambda _start, _chunk, _out: None, laz=laz,
            chunk_points=chunk_points)


def write_las_data(las: laspy.LasData, path: str | os.PathLike[str],
                   laz: bool | None = None) -> None:
    """Write a whole in-memory ``LasData`` (the simulator's clouds) atomically.

    ``laz=None`` compresses when ``path`` ends in ``.laz``.
    """
    path = Path(path)
    compress = path.suffix.lower() == ".laz" if laz is None else laz
    check_laz_output(path.name, las.header.point_format.id, compress)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        las.write(fh, do_compress=compress)
