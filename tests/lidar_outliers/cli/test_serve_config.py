"""The supervisord configuration `serve` writes, read back by supervisord's own parser: every
program restarts, stops with its process group, and gets its command line unchanged (``%`` and
quoting included)."""

from __future__ import annotations

import shlex
from pathlib import Path

from supervisor.datatypes import RestartUnconditionally
from supervisor.options import ServerOptions

from lidar_outliers.cli.serve import PROJECT_ROOT, Program, supervisord_config


def test_supervisord_reads_the_programs_as_given(tmp_path: Path) -> None:
    run_dir = tmp_path / "run 100%"
    run_dir.mkdir()
    programs = [
        Program("redis", ["/usr/bin/redis-server", "--save", "", "--dir", str(tmp_path / "a b")],
                priority=10),
        Program("worker", ["python", "-m", "celery", "-n", "worker-1@%h"], priority=20),
        Program("api", ["python", "-m", "uvicorn", "--port", "8000"], priority=30),
    ]
    config = tmp_path / "supervisord.conf"
    config.write_text(supervisord_config(run_dir, programs))
    options = ServerOptions()
    options.realize(args=["-c", str(config)])
    assert options.nodaemon
    assert options.logfile == str(run_dir / "supervisord.log")
    groups = {g.name: g.process_configs[0] for g in options.process_group_configs}
    assert list(groups) == ["redis", "worker", "api"]  # started in this order, stopped reversed
    for program in programs:
        read = groups[program.name]
        assert shlex.split(read.command) == program.argv
        assert read.autorestart is RestartUnconditionally and read.startretries > 100
        assert read.stopasgroup and read.killasgroup
        assert read.directory == str(PROJECT_ROOT)
        assert read.priority == program.priority


def test_job_processes_share_the_cpus(monkeypatch) -> None:
    import lidar_outliers.cli.serve as serve

    monkeypatch.setattr(serve, "available_cpus", lambda: 8)
    assert [serve.threads_per_job(c) for c in (1, 2, 3, 8, 16)] == [8, 4, 2, 1, 1]
