"""Run a pipeline of detectors over a cloud in memory, and gather the statistics.

A pipeline is an ordered list of stages (:class:`lidar_outliers.params.PipelineParams`). Each
stage sees only the points that earlier stages did not flag (the paper's Table 5 runs (a) and
then (b) on what (a) left); ``ground`` classifies the points not flagged as noise. The result
holds the ``outlier_flags`` bitmask, one float32 score per outlier detector (NaN where the
detector did not test the point), the new classification (``classify`` on) and a JSON-ready
statistics dict. :mod:`lidar_outliers.process` runs it from file to file.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pydantic import BaseModel

from algorithms.columns import column_max, column_min
from algorithms.result import DetectorResult
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors import GroundResult, StageModel, get_detector
from lidar_outliers.errors import ParameterError
from lidar_outliers.lasio import LasFacts
from lidar_outliers.output import FLAGS_DTYPE
from lidar_outliers.params import FLAG_BITS, PipelineParams

Progress = Callable[[float, str], None]

#: Point formats 0-5 store the class in 5 bits.
LEGACY_MAX_CLASS = 31
GROUND_CLASS, OTHER_CLASS = 2, 1


@dataclass
class PipelineResult:
    """Outcome of a pipeline on n points.

    flags : (n,) uint16 ``outlier_flags`` bitmask (:data:`~lidar_outliers.params.FLAG_BITS`).
    scores : name -> (n,) float32, per outlier detector that ran; NaN where untested.
    classification : (n,) uint8 with ``classify`` on, else None (classes left untouched).
    statistics : JSON-serialisable dict (see :func:`run_pipeline`).
    """

    flags: np.ndarray
    scores: dict[str, np.ndarray]
    classification: np.ndarray | None
    statistics: dict[str, Any] = field(default_factory=dict)


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
    evidence: Mapping[str, Any] | None = None,
) -> tuple[list, dict]:
    """The stages to run and a statistics note on where they came from.

    Without a named pipeline the profile decides: ``params.profile``, or for ``auto``
    :func:`~lidar_outliers.profiles.choose_profile` on ``evidence`` (the file's
    :func:`~lidar_outliers.profiles.profile_evidence`), else on the evidence of the header
    ``facts`` alone (weak: the airborne pipeline, said so). The note then holds ``profile``,
    ``profile_source`` (given / auto), ``profile_reason``, ``profile_confidence`` and the
    evidence used (``profile_facts``, and ``profile_basis`` in a few words).
    """
    from lidar_outliers.profiles import choose_profile, profile_evidence, profile_stages

    if params.pipeline is not None:
        stages = list(params.pipeline)
        note: dict[str, Any] = {"pipeline_source": "given"}
    else:
        ok, why = usable_gps_time(gps_time)
        if evidence is None:
            evidence = profile_evidence(facts or {})
        if params.profile == "auto":
            choice = choose_profile(evidence)
            profile, source = choice.profile, "auto"
            reason, confidence, basis = choice.reason, choice.confidence, choice.basis
        else:
            profile, source, reason = params.profile, "given", "named by the job"
            confidence = basis = None
        stages = profile_stages(profile, ok)
        names = " then ".join(s.detector for s in stages)
        note = {
            "pipeline_source": "default",
            "profile": profile,
            "profile_source": source,
            "profile_reason": reason,
            "profile_confidence": confidence,
            "profile_basis": basis,
            "profile_facts": dict(evidence),
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
    evidence: Mapping[str, Any] | None = None,
    progress_span: tuple[float, float] = (0.0, 1.0),
) -> PipelineResult:
    """Run the stages of ``params`` on ``cloud``.

    ``facts``: the file's header facts (``LasFacts`` or its dict); without them the cloud's own
    (:func:`cloud_facts`). ``evidence``: the file's profile evidence
    (:func:`~lidar_outliers.profiles.profile_evidence` of its header and a sample of its
    points), used to choose the profile of a job that names no pipeline; without it, the
    evidence of ``facts`` and of a sample of the cloud's own points.

    Statistics: ``input`` (file facts when given), ``pipeline_source`` (for a default pipeline
    also ``profile``, ``profile_source``, ``profile_reason``, ``profile_confidence``,
    ``profile_facts`` and ``default_reason``),
    ``stages`` (per stage: detector, params as resolved, the detector's ``info`` with sigma
    estimates, points_in, points_tested, points_flagged, critical_value, seconds and, with
    ``reference_classes``, ``confusion`` in the layout of the paper's Tables 2-5 or
    ``ground_scores`` for ``ground``), and ``overall`` (points, flagged, per-bit counts, confusion).
    """
    n = len(cloud)
    fact_dict = facts.to_dict() if isinstance(facts, LasFacts) else facts
    if evidence is None and params.pipeline is None and params.profile == "auto":
        from lidar_outliers.profiles import profile_evidence, sample_cloud

        evidence = profile_evidence(fact_dict or cloud_facts(cloud), sample_cloud(cloud))
    stages, note = resolve_stages(params, cloud.gps_time, fact_dict or cloud_facts(cloud),
                                  evidence)
    flags = np.zeros(n, dtype=FLAGS_DTYPE)
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
        entry = stage_entry(stage, int(index.size))
        if index.size == 0:
            entry.update(points_tested=0, points_flagged=0, skipped="no points left to test")
            stage_stats.append(entry)
            continue
        sub = cloud if index.size == n else cloud.subset(index)
        result = spec.run(sub, stage.parameters())
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
            entry.update(_outlier_stage(result, spec.flag_bit, index, flags, scores[spec.name]))
            if noise_truth is not None:
                from algorithms.metrics import outlier_confusion

                entry["confusion"] = outlier_confusion(noise_truth[index], result.flagged)
        entry["seconds"] = round(time.perf_counter() - started, 4)
        stage_stats.append(entry)
    if progress is not None:
        progress(hi, "detection done")
    if classes is not None:
        classes[flags != 0] = params.noise_class
    statistics = pipeline_statistics(
        params, fact_dict if fact_dict is not None else {"points": n}, note, stage_stats,
        _overall(flags, noise_truth))
    return PipelineResult(flags, scores, classes, statistics)


def stage_entry(stage: StageModel, points_in: int) -> dict[str, Any]:
    """The start of a stage's statistics: detector, parameters as resolved, points it got."""
    return {"detector": stage.detector, "params": stage.model_dump(mode="json"),
            "points_in": points_in}


def pipeline_statistics(
    params: PipelineParams, input_facts: Mapping[str, Any], note: Mapping[str, Any],
    stages: list[dict[str, Any]], overall: dict[str, Any],
) -> dict[str, Any]:
    """The statistics document of a run (JSON-ready), whichever way the points were read."""
    return jsonable({
        "input": dict(input_facts),
        **note,
        "classify": params.classify,
        "noise_class": params.noise_class,
        "reference_classes": params.reference_classes,
        "stages": stages,
        "overall": overall,
    })


def overall_statistics(
    points: int, points_flagged: int, flagged_by_bit: Mapping[str, int],
    confusion: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The ``overall`` part: points, points flagged, flags per detector (every registered bit)
    and, with reference classes, the confusion counts of all stages together."""
    out: dict[str, Any] = {
        "points": points,
        "points_flagged": points_flagged,
        "flagged_by_bit": {name: int(flagged_by_bit.get(name, 0)) for name in FLAG_BITS},
    }
    if confusion is not None:
        out["confusion"] = confusion
    return out


def noise_reference(reference: list[int] | None) -> list[int]:
    """The reference classes that mark noise (all but ground's class 2)."""
    return [c for c in reference or [] if c != GROUND_CLASS]


def cloud_facts(cloud: Cloud) -> dict[str, Any]:
    """Profile facts of an in-memory cloud: points, file-coordinate bounds, has_gps_time.

    A cloud does not know the file's extra dimensions, so ``auto`` never picks ``spinning``
    from these alone (pass the file's facts, or name the profile).
    """
    n = len(cloud)
    if n:
        lo = (column_min(cloud.xyz) + cloud.origin).tolist()
        hi = (column_max(cloud.xyz) + cloud.origin).tolist()
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
        flags[flagged] |= FLAGS_DTYPE(bit or 0)
    else:
        score_out[index] = result.score
        flags[index[flagged]] |= FLAGS_DTYPE(bit or 0)
    return {
        "info": result.info,
        "points_tested": int(np.count_nonzero(result.tested)),
        "points_flagged": int(np.count_nonzero(flagged)),
        "critical_value": _critical_summary(result.critical_value),
    }


def _critical_summary(critical: float | np.ndarray) -> float | None:
    """One number for the statistics: the critical value, or the median of per-point critical
    values (``section`` compares each fit with t(n - 9) of its own n)."""
    values = np.asarray(critical, dtype=np.float64)
    if values.ndim == 0:
        return float(values)
    finite = values[np.isfinite(values)]
    return float(np.median(finite)) if finite.size else None


def _reference_truth(
    cloud: Cloud, reference: list[int] | None
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Noise truth (the reference classes other than 2) and ground truth (class 2, if named)."""
    if not reference:
        return None, None
    noise_classes = noise_reference(reference)
    noise = np.isin(cloud.classification, noise_classes) if noise_classes else None
    ground = cloud.classification == GROUND_CLASS if GROUND_CLASS in reference else None
    return noise, ground


def _overall(flags: np.ndarray, noise_truth: np.ndarray | None) -> dict[str, Any]:
    from algorithms.metrics import outlier_confusion

    flagged = flags != 0
    by_bit = {name: int(np.count_nonzero(flags & bit)) for name, bit in FLAG_BITS.items()}
    confusion = None if noise_truth is None else outlier_confusion(noise_truth, flagged)
    return overall_statistics(int(flags.size), int(np.count_nonzero(flagged)), by_bit, confusion)


def jsonable(value: Any) -> Any:
    """Plain JSON types: numpy scalars to Python, NaN/inf to None, tuples to lists."""
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    return value


