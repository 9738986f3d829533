"""Real processes for the integration tests: redis-server, Celery workers, uvicorn, `serve`.

Every process is started in its own process group and stopped by signalling the group, so the
worker's pool processes go with it. A process that exits or does not answer in time raises
AssertionError with the end of its log; nothing here skips.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import psutil

ROOT = Path(__file__).resolve().parents[2]
REDIS_SERVER = shutil.which("redis-server") or "/usr/bin/redis-server"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(predicate: Callable[[], Any], timeout: float, what: str, interval: float = 0.1):
    """Poll ``predicate`` until it returns something truthy; fail after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    last: Any = None
    while time.monotonic() < deadline:
        last = predicate()
        if last:
            return last
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what} (last: {last!r})")


def log_tail(log: Path | None, lines: int = 20) -> str:
    """The last lines of a log file, for a failure message."""
    if log is None or not log.exists():
        return ""
    tail = log.read_text(errors="replace").splitlines()[-lines:]
    return "\n--- " + str(log) + " ---\n" + "\n".join(tail) if tail else ""


def wait_for_port(port: int, proc: subprocess.Popen, timeout: float = 60.0,
                  log: Path | None = None) -> None:
    def open_() -> bool:
        assert proc.poll() is None, f"{proc.args} exited with {proc.returncode}{log_tail(log)}"
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return True
        except OSError:
            return False

    try:
        wait_for(open_, timeout, f"port {port}")
    except AssertionError as err:
        if proc.poll() is not None:  # open_ said so, with the log
            raise
        raise AssertionError(f"{err}{log_tail(log)}") from None


def stop_group(proc: subprocess.Popen, grace: float = 20.0) -> None:
    """SIGTERM the process group, SIGKILL it after ``grace`` seconds, reap the leader."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
        try:
            proc.wait(timeout=grace)
        except subprocess.TimeoutExpired:
            pass
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


def descendants(pid: int) -> list[int]:
    try:
        return [p.pid for p in psutil.Process(pid).children(recursive=True)]
    except psutil.NoSuchProcess:
        return []


def alive(pids: list[int]) -> list[int]:
    out = []
    for pid in pids:
        try:
            if psutil.Process(pid).status() != psutil.STATUS_ZOMBIE:
                out.append(pid)
        except psutil.NoSuchProcess:
            pass
    return out


class RedisServer:
    #: Databases of the test server: one per stack of the whole run (Redis's default is 16).
    DATABASES = 256

    def __init__(self, folder: Path) -> None:
        self.port = free_port()
        folder.mkdir(parents=True, exist_ok=True)
        self.log = folder / "redis.log"
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen(
                [REDIS_SERVER, "--port", str(self.port), "--bind", "127.0.0.1", "--dir",
                 str(folder), "--save", "", "--appendonly", "yes", "--daemonize", "no",
                 "--loglevel", "warning", "--databases", str(self.DATABASES)],
                stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
            )
        try:
            wait_for_port(self.port, self.proc, log=self.log)
        except AssertionError:
            stop_group(self.proc)
            raise
        self._next_db = 0

    def new_url(self) -> str:
        """A database of its own for each stack, so queues do not mix."""
        self._next_db += 1
        assert self._next_db < self.DATABASES, "more stacks than the test Redis has databases"
        return f"redis://127.0.0.1:{self.port}/{self._next_db}"

    def stop(self) -> None:
        stop_group(self.proc)


class Stack:
    """One deployment: a DATA_DIR, a Redis database, any number of workers and API processes."""

    def __init__(self, data_dir: Path, redis_url: str, **settings: Any) -> None:
        self.data_dir = data_dir
        # PYTHONPATH: the commands (`lidar-outliers ...`) import this checkout's code too,
        # whichever checkout the virtual environment was installed from
        self.env = dict(os.environ, DATA_DIR=str(data_dir), REDIS_URL=redis_url,
                        PYTHONUNBUFFERED="1", PYTHONPATH=str(ROOT),
                        **{k.upper(): str(v) for k, v in settings.items()})
        self.env.pop("PYTEST_CURRENT_TEST", None)
        # this checkout's code in every process, wherever the console script's install points
        self.env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT),
                                                                os.environ.get("PYTHONPATH")]))
        self.workers: list[subprocess.Popen] = []
        self.api: subprocess.Popen | None = None
        self.port = 0
        self.logs = data_dir / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.log_of: dict[int, Path] = {}

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def _spawn(self, argv: list[str], log_name: str) -> subprocess.Popen:
        log = open(self.logs / log_name, "ab")  # noqa: SIM115 - kept for the process's life
        proc = subprocess.Popen(argv, env=self.env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)
        self.log_of[proc.pid] = self.logs / log_name
        return proc

    def start_worker(self) -> subprocess.Popen:
        n = len(self.workers) + 1
        proc = self._spawn(
            [sys.executable, "-m", "celery", "-A", "worker.celery_app", "worker",
             "--pool=prefork", "--concurrency=1", "--loglevel=INFO", "--without-gossip",
             "--without-mingle", "-n", f"w{n}-{os.getpid()}@%h"],
            f"worker{n}.log",
        )
        self.workers.append(proc)
        return proc

    def start_api(self) -> None:
        self.port = self.port or free_port()
        self.api = self._spawn(
            [sys.executable, "-m", "uvicorn", "--factory", "service.app:create_app",
             "--host", "127.0.0.1", "--port", str(self.port)],
            "api.log",
        )
        wait_for_port(self.port, self.api, log=self.log_of[self.api.pid])

    def stop_api(self) -> None:
        if self.api is not None:
            stop_group(self.api)
            self.api = None

    def wait_workers_ready(self, timeout: float = 120.0) -> None:
        """Until every worker answers a ping (they have connected to Redis)."""
        from celery import Celery

        def answered() -> bool:
            for proc in self.workers:
                assert proc.poll() is None, (f"a worker exited with {proc.returncode}"
                                             f"{log_tail(self.log_of[proc.pid])}")
            return len(app.control.ping(timeout=0.5) or []) >= len(self.workers)

        assert self.workers, "no worker to wait for"
        app = Celery(broker=self.env["REDIS_URL"])
        try:
            wait_for(answered, timeout, "the workers to answer a ping", interval=0.2)
        finally:
            app.close()

    def run_cli(self, *args: str) -> str:
        """Run `lidar-outliers ARGS` with this stack's settings; return its output."""
        out = subprocess.run(
            [sys.executable, "-m", "lidar_outliers", *args],  # this checkout's code
            env=self.env, cwd=ROOT, capture_output=True, text=True, timeout=60, check=True,
        )
        return out.stdout

    def add_user(self, name: str) -> str:
        """Create a user with the real command line; the key is the last line of its output."""
        return self.run_cli("users", "add", name).strip().splitlines()[-1]

    def client(self, key: str | None = None) -> httpx.Client:
        headers = {"Authorization": f"Bearer {key}"} if key else {}
        return httpx.Client(base_url=self.url, headers=headers, timeout=60.0)

    def stop(self) -> None:
        self.stop_api()
        for proc in self.workers:
            stop_group(proc)
        self.workers = []


@contextmanager
def running_stack(
    data_dir: Path, redis_url: str, *, workers: int = 1, **settings: Any
) -> Iterator[Stack]:
    """The API and ``workers`` Celery workers on ``data_dir``; every process stopped on exit."""
    stack = Stack(data_dir, redis_url, **settings)
    try:
        for _ in range(workers):
            stack.start_worker()
        stack.start_api()
        if workers:
            stack.wait_workers_ready()
        yield stack
    finally:
        stack.stop()


def assert_problem(answer: httpx.Response, status: int, slug: str) -> dict:
    """The answer is an RFC 9457 problem of ``status`` whose type ends in ``slug``."""
    assert answer.status_code == status, answer.text
    assert answer.headers["content-type"] == "application/problem+json"
    body = answer.json()
    assert body["status"] == status and body["type"].endswith(slug), body
    assert body["title"] and body["detail"]
    return body


def wait_job(client: httpx.Client, job_id: str, statuses: tuple[str, ...],
             timeout: float = 180.0) -> dict:
    def check() -> dict | None:
        doc = client.get(f"/jobs/{job_id}").json()
        return doc if doc["status"] in statuses else None

    return wait_for(check, timeout, f"job {job_id} to be one of {statuses}", interval=0.2)
