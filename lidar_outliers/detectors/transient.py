"""``transient``: clusters seen at one moment only and attached to nothing (moving objects,
:mod:`algorithms.transient`); with a trajectory also points that other beams saw through
(free-space evidence, :mod:`algorithms.free_space`), ORed into one flag."""

from __future__ import annotations

from typing import Any

import numpy as np

from algorithms.result import DetectorResult
from algorithms.transient import TransientParameters
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors.base import Detector
from lidar_outliers.errors import ParameterError


def run(cloud: Cloud, params: TransientParameters) -> DetectorResult:
    """Transient clusters, and with a trajectory free-space evidence.

    Score: the cluster detector's (0 persistent, 1 single-epoch, 2 transient), raised to 2 where
    a beam saw through the point; critical value 1.5 either way.
    """
    from algorithms.transient import detect_transient

    gps_time = cloud.require_gps_time("transient")
    result = detect_transient(
        cloud.xyz, gps_time, cloud.point_source_id, k=params.k, radius=params.radius,
        min_dt=params.min_dt)
    if cloud.trajectory is None:
        result.info["free_space"] = "no trajectory file given"
        return result
    seen_through, fs_info = _free_space(cloud, gps_time, params, result.score == 0.0)
    clusters = np.asarray(result.flagged, dtype=bool)
    flagged = clusters | seen_through
    score = np.where(seen_through, np.maximum(result.score, 2.0), result.score)
    info = dict(result.info)
    info.update(
        points_flagged_by_clusters=int(clusters.sum()),
        points_flagged_by_free_space=int(seen_through.sum()),
        points_flagged=int(flagged.sum()),
        free_space=fs_info,
    )
    return DetectorResult(score=score, flagged=flagged, critical_value=result.critical_value,
                          info=info)


def _free_space(
    cloud: Cloud, gps_time: np.ndarray, params: TransientParameters, persistent: np.ndarray
) -> tuple[np.ndarray, dict[str, Any]]:
    """(n,) bool seen-through points and the info, on the points the trajectory's time covers;
    ``persistent``: the points the cluster test found recorded again at another moment (they
    win a conflict with a beam, :func:`algorithms.free_space.detect_free_space`)."""
    from algorithms.free_space import detect_free_space, scanner_origins, vehicle_pose

    traj = cloud.trajectory
    assert traj is not None
    t0, t1 = float(traj[0, 0]), float(traj[-1, 0])
    covered = np.isfinite(gps_time) & (gps_time >= t0) & (gps_time <= t1)
    n_cov = int(covered.sum())
    if n_cov == 0:
        finite = gps_time[np.isfinite(gps_time)]
        span = f"{float(finite.min())!r}..{float(finite.max())!r}" if finite.size else "none finite"
        raise ParameterError(f"the trajectory's times {t0!r}..{t1!r} do not overlap the points' "
                             f"gps_time ({span}); both must use the same time base")
    index = np.flatnonzero(covered)
    source = cloud.point_source_id[index]
    position, heading = vehicle_pose(gps_time[index], traj)
    arms, arm_info = _lever_arms(cloud.xyz[index], gps_time[index], source, position, heading,
                                 params.lever_arms)
    origin = scanner_origins(gps_time[index], source, traj, arms)
    placed = np.isin(source, list(arms))
    fs = detect_free_space(cloud.xyz[index], origin, radius=params.free_space_radius,
                           margin=params.free_space_margin, min_rays=params.free_space_min_rays,
                           seen_again=persistent[index], beams=placed)
    seen = np.zeros(len(cloud), dtype=bool)
    seen[index] = fs.flagged
    info = {"radius": params.free_space_radius, "margin": params.free_space_margin,
            "min_rays": params.free_space_min_rays, "points_covered": n_cov,
            "points_uncovered": int(len(cloud) - n_cov),
            "lever_arms": arm_info,
            "points_without_lever_arm": int((~placed).sum()),
            "beams_counted": fs.info["beams_counted"],
            "beams_with_grazing_margin": fs.info["beams_with_grazing_margin"],
            "beam_margin_median": fs.info["beam_margin_median"],
            "points_flagged": int(fs.flagged.sum())}
    return seen, info


def _lever_arms(
    xyz: np.ndarray, gps_time: np.ndarray, source: np.ndarray, position: np.ndarray,
    heading: np.ndarray, given: tuple[tuple[int, float, float, float], ...],
) -> tuple[dict[int, tuple[float, float, float]], dict[str, Any]]:
    """The lever arm of every scanner that can be placed: as given, else fitted to its own
    points (:mod:`algorithms.lever_arms`); and per scanner how (for the statistics)."""
    from algorithms.lever_arms import fit_lever_arm

    arms = {int(a[0]): (float(a[1]), float(a[2]), float(a[3])) for a in given}
    info: dict[str, Any] = {}
    for sid in np.unique(source).tolist():
        if sid in arms:
            info[str(sid)] = {"source": "given", "arm": list(arms[sid])}
            continue
        m = source == sid
        fit = fit_lever_arm(xyz[m], gps_time[m], position[m], heading[m])
        if fit.arm is not None:
            arms[sid] = fit.arm
            info[str(sid)] = {"source": "estimated", "arm": list(fit.arm),
                              **fit.info}
        else:
            info[str(sid)] = {"source": "none", **fit.info}
    return arms, info


DETECTOR = Detector(
    name="transient",
    parameters=TransientParameters,
    run=run,
    summary=("Clusters seen at one moment only, attached to nothing, where their place was seen "
             "again (moving objects)."),
    flag_bit=128,
    needs=("gps_time",),
    # whether a floating cluster's place was seen again depends on the returns its scanner
    # fired just before and after it, which may lie anywhere: not run in tiles
    whole_cloud=("a cluster is compared with the returns its scanner fired just before and "
                 "after it (its scan-line neighbours), which may lie anywhere in the cloud"),
    uses_trajectory=True,
)
