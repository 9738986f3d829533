"""`lidar-outliers serve` (what `make run` starts): its own Redis, a worker and the API; a
development key on first start; SIGTERM or Ctrl-C stops every process it started."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import psutil

from tests.e2e.stack import ROOT, alive, descendants, free_port, wait_for, wait_job
from tests.lasfiles import write_cloud

CLI = str(Path(sys.executable).parent / "lidar-outliers")


def start_serve(data_dir: Path, port: int, log: Path, **settings: object) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k != "REDIS_URL"}
    # this checkout's code, also where the console script's install points elsewhere
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    env.update(DATA_DIR=str(data_dir), API_PORT=str(port),
               **{k.upper(): str(v) for k, v in settings.items()})
    with open(log, "ab") as out:
        return subprocess.Popen([CLI, "serve"], env=env, cwd=ROOT, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)


def wait_ready(proc: subprocess.Popen, log: Path, port: int) -> str:
    """Until the banner is printed and the health check sees Redis and the worker."""
    wait_for(lambda: proc.poll() is None and "Ctrl-C stops everything" in log.read_text(),
             240, "the serve banner")

    def healthy() -> bool:
        try:
            return httpx.get(f"http://127.0.0.1:{port}/health", timeout=5).status_code == 200
        except httpx.HTTPError:
            return False

    wait_for(healthy, 240, "GET /health to answer 200", interval=0.5)
    return log.read_text()


def stop_and_check(proc: subprocess.Popen, sig: int) -> None:
    family = [proc.pid, *descendants(proc.pid)]
    names = {psutil.Process(p).name() for p in family if alive([p])}
    assert len(family) >= 5, names  # serve, supervisord, redis-server, worker (+ pool), uvicorn
    try:
        if sig == signal.SIGTERM:
            os.killpg(proc.pid, sig)  # to its process group, as a service manager does
        else:
            os.kill(proc.pid, sig)  # Ctrl-C in a terminal
        assert proc.wait(timeout=120) == 0
        wait_for(lambda: not alive(family), 30, "every process serve started to exit")
    finally:
        for pid in alive(family):  # never leave anything behind, even when failing
            os.kill(pid, signal.SIGKILL)


def test_serve_runs_the_stack_and_stops_everything(tmp_path: Path) -> None:
    data_dir, port = tmp_path / "data", free_port()
    first_log = tmp_path / "serve1.log"
    proc = start_serve(data_dir, port, first_log)
    try:
        banner = wait_ready(proc, first_log, port)
        lines = banner.splitlines()
        key = lines[lines.index(next(x for x in lines if "development API key" in x)) + 1]
        cloud = tmp_path / "scan.las"
        write_cloud(cloud, n=2000)
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60,
                          headers={"Authorization": f"Bearer {key}"}) as client:
            answer = client.post("/processes/temporal/execution",
                                 files={"file": ("scan.las", cloud.read_bytes())})
            assert answer.status_code == 201, answer.text
            job = answer.json()["jobID"]
            assert wait_job(client, job, ("successful", "failed"))["status"] == "successful"
    finally:
        stop_and_check(proc, signal.SIGTERM)
    assert list((data_dir / "redis").iterdir())  # Redis kept its append-only file there

    # a second start keeps the keys and the jobs, and prints no new key
    second_log = tmp_path / "serve2.log"
    proc = start_serve(data_dir, port, second_log)
    try:
        banner = wait_ready(proc, second_log, port)
        assert "development API key" not in banner
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60,
                          headers={"Authorization": f"Bearer {key}"}) as client:
            assert client.get(f"/jobs/{job}").json()["status"] == "successful"
    finally:
        stop_and_check(proc, signal.SIGINT)
