"""`lidar-outliers simulate`: write a simulated mobile-mapping cloud (condition A, B or C) as LAS.

The seed draws the survey's system, street, drive and outliers (a family, see
:mod:`lidar_outliers.tools.simulator`); the condition keeps the paper's cloud size and outlier
share. Writes ``DIR/<condition>_<seed>.las`` (LAS 1.4, point format 6, 1 mm scale,
classification 0), the truth beside it (``.truth.npz``: ``is_outlier``, ``kind``,
``kind_names``, the system's ``lever_arms``, ``pose``, ``speed`` and ``facts``) and the vehicle
trajectory (``.trajectory.txt``: time x y z of the reference point, 100 Hz). This module is the
command.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from lidar_outliers.errors import ParameterError
from lidar_outliers.tools.simulator import simulate, write_simulation


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "simulate",
        help="simulate a mobile-mapping cloud like the paper's A, B or C",
        description="Simulate a mobile-mapping survey whose system, street, drive and outliers "
        "the seed draws, with the size and outlier share of the paper's Table 1, and write it "
        "as LAS with its truth and trajectory.",
    )
    parser.add_argument("--condition", required=True, choices=("A", "B", "C"),
                        help="A: 1.0 %% clumped, B: 0.3 %% spread, C: 0.01 %% near the surface")
    parser.add_argument("--seed", type=int, default=0,
                        help="draws the system, street, drive and outliers (default 0)")
    parser.add_argument("--out", required=True, type=Path, help="output directory")
    parser.add_argument("--scale", type=float, default=1.0,
                        help="shrink the strip and point count by this factor, 0.01-1 (default 1)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not 0.01 <= args.scale <= 1.0:
        raise ParameterError(f"--scale must be between 0.01 and 1, got {args.scale}")
    if args.seed < 0:
        raise ParameterError(f"--seed must be 0 or more, got {args.seed}")
    start = time.perf_counter()
    cloud = simulate(args.condition, args.seed, args.scale)
    path = write_simulation(cloud, args.out)
    share = 100.0 * cloud.is_outlier.mean()
    print(f"{path}: {len(cloud):,} points, {int(cloud.is_outlier.sum()):,} outliers "
          f"({share:.2f} %), {time.perf_counter() - start:.1f} s")
    return 0
