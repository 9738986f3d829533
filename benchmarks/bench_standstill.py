"""Free space at the vehicle's stops, without a trajectory: evidence for a detector not built yet.

    .venv/bin/python benchmarks/bench_standstill.py                       # seeds 0-2, 100-104
    .venv/bin/python benchmarks/bench_standstill.py --seeds 100 --scale 0.3

While the vehicle stands, a profile scanner fires the same beams every turn and every point,
plume or wall, lies in its scan plane: a surface test sees a plane everywhere. What separates
them is free space along the repeated beams: a droplet is passed by the beam's other pulses and
almost never returned to, a surface is returned to. This needs no trajectory, only the
scanner's position during the stop, which every beam of the stop passes through.

For each simulated cloud (condition A, :func:`~lidar_outliers.tools.simulator.simulate`) and
each scanner, the spans over which it stood still are found from its own points
(:func:`algorithms.standstill.still_spans`; ``--truth-stops``: the stops the simulator drew
instead) and, per span: the scanner's position from the span's own points
(:func:`algorithms.lever_arms.fit_lever_arm` at a zero pose: a still vehicle), the beams of the
span that saw through each point
(:func:`algorithms.free_space.see_through_counts`) and the returns of other pulses on the
point's own beam (:func:`algorithms.free_space.beam_returns`). A point is flagged when at least
``--min-passes`` beams passed it and its own beam returned to it at most ``--ratio`` times as
often. Prints, pooled over the spans, the points of each kind flagged and the real ones, and
how the spans found cover the simulator's stops.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from algorithms.free_space import beam_returns, grazing_margins, see_through_counts  # noqa: E402
from algorithms.lever_arms import fit_lever_arm  # noqa: E402
from algorithms.standstill import still_spans  # noqa: E402
from lidar_outliers.tools.simulator import KIND_NAMES, simulate  # noqa: E402

#: Metres: a beam passes a point within this (free space's default radius).
RADIUS = 0.006
#: Metres a beam must end beyond a point to see through it (free space's default margin).
MARGIN = 0.08


def stop_counts(xyz: np.ndarray, gps_time: np.ndarray, depth: float
                ) -> tuple[np.ndarray, np.ndarray, dict] | None:
    """(passes, returns, fit info) of one scanner's points during one stop; None when its
    position cannot be fitted."""
    n = len(xyz)
    fit = fit_lever_arm(xyz, gps_time, np.zeros((n, 3)), np.zeros(n))
    if fit.arm is None:
        return None
    origin = np.tile(np.asarray(fit.arm), (n, 1))
    margins = grazing_margins(xyz, origin, radius=RADIUS, margin=MARGIN)
    passes = see_through_counts(xyz, origin, radius=RADIUS, margin=margins)
    seen = np.flatnonzero(passes > 0)
    returns = np.zeros(n, dtype=np.int64)
    returns[seen] = beam_returns(xyz, origin, gps_time, seen, radius=RADIUS, depth=depth)
    return passes, returns, fit.info


def spans_of(cloud, sid: int, truth: bool) -> np.ndarray:
    """(m, 2) the spans over which scanner ``sid`` stood still: found, or the drawn stops."""
    if truth:
        return np.array(cloud.motion.stops, dtype=np.float64).reshape(-1, 2)
    rows = cloud.point_source_id == sid
    return still_spans(cloud.gps_time[rows], cloud.xyz[rows])


def overlap(spans: np.ndarray, stops: list) -> float:
    """Seconds of ``spans`` inside the simulator's ``stops``."""
    return sum(max(0.0, min(b, d) - max(a, c)) for a, b in spans for c, d in stops)


def run(seeds: list[int], scale: float, min_passes: int, ratio: float, depth: float,
        truth: bool) -> None:
    flagged: dict[str, int] = {}
    present: dict[str, int] = {}
    found_s = inside_s = stops_s = 0.0
    for seed in seeds:
        cloud = simulate("A", seed, scale)
        centre = cloud.xyz.mean(axis=0)
        stops = [(float(a), float(b)) for a, b in cloud.motion.stops]
        for sid in np.unique(cloud.point_source_id):
            spans = spans_of(cloud, int(sid), truth)
            found_s += float(np.sum(spans[:, 1] - spans[:, 0]))
            inside_s += overlap(spans, stops)
            stops_s += sum(b - a for a, b in stops)
            for a, b in spans:
                rows = np.flatnonzero((cloud.gps_time >= a) & (cloud.gps_time <= b)
                                      & (cloud.point_source_id == sid))
                if rows.size < 100:
                    continue
                start = time.perf_counter()
                got = stop_counts(cloud.xyz[rows] - centre, cloud.gps_time[rows], depth)
                seconds = time.perf_counter() - start
                if got is None:
                    print(f"seed {seed}, span at {a:.1f} s, scanner {sid}: no position fitted")
                    continue
                passes, returns, info = got
                hit = (passes >= min_passes) & (returns <= ratio * passes)
                kinds = cloud.kind[rows]
                for code in np.unique(kinds):
                    name = KIND_NAMES[code]
                    present[name] = present.get(name, 0) + int(np.count_nonzero(kinds == code))
                    flagged[name] = flagged.get(name, 0) + int(np.count_nonzero(hit
                                                                                & (kinds == code)))
                print(f"seed {seed}, span {a:.2f}-{b:.2f} s, scanner {sid}: {rows.size:,} points, "
                      f"mirror {info['mirror_hz']} Hz, {seconds:.1f} s, "
                      f"{int(hit.sum()):,} flagged")
    print(f"\nspans: {found_s:.2f} s, of them {inside_s:.2f} s inside the simulator's stops "
          f"({stops_s:.2f} s over all scanners)")
    print(f"pooled (at least {min_passes} beams through, own beam's returns at most {ratio} "
          f"times that, {depth} m along it):")
    for name in sorted(present, key=lambda k: (k != "surface", k)):
        print(f"  {name:16s} {flagged[name]:7,} of {present[name]:9,} flagged")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 100, 101, 102, 103, 104])
    ap.add_argument("--scale", type=float, default=0.3)
    ap.add_argument("--min-passes", type=int, default=5)
    ap.add_argument("--ratio", type=float, default=0.1)
    ap.add_argument("--depth", type=float, default=0.03, help="metres along the beam")
    ap.add_argument("--truth-stops", action="store_true",
                    help="the simulator's stops instead of the spans found from the points")
    args = ap.parse_args(argv)
    run(args.seeds, args.scale, args.min_passes, args.ratio, args.depth, args.truth_stops)


if __name__ == "__main__":
    main()
