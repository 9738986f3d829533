"""A resumable (tus) upload interrupted at half, resumed, completed: bytes sent, throughput and
the API's peak memory.

Target: a large upload interrupted at half resumes and completes without resending the first
half, and the API's memory does not grow with the file.

A LAS file of ``--megabytes`` (random points, LAS 1.4 point format 6) is generated; an API
(uvicorn, this checkout, its own DATA_DIR under ``--workdir``) is started. A first client sends
it in ``--chunk-mb`` pieces with sha1 checksums and is killed in the middle of the PATCH that
crosses half the file (the connection drops with part of the piece sent). A second client, as
after a restart, asks the server for its offset (HEAD) and sends the rest. Printed: the offset
the server held, the bytes each client put on the wire, what was sent twice, the throughput,
and the API process's peak resident memory (``VmHWM``) against its memory before the upload.
The stored object is compared with the file.

    .venv/bin/python benchmarks/bench_upload.py [--megabytes 50] [--chunk-mb 8] [--workdir DIR]

Check the free disk space first: the run holds the file, the partial upload and the stored
upload (three times the size) until it ends.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import laspy
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lidar_outliers.client import Client  # noqa: E402

MB = 1024**2


def make_las(path: Path, megabytes: float, seed: int = 0) -> int:
    """A LAS 1.4 file of about ``megabytes`` MiB written 1 M points at a time; its size."""
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.offsets = [500_000.0, 5_000_000.0, 0.0]
    header.scales = [0.001, 0.001, 0.001]
    n = max(1000, int(megabytes * MB) // header.point_format.size)
    rng = np.random.default_rng(seed)
    with laspy.open(path, mode="w", header=header) as writer:
        for start in range(0, n, 1_000_000):
            m = min(1_000_000, n - start)
            points = laspy.ScaleAwarePointRecord.zeros(m, header=header)
            points.x = 500_000.0 + rng.uniform(0, 1000, m)
            points.y = 5_000_000.0 + rng.uniform(0, 1000, m)
            points.z = rng.uniform(0, 50, m)
            points.gps_time = 4e5 + (start + np.arange(m)) * 1e-5
            writer.write_points(points)
    return path.stat().st_size


class Killed(BaseException):
    """The first client's process ends (not an error it could retry)."""


class Wire(httpx.HTTPTransport):
    """Real HTTP that counts the PATCH body bytes it sends; with ``kill_at``, the PATCH that
    crosses that offset is cut halfway through its body and the client is killed."""

    def __init__(self, kill_at: int | None = None) -> None:
        super().__init__()
        self.kill_at = kill_at
        self.sent = 0

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        if request.method != "PATCH":
            return super().handle_request(request)
        body = request.read()
        start = int(request.headers["upload-offset"])
        cut = self.kill_at is not None and start <= self.kill_at < start + len(body)

        def stream() -> Iterator[bytes]:
            part = body[:len(body) // 2] if cut else body
            self.sent += len(part)
            yield part
            if cut:
                raise Killed()

        request.stream = _Stream(stream())
        return super().handle_request(request)


class _Stream(httpx.SyncByteStream):
    def __init__(self, parts: Iterator[bytes]) -> None:
        self.parts = parts

    def __iter__(self) -> Iterator[bytes]:
        yield from self.parts


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def memory_kib(pid: int, field: str) -> int:
    """``VmRSS`` (now) or ``VmHWM`` (peak) of a process, KiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(8 * MB):
            digest.update(block)
    return digest.hexdigest()


def start_api(data_dir: Path) -> tuple[subprocess.Popen, str, str]:
    env = dict(os.environ, DATA_DIR=str(data_dir), PYTHONPATH=str(ROOT),
               MAX_UPLOAD_BYTES=str(64 * 1024**3), MAX_STORED_BYTES_PER_USER=str(64 * 1024**3),
               REDIS_URL="redis://127.0.0.1:1/0")  # no job is queued here
    key = subprocess.run([sys.executable, "-m", "lidar_outliers", "users", "add", "bench"],
                         env=env, cwd=ROOT, check=True, capture_output=True,
                         text=True).stdout.strip().splitlines()[-1]
    port = free_port()
    log = open(data_dir / "api.log", "ab")  # noqa: SIM115 - kept while the API runs
    api = subprocess.Popen([sys.executable, "-m", "uvicorn", "--factory",
                            "service.app:create_app", "--port", str(port), "--log-level",
                            "warning"], env=env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while True:
        try:
            httpx.options(f"{url}/uploads/tus")
            return api, url, key
        except httpx.TransportError:
            if time.monotonic() > deadline or api.poll() is not None:
                api.kill()
                raise SystemExit(f"the API did not start; see {data_dir / 'api.log'}") from None
            time.sleep(0.2)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--megabytes", type=float, default=50.0, help="file size, MiB")
    parser.add_argument("--chunk-mb", type=float, default=8.0, help="bytes per PATCH, MiB")
    parser.add_argument("--workdir", type=Path, default=None,
                        help="where the file and the API's DATA_DIR go (a temporary folder)")
    args = parser.parse_args()

    work = Path(tempfile.mkdtemp(prefix="bench-upload-", dir=args.workdir))
    try:
        path = work / "cloud.las"
        started = time.perf_counter()
        size = make_las(path, args.megabytes)
        print(f"file: {size / MB:.1f} MiB of LAS ({time.perf_counter() - started:.1f} s to "
              "generate)")
        api, url, key = start_api(work / "data")
        try:
            run(api, url, key, path, size, int(args.chunk_mb * MB), work)
        finally:
            api.terminate()
            api.wait(timeout=30)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def run(api: subprocess.Popen, url: str, key: str, path: Path, size: int, chunk: int,
        work: Path) -> None:
    idle_kib = memory_kib(api.pid, "VmRSS")
    half = size // 2
    first = Wire(kill_at=half)
    started = time.perf_counter()
    with Client(url, key, transport=first, chunk_bytes=chunk) as api1:
        location = api1.create_upload(path)["location"]
        try:
            api1.resume(location, path)
            raise SystemExit("the first client was not interrupted")
        except Killed:
            pass
    first_seconds = time.perf_counter() - started

    second = Wire()
    started = time.perf_counter()
    with Client(url, key, transport=second, chunk_bytes=chunk) as api2:
        held = api2.upload_offset(location)
        api2.resume(location, path)
        final = api2.upload_offset(location)
    second_seconds = time.perf_counter() - started

    peak_kib = memory_kib(api.pid, "VmHWM")
    upload_id = location.rsplit("/", 1)[1]
    stored = next((work / "data" / "uploads").glob(f"*/{upload_id}.las"))
    same = sha256_of(stored) == sha256_of(path)
    total = first.sent + second.sent
    print(f"chunk: {chunk / MB:g} MiB; interrupted in the PATCH that crosses {half / MB:.1f} MiB")
    print(f"first client:  sent {first.sent / MB:8.1f} MiB in {first_seconds:6.1f} s, "
          "killed mid-PATCH")
    print(f"server offset at resume: {held / MB:.1f} MiB ({held} bytes; the cut piece was "
          "dropped whole, its checksum unverifiable)")
    print(f"second client: sent {second.sent / MB:8.1f} MiB in {second_seconds:6.1f} s, "
          f"from offset {held / MB:.1f} MiB")
    print(f"total on the wire: {total / MB:.1f} MiB for a {size / MB:.1f} MiB file; sent twice "
          f"{(total - size) / MB:.1f} MiB (at most one piece); bytes before the offset "
          f"sent again: {max(0, second.sent - (size - held))}")
    print(f"throughput: {size / MB / (first_seconds + second_seconds):.0f} MiB/s over both "
          f"clients; second {second.sent / MB / second_seconds:.0f} MiB/s")
    print(f"API memory: {idle_kib / 1024:.0f} MiB before the upload, peak {peak_kib / 1024:.0f} "
          "MiB (VmHWM)")
    print(f"complete: offset {final} of {size}; stored object identical: {same}")
    if not same or final != size or second.sent != size - held:
        raise SystemExit("FAILED: the upload is not what was sent")


if __name__ == "__main__":
    main()
