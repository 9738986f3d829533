"""Speed and peak memory of the `patch` and `section` detectors on a synthetic mobile-like cloud.

    .venv/bin/python benchmarks/bench_spatial.py --points 1100000 --detector section
    .venv/bin/python benchmarks/bench_spatial.py --points 1100000 --detector patch

The cloud is a road surface 10 m wide with a parabolic crown (5 cm drop at the edges), a 1 %
longitudinal grade and a gentle 2 cm undulation, coordinates near (5e5, 5e6, 100) m, 5 mm Gaussian
noise, plus 0.1 % gross outliers 5-50 cm above or below the surface. Density ~1000 points/m^2.
Numba compilation is done (and cached) on a small cloud before the timed run. Recall and false
alarm rate against the injected outliers are printed too.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from algorithms.patch import detect_patch  # noqa: E402
from algorithms.section import detect_section  # noqa: E402


def road_cloud(n: int, seed: int = 0, outlier_fraction: float = 0.001):
    """(xyz (n, 3), is_outlier (n,)) for a crowned road with 5 mm noise and gross outliers."""
    rng = np.random.default_rng(seed)
    width = 10.0
    length = n / (1000.0 * width)
    x = rng.uniform(0.0, length, n)
    y = rng.uniform(-width / 2, width / 2, n)
    z = -0.002 * y**2 + 0.01 * x + 0.02 * np.sin(x / 7.0) + rng.normal(0.0, 0.005, n)
    out = rng.random(n) < outlier_fraction
    z[out] += rng.choice([-1.0, 1.0], out.sum()) * rng.uniform(0.05, 0.5, out.sum())
    xyz = np.c_[x + 5e5, y + 5e6, z + 100.0]
    return xyz, out


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1_100_000)
    ap.add_argument("--detector", choices=["patch", "section"], default="section")
    ap.add_argument(
        "--condition",
        choices=["road", "A", "B", "C"],
        default="road",
        help="road: the synthetic crowned road above; A/B/C: lidar_outliers.tools.simulator "
        "(--points is then ignored; --scale sets the size, 1.0 = the paper's cloud)",
    )
    ap.add_argument("--scale", type=float, default=1.0)
    args = ap.parse_args()

    detect = detect_patch if args.detector == "patch" else detect_section
    warm, _ = road_cloud(5000, seed=1)
    detect(warm)  # compile / load the numba cache outside the timing

    if args.condition == "road":
        xyz, truth = road_cloud(args.points)
    else:
        from lidar_outliers.tools.simulator import simulate

        cloud = simulate(args.condition, seed=0, scale=args.scale)
        xyz, truth = cloud.xyz, cloud.is_outlier
        args.points = len(xyz)
    cpu0 = _cpu_seconds()
    t0 = time.perf_counter()
    res = detect(xyz)
    seconds = time.perf_counter() - t0
    cpu = _cpu_seconds() - cpu0
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    flagged = res.flagged
    print(
        json.dumps(
            {
                "detector": args.detector,
                "cloud": args.condition,
                "points": args.points,
                "seconds": round(seconds, 2),
                "points_per_second": round(args.points / seconds),
                "cpu_seconds": round(cpu, 2),
                # What two otherwise idle cores would reach (the machine is shared).
                "points_per_second_2_idle_cores": round(args.points / (cpu / 2.0)),
                "peak_rss_mb": round(peak_mb),
                "outliers_injected": int(truth.sum()),
                "recall": round(float((flagged & truth).sum() / max(truth.sum(), 1)), 4),
                "false_alarm_rate": round(float((flagged & ~truth).sum() / (~truth).sum()), 6),
                "info": res.info,
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
