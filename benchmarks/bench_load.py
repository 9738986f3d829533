"""Status polls under load: ``GET /jobs/{id}`` at a fixed rate, latency percentiles.

Usage::

    # against a running service (one of your jobs is polled; one is submitted if you have none)
    .venv/bin/python benchmarks/bench_load.py --url http://127.0.0.1:8000 --key lo_...
    # or on a stack of its own: redis-server and the API (--api-workers processes), and with
    # --worker a Celery worker (without one, /health answers 503 after a fresh ping)
    .venv/bin/python benchmarks/bench_load.py [--rate 200] [--seconds 20] [--api-workers 2]
        [--worker]

Requests are sent open-loop: the i-th one at ``start + i / rate`` whatever the answers before
it, so a slow server shows as latency instead of as a lower request rate. Latency is measured
from the planned send time (a late send counts against the server). Prints polls per second
answered 200, p50 / p99 / max latency, the other statuses, and ``/health`` latency.
Target: 200 polls/s with p99 under 100 ms.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_port(port: int, proc: subprocess.Popen, what: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"{what} exited with {proc.returncode}")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"{what} did not listen on {port} within {timeout} s")


def cpu_seconds(pid: int) -> float:
    """CPU time of a process and its children (the uvicorn workers) so far."""
    import psutil

    total = 0.0
    procs = [psutil.Process(pid), *psutil.Process(pid).children(recursive=True)]
    for proc in procs:
        try:
            times = proc.cpu_times()
            total += times.user + times.system
        except psutil.NoSuchProcess:
            pass
    return total


@contextmanager
def own_stack(api_workers: int, worker: bool) -> Iterator[tuple[str, str, int]]:
    """redis-server, the API and (with ``worker``) a Celery worker on a temporary DATA_DIR;
    yields (base URL, key, API pid)."""
    folder = Path(tempfile.mkdtemp(prefix="bench-load-"))
    procs: list[subprocess.Popen] = []
    try:
        redis_port, api_port = _free_port(), _free_port()
        redis = shutil.which("redis-server") or "/usr/bin/redis-server"
        procs.append(subprocess.Popen(
            [redis, "--port", str(redis_port), "--bind", "127.0.0.1", "--dir", str(folder),
             "--save", "", "--appendonly", "no"], stdout=subprocess.DEVNULL,
            start_new_session=True))
        _wait_port(redis_port, procs[-1], "redis-server")
        env = dict(os.environ, DATA_DIR=str(folder / "data"),
                   REDIS_URL=f"redis://127.0.0.1:{redis_port}/0", PYTHONPATH=str(ROOT))
        out = subprocess.run([sys.executable, "-m", "lidar_outliers", "users", "add", "bench"],
                             env=env, cwd=ROOT, capture_output=True, text=True, check=True)
        key = out.stdout.strip().splitlines()[-1]
        log = open(folder / "api.log", "wb")  # noqa: SIM115 - closed with the folder
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "--factory", "service.app:create_app", "--host",
             "127.0.0.1", "--port", str(api_port), "--workers", str(api_workers),
             "--log-level", "warning", "--no-access-log"],
            env=env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True))
        _wait_port(api_port, procs[-1], "the API")
        api_pid = procs[-1].pid
        if worker:  # /health then answers 200 from its cached check
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "celery", "-A", "worker.celery_app", "worker",
                 "--concurrency=1", "--loglevel=WARNING", "-n", f"bench-{os.getpid()}@%h"],
                env=env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
                start_new_session=True))
            deadline = time.monotonic() + 300
            while httpx.get(f"http://127.0.0.1:{api_port}/health").status_code != 200:
                if time.monotonic() > deadline or procs[-1].poll() is not None:
                    raise RuntimeError("the worker did not answer /health's ping")
                time.sleep(1)
        yield f"http://127.0.0.1:{api_port}", key, api_pid
    finally:
        for proc in reversed(procs):
            try:
                os.killpg(proc.pid, 15)
                proc.wait(timeout=20)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                os.killpg(proc.pid, 9)
        shutil.rmtree(folder, ignore_errors=True)


def a_job(client: httpx.Client) -> str:
    """One of the caller's jobs; a small one is submitted when there is none."""
    jobs = client.get("/jobs", params={"limit": 1}).json()["jobs"]
    if jobs:
        return jobs[0]["jobID"]
    from tests.lasfiles import write_cloud

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "bench.las"
        write_cloud(path, n=2000)
        answer = client.post("/processes/temporal/execution",
                             files={"file": ("bench.las", path.read_bytes())})
    answer.raise_for_status()
    return answer.json()["jobID"]


async def _connection(host: str, port: int, request: bytes, planned: asyncio.Queue,
                      latencies: list[float], statuses: Counter) -> None:
    """One keep-alive connection sending the request at each planned time it takes.

    A minimal HTTP/1.1 client: httpx costs several ms of CPU per request, which on a small
    machine limits the rate before the server does."""
    reader, writer = await asyncio.open_connection(host, port)
    try:
        while True:
            when = await planned.get()
            if when is None:
                return
            await asyncio.sleep(max(0.0, when - time.perf_counter()))
            writer.write(request)
            head = await reader.readuntil(b"\r\n\r\n")
            status = int(head.split(b" ", 2)[1])
            length = re.search(rb"(?i)content-length: *(\d+)", head)
            await reader.readexactly(int(length.group(1)) if length else 0)
            statuses[status] += 1
            latencies.append(time.perf_counter() - when)
    except (OSError, asyncio.IncompleteReadError) as exc:
        statuses[type(exc).__name__] += 1
    finally:
        writer.close()


async def poll(base_url: str, key: str, job_id: str, rate: float, seconds: float,
               connections: int = 64) -> tuple[list[float], Counter, float]:
    """Latencies (s) of the answered polls, the statuses, and the time it all took."""
    url = httpx.URL(base_url)
    request = (f"GET /jobs/{job_id} HTTP/1.1\r\nHost: {url.host}:{url.port}\r\n"
               f"Authorization: Bearer {key}\r\n\r\n").encode()
    latencies: list[float] = []
    statuses: Counter = Counter()
    planned: asyncio.Queue = asyncio.Queue()
    start = time.perf_counter() + 0.5
    for i in range(int(rate * seconds)):
        planned.put_nowait(start + i / rate)
    for _ in range(connections):
        planned.put_nowait(None)
    await asyncio.gather(*(_connection(url.host, url.port or 80, request, planned, latencies,
                                       statuses) for _ in range(connections)))
    return latencies, statuses, time.perf_counter() - start


def report(base_url: str, key: str, rate: float, seconds: float,
           api_pid: int | None = None) -> None:
    with httpx.Client(base_url=base_url, headers={"Authorization": f"Bearer {key}"},
                      timeout=60.0) as client:
        job_id = a_job(client)
        for _ in range(20):  # warm up connections and caches
            client.get(f"/jobs/{job_id}")
        health = []
        for _ in range(10):
            t = time.perf_counter()
            client.get("/health")
            health.append(time.perf_counter() - t)
    cpu_before = cpu_seconds(api_pid) if api_pid else 0.0
    client_before = time.process_time()
    latencies, statuses, took = asyncio.run(poll(base_url, key, job_id, rate, seconds))
    client_cpu = time.process_time() - client_before
    cpu = cpu_seconds(api_pid) - cpu_before if api_pid else None
    ms = np.asarray(latencies) * 1000
    ok = statuses.get(200, 0)
    print(f"GET /jobs/{{id}} at {rate:.0f}/s for {seconds:.0f} s against {base_url}")
    print(f"  polls/s answered 200: {ok / took:.1f}  ({ok} of {int(rate * seconds)}; "
          f"statuses {dict(statuses)})")
    if len(ms):
        print(f"  latency ms: p50 {np.percentile(ms, 50):.1f}  p99 {np.percentile(ms, 99):.1f}"
              f"  max {ms.max():.1f}")
    sent = sum(statuses.values())
    if cpu is not None and sent:
        print(f"  API CPU per poll: {cpu / sent * 1000:.2f} ms")
    if sent:  # the client's own cost: on a busy machine it may be what limits the rate
        print(f"  client CPU per poll: {client_cpu / sent * 1000:.2f} ms; machine load average "
              f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    print(f"  /health ms (10 calls, no load): median {np.median(health) * 1000:.1f}  "
          f"max {max(health) * 1000:.1f}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--url", help="base URL of a running API (else a stack of its own)")
    parser.add_argument("--key", help="API key for --url")
    parser.add_argument("--rate", type=float, default=200.0, help="polls per second (200)")
    parser.add_argument("--seconds", type=float, default=20.0, help="how long (20)")
    parser.add_argument("--api-workers", type=int, default=2,
                        help="API processes of the own stack (2)")
    parser.add_argument("--worker", action="store_true",
                        help="start a Celery worker in the own stack (polls see the job run)")
    args = parser.parse_args(argv)
    # SIGTERM (e.g. from `timeout`) unwinds like Ctrl-C, so the own stack is stopped
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    if args.url:
        if not args.key:
            parser.error("--url needs --key")
        report(args.url.rstrip("/"), args.key, args.rate, args.seconds)
        return 0
    with own_stack(args.api_workers, args.worker) as (url, key, pid):
        report(url, key, args.rate, args.seconds, pid)
    return 0


if __name__ == "__main__":
    sys.exit(main())
