"""Every import points down: service, worker -> lidar_outliers -> algorithms.

Checked twice: statically over every import statement of every module (function-level imports
included), and at run time by importing each numerical module in a fresh interpreter.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: package -> the project's packages it must never import.
FORBIDDEN = {
    "algorithms": {"lidar_outliers", "worker", "service"},
    "lidar_outliers": {"worker", "service"},
    "worker": {"service"},
    "service": {"worker"},
}


def modules(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


def imported_packages(path: Path) -> set[str]:
    """Top-level names of every module an import statement in ``path`` names."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module.split(".")[0])
    return found


@pytest.mark.parametrize("package", list(FORBIDDEN))
def test_no_module_imports_upward(package: str) -> None:
    wrong = {str(path.relative_to(ROOT)): sorted(imported_packages(path) & FORBIDDEN[package])
             for path in modules(package)}
    assert {k: v for k, v in wrong.items() if v} == {}


def test_numerical_modules_import_nothing_of_the_project_at_run_time() -> None:
    names = [".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
             for p in modules("algorithms")]
    code = (
        "import importlib, sys\n"
        f"for name in {names!r}:\n"
        "    importlib.import_module(name)\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in "
        "('lidar_outliers', 'worker', 'service')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_the_service_enqueues_by_task_name() -> None:
    """The API knows the worker's task only by the name both sides take from the library."""
    from lidar_outliers.jobs.queue import RUN_JOB_TASK
    from worker.tasks import run_job

    assert run_job.name == RUN_JOB_TASK
    assert "RUN_JOB_TASK" in (ROOT / "service" / "queue.py").read_text()
