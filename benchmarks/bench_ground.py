"""Accuracy of the ``ground`` detector on the ISPRS samples and its speed on a large cloud.

    .venv/bin/python benchmarks/bench_ground.py isprs   # type I/II, total error, kappa per sample
    .venv/bin/python benchmarks/bench_ground.py speed   # points/s on 1.1 M synthetic points
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import laspy
import numpy as np

from algorithms.ground import classify_ground
from algorithms.metrics import ground_scores

ISPRS = Path(__file__).resolve().parents[1] / "tests" / "data" / "isprs"
SAMPLES = ["samp11", "samp21", "samp31", "samp41", "samp51", "samp61", "samp71"]


def isprs(**kwargs: float) -> dict[str, dict]:
    rows = {}
    for name in SAMPLES:
        las = laspy.read(ISPRS / f"{name}.laz")
        truth = np.asarray(las.classification) == 2
        xyz = np.column_stack([las.x, las.y, las.z])  # classification is not passed on
        res = classify_ground(xyz, **kwargs)
        s = ground_scores(truth, res.is_ground)
        s["iterations"] = res.info["iterations"]
        rows[name] = s
        print(f"{name}  I {s['type_i_pct']:6.2f}  II {s['type_ii_pct']:6.2f}  "
              f"total {s['total_error_pct']:6.2f}  kappa {s['kappa_pct']:6.2f}  "
              f"it {s['iterations']}  low {res.info['low_outliers']}")
    mean = {k: float(np.mean([r[k] for r in rows.values()]))
            for k in ("type_i_pct", "type_ii_pct", "total_error_pct", "kappa_pct")}
    print(f"mean    I {mean['type_i_pct']:6.2f}  II {mean['type_ii_pct']:6.2f}  "
          f"total {mean['total_error_pct']:6.2f}  kappa {mean['kappa_pct']:6.2f}")
    rows["mean"] = mean
    return rows


def synthetic_cloud(n: int, seed: int = 0) -> np.ndarray:
    """Rolling terrain at ~1 pt/m2 with box buildings and round trees, UTM-sized coordinates."""
    rng = np.random.default_rng(seed)
    side = np.sqrt(n)
    x, y = rng.random(n) * side, rng.random(n) * side
    z = 3 * np.sin(x / 40) + 2 * np.cos(y / 55) + 0.05 * rng.standard_normal(n)
    for _ in range(n // 4000):  # buildings
        cx, cy, w, h = *(rng.random(2) * side), rng.uniform(8, 40), rng.uniform(4, 15)
        inside = (np.abs(x - cx) < w / 2) & (np.abs(y - cy) < w / 3)
        z[inside] += h
    for _ in range(n // 1000):  # trees
        cx, cy, r = *(rng.random(2) * side), rng.uniform(1.5, 4)
        d = np.hypot(x - cx, y - cy)
        inside = d < r
        hit = rng.random(inside.sum()) < 0.8  # some returns reach the ground under the crown
        z[inside] += rng.uniform(5, 15) * (1 - 0.3 * d[inside] / r) * hit
    return np.column_stack([x + 500_000.0, y + 5_000_000.0, z + 300.0])


def speed(n: int, dense: bool = False, **kwargs: float) -> dict[str, float]:
    xyz = synthetic_cloud(n)
    if dense:  # the same scene shrunk 10.5x: ~110 points/m2, mobile-scanner-like density
        xyz[:, :2] = xyz[:, :2].min(axis=0) + (xyz[:, :2] - xyz[:, :2].min(axis=0)) / 10.5
    classify_ground(xyz[:1000], **kwargs)  # numba compile / cache load
    t0 = time.perf_counter()
    res = classify_ground(xyz, **kwargs)
    dt = time.perf_counter() - t0
    out = {"points": n, "dense": dense, "seconds": round(dt, 3),
           "points_per_second": round(n / dt), "iterations": res.info["iterations"],
           "triangulator": res.info["triangulator"],
           "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}
    print(json.dumps(out))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("what", choices=["isprs", "speed"])
    ap.add_argument("--points", type=int, default=1_100_000)
    ap.add_argument("--dense", action="store_true", help="speed: ~110 points/m2 instead of ~1")
    names = ["slope_threshold", "max_iterations", "min_object_height", "low_outlier_depth",
             "max_object_size", "terrain_slope", "ground_tolerance"]
    for name in names:
        kind = int if name == "max_iterations" else float
        ap.add_argument("--" + name.replace("_", "-"), type=kind)
    a = ap.parse_args()
    kwargs = {k: getattr(a, k) for k in names if getattr(a, k) is not None}
    if a.what == "isprs":
        isprs(**kwargs)
    else:
        speed(a.points, a.dense, **kwargs)


if __name__ == "__main__":
    main()
