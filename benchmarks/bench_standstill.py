"""Free space at the vehicle's stops on its own: what ``transient``'s ``stop_free_space`` flags.

    .venv/bin/python benchmarks/bench_standstill.py                        # A, seeds 0-2, 100-104
    .venv/bin/python benchmarks/bench_standstill.py --conditions BC --seeds 100 101 102 103 104

While the vehicle stands, a profile scanner fires the same beams every turn and every point,
plume or wall, lies in its scan plane: a surface test sees a plane everywhere. What separates
them is free space along the repeated beams: a droplet is passed by the beam's other pulses and
almost never returned to, a surface is returned to. :func:`algorithms.standstill.stop_flags`
finds each scanner's stops from its own returns, cuts them into seconds of GPS time, places the
scanner in each from that second's returns and flags what its beams saw through.

For each simulated cloud (:func:`~lidar_outliers.tools.simulator.simulate`) prints the share of
its returns at the stops found, the pieces found and placed, the seconds taken, the real returns
flagged and the outliers flagged (exhaust apart); then, pooled, the points of each kind flagged.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from algorithms.standstill import stop_flags  # noqa: E402
from lidar_outliers.tools.simulator import KIND_NAMES, simulate  # noqa: E402


def run(conditions: str, seeds: list[int], scale: float) -> None:
    flagged: dict[str, int] = {}
    present: dict[str, int] = {}
    exhaust = KIND_NAMES.index("exhaust_plume")
    for condition in conditions:
        for seed in seeds:
            cloud = simulate(condition, seed, scale)
            start = time.perf_counter()
            flags, info = stop_flags(cloud.gps_time, cloud.point_source_id, cloud.xyz)
            seconds = time.perf_counter() - start
            kind = cloud.kind
            for code in np.unique(kind):
                name = KIND_NAMES[code]
                present[name] = present.get(name, 0) + int(np.count_nonzero(kind == code))
                flagged[name] = flagged.get(name, 0) + int(np.count_nonzero(flags
                                                                            & (kind == code)))
            print(f"{condition} seed {seed}: {len(kind):,} returns, "
                  f"{info['stop_points'] / len(kind):.1%} at stops, "
                  f"{info['stop_pieces_placed']} of {info['stop_pieces']} pieces placed, "
                  f"{seconds:.2f} s; flagged: real {int(np.count_nonzero(flags & (kind == 0)))}, "
                  f"exhaust {int(np.count_nonzero(flags & (kind == exhaust)))} of "
                  f"{int(np.count_nonzero(kind == exhaust))}, other outliers "
                  f"{int(np.count_nonzero(flags & (kind > 0) & (kind != exhaust)))}")
    print("\npooled:")
    for name in sorted(present, key=lambda k: (k != "surface", k)):
        print(f"  {name:16s} {flagged[name]:7,} of {present[name]:9,} flagged")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--conditions", default="A", help="conditions to run (default A)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 100, 101, 102, 103, 104])
    ap.add_argument("--scale", type=float, default=0.3)
    args = ap.parse_args(argv)
    run(args.conditions, args.seeds, args.scale)


if __name__ == "__main__":
    main()
