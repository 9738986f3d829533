"""Run a pipeline of detectors over a cloud or a LAS/LAZ file, and gather the statistics.

A pipeline is an ordered list of stages (``worker.params.PipelineParams``). Each stage sees only
the points that earlier stages did not flag (the paper's Table 5 runs (a) and then (b) on what
(a) left); ``ground`` classifies the points not flagged as noise. The result holds the
``outlier_flags`` bitmask, one float32 score per outlier detector (NaN where the detector did not
test the point), the new classification (``classify`` on) and a JSON-ready statistics dict.

:func:`process_file` is the whole file-to-file run used by ``lidar-outliers detect`` and the
Celery worker: validate the header, read, run, write atomically, optionally write the statistics.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import laspy
import numpy as np
from pydantic import BaseModel, ValidationError

from algorithms.result import DetectorResult
from worker import lasio
from worker.detectors import GroundResult, get_detector
from worker.errors import ParameterError
from worker.lasio import Cloud, LasFacts
from worker.params import OUTLIER_DETECTOR_BITS, PipelineParams

Progress = Callable[[float, str], None]

#: Point formats 0-5 store the class in 5 bits.
LEGACY_MAX_CLASS = 31
GROUND_CLASS, OTHER_CLASS = 2, 1
#: A temporal-only pipeline streams above this many points (in memory: ~40 bytes a point).
STREAM_MIN_POINTS = 5_000_000
#: Share of the progress bar given to reading, detecting and writing in :func:`process_file`.
_READ, _DETECT = 0.25, 0.75


@dataclass
class PipelineResult:
    """Outcome of a pipeline on n points.

    flags : (n,) uint8, ``outlier_flags`` bitmask (``worker.params.OUTLIER_DETECTOR_BITS``).
    scores : name -> (n,) float32, per outlier detector that ran; NaN where untested.
    classification : (n,) uint8 with ``classify`` on, else None (classes left untouched).
    statistics : JSON-serialisable dict (see :func:`run_pipeline`).
    """

    flags: np.ndarray
    scores: dict[str, np.ndarray]
    classification: np.ndarray | None
    statistics: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------- parameters


def validation_message(exc: ValidationError, *, option_style: bool = False) -> str:
    """One line naming the offending field(s) of a pydantic error.

    ``pipeline.0.temporal.n1`` becomes ``pipeline[0].n1`` (or ``--n1`` with ``option_style``).
    """
    parts: list[str] = []
    seen: set[tuple[str, ...]] = set()
    for err in exc.errors():
        loc = [str(x) for x in err.get("loc", ())]
        # A union reports one error per member, tagged with the member type: keep the field,
        # once.
        while loc and (loc[-1] in _TYPE_TAGS or "[" in loc[-1]):
            loc.pop()
        if tuple(loc) in seen:
            continue
        seen.add(tuple(loc))
        # The discriminated union inserts the detector name after the index: drop it.
        cleaned: list[str] = []
        for i, item in enumerate(loc):
            if i > 0 and loc[i - 1].isdigit() and item in _stage_names():
                continue
            cleaned.append(f"[{item}]" if item.isdigit() else item)
        name = ".".join(cleaned).replace(".[", "[") or "parameters"
        if option_style and cleaned:
            name = "--" + cleaned[-1].replace("_", "-")
        msg = err.get("msg", "invalid value")
        msg = msg.removeprefix("Value error, ")
        if err.get("type") == "extra_forbidden":
            msg = "unknown parameter"
        elif err.get("type") == "union_tag_not_found":
            msg = f"each stage needs a \"detector\" key (one of: {', '.join(_stage_names())})"
        elif err.get("type") == "union_tag_invalid":
            tag = (err.get("ctx") or {}).get("tag", err.get("input"))
            msg = f"unknown detector {tag!r} (known: {', '.join(_stage_names())})"
        elif "input" in err and err.get("type") not in ("missing",):
            given = err["input"]
            if not isinstance(given, dict | list):
                msg = f"{msg} (got {given!r})"
        parts.append(f"{name}: {msg}")
    return "; ".join(parts)


_TYPE_TAGS = {"float", "int", "str", "bool", "list", "dict", "none"}


def _stage_names() -> list[str]:
    from worker.detectors import DETECTORS

    return list(DETECTORS)


def parse_pipeline_params(data: Any) -> PipelineParams:
    """Validate a pipeline document (dict or JSON text); ParameterError with one line otherwise."""
    if isinstance(data, str | bytes):
        try:
            data = json.loads(data)
        except json.JSONDecodeError as exc:
            raise ParameterError(f"parameters are not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ParameterError("parameters must be a JSON object")
    try:
        return PipelineParams.model_validate(data)
    except ValidationError as exc:
        raise ParameterError(validation_message(exc)) from None


def usable_gps_time(gps_time: np.ndarray | None) -> tuple[bool, str]:
    """Whether the temporal detector can work on these times, and why not."""
    if gps_time is None:
        return False, "the point format has no gps_time"
    finite = gps_time[np.isfinite(gps_time)]
    if gps_time.size and finite.size == 0:
        return False, "gps_time is NaN in every point"
    if finite.size >= 2 and finite.min() == finite.max():
        return False, f"gps_time is the same ({finite[0]!r}) in every point"
    return True, "the file has gps_time"


def resolve_stages(
    params: PipelineParams, gps_time: np.ndarray | None,
    facts: Mapping[str, Any] | None = None,
) -> tuple[list, dict]:
    """The stages to run and a statistics note on where they came from.

    Without a named pipeline the profile decides (``params.profile``, or for ``auto``
    :func:`worker.profiles.choose_profile` on ``facts``: the file's header facts, or those of
    the cloud; without facts ``auto`` means mobile). The note then holds ``profile``,
    ``profile_source`` (given / auto), ``profile_reason`` and the facts used.
    """
    from worker.profiles import profile_evidence, profile_stages

    if params.pipeline is not None:
        stages = list(params.pipeline)
        note: dict[str, Any] = {"pipeline_source": "given"}
    else:
        ok, why = usable_gps_time(gps_time)
        evidence = profile_evidence(facts or {})
        if params.profile == "auto":
            profile, source = evidence["profile"], "auto"
            reason = evidence["reason"] if facts else "no file facts given: mobile"
        else:
            profile, source, reason = params.profile, "given", "named by the job"
        stages = profile_stages(profile, ok)
        names = " then ".join(s.detector for s in stages)
        note = {
            "pipeline_source": "default",
            "profile": profile,
            "profile_source": source,
            "profile_reason": reason,
            "profile_facts": {k: v for k, v in evidence.items() if k not in ("profile", "reason")},
            "default_reason": f"{profile} profile, {why}: {names}",
        }
    seen: set[str] = set()
    for stage in stages:
        spec = get_detector(stage.detector)
        if spec.kind == "outlier" and stage.detector in seen:
            raise ParameterError(
                f"detector {stage.detector} appears twice in the pipeline; each outlier detector "
                f"runs at most once (it has one score dimension)"
            )
        seen.add(stage.detector)
    return stages, note


def check_noise_class(params: PipelineParams, point_format: int) -> None:
    """Point formats 0-5 hold classes 0-31 only."""
    if params.classify and point_format <= 5 and params.noise_class > LEGACY_MAX_CLASS:
        raise ParameterError(
            f"noise_class {params.noise_class} does not fit point format {point_format} "
            f"(classes 0-{LEGACY_MAX_CLASS}); use e.g. 7"
        )


# --------------------------------------------------------------------------- running


def run_pipeline(
    cloud: Cloud,
    params: PipelineParams,
    progress: Progress | None = None,
    *,
    facts: LasFacts | Mapping[str, Any] | None = None,
    progress_span: tuple[float, float] = (0.0, 1.0),
) -> PipelineResult:
    """Run the stages of ``params`` on ``cloud``.

    ``facts``: the file's header facts (``LasFacts`` or its dict), used to choose the profile
    of a job that names no pipeline; without them the cloud's own (:func:`cloud_facts`).

    Statistics: ``input`` (file facts when given), ``pipeline_source`` (for a default pipeline
    also ``profile``, ``profile_source``, ``profile_reason``, ``profile_facts`` and
    ``default_reason``),
    ``stages`` (per stage: detector, params as resolved, the detector's ``info`` with sigma
    estimates, points_in, points_tested, points_flagged, critical_value, seconds and, with
    ``reference_classes``, ``confusion`` in the layout of the paper's Tables 2-5 or
    ``ground_scores`` for ``ground``), and ``overall`` (points, flagged, per-bit counts, confusion).
    """
    n = len(cloud)
    fact_dict = facts.to_dict() if isinstance(facts, LasFacts) else facts
    stages, note = resolve_stages(params, cloud.gps_time, fact_dict or cloud_facts(cloud))
    flags = np.zeros(n, dtype=np.uint8)
    scores: dict[str, np.ndarray] = {}
    classes = cloud.classification.astype(np.uint8, copy=True) if params.classify else None
    noise_truth, ground_truth = _reference_truth(cloud, params.reference_classes)
    lo, hi = progress_span
    step = (hi - lo) / max(len(stages), 1)
    stage_stats = []
    for i, stage in enumerate(stages):
        spec = get_detector(stage.detector)
        if progress is not None:
            progress(lo + i * step, f"stage {i + 1}/{len(stages)}: {spec.name}")
        index = np.flatnonzero(flags == 0)
        if spec.kind == "outlier":
            scores[spec.name] = np.full(n, np.nan, dtype=np.float32)
        started = time.perf_counter()
        entry: dict[str, Any] = {
            "detector": spec.name,
            "params": stage.model_dump(mode="json"),
            "points_in": int(index.size),
        }
        if index.size == 0:
            entry.update(points_tested=0, points_flagged=0, skipped="no points left to test")
            stage_stats.append(entry)
            continue
        sub = cloud if index.size == n else cloud.subset(index)
        result = spec.run(sub, stage)
        if isinstance(result, GroundResult):
            is_ground = result.is_ground
            if classes is not None:
                classes[index] = np.where(is_ground, GROUND_CLASS, OTHER_CLASS)
            entry.update(
                info=result.info,
                points_tested=int(index.size),
                points_flagged=0,
                points_ground=int(np.count_nonzero(is_ground)),
                points_other=int(index.size - np.count_nonzero(is_ground)),
            )
            if ground_truth is not None:
                from algorithms.metrics import ground_scores

                entry["ground_scores"] = ground_scores(ground_truth[index], is_ground)
        else:
            entry.update(_outlier_stage(result, spec.bit, index, flags, scores[spec.name]))
            if noise_truth is not None:
                from algorithms.metrics import outlier_confusion

                entry["confusion"] = outlier_confusion(noise_truth[index], result.flagged)
        entry["seconds"] = round(time.perf_counter() - started, 4)
        stage_stats.append(entry)
    if progress is not None:
        progress(hi, "detection done")
    if classes is not None:
        classes[flags != 0] = params.noise_class
    statistics: dict[str, Any] = {
        "input": fact_dict if fact_dict is not None else {"points": n},
        **note,
        "classify": params.classify,
        "noise_class": params.noise_class,
        "reference_classes": params.reference_classes,
        "stages": stage_stats,
        "overall": _overall(flags, noise_truth),
    }
    return PipelineResult(flags, scores, classes, _jsonable(statistics))


def cloud_facts(cloud: Cloud) -> dict[str, Any]:
    """Profile facts of an in-memory cloud: points, file-coordinate bounds, has_gps_time.

    A cloud does not know the file's extra dimensions, so ``auto`` never picks ``spinning``
    from these alone (pass the file's facts, or name the profile).
    """
    n = len(cloud)
    if n:
        lo = (cloud.xyz.min(axis=0) + cloud.origin).tolist()
        hi = (cloud.xyz.max(axis=0) + cloud.origin).tolist()
        bounds: dict[str, list[float]] | None = {"min": lo, "max": hi}
    else:
        bounds = None
    return {"points": n, "bounds": bounds, "extra_dimensions": [],
            "has_gps_time": cloud.gps_time is not None}


def _outlier_stage(
    result: DetectorResult, bit: int | None, index: np.ndarray, flags: np.ndarray,
    score_out: np.ndarray,
) -> dict[str, Any]:
    flagged = np.asarray(result.flagged, dtype=bool)
    if index.size == flags.size:  # every point tested (index is 0..n-1): no gathers
        score_out[:] = result.score
        flags[flagged] |= np.uint8(bit or 0)
    else:
        score_out[index] = result.score
        flags[index[flagged]] |= np.uint8(bit or 0)
    return {
        "info": result.info,
        "points_tested": int(np.count_nonzero(result.tested)),
        "points_flagged": int(np.count_nonzero(flagged)),
        "critical_value": result.critical_value,
    }


def _reference_truth(
    cloud: Cloud, reference: list[int] | None
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Noise truth (the reference classes other than 2) and ground truth (class 2, if named)."""
    if not reference:
        return None, None
    noise_classes = [c for c in reference if c != GROUND_CLASS]
    noise = np.isin(cloud.classification, noise_classes) if noise_classes else None
    ground = cloud.classification == GROUND_CLASS if GROUND_CLASS in reference else None
    return noise, ground


def _overall(flags: np.ndarray, noise_truth: np.ndarray | None) -> dict[str, Any]:
    flagged = flags != 0
    out: dict[str, Any] = {
        "points": int(flags.size),
        "points_flagged": int(np.count_nonzero(flagged)),
        "flagged_by_bit": {
            name: int(np.count_nonzero(flags & bit)) for name, bit in OUTLIER_DETECTOR_BITS.items()
        },
    }
    if noise_truth is not None:
        from algorithms.metrics import outlier_confusion

        out["confusion"] = outlier_confusion(noise_truth, flagged)
    return out


def _jsonable(value: Any) -> Any:
    """Plain JSON types: numpy scalars to Python, NaN/inf to None, tuples to lists."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    return value


# --------------------------------------------------------------------------- file to file


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
) -> dict[str, Any]:
    """Validate, read, run the pipeline, write the flagged cloud; return the statistics.

    ``trajectory``: an optional trajectory file (``worker.trajectory``: lines of ``time x y z``
    in the cloud's coordinates) or its (m, 4) array; the ``transient`` detector then also flags
    points other beams saw through. The statistics' ``trajectory`` says whether it was used.

    ``laz=None`` writes LAZ when the input is LAZ. ``progress(fraction, message)`` is called while
    reading, per stage and while writing; whatever it raises propagates unchanged (the service
    cancels jobs that way) and no output file is left behind. ``stats_path`` also receives the
    statistics as JSON (written atomically). A temporal-only pipeline on a file in time order
    per scanner runs in one streaming pass when the file holds more than
    ``STREAM_MIN_POINTS`` points (``streaming=None``), always (``True``) or never (``False``);
    below that size the in-memory path is faster and its memory is bounded by the threshold.
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
    traj, traj_info = _load_trajectory(trajectory)
    compress = facts.compressed if laz is None else laz
    if laz is None and facts.point_format in lasio.LAZ_LOSSY_FORMATS:
        compress = False  # lazrs would change the waveform fields; keep the data, write LAS
    streaming_note = None
    if streaming is None:
        streaming = facts.points > STREAM_MIN_POINTS
    if streaming and _temporal_only(params) and facts.has_gps_time and facts.points > 0:
        stats, streaming_note = _stream_temporal(
            in_path, out_path, params, facts, compress, progress, chunk_points
        )
        if stats is not None:
            stats["seconds"] = {"total": round(time.perf_counter() - t0, 4)}
            return _finish(stats, out_path, compress, stats_path, progress, traj_info)
    # Up to STREAM_MIN_POINTS the point records stay in memory for the writer (one read and,
    # for LAZ, one decompression instead of two); larger files are read again.
    records: list[Any] | None = [] if facts.points <= STREAM_MIN_POINTS else None
    cloud = lasio.read_cloud(
        in_path, chunk_points=chunk_points, progress=progress, progress_span=(0.0, _READ),
        records=records,
    )
    if traj is not None:
        cloud = cloud.with_trajectory(traj)
    t_read = time.perf_counter()
    result = run_pipeline(
        cloud, params, progress, facts=facts, progress_span=(_READ, _DETECT)
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
    stats["seconds"] = {
        "read": round(t_read - t0, 4),
        "detect": round(t_detect - t_read, 4),
        "write": round(t_write - t_detect, 4),
        "total": round(t_write - t0, 4),
    }
    return _finish(stats, out_path, compress, stats_path, progress, traj_info)


def _load_trajectory(
    trajectory: str | os.PathLike[str] | np.ndarray | None,
) -> tuple[np.ndarray | None, dict[str, Any] | None]:
    """(m, 4) trajectory in file coordinates and its facts, or (None, None)."""
    from worker.trajectory import check_trajectory, describe_trajectory, read_trajectory

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


def _finish(
    stats: dict[str, Any], out_path: Path, compress: bool,
    stats_path: str | os.PathLike[str] | None, progress: Progress | None,
    traj_info: dict[str, Any] | None = None,
) -> dict[str, Any]:
    if traj_info is not None:
        stats["trajectory"] = _jsonable(_trajectory_use(stats, traj_info))
    detectors = [s["detector"] for s in stats["stages"] if s["detector"] in OUTLIER_DETECTOR_BITS]
    stats["output"] = {
        "name": out_path.name,
        "compressed": compress,
        "dimensions_added": [name for name, _, _ in lasio.result_dimensions(detectors)],
    }
    if stats_path is not None:
        write_json_atomic(stats_path, stats)
    if progress is not None:
        progress(1.0, "done")
    return stats


# --------------------------------------------------------------------------- streaming temporal


class _NotTimeOrdered(Exception):
    """Raised inside the streaming run to fall back to the in-memory path."""


def _temporal_only(params: PipelineParams) -> bool:
    return params.pipeline is not None and [s.detector for s in params.pipeline] == ["temporal"]


def _stream_temporal(
    in_path: Path, out_path: Path, params: PipelineParams, facts: LasFacts, compress: bool,
    progress: Progress | None, chunk_points: int,
) -> tuple[dict[str, Any] | None, str]:
    """Run a temporal-only pipeline in one streaming pass (memory bounded by a few chunks).

    Needs the points in time order within each scanner group; at the first point that breaks
    it, the partial output is discarded and ``(None, reason)`` returned so that the caller runs
    the in-memory path. Otherwise returns the statistics.
    """
    try:
        from algorithms.temporal import TemporalStream
    except ImportError:
        return None, "algorithms.temporal.TemporalStream is not available"
    stage = params.pipeline[0]
    spec = get_detector("temporal")
    stream = TemporalStream(n1=stage.n1, n2=stage.n2, sigma=stage.sigma, alpha=stage.alpha,
                            max_gap=stage.max_gap)
    critical = stream.critical_value
    bit = np.uint8(spec.bit)
    counts = _StreamCounts()
    started = time.perf_counter()
    pending: list[_Pending] = []
    last_time: dict[int, float] = {}
    with lasio._laspy_errors(in_path.name), laspy.open(in_path) as reader:
        grid, _ = lasio.grid_origin(reader.header)
        scales = np.asarray(reader.header.scales)
    n = facts.points
    try:
        with lasio.ResultWriter(in_path, out_path, lasio.result_dimensions(["temporal"]),
                                laz=compress) as writer:
            start = 0
            for chunk in lasio.iter_chunks(in_path, chunk_points):
                stop = start + len(chunk)
                t = np.asarray(chunk.array["gps_time"], dtype=np.float64)
                group = (None if stage.group_by == "none"
                         else np.asarray(chunk.array["point_source_id"]))
                if not _in_time_order(t, group, last_time):
                    raise _NotTimeOrdered
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
    except _NotTimeOrdered:
        return None, "points are not in time order per scanner: read into memory instead"
    entry = {
        "detector": "temporal",
        "params": stage.model_dump(mode="json"),
        "points_in": n,
        "info": stream.info,
        "points_tested": counts.tested,
        "points_flagged": counts.flagged,
        "critical_value": critical,
        "seconds": round(time.perf_counter() - started, 4),
    }
    noise_ref = [c for c in params.reference_classes or [] if c != GROUND_CLASS]
    overall: dict[str, Any] = {
        "points": n,
        "points_flagged": counts.flagged,
        "flagged_by_bit": {name: counts.flagged if name == "temporal" else 0
                           for name in OUTLIER_DETECTOR_BITS},
    }
    if noise_ref:
        confusion = counts.confusion()
        entry["confusion"] = overall["confusion"] = confusion
    stats = {
        "input": facts.to_dict(),
        "pipeline_source": "given",
        "mode": "streaming",
        "classify": params.classify,
        "noise_class": params.noise_class,
        "reference_classes": params.reference_classes,
        "stages": [entry],
        "overall": overall,
    }
    return _jsonable(stats), "streamed in one pass"


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
        from algorithms.metrics import outlier_confusion

        # Rebuild boolean arrays of the right counts: the metric needs only the four counts.
        tp, fp = self.identified, self.flagged - self.identified
        fn, tn = self.outliers - tp, self.points - self.outliers - fp
        truth = np.repeat([True, False, True, False], [tp, fp, fn, tn])
        flagged = np.repeat([True, True, False, False], [tp, fp, fn, tn])
        return outlier_confusion(truth, flagged)


def _assign(pending: list[_Pending], index: np.ndarray, score: np.ndarray) -> None:
    if index.size == 0:
        return
    starts = np.array([p.start for p in pending])
    which = np.searchsorted(starts, index, side="right") - 1
    for k in np.unique(which):
        sel = which == k
        p = pending[int(k)]
        p.score[index[sel] - p.start] = score[sel]
        p.done += int(np.count_nonzero(sel))


def _flush(
    pending: list[_Pending], writer: lasio.ResultWriter, params: PipelineParams, critical: float,
    bit: np.uint8, counts: _StreamCounts, *, final: bool,
) -> None:
    """Write the leading chunks whose points all have their final score."""
    noise_ref = [c for c in params.reference_classes or [] if c != GROUND_CLASS]
    while pending and (pending[0].done == len(pending[0].record) or final):
        p = pending.pop(0)
        flagged = p.score > critical
        record = p.record
        record[lasio.FLAGS_DIMENSION] = np.where(flagged, bit, np.uint8(0))
        record[lasio.score_dimension("temporal")] = p.score
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


def write_json_atomic(path: str | os.PathLike[str], data: Any) -> None:
    """Write JSON to a temporary name beside ``path`` and rename it into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.part")
    try:
        tmp.write_text(json.dumps(data, indent=2) + "\n")
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
