"""The mobile profile's default pipeline alone on simulated clouds: recall, false alarms and
recall per outlier kind, without and with the trajectory (the lever arms estimated from the
points, or the system's true ones given).

    .venv/bin/python benchmarks/bench_default_mobile.py 100,101,102,103,104      # reporting seeds
    .venv/bin/python benchmarks/bench_default_mobile.py 0,1,2 --conditions B     # tuning seeds

The same clouds, pipeline and scoring as the default-pipeline rows of ``lidar-outliers bench``
(:mod:`lidar_outliers.tools.bench`), without the other pipelines; clouds are cached under
``--cache``. Percentages are pooled over the seeds.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lidar_outliers.lasio import read_cloud  # noqa: E402
from lidar_outliers.params import default_stages  # noqa: E402
from lidar_outliers.tools import bench  # noqa: E402


def run(seeds: list[int], conditions: str, scale: float, cache: Path) -> None:
    """Print one line per condition and variant."""
    stages = [s.detector for s in default_stages(True)]
    for cond in conditions:
        for variant in ("no trajectory", "trajectory, lever arms estimated",
                        "trajectory, lever arms given"):
            tp = fp = n_out = n_real = 0
            kinds: dict[str, list[int]] = {}
            for seed in seeds:
                path = bench.simulated_cloud(cache, cond, seed, scale)
                cloud = read_cloud(path)
                with np.load(path.with_suffix(".truth.npz")) as t:
                    out = np.asarray(t["is_outlier"], dtype=bool)
                    kind = np.asarray(t["kind"])
                    names = [str(k) for k in t["kind_names"]]
                settings = None
                if variant.startswith("trajectory"):
                    cloud = bench.with_simulated_trajectory(cloud, path)
                if variant.endswith("given"):
                    settings = {"transient": {"lever_arms": bench.simulated_lever_arms(path)}}
                flags = bench.run_outlier_pipeline(cloud, stages, settings).flagged
                tp += int((flags & out).sum())
                fp += int((flags & ~out).sum())
                n_out += int(out.sum())
                n_real += int((~out).sum())
                for code in np.unique(kind[out]):
                    m = kind == code
                    k = kinds.setdefault(names[code], [0, 0])
                    k[0] += int((flags & m).sum())
                    k[1] += int(m.sum())
            per_kind = ", ".join(f"{k} {100 * a / b:.0f}" for k, (a, b) in kinds.items())
            print(f"{cond} {variant}: recall {100 * tp / max(n_out, 1):.1f} %, false alarms "
                  f"{100 * fp / max(n_real, 1):.3f} % ({fp}) | {per_kind}", flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seeds", help="comma-separated seeds, e.g. 100,101,102,103,104")
    parser.add_argument("--conditions", default="ABC")
    parser.add_argument("--scale", type=float, default=0.3)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/lidar-outliers-bench"))
    args = parser.parse_args(argv)
    run([int(s) for s in args.seeds.split(",")], args.conditions, args.scale, args.cache)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
