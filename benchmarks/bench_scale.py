"""Scale: a large simulated cloud through the command line and through the service with one and
two worker processes; wall time, points per second, peak memory per process.

The cloud is simulated cloud A (seed 0, about 0.9 M points; ``lidar-outliers simulate``) laid
side by side in X (and later in time) as often as ``--points`` needs. The first
``--base-points`` of such a file (default 1.2 M: the copy and the start of the next) run through
the command line first, whole: the ratio column compares each run with that base cloud.

    .venv/bin/python benchmarks/bench_scale.py --points 50000000          # the real benchmark
    .venv/bin/python benchmarks/bench_scale.py --points 2500000 --workers 1 2
    .venv/bin/python benchmarks/bench_scale.py --points 2500000 \\
        --params '{"pipeline": [{"detector": "height_field", "sigma": 0.01, "low": false}]}'

Peak memory is the largest resident set a process had, sampled every 0.2 s (psutil) over the
command's or the service's whole process tree (for the service: the API, Redis, the Celery main
process and its pool processes, which run the job and its tiles). "Cores busy" is the CPU time
of that tree (user + system) over the wall time: how much of the machine a run kept busy.
"Anonymous" is the largest ``RssAnon`` of a process: its memory that is not file pages (the
per-point columns a tiled run keeps in memory-mapped files count in RSS while their pages are
cached, but the kernel can drop them).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import laspy
import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
CLI = [sys.executable, "-m", "lidar_outliers"]
GAP = 10.0  # metres and seconds between two copies of the base cloud


@dataclass
class Peaks:
    """Largest RSS seen per process of a tree (pid -> (name, bytes))."""

    root: int
    rss: dict[int, tuple[str, int]] = field(default_factory=dict)
    cpu: dict[int, float] = field(default_factory=dict)  # pid -> CPU seconds (user + system)
    anon: dict[int, int] = field(default_factory=dict)  # pid -> largest RssAnon, bytes
    stop: threading.Event = field(default_factory=threading.Event)

    def sample(self) -> None:
        try:
            procs = [psutil.Process(self.root)]
            procs += procs[0].children(recursive=True)
        except psutil.NoSuchProcess:
            return
        for p in procs:
            try:
                name = " ".join([p.name(), *p.cmdline()[1:4]])
                rss = p.memory_info().rss
                times = p.cpu_times()
            except psutil.Error:
                continue
            self.cpu[p.pid] = max(self.cpu.get(p.pid, 0.0), times.user + times.system)
            self.anon[p.pid] = max(self.anon.get(p.pid, 0), anonymous_rss(p.pid))
            old = self.rss.get(p.pid, ("", 0))[1]
            self.rss[p.pid] = (name, max(old, rss))

    def run(self) -> None:
        while not self.stop.is_set():
            self.sample()
            self.stop.wait(0.2)

    def __enter__(self) -> Peaks:
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join()

    def largest_anonymous(self) -> int:
        """The largest anonymous resident set of any process of the tree (bytes)."""
        return max(self.anon.values(), default=0)

    def cpu_seconds(self) -> float:
        """CPU time of the tree's processes as last sampled (a process that ended between two
        samples loses at most 0.2 s)."""
        return sum(self.cpu.values())

    def largest(self) -> tuple[str, int]:
        return max(self.rss.values(), key=lambda v: v[1], default=("", 0))

    def by_role(self) -> dict[str, int]:
        """Peak per kind of process (the largest of each kind)."""
        out: dict[str, int] = {}
        for name, rss in self.rss.values():
            role = ("worker" if "celery" in name else "api" if "uvicorn" in name
                    else "redis" if "redis" in name else "serve" if "serve" in name
                    else "detect" if "detect" in name else name.split(" ")[0])
            out[role] = max(out.get(role, 0), rss)
        return out


def anonymous_rss(pid: int) -> int:
    """``RssAnon`` of a process (bytes; Linux, else 0): its resident memory that is not file
    pages. The rest of its RSS (memory-mapped per-point columns, mapped libraries) is page
    cache the kernel can drop and read again."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("RssAnon:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def simulated_cloud(folder: Path) -> Path:
    """Simulated cloud A, seed 0, full scale (made once, kept in ``folder``)."""
    found = sorted(folder.glob("A_0*.las"))
    if not found:
        subprocess.run([*CLI, "simulate", "--condition", "A", "--seed", "0", "--out",
                        str(folder)], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
        found = sorted(folder.glob("A_0*.las"))
    return next(p for p in found if "truth" not in p.name)


def tiled_copy(base: Path, out: Path, points: int) -> int:
    """Copies of ``base`` side by side in X and one after another in time, up to ``points``
    points (the last copy cut short); written chunk by chunk. Returns the points written."""
    las = laspy.read(base)
    n = len(las.points)
    width = float(las.header.maxs[0] - las.header.mins[0]) + GAP
    t = np.asarray(las.gps_time)
    span = float(t.max() - t.min()) + GAP
    header = laspy.LasHeader(point_format=las.header.point_format, version=las.header.version)
    header.offsets, header.scales = las.header.offsets, las.header.scales
    header.add_extra_dims([laspy.ExtraBytesParams(d.name, d.dtype) for d in
                           las.point_format.extra_dimensions])
    written = 0
    with laspy.open(out, mode="w", header=header) as writer:
        copy = 0
        while written < points:
            take = min(n, points - written)
            part = laspy.ScaleAwarePointRecord(las.points.array[:take].copy(), las.point_format,
                                               las.header.scales, las.header.offsets)
            part.array["X"] += int(round(copy * width / las.header.scales[0]))
            part.array["gps_time"] += copy * span
            writer.write_points(part)
            written += take
            copy += 1
    return written


def copies(simulated: Path, out: Path, points: int) -> Path:
    """``out``: :func:`tiled_copy` of ``points`` points (made once, kept)."""
    if not out.exists():
        part = out.with_suffix(".part")
        tiled_copy(simulated, part, points)
        part.rename(out)
    return out


def run_cli(cloud: Path, out: Path, params: str | None, tile_size: float | None) -> dict:
    argv = [*CLI, "detect", str(cloud), "-o", str(out), "-q", "--stats", str(out) + ".json"]
    if params:
        argv += ["--params", params]
    if tile_size:
        argv += ["--tile-size", str(tile_size)]
    started = time.perf_counter()
    proc = subprocess.Popen(argv, cwd=ROOT)
    with Peaks(proc.pid) as peaks:
        code = proc.wait()
    wall = time.perf_counter() - started
    if code:
        raise SystemExit(f"detect failed with exit code {code}")
    stats = json.loads(Path(str(out) + ".json").read_text())
    return {"wall": wall, "peaks": peaks, "mode": stats.get("mode"),
            "tiling": stats.get("tiling"), "flagged": stats["overall"]["points_flagged"]}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_service(cloud: Path, folder: Path, workers: int, params: str | None,
                tile_job_points: int, tile_size: float | None) -> dict:
    """``lidar-outliers serve`` with ``workers`` worker processes; one job, timed from submit
    (upload included) to the result downloaded."""
    from lidar_outliers.client import Client

    shutil.rmtree(folder, ignore_errors=True)  # a fresh service: no users or jobs of a run before
    port = free_port()
    env = dict(os.environ, DATA_DIR=str(folder), WORKER_CONCURRENCY=str(workers),
               API_PORT=str(port), TILE_JOB_POINTS=str(tile_job_points),
               TILE_SIZE=str(tile_size or 0), MAX_UPLOAD_BYTES=str(64 * 1024**3),
               MAX_STORED_BYTES_PER_USER=str(1024**4), PYTHONPATH=str(ROOT))
    env.pop("REDIS_URL", None)
    key = subprocess.run([*CLI, "users", "add", "bench"], env=env, cwd=ROOT, check=True,
                         capture_output=True, text=True).stdout.strip().splitlines()[-1]
    serve = subprocess.Popen([*CLI, "serve"], env=env, cwd=ROOT, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        with Peaks(serve.pid) as peaks:
            url = f"http://127.0.0.1:{port}"
            _wait_up(url)
            inputs = json.loads(params) if params else {}
            started = time.perf_counter()
            with Client(url, key, timeout=600) as api:
                job = api.submit(cloud, inputs=inputs)
                doc = api.wait(job["jobID"], timeout=24 * 3600)
                if doc["status"] != "successful":
                    raise SystemExit(f"the job ended {doc['status']}: {doc.get('message')}")
                api.download(job["jobID"], folder / "result.las")
                stats = api.statistics(job["jobID"])
            wall = time.perf_counter() - started
    finally:
        serve.terminate()
        try:
            serve.wait(60)
        except subprocess.TimeoutExpired:
            serve.kill()
    return {"wall": wall, "peaks": peaks, "mode": stats.get("mode"),
            "tiling": stats.get("tiling"), "flagged": stats["overall"]["points_flagged"]}


def _wait_up(url: str, timeout: float = 120.0) -> None:
    import httpx

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if httpx.get(url + "/health", timeout=2).status_code == 200:
                time.sleep(2)  # the worker connects to Redis beside the API
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.5)
    raise SystemExit("the service did not start")


def row(label: str, points: int, res: dict, base_seconds: float | None,
        base_points: int) -> str:
    name, rss = res["peaks"].largest()
    ratio = "" if base_seconds is None else f"{res['wall'] / base_seconds:.1f}x"
    roles = ", ".join(f"{k} {v / 1e9:.2f}" for k, v in sorted(res["peaks"].by_role().items()))
    cores = res["peaks"].cpu_seconds() / res["wall"]
    anon = res["peaks"].largest_anonymous()
    return (f"| {label} | {points:,} | {res['wall']:.1f} | {points / res['wall']:,.0f} | "
            f"{cores:.2f} | {rss / 1e9:.2f} | {anon / 1e9:.2f} | {roles} | {ratio} (points "
            f"{points / base_points:.1f}x) | {res['mode']} |")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=50_000_000, help="points of the cloud")
    parser.add_argument("--workers", type=int, nargs="*", default=[1, 2],
                        help="service runs with this many worker processes (none: CLI only)")
    parser.add_argument("--params", help="pipeline JSON (default: the file's default pipeline)")
    parser.add_argument("--base-points", type=int, default=1_200_000,
                        help="points of the base cloud the times are compared with")
    parser.add_argument("--tile-size", type=float, help="tile edge in metres (default: auto)")
    parser.add_argument("--tile-job-points", type=int, default=2_000_000,
                        help="the service's TILE_JOB_POINTS")
    parser.add_argument("--folder", type=Path, help="work folder (default: a temporary one)")
    parser.add_argument("--no-cli", action="store_true",
                        help="skip the large cloud's command-line run (the base run still runs)")
    args = parser.parse_args(argv)
    folder = args.folder or Path(tempfile.mkdtemp(prefix="bench-scale-"))
    folder.mkdir(parents=True, exist_ok=True)
    simulated = simulated_cloud(folder / "base")
    base = copies(simulated, folder / f"base_{args.base_points}.las", args.base_points)
    base_points = laspy.open(base).header.point_count
    big = copies(simulated, folder / f"cloud_{args.points}.las", args.points)
    print(f"cloud: {big} ({args.points:,} points, {big.stat().st_size / 1e6:,.0f} MB); "
          f"base {base_points:,} points; params {args.params or 'default pipeline'}")
    print("| run | points | seconds | points/s | cores busy | peak RSS GB (largest process) | "
          "of it anonymous, GB | peak RSS GB by process | time vs base | mode |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: | --- |")
    ref = run_cli(base, folder / "base_out.las", args.params, args.tile_size)
    print(row("CLI, base cloud", base_points, ref, None, base_points), flush=True)
    if not args.no_cli:
        res = run_cli(big, folder / "out.las", args.params, args.tile_size)
        print(row("CLI", args.points, res, ref["wall"], base_points), flush=True)
    for workers in args.workers:
        svc = run_service(big, folder / f"service_{workers}", workers, args.params,
                          args.tile_job_points, args.tile_size)
        print(row(f"service, {workers} worker{'s' if workers > 1 else ''}", args.points, svc,
                  ref["wall"], base_points), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
