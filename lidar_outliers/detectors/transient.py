"""``transient``: clusters seen at one moment only and attached to nothing (moving objects,
:mod:`algorithms.transient`); with a trajectory also points that other beams saw through
(free-space evidence, :mod:`algorithms.free_space`), ORed into one flag.

Without a trajectory it runs tile by tile: a pre-pass over tiles (halo ``2 * radius``) finds
each point's persistence and what the cluster decisions read around it
(:func:`~algorithms.transient.point_facts`), one pass over the whole file the scan-line
neighbours and the clusters of the single-epoch points with their decisions
(:func:`combine_clusters`) and, with ``stop_free_space``, what each scanner's beams saw through
where it stood still (:func:`combine_stops`), and the tiles read each point's score (no halo).
With a trajectory the beams cross the whole cloud, so it runs whole.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from algorithms.result import DetectorResult
from algorithms.transient import ScanLineSide, TransientParameters
from lidar_outliers.cloud import Cloud
from lidar_outliers.detectors.base import Detector, Prepass
from lidar_outliers.errors import LidarOutliersError, ParameterError
from lidar_outliers.pages import filled, gathered, release, scattered

#: Points per step of the passes over the whole file.
STREAM_POINTS = 4_000_000
#: What the pass over the whole file finds per point: persistent, its scan-line neighbours
#: before and after (file index, -1 none) and whether they are persistent, and its score (0
#: persistent, 1 single-epoch, 2 flagged), which is what a tile reads.
KNOWN_DTYPE = np.dtype([("persistent", "?"), ("before", "<i8"), ("after", "<i8"),
                        ("before_persistent", "?"), ("after_persistent", "?"), ("score", "u1")])


def run(cloud: Cloud, params: TransientParameters) -> DetectorResult:
    """Transient clusters, and with a trajectory free-space evidence.

    Score: the cluster detector's (0 persistent, 1 single-epoch, 2 transient), raised to 2 where
    a beam saw through the point; critical value 1.5 either way.
    """
    from algorithms.transient import detect_transient

    gps_time = cloud.require_gps_time("transient")
    known = None if cloud.known is None else cloud.known.get("transient")
    if known is not None and cloud.trajectory is None:
        return _run_given(cloud, known, params)
    timed = np.isfinite(gps_time)
    if not timed.all():
        return _without_untimed(cloud, timed, params)
    # cloud.xyz is in the file's local frame: a tiled run computes on the same numbers
    result = detect_transient(
        cloud.xyz, gps_time, cloud.point_source_id, k=params.k, radius=params.radius,
        min_dt=params.min_dt, max_extent=params.max_extent, centre=False)
    clusters = np.asarray(result.flagged, dtype=bool)
    info = dict(result.info)
    seen_through = np.zeros(len(cloud), dtype=bool)
    if cloud.trajectory is None:
        info["free_space"] = "no trajectory file given"
    else:
        seen_through, info["free_space"] = _free_space(cloud, gps_time, params,
                                                       result.score == 0.0)
        info["points_flagged_by_free_space"] = int(seen_through.sum())
    if params.stop_free_space:
        from algorithms.standstill import stop_flags

        at_stops, info["stops"] = stop_flags(gps_time, cloud.point_source_id, cloud.xyz)
        seen_through |= at_stops
    flagged = clusters | seen_through
    score = np.where(seen_through, np.maximum(result.score, 2.0), result.score)
    info.update(points_flagged_by_clusters=int(clusters.sum()),
                points_flagged=int(flagged.sum()))
    return DetectorResult(score=score, flagged=flagged, critical_value=result.critical_value,
                          info=info)


def _without_untimed(cloud: Cloud, timed: np.ndarray, params: TransientParameters
                     ) -> DetectorResult:
    """The points whose gps_time is NaN or infinite cannot be placed on a scan line or in an
    epoch: they are left untested (score NaN) and the others run without them."""
    inner = run(cloud.subset(np.flatnonzero(timed)), params)
    score = np.full(len(cloud), np.nan)
    score[timed] = inner.score
    flagged = np.zeros(len(cloud), dtype=bool)
    flagged[timed] = inner.flagged
    info = {**inner.info, "points_without_time": int(np.count_nonzero(~timed))}
    return DetectorResult(score=score, flagged=flagged, critical_value=inner.critical_value,
                          info=info)


def _run_given(cloud: Cloud, known: np.ndarray, params: TransientParameters) -> DetectorResult:
    """A tile's run: each point's score from the pass over the whole file."""
    score = np.asarray(known["score"], dtype=np.float64)
    flagged = score == 2.0
    info = {"k": params.k, "radius": params.radius, "min_dt": params.min_dt,
            "max_extent": params.max_extent, "points": len(score),
            "points_tested": len(score), "points_flagged": int(flagged.sum()),
            "free_space": "no trajectory file given"}
    return DetectorResult(score=score, flagged=flagged, critical_value=1.5, info=info)


def persistent_values(cloud: Cloud, params: TransientParameters) -> dict[str, np.ndarray]:
    """Step 1 and what steps 3-4 read around each point of a tile's region
    (:func:`~algorithms.transient.point_facts`), exact for the points with every point within
    ``2 * radius`` at hand."""
    from algorithms.transient import point_facts

    gps_time = cloud.require_gps_time("transient")
    if not np.all(np.isfinite(gps_time)):
        raise LidarOutliersError(
            f"transient: {int(np.count_nonzero(~np.isfinite(gps_time)))} points of this tile "
            "have a gps_time that is NaN or infinite, which a run in tiles cannot place on the "
            "file's scan lines (a file run whole leaves them untested); give those points a "
            "time or remove them")
    return point_facts(cloud.xyz, gps_time, k=params.k, radius=params.radius,
                       min_dt=params.min_dt)


def combine_scan_lines(params: TransientParameters, columns: dict[str, np.ndarray],
                       out: np.ndarray) -> dict[str, Any]:
    """Each point's scan-line neighbours among the points that reached the stage, and whether
    they are persistent, over the whole file.

    A file whose returns come in time order per scanner (as recorded) takes one pass of a few
    million points at a time (:func:`~algorithms.transient.stream_scan_lines`); any other is
    sorted by (point_source_id, gps_time) in memory: about 60 bytes a point that reached the
    stage (times, scanners, the sort's order and the neighbours), 6 GB for 100 M points. The
    columns and ``out`` stay on disk.
    """
    from algorithms.transient import scan_line_neighbours, stream_scan_lines

    use, persistent = columns["in_stage"], columns["persistent"]
    before, after = out["before"], out["after"]

    def chunk_done() -> None:
        release(*columns.values(), out)

    streamed = stream_scan_lines(columns["gps_time"], columns["point_source_id"], use,
                                 before, after, STREAM_POINTS, chunk_done)
    if not streamed:
        rows = np.flatnonzero(use)
        before[:], after[:] = -1, -1
        found = scan_line_neighbours(np.asarray(columns["gps_time"][rows]),
                                     np.asarray(columns["point_source_id"][rows]))
        for side, j in zip((before, after), found, strict=True):
            side[rows] = np.where(j >= 0, rows[np.maximum(j, 0)], -1)
        del rows, found
    for s in range(0, len(out), STREAM_POINTS):
        part = out[s:s + STREAM_POINTS]
        part["persistent"] = persistent[s:s + STREAM_POINTS]
        for name in ("before", "after"):
            j = part[name]
            part[f"{name}_persistent"] = (j >= 0) & persistent[np.maximum(j, 0)]
        chunk_done()
    return {"scan_lines": "in file order (time order per scanner)" if streamed else
            "sorted by scanner and time over the whole file",
            "scan_line_points": int(np.count_nonzero(use))}


def combine_clusters(params: TransientParameters, columns: dict[str, np.ndarray],
                     out: np.ndarray) -> dict[str, Any]:
    """The scan-line neighbours (:func:`combine_scan_lines`), then steps 3-4 over the whole
    file's single-epoch points (:func:`~algorithms.transient.cluster_decisions`) into each
    point's ``score``. Memory: the single-epoch points' coordinates and facts (about 100 bytes
    each) besides what the scan lines take."""
    from algorithms.transient import cluster_decisions

    info = combine_scan_lines(params, columns, out)
    use, persistent = columns["in_stage"], columns["persistent"]
    single = np.concatenate([s + np.flatnonzero(np.asarray(use[s:s + STREAM_POINTS])
                                                & ~np.asarray(persistent[s:s + STREAM_POINTS]))
                             for s in range(0, len(out), STREAM_POINTS)] or [np.zeros(0, int)])
    # gathered a span of the file at a time: single-epoch points lie all over it
    xyz = np.column_stack([gathered(columns[c], single) for c in ("x", "y", "z")])
    facts = {name: gathered(columns[name], single).astype(bool) for name in ("touches",
                                                                              "covered")}
    sides = []
    for name in ("before", "after"):
        j = gathered(out[name], single)
        pos = np.minimum(np.searchsorted(single, j), max(single.size - 1, 0))
        mine = (j >= 0) & (single[pos] == j) if single.size else np.zeros(0, bool)
        sides.append(ScanLineSide(j >= 0, np.where(mine, pos, -1),
                                  gathered(out[f"{name}_persistent"], single).astype(bool)))
    clusters, n_comp = cluster_decisions(xyz, facts, tuple(sides), radius=params.radius,
                                         max_extent=params.max_extent)
    filled(out["score"], 0)
    scattered(out["score"], single, np.where(clusters.flagged, 2, 1).astype(np.uint8))
    flagged = int(clusters.flagged.sum())
    if params.stop_free_space:
        at_stops, info["stops"] = combine_stops(columns)
        scattered(out["score"], at_stops, np.full(at_stops.size, 2, np.uint8))
        info["points_flagged_by_clusters"] = flagged
        flagged = int(np.count_nonzero(out["score"] == 2))
    info.update(single_epoch=int(single.size), single_epoch_clusters=n_comp,
                points_flagged=flagged,
                floating_not_revisited=int((clusters.floating & ~clusters.flagged).sum()),
                single_epoch_wide=int(clusters.wide.sum()))
    return info


def combine_stops(columns: dict[str, np.ndarray]) -> tuple[np.ndarray, dict[str, Any]]:
    """(m,) sorted file indices of the points seen through at a stop
    (:mod:`algorithms.standstill`) among those that reached the stage, over the whole file,
    and the counts. A file whose returns come in time order per scanner takes one pass of a
    few million points at a time; any other is sorted by (point_source_id, gps_time) in memory
    (about 60 bytes a point that reached the stage)."""
    from algorithms.standstill import stop_flags, stream_stop_flags

    marked: list[np.ndarray] = []

    def chunk_done() -> None:
        release(*columns.values())

    info = stream_stop_flags(columns["gps_time"], columns["point_source_id"],
                             columns["in_stage"], (columns["x"], columns["y"], columns["z"]),
                             marked.append, STREAM_POINTS, chunk_done)
    if info is not None:
        rows = np.unique(np.concatenate(marked)) if marked else np.zeros(0, np.int64)
        return rows, {**info, "order": "in file order (time order per scanner)"}
    use = np.flatnonzero(columns["in_stage"])
    xyz = np.column_stack([gathered(columns[c], use) for c in ("x", "y", "z")])
    got, info = stop_flags(gathered(columns["gps_time"], use),
                           gathered(columns["point_source_id"], use), xyz)
    return use[got], {**info, "order": "sorted by scanner and time over the whole file"}


def _free_space(
    cloud: Cloud, gps_time: np.ndarray, params: TransientParameters, persistent: np.ndarray
) -> tuple[np.ndarray, dict[str, Any]]:
    """(n,) bool seen-through points and the info, on the points the trajectory's time covers;
    ``persistent``: the points the cluster test found recorded again at another moment (they
    win a conflict with a beam, :func:`algorithms.free_space.detect_free_space`)."""
    from algorithms.free_space import detect_free_space, posed_origins, vehicle_pose

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
    origin = posed_origins(position, heading, source, arms)
    placed = np.isin(source, list(arms))
    fs = detect_free_space(cloud.xyz[index], origin, radius=params.free_space_radius,
                           margin=params.free_space_margin, min_rays=params.free_space_min_rays,
                           seen_again=persistent[index], beams=placed,
                           gps_time=gps_time[index], hit_ratio=params.free_space_hit_ratio)
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
            "hit_ratio": params.free_space_hit_ratio,
            "points_returned_to": fs.info["points_returned_to"],
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
             "again (moving objects), and points a standing scanner's repeated beams saw through "
             "(exhaust at a stop)."),
    flag_bit=128,
    needs=("gps_time",),
    # the pass over the whole file decides every point (its clusters joined over the file): a
    # tile reads its points' scores only
    halo=lambda params: 0.0,
    prepass=Prepass(halo=lambda params: 2.0 * params.radius, values=persistent_values,
                    dtype=KNOWN_DTYPE, combine=combine_clusters),
    uses_trajectory=True,
)
