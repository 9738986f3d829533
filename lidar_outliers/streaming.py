"""A temporal-only pipeline in one streaming pass over a file in time order per scanner.

Memory is bounded by a few chunks, whatever the file's size: points are read chunk by chunk,
scored by :class:`algorithms.temporal.TemporalStream` and written as soon as every point of a
chunk has its final score.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import laspy
import numpy as np

from algorithms.errors import NotTimeOrderedError
from algorithms.stats import rounding_sigma
from algorithms.temporal import TemporalStream
from algorithms.temporal.windows import use_compiled
from lidar_outliers import lasio
from lidar_outliers.detectors import get_detector
from lidar_outliers.lasio import LasFacts
from lidar_outliers.output import FLAGS_DIMENSION, FLAGS_DTYPE, result_dimensions, score_dimension
from lidar_outliers.params import PipelineParams
from lidar_outliers.pipeline import (
    Progress,
    noise_reference,
    overall_statistics,
    pipeline_statistics,
    stage_entry,
)


def temporal_only(params: PipelineParams) -> bool:
    return params.pipeline is not None and [s.detector for s in params.pipeline] == ["temporal"]


def stream_temporal(
    in_path: Path, out_path: Path, params: PipelineParams, facts: LasFacts, compress: bool,
    progress: Progress | None, chunk_points: int,
) -> tuple[dict[str, Any] | None, str]:
    """Run a temporal-only pipeline in one streaming pass (memory bounded by a few chunks).

    Needs the points in time order within each scanner group; at the first point that breaks
    it, the partial output is discarded and ``(None, reason)`` returned so that the caller runs
    the in-memory path. Otherwise returns the statistics.
    """
    stage = params.pipeline[0]
    spec = get_detector("temporal")
    stream = TemporalStream(n1=stage.n1, n2=stage.n2, sigma=stage.sigma, alpha=stage.alpha,
                            max_gap=stage.max_gap, sigma_floor=rounding_sigma(facts.scales),
                            compiled=use_compiled(facts.points))
    critical = stream.critical_value
    bit = FLAGS_DTYPE(spec.flag_bit)
    counts = _StreamCounts()
    started = time.perf_counter()
    pending: list[_Pending] = []
    with lasio._laspy_errors(in_path.name), laspy.open(in_path) as reader:
        grid, _ = lasio.grid_origin(reader.header)
        scales = np.asarray(reader.header.scales)
    n = facts.points
    try:
        with lasio.ResultWriter(in_path, out_path, result_dimensions(["temporal"]),
                                laz=compress) as writer:
            start = 0
            for chunk in lasio.iter_chunks(in_path, chunk_points):
                stop = start + len(chunk)
                t = np.asarray(chunk.array["gps_time"], dtype=np.float64)
                group = (None if stage.group_by == "none"
                         else np.asarray(chunk.array["point_source_id"]))
                pending.append(_Pending(start, writer.record(chunk)))
                done = stream.push(lasio.local_xyz(chunk, grid, scales), t, group,
                                   np.arange(start, stop, dtype=np.int64))
                _assign(pending, *done)
                _flush(pending, writer, params, critical, bit, counts, final=False)
                start = stop
                if progress is not None:
                    progress(0.95 * stop / n, f"temporal (streaming): {stop:,} of {n:,} points")
            _assign(pending, *stream.finish())
            _flush(pending, writer, params, critical, bit, counts, final=True)
    except NotTimeOrderedError:  # the stream checks the order of every group as it goes
        return None, "points are not in time order per scanner: read into memory instead"
    entry = stage_entry(stage, n)
    entry.update(info=stream.info, points_tested=counts.tested, points_flagged=counts.flagged,
                 critical_value=critical, seconds=round(time.perf_counter() - started, 4))
    confusion = counts.confusion() if noise_reference(params.reference_classes) else None
    if confusion is not None:
        entry["confusion"] = confusion
    overall = overall_statistics(n, counts.flagged, {"temporal": counts.flagged}, confusion)
    stats = pipeline_statistics(params, facts.to_dict(), {"pipeline_source": "given"}, [entry],
                                overall)
    stats["mode"] = "streaming"
    return stats, "streamed in one pass"


@dataclass
class _Pending:
    """An output chunk waiting for the scores of all its points."""

    start: int
    record: Any
    score: np.ndarray = field(init=False)
    done: int = 0

    def __post_init__(self) -> None:
        self.score = np.full(len(self.record), np.nan, dtype=np.float32)

    @property
    def stop(self) -> int:
        return self.start + len(self.record)


@dataclass
class _StreamCounts:
    points: int = 0
    tested: int = 0
    flagged: int = 0
    outliers: int = 0
    identified: int = 0

    def confusion(self) -> dict[str, Any]:
        from algorithms.metrics import confusion_from_counts

        return confusion_from_counts(points=self.points, outliers=self.outliers,
                                     identified=self.identified,
                                     false_alarms=self.flagged - self.identified)


def _assign(pending: list[_Pending], index: np.ndarray, score: np.ndarray) -> None:
    """Give the pending chunks the final scores of their points (``index``: file positions)."""
    if index.size == 0:
        return
    for p in pending:  # a few chunks, each a contiguous range of positions
        sel = (index >= p.start) & (index < p.stop)
        if sel.any():
            p.score[index[sel] - p.start] = score[sel]
            p.done += int(np.count_nonzero(sel))


def _flush(
    pending: list[_Pending], writer: lasio.ResultWriter, params: PipelineParams, critical: float,
    bit: np.unsignedinteger, counts: _StreamCounts, *, final: bool,
) -> None:
    """Write the leading chunks whose points all have their final score."""
    noise_ref = noise_reference(params.reference_classes)
    while pending and (pending[0].done == len(pending[0].record) or final):
        p = pending.pop(0)
        flagged = p.score > critical
        record = p.record
        record[FLAGS_DIMENSION] = np.where(flagged, bit, FLAGS_DTYPE(0))
        record[score_dimension("temporal")] = p.score
        classes = np.asarray(record.classification)
        if noise_ref:
            truth = np.isin(classes, noise_ref)
            counts.outliers += int(np.count_nonzero(truth))
            counts.identified += int(np.count_nonzero(truth & flagged))
        if params.classify:
            record.classification = np.where(flagged, params.noise_class, classes).astype(np.uint8)
        counts.points += len(record)
        counts.tested += int(np.count_nonzero(~np.isnan(p.score)))
        counts.flagged += int(np.count_nonzero(flagged))
        writer.write(record)


