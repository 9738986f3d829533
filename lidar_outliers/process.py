"""The whole file-to-file run of ``lidar-outliers detect`` and of a job: validate the header, read,
run the pipeline, write the flagged cloud atomically, optionally write the statistics.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from lidar_outliers import lasio
from lidar_outliers.atomic import write_json_atomic
from lidar_outliers.errors import ParameterError
from lidar_outliers.output import result_dimensions
from lidar_outliers.params import FLAG_BITS, PipelineParams, parse_pipeline_params
from lidar_outliers.pipeline import Progress, check_noise_class, jsonable, run_pipeline
from lidar_outliers.streaming import stream_temporal, temporal_only
from lidar_outliers.tiling import WHOLE_CLOUD_POINTS, auto_tile_size, process_tiled
from lidar_outliers.trajectory import check_trajectory, describe_trajectory, read_trajectory

#: Files up to this many points keep their point records in memory for the writer.
KEEP_RECORDS_POINTS = 5_000_000
#: Share of the progress bar given to reading, detecting and writing in :func:`process_file`.
_READ, _DETECT = 0.25, 0.75


def process_file(
    in_path: str | os.PathLike[str],
    out_path: str | os.PathLike[str],
    params: PipelineParams | dict[str, Any] | None = None,
    *,
    laz: bool | None = None,
    progress: Progress | None = None,
    stats_path: str | os.PathLike[str] | None = None,
    chunk_points: int = lasio.DEFAULT_CHUNK_POINTS,
    streaming: bool | None = None,
    trajectory: str | os.PathLike[str] | np.ndarray | None = None,
    tile_size: float | None = None,
) -> dict[str, Any]:
    """Validate, read, run the pipeline, write the flagged cloud; return the statistics.

    ``trajectory``: an optional trajectory file (:mod:`~lidar_outliers.trajectory`: lines of
    ``time x y z`` in the cloud's coordinates) or its (m, 4) array; the ``transient`` detector
    then also flags points other beams saw through. The statistics' ``trajectory`` says whether
    it was used.

    ``laz=None`` writes LAZ when the input is LAZ. ``progress(fraction, message)`` is called while
    reading, per stage and while writing; whatever it raises propagates unchanged (the service
    cancels jobs that way) and no output file is left behind. ``stats_path`` also receives the
    statistics as JSON (written atomically). A temporal-only pipeline on a file in time order
    per scanner runs in one streaming pass when the file holds more than ``WHOLE_CLOUD_POINTS``
    points (``streaming=None``; beyond it the other pipelines run in tiles, which a
    temporal-only pipeline does not need: streamed, 4 M points took 2.4 s against 5.3 s in
    tiles), always (``True``) or never (``False``); below that size the in-memory path is
    faster and its memory is bounded by the threshold.

    ``tile_size`` (metres) runs the pipeline tile by tile (:mod:`lidar_outliers.tiling`: the
    same result, memory set by the tile); None tiles files of more than
    ``WHOLE_CLOUD_POINTS`` points with a tile size chosen from their density. Leading stages
    along the time series (``temporal``) are streamed over the file first
    (:mod:`lidar_outliers.prepass`). A pipeline with a stage that depends on the whole cloud
    runs in memory, and the statistics' ``tiling`` says why.
    """
    t0 = time.perf_counter()
    if params is None:
        params = PipelineParams()
    elif not isinstance(params, PipelineParams):
        params = parse_pipeline_params(params)
    in_path, out_path = Path(in_path), Path(out_path)
    if out_path.resolve() == in_path.resolve():
        raise ParameterError("the output file must differ from the input file")
    if progress is not None:
        progress(0.0, f"checking {in_path.name}")
    facts = lasio.inspect_las(in_path)
    check_noise_class(params, facts.point_format)
    evidence = None
    if params.pipeline is None and params.profile == "auto":
        # The profile is chosen once per file, from a bounded sample of its points.
        from lidar_outliers.profiles import file_evidence

        if progress is not None:
            progress(0.0, f"sampling {in_path.name} for its sensor profile")
        evidence = file_evidence(in_path, facts.to_dict())
    traj, traj_info = _load_trajectory(trajectory)
    compress = facts.compressed if laz is None else laz
    if laz is None and facts.point_format in lasio.LAZ_LOSSY_FORMATS:
        compress = False  # lazrs would change the waveform fields; keep the data, write LAS
    streaming_note = None
    if streaming is None:
        streaming = facts.points > WHOLE_CLOUD_POINTS
    if streaming and temporal_only(params) and facts.has_gps_time and facts.points > 0:
        stats, streaming_note = stream_temporal(
            in_path, out_path, params, facts, compress, progress, chunk_points
        )
        if stats is not None:
            stats["seconds"] = {"total": round(time.perf_counter() - t0, 4)}
            return finish_statistics(stats, out_path, compress, stats_path, progress, traj_info)
    tiling_note = None
    if tile_size is not None and not tile_size > 0:
        raise ParameterError(f"tile_size must be > 0 metres, got {tile_size}")
    if (tile_size is not None or facts.points > WHOLE_CLOUD_POINTS) and facts.points > 0:
        size = tile_size if tile_size is not None else auto_tile_size(facts)
        tiled = process_tiled(in_path, out_path, params, facts, evidence, tile_size=size,
                              compress=compress, progress=progress, chunk_points=chunk_points,
                              trajectory=traj)
        if isinstance(tiled, dict):
            return finish_statistics(tiled, out_path, compress, stats_path, progress, traj_info)
        tiling_note = f"whole cloud in memory: {tiled}"
    # Up to KEEP_RECORDS_POINTS the point records stay in memory for the writer (one read and,
    # for LAZ, one decompression instead of two); larger files are read again.
    records: list[Any] | None = [] if facts.points <= KEEP_RECORDS_POINTS else None
    cloud = lasio.read_cloud(
        in_path, chunk_points=chunk_points, progress=progress, progress_span=(0.0, _READ),
        records=records,
    )
    if traj is not None:
        cloud = cloud.with_trajectory(traj)
    t_read = time.perf_counter()
    result = run_pipeline(
        cloud, params, progress, facts=facts, evidence=evidence, progress_span=(_READ, _DETECT)
    )
    del cloud
    t_detect = time.perf_counter()
    lasio.write_result(
        in_path, out_path, flags=result.flags, scores=result.scores,
        classification=result.classification, laz=compress, chunk_points=chunk_points,
        progress=progress, progress_span=(_DETECT, 1.0), records=records,
    )
    del records
    t_write = time.perf_counter()
    stats = result.statistics
    stats["mode"] = "in memory"
    if streaming_note:
        stats["streaming"] = streaming_note
    if tiling_note:
        stats["tiling"] = tiling_note
    stats["seconds"] = {
        "read": round(t_read - t0, 4),
        "detect": round(t_detect - t_read, 4),
        "write": round(t_write - t_detect, 4),
        "total": round(t_write - t0, 4),
    }
    return finish_statistics(stats, out_path, compress, stats_path, progress, traj_info)


def _load_trajectory(
    trajectory: str | os.PathLike[str] | np.ndarray | None,
) -> tuple[np.ndarray | None, dict[str, Any] | None]:
    """(m, 4) trajectory in file coordinates and its facts, or (None, None)."""

    if trajectory is None:
        return None, None
    if isinstance(trajectory, np.ndarray):
        traj = check_trajectory(trajectory, "array")
        return traj, describe_trajectory(traj, "array")
    traj = read_trajectory(trajectory)
    return traj, describe_trajectory(traj, Path(trajectory).name)


def _trajectory_use(stats: dict[str, Any], info: dict[str, Any]) -> dict[str, Any]:
    """The trajectory's facts plus whether a stage used it."""
    info = dict(info)
    used = [s for s in stats.get("stages", []) if s["detector"] == "transient" and "info" in s]
    if used:
        info["used_by"] = "transient"
    else:
        info["used_by"] = None
        info["note"] = "no transient stage ran (it needs gps_time): the trajectory was not used"
    return info


def finish_statistics(
    stats: dict[str, Any], out_path: Path, compress: bool,
    stats_path: str | os.PathLike[str] | None, progress: Progress | None,
    traj_info: dict[str, Any] | None = None,
) -> dict[str, Any]:
    if traj_info is not None:
        stats["trajectory"] = jsonable(_trajectory_use(stats, traj_info))
    detectors = [s["detector"] for s in stats["stages"] if s["detector"] in FLAG_BITS]
    stats["output"] = {
        "name": out_path.name,
        "compressed": compress,
        "dimensions_added": [name for name, _, _ in result_dimensions(detectors)],
    }
    if stats_path is not None:
        write_json_atomic(stats_path, stats)
    if progress is not None:
        progress(1.0, "done")
    return stats


