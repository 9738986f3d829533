"""Whole-command speed of ``lidar-outliers detect --detector temporal`` against plain laspy I/O.

Target: the whole command within 3x of just reading and writing the file with laspy,
on a 1.1 million point mobile cloud. The cloud is synthetic: two profile scanners interleaved in
time order, coordinates near 5e6 m, GPS times near 5e5 s, LAS 1.4 point format 6.

Two comparisons, like for like:

- commands: ``lidar-outliers detect IN -o OUT --detector temporal`` against the smallest laspy
  command, ``python -c "laspy.read(IN).write(OUT)"``, each a fresh process (interpreter start,
  imports, I/O, exit), run alternately ``--repeat`` times; min and median wall seconds;
- in this process: ``lidar_outliers.process.process_file`` (in memory, and streaming) against
  ``laspy.read(IN).write(OUT)``; best of ``--repeat``, CPU seconds beside.

The machine is shared and its speed drifts by 10-20 % within minutes, hence the alternation.

    .venv/bin/python benchmarks/bench_detect_io.py [--points 1100000] [--laz] [--repeat 10]
    .venv/bin/python benchmarks/bench_detect_io.py --input CLOUD.las   # a file of your own
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lidar_outliers.process import process_file  # noqa: E402
from lidar_outliers.tiling import WHOLE_CLOUD_POINTS  # noqa: E402


def make_cloud(path: Path, n: int, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    t = 5e5 + np.cumsum(rng.uniform(0.5e-5, 1.5e-5, n))
    scanner = np.where(np.arange(n) % 2 == 0, 1, 2).astype(np.uint16)
    phase = (t - t[0]) * 200.0 + scanner
    xyz = np.column_stack([
        5_000_000.0 + 10 * (t - t[0]) + 8 * np.cos(phase),
        4_000_000.0 + 8 * np.sin(phase),
        100.0 + 0.3 * np.sin(3 * phase),
    ]) + rng.normal(0, 0.004, (n, 3))
    spikes = rng.choice(n, n // 200, replace=False)
    xyz[spikes, 2] += rng.uniform(0.2, 2.0, spikes.size)
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.offsets = [5_000_000.0, 4_000_000.0, 0.0]
    header.scales = [0.001, 0.001, 0.001]
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    las.gps_time = t
    las.point_source_id = scanner
    las.intensity = rng.integers(0, 4000, n).astype(np.uint16)
    las.write(str(path))


def timed(fn) -> tuple[float, float]:
    c0, w0 = time.process_time(), time.perf_counter()
    fn()
    return time.perf_counter() - w0, time.process_time() - c0


def best(fn, repeat: int) -> tuple[float, float]:
    runs = [timed(fn) for _ in range(repeat)]
    return min(runs)


def run_command(command: list[str]) -> float:
    w0 = time.perf_counter()
    subprocess.run(command, check=True, cwd=ROOT)
    return time.perf_counter() - w0


def compare_commands(ours: list[str], laspy_cmd: list[str], repeat: int) -> dict[str, list[float]]:
    """Wall seconds of both commands, run alternately (one warm-up run each first)."""
    run_command(ours)
    run_command(laspy_cmd)
    walls: dict[str, list[float]] = {"ours": [], "laspy": []}
    for _ in range(repeat):
        walls["ours"].append(run_command(ours))
        walls["laspy"].append(run_command(laspy_cmd))
    return walls


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1_100_000)
    ap.add_argument("--laz", action="store_true", help="LAZ in and out instead of LAS")
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--input", type=Path, help="an existing LAS/LAZ file instead of the synthetic")
    args = ap.parse_args()
    suffix = args.input.suffix.lstrip(".").lower() if args.input else "laz" if args.laz else "las"
    with tempfile.TemporaryDirectory(prefix="bench_detect_io_") as tmp:
        tmp = Path(tmp)
        src = args.input.resolve() if args.input else tmp / f"cloud.{suffix}"
        if not args.input:
            make_cloud(src, args.points)
        with laspy.open(str(src)) as reader:
            n = int(reader.header.point_count)
        params = {"pipeline": [{"detector": "temporal"}]}
        process_file(src, tmp / f"warm.{suffix}", params)

        def laspy_io() -> None:
            laspy.read(str(src)).write(str(tmp / f"laspy_out.{suffix}"))

        def streaming() -> None:
            stats = process_file(src, tmp / f"s.{suffix}", params, streaming=True)
            assert stats["mode"] == "streaming", stats.get("streaming")

        def in_memory() -> None:
            stats = process_file(src, tmp / f"m.{suffix}", params, streaming=False)
            assert stats["mode"] == "in memory"

        script = Path(sys.executable).with_name("lidar-outliers")
        ours = [str(script)] if script.exists() else [sys.executable, "-m", "lidar_outliers.cli"]
        ours += ["detect", str(src), "-o", str(tmp / f"c.{suffix}"), "-q",
                 "--detector", "temporal", "--stats", str(tmp / "c.json")]
        laspy_cmd = [sys.executable, "-c", "import sys, laspy; "
                     "laspy.read(sys.argv[1]).write(sys.argv[2])",
                     str(src), str(tmp / f"lc.{suffix}")]
        walls = compare_commands(ours, laspy_cmd, args.repeat)
        print(f"{src.name}: {n:,} points, {suffix.upper()} {src.stat().st_size / 1e6:.1f} MB, "
              f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
        print(f"\ncommands, {args.repeat} alternate runs each:")
        print(f"{'':36} {'min s':>8} {'median s':>9}")
        for label, key in (("lidar-outliers detect --detector temporal", "ours"),
                           ("python -c laspy.read(IN).write(OUT)", "laspy")):
            print(f"{label:42} {min(walls[key]):6.3f} {statistics.median(walls[key]):9.3f}")
        print(f"ratio: {min(walls['ours']) / min(walls['laspy']):.2f}x (min), "
              f"{statistics.median(walls['ours']) / statistics.median(walls['laspy']):.2f}x "
              f"(median); target 3x")

        base = best(laspy_io, args.repeat)
        rows = [("laspy read + write", base)]
        if n <= WHOLE_CLOUD_POINTS:  # larger files never run in memory (they stream)
            rows.append(("detect (in memory)", best(in_memory, args.repeat)))
        rows.append(("detect (streaming)", best(streaming, args.repeat)))
        print(f"\nin this process, best of {args.repeat}:")
        print(f"{'':36} {'wall s':>8} {'cpu s':>8} {'Mpts/s':>8} {'x laspy (wall/cpu)':>20}")
        for label, (wall, cpu) in rows:
            print(f"{label:36} {wall:8.3f} {cpu:8.3f} {n / wall / 1e6:8.2f} "
                  f"{wall / base[0]:9.2f} / {cpu / base[1]:.2f}")
        print(f"peak RSS of this process: "
              f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB; of the "
              f"commands: {resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
