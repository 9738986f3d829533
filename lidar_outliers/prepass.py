"""The leading time-series stages of a tiled run, streamed over the file before the tiles.

A stage whose detector declares ``streams`` (``temporal``) reads each scanner's points in time
order and nothing of their XY neighbourhood: it has no halo, so it cannot run in tiles, but it
can run over the whole file in memory bounded by a few chunks. A tiled run whose pipeline
starts with such stages runs them here first, into arrays on disk in the file's point order
(``outlier_flags`` and each stage's score); the remaining stages then run tile by tile on the
points those stages left (:func:`lidar_outliers.tiling.run_tile` drops the points flagged
here, as :func:`~lidar_outliers.pipeline.run_pipeline` runs later stages on ``flags == 0``) and
the merge starts from these arrays.

The result is the whole cloud's, whatever the order of the file's records:

- order: a file in time order per scanner (the check of :mod:`lidar_outliers.streaming`) is
  read as it is. Any other is sorted on disk first: its points go to files by time span, each
  file sorted in memory (equal times in file order, as the batch detector's stable sort), a
  file too large for that split again by its own time span.
- ``max_gap: auto``: five times each scanner's median positive time step over its whole
  series, found exactly by a radix selection over the steps on disk.
- ``sigma: auto``: the unit-sigma differences of eqs. 15-16 go to disk in the batch's
  (scanner, time) order; sigma comes from the strided sample the batch takes, and the scores
  from the differences as the batch computes them (:mod:`algorithms.temporal.batch`).
"""

from __future__ import annotations

import math
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import laspy
import numpy as np

from algorithms.stats import rounding_sigma
from algorithms.temporal import TemporalParameters, TemporalStream
from algorithms.temporal.batch import (
    SIGMA_SAMPLE_POINTS,
    estimate_sigma,
    finite_points,
    result_info,
    scores_from_differences,
)
from algorithms.temporal.parameters import check_params
from algorithms.temporal.windows import use_compiled
from lidar_outliers import lasio
from lidar_outliers.detectors import StageModel, get_detector
from lidar_outliers.errors import MissingDimensionError
from lidar_outliers.output import FLAGS_DTYPE
from lidar_outliers.pages import filled, release
from lidar_outliers.pipeline import Progress

#: One point of a time series on disk: its index in the file, time, scanner and position.
SERIES_DTYPE = np.dtype([("index", "<i8"), ("t", "<f8"), ("group", "<u2"), ("xyz", "<f8", (3,))])
#: One positive time step on disk: the scanner's rank among the groups and the step's bits.
STEP_DTYPE = np.dtype([("group", "<u4"), ("bits", "<u8")])
#: A time-span file holding more than this many chunks is split again by its own time span.
SPLIT_CHUNKS = 4

Chunks = Callable[[], Iterator[np.ndarray]]


@dataclass
class Streamed:
    """What the leading stages left: file-order arrays on disk and each stage's statistics
    (``info`` and ``critical_value``, as a tile reports them)."""

    flags: np.ndarray
    scores: dict[str, np.ndarray]
    stages: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0


def leading_streamed(stages: list[StageModel]) -> int:
    """How many stages at the start of the pipeline stream along time (declared ``streams``)."""
    count = 0
    for stage in stages:
        if not get_detector(stage.detector).streams:
            break
        count += 1
    return count


def run_streamed(
    in_path: Path, stages: list[StageModel], points: int, folder: Path, *,
    chunk_points: int = lasio.DEFAULT_CHUNK_POINTS, progress: Progress | None = None,
    progress_at: float = 0.1, scales: np.ndarray | None = None,
) -> Streamed:
    """Run ``stages`` (each declared ``streams``) over ``in_path``, one after the other, each
    on the points the stages before it left; their arrays go to ``folder``.

    ``progress(progress_at, message)`` is called for every chunk of every pass (the service
    cancels a job through it). ``scales``: the file's coordinate resolution (the header's),
    below whose rounding no ``sigma: auto`` goes."""
    started = time.perf_counter()
    folder.mkdir(parents=True, exist_ok=True)
    # a new file of zeros ("w+" truncates)
    flags = np.lib.format.open_memmap(folder / "flags.npy", mode="w+", dtype=FLAGS_DTYPE,
                                      shape=(points,))
    out = Streamed(flags, {})
    floor = rounding_sigma(scales)
    for k, stage in enumerate(stages):
        spec = get_detector(stage.detector)
        assert spec.streams and spec.flag_bit is not None
        score = np.lib.format.open_memmap(folder / f"score_{spec.name}.npy", mode="w+",
                                          dtype=np.float32, shape=(points,))
        filled(score, np.nan)
        params = stage.parameters()
        assert isinstance(params, TemporalParameters)
        source = _file_series(in_path, params.group_by, flags if k else None, chunk_points)
        work = folder / f"stage_{k}"
        report = None if progress is None else _reporter(progress, progress_at, spec.name)
        entry = stream_temporal_stage(source, params, points, work, score, flags,
                                      FLAGS_DTYPE(spec.flag_bit), chunk_points, report, floor)
        shutil.rmtree(work, ignore_errors=True)
        out.scores[spec.name] = score
        out.stages.append(entry)
    out.seconds = time.perf_counter() - started
    return out


def _reporter(progress: Progress, at: float, name: str) -> Callable[[str], None]:
    def report(message: str) -> None:
        progress(at, f"{name} along time: {message}")
    return report


def _reported(chunks: Chunks, report: Callable[[str], None] | None, what: str,
              total: int) -> Chunks:
    """``chunks`` reporting how far the pass is after each chunk."""
    if report is None:
        return chunks

    def counted() -> Iterator[np.ndarray]:
        done = 0
        for rec in chunks():
            yield rec
            done += len(rec)
            report(f"{what}, {done:,} of {total:,} points")
    return counted


# --------------------------------------------------------------------------- reading


def _file_series(in_path: Path, group_by: str, flags: np.ndarray | None,
                 chunk_points: int) -> Chunks:
    """The file's points as :data:`SERIES_DTYPE` chunks in file order (those ``flags`` leave)."""
    with lasio._laspy_errors(in_path.name), laspy.open(in_path) as reader:
        header = reader.header
    grid, _ = lasio.grid_origin(header)
    scales = np.asarray(header.scales)
    if "gps_time" not in set(header.point_format.dimension_names):
        raise MissingDimensionError("the temporal detector needs gps_time, which this point "
                                    "format does not have")

    def chunks() -> Iterator[np.ndarray]:
        start = 0
        for chunk in lasio.iter_chunks(in_path, chunk_points):
            stop = start + len(chunk)
            rec = np.empty(stop - start, dtype=SERIES_DTYPE)
            rec["index"] = np.arange(start, stop, dtype=np.int64)
            rec["t"] = chunk.array["gps_time"]
            rec["group"] = 0 if group_by == "none" else chunk.array["point_source_id"]
            lasio.local_xyz(chunk, grid, scales, out=rec["xyz"])
            start = stop
            yield rec if flags is None else rec[flags[rec["index"]] == 0]
            release(flags)

    return chunks


def _valid(rec: np.ndarray) -> np.ndarray:
    """Points the detector uses: finite time and position (the others score NaN)."""
    return finite_points(rec["xyz"], rec["t"])


@dataclass
class Survey:
    """One pass over the points: how many, per scanner, whether in time order, time span."""

    points: int = 0
    groups: dict[int, int] = field(default_factory=dict)  # scanner -> valid points
    ordered: bool = True
    t_range: tuple[float, float] = (math.inf, -math.inf)

    @property
    def valid(self) -> int:
        return sum(self.groups.values())


def survey(chunks: Chunks) -> Survey:
    out = Survey()
    last: dict[int, float] = {}
    lo, hi = math.inf, -math.inf
    for rec in chunks():
        out.points += len(rec)
        rec = rec[_valid(rec)]
        if not len(rec):
            continue
        g, n = np.unique(rec["group"], return_counts=True)
        for gid, count in zip(g.tolist(), n.tolist(), strict=True):
            out.groups[gid] = out.groups.get(gid, 0) + count
        if out.ordered and not _in_time_order(rec["t"], rec["group"], last):
            out.ordered = False
        lo, hi = min(lo, float(rec["t"].min())), max(hi, float(rec["t"].max()))
    out.t_range = (lo, hi)
    return out


def time_ordered(chunks: Chunks, facts: Survey, folder: Path, chunk_points: int) -> Chunks:
    """The valid points in time order per scanner (equal times in file order): the file as it
    is when it is in that order already, else sorted on disk under ``folder``."""
    if facts.ordered:
        def as_read() -> Iterator[np.ndarray]:
            for rec in chunks():
                yield rec[_valid(rec)]
        return as_read
    folder.mkdir(parents=True, exist_ok=True)
    spans = max(1, math.ceil(facts.valid / chunk_points))
    _split(chunks(), folder, facts.t_range, spans)

    def sorted_chunks() -> Iterator[np.ndarray]:
        yield from _sorted_spans(folder, chunk_points)
    return sorted_chunks


def _split(parts: Iterator[np.ndarray], folder: Path, t_range: tuple[float, float],
           spans: int) -> None:
    """Append the valid points of ``parts`` to one file per time span, in the order given."""
    lo, hi = t_range
    width = (hi - lo) / spans if hi > lo else 0.0
    for rec in parts:
        rec = rec[_valid(rec)]
        if width > 0:
            which = np.clip(((rec["t"] - lo) / width).astype(np.int64), 0, spans - 1)
        else:
            which = np.zeros(len(rec), dtype=np.int64)
        order = np.argsort(which, kind="stable")
        which, rec = which[order], rec[order]
        cuts = np.flatnonzero(np.r_[True, which[1:] != which[:-1]]) if len(rec) else []
        for a, b in zip(cuts, [*cuts[1:], len(rec)], strict=True):
            with open(folder / f"span_{int(which[a]):08d}.bin", "ab") as fh:
                rec[a:b].tofile(fh)


def _sorted_spans(folder: Path, chunk_points: int) -> Iterator[np.ndarray]:
    """The span files of ``folder`` in time order, each sorted by time (stable: ties keep
    the file order), in pieces of ``chunk_points``; a span too large is split again."""
    for path in sorted(folder.glob("span_*.bin")):
        rec = np.fromfile(path, dtype=SERIES_DTYPE)
        t = rec["t"]
        if len(rec) > SPLIT_CHUNKS * chunk_points and t.min() < t.max():
            sub = folder / path.stem
            sub.mkdir()
            spans = math.ceil(len(rec) / chunk_points)
            _split(iter([rec]), sub, (float(t.min()), float(t.max())), spans)
            del rec, t
            yield from _sorted_spans(sub, chunk_points)
            shutil.rmtree(sub, ignore_errors=True)
            continue
        rec = rec[np.argsort(t, kind="stable")]
        for a in range(0, len(rec), chunk_points):
            yield rec[a:a + chunk_points]


# --------------------------------------------------------------------------- temporal


def stream_temporal_stage(
    source: Chunks, params: TemporalParameters, points: int, folder: Path, score: np.ndarray,
    flags: np.ndarray, bit: np.unsignedinteger, chunk_points: int,
    report: Callable[[str], None] | None = None, sigma_floor: np.ndarray | float = 0.0,
) -> dict[str, Any]:
    """``temporal`` over the points of ``source``: scores into ``score`` and ``bit`` into
    ``flags`` (file order); returns the stage's ``info`` and ``critical_value`` as
    ``detect_temporal`` gives them on those points (``sigma_floor`` as it takes it).
    ``report(message)`` after every chunk."""
    p = check_params(params.n1, params.n2, params.sigma, params.alpha, params.max_gap)
    facts = survey(_reported(source, report, "reading", points))
    if facts.points == 0:  # the stages before flagged every point: the stage is skipped
        return {"info": None, "critical_value": None}
    if not facts.valid:
        raise MissingDimensionError("gps_time is all NaN: the temporal detector cannot run")
    folder.mkdir(parents=True, exist_ok=True)
    sorting = source if facts.ordered else _reported(source, report, "sorting by time", points)
    ordered = time_ordered(sorting, facts, folder / "spans", chunk_points)
    groups = sorted(facts.groups)
    if p.max_gap is None:
        gaps = resolved_gaps(_reported(ordered, report, "time steps", facts.valid), groups,
                             folder / "steps.bin", chunk_points)
    else:
        gaps = {g: p.max_gap for g in groups}
    diffs, index, segments = unit_differences(
        _reported(ordered, report, "smoothing", facts.valid), params, facts, gaps, folder,
        p.n1, p.n2)
    if p.sigma is None:
        sigma, source_name = sample_sigma(diffs, chunk_points, sigma_floor)
    else:
        sigma, source_name = p.sigma, "given"
    tested = flagged = 0
    for a in range(0, len(index), chunk_points):
        d = np.asarray(diffs[a:a + chunk_points])
        s = scores_from_differences(d[:, :3], d[:, 3], sigma)
        where = np.asarray(index[a:a + chunk_points])
        score[where] = s
        hit = s > p.critical_value
        flags[where[hit]] |= bit
        tested += int(np.count_nonzero(~np.isnan(s)))
        flagged += int(np.count_nonzero(hit))
        release(diffs, index, score, flags)
    del diffs, index
    gap_by_group = {g: (v if math.isfinite(v) else None) for g, v in gaps.items()}
    info = result_info(p, sigma, source_name, gap_by_group)
    info.update(points=facts.points, points_tested=tested, points_flagged=flagged, **segments)
    return {"info": info, "critical_value": p.critical_value}


def resolved_gaps(ordered: Chunks, groups: list[int], path: Path,
                  chunk_points: int) -> dict[int, float]:
    """Each scanner's max_gap for ``auto``: 5 x the median positive step of its whole series
    (inf where it has none), as :func:`algorithms.temporal.batch.prepare` resolves it."""
    last: dict[int, float] = {}
    counts = np.zeros(len(groups), dtype=np.int64)
    with open(path, "wb") as fh:
        for rec in ordered():
            rank = np.searchsorted(np.asarray(groups), rec["group"])
            order = np.argsort(rank, kind="stable")
            rank, t = rank[order], rec["t"][order]
            cuts = np.flatnonzero(np.r_[True, rank[1:] != rank[:-1]]) if len(t) else []
            for a, b in zip(cuts, [*cuts[1:], len(t)], strict=True):
                g = int(rank[a])
                series = t[a:b] if g not in last else np.r_[last[g], t[a:b]]
                last[g] = float(t[b - 1])
                step = np.diff(series)
                step = step[step > 0]
                steps = np.empty(step.size, dtype=STEP_DTYPE)
                steps["group"], steps["bits"] = g, step.view(np.uint64)
                steps.tofile(fh)
                counts[g] += step.size
    median = middle_values(path, counts, chunk_points)
    gaps = {}
    for g, gid in enumerate(groups):
        value = 5.0 * median[g]
        gaps[gid] = float(value) if math.isfinite(value) else math.inf
    path.unlink()
    return gaps


def middle_values(path: Path, counts: np.ndarray, chunk_points: int) -> np.ndarray:
    """(groups,) the median of each group's positive steps in ``path`` (NaN where it has
    none), as ``median_positive_step``: the mean of its two middle values.

    Positive float64 values order as their bit patterns do, so each middle value is found
    byte by byte from the top: eight passes over the file, memory 256 counts a group.
    """
    size = len(counts)
    data = np.memmap(path, dtype=STEP_DTYPE, mode="r") if counts.sum() else None
    want = [(counts - 1) // 2, counts // 2]
    prefix = [np.zeros(size, np.uint64), np.zeros(size, np.uint64)]
    for shift in range(56, -8, -8):
        hist = [np.zeros(size * 256, np.int64), np.zeros(size * 256, np.int64)]
        for a in range(0, 0 if data is None else len(data), chunk_points):
            part = data[a:a + chunk_points]
            g, bits = part["group"].astype(np.int64), np.asarray(part["bits"])
            digit = ((bits >> np.uint64(shift)) & np.uint64(255)).astype(np.int64)
            for k in range(2):
                sel = (slice(None) if shift == 56
                       else (bits >> np.uint64(shift + 8)) == prefix[k][g])
                hist[k] += np.bincount(g[sel] * 256 + digit[sel], minlength=size * 256)
            release(data)
        for k in range(2):
            cum = np.cumsum(hist[k].reshape(size, 256), axis=1)
            digit = np.argmax(cum > want[k][:, None], axis=1)
            below = np.where(digit > 0, cum[np.arange(size), np.maximum(digit - 1, 0)], 0)
            want[k] = want[k] - below
            prefix[k] = (prefix[k] << np.uint64(8)) | digit.astype(np.uint64)
    del data
    lo, hi = prefix[0].view(np.float64), prefix[1].view(np.float64)
    out = np.full(size, np.nan)
    has = counts > 0
    out[has] = (lo[has] + hi[has]) / 2.0
    return out


def unit_differences(
    ordered: Chunks, params: TemporalParameters, facts: Survey, gaps: dict[int, float],
    folder: Path, n1: int, n2: int,
) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Each valid point's unit-sigma differences (dz per axis, sqrt(eq. 16)) on disk, row r
    for the r-th point in (scanner, time) order (the batch's order), the file index of each
    row, and the segment counts."""
    groups = sorted(facts.groups)
    first = np.cumsum([0, *(facts.groups[g] for g in groups)])[:-1]
    seen = np.zeros(len(groups), dtype=np.int64)
    diffs = np.lib.format.open_memmap(folder / "differences.npy", mode="w+", dtype=np.float64,
                                      shape=(facts.valid, 4))
    index = np.lib.format.open_memmap(folder / "index.npy", mode="w+", dtype=np.int64,
                                      shape=(facts.valid,))
    stream = TemporalStream(n1=n1, n2=n2, sigma=1.0, alpha=params.alpha,
                            max_gap=params.max_gap, max_gap_by_group=gaps, differences=True,
                            compiled=use_compiled(facts.valid))
    grouped = params.group_by != "none"
    for rec in ordered():
        rank = np.searchsorted(np.asarray(groups), rec["group"])
        row = first[rank] + seen[rank] + _count_before(rank)
        seen += np.bincount(rank, minlength=len(groups))
        index[row] = rec["index"]
        done, d = stream.push(rec["xyz"], rec["t"], rec["group"] if grouped else None, row)
        diffs[done] = d
        release(diffs, index)
    done, d = stream.finish()
    diffs[done] = d
    info = stream.info
    return diffs, index, {"segments": int(info["segments"]),
                          "segments_untested": int(info["segments_untested"])}


def _count_before(rank: np.ndarray) -> np.ndarray:
    """(n,) how many earlier entries of ``rank`` hold the same value."""
    order = np.argsort(rank, kind="stable")
    sorted_rank = rank[order]
    starts = np.flatnonzero(np.r_[True, sorted_rank[1:] != sorted_rank[:-1]]) if rank.size else (
        np.zeros(0, np.int64))
    run_start = np.repeat(starts, np.diff(np.r_[starts, rank.size]))
    out = np.empty(rank.size, dtype=np.int64)
    out[order] = np.arange(rank.size) - run_start
    return out


def sample_sigma(diffs: np.ndarray, chunk_points: int,
                 floor: np.ndarray | float = 0.0) -> tuple[np.ndarray, str]:
    """Sigma per axis as ``estimate_sigma`` makes it from all the rows: from the same evenly
    strided sample of the tested rows, gathered chunk by chunk."""
    tested = 0
    for a in range(0, len(diffs), chunk_points):
        tested += int(np.count_nonzero(~np.isnan(diffs[a:a + chunk_points, 3])))
        release(diffs)
    stride = -(-tested // SIGMA_SAMPLE_POINTS) if tested > SIGMA_SAMPLE_POINTS else 1
    parts, seen = [], 0
    for a in range(0, len(diffs), chunk_points):
        d = np.asarray(diffs[a:a + chunk_points])
        rows = np.flatnonzero(~np.isnan(d[:, 3]))
        take = rows[(seen + np.arange(rows.size)) % stride == 0]
        seen += rows.size
        parts.append(d[take])
        release(diffs)
    sample = np.concatenate(parts) if parts else np.zeros((0, 4))
    return estimate_sigma(sample[:, :3], sample[:, 3], floor)


def _in_time_order(t: np.ndarray, group: np.ndarray | None, last: dict[int, float]) -> bool:
    """Whether finite times never decrease within a group, across chunks too (updates ``last``)."""
    finite = np.isfinite(t)
    tt = t[finite]
    if tt.size == 0:
        return True
    if group is None:
        gs, ts = np.zeros(tt.size, np.uint8), tt
    else:
        g = group[finite]  # uint16 point_source_id: numpy's stable sort is a radix sort here
        order = np.argsort(g, kind="stable")
        gs, ts = g[order], tt[order]
    same = gs[1:] == gs[:-1]
    if np.any(ts[1:][same] < ts[:-1][same]):
        return False
    firsts = np.flatnonzero(np.r_[True, ~same])
    lasts = np.r_[firsts[1:] - 1, gs.size - 1]
    for f, l in zip(firsts, lasts, strict=True):
        gid = int(gs[f])
        if gid in last and ts[f] < last[gid]:
            return False
        last[gid] = float(ts[l])
    return True
