"""Speed and untested points of the `patch` detector on the first points (time order) of simulated
mobile clouds.

    .venv/bin/python benchmarks/bench_quadric.py --condition A --seeds 0 5 --points 100000

Each cloud comes from the project's simulator (``lidar-outliers simulate``; ``--scale`` sets its
size); its first ``--points`` points in GPS time are fitted with the default parameters. Numba
compilation is done (and cached) on a small cloud before the timed runs. Printed per cloud: wall
and CPU seconds, points per second, what two otherwise idle cores would reach (CPU seconds / 2),
the untested points by reason, mean adjustments per point, and the load average of the machine
before and after (the machine may be shared: the wall-clock figure depends on it).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from algorithms.patch import detect_patch  # noqa: E402


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def first_points(condition: str, seed: int, scale: float, points: int) -> np.ndarray:
    """The first ``points`` points (GPS time order) of a simulated mobile cloud: (m, 3)."""
    from lidar_outliers.tools.simulator import simulate

    cloud = simulate(condition, seed=seed, scale=scale)
    order = np.argsort(cloud.gps_time, kind="stable")[:points]
    return cloud.xyz[order]


def run(xyz: np.ndarray) -> dict:
    """Time detect_patch on xyz with its defaults."""
    load_before = os.getloadavg()[0]
    cpu0 = _cpu_seconds()
    t0 = time.perf_counter()
    res = detect_patch(xyz)
    seconds = time.perf_counter() - t0
    cpu = _cpu_seconds() - cpu0
    n = len(xyz)
    untested = res.info["points_untested"]
    return {
        "points": n,
        "seconds": round(seconds, 2),
        "points_per_second": round(n / seconds),
        "cpu_seconds": round(cpu, 2),
        "points_per_second_2_idle_cores": round(n / (cpu / 2.0)),
        "untested": untested,
        "untested_percent": round(100.0 * sum(untested.values()) / max(n, 1), 3),
        "mean_iterations": round(res.info["mean_iterations"] or 0.0, 2),
        "load_average_before_after": [round(load_before, 2), round(os.getloadavg()[0], 2)],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--condition", choices=["A", "B", "C"], default="A")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--scale", type=float, default=0.2,
                    help="simulator scale (0.2 gives clouds of 130-170 k points)")
    ap.add_argument("--points", type=int, default=100_000)
    args = ap.parse_args()

    rng = np.random.default_rng(0)
    detect_patch(np.c_[rng.uniform(0, 2, (2000, 2)), rng.normal(0, 0.005, 2000)])  # compile
    for seed in args.seeds:
        xyz = first_points(args.condition, seed, args.scale, args.points)
        out = {"condition": args.condition, "seed": seed, "scale": args.scale} | run(xyz)
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
